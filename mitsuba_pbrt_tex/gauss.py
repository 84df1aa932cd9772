"""The film's Gaussian filter as a texture kernel around a pixel centre (``pbrt_path``
``footprint="pixel"`` with Mitsuba's ``gaussian`` film filter; :mod:`mitsuba_pbrt_tex.pixel`).

A Gaussian film gives pixel ``c`` the value ``∫ f(a) f(b) L(a, b) da db / ∫∫ f f``, ``(a, b)`` the
film offset from the pixel centre, ``f`` the filter (``rfilter.eval``: Mitsuba's windowed Gaussian,
standard deviation σ, zero beyond the radius 4σ). For a texture that enters the shading linearly the
pixel-centred lookup must return the same weighting of the texture,

    T_c = ∫∫ f(a) f(b) T(st(a, b)) da db / ∫∫ f(a) f(b) da db,

    st(a, b) = st_c + (a·D0 + b·D1) / (1 + a·g + b·h),

the projective map of the pixel's tangent plane (:mod:`mitsuba_pbrt_tex.pixel`: ``st_c`` the
centre ray's texture coordinates, ``D0``, ``D1`` the exact partials there, ``g``, ``h`` the
perspective terms). ``T`` is the bilinear reconstruction of the image (level 0), as Mitsuba's
``bitmap`` reads it.

How (per lane): a sum over a lattice in texture space, ``T_c ≈ Σ_t w_t v_t / Σ_t w_t``, with the
weight of each lattice point the filter at the film offset that maps to it — ``(a, b)`` from
inverting the projective map (a 2×2 solve), times the Jacobian ``(1 + a·g + b·h)³`` — so the
kernel is the filter's own, warped exactly by the perspective:

* The lattice has spacing ``2^l`` level-0 texels, ``l`` chosen per lane so that the kernel's
  smaller standard deviation spans :data:`LATTICE_SIGMA` (2) to twice that lattice units (the
  sum has about ``50·σ_min·σ_max`` terms in lattice units; with 1–2 units instead, 4× fewer,
  MIP-level lookups of white noise were off by up to 1.5e-2 instead of 2.4e-3). ``l ≥ 0``: the
  texels of MIP level ``l``; ``l < 0`` (magnification): points between the texels, each the
  bilinear value there (the bilinear surface *is* the bilinear interpolant of those points, so
  this stays exact however small the footprint — no minimum width as EWA's "+1 texel²").
* Second-moment corrections make the lattice sum match the integral of the *reconstruction*: the
  weight of a texel in ``∫ K·T`` is ``K`` convolved with the bilinear tent (variance 1/6 texel²
  per axis), and a MIP texel of level ``l ≥ 1`` is the mean of ``2^l × 2^l`` level-0 texels
  (variance ``(4^l - 1)/12`` level-0 texel²), which the weights undo. So the kernel's covariance
  is increased by ``(3·4^-l - 1)/12`` lattice units² (``1/6`` for ``l ≤ 0``), applied in the film
  plane through the footprint's Jacobian at the centre. What is left is of fourth order in
  (lattice spacing / σ) — and at ``l ≥ 1`` what any MIP filter loses: detail below the level's
  texel (measured against numpy integration: ≤ 5e-4 of the texel range on level 0 and finer
  lattices, ≤ 2.4e-3 on levels 1–2, white noise; ``tests/test_gaussian_pixel.py``).
* The support is the disc of the filter's radius (the separable filter's square corners, where
  ``f(a)·f(b) < 3.4e-4·f(0)²``, are left out).
* Kernels whose larger deviation exceeds :data:`MAX_SIGMA` lattice units go to a coarser lattice
  (bounded cost) and are widened there until the smaller deviation spans
  :data:`MIN_SIGMA_UNITS` lattice unit — blurred along the shorter axis, as EWA's anisotropy limit, rather than sampled
  by a few lattice points (which aliased: single pixels near the horizon of the bench's grazing
  plane returned a check's colour instead of its neighbourhood's mean); kernels wider than the
  whole image at its 1×1 level give the image mean.

The filter is separable in the film plane, ``f(a)·f(b)``, so a kernel sheared by the Jacobian is
evaluated as Mitsuba's film does — a product of two 1D filters — after the second-moment
correction (the covariance ``σ²I + ΔC`` as ``σ·C^{-1/2}`` applied to ``(a, b)``).
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from .wrap import sanitize_coord

#: Finest lattice: 2^MIN_LATTICE level-0 texels (footprints below it are points for the sum).
MIN_LATTICE = -4
#: A kernel's smaller standard deviation spans at least this many lattice units (where the
#: lattice can be fine enough).
LATTICE_SIGMA = 2.0
#: A kernel's smaller standard deviation spans at least this many lattice units where the
#: lattice is coarsened for its larger one (it is widened to it: one unit samples a Gaussian
#: well; fewer aliased).
MIN_SIGMA_UNITS = 1.0
#: A kernel's larger standard deviation spans at most this many lattice units.
MAX_SIGMA = 16.0
#: Loop extent bound in lattice units (non-finite or huge footprints cannot loop forever).
MAX_EXTENT = 4.0 * 4.0 * MAX_SIGMA + 8.0


def _sym_inv_sqrt(a, b, c):
    """``S^{-1/2}`` of the symmetric positive definite ``S = [[a, b], [b, c]]`` (closed form:
    ``sqrt(S) = (S + √det·I)/√(tr + 2√det)``), as (p, q, r) of ``[[p, q], [q, r]]``."""
    s = dr.safe_sqrt(a * c - b * b)
    t = dr.safe_sqrt(a + c + 2 * s)
    ra, rb, rc = (a + s) / t, b / t, (c + s) / t           # sqrt(S)
    det = ra * rc - rb * rb
    inv = dr.rcp(det)
    return rc * inv, -rb * inv, ra * inv


@dataclass(frozen=True)
class FilmKernel:
    """A film filter as :func:`pixel_filter` reads it (``FilterPixels`` has the same fields):
    its standard deviation and radius in pixels, and the filter itself (its ``eval``)."""
    stddev: float
    radius: float
    rfilter: object


@dataclass
class _Lattice:
    """One lane's lattice (see the module docstring): ``X``, ``Y`` the centre in lattice units;
    ``l00…l11`` the footprint Jacobian in lattice units; ``sx, sy, ox, oy`` the map st → lattice;
    ``fine`` (below level 0) and ``view`` (the level read otherwise); ``ma, mb, mc`` the
    second-moment correction ``σ·C^{-1/2}``; the row bounds (``t0``, ``t1``, ``shear``,
    ``width2``, ``rl``, ``bc``); ``run`` (lanes summed) and ``beyond`` (wider than the image)."""
    X: object
    Y: object
    l00: object
    l01: object
    l10: object
    l11: object
    sx: object
    sy: object
    ox: object
    oy: object
    fine: object
    view: object
    ma: object
    mb: object
    mc: object
    t0: object
    t1: object
    shear: object
    width2: object
    rl: object
    bc: object
    run: object
    beyond: object


def pixel_filter(mip, st, d0, d1, g, h, kernel, active):
    """``T_c`` above for each lane: ``st`` the centre's texture coordinates, ``d0``, ``d1``
    (Vector2f) the partials of st with respect to the film position (one pixel), ``g``, ``h``
    the perspective terms, ``kernel`` the film's filter (a :class:`FilmKernel`, or the render's
    ``FilterPixels``). Float (1 channel) or Color3f (RGB)."""
    active = mi.Bool(active)
    lat = _lattice(mip, st, d0, d1, g, h, kernel, active)
    acc, acc_w = _lattice_sum(mip, lat, g, h, kernel)
    result = acc / dr.select(acc_w > 0, acc_w, 1)
    summed = lat.run & (acc_w > 0)
    fallback = mip.bilinear(0, st, active & ~summed & ~lat.beyond)
    out = dr.select(summed, result, fallback)
    if len(mip.sizes) > 1:
        out = dr.select(lat.beyond, mip.coarsest(active & lat.beyond), out)
    return out


def _lattice(mip, st, d0, d1, g, h, kernel, active) -> _Lattice:
    """The lattice, its level and the kernel's shape on it, per lane."""
    W, H = float(mip.width), float(mip.height)
    sigma = float(kernel.stddev)
    R = float(kernel.radius) / sigma
    last = len(mip.sizes) - 1
    # ---- the lattice: spacing from the kernel's covariance in level-0 texels -----------------
    j00, j01 = d0.x * W, d1.x * W
    j10, j11 = d0.y * H, d1.y * H
    ca = sigma * sigma * (j00 * j00 + j01 * j01)
    cb = sigma * sigma * (j00 * j10 + j01 * j11)
    cc = sigma * sigma * (j10 * j10 + j11 * j11)
    half = 0.5 * (ca + cc)
    disc = dr.safe_sqrt(0.25 * (ca - cc) * (ca - cc) + cb * cb)
    sig_min = dr.safe_sqrt(half - disc)
    sig_max = dr.safe_sqrt(half + disc)
    ok = active & dr.isfinite(sig_max) & (sig_min > 0) & dr.isfinite(g) & dr.isfinite(h)
    sig_min = dr.select(ok, sig_min, 1.0)
    sig_max = dr.select(ok, sig_max, 1.0)
    by_min = dr.floor(dr.log2(sig_min * (1.0 / LATTICE_SIGMA)))
    by_max = dr.ceil(dr.log2(sig_max * (1.0 / MAX_SIGMA)))
    lat = dr.clip(dr.maximum(by_min, by_max), MIN_LATTICE, last)
    fine = lat < 0
    spacing = dr.exp2(lat)                                  # level-0 texels per lattice unit
    view = mip.view(mi.UInt32(dr.maximum(lat, 0))) if last > 0 else mip.view(0)
    lw, lh = view.size
    # lattice coordinates: X = st·scale - offset; lattice points at integers
    sx = dr.select(fine, W / spacing, lw)
    sy = dr.select(fine, H / spacing, lh)
    ox = dr.select(fine, 0.5 / spacing, 0.5)
    oy = ox
    X = sanitize_coord(st.x * sx - ox)
    Y = sanitize_coord(st.y * sy - oy)
    # footprint Jacobian in lattice units
    l00, l01 = d0.x * sx, d1.x * sx
    l10, l11 = d0.y * sy, d1.y * sy
    # ---- second-moment correction (lattice units²), in the film plane: σ²I + δ·J⁻¹J⁻ᵀ ----------
    delta = dr.select(lat <= 0, 1.0 / 6.0, (3 * dr.exp2(-2 * lat) - 1) * (1.0 / 12.0))
    # a lattice coarsened for the larger deviation (MAX_SIGMA) may sample the smaller one with
    # under one unit — a few points on a line, aliasing: widen it to one unit (a blur along the
    # shorter axis, as EWA's anisotropy limit)
    sig_min_lat = sig_min / spacing
    widen = (by_max > by_min) & (lat > MIN_LATTICE)
    delta = delta + dr.select(widen, dr.maximum(MIN_SIGMA_UNITS ** 2 - sig_min_lat * sig_min_lat,
                                                0), 0)
    ma, mb, mc = _corrected_shape(l00, l01, l10, l11, sigma, delta)
    # ---- loop bounds: the kernel's ellipse in lattice units, widened for the perspective -----
    ba = sigma * sigma * (l00 * l00 + l01 * l01) + dr.maximum(delta, 0)
    bb = sigma * sigma * (l00 * l10 + l01 * l11)
    bc = sigma * sigma * (l10 * l10 + l11 * l11) + dr.maximum(delta, 0)
    # a film offset within the radius maps at most 1/(1 - radius·(|g| + |h|)) times as far
    rl = R / dr.maximum(1 - float(kernel.radius) * (dr.abs(g) + dr.abs(h)), 0.25) + 0.01
    det_b = ba * bc - bb * bb
    ey = dr.minimum(rl * dr.safe_sqrt(bc), MAX_EXTENT)
    beyond = ok & (lat >= last) & (sig_min * dr.exp2(-lat) > 4)      # wider than the image
    run = ok & ~beyond & (det_b > 0) & dr.isfinite(ey)
    return _Lattice(X, Y, l00, l01, l10, l11, sx, sy, ox, oy, fine, view, ma, mb, mc,
                    dr.ceil(Y - ey), dr.floor(Y + ey), dr.select(run, bb / bc, 0.0),
                    dr.select(run, det_b / bc, 0.0), rl, bc, run, beyond)


def _corrected_shape(l00, l01, l10, l11, sigma, delta):
    """``σ·C^{-1/2}`` (as ``ma, mb, mc`` of a symmetric matrix) for the film-plane covariance
    ``C = σ²I + δ·J⁻¹J⁻ᵀ`` (J the footprint Jacobian in lattice units); the identity where it
    is not finite."""
    inv_det = dr.rcp(l00 * l11 - l01 * l10)
    i00, i01 = l11 * inv_det, -l01 * inv_det
    i10, i11 = -l10 * inv_det, l00 * inv_det
    pa = sigma * sigma + delta * (i00 * i00 + i01 * i01)
    pb = delta * (i00 * i10 + i01 * i11)
    pc = sigma * sigma + delta * (i10 * i10 + i11 * i11)
    ma, mb, mc = _sym_inv_sqrt(pa, pb, pc)
    ma, mb, mc = ma * sigma, mb * sigma, mc * sigma
    good = dr.isfinite(ma) & dr.isfinite(mb) & dr.isfinite(mc) & (pa * pc - pb * pb > 0)
    return dr.select(good, ma, 1.0), dr.select(good, mb, 0.0), dr.select(good, mc, 1.0)


def _lattice_sum(mip, lat: _Lattice, g, h, kernel):
    """(Σ w·v, Σ w) over the lattice points inside each lane's kernel, row by row."""
    radius, rfilter = float(kernel.radius), kernel.rfilter
    T = mip.value_type()

    def span(t):
        dy = t - lat.Y
        rem = lat.rl * lat.rl - dy * dy / lat.bc
        hw = dr.minimum(dr.safe_sqrt(rem * lat.width2), MAX_EXTENT)
        mid = lat.X + lat.shear * dy
        lo = dr.ceil(mid - hw)
        hi = dr.select(rem >= 0, dr.floor(mid + hw), lo - 1)
        return lo, hi

    def weight(i, t, inside):
        """The filter at the film offset (a, b) whose projective image is lattice point (i, t),
        times the Jacobian ``(1 + a·g + b·h)³``."""
        dx, dy = i - lat.X, t - lat.Y
        m00, m01 = lat.l00 - g * dx, lat.l01 - h * dx
        m10, m11 = lat.l10 - g * dy, lat.l11 - h * dy
        inv = dr.rcp(m00 * m11 - m01 * m10)
        a = (dx * m11 - m01 * dy) * inv
        b = (m00 * dy - m10 * dx) * inv
        den = 1 + a * g + b * h
        aa = lat.ma * a + lat.mb * b
        bb = lat.mb * a + lat.mc * b
        use = inside & (den > 0) & (dr.abs(aa) < radius) & (dr.abs(bb) < radius) \
            & dr.isfinite(aa) & dr.isfinite(bb)
        w = rfilter.eval(dr.select(use, aa, 0), use) * rfilter.eval(dr.select(use, bb, 0), use)
        return dr.select(use, dr.maximum(w, 0) * den * den * den, 0), use

    def cond(t, i, i_end, acc, acc_w):
        return lat.run & (t <= lat.t1)

    def body(t, i, i_end, acc, acc_w):
        w, use = weight(i, t, lat.run & (i <= i_end))
        v_fine = mip.bilinear(0, mi.Point2f((i + lat.ox) / lat.sx, (t + lat.oy) / lat.sy),
                              use & lat.fine)
        v_level = mip.fetch(lat.view, i, t, use & ~lat.fine)
        acc = dr.fma(dr.select(lat.fine, v_fine, v_level), w, acc)
        acc_w = acc_w + w
        next_row = i + 1 > i_end
        t = dr.select(next_row, t + 1, t)
        lo, hi = span(t)
        i = dr.select(next_row, lo, i + 1)
        i_end = dr.select(next_row, hi, i_end)
        return t, i, i_end, acc, acc_w

    i0, i1 = span(lat.t0)
    state = (mi.Float(lat.t0), mi.Float(i0), mi.Float(i1), dr.zeros(T), mi.Float(0))
    *_, acc, acc_w = dr.while_loop(state, cond, body, max_iterations=-1,
                                   label='pbrt_gaussian_pixel')
    return acc, acc_w
