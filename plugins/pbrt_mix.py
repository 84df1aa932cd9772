"""pbrt_mix — linear interpolation of two textures (pbrt ``MixTexture``).

| parameter | type | default | meaning | differentiable |
|---|---|---|---|---|
| tex1 | float, rgb, texture | 0 | the value where amount = 0 | yes |
| tex2 | float, rgb, texture | 1 | the value where amount = 1 | yes |
| amount | float, texture | 0.5 | the blend weight (a float texture, so an rgb value is refused; not clamped) | yes |

``(1 - amount)·tex1 + amount·tex2``; like pbrt-v4, ``tex1`` is not evaluated where amount = 1 and
``tex2`` not where amount = 0 (both are where the amount carries gradients: the derivative is
``tex2 - tex1`` there too, 0 where the skipped one is not finite). Evaluated as
``tex1 + amount·(tex2 - tex1)``, exact where the two are equal whatever the amount; a result
beyond float32's range is float32's largest finite value (``PbrtTexture.blend_nested``).
"""

import drjit as dr
import mitsuba as mi

from mitsuba_pbrt_tex.texture import FLOAT, PbrtTexture, finite_range, nested_mean


class Plugin(PbrtTexture):
    NAME = 'pbrt_mix'

    def configure(self, p):
        self.nested_texture(p, 'tex1', 0.0)
        self.nested_texture(p, 'tex2', 1.0)
        self.nested_texture(p, 'amount', 0.5, float_only=True)

    def evaluate(self, si, kind, active):
        amount = self.nested_eval('amount', si, FLOAT, active)
        return self.blend_nested(amount, si, kind, active)

    def is_spatially_varying(self):
        return self.nested_vary()

    def multiplies_varying(self):
        return self.varies('amount') and self.varies('tex1', 'tex2')

    def mean(self):
        a = nested_mean(self._nested['amount'])
        m1 = nested_mean(self._nested['tex1'])
        return finite_range(mi.Float(dr.fma(a, nested_mean(self._nested['tex2']) - m1, m1)))
