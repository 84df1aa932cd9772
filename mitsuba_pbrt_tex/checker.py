"""Checkerboard antialiasing in closed form (pbrt sections 10.1 and 10.5.1).

The checkerboard is the product of square waves ``c(x) = +1`` on even cells, ``-1`` on odd ones;
the weight of ``tex2`` is ``w = (1 - Π c(x_i)) / 2``. A separable filter averages each factor on
its own, so ``w = (1 - Π E[c(x_i)]) / 2`` exactly, for any dimension:

* ``box`` (pbrt-v3's ``closedform``) — E over ``[x - r, x + r]`` with half-width
  ``r = max(|dx/dx|, |dx/dy|)``, from the integral of the odd-cell indicator
  ``bumpInt(x) = floor(x/2) + 2·max(x/2 - floor(x/2) - 1/2, 0)``. In 2D this is pbrt-v3's
  ``sint + tint - 2·sint·tint``; like pbrt-v3 the result is 1/2 once a half-width exceeds 1.
  *Fix*: pbrt-v3 divides 0 by 0 (NaN) when exactly one width is 0 and the other footprint straddles
  an edge; an axis of zero width is point-sampled here.
* ``triangle`` (pbrt-v4) — E under a triangle of radius ``r = 1.5·max(...)``:
  ``(d(x+r) - 2d(x) + d(x-r)) / r²`` with ``d`` the double integral of the square wave, or the
  point value when the footprint stays in one cell.
* ``none`` — the parity rule: ``floor(s) + floor(t) (+ floor(z))`` even → ``tex1``.
* ``area`` (2D) — the exact average over the footprint *parallelogram* ``st + a·dst/dx +
  b·dst/dy``, ``a, b ∈ [-1/2, 1/2]`` (one pixel, as ``pbrt_imagemap``'s ``box`` filter, and
  pixel-centred like it under ``pbrt_path`` ``footprint="pixel"``), not over a bounding square.
  Not separable, so not a product of 1D means: Green's theorem turns the area integral of
  ``c(x)·c(y)`` into ``∮ S(x)·c(y) dy`` around the four edges, with ``S`` the integral of the
  square wave (a triangle wave), walked counter-clockwise (:func:`.outline.walk`, as the
  ``box`` image filter's integral). Each edge is cut where it crosses a cell row (``c(y)`` is
  constant between) and, on a piece that moves less than a quarter cell along x, where it
  crosses a cell column (``S`` is linear between, and the trapezoid rule is exact); longer pieces
  use ``S``'s own integral in closed form. The rows are those of the footprint's shorter axis
  (the checkerboard is symmetric in x and y), at most :data:`AREA_MAX_ROWS` of them; wider
  footprints get the product's Fourier series averaged over the parallelogram
  (:func:`fourier_mean`, where :func:`fourier_bound` does not make it negligible), degenerate
  ones (zero area) and 3D checkerboards the ``box`` closed form.

pbrt-v3 has no antialiasing for 3D checkerboards and pbrt-v4 only the triangle; the box form is
the same product in 3D.

Numerics: pbrt's closed forms subtract O(x) quantities to get O(r) or O(r²) differences, which
loses most float32 digits for small footprints (at x ≈ 5 and r ≈ 10⁻³ the triangle form is off by
~10⁻³). Where r < 1/2 at most one cell edge lies in the footprint, and we evaluate the same
function as ``c_left·F + c_right·(1 - F)`` with F the kernel mass left of that edge (box:
``(1 + t)/2``; triangle: its piecewise-quadratic CDF), which is exact to float rounding. The
``area`` form works relative to the lattice point nearest the footprint's centre and takes S as
a distance to the nearest even integer, so a footprint much smaller than a cell keeps its shape
and S its digits near that point (~10⁻⁷); along an axis where the centre is half a cell from
it, the corners keep float32's absolute resolution there (6·10⁻⁸), so the error grows as
~2·10⁻⁸ cell / the footprint's width (10⁻³ cell: ~2·10⁻⁵). Results are clamped to [-1, 1].
"""

from __future__ import annotations

import math

import drjit as dr

import mitsuba as mi

from .outline import Parallelogram, Piece, walk

AAMODES = ('none', 'box', 'closedform', 'triangle', 'area')
#: ``area``: footprints crossing more cell rows than this along their shorter axis get the
#: checkerboard's Fourier series (:func:`fourier_mean`) instead of the walk.
AREA_MAX_ROWS = 16


def _odd(x):
    """1 on odd cells, 0 on even ones."""
    f = dr.floor(x)
    return f - 2 * dr.floor(0.5 * f)


def square_wave(x):
    return 1 - 2 * _odd(x)


def _bump_int(x):
    h = 0.5 * x
    fh = dr.floor(h)
    return fh + 2 * dr.maximum(h - fh - 0.5, 0)


def _one_edge(x, r, mass_left):
    """Filtered square wave when exactly one cell edge e lies in (x - r, x + r] (r < 1/2):
    ``c_left·F + c_right·(1 - F)`` with F the kernel mass left of e, c_right = -c_left."""
    e = dr.floor(x + r)
    c_left = square_wave(e - 0.5)
    return c_left * (2 * mass_left((e - x) / r) - 1)


def _box_mass_left(t):
    return 0.5 * (1 + t)


def _triangle_mass_left(t):
    return dr.select(t <= 0, 0.5 * (1 + t) * (1 + t), 1 - 0.5 * (1 - t) * (1 - t))


def box_filtered(x, r):
    """Mean of the square wave over [x - r, x + r] (pbrt-v3)."""
    same = (dr.floor(x - r) == dr.floor(x + r)) | (r <= 0)
    safe_r = dr.select(same, 1.0, r)
    odd_frac = (_bump_int(x + r) - _bump_int(x - r)) / (2 * safe_r)
    filtered = dr.select(r < 0.5, _one_edge(x, safe_r, _box_mass_left), 1 - 2 * odd_frac)
    return dr.clip(dr.select(same, square_wave(x), filtered), -1, 1)


def _d(x):
    y = 0.5 * x - dr.floor(0.5 * x) - 0.5
    return 0.5 * x + y * (1 - 2 * dr.abs(y))


def triangle_filtered(x, r):
    """The square wave convolved with a unit-area triangle of radius r (pbrt-v4 ``bf``)."""
    same = (dr.floor(x - r) == dr.floor(x + r)) | (r <= 0)
    safe_r = dr.select(same, 1.0, r)
    second_difference = (_d(x + r) - 2 * _d(x) + _d(x - r)) / (safe_r * safe_r)
    filtered = dr.select(r < 0.5, _one_edge(x, safe_r, _triangle_mass_left), second_difference)
    return dr.clip(dr.select(same, square_wave(x), filtered), -1, 1)


def _finite(x):
    return dr.select(dr.isfinite(x), x, 0.0)


def tex2_weight(coords, widths, aamode: str):
    """Weight of tex2 for coordinates ``coords`` with per-axis footprint ``widths``
    (``max(|d/dx|, |d/dy|)`` of each coordinate)."""
    coords = [_finite(x) for x in coords]
    widths = [_finite(w) for w in widths]
    if aamode == 'none':
        prod = 1.0
        for x in coords:
            prod = prod * square_wave(x)
        return 0.5 - 0.5 * prod
    if aamode in ('box', 'closedform'):
        prod, wide = 1.0, False
        for x, r in zip(coords, widths):
            prod = prod * box_filtered(x, r)
            wide = wide | (r > 1)
        return dr.select(wide, 0.5, 0.5 - 0.5 * prod)
    prod = 1.0
    for x, r in zip(coords, widths):
        prod = prod * triangle_filtered(x, 1.5 * r)
    return 0.5 - 0.5 * prod


# ------------------------------------------------------------------------------------ area
def _triangle(x):
    """S(x) = ∫_0^x c: the triangle wave, x's distance to the nearest even integer (0 at even
    integers, 1 at odd) — computed as that distance, exact in float, so that S keeps its
    relative precision near 0 (``1 - |x mod 2 - 1|`` would round it to multiples of 2^-24)."""
    return dr.abs(x - 2 * dr.round(0.5 * x))


def _triangle_integral(x):
    """∫_0^x S: floor(x/2) whole periods of area 1, plus the part of the current one."""
    half = dr.floor(0.5 * x)
    m = x - 2 * half
    return half + dr.select(m <= 1, 0.5 * m * m, 1 - 0.5 * (2 - m) * (2 - m))


def _piece_integral(p: Piece, acc):
    """``∫ S(x) c(y) dy`` along one piece of the walk (c(y) is constant in the band): long pieces
    by the closed form of ``∫ S``, short ones by trapezoids on each side of the one column they
    may cross (S is linear between columns)."""
    x, x1 = p.x, p.x1
    run = x1 - x
    long = dr.abs(run) >= 0.25
    long_part = (_triangle_integral(x1) - _triangle_integral(x)) / dr.select(long, run, 1)
    col = dr.maximum(dr.floor(x), dr.floor(x1))
    crosses = dr.floor(x) != dr.floor(x1)
    frac = dr.select(crosses, (col - x) / dr.select(run != 0, run, 1), 1)
    s_x, s_next, s_col = _triangle(x), _triangle(x1), _triangle(col)
    short_part = dr.select(crosses,
                           0.5 * (s_x + s_col) * frac + 0.5 * (s_col + s_next) * (1 - frac),
                           0.5 * (s_x + s_next))
    mean_s = dr.select(long, long_part, short_part)
    return (dr.fma(square_wave(p.j + 0.5) * mean_s, p.y1 - p.y, acc),)


#: :func:`fourier_mean` sums the checkerboard's harmonics of odd orders up to this.
FOURIER_ORDER = 7


def _sinc(t):
    """sin(t)/t; 0 beyond |t| = 10⁴, where it is below 10⁻⁴ and float32's ``sin`` fails
    (sin(10⁹) came out as -117115: footprints 10⁸ cells long)."""
    big = ~(dr.abs(t) <= 1e4)
    safe = dr.select(big, 1.0, t)
    return dr.select(big, 0.0, dr.select(dr.abs(t) < 1e-3, 1 - t * t * (1.0 / 6.0),
                                         dr.sin(safe) / safe))


def fourier_mean(c, e0, e1, active=True):
    """Mean of ``c(x)·c(y)`` over the parallelogram ``c + a·e0 + b·e1`` from the product's
    Fourier series, ``c(x)·c(y) = (8/π²) Σ [cos π(mx − ny) − cos π(mx + ny)] / (mn)`` over odd
    m, n: a plane wave ``cos(k·p)`` averages to ``cos(k·c)·sinc(k·e0/2)·sinc(k·e1/2)``. For
    footprints crossing more rows than the walk takes: the terms up to :data:`FOURIER_ORDER`;
    what the rest leaves is largest for a thin footprint along a diagonal of the cells, where
    the harmonics m = n are not averaged away (≤ (8/π²)·Σ_{m > 7} 1/m² ≈ 0.050 of the ±1
    range, 0.025 in the weight, reached by lines 10⁻⁴ cell wide; 0.011 at 0.05 cell), and
    falls with the footprint's width across such a direction.
    A loop over the (m, n) pairs, lanes ``active`` only: a packet without such a lane skips
    it (a symbolic conditional ran its branch for every packet: +50% on a grazing frame)."""
    cx = c.x - 2 * dr.floor(0.5 * c.x)          # the product has period 2 in x and y
    cy = c.y - 2 * dr.floor(0.5 * c.y)
    side = (FOURIER_ORDER + 1) // 2

    def body(i, total):
        m = mi.Float(2 * (i // side) + 1)
        n = mi.Float(2 * (i % side) + 1)
        for sign, coef in ((-1.0, 1.0), (1.0, -1.0)):
            kx, ky = math.pi * m, sign * math.pi * n
            wave = dr.cos(kx * cx + ky * cy)
            wave = wave * _sinc(0.5 * (kx * e0.x + ky * e0.y))
            wave = wave * _sinc(0.5 * (kx * e1.x + ky * e1.y))
            total = dr.fma(coef * 8.0 / (math.pi ** 2) / (m * n), wave, total)
        return i + 1, total

    active = mi.Bool(active)
    _, total = dr.while_loop((mi.UInt32(0), mi.Float(0)),
                             lambda i, total: active & (i < side * side), body,
                             label='pbrt_checkerboard (harmonics)')
    return dr.select(dr.isfinite(total), dr.clip(total, -1, 1), 0.0)


#: :func:`fourier_bound` below this: the mean is 0 (the box form's) within it.
FOURIER_NEGLIGIBLE = 0.01


def fourier_bound(e0, e1):
    """An upper bound of ``|fourier_mean|`` from the attenuations alone (``|sinc t| ≤
    min(1, 1/|t|)``), no transcendental function: where it is small, the harmonics average away
    over the footprint (a footprint many cells wide in every direction that matters)."""
    total = mi.Float(0)
    for m in range(1, FOURIER_ORDER + 1, 2):
        for n in range(1, FOURIER_ORDER + 1, 2):
            for sign in (-1.0, 1.0):
                kx, ky = 0.5 * math.pi * m, 0.5 * sign * math.pi * n
                a0 = dr.minimum(1, dr.rcp(dr.abs(kx * e0.x + ky * e0.y)))
                a1 = dr.minimum(1, dr.rcp(dr.abs(kx * e1.x + ky * e1.y)))
                total = dr.fma(8.0 / (math.pi ** 2 * m * n), a0 * a1, total)
    return total


def area_mean(st, d0, d1):
    """(mean of c(s)·c(t) over ``st + a·d0 + b·d1``, a, b ∈ [-1/2, 1/2]; where it was
    computed): False for degenerate or non-finite footprints that cross a cell
    edge."""
    p = Parallelogram(mi.Point2f(_finite(st[0]), _finite(st[1])),
                      mi.Vector2f(_finite(d0[0]), _finite(d0[1])),
                      mi.Vector2f(_finite(d1[0]), _finite(d1[1])))
    # inside one cell: that cell's value, exactly (the walk below, relative to a lattice point
    # up to half a cell away, would round a footprint of 1e-8 cell to nothing there). "Inside"
    # with a margin of a few float32 ulps of the coordinates: a footprint that may cross an
    # edge within their rounding is walked, relative to that edge
    h = p.half_extent()
    h = h + (dr.abs(p.c) + h) * 2.0 ** -21
    inside = ((dr.floor(p.c.x - h.x) == dr.floor(p.c.x + h.x)) &
              (dr.floor(p.c.y - h.y) == dr.floor(p.c.y + h.y)))
    cell = square_wave(p.c.x) * square_wave(p.c.y)
    # rows along the shorter axis (swapping x and y leaves c(x)·c(y) unchanged)
    p = p.transposed(p.taller())
    # relative to the lattice point nearest the centre: small numbers, exact, so that a
    # footprint much smaller than a cell keeps its shape. Moving the origin by one cell flips
    # c and turns S into 1 - S; the constant integrates to 0 around the closed outline
    # (∮ c(y) dy = 0), so the integral only changes sign: by c(X + 1/2)·c(Y + 1/2)
    lattice = dr.round(p.c)
    sign = square_wave(lattice.x + 0.5) * square_wave(lattice.y + 0.5)
    p = p.moved(p.c - lattice)
    area = dr.abs(p.det())
    rows = 2 * p.half_extent().y
    ok = (area > 1e-12 * dr.maximum(rows * rows, 1e-30)) & (rows <= AREA_MAX_ROWS) & \
        dr.isfinite(area) & ~inside
    # counter-clockwise: ∮ S(x) c(y) dy = the integral of c(x) c(y) over the footprint
    total, = walk(p.outline(), ok, _piece_integral, (mi.Float(0),), knots=False, flush=False,
                  label='pbrt_checkerboard (area)')
    mean = dr.clip(sign * total / dr.select(ok, area, 1), -1, 1)
    # wider than the walk's rows (not degenerate): the Fourier series, relative to the lattice
    # point as the walk (pbrt-v3's box form, used before, is 0 there whatever the direction —
    # far off for thin footprints along a diagonal of the cells, where cells of one colour line
    # up: 0 for -0.79, a user trial)
    wide = ~ok & ~inside & (rows > AREA_MAX_ROWS) & (area > 0) & dr.isfinite(area)
    needed = wide & (fourier_bound(p.e0, p.e1) >= FOURIER_NEGLIGIBLE)
    mean = dr.select(wide, sign * fourier_mean(p.c, p.e0, p.e1, needed), mean)
    return dr.select(inside, cell, mean), ok | inside | wide
