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
inverting the projective map, times the Jacobian ``(1 + a·g + b·h)³`` — so the
kernel is the filter's own, warped exactly by the perspective:

* The lattice has spacing ``2^l`` level-0 texels, ``l`` chosen per lane from the kernel's
  smaller standard deviation: the coarsest lattice on which it spans at least
  :data:`LATTICE_SIGMA` (1) unit while that is level 0 or finer, else the coarsest on which it
  spans :data:`MIP_LATTICE_SIGMA` (2) units (so level 0 takes deviations of 1 to 4 texels; the
  sum has about ``50·σ_min·σ_max`` terms in lattice units). ``l ≥ 0``: the texels of MIP
  level ``l``; ``l < 0`` (magnification): points between the texels, each the bilinear value
  there (the bilinear surface *is* the bilinear interpolant of those points, so this stays
  exact however small the footprint — no minimum width as EWA's "+1 texel²"). One unit is
  where the corrections below still make a sampled kernel sum to its integral; a MIP texel is
  a box mean, whose lost detail grows with its size against the kernel's, so MIP levels get
  the finer two (one unit there: up to 1.5e-2 off on white noise).
* Second-moment corrections make the lattice sum match the integral of the *reconstruction*: the
  weight of a texel in ``∫ K·T`` is ``K`` convolved with the bilinear tent (variance 1/6 texel²
  per axis), and a MIP texel of level ``l ≥ 1`` is the mean of ``2^l × 2^l`` level-0 texels
  (variance ``(4^l - 1)/12`` level-0 texel²), which the weights undo. So the kernel's covariance
  is increased by ``(3·4^-l - 1)/12`` lattice units² (``1/6`` for ``l ≤ 0``), applied in the film
  plane through the footprint's Jacobian at the centre. On level 0 and finer lattices the
  bilinear tent's fourth cumulant (-1/60 per axis, which a Gaussian widening lacks) is added
  as its Edgeworth term on the weights. What is left is of higher order in (lattice spacing /
  σ), and the perspective's change of the Jacobian across the support — and at ``l ≥ 1`` what
  any MIP filter loses: detail below the level's texel (measured against numpy integration,
  white noise: ≤ 1.4e-3 of the texel range on level 0 and finer lattices, ≤ 2.4e-3 on levels
  1–2; ``tests/test_gaussian_pixel.py``).
* The support is the disc of the filter's radius (the separable filter's square corners, where
  ``f(a)·f(b) < 3.4e-4·f(0)²``, are left out). Its projective image in the lattice is a conic,
  an ellipse while the disc stays off the horizon: each row of the sum spans exactly the
  lattice points inside it (a quadratic per row), and each point's film offset comes from the
  inverse projective map, itself projective (a division per point).
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

from .wrap import texel_coord

#: Finest lattice: 2^MIN_LATTICE level-0 texels (footprints below it are points for the sum).
MIN_LATTICE = -4
#: A kernel's smaller standard deviation spans at least this many lattice units (where the
#: lattice can be fine enough).
LATTICE_SIGMA = 1.0
#: ... and at least this many where that lattice would be a MIP level (1 or coarser).
MIP_LATTICE_SIGMA = 2.0
#: A kernel's smaller standard deviation spans at least this many lattice units where the
#: lattice is coarsened for its larger one (it is widened to it: one unit samples a Gaussian
#: well; fewer aliased).
MIN_SIGMA_UNITS = 1.0
#: A kernel's larger standard deviation spans at most this many lattice units.
MAX_SIGMA = 32.0
#: The loop's support is the filter's disc widened by this factor in radius² (float32 rounding
#: of its bound; the filter is zero at its radius).
_SPAN_MARGIN = 1.002
#: Where the disc's projective image would reach the horizon, its bound is that of a weaker
#: perspective reaching this fraction of the way (ρ²·kᵀ(NᵀN)⁻¹k).
_MAX_REACH = 0.75
#: Texels are summed scaled by 2^-20 and the normalised sum scaled back (powers of two: the
#: same result bit for bit above ~1e-30), so that sums of thousands of points with the
#: perspective's Jacobian on texels near ±1e38 stay finite instead of overflowing to inf.
_ACC_SCALE = 2.0 ** -20
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
    ``i00…i11`` the inverse of the footprint Jacobian in lattice units and ``n00…n11`` the same
    followed by the second-moment correction ``σ·C^{-1/2}`` (lattice offset → film offset, and
    → corrected film offset, before the perspective division); ``sx, sy, ox, oy`` the map st →
    lattice; ``fine`` (below level 0) and ``view`` (the level read otherwise); the row bounds
    (``t0``, ``t1``) and the support's conic (``qa, qb, qc``, ``p0, p1``, ``r2``: see
    :func:`_support_conic`); the precision matrix ``pxx, pxy, pyy`` and the coefficient
    ``kurt`` of the fourth-cumulant term (:func:`_fourth_cumulant`); ``run`` (lanes summed) and
    ``beyond`` (wider than the image)."""
    X: object
    Y: object
    i00: object
    i01: object
    i10: object
    i11: object
    n00: object
    n01: object
    n10: object
    n11: object
    sx: object
    sy: object
    ox: object
    oy: object
    fine: object
    view: object
    t0: object
    t1: object
    qa: object
    qb: object
    qc: object
    p0: object
    p1: object
    r2: object
    pxx: object
    pxy: object
    pyy: object
    kurt: object
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
    result = acc / dr.select(acc_w > 0, acc_w, 1) * (1 / _ACC_SCALE)
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
    by_min = dr.select(by_min > 0, dr.floor(dr.log2(sig_min * (1.0 / MIP_LATTICE_SIGMA))), by_min)
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
    X = texel_coord(st.x, sx, mip.wrap, -ox)
    Y = texel_coord(st.y, sy, mip.wrap, -oy)
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
    inv_det = dr.rcp(l00 * l11 - l01 * l10)
    i00, i01, i10, i11 = l11 * inv_det, -l01 * inv_det, -l10 * inv_det, l00 * inv_det
    ma, mb, mc = _corrected_shape(i00, i01, i10, i11, sigma, delta)
    n00, n01 = ma * i00 + mb * i10, ma * i01 + mb * i11
    n10, n11 = mb * i00 + mc * i10, mb * i01 + mc * i11
    pxx, pxy, pyy, kurt = _fourth_cumulant(l00, l01, l10, l11, sigma, delta, lat)
    # ---- loop bounds: the support's projective image, a conic ---------------------------------
    qa, qb, qc, p0, p1, ey, y0 = _support_conic(n00, n01, n10, n11, g * i00 + h * i10,
                                                g * i01 + h * i11, float(kernel.radius))
    ey = dr.minimum(ey, MAX_EXTENT)
    beyond = ok & (lat >= last) & (sig_min * dr.exp2(-lat) > 4)      # wider than the image
    run = ok & ~beyond & (qa > 0) & dr.isfinite(ey + y0) & dr.isfinite(n00 + n01 + n10 + n11)
    return _Lattice(X, Y, i00, i01, i10, i11, n00, n01, n10, n11, sx, sy, ox, oy, fine, view,
                    dr.ceil(Y + y0 - ey), dr.floor(Y + y0 + ey), qa, qb, qc, p0, p1,
                    float(kernel.radius) ** 2 * _SPAN_MARGIN, pxx, pxy, pyy, kurt, run, beyond)


def _support_conic(n00, n01, n10, n11, k0, k1, radius):
    """The lattice offsets ``d`` whose corrected film offset ``N·d / (1 - k·d)`` lies in the disc
    of the filter's radius ρ: ``|N·d|² ≤ ρ²·(1 - k·d)²``, the conic ``dᵀQd + 2p·d - ρ² ≤ 0`` with
    ``Q = NᵀN - ρ²·kkᵀ``, ``p = ρ²·k`` — an ellipse while the disc's image stays off the
    horizon (``ρ²·kᵀ(NᵀN)⁻¹k < 1``). Closer to it (where the disc would reach the horizon) the
    perspective term of the bound is scaled down to keep the ellipse bounded (the support's far
    tail is cut there, as any bound must). Returns ``Q`` (``qa, qb, qc``), ``p`` and the
    ellipse's vertical half extent and centre offset."""
    ga = n00 * n00 + n10 * n10
    gb = n00 * n01 + n10 * n11
    gc = n01 * n01 + n11 * n11
    r2 = radius * radius * _SPAN_MARGIN
    reach = r2 * (gc * k0 * k0 - 2 * gb * k0 * k1 + ga * k1 * k1) / (ga * gc - gb * gb)
    scale = dr.sqrt(dr.minimum(1.0, _MAX_REACH / dr.maximum(reach, 1e-30)))
    k0, k1 = k0 * scale, k1 * scale
    qa, qb, qc = ga - r2 * k0 * k0, gb - r2 * k0 * k1, gc - r2 * k1 * k1
    p0, p1 = r2 * k0, r2 * k1
    det = qa * qc - qb * qb
    # centre -Q⁻¹p, and (d - centre)ᵀQ(d - centre) ≤ ρ² + pᵀQ⁻¹p
    y0 = (qb * p0 - qa * p1) / det
    level = r2 + (qc * p0 * p0 - 2 * qb * p0 * p1 + qa * p1 * p1) / det
    ey = dr.safe_sqrt(level * qa / det)
    return qa, qb, qc, p0, p1, ey, y0


def _fourth_cumulant(l00, l01, l10, l11, sigma, delta, lat):
    """The kernel's precision matrix ``P = B⁻¹`` in lattice units (``B = σ²·JJᵀ + δ·I``, the
    corrected covariance at the centre) and the coefficient of the fourth-order term a lattice
    at or below level 0 leaves: the bilinear tent's fourth cumulant, -1/60 per axis, which the
    Gaussian widening does not have. Its weight is ``1 + κ/24·(He₄(x) + He₄(y))`` with the
    Hermite terms of ``P`` (the Edgeworth term of ``K ⊛ tent``); at MIP levels the sum's
    error is the level's lost detail instead, and the term is 0."""
    ba = sigma * sigma * (l00 * l00 + l01 * l01) + delta
    bb = sigma * sigma * (l00 * l10 + l01 * l11)
    bc = sigma * sigma * (l10 * l10 + l11 * l11) + delta
    inv_b = dr.rcp(ba * bc - bb * bb)
    kurt = dr.select(lat <= 0, -1.0 / (60.0 * 24.0), 0.0)
    return bc * inv_b, -bb * inv_b, ba * inv_b, kurt


def _corrected_shape(i00, i01, i10, i11, sigma, delta):
    """``σ·C^{-1/2}`` (as ``ma, mb, mc`` of a symmetric matrix) for the film-plane covariance
    ``C = σ²I + δ·J⁻¹J⁻ᵀ`` (``i00…i11``: J⁻¹, J the footprint Jacobian in lattice units); the
    identity where it is not finite."""
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
        """The row's lattice points inside the support's conic (``A·dx² + B·dx + C ≤ 0``)."""
        dy = t - lat.Y
        b = lat.qb * dy + lat.p0                                # B / 2
        c = (lat.qc * dy + 2 * lat.p1) * dy - lat.r2
        rem = b * b - lat.qa * c
        inv = dr.rcp(lat.qa)
        hw = dr.minimum(dr.safe_sqrt(rem) * inv, MAX_EXTENT)
        mid = lat.X - b * inv
        lo = dr.ceil(mid - hw)
        hi = dr.select(rem >= 0, dr.floor(mid + hw), lo - 1)
        return lo, hi

    def weight(i, t, inside):
        """The filter at the film offset (a, b) whose projective image is lattice point (i, t),
        times the Jacobian ``(1 + a·g + b·h)³``. The projective map ``d = J·(a, b) / (1 + a·g +
        b·h)`` inverts to ``(a, b) = u / q``, ``u = J⁻¹·d``, ``q = 1 - g·u₀ - h·u₁`` (Sherman–
        Morrison), and ``1 + a·g + b·h = 1/q``: a division per point, no 2×2 solve."""
        dx, dy = i - lat.X, t - lat.Y
        q = 1 - g * (lat.i00 * dx + lat.i01 * dy) - h * (lat.i10 * dx + lat.i11 * dy)
        den = dr.rcp(q)
        aa = (lat.n00 * dx + lat.n01 * dy) * den
        bb = (lat.n10 * dx + lat.n11 * dy) * den
        use = inside & (q > 0) & (dr.abs(aa) < radius) & (dr.abs(bb) < radius)
        w = rfilter.eval(dr.select(use, aa, 0), use) * rfilter.eval(dr.select(use, bb, 0), use)
        ux = lat.pxx * dx + lat.pxy * dy
        uy = lat.pxy * dx + lat.pyy * dy
        ux2, uy2 = ux * ux, uy * uy
        he4 = (ux2 - 6 * lat.pxx) * ux2 + 3 * lat.pxx * lat.pxx \
            + (uy2 - 6 * lat.pyy) * uy2 + 3 * lat.pyy * lat.pyy
        w = w * (1 + lat.kurt * he4)
        return dr.select(use, dr.maximum(w, 0) * den * den * den, 0), use

    def cond(t, i, i_end, acc, acc_w):
        return lat.run & (t <= lat.t1)

    def body(t, i, i_end, acc, acc_w):
        w, use = weight(i, t, lat.run & (i <= i_end))
        v = dr.if_stmt(
            (i, t, use), lat.fine,
            lambda i, t, use: mip.bilinear(
                0, mi.Point2f((i + lat.ox) / lat.sx, (t + lat.oy) / lat.sy), use),
            lambda i, t, use: mip.fetch(lat.view, i, t, use), label='pbrt_gaussian_read')
        acc = dr.fma(v, w * _ACC_SCALE, acc)
        acc_w = acc_w + w
        next_row = i + 1 > i_end
        t = dr.select(next_row, t + 1, t)
        i, i_end = dr.if_stmt((t, i, i_end), next_row, lambda t, i, i_end: span(t),
                              lambda t, i, i_end: (i + 1, i_end), label='pbrt_gaussian_row')
        return t, i, i_end, acc, acc_w

    i0, i1 = span(lat.t0)
    state = (mi.Float(lat.t0), mi.Float(i0), mi.Float(i1), dr.zeros(T), mi.Float(0))
    *_, acc, acc_w = dr.while_loop(state, cond, body, max_iterations=-1,
                                   label='pbrt_gaussian_pixel')
    return acc, acc_w
