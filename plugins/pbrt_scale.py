"""pbrt_scale — a texture multiplied by a float texture (pbrt-v4 ``ScaledTexture``).

| parameter | type | default | meaning | differentiable |
|---|---|---|---|---|
| tex | float, rgb, texture | 1 | the texture to scale | yes |
| scale | float, texture | 1 | the factor (evaluated as a float texture, so an rgb value is refused) | yes |

Where ``scale`` is 0 the result is 0 and ``tex`` is not evaluated (pbrt-v4), so an infinite or NaN
``tex`` there cannot leak into the image; where ``scale`` carries gradients, ``tex`` is read there
too (the derivative is ``tex``; 0 where ``tex`` is not finite). A product beyond float32's range
(``scale`` 3e38 times 2) is float32's largest finite value of that sign, not inf.
"""

import drjit as dr
import mitsuba as mi

from mitsuba_pbrt_tex.texture import (FLOAT, PbrtTexture, derivative_unskipped, finite_range,
                                      nested_mean)


class Plugin(PbrtTexture):
    NAME = 'pbrt_scale'

    def configure(self, p):
        self.nested_texture(p, 'tex', 1.0)
        self.nested_texture(p, 'scale', 1.0, float_only=True)

    def evaluate(self, si, kind, active):
        sc = self.nested_eval('scale', si, FLOAT, active)
        nonzero = sc != 0
        # a scale carrying gradients reads tex everywhere: d/d scale = tex, also at scale 0
        differentiated = dr.grad_enabled(sc)
        value = self.nested_eval('tex', si, kind, active & (nonzero | differentiated))
        out = dr.select(nonzero, finite_range(value * sc), 0)
        return derivative_unskipped(out, value * sc) if differentiated else out

    def is_spatially_varying(self):
        return self.nested_vary()

    def multiplies_varying(self):
        return self.varies('tex') and self.varies('scale')

    def mean(self):
        return finite_range(mi.Float(nested_mean(self._nested['tex'])
                                     * nested_mean(self._nested['scale'])))
