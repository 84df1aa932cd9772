"""Texture-coordinate mappings (pbrt section 10.2) with analytic derivatives.

A 2D mapping turns a :class:`~mitsuba_pbrt_tex.differentials.TextureEvalContext` into a
:class:`TexCoord2D` — ``(s, t)`` and ``ds/dx, ds/dy, dt/dx, dt/dy`` — and the 3D mapping into a
:class:`TexCoord3D` — ``p, dp/dx, dp/dy`` in texture space. Every derivative is the exact chain
rule of the mapping applied to the context's screen-space derivatives.

The texture space is given by ``to_world`` (pbrt's CTM at the ``Texture`` directive,
``renderFromTexture`` in pbrt-v4); mappings evaluate points in texture space, i.e. they apply
its inverse.

Deliberate deviations from pbrt (each has a test in ``tests/test_mapping.py``):

1. *pbrt-v4 spherical mapping swaps its derivatives*: it returns ``s = θ/π, t = φ/2π`` but pairs
   ``s`` with ∇(φ/2π) and ``t`` with ∇(θ/π). We pair each coordinate with its own gradient
   (verified against central differences of the mapping).
2. *pbrt-v3 cylindrical/spherical mappings use forward differences* (δ = .01, .1) and a seam fix on
   the wrong component (``[1]``, i.e. t, where the seam is in s). We use pbrt-v4's analytic
   derivatives, which have no seam problem at all (they are derivatives of φ, which is smooth
   across the ±π cut).
3. *pbrt-v3 planar mapping ignores the texture transform* and *pbrt-v3 3D mapping uses the
   texture-to-world transform un-inverted*; we follow pbrt-v4 (both use world→texture).
4. Poles and the axis: ``∇φ`` is undefined where ``x² + y² = 0`` and ``∇θ`` at the origin; pbrt
   divides by zero there. We return 0 for those derivative terms, so lookups stay finite.

``uv`` mapping extension: Mitsuba's ``to_uv`` (a 2D affine transform, as on ``bitmap``) is
accepted and applied *before* pbrt's scale and offset: ``(s, t) = S · to_uv · (u, v)`` with
``S = [[uscale, 0, udelta], [0, vscale, vdelta]]``.

2D mapping parameters (``mapping`` and those of the chosen kind; a parameter of another kind is an
error):

| parameter | type | default | meaning | differentiable |
|---|---|---|---|---|
| mapping | string | uv | `uv`, `spherical`, `cylindrical` or `planar` | no |
| uscale, vscale | float | 1 | `uv`: scale of u and v | no |
| udelta, vdelta | float | 0 | `uv` and `planar`: offset added to s and t | no |
| to_uv | transform | identity | `uv`: Mitsuba-style 2D transform applied to (u, v) first | no |
| v1, v2 | vector | (1,0,0), (0,1,0) | `planar`: s = udelta + v1·p, t = vdelta + v2·p (texture space) | no |
| to_world | transform | identity | `spherical`, `cylindrical`, `planar`: texture space → world; invertible (singular values of its 3×3 part ≥ 1e-9 and ≥ the largest / 1e7) | no |

3D mapping parameters (solid textures):

| parameter | type | default | meaning | differentiable |
|---|---|---|---|---|
| to_world | transform | identity | texture space → world; lookups use p in texture space; invertible as above | no |
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from .differentials import TextureEvalContext
from .params import Params

MAPPINGS_2D = ('uv', 'spherical', 'cylindrical', 'planar')
INV_PI = 1.0 / math.pi
INV_2PI = 0.5 / math.pi


@dataclass
class TexCoord2D:
    """(s, t) and their screen-space derivatives (pbrt-v4 ``TexCoord2D``; a PyTree)."""

    st: object       # Point2f
    dsdx: object     # Float
    dsdy: object
    dtdx: object
    dtdy: object


@dataclass
class TexCoord3D:
    """A texture-space point and its screen-space derivatives (pbrt-v4 ``TexCoord3D``)."""

    p: object        # Point3f
    dpdx: object     # Vector3f
    dpdy: object


#: :func:`finite_st` clamps texture coordinates to this magnitude (pbrt-v4's clamp of the partials)
ST_LIMIT = 1e8


def finite_st(st):
    """(s, t) for textures that use the coordinates as values (``pbrt_bilerp``, ``pbrt_uv``):
    NaN → 0 and clamped to ±ST_LIMIT (±inf → ±1e8), so the result is finite (NaN/inf uv come
    from meshes with bad ``vt`` entries; image lookups sanitise their own coordinates)."""
    def one(x):
        return dr.clip(dr.select(dr.isnan(x), 0.0, x), -ST_LIMIT, ST_LIMIT)
    return mi.Point2f(one(st.x), one(st.y))


def _safe_div(a, b):
    return dr.select(b != 0, a / b, 0.0)


class _WorldToTexture:
    """world → texture space (inverse of ``to_world``), applied to points and vectors."""

    def __init__(self, to_world: mi.ScalarTransform4f | None):
        self.to_world = mi.ScalarTransform4f() if to_world is None else to_world
        self.identity = to_world is None
        self.scalar = self.to_world.inverse()

    def point(self, p):
        return mi.Point3f(p) if self.identity else mi.Transform4f(self.scalar) @ mi.Point3f(p)

    def vector(self, v):
        return mi.Vector3f(v) if self.identity else mi.Transform4f(self.scalar) @ mi.Vector3f(v)


#: A uv mapping's 2×2 matrix maps u and v each onto one axis when the product of its other
#: diagonal's entries is below this fraction of its own: :func:`_without_rounding`.
ROUNDING = 1e-6


def _without_rounding(a):
    """The 2×2 matrix ``a`` with rounding set to 0: where one diagonal's product is below
    ROUNDING² of the other's, its entries are rounding of a rotation by a multiple of 90° (cos
    90° = -4.4e-8), and the matrix maps u and v each onto one axis, as it means to — and as the
    emitter sampling's density (:mod:`mitsuba_pbrt_tex.sampling`, which samples axis by axis)
    assumes: with the rounding left in, a texture's value and the density at one uv were read a
    few thousandths of a texel apart (a sparse light's weights 0.70–1.17× their median). A test
    of products does not change when rows or columns are scaled: ``uscale`` 1e7 next to
    ``vscale`` 1, before or after any rotation, keeps both rows (entry by entry, a comparison
    with the largest had zeroed v's row); a rotation's rounding leaves both entries non-zero,
    so a diagonal with an exact 0 (a shear) is kept."""
    (p, q), (r, t) = a
    if 0 not in (p, t) and abs(p * t) < ROUNDING ** 2 * abs(q * r):
        return [[0.0, q], [r, 0.0]]
    if 0 not in (q, r) and abs(q * r) < ROUNDING ** 2 * abs(p * t):
        return [[p, 0.0], [0.0, t]]
    return [list(row) for row in a]


class UVMapping:
    """``(s, t) = A · (u, v) + b``: pbrt's scale/offset, optionally after Mitsuba's ``to_uv``."""

    name = 'uv'

    def __init__(self, su=1.0, sv=1.0, du=0.0, dv=0.0, to_uv: mi.ScalarTransform4f | None = None):
        # 2x3 affine matrix of to_uv (rows 0-1, columns 0-1 and translation column 3)
        m = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
        if to_uv is not None:
            tm = to_uv.matrix
            m = [[float(tm[r][0]), float(tm[r][1]), float(tm[r][3])] for r in range(2)]
        s, d = (su, sv), (du, dv)
        self.a = _without_rounding([[s[r] * m[r][0], s[r] * m[r][1]] for r in range(2)])
        self.b = [s[r] * m[r][2] + d[r] for r in range(2)]
        self.to_uv = m                  # its 2x3 affine matrix (identity when not given)
        self.params = dict(uscale=su, vscale=sv, udelta=du, vdelta=dv)
        if to_uv is not None:
            self.params['to_uv'] = 'custom'

    def to_uv_3x3(self) -> mi.ScalarAffineTransform3f:
        """``to_uv`` as Mitsuba's ``bitmap`` exposes it in ``mi.traverse``."""
        (a, b, c), (d, e, f) = self.to_uv
        return mi.ScalarAffineTransform3f(mi.ScalarMatrix3f(a, b, c, d, e, f, 0, 0, 1))

    def with_to_uv(self, to_uv3) -> 'UVMapping':
        """The same scale and offset after another ``to_uv`` (a 3x3 affine transform)."""
        m = to_uv3.matrix
        t4 = mi.ScalarTransform4f(mi.ScalarMatrix4f(m[0][0], m[0][1], 0, m[0][2],
                                                    m[1][0], m[1][1], 0, m[1][2],
                                                    0, 0, 1, 0, 0, 0, 0, 1))
        p = self.params
        return UVMapping(p['uscale'], p['vscale'], p['udelta'], p['vdelta'], t4)

    def map(self, ctx: TextureEvalContext) -> TexCoord2D:
        (a00, a01), (a10, a11) = self.a
        u, v = ctx.uv.x, ctx.uv.y
        st = mi.Point2f(dr.fma(a00, u, dr.fma(a01, v, self.b[0])),
                        dr.fma(a10, u, dr.fma(a11, v, self.b[1])))
        return TexCoord2D(st,
                          dsdx=a00 * ctx.dudx + a01 * ctx.dvdx, dsdy=a00 * ctx.dudy + a01 * ctx.dvdy,
                          dtdx=a10 * ctx.dudx + a11 * ctx.dvdx, dtdy=a10 * ctx.dudy + a11 * ctx.dvdy)

    def describe(self) -> str:
        return 'uv(' + ', '.join(f'{k}={v:g}' if isinstance(v, float) else f'{k}={v}'
                                 for k, v in self.params.items()) + ')'


def _chain(grad_s: mi.Vector3f, grad_t: mi.Vector3f, dpdx, dpdy, st) -> TexCoord2D:
    return TexCoord2D(st, dsdx=dr.dot(grad_s, dpdx), dsdy=dr.dot(grad_s, dpdy),
                      dtdx=dr.dot(grad_t, dpdx), dtdy=dr.dot(grad_t, dpdy))


def _grad_phi(pt: mi.Point3f) -> mi.Vector3f:
    """∇ atan2(y, x) = (-y, x, 0) / (x² + y²); 0 on the z axis (where it is undefined)."""
    rho2 = dr.fma(pt.x, pt.x, pt.y * pt.y)
    return mi.Vector3f(_safe_div(-pt.y, rho2), _safe_div(pt.x, rho2), 0.0)


class _DirectionMapping:
    """A mapping of the texture-space point of p (``to_world``: texture space → world): st and
    the gradients of s and t there (:meth:`st_gradients`), chained with dp/dx, dp/dy."""

    name = 'direction'

    def __init__(self, to_world=None):
        self.xf = _WorldToTexture(to_world)

    def map(self, ctx: TextureEvalContext) -> TexCoord2D:
        st, grad_s, grad_t = self.st_gradients(self.xf.point(ctx.p))
        return _chain(grad_s, grad_t, self.xf.vector(ctx.dpdx), self.xf.vector(ctx.dpdy), st)

    def st_gradients(self, pt):
        raise NotImplementedError

    def describe(self) -> str:
        return self.name


class SphericalMapping(_DirectionMapping):
    """``s = θ/π, t = φ/2π`` of the texture-space direction of p (θ from +z, φ from +x)."""

    name = 'spherical'

    def st_gradients(self, pt):
        rho2 = dr.fma(pt.x, pt.x, pt.y * pt.y)
        r2 = dr.fma(pt.z, pt.z, rho2)
        rho = dr.sqrt(rho2)
        theta = dr.atan2(rho, pt.z)                 # = acos(z / r), robust near the poles
        phi = dr.atan2(pt.y, pt.x)
        phi = dr.select(phi < 0, phi + 2 * math.pi, phi)
        st = mi.Point2f(theta * INV_PI, phi * INV_2PI)
        # ∇θ = (x z / ρ, y z / ρ, -ρ) / r²   (s = θ/π: this is what pbrt-v4 calls dtdp)
        grad_theta = mi.Vector3f(_safe_div(pt.x * pt.z, rho), _safe_div(pt.y * pt.z, rho), -rho)
        return st, _safe_div(1.0, r2) * grad_theta * INV_PI, _grad_phi(pt) * INV_2PI


class CylindricalMapping(_DirectionMapping):
    """``s = (π + atan2(y, x)) / 2π``, ``t = z`` in texture space (pbrt-v4: raw z)."""

    name = 'cylindrical'

    def st_gradients(self, pt):
        st = mi.Point2f((math.pi + dr.atan2(pt.y, pt.x)) * INV_2PI, pt.z)
        return st, _grad_phi(pt) * INV_2PI, mi.Vector3f(0, 0, 1)


class PlanarMapping:
    """``s = udelta + v1·p``, ``t = vdelta + v2·p`` in texture space."""

    name = 'planar'

    def __init__(self, v1, v2, du=0.0, dv=0.0, to_world=None):
        self.xf = _WorldToTexture(to_world)
        self.v1, self.v2 = mi.ScalarVector3f(v1), mi.ScalarVector3f(v2)
        self.du, self.dv = float(du), float(dv)

    def map(self, ctx: TextureEvalContext) -> TexCoord2D:
        pt = mi.Vector3f(self.xf.point(ctx.p))
        v1, v2 = mi.Vector3f(self.v1), mi.Vector3f(self.v2)
        st = mi.Point2f(self.du + dr.dot(v1, pt), self.dv + dr.dot(v2, pt))
        return _chain(v1, v2, self.xf.vector(ctx.dpdx), self.xf.vector(ctx.dpdy), st)

    def describe(self) -> str:
        return f'planar(v1={list(self.v1)}, v2={list(self.v2)}, udelta={self.du:g}, vdelta={self.dv:g})'


class PointTransformMapping:
    """3D mapping: p, dp/dx, dp/dy in texture space (pbrt-v4 ``PointTransformMapping``)."""

    name = '3d'

    def __init__(self, to_world=None):
        self.xf = _WorldToTexture(to_world)

    def map(self, ctx: TextureEvalContext) -> TexCoord3D:
        return TexCoord3D(self.xf.point(ctx.p), self.xf.vector(ctx.dpdx), self.xf.vector(ctx.dpdy))

    def describe(self) -> str:
        return 'transform' if not self.xf.identity else 'identity'


# ------------------------------------------------------------------------------ factories
_UV_ONLY = ('uscale', 'vscale', 'to_uv')
_DELTA = ('udelta', 'vdelta')
_PLANAR_ONLY = ('v1', 'v2')


def mapping_2d(p: Params):
    """Build the 2D mapping a plugin's parameters describe (``mapping`` + its parameters)."""
    kind = p.enum('mapping', 'uv', MAPPINGS_2D)
    used = {'uv': _UV_ONLY + _DELTA, 'planar': _PLANAR_ONLY + _DELTA + ('to_world',),
            'spherical': ('to_world',), 'cylindrical': ('to_world',)}[kind]
    for name in _UV_ONLY + _DELTA + _PLANAR_ONLY + ('to_world',):
        if p.has(name) and name not in used:
            raise p.error(name, f'does not apply to mapping "{kind}"; parameters of "{kind}": '
                                f'{", ".join(used) if used else "(none)"}')
    if kind == 'uv':
        return UVMapping(p.float('uscale', 1.0), p.float('vscale', 1.0),
                         p.float('udelta', 0.0), p.float('vdelta', 0.0), p.transform('to_uv'))
    to_world = p.transform('to_world', invertible=True)
    if kind == 'spherical':
        return SphericalMapping(to_world)
    if kind == 'cylindrical':
        return CylindricalMapping(to_world)
    v1, v2 = p.vector('v1', (1, 0, 0)), p.vector('v2', (0, 1, 0))
    return PlanarMapping(v1, v2, p.float('udelta', 0.0), p.float('vdelta', 0.0), to_world)


def mapping_3d(p: Params) -> PointTransformMapping:
    return PointTransformMapping(p.transform('to_world', invertible=True))
