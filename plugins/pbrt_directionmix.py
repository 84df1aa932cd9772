"""pbrt_directionmix — blend two textures by how much the surface faces a direction (pbrt-v4).

| parameter | type | default | meaning | differentiable |
|---|---|---|---|---|
| tex1 | float, rgb, texture | 0 | the value where the normal is parallel to dir | yes |
| tex2 | float, rgb, texture | 1 | the value where the normal is perpendicular to dir | yes |
| dir | vector | (0,1,0) | the direction, in texture space | no |
| to_world | transform | identity | texture space → world (pbrt's CTM); dir is transformed by it; must be invertible (see Mappings) | no |

``amount = |n · normalize(to_world(dir))|`` with the geometric normal n, then
``amount·tex1 + (1 - amount)·tex2`` (note: tex1 is weighted by amount, as in pbrt-v4).
"""

import math

import drjit as dr
import mitsuba as mi

from mitsuba_pbrt_tex.texture import PbrtTexture, nested_mean


class Plugin(PbrtTexture):
    NAME = 'pbrt_directionmix'

    def configure(self, p):
        self.nested_texture(p, 'tex1', 0.0)
        self.nested_texture(p, 'tex2', 1.0)
        d = [float(c) for c in p.vector('dir', (0, 1, 0))]
        to_world = p.transform('to_world', invertible=True)
        if to_world is not None:        # a direction: the 3×3 part, in float64
            m = to_world.matrix
            d = [sum(float(m[i][j]) * d[j] for j in range(3)) for i in range(3)]
        # normalised in float64: float32's squared norm is 0 for subnormal vectors (1e-40,
        # whose direction is well defined) and inf beyond ~1e19
        norm = math.sqrt(sum(c * c for c in d))
        if not 0 < norm < math.inf:
            raise p.error('dir', f'must be a non-zero vector{" after to_world" if to_world else ""}'
                                 f' within float range, got {tuple(d)}')
        self.dir = mi.ScalarVector3f(*(c / norm for c in d))
        self.describe('dir', list(self.dir))

    def evaluate(self, si, kind, active):
        amount = dr.abs(dr.dot(mi.Vector3f(self.context(si).n), mi.Vector3f(self.dir)))
        return self.blend_nested(1 - amount, si, kind, active)

    def mean(self):
        return mi.Float(0.5 * (nested_mean(self._nested['tex1']) + nested_mean(self._nested['tex2'])))
