"""The ``box`` image filter: the exact average of the bilinear reconstruction over the footprint.

A lookup's footprint is the parallelogram ``st + a·dst0 + b·dst1``, ``a, b ∈ [-1/2, 1/2]`` (one
pixel around the point the texture is evaluated at, from the four screen-space derivatives). The
filter returns the area average over it of the bilinear reconstruction of one pyramid level —
*exactly* (to float32 rounding), at any orientation and anisotropy, also under magnification (no
minimum width as EWA's "+1 texel²"; a footprint smaller than a texel averages the bilinear
surface over that small area). Everything is float32 and reads only the pyramid's buffer: no
table beyond the pyramid (:func:`build_box_tables` returns aliases of its buffer, see
:class:`BoxTables`).

How (per lane, at one level, in texel coordinates with texel centres at integers, relative to an
integer origin next to the footprint's centre; in the texture's frame or its transpose, whichever
makes the rows run along the footprint's longer extent, so that fewer rows need a chord):

* Green's theorem turns the area integral into ``∮ F dy`` with ``F(x, y) = ∫ f dx`` an
  antiderivative of the reconstruction along rows: between texel rows ``j`` and ``j+1`` (a
  *band*), ``f`` is the linear blend of the two rows' piecewise-linear interpolants, so ``F =
  (1-τ)·Q_j(x) + τ·Q_{j+1}(x)``, ``τ = y - j``, with ``Q_j`` an antiderivative of row ``j``. The
  boundary is walked counter-clockwise from the lowest corner ``B``: up the right chain to the
  highest corner ``T``, down the left chain back to ``B``.
* Each row's constant is chosen where it enters the footprint (its lower band boundary, or
  ``B``): ``Q_j = 0`` on the left chain there and ``Q_j`` = the row's integral across the
  footprint (the *chord*, from the left chain to the right one) on the right chain. So every
  value ``F`` takes is an integral over a few texels near the footprint, wherever it lies — no
  prefix of a whole row, no cancellation of large numbers.
* An iteration of the walk goes to the next knot (texel centre column), band boundary or corner.
  On the piece it crossed a row's ``Q`` grows by ``∫ r dx`` (``r`` linear between two knots), and
  that gain counts, by parts, with the row's remaining tent weight ``Λ(y)`` — the integral of
  its weight (``1 - τ`` or ``τ``) from y up to where the footprint leaves the row: the piece's
  contribution is ``∫ Λ(y) r(x) dx`` along it, a cubic (two Gauss–Legendre points, exact), in
  the direction walked (so the left chain, walked downwards, subtracts). It is a weight on each
  of the four texels of the cell; each texel of that 2×2 block collects its weight while the walk
  stays next to it and is read once, when it leaves the block (two texels per knot or band
  crossed).
* The chords, in a second loop: the integral of the entering row's knot "hats" from the left
  chain to the right one, times the row's tent weight, a closed form per knot, four knots per
  iteration.
* The sum is divided by the sum of the weights — the area of the polygon actually integrated
  (corners and crossings rounded to float32), so a constant texture averages to itself exactly
  and a thin footprint loses no digits to a mismatched area (worst error against polygon
  clipping, 64:1 footprints down to 0.006 texel across: 3e-6 on values in [0, 1]).
* Every iteration adds ``weights · texels`` for the texels it reads and carries no texel value:
  both loops are differentiable by Dr.Jit's sum-style reverse mode and by its forward mode
  (gradients reach the pyramid buffer exactly; the weights are geometry, not differentiated).
* A footprint inside one cell between four texel centres (magnification) needs no loop: the
  average of the bilinear polynomial over a parallelogram is its value at the centre plus the
  twist term ``f_xy·(e0x·e0y + e1x·e1y)/12``.

Cost and level: the walk's iterations are about the footprint's Manhattan perimeter in texels of
its level (one per knot and band crossed), the chords' about a quarter of its area plus its
shorter extent — about 45 and 9 for an 8:1 footprint 1.5 texels across. The level is the finest
at which the footprint's short side (its smaller height, area / longest side) is at most
:data:`MAX_BANDS` texels and its Manhattan perimeter at most :data:`MAX_PERIMETER` texels — level
0 (exact for the image itself) while both hold at level 0, whatever the orientation; beyond, the
exact average of a coarser level's reconstruction (as every MIP filter, blurred by that level's
texel size). Positions are float32: a footprint ``x`` texels from the level's origin carries
``x·2^-24`` texel of rounding, as every float32 lookup does.

Footprints that are degenerate (zero area) get the bilinear lookup at level 0; footprints that
would need a level beyond the top (many times wider than the image) get the coarsest texel (the
image mean), as pbrt does beyond the top level. Wrap modes act per texel read, as for every
filter: ``repeat`` and ``mirror`` footprints are first moved by whole periods next to the image,
``clamp`` and ``black`` ones far outside moved towards it along the region where the
reconstruction is constant (no change of value; keeps coordinates small).

``octahedralsphere`` wrapping couples the axes: ``pbrt_imagemap`` refuses ``filter="box"`` with it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from .wrap import COORD_LIMIT, wrap_1d

#: The level's short side (area / longest side) is at most this many texels.
MAX_BANDS = 16
#: The level's Manhattan perimeter 2·(|e0x| + |e0y| + |e1x| + |e1y|) is at most this many texels.
MAX_PERIMETER = 256
#: Footprints under this area (level-0 texels²) are points: bilinear at level 0.
MIN_AREA = 1e-8
BOX_WRAPS = ('repeat', 'mirror', 'clamp', 'black')
_GL = 0.5 / math.sqrt(3.0)              # two-point Gauss–Legendre nodes on [0, 1]: 1/2 ∓ _GL


class BoxTables:
    """What the box filter reads besides the pyramid, for one wrap mode: no table — the two
    walks read the pyramid's texels through ``walk`` and ``chords``, each the pyramid's buffer
    (the same memory) or, when it carries gradients, an AD variable of its own with an edge from
    it. Dr.Jit's forward mode through a loop follows every edge out of the variables the loop
    reads; a buffer also read elsewhere (the other loop, the closed forms, other filters on the
    pyramid) would take it onto edges outside the loop's scope, an error. A Dr.Jit struct
    (``walk`` and ``chords`` are traversed); made by :func:`build_box_tables`."""

    DRJIT_STRUCT = {'walk': object, 'chords': object}

    def __init__(self, walk=None, chords=None, wrap: str = 'repeat', channels: int = 1,
                 pyramid=None):
        self.walk = walk
        self.chords = chords
        self.wrap = wrap
        self.channels = channels
        self.pyramid = pyramid          # the pyramid they alias

    def nbytes(self) -> int:
        return 0                        # aliases of the pyramid's buffer


def _alias(buffer):
    """``buffer`` itself, or with gradients a new AD node for the same JIT variable."""
    if not dr.grad_enabled(buffer):
        return buffer
    return dr.replace_grad(dr.detach(buffer), buffer * 1.0)


def build_box_tables(pyramid, wrap: str) -> BoxTables:
    """The box filter's record for ``pyramid`` (which must hold every level) and ``wrap``: a
    pure function of the pyramid (gradients on its buffer reach the aliases). Call it where the
    pyramid is built (not inside a symbolic loop or call: an AD alias cannot be made there)."""
    if wrap not in BOX_WRAPS:
        raise ValueError(f'box filter: unsupported wrap mode "{wrap}"')
    return BoxTables(_alias(pyramid.buffer), _alias(pyramid.buffer), wrap, pyramid.channels,
                     pyramid)


# ------------------------------------------------------------------------------------ level
def _ceil_log2(x):
    """``ceil(log2(x))`` of positive normal float32 ``x``, exactly (from its bits)."""
    bits = dr.reinterpret_array(mi.UInt32, mi.Float(x))
    return mi.Int32(bits >> 23) - 127 + mi.Int32((bits & 0x7FFFFF) != 0)


def select_level(s0, t0, s1, t1, W: int, H: int):
    """(wanted level, area in level-0 texels²) of the footprint: the finest level at which its
    short side is ≤ MAX_BANDS texels and its Manhattan perimeter ≤ MAX_PERIMETER texels."""
    ax, ay, bx, by = s0 * W, t0 * H, s1 * W, t1 * H
    area = dr.abs(ax * by - ay * bx)
    longest = dr.sqrt(dr.maximum(ax * ax + ay * ay, bx * bx + by * by))
    short = area / dr.maximum(longest, 1e-30)
    perimeter = 2 * (dr.abs(ax) + dr.abs(ay) + dr.abs(bx) + dr.abs(by))
    tiny = 1e-30
    want = dr.maximum(_ceil_log2(dr.maximum(short / MAX_BANDS, tiny)),
                      _ceil_log2(dr.maximum(perimeter / MAX_PERIMETER, tiny)))
    return dr.maximum(want, 0), area


# ------------------------------------------------------------------------------------ frame
@dataclass
class _Texels:
    """Reading texel (column, row) of the lane's level in the walk's frame (float-valued
    integers, any range) — the texture's own, or transposed (``swap``: walk columns are texture
    rows): the level's first texel ``off``, the buffer strides of a walk row and column, the
    walk frame's size ``(w, h)`` and the wrap's data."""
    off: object
    row_stride: object
    col_stride: object
    w: object
    h: object
    inv_w: object
    inv_h: object
    mask: object          # (mask_x, mask_y) for power-of-two repeat, else None
    wrap: str
    buffer: object
    rgb: bool

    @staticmethod
    def of(mip, view, wrap: str, swap) -> '_Texels':
        (w, h), (inv_w, inv_h) = view.size, view.inv_size
        pow2 = not (mip.width & (mip.width - 1) or mip.height & (mip.height - 1))
        mask = None
        if pow2 and wrap == 'repeat':
            mx, my = mi.Int32(view.mask[0]), mi.Int32(view.mask[1])
            mask = (dr.select(swap, my, mx), dr.select(swap, mx, my))
        iw = mi.UInt32(view.iw)
        return _Texels(view.off, dr.select(swap, 1, iw), dr.select(swap, iw, 1),
                       dr.select(swap, h, w), dr.select(swap, w, h),
                       dr.select(swap, inv_h, inv_w), dr.select(swap, inv_w, inv_h), mask, wrap,
                       mip.pyr.buffer, mip.channels == 3)

    def _wrap(self, v, n, inv_n, mask):
        if self.wrap == 'black':
            return mi.UInt32(dr.clip(v, 0, n - 1)), (v >= 0) & (v < n)
        if mask is not None:
            return mi.UInt32(mi.Int32(v) & mask), mi.Bool(True)
        return mi.UInt32(wrap_1d(v, n, self.wrap, inv_n)), mi.Bool(True)

    def reading(self, buffer) -> '_Texels':
        """The same texels read through ``buffer`` (an alias of the pyramid's buffer)."""
        return _Texels(self.off, self.row_stride, self.col_stride, self.w, self.h, self.inv_w,
                       self.inv_h, self.mask, self.wrap, buffer, self.rgb)

    def row(self, y):
        """(first index of walk row y, validity)."""
        iy, ok = self._wrap(y, self.h, self.inv_h, None if self.mask is None else self.mask[1])
        return dr.fma(iy, self.row_stride, self.off), ok

    def read(self, row, x, active):
        """Texel x of a row from :meth:`row`: Float or Color3f."""
        ix, ok = self._wrap(x, self.w, self.inv_w, None if self.mask is None else self.mask[0])
        index = dr.fma(ix, self.col_stride, row[0])
        active = active & ok & row[1]
        if self.rgb:
            v = dr.gather(mi.Array4f, self.buffer, index, active)
            return mi.Color3f(v.x, v.y, v.z)
        return dr.gather(mi.Float, self.buffer, index, active)


@dataclass
class _Frame:
    """One lane's footprint at its level, relative to the integer origin ``(X0, Y0)``: the
    lowest corner ``B``, the right chain's middle corner ``R``, the highest corner ``T``, the
    left chain's middle corner ``L`` (counter-clockwise B, R, T, L), and which lanes take which
    path (``run``: the walk; ``in_cell``, ``degenerate``, ``beyond``:
    closed forms)."""
    level: object
    texels: _Texels
    X0: object
    Y0: object
    B: tuple
    R: tuple
    T: tuple
    L: tuple
    run: object
    in_cell: object
    degenerate: object
    beyond: object


def _finite(x):
    x = dr.detach(mi.Float(x))
    return dr.select(dr.isfinite(x), x, 0.0)


def _frame(mip, wrap, st, dst0, dst1, active) -> _Frame:
    """The level and the footprint's corners in the level's texels, per lane."""
    s0, t0, s1, t1 = _finite(dst0.x), _finite(dst0.y), _finite(dst1.x), _finite(dst1.y)
    want, area0 = select_level(s0, t0, s1, t1, mip.width, mip.height)
    degenerate = ~(area0 > MIN_AREA)
    last = len(mip.sizes) - 1
    beyond = want > last
    level = mi.UInt32(dr.minimum(want, last))
    view = mip.view(level)
    w, h = view.size
    sx = dr.clip(_finite(st.x), -COORD_LIMIT, COORD_LIMIT)
    sy = dr.clip(_finite(st.y), -COORD_LIMIT, COORD_LIMIT)
    cx, cy = dr.fma(sx, w, -0.5), dr.fma(sy, h, -0.5)
    ax, ay, bx, by = s0 * w, t0 * h, s1 * w, t1 * h
    hx, hy = 0.5 * (dr.abs(ax) + dr.abs(bx)), 0.5 * (dr.abs(ay) + dr.abs(by))
    # a footprint inside one cell (magnification): closed form, no loop
    in_cell = ((dr.floor(cx - hx) == dr.floor(cx + hx)) & (dr.floor(cy - hy) == dr.floor(cy + hy))
               & ~degenerate & active)
    # the walk's rows along the footprint's longer extent: fewer chords (one per row entered)
    swap = hy > hx
    cx, cy, ax, ay, bx, by, hx, hy = (dr.select(swap, q, p) for p, q in
                                      ((cx, cy), (cy, cx), (ax, ay), (ay, ax), (bx, by),
                                       (by, bx), (hx, hy), (hy, hx)))
    texels = _Texels.of(mip, view, wrap, swap)
    w, h = texels.w, texels.h
    cx, cy = _near_image(cx, cy, hx, hy, w, h, wrap)
    X0, Y0 = dr.floor(cx), dr.floor(cy)
    cx, cy = cx - X0, cy - Y0
    B, R = _lowest_corner(cx, cy, ax, ay, bx, by)
    T = (2 * cx - B[0], 2 * cy - B[1])                  # opposite corners: B + T = 2·centre
    L = (2 * cx - R[0], 2 * cy - R[1])
    run = active & ~degenerate & ~beyond & ~in_cell
    return _Frame(level, texels, X0, Y0, B, R, T, L, run, in_cell, degenerate, beyond)


def _near_image(cx, cy, hx, hy, w, h, wrap):
    """The footprint's centre moved by whole periods (repeat, mirror) into the first one, or
    (clamp, black) no farther than its half extent beyond the knots next to the image, where the
    reconstruction is constant along that axis: the same average, small coordinates."""
    if wrap in ('repeat', 'mirror'):
        n = 1 if wrap == 'repeat' else 2
        return cx - dr.floor(cx / (n * w)) * (n * w), cy - dr.floor(cy / (n * h)) * (n * h)
    return dr.clip(cx, -1 - hx, w + hx), dr.clip(cy, -1 - hy, h + hy)


def _lowest_corner(cx, cy, ax, ay, bx, by):
    """The lowest corner of the parallelogram and the next one counter-clockwise."""
    hx0, hy0, hx1, hy1 = 0.5 * ax, 0.5 * ay, 0.5 * bx, 0.5 * by
    corners = [(cx - hx0 - hx1, cy - hy0 - hy1), (cx + hx0 - hx1, cy + hy0 - hy1),
               (cx + hx0 + hx1, cy + hy0 + hy1), (cx - hx0 + hx1, cy - hy0 + hy1)]
    ccw = ax * by - ay * bx >= 0
    # clockwise: the same corners in the other order
    corners[1], corners[3] = ([tuple(dr.select(ccw, p, q) for p, q in zip(corners[1], corners[3])),
                               tuple(dr.select(ccw, q, p) for p, q in zip(corners[1], corners[3]))])
    k, best = mi.UInt32(0), corners[0][1]
    for m in (1, 2, 3):
        lower = corners[m][1] < best
        k = dr.select(lower, m, k)
        best = dr.select(lower, corners[m][1], best)

    def pick(idx):
        out = corners[3]
        for m in (2, 1, 0):
            out = tuple(dr.select(idx == m, p, q) for p, q in zip(corners[m], out))
        return out

    return pick(k), pick((k + 1) & 3)


# ------------------------------------------------------------------------------------ geometry
@dataclass
class _Edges:
    """The four edges counter-clockwise: 0 = B→R, 1 = R→T (the right chain, upwards), 2 = T→L,
    3 = L→B (the left chain, downwards): start points, directions and their reciprocals (0 where
    a component is 0)."""
    start: list
    d: list
    inv: list

    @staticmethod
    def of(f: _Frame) -> '_Edges':
        corners = [f.B, f.R, f.T, f.L]
        d = [(q[0] - p[0], q[1] - p[1]) for p, q in zip(corners, corners[1:] + corners[:1])]
        inv = [tuple(dr.select(c != 0, dr.rcp(c), 0.0) for c in v) for v in d]
        return _Edges(corners, d, inv)

    def pick(self, e):
        """Edge e's start, direction and reciprocals (the walk and :func:`_chain_x` read the
        same values, so a row's chord starts where the walk meets the row, to the last bit)."""
        def sel(items):
            odd = (e & 1) == 1
            lo = tuple(dr.select(odd, p, q) for p, q in zip(items[1], items[0]))
            hi = tuple(dr.select(odd, p, q) for p, q in zip(items[3], items[2]))
            return tuple(dr.select(e >= 2, p, q) for p, q in zip(hi, lo))
        return sel(self.start), sel(self.d), sel(self.inv)


@dataclass
class _Remaining:
    """The remaining tent weights of a band's two rows as functions of the height z ∈ [0, 1]
    in the band: Λ(z) = ∫ of the row's tent weight from z up to where the chain leaves the row
    (the top corner T, ``zT`` above the band's floor, or the row's last band). Lower row (weight
    1 - z, up to min(1, zT)): ``lo - z + z²/2``; upper row (weight z, then 2 - z in the band
    above, up to min(2, zT)): ``hi - z²/2``."""
    lo: object
    hi: object

    @staticmethod
    def of(zT) -> '_Remaining':
        e = dr.clip(zT, 0.0, 1.0)
        e2 = dr.clip(zT, 1.0, 2.0)
        half_e2 = 0.5 * e * e
        return _Remaining(e - half_e2, half_e2 + dr.fma(e2, dr.fma(e2, -0.5, 2.0), -1.5))

    def lower(self, z):
        return dr.fma(0.5 * z, z, self.lo - z)

    def upper(self, z):
        return dr.fma(-0.5 * z, z, self.hi)


def _hat_cdf(z):
    """∫ (1 - |t|) dt from -1 to z (clamped to [-1, 1])."""
    z = dr.clip(z, -1.0, 1.0)
    return dr.fma(z, dr.fma(dr.abs(z), -0.5, 1.0), 0.5)


@dataclass
class _Step:
    """Where an iteration of the walk goes on its edge: to param ``s1`` and point ``(x1, y1)``,
    because of a knot (``knot``, in direction ``right``), a band boundary (``band``) or the
    edge's end (``end``)."""
    s1: object
    x1: object
    y1: object
    knot: object
    band: object
    end: object
    right: object


def _next_event(start, d, inv, s, i, j, up) -> _Step:
    """The next knot, band boundary or end along the edge from param ``s`` in cell (i, j)
    (``up``: the edge goes upwards, else downwards)."""
    right = d[0] > 0
    knot_x = dr.select(right, i + 1, i)
    band_y = dr.select(up, j + 1, j)
    sk = dr.select(d[0] != 0, (knot_x - start[0]) * inv[0], dr.inf)
    # band boundaries only in the chain's direction: corners opposite each other come from the
    # centre (rounded), so a side of a nearly axis-aligned footprint can run an ulp the other
    # way, and its next boundary would then lie behind it, for ever
    along = dr.select(up, d[1] > 0, d[1] < 0)
    sb = dr.select(along, (band_y - start[1]) * inv[1], dr.inf)
    first = dr.minimum(sk, sb)
    end = ~(first < 1)
    band = ~end & (sb <= sk)
    knot = ~end & ~band
    s1 = dr.clip(first, s, 1.0)
    x1 = dr.select(knot, knot_x, dr.fma(s1, d[0], start[0]))
    y1 = dr.select(band, band_y, dr.fma(s1, d[1], start[1]))
    x1 = dr.select(end, start[0] + d[0], x1)
    y1 = dr.select(end, start[1] + d[1], y1)
    return _Step(s1, dr.clip(x1, i, i + 1), dr.clip(y1, j, j + 1), knot, band, end, right)


def _piece_weights(x, y, x1, y1, i, j, rem: _Remaining):
    """Weights of texels (i, j), (i+1, j), (i, j+1), (i+1, j+1) for the walk's piece from
    (x, y) to (x1, y1) inside cell (i, j). Along the chain, a row's antiderivative gains
    ``∫ r dx`` on the piece, and that gain counts with the row's remaining tent weight Λ(y)
    (:class:`_Remaining`): by parts, the piece's whole contribution is ``∫ Λ(y) r(x) dx``
    along it, in the direction walked (so the left chain, walked downwards, subtracts). Λ is
    quadratic in y and r linear in x, both linear along the piece: a cubic, exact with two
    Gauss–Legendre points."""
    h = 0.5 * (x1 - x)
    z0, dz, dx = y - j, y1 - y, x1 - x
    out = [0.0, 0.0, 0.0, 0.0]
    for node in (0.5 - _GL, 0.5 + _GL):
        u = dr.fma(node, dx, x) - i
        z = dr.fma(node, dz, z0)
        lo, hi = h * rem.lower(z), h * rem.upper(z)
        lo_b, hi_b = lo * u, hi * u
        out = [out[0] + (lo - lo_b), out[1] + lo_b, out[2] + (hi - hi_b), out[3] + hi_b]
    return out


def _chain_x(f: _Frame, edges: _Edges, chain: int, y):
    """x of the right (0) or left (1) chain at height y (strictly between B and T)."""
    middle = f.R if chain == 0 else f.L
    lower, upper = (0, 1) if chain == 0 else (3, 2)
    on_lower = y <= middle[1]
    p = [dr.select(on_lower, a, b) for a, b in zip(edges.start[lower], edges.start[upper])]
    dx = dr.select(on_lower, edges.d[lower][0], edges.d[upper][0])
    inv_dy = dr.select(on_lower, edges.inv[lower][1], edges.inv[upper][1])
    return dr.fma((y - p[1]) * inv_dy, dx, p[0])


# ------------------------------------------------------------------------------------ lookup
def box(mip, tables: BoxTables, st, dst0, dst1, active):
    """The exact box-filtered value at ``st`` for the footprint spanned by ``dst0 = (ds/dx,
    dt/dx)`` and ``dst1 = (ds/dy, dt/dy)``: Float (1 channel) or Color3f (RGB)."""
    if not mip.has_pyramid:
        raise ValueError('the box filter needs every level of the MIP pyramid')
    active = mi.Bool(active)
    f = _frame(mip, tables.wrap, st, dst0, dst1, active)
    edges = _Edges.of(f)
    value_type = mip.value_type()
    acc, area = _walk(f, edges, f.texels.reading(tables.walk), value_type)
    acc_c, area_c = _chords(f, edges, f.texels.reading(tables.chords), value_type)
    # divided by the weights' own sum, the area of the polygon the walk integrated (its corners
    # and crossings rounded to float32): a constant texture averages to itself exactly, and a
    # thin footprint's area is not cancelled away against another rounding
    area = dr.select(f.run, area + area_c, 1.0)
    result = dr.select(f.run, (acc + acc_c) / dr.select(area > 0, area, 1.0), 0)
    cell = _single_cell(mip, f.level, st, dst0, dst1, f.in_cell)
    result = dr.select(f.in_cell, cell, result)
    result = dr.select(f.degenerate, mip.bilinear(0, st, active & f.degenerate), result)
    coarse = f.beyond & ~f.degenerate & ~f.in_cell
    return dr.select(coarse, mip.coarsest(active & coarse), result)


# ------------------------------------------------------------------------------------ the loops
@dataclass
class _Leaving:
    """The two texels of the walk's 2×2 block that an iteration reads — the ones leaving it —
    at block columns ``col_a``, ``col_b`` and rows ``row_a``, ``row_b`` (0/1), their weights,
    and the weights the block keeps, moved to their place in its new position."""
    col_a: object
    row_a: object
    col_b: object
    row_b: object
    w_a: object
    w_b: object
    kept: list


def _leaving(w, knot, right, band, up) -> _Leaving:
    """Which block texels leave (slots: (i, j), (i+1, j), (i, j+1), (i+1, j+1)): a knot crossed
    to the right takes the left column away, to the left the right one; a band boundary crossed
    upwards the lower row, downwards the upper one."""
    z = mi.Float(0)
    kr, kl = knot & right, knot & ~right
    bu, bd = band & up, band & ~up
    kept = [dr.select(kr, w[1], dr.select(bu, w[2], dr.select(kl | bd, z, w[0]))),
            dr.select(kl, w[0], dr.select(bu, w[3], dr.select(kr | bd, z, w[1]))),
            dr.select(kr, w[3], dr.select(bd, w[0], dr.select(kl | bu, z, w[2]))),
            dr.select(kl, w[2], dr.select(bd, w[1], dr.select(kr | bu, z, w[3])))]
    col_a = dr.select(kl, 1.0, 0.0)
    row_a = dr.select(bd, 1.0, 0.0)
    return _Leaving(col_a, row_a, dr.select(knot, col_a, 1.0), dr.select(knot, 1.0, row_a),
                    dr.select(kl, w[1], dr.select(bd, w[2], w[0])),
                    dr.select(kr, w[2], dr.select(knot | bd, w[3], w[1])), kept)


def _walk(f: _Frame, edges: _Edges, tex: _Texels, value_type):
    """∮ F dy counter-clockwise: up the right chain, down the left one (lanes ``f.run``),
    without the chords. Each texel of the cell's 2×2 block collects its weight while the walk
    stays next to it and is read once, when it leaves the block (a knot or band crossed; back at
    B the lower row, then — edge 4, a flush — the upper one)."""
    def body(e, s, x, y, i, j, w, acc, area):
        start, d, inv = edges.pick(e)
        up = e < 2
        step = _next_event(start, d, inv, s, i, j, up)
        walking = e < 4
        x1 = dr.select(walking, step.x1, x)             # the flush stays put: no piece
        y1 = dr.select(walking, step.y1, y)
        piece = _piece_weights(x, y, x1, y1, i, j, _Remaining.of(f.T[1] - j))
        w = [c + p for p, c in zip(piece, w)]
        knot = walking & step.knot
        closed = (walking & step.end & (e == 3)) | ~walking     # back at B: flush the block
        band = (walking & step.band) | closed
        rising = up | closed
        out = _leaving(w, knot, step.right, band, rising)
        for col, row, wt in ((out.col_a, out.row_a, out.w_a), (out.col_b, out.row_b, out.w_b)):
            v = tex.read(tex.row(f.Y0 + j + row), f.X0 + i + col, knot | band)
            acc = dr.fma(v, wt, acc)
            area = area + dr.select(knot | band, wt, 0.0)     # (black: outside texels too)
        # the walk moves on
        i_n = dr.select(knot, dr.select(step.right, i + 1, i - 1), i)
        j_n = dr.select(band, dr.select(rising, j + 1, j - 1), j)
        next_edge = (walking & step.end) | ~walking
        return (dr.select(next_edge, e + 1, e), dr.select(next_edge, 0.0, step.s1), x1, y1,
                i_n, j_n, out.kept, acc, area)

    zero = mi.Float(0)
    state = (mi.UInt32(0), zero, f.B[0], f.B[1], dr.floor(f.B[0]), dr.floor(f.B[1]),
             [zero] * 4, dr.zeros(value_type), zero)
    # every iteration ends the edge or moves to the next knot or band towards its end: at most
    # |Δx| + |Δy| + 3 per edge (a NaN ends it), so no step count is needed
    return dr.while_loop(state, lambda e, *_: f.run & (e < 5), body, max_iterations=-1,
                         label='pbrt_box_walk')[-2:]


def _chords(f: _Frame, edges: _Edges, tex: _Texels, value_type):
    """The right chain's row constants: at every band boundary y strictly between B and T, the
    row entering there (y + 1) integrated from the left chain to the right one, times its tent
    weight over the rest of the footprint — four knots per iteration."""

    def cond(y, k, acc, area):
        return f.run & (y < f.T[1])

    def body(y, k, acc, area):
        xa, xb = _chain_x(f, edges, 1, y), _chain_x(f, edges, 0, y)
        lo, hi = dr.floor(dr.minimum(xa, xb)), dr.ceil(dr.maximum(xa, xb))
        omega = _Remaining.of(f.T[1] - y).hi
        row = tex.row(f.Y0 + y + 1)
        for m in range(4):
            knot = lo + k + m
            wt = omega * (_hat_cdf(xb - knot) - _hat_cdf(xa - knot))
            acc = dr.fma(tex.read(row, f.X0 + knot, knot <= hi), wt, acc)
            area = area + wt
        done = ~(lo + k + 4 <= hi)                      # (a NaN ends it too)
        return dr.select(done, y + 1, y), dr.select(done, 0.0, k + 4), acc, area

    # ends: k grows by 4 up to the chord's last knot, then y by 1 up to T
    state = (dr.floor(f.B[1]) + 1, mi.Float(0), dr.zeros(value_type), mi.Float(0))
    return dr.while_loop(state, cond, body, max_iterations=-1, label='pbrt_box_chords')[-2:]


def _single_cell(mip, level, st, dst0, dst1, active):
    """The exact average over a parallelogram inside one cell between four texel centres: the
    bilinear value at its centre plus the twist term ``f_xy·(e0x·e0y + e1x·e1y)/12``."""
    texels, wx, wy, (w, h) = mip.corners(level, st, active)
    f00, f10, f01, f11 = texels
    centre = (f00 * wx[0] + f10 * wx[1]) * wy[0] + (f01 * wx[0] + f11 * wx[1]) * wy[1]
    e0 = (_finite(dst0.x) * w, _finite(dst0.y) * h)
    e1 = (_finite(dst1.x) * w, _finite(dst1.y) * h)
    twist = (e0[0] * e0[1] + e1[0] * e1[1]) * (1.0 / 12.0)
    return centre + (f00 - f10 - f01 + f11) * twist
