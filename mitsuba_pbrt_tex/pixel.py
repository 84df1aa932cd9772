"""Pixel-centred texture footprints for camera hits (``pbrt_path`` ``footprint="pixel"``).

With a box pixel filter every camera sample counts only in its own pixel, so a texture that
enters the shading linearly (albedo, emission) may be looked up *for the pixel* rather than for
the sample: the average of the texture over the pixel's footprint is then what the pixel
converges to, and every sample of the pixel sees it (a 1-spp image is already converged there).

The pixel's footprint on the hit's tangent plane, under a pinhole camera, is exactly

    p(a, b) = p_c + (a·P0 + b·P1) / (1 + a·g + b·h),   a, b ∈ [-1/2, 1/2]

with ``p_c`` the pixel-centre ray's hit, ``P0``, ``P1`` the derivatives of the hit with respect
to the film position (one pixel) at the centre, and ``1 + g = q(d_x)/q(d_c)``, ``1 + h =
q(d_y)/q(d_c)``, ``q(d) = (n·d)/(f·d)``, ``f`` the camera's forward axis, ``d_c``, ``d_x``,
``d_y`` the directions of the centre ray and of its one-pixel neighbours. The sensor's forward
differences reach only ``P0/(1+g)``: they are scaled by ``(1+g)``, ``(1+h)``. The uv partials
follow by pbrt-v4's least squares, as everywhere else.

A texture filters a parallelogram (``pbrt_imagemap`` ``box``): it gets the one with edges ``P0``,
``P1`` (in uv: ``D0``, ``D1``) centred on the *screen-weighted centroid* of the pixel's footprint,
``p_c - (g·P0 + h·P1)/12`` (the exact mean of ``p(a, b)`` up to fourth order in ``g``, ``h``), so
its average is right for every texture that is linear across the pixel and the remaining
difference is of second order in the perspective change across one pixel.

How a texture learns the pixel (the path from ``pbrt_path`` to the textures that opt in): a
texture sees only the ``SurfaceInteraction3f`` the BSDF passes on, and a per-lane value from the
integrator cannot reach it otherwise (a symbolic BSDF call admits no per-lane inputs but its
arguments). So nothing per lane is passed: while ``pbrt_path`` traces (or, in wavefront mode,
runs) its ``sample()`` with ``footprint="pixel"``, it *publishes* the sensor on this thread
(:func:`published`). A texture that opts in builds its context with :func:`context` instead of
``TextureEvalContext.from_si``; that reconstructs everything from the hit itself:

* a camera hit is a hit whose ray started at the camera: ``si.p + si.t·wi`` is where the
  direction ``-wi`` from the sensor's position meets its near clipping plane (within 1e-4 of the
  distance; secondary rays do not start there);
* its pixel is where the sensor projects ``si.p`` (``Sensor.sample_direction``), the centre ray is
  the sensor's ray through that pixel's centre (``Sensor.sample_ray_differential``), and the rest
  is the tangent-plane geometry of ``si`` (``p``, ``n``, ``dp_du``, ``dp_dv``).

No field of ``si`` is changed or reused, so it works the same inside Mitsuba's symbolic loop,
inside the BSDF's symbolic call and in wavefront mode. Lanes where it cannot hold — not a camera
hit, no publication (Mitsuba's own integrators, a direct ``tex.eval(si)``), a plane missed by
the centre ray, ``|g|`` or ``|h|`` ≥ 1 (the pixel sees the plane's horizon), non-finite values —
use the sample-centred context.

Gaussian film filter (Mitsuba's default). A Gaussian film gives a pixel the filter-weighted
average of the samples within its radius (2 pixels), and Mitsuba's ``ImageBlock`` splats every
sample into all of those pixels — so a texture value centred on one pixel would be blurred a
second time, and the pixel a hit "belongs to" is not even defined. ``pbrt_path`` therefore
changes how samples are *placed*, not what reaches a texture (still only ``si``):

* each pixel's film positions are drawn from the filter itself (``rfilter.eval``, tabulated;
  separable), and every sample counts with weight 1 in that pixel alone: Mitsuba's ``render``,
  ``render_forward`` and ``render_backward`` run unchanged, given a sensor view whose film
  makes image blocks without the filter (``pbrt_path`` ``pixel_view``; the converged image is
  the Gaussian-filtered one; border pixels estimate the whole filter, as with
  ``sample_border``);
* the pixel is recoverable from the position (:class:`FilterPixels`): in one render all
  pixels share their samples' offsets — sample ``s`` of every pixel lies at the same offset
  ``v_s`` from its pixel's centre, drawn from the filter per render (the position in the pixel
  stratified over the samples and shifted by one random vector, the integer displacement drawn
  given it) — so ``frac(x)`` names the sample ``s`` (with a margin of half a stratum, ≥ 1/64
  pixel up to 1024 spp, against the rounding of a hit projected back to the film: up to 3e-3
  pixel on the bench's 400-unit plane, far more than the ~1e-5 of the box case) and
  ``round(x - 1/2 - v_s)`` the pixel. The texture decodes it from the projected hit, and
  ``pbrt_path`` decodes it the same way (same function, same inputs) at the first hit and
  counts the sample there, so the pixel a texture centred on and the pixel the sample counts in
  are always the same. (The pixel cannot be encoded in the positions' sub-pixel bits instead:
  that needs margins of ~1e-2 pixel on such scenes, or a quarter of the samples decode to a
  neighbour and a fifth of the pixels of a 1-spp image stay empty.) The price: at low
  spp every pixel samples the same offsets, so silhouettes alias rather than being noisy;
* the texture filters the film filter's own kernel around the pixel centre
  (:func:`filter_context`, :func:`mitsuba_pbrt_tex.gauss.pixel_filter`): ``f(a)·f(b)`` over film
  offsets ``(a, b)``, warped by the projective map of the tangent plane — valid where the
  perspective terms satisfy ``(|g| + |h|)·radius < 1/2`` (else the sample's footprint, as for
  any lane where the pixel footprint cannot hold).

Limits: ``perspective`` sensors (a pinhole: the aperture sample plays no role), box or Gaussian
film filter (``pbrt_path`` refuses the others; ``silhouette_spp`` needs the box). A sample within
~1e-5 pixel of a pixel edge can be assigned to the neighbouring pixel by float32 rounding of its
hit point (box filter; the Gaussian path counts it where the texture centred).
"""

from __future__ import annotations

import contextlib
import math
import threading

import drjit as dr
import mitsuba as mi

from .differentials import TextureEvalContext
from .raydiff import uv_partials

_STATE = threading.local()
#: A ray starts at the camera when its origin is within this fraction of the hit distance.
CAMERA_TOLERANCE = 1e-4


@contextlib.contextmanager
def published(sensor, pixels=None):
    """Within this block (on this thread), opting-in textures centre camera hits on the pixel
    of ``sensor``; ``pixels`` (a :class:`FilterPixels`) for a film filter other than the box:
    the pixel a sample counts in is encoded in its film position."""
    previous = getattr(_STATE, 'sensor', None), getattr(_STATE, 'pixels', None)
    _STATE.sensor, _STATE.pixels = sensor, pixels
    try:
        yield
    finally:
        _STATE.sensor, _STATE.pixels = previous


def current_sensor():
    return getattr(_STATE, 'sensor', None)


def current_pixels():
    """The published :class:`FilterPixels` (None with a box film filter or no publication)."""
    return getattr(_STATE, 'pixels', None) if current_sensor() is not None else None


class _Lattice:
    """The fractional position ``φ ∈ [0, 1)`` of a film offset ``v ~ f`` measured from the
    pixel's corner has the density ``G(φ) = Σ_m f(φ + m - 1/2)`` (the filter's lattice sum,
    within 1.5% of uniform for Mitsuba's Gaussian). Its CDF and the inverse, in closed form
    from the windowed Gaussian ``f(x) = exp(-x²/2σ²) - exp(-r²/2σ²)`` (the function Mitsuba's
    filter approximates to ~1e-7) — no table, so nothing created before a ``dr.freeze``
    recording is read."""

    def __init__(self, stddev: float, radius: float):
        self.sigma, self.radius = stddev, radius
        self.bias = math.exp(-radius * radius / (2 * stddev * stddev))
        self.reach = int(math.ceil(radius)) + 1
        z = sum(self._F_scalar(m + 0.5) - self._F_scalar(m - 0.5)
                for m in range(-self.reach, self.reach + 1))
        self.norm = 1.0 / z

    def _F_scalar(self, x):
        x = min(max(x, -self.radius), self.radius)
        s = self.sigma
        return s * math.sqrt(math.pi / 2) * math.erf(x / (s * math.sqrt(2))) - self.bias * x

    def _F(self, x):
        x = dr.clip(x, -self.radius, self.radius)
        s = self.sigma
        return s * math.sqrt(math.pi / 2) * dr.erf(x * (1 / (s * math.sqrt(2)))) - self.bias * x

    def _f(self, x):
        inside = dr.abs(x) < self.radius
        return dr.select(inside, dr.exp(x * x * (-0.5 / self.sigma ** 2)) - self.bias, 0)

    def cdf(self, phi):
        total = mi.Float(0)
        for m in range(-self.reach, self.reach + 1):
            total += self._F(phi + (m - 0.5)) - self._F_scalar(m - 0.5)
        return total * self.norm

    def density(self, phi):
        total = mi.Float(0)
        for m in range(-self.reach, self.reach + 1):
            total += self._f(phi + (m - 0.5))
        return total * self.norm

    def inverse(self, psi):
        phi = mi.Float(psi)
        for _ in range(4):              # Newton from the identity (G is within 1.5% of 1)
            phi = dr.clip(phi - (self.cdf(phi) - psi) / self.density(phi), 0, 1 - 2 ** -24)
        return phi


class FilterPixels:
    """Each sample of a (non-box) film filter in one pixel, and the pixel recoverable from the
    sample's film position alone (``pbrt_path`` ``footprint="pixel"`` with Mitsuba's
    ``gaussian`` film filter; see the module docstring).

    All pixels share, per render, the film offsets of their samples: sample ``s`` (of ``n``
    per pixel) of pixel ``c`` lies at ``c + φ_s + m_s`` (crop pixel coordinates, per axis;
    ``φ_s ∈ [0, 1)`` the position in the pixel, ``m_s`` an integer displacement), so the offset
    from the pixel centre is ``v_s = φ_s + m_s - 1/2``. Drawn per render:

    * ``φ_s``: the cells of an ``a × b`` grid (``a·b ≥ n``) in the *lattice-sum coordinate*
      ``ψ = G_cdf(φ)``, all shifted by one random ``ρ`` (mod 1): ``ψ_s = frac(ρ + (i + 1/2)/a)``,
      ``φ_s = G_cdf⁻¹(ψ_s)`` — each ``φ_s`` has density ``G(φ) = Σ_m f(φ + m - 1/2)``;
    * ``m_s`` with probability ``f(φ_s + m - 1/2)/G(φ_s)``,

    so each ``v_s`` has density ``f`` exactly (weight 1: every sample counts once in ``c``, and
    the pixel is an unbiased estimate of the filter-weighted average). From a film position
    ``x``, ``frac(x)`` gives ``ψ`` and the grid cell ``s`` — with a margin of half a cell
    (``1/(2a)`` in ψ, ≥ 1/64 pixel up to 1024 spp) against the rounding of a hit point
    projected back to the film (measured up to 3e-3 pixel on the bench's 400-unit plane) — and
    ``c = round(x - φ_s - m_s)``.

    Border pixels: their samples may lie outside the crop window, where the film's own weights
    (``sample_border`` false) would not look — they estimate the whole filter, as with
    ``sample_border`` true.
    """

    def __init__(self, film, seed=0):
        rfilter = film.rfilter()
        self.rfilter = rfilter
        self.radius = float(rfilter.radius())
        self.stddev = self.radius / 4.0          # Mitsuba's gaussian: radius = 4 stddev
        size = film.crop_size()
        self.size = (int(size[0]), int(size[1]))
        self.offset = mi.ScalarVector2f(film.crop_offset())
        self.lattice = _Lattice(self.stddev, self.radius)
        # the render's seed (an int, or a UInt32 under dr.freeze): opaque, one kernel for all
        self.seed = seed if isinstance(seed, mi.UInt32) else dr.opaque(mi.UInt32, int(seed))
        self.n = None

    def draw(self, n: int):
        """This render's offsets for ``n`` samples per pixel, drawn on the device from the
        seed (``mi.sample_tea_float32``; no host round trip, so ``dr.freeze`` records it), and
        made opaque: symbolic calls read them, and kernels are reused across renders. The
        tables hold ``n + 1`` entries: a gather from a 1-entry array would be turned into its
        value, a literal (a new kernel for every value drawn)."""
        t = self.lattice
        self.n = n = int(n)
        self.a = a = int(math.ceil(math.sqrt(n)))
        self.b = int(math.ceil(n / a))
        seed = self.seed
        k = dr.arange(mi.UInt32, n + 1)
        s = dr.select(k < n, k, 0)
        rho = mi.Point2f(mi.sample_tea_float32(seed, mi.UInt32(0xfffffff0), 4),
                         mi.sample_tea_float32(seed, mi.UInt32(0xfffffff1), 4))
        cells = (mi.Point2f(mi.Float(s % a), mi.Float(s // a)) + 0.5) \
            / mi.ScalarPoint2f(a, self.b)
        psi = dr.gather(mi.Point2f, rho, mi.UInt32(0)) + cells
        psi = psi - dr.floor(psi)
        phi, m = [], []
        for axis in range(2):
            p = t.inverse(psi[axis])
            # m with probability f(φ + m - 1/2) / G(φ)
            js = list(range(-t.reach, t.reach + 1))
            weights = [dr.maximum(self.rfilter.eval(p + (j - 0.5)), 0) for j in js]
            total = weights[0]
            for w in weights[1:]:
                total = total + w
            u = mi.sample_tea_float32(seed, k * 2 + axis, 4) * total
            pick, cum, done = mi.Float(js[-1]), mi.Float(0), mi.Bool(False)
            for j, w in zip(js, weights):
                cum = cum + w
                take = ~done & (cum > u)
                pick = dr.select(take, j, pick)
                done |= take
            phi.append(p)
            m.append(pick)
        self.rho_jit = mi.Point2f(dr.gather(mi.Point2f, rho, mi.UInt32(0)))
        self.phi = mi.Point2f(phi[0], phi[1])
        self.m = mi.Point2f(m[0], m[1])
        dr.make_opaque(self.m, self.phi, self.rho_jit)

    def film_positions(self, pixel, index):
        """Film positions (crop pixel coordinates) of sample ``index`` (UInt32) of ``pixel``
        (crop coordinates, float-valued integers)."""
        phi = dr.gather(mi.Point2f, self.phi, index)
        m = dr.gather(mi.Point2f, self.m, index)
        return mi.Point2f(pixel + phi + m)

    def decode(self, x):
        """(pixel, ok): the pixel (crop coordinates) whose sample lies at film position ``x``
        (Point2f); ``ok`` false where ``x`` lies in no sample's cell."""
        cell = []
        for axis, count in ((0, self.a), (1, self.b)):
            psi = self.lattice.cdf(x[axis] - dr.floor(x[axis]))
            rel = psi - self.rho_jit[axis]
            rel = rel - dr.floor(rel)
            cell.append(dr.minimum(dr.floor(rel * count), count - 1))
        index = cell[1] * self.a + cell[0]
        ok = dr.isfinite(index) & (index >= 0) & (index < self.n)
        i = mi.UInt32(dr.select(ok, index, 0))
        phi = dr.gather(mi.Point2f, self.phi, i, ok)
        m = dr.gather(mi.Point2f, self.m, i, ok)
        return dr.round(x - phi - m), ok

    def rays(self, sensor, ray, pos, n):
        """The camera rays of :meth:`film_positions` for the pixels of ``ADIntegrator.
        sample_rays``' rays (its ``pos``: full-film position of pixel + uniform offset, ``n``
        consecutive lanes per pixel; same time sample), with their weights and the pixel
        centres (full-film coordinates) to count them in."""
        self.draw(n)
        local = mi.Vector2f(pos) - self.offset
        pix = dr.floor(local)
        index = dr.arange(mi.UInt32, dr.width(pos)) % n
        x = self.film_positions(pix, index)
        crop = mi.ScalarVector2f(self.size)
        with dr.resume_grad():
            ray, weight = sensor.sample_ray_differential(
                time=ray.time, sample1=mi.Float(0.5), sample2=mi.Point2f(x / crop),
                sample3=mi.Point2f(0.5))
        return ray, weight, mi.Vector2f(pix + self.offset + 0.5)


class PixelFootprint:
    """The footprint of the pixel a camera hit belongs to (see the module docstring): ``uv_c``
    (the centre ray's uv), ``d0``, ``d1`` (uv derivatives with respect to the film position, one
    pixel), ``g``, ``h`` and the world-space ``p_c``, ``dp0``, ``dp1``; ``ok`` per lane."""

    def __init__(self, uv_c, d0, d1, g, h, p_c, dp0, dp1, ok):
        self.uv_c, self.d0, self.d1, self.g, self.h = uv_c, d0, d1, g, h
        self.p_c, self.dp0, self.dp1, self.ok = p_c, dp0, dp1, ok


def _film_position(sensor, si):
    """(camera hit?, the hit's film position in crop pixel coordinates) — the one computation
    both ``pbrt_path`` and the textures make, so that both find the same pixel."""
    p = mi.Point3f(si.p)
    to_world = sensor.world_transform()
    cam_o = mi.Point3f(to_world.translation())
    forward = dr.normalize(mi.Vector3f(to_world @ mi.Vector3f(0, 0, 1)))
    wi = si.to_world(si.wi)
    dist = dr.norm(p - cam_o)
    # a camera ray starts where its direction meets the near clipping plane
    origin = p + si.t * wi
    expected = cam_o - wi * (float(sensor.near_clip()) / dr.dot(forward, -wi))
    camera_hit = si.is_valid() & (dr.norm(origin - expected) <= CAMERA_TOLERANCE * dist)
    it = dr.zeros(mi.Interaction3f)
    it.p, it.time = p, si.time
    ds, _ = sensor.sample_direction(it, mi.Point2f(0.5), camera_hit)
    return camera_hit, mi.Point2f(ds.uv)


def _pixel_of(uv, pixels):
    """(pixel, ok) of film position ``uv``: its floor (box filter) or ``pixels.decode``."""
    if pixels is None:
        return dr.floor(uv), mi.Bool(True)
    return pixels.decode(uv)


def sample_pixel(sensor, si, pixels=None):
    """(pixel in crop coordinates, ok) of camera hits ``si``: the pixel the textures centre on
    (``pbrt_path`` counts the sample there)."""
    si = dr.detach(si)
    camera_hit, uv = _film_position(sensor, si)
    pix, ok = _pixel_of(uv, pixels)
    return pix, camera_hit & ok & dr.all(dr.isfinite(pix))


def pixel_footprint(sensor, si, pixels=None) -> PixelFootprint:
    """The pixel footprint of each lane of ``si`` for ``sensor`` (detached); ``pixels``: the
    published :class:`FilterPixels` (the pixel is decoded from the film position, and the
    filter's radius must keep the perspective terms small), None for the box filter."""
    si = dr.detach(si)
    p, n = mi.Point3f(si.p), mi.Vector3f(si.n)
    to_world = sensor.world_transform()
    cam_o = mi.Point3f(to_world.translation())
    forward = dr.normalize(mi.Vector3f(to_world @ mi.Vector3f(0, 0, 1)))
    camera_hit, uv = _film_position(sensor, si)
    crop = mi.ScalarVector2f(sensor.film().crop_size())
    pix, decoded = _pixel_of(uv, pixels)
    camera_hit &= decoded
    centre = (pix + 0.5) / crop
    ray, _ = sensor.sample_ray_differential(si.time, mi.Float(0.5), centre, mi.Point2f(0.5),
                                            camera_hit)

    def q(d):
        return dr.dot(n, d) / dr.dot(forward, d)

    qc = q(ray.d)
    g = q(ray.d_x) / qc - 1
    h = q(ray.d_y) / qc - 1

    def hit(o, d):
        return o + d * (dr.dot(n, p - o) / dr.dot(n, d))

    # all three rays from the pinhole itself: Mitsuba starts each camera ray on the near plane
    # and its offset rays at the main ray's origin, off their own lines by ~near_clip × one
    # pixel's angle (a 0.4% error in the footprint in the test scene)
    p_c = hit(cam_o, ray.d)
    dp0 = (hit(cam_o, ray.d_x) - p_c) * (1 + g)
    dp1 = (hit(cam_o, ray.d_y) - p_c) * (1 + h)
    t_c = dr.dot(n, p - cam_o) / dr.dot(n, ray.d)
    dp_du, dp_dv = mi.Vector3f(si.dp_du), mi.Vector3f(si.dp_dv)
    duv_c, _ = uv_partials(dp_du, dp_dv, mi.Vector3f(p_c - p), mi.Vector3f(0))
    d0, d1 = uv_partials(dp_du, dp_dv, dp0, dp1)
    uv_c = mi.Point2f(si.uv + duv_c)
    ok = (camera_hit & (t_c > 0) & (dr.abs(g) < 1) & (dr.abs(h) < 1)
          & dr.all(dr.isfinite(p_c)) & dr.all(dr.isfinite(dp0)) & dr.all(dr.isfinite(dp1))
          & dr.isfinite(g) & dr.isfinite(h))
    if pixels is not None:
        # the filter's support reaches `radius` pixels: 1 + a·g + b·h stays above 1/2 there
        ok &= (dr.abs(g) + dr.abs(h)) * pixels.radius < 0.5
    return PixelFootprint(uv_c, d0, d1, g, h, p_c, dp0, dp1, ok)


def filter_context(si, pixels):
    """For the film filter of ``pixels``: (the context at the pixel *centre* — uv of the centre
    ray, exact partials there —, g, h, ok). A texture filters the film filter's kernel around
    it (:func:`mitsuba_pbrt_tex.gauss.pixel_filter`) where ``ok``, the sample's own context
    elsewhere."""
    ctx = TextureEvalContext.from_si(si)
    fp = pixel_footprint(current_sensor(), si, pixels)
    ok = fp.ok
    centre = TextureEvalContext(
        p=dr.select(ok, fp.p_c, ctx.p), dpdx=dr.select(ok, fp.dp0, ctx.dpdx),
        dpdy=dr.select(ok, fp.dp1, ctx.dpdy), n=ctx.n, uv=dr.select(ok, fp.uv_c, ctx.uv),
        dudx=dr.select(ok, fp.d0.x, ctx.dudx), dudy=dr.select(ok, fp.d1.x, ctx.dudy),
        dvdx=dr.select(ok, fp.d0.y, ctx.dvdx), dvdy=dr.select(ok, fp.d1.y, ctx.dvdy))
    return centre, dr.select(ok, fp.g, 0), dr.select(ok, fp.h, 0), ok


def context(si) -> TextureEvalContext:
    """The context an opting-in texture filters: the pixel's (centred on its screen-weighted
    centroid, partials exact at the pixel centre) for camera hits while ``pbrt_path`` publishes
    a sensor with a box film filter, else the sample's (``TextureEvalContext.from_si``). The
    parallelogram is the box filter's pixel: with a Gaussian film (``current_pixels()``) a
    texture that has no kernel of the film's filter (:func:`filter_context`) keeps the sample's
    footprint."""
    ctx = TextureEvalContext.from_si(si)
    sensor = current_sensor()
    if sensor is None or current_pixels() is not None:
        return ctx
    fp = pixel_footprint(sensor, si)
    ok = fp.ok
    uv = fp.uv_c - (fp.d0 * fp.g + fp.d1 * fp.h) * (1.0 / 12.0)
    p = fp.p_c - (fp.dp0 * fp.g + fp.dp1 * fp.h) * (1.0 / 12.0)
    return TextureEvalContext(
        p=dr.select(ok, p, ctx.p), dpdx=dr.select(ok, fp.dp0, ctx.dpdx),
        dpdy=dr.select(ok, fp.dp1, ctx.dpdy), n=ctx.n,
        uv=dr.select(ok, uv, ctx.uv),
        dudx=dr.select(ok, fp.d0.x, ctx.dudx), dudy=dr.select(ok, fp.d1.x, ctx.dudy),
        dvdx=dr.select(ok, fp.d0.y, ctx.dvdx), dvdy=dr.select(ok, fp.d1.y, ctx.dvdy))
