"""pbrt_supersample — average any texture over the pixel footprint (pbrt section 10.1.2).

| parameter | type | default | meaning | differentiable |
|---|---|---|---|---|
| texture | texture | — | the texture to antialias (ours or any Mitsuba texture) | yes |
| samples | integer | 16 | lookups per evaluation, a perfect square n² (n×n strata), at most 65536; they spread over at most 1024 texture units per differential, at uv within ±2^17 | no |

The footprint is the parallelogram spanned by the texture differentials: with offsets
``(a, b) ∈ [-1/2, 1/2]²`` the wrapped texture is evaluated at ``uv + a·duv/dx + b·duv/dy`` and
``p + a·dp/dx + b·dp/dy`` at the centre of each of the n×n strata, with differentials shrunk to
the stratum (``duv/n``), and the results are averaged — a box filter over the pixel, computed by
the midpoint rule. Deterministic; with zero differentials (Mitsuba's integrators) it equals the
wrapped texture. Each differential component is limited to ±1024 texture units (non-finite ones
count as 0), and the coordinates handed to the nested texture are finite: NaN → 0, uv within
±2^17 and p within ±1e8, so the sub-samples stay where nested textures such as Mitsuba's
``bitmap`` are defined (it returns NaN where uv times its resolution overflows an int32: uv of
1e30 or inf; ±2^17 is safe up to 16384-texel-wide images).
"""

import math

import drjit as dr
import mitsuba as mi

from mitsuba_pbrt_tex.differentials import with_shifting_fields
from mitsuba_pbrt_tex.texture import PbrtTexture, nested_mean

#: 256 x 256 lookups per evaluation at most (the loop's counter and n² must stay far inside
#: UInt32; more is never useful for one lookup)
MAX_SAMPLES = 65536

#: The sub-samples spread over at most this many texture units per differential: Mitsuba's
#: ``bitmap`` is undefined where uv·resolution overflows an int32 (it returned NaN and 4.6e11
#: around uv ≈ 1e8), and a footprint of 1024 units already averages over 1024 periods of any
#: repeated texture.
MAX_FOOTPRINT = 1024.0


#: uv handed to the nested texture is limited to ±UV_LIMIT: Mitsuba's ``bitmap`` overflows
#: int32 beyond 2^31 / resolution. Positions are limited to ±P_LIMIT, as pbrt_uv's coordinates.
UV_LIMIT = 2.0**17
P_LIMIT = 1e8


def _footprint(x):
    """A (sanitized) uv partial limited to ±MAX_FOOTPRINT."""
    return dr.clip(x, -MAX_FOOTPRINT, MAX_FOOTPRINT)


def _coordinate(x, limit):
    """NaN → 0, then within ±limit."""
    return dr.clip(dr.select(dr.isnan(x), 0.0, x), -limit, limit)


class Plugin(PbrtTexture):
    NAME = 'pbrt_supersample'

    def configure(self, p):
        if not p.has('texture'):
            raise p.error('texture', 'is required (the texture to supersample)')
        self.nested_texture(p, 'texture', 0.0)
        self.samples = p.int('samples', 16, lo=1, hi=MAX_SAMPLES)
        self.n = int(round(math.sqrt(self.samples)))
        if self.n * self.n != self.samples:
            raise p.error('samples', f'must be a perfect square (1, 4, 9, 16, 25, ...), got '
                                     f'{self.samples}')
        self.describe('samples', self.samples)

    def evaluate(self, si, kind, active):
        n = self.n
        tex = self._nested['texture']
        ctx = self.context(si)          # sanitized partials; empty fields of a bare si are 0
        duv_dx = mi.Vector2f(_footprint(ctx.dudx), _footprint(ctx.dvdx))
        duv_dy = mi.Vector2f(_footprint(ctx.dudy), _footprint(ctx.dvdy))
        # p's offsets from the limited uv partials, as the context derives its own: 3D textures
        # get the same bounded footprint (its 1e8-wide one put fbm's sub-samples 5e7 units out)
        shifting = with_shifting_fields(si)
        dp_dx = dr.fma(shifting.dp_du, duv_dx.x, shifting.dp_dv * duv_dx.y)
        dp_dy = dr.fma(shifting.dp_du, duv_dy.x, shifting.dp_dv * duv_dy.y)
        uv, p = ctx.uv, ctx.p
        weight = 1.0 / (n * n)          # each term scaled: a sum of n² values near 3e38 is inf

        def cond(k, acc):
            return k < n * n

        def body(k, acc):
            a = (mi.Float(k % n) + 0.5) / n - 0.5
            b = (mi.Float(k // n) + 0.5) / n - 0.5
            sub = mi.SurfaceInteraction3f(si)
            sub.uv = mi.Point2f(_coordinate(uv + a * duv_dx + b * duv_dy, UV_LIMIT))
            sub.p = mi.Point3f(_coordinate(p + a * dp_dx + b * dp_dy, P_LIMIT))
            sub.duv_dx = duv_dx / n
            sub.duv_dy = duv_dy / n
            return k + 1, dr.fma(kind.nested(tex, sub, active), weight, acc)

        zero = kind.nested(tex, si, mi.Bool(False)) * 0
        _, acc = dr.while_loop((mi.UInt32(0), zero), cond, body, max_iterations=-1,
                               label='pbrt_supersample')
        return acc

    def mean(self):
        return nested_mean(self._nested['texture'])

    def prepare_differentials(self):
        PbrtTexture.prepare_differentials(self)
        return True
