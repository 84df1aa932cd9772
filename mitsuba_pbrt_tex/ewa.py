"""Elliptically weighted average filtering (pbrt section 10.4.5; pbrt-v3/v4 ``MIPMap::EWA``).

Exactly pbrt's filter:

1. The two screen-space derivative vectors of (s, t) are the ellipse's axes; the longer is the
   major axis. If ``minor · maxanisotropy < major`` (and minor > 0) the *minor* axis is lengthened
   to ``major / maxanisotropy`` (more blur, bounded cost). A zero minor axis means bilinear at
   level 0.
2. The level comes from the minor axis: ``lod = max(0, L - 1 + log2(minor))``; the result is the
   linear blend of the EWA sums at ``floor(lod)`` and ``floor(lod) + 1``.
3. At one level, in texel units, the implicit ellipse ``A·ds² + B·ds·dt + C·dt² < 1`` has
   ``A = dt0² + dt1² + 1``, ``B = -2(ds0·dt0 + ds1·dt1)``, ``C = ds0² + ds1² + 1`` normalised by
   ``1 / (AC - B²/4)``: the ``+1`` texel² keeps at least the nearest texel inside when the ellipse
   is thinner than a texel (magnification; pbrt-v2 issue #25). Each texel centre inside gets the
   weight ``LUT[min(int(r²·128), 127)]`` from the 128-entry table ``exp(-2·i/127) - exp(-2)``
   (a Gaussian with α = 2, truncated to 0 at the border; pbrt indexes with 128 but builds with
   127, which we keep for identical results), and the result is the weighted average.

Vectorisation: each lane loops over *the texels of its own ellipse*, row by row — for every row
the two roots of the quadratic give the column span — instead of pbrt's bounding box. Texels the
bounding box adds are outside the ellipse and have weight 0, so the result is identical while a
45° 8:1 footprint visits several times fewer texels. Each iteration takes two adjacent columns
(:data:`COLUMNS_PER_STEP`, half the per-iteration bookkeeping), and the wrapped row is computed
once per row. The table weight ``LUT[i]`` is computed rather than gathered, as a degree-7
polynomial in ``i`` fitted to the table (relative error 3.6e-7 in float32, against 1.4e-7 for
the float32 table itself; a third of the instructions of ``exp``). Texels with ``r²·128 ≥ 127``
get table entry 127, which is exactly 0, so the loop tests ``r² < 127/128``. The loop is a
``dr.while_loop`` with the ``max_iterations=-1`` hint (a sum-style loop), so reverse-mode AD
through it reaches the texels.

Memory: at random uv the filter is bound by memory latency, not arithmetic — an 8:1 footprint
with a 1.5-texel minor axis touches about 40 cache lines (levels 0 and 1), against about 2.5 for
a bilinear lookup, and the same ellipses cost 3–4× less on levels small enough to stay in cache
(``bench lookups``). So :meth:`EWAFilter.__call__` hands batches that can be reordered —
evaluated arrays, outside a symbolic loop or call — to :mod:`~mitsuba_pbrt_tex.lookup_order`,
which filters them sorted by texture tile when enough of their lookups read such large levels
(the same values, 2.5–3.5× faster at random uv). The levels stay plain rows of texels: the other
layouts and loop shapes measured, and why they lost, are in the design notes of
``mitsuba_pbrt_tex/bench/report/lookups.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .lookup_order import MIN_LEVEL_BYTES, in_tile_order
from .mipmap import ad_alias
from .wrap import adjacent_wrapped, texel_coord, wrap_2d

LUT_SIZE = 128
ALPHA = 2.0
#: Texels whose centre is within this distance (texels) outside a row's exact span are still
#: tested against r² < 1, so rounding in the span computation can never drop a weighted texel.
SPAN_SLACK = 1e-3
COLUMNS_PER_STEP = 2          # adjacent_wrapped() below gives exactly two columns
_EXP_NEG_ALPHA = float(np.float32(np.exp(-ALPHA)))
#: Taps are summed scaled by 2^-20 and the normalised sum scaled back: powers of two, so every
#: result is bit-identical (texels above ~1e-32 in magnitude), while sums of up to 2^20 taps of
#: texels near float32's maximum (3.4e38) stay finite instead of overflowing to inf.
_ACC_SCALE = 2.0 ** -20


def _finite(x):
    return dr.select(dr.isfinite(x), x, 0.0)


class EWABuffers:
    """What EWA's two level sums read: each an :func:`~mitsuba_pbrt_tex.mipmap.ad_alias` of the
    pyramid's buffer (the same memory; with gradients, an AD variable of each loop's own, so
    that forward mode through one loop does not follow the other's edges). A Dr.Jit struct;
    made by :func:`build_ewa_buffers` where the pyramid is built."""

    DRJIT_STRUCT = {'lower': object, 'upper': object}

    def __init__(self, lower=None, upper=None):
        self.lower = lower
        self.upper = upper


def build_ewa_buffers(pyramid) -> EWABuffers:
    """The aliases EWA's level sums read, for ``pyramid`` (not inside a symbolic loop or
    call)."""
    return EWABuffers(ad_alias(pyramid.buffer), ad_alias(pyramid.buffer))


class EWAFilter:
    """pbrt's EWA over a :class:`~mitsuba_pbrt_tex.mipmap.MIPMap`."""

    def __init__(self, max_anisotropy: float, reorder: bool = True):
        self.max_anisotropy = float(max_anisotropy)
        self.reorder = reorder

    def __call__(self, mip, st, dst0, dst1, active, buffers: EWABuffers | None = None):
        """``dst0 = (ds/dx, dt/dx)``, ``dst1 = (ds/dy, dt/dy)`` (Vector2f); ``mip`` must hold
        every level. ``buffers``: what the level sums read (:func:`build_ewa_buffers`; without,
        the pyramid's buffer itself — enough where no forward-mode derivative passes)."""
        if not mip.has_pyramid:
            raise ValueError('EWA needs every level of the MIP pyramid')
        # Filter large batches in texture-tile order (:mod:`~mitsuba_pbrt_tex.lookup_order`)
        # when levels 0 … cached_from-1 are too large to stay in cache (lookups there gain).
        level0_bytes = mip.level_nbytes(0)
        cached_from = math.floor(math.log(level0_bytes / MIN_LEVEL_BYTES, 4)) + 1
        if not self.reorder or cached_from <= 0:
            return self.filter(mip, st, dst0, dst1, active, buffers)
        active = mi.Bool(active)

        def uncached():
            return active & (mip.level_of(self.axes(dst0, dst1)[3]) < cached_from)

        return in_tile_order(lambda *a: self.filter(mip, *a, buffers), st, dst0, dst1, active,
                             width=mip.width, height=mip.height, worth=uncached)

    def axes(self, dst0, dst1):
        """(major vector, minor vector, major length, minor length) after pbrt's anisotropy
        clamp (non-finite derivatives count as 0)."""
        dst0 = mi.Vector2f(_finite(dst0.x), _finite(dst0.y))
        dst1 = mi.Vector2f(_finite(dst1.x), _finite(dst1.y))
        swap = dr.squared_norm(dst0) < dr.squared_norm(dst1)
        dst0, dst1 = dr.select(swap, dst1, dst0), dr.select(swap, dst0, dst1)
        major, minor = dr.norm(dst0), dr.norm(dst1)
        clamp = (minor * self.max_anisotropy < major) & (minor > 0)
        scale = dr.select(clamp, major / (minor * self.max_anisotropy), 1.0)
        return dst0, dst1 * scale, major, minor * scale

    def filter(self, mip, st, dst0, dst1, active, buffers: EWABuffers | None = None):
        """The filter itself, lanes in the order given."""
        dst0, dst1, _, minor = self.axes(dst0, dst1)

        degenerate = ~(minor > 0)
        n_levels = mip.n_levels
        lod = dr.maximum(0.0, mip.level_of(minor))
        lod = dr.minimum(lod, float(n_levels))              # beyond: the coarsest texel anyway
        ilod = dr.floor(lod)
        frac = lod - ilod
        run = active & ~degenerate
        lower, upper = (None, None) if buffers is None else (buffers.lower, buffers.upper)
        v0 = self.level(mip, ilod, st, dst0, dst1, run & (frac < 1), lower)
        v1 = self.level(mip, ilod + 1, st, dst0, dst1, run & (frac > 0), upper)
        ewa = dr.select(frac <= 0, v0, dr.select(frac >= 1, v1, dr.lerp(v0, v1, frac)))
        fallback = mip.bilinear(0, st, active & degenerate)
        return dr.select(degenerate, fallback, ewa)

    def level(self, mip, flevel, st, dst0, dst1, active, buffer=None):
        """The EWA sum at one level (per lane, a whole Float), reading ``buffer`` (an alias of
        the pyramid's, or None: the pyramid's); levels beyond the last give the coarsest
        texel."""
        last = len(mip.sizes) - 1
        beyond = flevel > last
        view = mip.view(mi.UInt32(dr.minimum(flevel, last)))
        e = self._ellipse(mip, view, st, dst0, dst1)
        acc, acc_w = _ellipse_sum(mip, view, e, active & ~beyond, buffer)
        T = mip.value_type()
        result = dr.select(acc_w > 0, acc / dr.select(acc_w > 0, acc_w, 1) * (1 / _ACC_SCALE),
                           dr.zeros(T))
        return dr.select(beyond, mip.coarsest(active & beyond), result)

    def _ellipse(self, mip, view, st, dst0, dst1) -> '_Ellipse':
        """pbrt's ellipse at the level of ``view``, in its texel coordinates, and its bounding
        box."""
        w, h = view.size
        s = texel_coord(st.x, w, mip.wrap, -0.5)
        t = texel_coord(st.y, h, mip.wrap, -0.5)
        ds0, dt0 = dst0.x * w, dst0.y * h
        ds1, dt1 = dst1.x * w, dst1.y * h

        A = dt0 * dt0 + dt1 * dt1 + 1
        B = -2 * (ds0 * dt0 + ds1 * dt1)
        C = ds0 * ds0 + ds1 * ds1 + 1
        inv_f = dr.rcp(A * C - B * B * 0.25)
        A, B, C = A * inv_f, B * inv_f, C * inv_f

        det = -B * B + 4 * A * C
        inv_det = dr.rcp(det)
        # pbrt's 2·sqrt(det·C)/det as 2·sqrt(C/det): the same number, but det·C underflows to 0
        # for footprints of ~1e8 texels (a 1×1 image), which emptied the ellipse
        u_ext = 2 * dr.safe_sqrt(C * inv_det)
        v_ext = 2 * dr.safe_sqrt(A * inv_det)
        # Bounded extents: a non-finite footprint (huge derivatives at a coarse level) cannot
        # produce an endless loop; such lanes are at the coarsest level where 1 texel suffices.
        # The bound is above every finite footprint's extent, so it never cuts an ellipse: after
        # the anisotropy clamp and the level choice the axes are at most 2 and
        # 2·maxanisotropy texels long, the half-width at most their length + 1 (a bound of twice
        # the image size would cut the ellipses of images a few texels wide, where the level
        # cannot grow with the footprint).
        limit = 2.0 * max(mip.width, mip.height, 4.0 * self.max_anisotropy) + 2
        u_ext = dr.minimum(_finite(u_ext), limit)
        v_ext = dr.minimum(_finite(v_ext), limit)
        return _Ellipse(s, t, A, B, C, dr.ceil(s - u_ext), dr.floor(s + u_ext),
                        dr.ceil(t - v_ext), dr.floor(t + v_ext))


@dataclass
class _Ellipse:
    """pbrt's EWA ellipse ``A·ds² + B·ds·dt + C·dt² < 1`` around ``(s, t)`` (texel coordinates of
    one level) and its bounding box ``[s0, s1] × [t0, t1]``."""
    s: object
    t: object
    A: object
    B: object
    C: object
    s0: object
    s1: object
    t0: object
    t1: object


def _ellipse_sum(mip, view, e: _Ellipse, run, buffer=None):
    """(Σ weight·texel, Σ weight) over the texels inside each lane's ellipse, row by row: each
    row's column span from the roots of the quadratic, ``COLUMNS_PER_STEP`` columns a step;
    texels read from ``buffer`` (None: the pyramid's)."""
    w, h = view.size
    inv_2a = 0.5 * dr.rcp(e.A)
    separable = mip.wrap != 'octahedralsphere'

    def start_row(it):
        """Column span of row ``it`` (roots of the quadratic) and its wrapped row."""
        tt = it - e.t
        disc = (e.B * tt) * (e.B * tt) - 4 * e.A * (e.C * tt * tt - 1)
        root = dr.safe_sqrt(disc)
        lo = dr.maximum(e.s0, dr.ceil(e.s + (-e.B * tt - root) * inv_2a - SPAN_SLACK))
        hi = dr.minimum(e.s1, dr.floor(e.s + (-e.B * tt + root) * inv_2a + SPAN_SLACK))
        hi = dr.select(disc >= 0, hi, lo - 1)
        if separable:
            _, wy, valid_y = wrap_2d(mi.Float(0), it, w, h, mip.wrap, *view.inv_size)
            return lo, hi, mi.Float(wy), valid_y
        return lo, hi, it, mi.Bool(True)

    def cond(it, i_s, s_end, row_y, row_ok, acc, acc_w):
        return run & (it <= e.t1)

    def body(it, i_s, s_end, row_y, row_ok, acc, acc_w):
        tt = it - e.t
        ctt = e.C * tt * tt
        btt = e.B * tt
        if separable:                       # the columns' wrapped indices, wrapping once
            cols = adjacent_wrapped(i_s, w, mip.wrap, view.inv_size[0])
        for k in range(COLUMNS_PER_STEP):
            col = i_s + k
            ss = col - e.s
            r2 = dr.fma(e.A * ss, ss, dr.fma(btt, ss, ctt))
            inside = (col <= s_end) & (r2 < R2_MAX) & run
            wgt = dr.select(inside, lut_weight(r2), 0)
            if separable:
                ix, valid = cols[k]
                texel = view.gather(row_y, ix, inside & row_ok & valid, buffer)
            else:
                texel = mip.fetch(view, col, it, inside, buffer)
            acc = dr.fma(texel, wgt * _ACC_SCALE, acc)
            acc_w = acc_w + wgt
        # advance: next columns, or the first column of the next row
        next_row = i_s + COLUMNS_PER_STEP > s_end
        it = dr.select(next_row, it + 1, it)
        lo, hi, ny, nok = start_row(it)
        i_s = dr.select(next_row, lo, i_s + COLUMNS_PER_STEP)
        s_end = dr.select(next_row, hi, s_end)
        row_y = dr.select(next_row, ny, row_y)
        row_ok = dr.select(next_row, nok, row_ok)
        return it, i_s, s_end, row_y, row_ok, acc, acc_w

    it = mi.Float(e.t0)
    i_s, s_end, row_y, row_ok = start_row(it)
    state = (it, i_s, s_end, row_y, row_ok, dr.zeros(mip.value_type()), mi.Float(0))
    *_, acc, acc_w = dr.while_loop(state, cond, body, max_iterations=-1, label='pbrt_ewa')
    return acc, acc_w


def _weight_polynomial(degree: int = 7) -> list[float]:
    """Coefficients (in ``u = i/63 - 1``) of a polynomial through pbrt's table
    ``exp(-α·i/127)``, i = 0 … 126, fitted for relative error: 3.6e-7 in float32 (the float32
    table itself is rounded by 1.4e-7). Evaluating it is ~3× cheaper than ``exp``."""
    i = np.arange(LUT_SIZE - 1, dtype=np.float64)
    want = np.exp(-ALPHA * i / (LUT_SIZE - 1))
    basis = np.vander(i / 63 - 1, degree + 1, increasing=True)
    coef = np.linalg.lstsq(basis / want[:, None], np.ones_like(i), rcond=None)[0]
    return [float(np.float32(c)) for c in coef]


_WEIGHT_POLY = _weight_polynomial()
#: Table entry 127 is 0 (``exp(-α) - exp(-α)``): texels with ``r2·128 ≥ 127`` weigh nothing.
R2_MAX = (LUT_SIZE - 1) / LUT_SIZE


def lut_weight(r2):
    """pbrt's table entry ``LUT[int(r2·128)]`` for ``0 ≤ r2 < R2_MAX`` (callers mask the rest),
    computed (polynomial in the entry's index) instead of gathered."""
    u = dr.fma(dr.floor(dr.maximum(r2, 0) * LUT_SIZE), 1 / 63, -1)
    value = mi.Float(_WEIGHT_POLY[-1])
    for coef in _WEIGHT_POLY[-2::-1]:
        value = dr.fma(value, u, coef)
    return value - _EXP_NEG_ALPHA
