"""The Gaussian film (Mitsuba's default) under ``pbrt_path`` ``footprint="pixel"``: where its
samples go and how Mitsuba's ``render`` counts them.

A Gaussian film gives a pixel the filter-weighted average of the samples within its radius
(2 pixels), and Mitsuba's ``ImageBlock`` splats every sample into all of those pixels — so a
texture value centred on one pixel would be blurred a second time, and the pixel a hit "belongs
to" is not even defined. ``pbrt_path`` therefore changes how samples are *placed*, not what
reaches a texture (still only ``si``):

* each pixel's film positions are drawn from the filter itself, and every sample counts with
  weight 1 in that pixel alone (:class:`FilterPixels`): the converged image is the
  Gaussian-filtered one; border pixels estimate the whole filter, as with ``sample_border``;
* the pixel is recoverable from the position: in one render all pixels share their samples'
  offsets from their centres, so a film position's fractional part names the sample and its
  offset, hence the pixel (:meth:`FilterPixels.decode`). The texture decodes it from the hit
  projected back to the film, and ``pbrt_path`` decodes it the same way (same function, same
  inputs) at the first hit and counts the sample there, so the pixel a texture centred on and
  the pixel the sample counts in are always the same. A margin of half a stratum (≥ 1/64
  pixel up to 1024 spp) absorbs the rounding of a hit's film position (~1e-4 pixel from its
  ray's direction; the hit point itself was off by up to 7e-3 pixel on the bench's 400-unit
  plane). The pixel cannot be encoded in the positions'
  sub-pixel bits instead: that needs margins of ~1e-2 pixel on such scenes, or a quarter of the
  samples decode to a neighbour. The price: at low spp every pixel samples the same offsets,
  so silhouettes alias rather than being noisy;
* Mitsuba's ``render``, ``render_forward`` and ``render_backward`` run unchanged, given a view of
  the sensor (:class:`PixelSensor`) whose film (:class:`PixelFilm`) makes image blocks without
  the filter that splat each sample at the pixel it decoded to (:class:`CountingBlock`, reading
  the render's :class:`~mitsuba_pbrt_tex.render_scope.RenderScope`).
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from .raydiff import film_ray
from .render_scope import RenderScope


class Lattice:
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

    def filter_inverse(self, u):
        """The offset ``x ∈ [-radius, radius]`` at which the filter's own CDF is ``u`` (a film
        offset drawn from ``f``, per axis): Newton from the Gaussian's inverse."""
        lo = self._F_scalar(-self.radius)
        total = self._F_scalar(self.radius) - lo
        target = lo + mi.Float(u) * total
        x = dr.clip(self.sigma * math.sqrt(2.0) * dr.erfinv(dr.clip(2 * mi.Float(u) - 1,
                                                                   -0.999999, 0.999999)),
                    -self.radius, self.radius)
        for _ in range(5):
            step = (self._F(x) - target) / dr.maximum(self._f(x), 1e-6)
            x = dr.clip(x - step, -self.radius, self.radius)
        return x

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
    (``1/(2a)`` in ψ, ≥ 1/64 pixel up to 1024 spp) against the rounding of a hit's film
    position (~1e-4 pixel: :func:`mitsuba_pbrt_tex.pixel._film_uv`) — and
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
        self.lattice = Lattice(self.stddev, self.radius)
        # the render's seed (an int, or a UInt32: a literal, as mi.UInt32(step) in a loop, or
        # a frozen function's input): opaque, one kernel for all — a literal would be a
        # constant of the kernels, a new kernel (and its memory) for every seed
        if isinstance(seed, mi.UInt32):
            self.seed = mi.UInt32(seed)          # our own copy: the caller's stays as it is
            dr.make_opaque(self.seed)
        else:
            self.seed = dr.opaque(mi.UInt32, int(seed))
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

    def filter_offset(self, u):
        """A film offset (Vector2f, pixels) from the pixel centre drawn from the filter
        ``f(a)·f(b)`` by the uniform 2D sample ``u``, independently of the render's shared
        offsets (silhouette samples)."""
        return mi.Vector2f(self.lattice.filter_inverse(u.x), self.lattice.filter_inverse(u.y))

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
        with dr.resume_grad():
            ray, weight = film_ray(sensor, x, ray.time)
        return ray, weight, mi.Vector2f(pix + self.offset + 0.5)


class CountingBlock:
    """An image block without the film's filter (``ImageBlock`` treats a missing filter as the
    box) that splats each sample at the position the render's scope says it counts at
    (``RenderScope.counted``: the pixel its first hit decoded to) rather than the one Mitsuba
    passes (where it was drawn). Everything else is the block's."""

    def __init__(self, block, scope: RenderScope):
        self.block, self.scope = block, scope

    def put(self, pos, values, *args, **kwargs):
        counted = self.scope.counted
        return self.block.put(pos if counted is None else counted, values, *args, **kwargs)

    def __getattr__(self, name):
        return getattr(self.block, name)


class PixelFilm:
    """The film as :class:`PixelSensor` shows it: the film's own, except that
    :meth:`create_block` gives :class:`CountingBlock` s and :meth:`put_block` takes them."""

    def __init__(self, film, scope: RenderScope):
        self.film, self.scope = film, scope

    def __getattr__(self, name):
        return getattr(self.film, name)

    def create_block(self, *args, **kwargs):
        block = self.film.create_block(*args, **kwargs)
        plain = mi.ImageBlock(block.size(), block.offset(), block.channel_count(), None,
                              border=False, normalize=block.normalize(),
                              coalesce=block.coalesce(), warn_negative=block.warn_negative(),
                              warn_invalid=block.warn_invalid())
        return CountingBlock(plain, self.scope)

    def put_block(self, block):
        return self.film.put_block(getattr(block, 'block', block))


class PixelSensor:
    """The sensor as ``pbrt_path`` gives it to Mitsuba's ``render`` methods with a Gaussian film
    and pixel footprints: the sensor's own methods, the film of :class:`PixelFilm`, and the
    render's ``scope``."""

    def __init__(self, scope: RenderScope):
        self.sensor = scope.sensor
        self.scope = scope
        self._film = PixelFilm(scope.sensor.film(), scope)

    def film(self):
        return self._film

    def __getattr__(self, name):
        return getattr(self.sensor, name)
