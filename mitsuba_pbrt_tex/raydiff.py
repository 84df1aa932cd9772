"""Ray differentials for texture filtering in an integrator (pbrt section 10.1.1, pbrt-v4 9.x).

Three sources of the screen-space footprint ``dp/dx, dp/dy`` of a hit point:

* :func:`tangent_plane_offsets` — the two offset rays of a ray differential intersected with the
  tangent plane of the hit (camera rays, and rays after specular bounces);
* :class:`CameraFootprint` — pbrt-v4's ``Approximate_dp_dxy``: the camera's smallest one-pixel
  differentials (found once by sampling the sensor along the film diagonal) placed at the hit
  point, as if a camera ray hit it directly. Used after non-specular bounces, so filtered
  textures keep a footprint at every depth;
* :func:`reflect_differential` / :func:`refract_differential` — propagation through ideal
  specular reflection and transmission, shading-normal derivatives included.

:func:`uv_partials` turns ``dp/dx, dp/dy`` into ``du/dx, du/dy, dv/dx, dv/dy`` by pbrt-v4's least
squares over all three dimensions, with non-finite → 0 and a clamp to ±1e8.

Deviation from pbrt-v4 (``SurfaceInteraction::SpawnRay``, transmission): with relative index
``η`` (pbrt's ``BSDFSample::eta``) the refracted direction is ``wi = -wo/η + μ n`` with
``μ = (wo·n)/η - |wi·n|``; its derivative is ``dwi = -dwo/η + μ dn + dμ n``. pbrt-v4 writes
``-η·dwo`` for the first term while using ``1/η`` in μ, which mis-scales the footprint through
glass by η² (a 2.25× error for η = 1.5). We use ``-dwo/η``; ``tests/test_raydiff.py`` checks both
propagation formulas against finite differences of the exact refracted/reflected direction.
Grazing cases (offset ray parallel to the plane, camera at the hit point) give a zero footprint
instead of pbrt's inf/NaN.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from .differentials import sanitize_partial

#: pbrt-v4 drops differentials whose squared offsets exceed this (commit 0d3b3d73).
SQUASH_LIMIT = 1e16


def spp_scale(spp: int, mode) -> float:
    """pbrt-v4: ``max(1/8, 1/√spp)``; ``'none'``: 1; a number: that number."""
    if mode == 'pbrt':
        return max(0.125, 1.0 / math.sqrt(max(spp, 1)))
    if mode == 'none':
        return 1.0
    return float(mode)


def film_ray(sensor, position, time=None, active=True):
    """(ray differential, weight) of ``sensor`` through film ``position`` (crop pixel
    coordinates, Point2f) at the aperture's centre; ``time`` defaults to the shutter opening."""
    crop = mi.ScalarVector2f(sensor.film().crop_size())
    time = mi.Float(sensor.shutter_open()) if time is None else time
    return sensor.sample_ray_differential(time, mi.Float(0.5), mi.Point2f(position / crop),
                                          mi.Point2f(0.5), active)


def plane_hit(o, d, p, n):
    """Where the line ``o + t·d`` meets the plane through ``p`` with normal ``n`` (non-finite
    where they are parallel)."""
    return o + d * (dr.dot(n, p - o) / dr.dot(n, d))


def tangent_plane_offsets(p, n, o_x, d_x, o_y, d_y, active):
    """Offsets ``dp/dx, dp/dy`` of the offset rays' hits on the plane through p with normal n.

    Returns (dpdx, dpdy, ok); ok is False where an offset ray is parallel to the plane or the
    result is not finite (pbrt-v4 then falls back to the camera approximation)."""
    n, p = mi.Vector3f(n), mi.Point3f(p)
    d_x, d_y = mi.Vector3f(d_x), mi.Vector3f(d_y)
    dpdx = mi.Vector3f(plane_hit(mi.Point3f(o_x), d_x, p, n) - p)
    dpdy = mi.Vector3f(plane_hit(mi.Point3f(o_y), d_y, p, n) - p)
    ok = active & (dr.dot(n, d_x) != 0) & (dr.dot(n, d_y) != 0) & \
        dr.all(dr.isfinite(dpdx)) & dr.all(dr.isfinite(dpdy))
    return dr.select(ok, dpdx, 0.0), dr.select(ok, dpdy, 0.0), ok


def uv_partials(dp_du, dp_dv, dpdx, dpdy):
    """pbrt-v4 least squares: (du/dx, dv/dx), (du/dy, dv/dy) as Vector2f, sanitised."""
    ata00 = dr.dot(dp_du, dp_du)
    ata01 = dr.dot(dp_du, dp_dv)
    ata11 = dr.dot(dp_dv, dp_dv)
    det = dr.fma(ata00, ata11, -ata01 * ata01)
    inv_det = dr.rcp(det)
    inv_det = dr.select(dr.isfinite(inv_det), inv_det, 0.0)
    out = []
    for dp in (dpdx, dpdy):
        atb0, atb1 = dr.dot(dp_du, dp), dr.dot(dp_dv, dp)
        du = dr.fma(ata11, atb0, -ata01 * atb1) * inv_det
        dv = dr.fma(ata00, atb1, -ata01 * atb0) * inv_det
        out.append(mi.Vector2f(sanitize_partial(du), sanitize_partial(dv)))
    return out[0], out[1]


def reflect_differential(wo, wi, n, dndx, dwodx):
    """Direction derivative of specular reflection ``wi = -wo + 2(wo·n)n`` (pbrt)."""
    dDNdx = dr.dot(dwodx, n) + dr.dot(wo, dndx)
    return wi - dwodx + 2 * (dr.dot(wo, n) * dndx + dDNdx * n)


def refract_differential(wo, wi, n, dndx, dwodx, eta):
    """Direction derivative of refraction ``wi = -wo/η + μ n`` (see the module docstring).

    ``wo`` and ``n`` on the same side (flip n, dndx beforehand), ``eta`` = η_t/η_i."""
    wo_n = dr.dot(wo, n)
    wi_n = dr.dot(wi, n)
    inv_eta = dr.rcp(eta)
    mu = wo_n * inv_eta - dr.abs(wi_n)
    dDNdx = dr.dot(dwodx, n) + dr.dot(wo, dndx)
    dmudx = dDNdx * (inv_eta + inv_eta * inv_eta * wo_n / wi_n)
    return wi - inv_eta * dwodx + (mu * dndx + dmudx * n)


def camera_differential_defined(ray) -> mi.Bool:
    """Per lane, does a sensor's ``RayDifferential3f`` hold a differential? Sensors that define
    none (``radiancemeter``, ``irradiancemeter``, ``distant``) leave the offset rays zero, and
    ``batch`` defines them per sub-sensor but reports ``has_differentials`` false (the flag does
    not survive its call to the sub-sensor), so the offset directions, unit vectors where they
    exist, decide."""
    return (dr.squared_norm(mi.Vector3f(ray.d_x)) > 0) & (dr.squared_norm(mi.Vector3f(ray.d_y)) > 0)


def _no_common_frame(sensor) -> bool:
    """A ``batch`` sensor's sub-sensors look from different places: no one camera frame to place
    the camera approximation in (its hits after bounces get a zero footprint)."""
    return sensor.class_name() == 'BatchSensor'


class CameraFootprint:
    """pbrt-v4 ``FindMinimumDifferentials`` + ``Approximate_dp_dxy`` for a Mitsuba sensor: the
    smallest one-pixel differentials of the sensor's rays that have one (orthographic cameras:
    constant origin offsets and no spread; perspective: the reverse); zero where the sensor
    defines none."""

    SAMPLES = 512

    def __init__(self, sensor: mi.Sensor):
        self.to_world = sensor.world_transform()          # camera → world (a JIT transform)
        self.from_world = self.to_world.inverse()
        n = self.SAMPLES
        t = dr.arange(mi.Float, n) / (n - 1)
        pos = mi.Point2f(t, t)                              # the film diagonal
        ray, _ = sensor.sample_ray_differential(
            time=mi.Float(sensor.shutter_open()), sample1=mi.Float(0.5), sample2=pos,
            sample3=mi.Point2f(0.5, 0.5), active=mi.Bool(True))
        cam = self.from_world
        dox = cam @ mi.Vector3f(ray.o_x - ray.o)
        doy = cam @ mi.Vector3f(ray.o_y - ray.o)
        d = dr.normalize(ray.d)
        frame = mi.Frame3f(d)
        dxf = dr.normalize(frame.to_local(dr.normalize(ray.d_x))) - mi.Vector3f(0, 0, 1)
        dyf = dr.normalize(frame.to_local(dr.normalize(ray.d_y))) - mi.Vector3f(0, 0, 1)
        # rays without a differential take no part (none: a zero footprint after bounces)
        defined = camera_differential_defined(ray) & (not _no_common_frame(sensor))
        self.min_pos_x, self.min_pos_y, self.min_dir_x, self.min_dir_y = self._shortest(
            [dr.select(defined, v, dr.inf) for v in (dox, doy, dxf, dyf)])
        # none (all zero): no footprint at all, not the rounding of placing a zero one at p
        self.exists = ((dr.squared_norm(self.min_pos_x) + dr.squared_norm(self.min_dir_x) > 0)
                       & (dr.squared_norm(self.min_pos_y) + dr.squared_norm(self.min_dir_y) > 0))
        # evaluated now: left lazy, the first render would compute them inside its kernel and
        # every later one read them, two kernels to compile for one scene
        dr.eval(self.min_pos_x, self.min_pos_y, self.min_dir_x, self.min_dir_y, self.exists)

    @staticmethod
    def _shortest(vectors) -> list:
        """For each array of vectors (of width n, or 1 for a constant), its shortest finite vector (the first
        one on ties; 0 if none is finite), found on the device in two block reductions — no
        read-back, so a frozen function can record it, and few kernel launches per render."""
        n = max(dr.width(u) for u in vectors)
        # a sensor's constant differentials (orthographic: every ray's d_x is d) are one lane wide
        v = mi.Vector3f(*(dr.concat([dr.zeros(mi.Float, n) + u[i] for u in vectors])
                          for i in range(3)))
        length2 = dr.select(dr.all(dr.isfinite(v)), dr.squared_norm(v), dr.inf)
        shortest = dr.block_reduce(dr.ReduceOp.Min, length2, n)
        index = dr.arange(mi.UInt32, len(vectors) * n)
        at_min = length2 == dr.repeat(shortest, n)
        first = dr.block_reduce(dr.ReduceOp.Min, dr.select(at_min, index, 0xFFFFFFFF), n)
        found = dr.select(dr.isfinite(shortest), dr.gather(mi.Vector3f, v, first), 0.0)
        return [dr.gather(mi.Vector3f, found, mi.UInt32(k)) for k in range(len(vectors))]

    def dp_dxy(self, p, n, scale: float, active):
        """Approximate ``dp/dx, dp/dy`` at world point p with geometric normal n."""
        cam = self.from_world
        p_cam = mi.Vector3f(cam @ mi.Point3f(p))
        dist = dr.norm(p_cam)
        ok = active & (dist > 0) & self.exists
        frame = mi.Frame3f(dr.normalize(dr.select(ok, p_cam, mi.Vector3f(0, 0, 1))))
        n_down = frame.to_local(mi.Vector3f(cam @ mi.Normal3f(n)))
        p_down = mi.Vector3f(0, 0, dist)
        d = n_down.z * p_down.z
        out = []
        for pos, dirv in ((self.min_pos_x, self.min_dir_x), (self.min_pos_y, self.min_dir_y)):
            o = mi.Vector3f(pos)
            direction = mi.Vector3f(0, 0, 1) + mi.Vector3f(dirv)
            den = dr.dot(n_down, direction)
            t = -(dr.dot(n_down, o) - d) / den
            hit = o + t * direction
            local = hit - p_down
            world = self.to_world @ frame.to_world(local)
            good = ok & (den != 0) & dr.all(dr.isfinite(world))
            out.append(dr.select(good, scale * world, 0.0))
        return out[0], out[1]


class RayDiff:
    """The two offset rays of a ray differential (origins ``o_x, o_y``, directions ``d_x, d_y``)
    and, per lane, whether it holds: one value that a path tracer carries from bounce to bounce
    (a Dr.Jit struct, so it can be loop state)."""

    DRJIT_STRUCT = {'o_x': object, 'd_x': object, 'o_y': object, 'd_y': object, 'valid': object}

    def __init__(self, o_x=None, d_x=None, o_y=None, d_y=None, valid=None):
        self.o_x = mi.Point3f(0) if o_x is None else o_x
        self.d_x = mi.Vector3f(0) if d_x is None else d_x
        self.o_y = mi.Point3f(0) if o_y is None else o_y
        self.d_y = mi.Vector3f(0) if d_y is None else d_y
        self.valid = mi.Bool(False) if valid is None else valid

    @staticmethod
    def of_camera_ray(ray, scale) -> 'RayDiff':
        """The sensor's one-pixel differential of ``ray``, scaled by ``scale`` (detached); valid
        where the sensor defines one (:func:`camera_differential_defined`)."""
        o, d = mi.Point3f(dr.detach(ray.o)), mi.Vector3f(dr.detach(ray.d))
        return RayDiff(dr.fma(mi.Point3f(dr.detach(ray.o_x)) - o, scale, o),
                       dr.fma(mi.Vector3f(dr.detach(ray.d_x)) - d, scale, d),
                       dr.fma(mi.Point3f(dr.detach(ray.o_y)) - o, scale, o),
                       dr.fma(mi.Vector3f(dr.detach(ray.d_y)) - d, scale, d),
                       camera_differential_defined(dr.detach(ray)))

    def fields(self) -> tuple:
        return self.o_x, self.d_x, self.o_y, self.d_y, self.valid

    def dropped(self) -> 'RayDiff':
        """The same rays, no longer valid (after a non-specular bounce)."""
        return RayDiff(self.o_x, self.d_x, self.o_y, self.d_y, mi.Bool(False))

    def footprint(self, p, n, active):
        """(dp/dx, dp/dy, ok) on the tangent plane at p (see :func:`tangent_plane_offsets`)."""
        return tangent_plane_offsets(p, n, self.o_x, self.d_x, self.o_y, self.d_y,
                                     active & self.valid)

    def after_specular(self, si, bs, wo_world, origin, dpdx, dpdy) -> 'RayDiff':
        """The differential of the ray leaving ``si`` in ``wo_world`` through the sampled lobe
        ``bs`` (pbrt-v4 ``SpawnRay``): propagated through ideal specular reflection or
        transmission where this one holds, otherwise none (the next hit then uses the camera
        approximation, as in pbrt-v4).

        The offset rays start at ``origin`` — Mitsuba's *spawned* origin of the main ray — plus
        the footprint offsets: spawned origins are offset along the normal by ~1e-4·|p|, and
        starting the offset rays from the un-offset hit (as pbrt does) would add that
        displacement to the next footprint (a 0.2% error in the mirror test)."""
        reflect = mi.has_flag(bs.sampled_type, mi.BSDFFlags.DeltaReflection)
        transmit = mi.has_flag(bs.sampled_type, mi.BSDFFlags.DeltaTransmission)
        si_d = dr.detach(si)
        wo = si_d.to_world(si_d.wi)                      # pbrt's wo: towards the origin
        wi = dr.detach(wo_world)
        n = mi.Vector3f(si_d.sh_frame.n)
        duv_dx, duv_dy = si_d.duv_dx, si_d.duv_dy
        dndx = si_d.dn_du * duv_dx.x + si_d.dn_dv * duv_dx.y
        dndy = si_d.dn_du * duv_dy.x + si_d.dn_dv * duv_dy.y
        dwodx, dwody = -self.d_x - wo, -self.d_y - wo
        flip = dr.dot(wo, n) < 0
        n_t = dr.select(flip, -n, n)
        dndx_t, dndy_t = dr.select(flip, -dndx, dndx), dr.select(flip, -dndy, dndy)
        eta = dr.detach(bs.eta)
        rx = dr.select(reflect, reflect_differential(wo, wi, n, dndx, dwodx),
                       refract_differential(wo, wi, n_t, dndx_t, dwodx, eta))
        ry = dr.select(reflect, reflect_differential(wo, wi, n, dndy, dwody),
                       refract_differential(wo, wi, n_t, dndy_t, dwody, eta))
        base = mi.Point3f(dr.detach(origin))
        o_x, o_y = base + dpdx, base + dpdy
        squash = ((dr.squared_norm(rx) > SQUASH_LIMIT) | (dr.squared_norm(ry) > SQUASH_LIMIT)
                  | (dr.squared_norm(o_x) > SQUASH_LIMIT) | (dr.squared_norm(o_y) > SQUASH_LIMIT)
                  | ~dr.all(dr.isfinite(rx)) | ~dr.all(dr.isfinite(ry)))
        keep = (reflect | transmit) & si.is_valid() & self.valid & ~squash
        return RayDiff(dr.select(keep, o_x, self.o_x), dr.select(keep, rx, self.d_x),
                       dr.select(keep, o_y, self.o_y), dr.select(keep, ry, self.d_y), keep)
