"""Pixel-centred texture footprints for camera hits: what an opting-in texture filters under
``pbrt_path`` ``footprint="pixel"`` (its producer is ``pbrt_path``, through the published
:class:`~mitsuba_pbrt_tex.render_scope.RenderScope`; its readers are the textures).

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
difference is of second order in the perspective change across one pixel (:func:`context`).
With a Gaussian film the texture filters the film's kernel around the pixel centre instead
(:func:`filter_context`, :func:`mitsuba_pbrt_tex.gauss.pixel_filter`), for the pixel decoded from
the sample's film position (:mod:`mitsuba_pbrt_tex.film_view`).

Everything is reconstructed from the hit itself, since a texture sees only ``si``:

* a camera hit is a hit whose ray started at the camera: ``si.p + si.t·wi`` is where the
  direction ``-wi`` from the sensor's position meets its near clipping plane (within 1e-4 of the
  distance; secondary rays do not start there);
* its pixel is where the sensor projects ``si.p`` (``Sensor.sample_direction``), the centre ray is
  the sensor's ray through that pixel's centre, and the rest is the tangent-plane geometry of
  ``si`` (``p``, ``n``, ``dp_du``, ``dp_dv``).

No field of ``si`` is changed or reused, so it works the same inside Mitsuba's symbolic loop,
inside the BSDF's symbolic call and in wavefront mode. Lanes where it cannot hold — not a camera
hit, nothing published (Mitsuba's own integrators, a direct ``tex.eval(si)``), a plane missed by
the centre ray, ``|g|`` or ``|h|`` ≥ 1 (the pixel sees the plane's horizon), non-finite values —
use the sample-centred context.

Limits: ``perspective`` sensors (a pinhole: the aperture sample plays no role), box or Gaussian
film filter (``pbrt_path`` refuses the others). A hit's film position, found again from its
ray's direction (:func:`_film_uv`), carries ~1e-4 pixel of float32 rounding: on a box film
``pbrt_path`` keeps its camera samples :data:`EDGE_MARGIN` inside their pixel
(:func:`inset_camera_rays`), so that no sample is assigned to the neighbouring pixel (the
Gaussian path counts each sample where its texture centred).
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from . import render_scope
from .differentials import TextureEvalContext
from .raydiff import film_ray, plane_hit, uv_partials

#: A ray starts at the camera when its origin is within this fraction of the hit distance.
CAMERA_TOLERANCE = 1e-4
#: ... and, found through the mirror image of wi in the geometric tangent plane, within this
#: one: float32 rounding of the frames it went through (a few 1e-7), no more — an angle of
#: 1e-6 moves a 4K film position by 7e-3 pixel (see :func:`_film_position`).
GEOMETRIC_MIRROR_TOLERANCE = 1e-6
#: The Gaussian kernel holds where the perspective terms keep 1 + a·g + b·h above 1 - this over
#: the filter's support.
PERSPECTIVE_LIMIT = 0.5
#: Box-film camera samples are kept this many pixels inside their pixel's edges.
EDGE_MARGIN = 1e-3
#: A box-film pixel whose larger perspective term exceeds this is cut into strips across it, each
#: a pixel footprint of its own with a term at most this (:func:`strips`): small enough that the
#: parallelogram's second-order shape error stays below a converged pixel's noise where a pixel
#: spans a few texels of detail (README, *Pixel footprints*).
STRIP_PERSPECTIVE = 1.0 / 32.0
#: At most this many strips (a kernel holds this many lookups of an opting-in texture; each
#: strip is a whole lookup, so this bounds the cost of the pixels nearest the horizon).
MAX_STRIPS = 2


@dataclass
class PixelFootprint:
    """The footprint of the pixel a camera hit belongs to (see the module docstring), per
    lane."""

    uv_c: object        # the centre ray's uv
    d0: object          # uv derivatives with respect to the film position (one pixel)
    d1: object
    g: object           # the perspective terms
    h: object
    p_c: object         # world space: the centre ray's hit and its derivatives
    dp0: object
    dp1: object
    ok: object          # where the footprint holds

    def uv_map(self) -> '_Projective':
        """The footprint in uv, as a projective map of the pixel."""
        return _Projective(self.uv_c, self.d0, self.d1, self.g, self.h)

    def world_map(self) -> '_Projective':
        """The footprint in world space, as a projective map of the pixel."""
        return _Projective(self.p_c, self.dp0, self.dp1, self.g, self.h)


def _film_uv(sensor, direction, time, active=True):
    """The film position (crop pixel coordinates) of the camera ray through the pinhole along
    world-space ``direction``: Mitsuba's projection of a point far along it (half the far clip
    distance, at most 1e7), so that the point's float32 rounding, relative to its distance, is
    that of the direction itself (~1e-7). The hit point itself, on a plane hundreds of units
    across, seen from a few units away, is rounded ~1e-5 of its coordinates: its film position
    was off by up to 7e-3 pixel (the bench's grazing plane)."""
    to_world = sensor.world_transform()
    cam_o = mi.Point3f(to_world.translation())
    it = dr.zeros(mi.Interaction3f)
    it.p = cam_o + dr.normalize(direction) * min(0.5 * float(sensor.far_clip()), 1e7)
    it.time = time
    ds, _ = sensor.sample_direction(it, mi.Point2f(0.5), active)
    return mi.Point2f(ds.uv)


def _film_position(sensor, si):
    """(camera hit?, the hit's film position in crop pixel coordinates) — the one computation
    both ``pbrt_path`` and the textures make, so that both find the same pixel."""
    p = mi.Point3f(si.p)
    to_world = sensor.world_transform()
    cam_o = mi.Point3f(to_world.translation())
    forward = dr.normalize(mi.Vector3f(to_world @ mi.Vector3f(0, 0, 1)))
    dist = dr.norm(p - cam_o)

    def from_camera(wi, tolerance=CAMERA_TOLERANCE):
        """Did a ray towards ``-wi`` start on the camera's near clipping plane, where a camera
        ray starts (its direction meeting that plane), and end here?"""
        origin = p + si.t * wi
        expected = cam_o - wi * (float(sensor.near_clip()) / dr.dot(forward, -wi))
        return dr.norm(origin - expected) <= tolerance * dist

    # the direction the ray came from — or its mirror image in the tangent plane: a ``twosided``
    # BSDF hands its nested BSDF (and so the textures) a back-side hit with the local wi's z
    # negated (a plane with flip_normals seen from its back lost its pixel footprints: a
    # trial), in the shading frame of the hit — which a normal or bump map inside the
    # ``twosided`` then replaces: there the mirror image in the geometric tangent plane, exact
    # where the shading frame was the geometric one (flat shapes) and accepted only to the
    # frames' rounding (GEOMETRIC_MIRROR_TOLERANCE): a smooth-shaded mesh's shading normal
    # makes it inexact, and within the camera tolerance it named film positions up to 0.7
    # pixel off (a review, 4K film) — such back sides keep the sample's footprint
    wi = si.to_world(si.wi)
    shading = si.to_world(mi.Vector3f(si.wi.x, si.wi.y, -si.wi.z))
    n = mi.Vector3f(si.n)
    geometric = wi - 2 * dr.dot(wi, n) * n
    direct, back = from_camera(wi), from_camera(shading)
    flat = ~direct & ~back & from_camera(geometric, GEOMETRIC_MIRROR_TOLERANCE)
    wi = dr.select(direct, wi, dr.select(back, shading, geometric))
    camera_hit = si.is_valid() & (direct | back | flat)
    return camera_hit, _film_uv(sensor, -wi, si.time, camera_hit)


def inset_camera_rays(sensor, ray, pixel_pos):
    """``ray`` (Mitsuba's camera rays of a box film, drawn in pixels ``pixel_pos``, film
    coordinates), moved where needed to a film position :data:`EDGE_MARGIN` inside the pixel
    (0.4% of the samples, by at most that margin): a hit's film position, found from its ray's
    direction, then falls in the pixel its sample was drawn in."""
    corner = mi.Point2f(pixel_pos) - mi.ScalarVector2f(sensor.film().crop_offset())
    uv = _film_uv(sensor, ray.d, ray.time)
    inside = dr.clip(uv, corner + EDGE_MARGIN, corner + (1 - EDGE_MARGIN))
    moved = dr.any(inside != uv) & dr.all(dr.isfinite(uv))
    moved_ray, _ = film_ray(sensor, inside, ray.time, moved)
    return dr.select(moved, moved_ray, ray)


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
    pix, decoded = _pixel_of(uv, pixels)
    camera_hit &= decoded
    ray, _ = film_ray(sensor, pix + 0.5, si.time, camera_hit)

    def q(d):
        return dr.dot(n, d) / dr.dot(forward, d)

    qc = q(ray.d)
    g = q(ray.d_x) / qc - 1
    h = q(ray.d_y) / qc - 1

    def hit(o, d):
        return plane_hit(o, d, p, n)

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
        ok &= (dr.abs(g) + dr.abs(h)) * pixels.radius < PERSPECTIVE_LIMIT
    return PixelFootprint(uv_c, d0, d1, g, h, p_c, dp0, dp1, ok)


def filter_context(si, pixels):
    """For the film filter of ``pixels``: (the context at the pixel *centre* — uv of the centre
    ray, exact partials there —, g, h, ok). A texture filters the film filter's kernel around
    it (:func:`mitsuba_pbrt_tex.gauss.pixel_filter`) where ``ok``, the sample's own context
    elsewhere."""
    ctx = TextureEvalContext.from_si(si)
    fp = pixel_footprint(render_scope.current().sensor, si, pixels)
    ok = fp.ok
    centre = TextureEvalContext(
        p=dr.select(ok, fp.p_c, ctx.p), dpdx=dr.select(ok, fp.dp0, ctx.dpdx),
        dpdy=dr.select(ok, fp.dp1, ctx.dpdy), n=ctx.n, uv=dr.select(ok, fp.uv_c, ctx.uv),
        dudx=dr.select(ok, fp.d0.x, ctx.dudx), dudy=dr.select(ok, fp.d1.x, ctx.dudy),
        dvdx=dr.select(ok, fp.d0.y, ctx.dvdx), dvdy=dr.select(ok, fp.d1.y, ctx.dvdy))
    return centre, dr.select(ok, fp.g, 0), dr.select(ok, fp.h, 0), ok


def published_pixels():
    """The published render's FilterPixels (Gaussian film), or None (a box film, or nothing
    published): what tells a texture to filter the film's kernel (:func:`filter_context`)."""
    scope = render_scope.current()
    return None if scope is None else scope.pixels


@dataclass
class _Projective:
    """``c + (a·e0 + b·e1) / (1 + a·g + b·h)`` over ``a, b ∈ [-1/2, 1/2]``: a pixel's footprint
    in one space (uv or world), per lane."""

    c: object
    e0: object
    e1: object
    g: object
    h: object

    def strip(self, along_b, n, k) -> '_Projective':
        """Strip ``k`` of ``n`` equal strips of the pixel, cut across ``b`` where ``along_b``
        and across ``a`` elsewhere, as a footprint of the same form. Across ``b``: with ``s =
        1 + b_k·h`` at the strip's centre ``b_k``, centre ``c + b_k·e1/s``, edges ``(e0 -
        g·b_k·e1/s)/s`` and ``e1/(n·s²)``, terms ``g/s`` and ``h/(n·s)``; across ``a`` the
        same with the roles of (a, e0, g) and (b, e1, h) swapped."""
        mid = -0.5 + (k + 0.5) / n
        e_cut, e_other = dr.select(along_b, self.e1, self.e0), dr.select(along_b, self.e0, self.e1)
        t_cut, t_other = dr.select(along_b, self.h, self.g), dr.select(along_b, self.g, self.h)
        inv = dr.rcp(1 + mid * t_cut)
        centre = self.c + e_cut * (mid * inv)
        other = (e_other - e_cut * (t_other * mid * inv)) * inv
        cut = e_cut * (inv * inv / n)
        t_o, t_c = t_other * inv, t_cut * inv / n
        return _Projective(centre, dr.select(along_b, other, cut), dr.select(along_b, cut, other),
                           dr.select(along_b, t_o, t_c), dr.select(along_b, t_c, t_o))

    def centroid(self):
        """The screen-weighted centroid, ``c - (g·e0 + h·e1)/12`` (see the module docstring)."""
        return self.c - (self.e0 * self.g + self.e1 * self.h) * (1.0 / 12.0)


@dataclass
class PixelPart:
    """One lookup of a pixel's average: the context of a part of the pixel (a strip of it, or
    the sample's own where no pixel footprint holds) and its share of the pixel."""

    context: TextureEvalContext
    weight: object


def _part_context(ctx, uv: _Projective, p: _Projective, ok) -> TextureEvalContext:
    """The parallelogram of footprint ``uv`` (world space ``p``) on its centroid, where ``ok``;
    ``ctx`` elsewhere."""
    return TextureEvalContext(
        p=dr.select(ok, p.centroid(), ctx.p), dpdx=dr.select(ok, p.e0, ctx.dpdx),
        dpdy=dr.select(ok, p.e1, ctx.dpdy), n=ctx.n, uv=dr.select(ok, uv.centroid(), ctx.uv),
        dudx=dr.select(ok, uv.e0.x, ctx.dudx), dudy=dr.select(ok, uv.e1.x, ctx.dudy),
        dvdx=dr.select(ok, uv.e0.y, ctx.dvdx),
        dvdy=dr.select(ok, uv.e1.y, ctx.dvdy))


@dataclass
class PixelStrips:
    """A box-film pixel's footprint cut into ``n`` strips (per lane; see :func:`strips`)."""

    uv: _Projective
    p: _Projective
    along_b: object     # cut across b (else across a)
    n: object           # how many (1 where no pixel footprint holds)
    ok: object          # where the pixel footprint holds

    def part(self, ctx, k) -> PixelPart:
        """Strip ``k`` (per lane, ``k < n``) as a lookup; where no footprint holds (``n`` = 1)
        the sample's own ``ctx``."""
        uv_k = self.uv.strip(self.along_b, self.n, k)
        p_k = self.p.strip(self.along_b, self.n, k)
        return PixelPart(_part_context(ctx, uv_k, p_k, self.ok),
                         dr.select(self.ok, dr.rcp(self.n), 1.0))


def strips(si):
    """The strips whose average is the pixel's average for an opting-in texture, or None where
    ``pbrt_path`` publishes no box-film render (every lane then looks up the sample's own
    context). For camera hits the pixel's footprint (exact on the tangent plane: a projective
    image of the pixel) is cut into ``n`` equal strips across its larger perspective term,
    ``n`` the fewest that bring every strip's term to at most :data:`STRIP_PERSPECTIVE` (at
    most :data:`MAX_STRIPS`), each looked up as the parallelogram on its screen-weighted
    centroid, with weight ``1/n``. A parallelogram misses the footprint's perspective at second
    order in its terms (a trapezoid with a weight growing towards its far side): next to a
    plane's far edge, where a pixel spans much more texture on its far side than on its near
    one, the strips keep that error at the strips' terms."""
    scope = render_scope.current()
    if scope is None or scope.pixels is not None:
        return None
    fp = pixel_footprint(scope.sensor, si)
    term = dr.maximum(dr.abs(fp.g), dr.abs(fp.h))
    n = dr.clip(dr.ceil(term * (1.0 / STRIP_PERSPECTIVE)), 1, MAX_STRIPS)
    return PixelStrips(fp.uv_map(), fp.world_map(), dr.abs(fp.h) >= dr.abs(fp.g),
                       dr.select(fp.ok, n, 1), fp.ok)


def pixel_average(si, lookup, value_type, active=True):
    """``Σ weight · lookup(context, active)`` over the pixel's :func:`strips` (values of
    ``value_type``) — a texture's pixel-footprint value from its lookup of one context; the
    sample's own lookup where no box-film render is published."""
    active = mi.Bool(active)
    ctx = TextureEvalContext.from_si(si)
    cut = strips(si)
    if cut is None:
        return lookup(ctx, active)
    return _strip_sum(cut, ctx, lookup, value_type, active)


@dr.syntax
def _strip_sum(cut: PixelStrips, ctx, lookup, value_type, active):
    """The strips' weighted lookups, in a symbolic loop (one lookup in the kernel, traced
    once)."""
    total = dr.zeros(value_type, dr.width(active))
    k = mi.Float(0)
    while dr.hint(active & (k < cut.n), label='pixel footprint: strips', exclude=[cut, ctx],
                  max_iterations=-1):              # a sum: Dr.Jit's fast reverse mode
        part = cut.part(ctx, k)
        total += lookup(part.context, active) * part.weight
        k += 1
    return total


def context(si) -> TextureEvalContext:
    """The context an opting-in texture filters: the pixel's (centred on its screen-weighted
    centroid, partials exact at the pixel centre) for camera hits while ``pbrt_path`` publishes
    a render with a box film filter, else the sample's (``TextureEvalContext.from_si``). The
    parallelogram is the box filter's pixel: with a Gaussian film (:func:`published_pixels`) a
    texture that has no kernel of the film's filter (:func:`filter_context`) keeps the sample's
    footprint."""
    ctx = TextureEvalContext.from_si(si)
    scope = render_scope.current()
    if scope is None or scope.pixels is not None:
        return ctx
    fp = pixel_footprint(scope.sensor, si)
    return _part_context(ctx, fp.uv_map(), fp.world_map(), fp.ok)
