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
  highest corner ``T``, down the left chain back to ``B`` (:func:`.outline.walk`, the walk the
  checkerboard's ``area`` mode takes too; here cut at knots as well as band boundaries).
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
  (corners and crossings rounded to float32), so a constant texture averages to itself up to
  the float32 rounding of the two sums, and a thin footprint loses no digits to a mismatched
  area (worst error against polygon clipping, 64:1 footprints down to 0.006 texel across: 3e-6
  on values in [0, 1]). Those roundings grow with the walk: its partial weights have both signs
  and cancel, so long walks on the coarse levels of elongated images return a constant up to
  ~2e-4 of its value off (footprints to 10³ image widths, any orientation: 1.8e-5 on a 33×5
  image, 0.5–1.8e-4 on 3×1000, 2×700, 700×1, 3×257 and 8×2048 ones, up to 8e-6 on square
  ones).
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

from .mipmap import ad_alias
from .outline import Outline, Parallelogram, Piece, walk
from .wrap import COORD_LIMIT, PERIODIC, first_period, wrap_1d

#: The level's short side (area / longest side) is at most this many texels. A footprint wider
#: than this is walked on a coarser level, in about half the walk's and chords' iterations per
#: level, and loses the detail of the levels it skips: a coarser level's reconstruction blurs
#: the footprint's outline by about its texel, an error of about (that texel / the short side)
#: of the contrast there — 16 keeps pixel averages of minified images with sharp detail at the
#: reference's noise where 6 left them at up to 19× it (README, *Speed against error*).
MAX_BANDS = 16
#: The level's Manhattan perimeter 2·(|e0x| + |e0y| + |e1x| + |e1y|) is at most this many texels:
#: the walk's iterations, and a SIMD packet runs as long as its longest lane (README, *Speed
#: against error*: what 128 instead of 256 saves and costs next to a far edge).
MAX_PERIMETER = 128
#: Footprints under this area (level-0 texels²) are points: bilinear at level 0.
MIN_AREA = 1e-8
BOX_WRAPS = ('repeat', 'mirror', 'clamp', 'black')
_GL = 0.5 / math.sqrt(3.0)              # two-point Gauss–Legendre nodes on [0, 1]: 1/2 ∓ _GL
#: Texels are summed scaled by 2^-12 and the normalised sum scaled back (powers of two: the
#: same result bit for bit above ~1e-34), so that sums over a level's footprint (at most
#: MAX_BANDS × MAX_PERIMETER / 2 texels² and the walk's partial weights) of texels near ±1e38
#: stay finite instead of overflowing to inf.
_ACC_SCALE = 2.0 ** -12


class BoxTables:
    """What the box filter reads besides the pyramid, for one wrap mode: no table — the two
    walks read the pyramid's texels through ``walk`` and ``chords``, each an
    :func:`~mitsuba_pbrt_tex.mipmap.ad_alias` of the pyramid's buffer (the same memory; with
    gradients, an AD variable of each loop's own). A Dr.Jit struct (``walk`` and ``chords`` are
    traversed); made by :func:`build_box_tables`."""

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


def build_box_tables(pyramid, wrap: str) -> BoxTables:
    """The box filter's record for ``pyramid`` (which must hold every level) and ``wrap``: a
    pure function of the pyramid (gradients on its buffer reach the aliases). Call it where the
    pyramid is built (not inside a symbolic loop or call: an AD alias cannot be made there)."""
    if wrap not in BOX_WRAPS:
        raise ValueError(f'box filter: unsupported wrap mode "{wrap}"')
    return BoxTables(ad_alias(pyramid.buffer), ad_alias(pyramid.buffer), wrap, pyramid.channels,
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
    """One lane's footprint at its level, relative to the integer origin ``(X0, Y0)``, in the
    walk's frame (:class:`_Texels`), and which lanes take which path (``run``: the walk;
    ``in_cell``, ``degenerate``, ``beyond``: closed forms)."""
    level: object
    texels: _Texels
    X0: object
    Y0: object
    outline: Outline
    run: object
    in_cell: object
    degenerate: object
    beyond: object


def _finite(x):
    x = dr.detach(mi.Float(x))
    return dr.select(dr.isfinite(x), x, 0.0)


def _frame(mip, wrap, st, dst0, dst1, active) -> _Frame:
    """The level and the footprint's outline in the level's texels, per lane."""
    s0, t0, s1, t1 = _finite(dst0.x), _finite(dst0.y), _finite(dst1.x), _finite(dst1.y)
    want, area0 = select_level(s0, t0, s1, t1, mip.width, mip.height)
    degenerate = ~(area0 > MIN_AREA)
    last = len(mip.sizes) - 1
    beyond = want > last
    level = mi.UInt32(dr.minimum(want, last))
    view = mip.view(level)
    w, h = view.size
    sx, sy = _near_origin(_finite(st.x), wrap), _near_origin(_finite(st.y), wrap)
    p = Parallelogram(mi.Point2f(dr.fma(sx, w, -0.5), dr.fma(sy, h, -0.5)),
                      mi.Vector2f(s0 * w, t0 * h), mi.Vector2f(s1 * w, t1 * h))
    c, half = p.c, p.half_extent()
    # a footprint inside one cell (magnification): closed form, no loop
    in_cell = ((dr.floor(c.x - half.x) == dr.floor(c.x + half.x)) &
               (dr.floor(c.y - half.y) == dr.floor(c.y + half.y)) & ~degenerate & active)
    # the walk's rows along the footprint's longer extent: fewer chords (one per row entered)
    swap = p.taller()
    p = p.transposed(swap)
    texels = _Texels.of(mip, view, wrap, swap)
    c = _near_image(p.c, p.half_extent(), texels.w, texels.h, wrap)
    origin = dr.floor(c)
    run = active & ~degenerate & ~beyond & ~in_cell
    return _Frame(level, texels, origin.x, origin.y, p.moved(c - origin).outline(), run, in_cell,
                  degenerate, beyond)


def _near_origin(s, wrap):
    """Texture coordinate ``s`` moved by whole periods into the first (repeat, mirror: the same
    lookup, and the footprint's texel coordinates keep their float32 digits however far out it
    was), else within ±COORD_LIMIT (clamp, black: the reconstruction is constant that far
    out)."""
    if wrap in PERIODIC:
        return first_period(s, wrap)
    return dr.clip(s, -COORD_LIMIT, COORD_LIMIT)


def _near_image(c, half, w, h, wrap):
    """The footprint's centre, (clamp, black) moved no farther than its half extent beyond the
    knots next to the image, where the reconstruction is constant along that axis: the same
    average, small coordinates. (Repeat and mirror centres are in the first period already:
    :func:`_near_origin`.)"""
    if wrap in PERIODIC:
        return c
    return mi.Point2f(dr.clip(c.x, -1 - half.x, w + half.x), dr.clip(c.y, -1 - half.y, h + half.y))


# ------------------------------------------------------------------------------------ geometry
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


# ------------------------------------------------------------------------------------ lookup
def box(mip, tables: BoxTables, st, dst0, dst1, active):
    """The exact box-filtered value at ``st`` for the footprint spanned by ``dst0 = (ds/dx,
    dt/dx)`` and ``dst1 = (ds/dy, dt/dy)``: Float (1 channel) or Color3f (RGB)."""
    if not mip.has_pyramid:
        raise ValueError('the box filter needs every level of the MIP pyramid')
    active = mi.Bool(active)
    f = _frame(mip, tables.wrap, st, dst0, dst1, active)
    value_type = mip.value_type()
    acc, area = _walk(f, f.texels.reading(tables.walk), value_type)
    acc_c, area_c = _chords(f, f.texels.reading(tables.chords), value_type)
    # divided by the weights' own sum, the area of the polygon the walk integrated (its corners
    # and crossings rounded to float32): a constant texture averages to itself (to the sums'
    # rounding), and a thin footprint's area is not cancelled away against another rounding
    area = dr.select(f.run, area + area_c, 1.0)
    result = dr.select(f.run, (acc + acc_c) / dr.select(area > 0, area, 1.0) * (1 / _ACC_SCALE),
                       0)
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


def _walk(f: _Frame, tex: _Texels, value_type):
    """∮ F dy counter-clockwise: up the right chain, down the left one (lanes ``f.run``),
    without the chords, cut at knots and band boundaries. Each texel of the cell's 2×2 block
    collects its weight while the walk stays next to it and is read once, when it leaves the
    block (a knot or band crossed; back at B the lower row, then — the flush — the upper one)."""
    top = f.outline.T.y

    def integrand(p: Piece, w, acc, area):
        piece = _piece_weights(p.x, p.y, p.x1, p.y1, p.i, p.j, _Remaining.of(top - p.j))
        w = [c + q for q, c in zip(piece, w)]
        out = _leaving(w, p.knot, p.right, p.band, p.rising)
        crossed = p.knot | p.band
        for col, row, wt in ((out.col_a, out.row_a, out.w_a), (out.col_b, out.row_b, out.w_b)):
            v = tex.read(tex.row(f.Y0 + p.j + row), f.X0 + p.i + col, crossed)
            acc = dr.fma(v, wt * _ACC_SCALE, acc)
            area = area + dr.select(crossed, wt, 0.0)     # (black: outside texels too)
        return out.kept, acc, area

    zero = mi.Float(0)
    return walk(f.outline, f.run, integrand, ([zero] * 4, dr.zeros(value_type), zero),
                knots=True, flush=True, label='pbrt_box_walk')[1:]


def _chords(f: _Frame, tex: _Texels, value_type):
    """The right chain's row constants: at every band boundary y strictly between B and T, the
    row entering there (y + 1) integrated from the left chain to the right one, times its tent
    weight over the rest of the footprint — four knots per iteration."""

    top = f.outline.T.y

    def cond(y, k, acc, area):
        return f.run & (y < top)

    def body(y, k, acc, area):
        xa, xb = f.outline.chain_x(False, y), f.outline.chain_x(True, y)
        lo, hi = dr.floor(dr.minimum(xa, xb)), dr.ceil(dr.maximum(xa, xb))
        omega = _Remaining.of(top - y).hi
        row = tex.row(f.Y0 + y + 1)
        for m in range(4):
            knot = lo + k + m
            wt = omega * (_hat_cdf(xb - knot) - _hat_cdf(xa - knot))
            acc = dr.fma(tex.read(row, f.X0 + knot, knot <= hi), wt * _ACC_SCALE, acc)
            area = area + wt
        done = ~(lo + k + 4 <= hi)                      # (a NaN ends it too)
        return dr.select(done, y + 1, y), dr.select(done, 0.0, k + 4), acc, area

    # ends: k grows by 4 up to the chord's last knot, then y by 1 up to T
    state = (dr.floor(f.outline.B.y) + 1, mi.Float(0), dr.zeros(value_type), mi.Float(0))
    return dr.while_loop(state, cond, body, max_iterations=-1, label='pbrt_box_chords')[-2:]


def _single_cell(mip, level, st, dst0, dst1, active):
    """The exact average over a parallelogram inside one cell between four texel centres: the
    bilinear value at its centre plus the twist term ``f_xy·(e0x·e0y + e1x·e1y)/12``."""
    texels, wx, wy, (w, h) = mip.corners(level, st, active)
    f00, f10, f01, f11 = texels
    centre = (f00 * wx[0] + f10 * wx[1]) * wy[0] + (f01 * wx[0] + f11 * wx[1]) * wy[1]
    e0 = (_finite(dst0.x) * w, _finite(dst0.y) * h)
    e1 = (_finite(dst1.x) * w, _finite(dst1.y) * h)
    twist = (e0[0] * e0[1] + e1[0] * e1[1]) * (1.0 / 6.0)
    # halved differences: f00 - f10 - f01 + f11 reaches 4e38 on texels of ±1e38
    return centre + (0.5 * (f00 - f10) - 0.5 * (f01 - f11)) * twist
