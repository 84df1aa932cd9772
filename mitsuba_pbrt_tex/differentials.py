"""Texture differentials (pbrt section 10.1): what a texture needs to know about one lookup.

:class:`TextureEvalContext` is pbrt-v4's ``TextureEvalContext`` built from Mitsuba's
``SurfaceInteraction3f``:

* ``uv`` and the four partials ``du/dx, du/dy, dv/dx, dv/dy`` from ``si.duv_dx``/``si.duv_dy``.
  Non-finite partials become 0 and finite ones are clamped to ±1e8, as pbrt-v4 does after its
  least-squares solve (pbrt-v4 commit 0d3b3d73).
* ``p``, ``dp/dx``, ``dp/dy`` for 3D textures. Mitsuba stores no ``dp/dx``; we reconstruct it as
  ``dp_du·du/dx + dp_dv·dv/dx``. When ``dp_du``, ``dp_dv`` span the tangent plane this equals the
  tangent-plane offset pbrt intersects, because the least-squares uv solution reproduces any
  in-plane vector exactly.
* ``n`` — the geometric normal (pbrt's ``ctx.n``, used by ``directionmix``).

A bare ``mi.SurfaceInteraction3f()`` with only ``uv`` set is accepted: its empty fields count
as 0. Mitsuba's own integrators leave ``si.duv_dx = si.duv_dy = 0``: every derivative here is then 0, so
filters select the finest MIP level, checkerboards point-sample and noise uses all octaves — the
behaviour of a point sample. ``pbrt_path`` fills them in.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

#: pbrt-v4 clamps uv partials to this magnitude.
PARTIAL_CLAMP = 1e8


def sanitize_partial(x: mi.Float) -> mi.Float:
    """Non-finite → 0, otherwise clamp to ±PARTIAL_CLAMP (pbrt-v4 ``ComputeDifferentials``)."""
    return dr.select(dr.isfinite(x), dr.clip(x, -PARTIAL_CLAMP, PARTIAL_CLAMP), 0.0)


@dataclass
class TextureEvalContext:
    """Everything a mapping or texture reads about one lookup (all Dr.Jit values; a PyTree)."""

    p: object        # Point3f, world space
    dpdx: object     # Vector3f
    dpdy: object     # Vector3f
    n: object        # Normal3f, geometric
    uv: object       # Point2f
    dudx: object     # Float
    dudy: object
    dvdx: object
    dvdy: object

    @staticmethod
    def from_si(si: mi.SurfaceInteraction3f) -> 'TextureEvalContext':
        duv_dx, duv_dy = _field(si, 'duv_dx', mi.Vector2f), _field(si, 'duv_dy', mi.Vector2f)
        dp_du, dp_dv = _field(si, 'dp_du', mi.Vector3f), _field(si, 'dp_dv', mi.Vector3f)
        dudx = sanitize_partial(duv_dx.x)
        dvdx = sanitize_partial(duv_dx.y)
        dudy = sanitize_partial(duv_dy.x)
        dvdy = sanitize_partial(duv_dy.y)
        dpdx = dr.fma(dp_du, dudx, dp_dv * dvdx)
        dpdy = dr.fma(dp_du, dudy, dp_dv * dvdy)
        return TextureEvalContext(p=_field(si, 'p', mi.Point3f), dpdx=mi.Vector3f(dpdx),
                                  dpdy=mi.Vector3f(dpdy), n=_field(si, 'n', mi.Normal3f),
                                  uv=_field(si, 'uv', mi.Point2f), dudx=dudx, dudy=dudy,
                                  dvdx=dvdx, dvdy=dvdy)

    @staticmethod
    def uv_jacobian(si: mi.SurfaceInteraction3f) -> 'TextureEvalContext':
        """A context whose "x" is u and whose "y" is v.

        Mapping it yields ``ds/du, ds/dv, dt/du, dt/dv`` in the ``dsdx, dsdy, dtdx, dtdy`` slots:
        the Jacobian used to turn a gradient in (s, t) into one in (u, v) (``eval_1_grad``).
        """
        one, zero = mi.Float(1), mi.Float(0)
        return TextureEvalContext(p=_field(si, 'p', mi.Point3f),
                                  dpdx=_field(si, 'dp_du', mi.Vector3f),
                                  dpdy=_field(si, 'dp_dv', mi.Vector3f),
                                  n=_field(si, 'n', mi.Normal3f), uv=_field(si, 'uv', mi.Point2f),
                                  dudx=one, dudy=zero, dvdx=zero, dvdy=one)


def with_shifting_fields(si: mi.SurfaceInteraction3f) -> mi.SurfaceInteraction3f:
    """A copy of ``si`` in which what a lookup moved along u or v reads — ``uv``, ``p``,
    ``dp_du``, ``dp_dv``, ``duv_dx``, ``duv_dy`` — is 0 where a bare interaction left it empty
    (see :func:`_field`), so that it can be shifted."""
    out = mi.SurfaceInteraction3f(si)
    for name, cls in (('uv', mi.Point2f), ('p', mi.Point3f), ('dp_du', mi.Vector3f),
                      ('dp_dv', mi.Vector3f), ('duv_dx', mi.Vector2f), ('duv_dy', mi.Vector2f)):
        setattr(out, name, _field(si, name, cls))
    return out


def without_differentials(si: mi.SurfaceInteraction3f) -> mi.SurfaceInteraction3f:
    """A copy of ``si`` whose uv partials are 0: the lookup without a footprint."""
    out = mi.SurfaceInteraction3f(si)
    out.duv_dx = out.duv_dy = dr.zeros(mi.Vector2f)
    return out


def _field(si, name: str, cls):
    """``si.<name>`` as ``cls``; 0 where the caller left it empty.

    A bare ``mi.SurfaceInteraction3f()`` (only ``uv`` set, as a user or an emitter builds for a
    lookup) has fields of width 0, which cannot be combined with width-1 or width-N arrays; they
    mean "not given": zero differentials, p = n = 0 (``bitmap`` evaluates such a record too).
    """
    value = getattr(si, name)
    return cls(value) if dr.width(value) > 0 else dr.zeros(cls)
