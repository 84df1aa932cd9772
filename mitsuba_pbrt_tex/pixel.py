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
use the sample-centred context, as before.

Limits: ``perspective`` sensors (a pinhole: the aperture sample plays no role), box film filter
(``pbrt_path`` refuses the others). A sample within ~1e-5 pixel of a pixel edge can be assigned
to the neighbouring pixel by float32 rounding of its hit point.
"""

from __future__ import annotations

import contextlib
import threading

import drjit as dr
import mitsuba as mi

from .differentials import TextureEvalContext
from .raydiff import uv_partials

_STATE = threading.local()
#: A ray starts at the camera when its origin is within this fraction of the hit distance.
CAMERA_TOLERANCE = 1e-4


@contextlib.contextmanager
def published(sensor):
    """Within this block (on this thread), opting-in textures centre camera hits on the pixel
    of ``sensor``."""
    previous = getattr(_STATE, 'sensor', None)
    _STATE.sensor = sensor
    try:
        yield
    finally:
        _STATE.sensor = previous


def current_sensor():
    return getattr(_STATE, 'sensor', None)


class PixelFootprint:
    """The footprint of the pixel a camera hit belongs to (see the module docstring): ``uv_c``
    (the centre ray's uv), ``d0``, ``d1`` (uv derivatives with respect to the film position, one
    pixel), ``g``, ``h`` and the world-space ``p_c``, ``dp0``, ``dp1``; ``ok`` per lane."""

    def __init__(self, uv_c, d0, d1, g, h, p_c, dp0, dp1, ok):
        self.uv_c, self.d0, self.d1, self.g, self.h = uv_c, d0, d1, g, h
        self.p_c, self.dp0, self.dp1, self.ok = p_c, dp0, dp1, ok


def pixel_footprint(sensor, si) -> PixelFootprint:
    """The pixel footprint of each lane of ``si`` for ``sensor`` (detached)."""
    si = dr.detach(si)
    p, n = mi.Point3f(si.p), mi.Vector3f(si.n)
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
    crop = mi.ScalarVector2f(sensor.film().crop_size())
    centre = (dr.floor(ds.uv) + 0.5) / crop
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
    return PixelFootprint(uv_c, d0, d1, g, h, p_c, dp0, dp1, ok)


def context(si) -> TextureEvalContext:
    """The context an opting-in texture filters: the pixel's (centred on its screen-weighted
    centroid, partials exact at the pixel centre) for camera hits while ``pbrt_path`` publishes
    a sensor, else the sample's (``TextureEvalContext.from_si``)."""
    ctx = TextureEvalContext.from_si(si)
    sensor = current_sensor()
    if sensor is None:
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
