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

pbrt-v3 has no antialiasing for 3D checkerboards and pbrt-v4 only the triangle; the box form is
the same product in 3D.

Numerics: pbrt's closed forms subtract O(x) quantities to get O(r) or O(r²) differences, which
loses most float32 digits for small footprints (at x ≈ 5 and r ≈ 10⁻³ the triangle form is off by
~10⁻³). Where r < 1/2 at most one cell edge lies in the footprint, and we evaluate the same
function as ``c_left·F + c_right·(1 - F)`` with F the kernel mass left of that edge (box:
``(1 + t)/2``; triangle: its piecewise-quadratic CDF), which is exact to float rounding. Results
are clamped to [-1, 1].
"""

from __future__ import annotations

import drjit as dr

AAMODES = ('none', 'box', 'closedform', 'triangle')


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
