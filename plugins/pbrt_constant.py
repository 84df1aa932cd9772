"""pbrt_constant — the same value everywhere (pbrt ``ConstantTexture``).

| parameter | type | default | meaning | differentiable |
|---|---|---|---|---|
| value | float, rgb | 1 | the value (a float gives a grey/float texture) | yes |

``eval_1`` of an rgb value is its luminance (as for every pbrt_* texture and Mitsuba's ``bitmap``).
"""

import drjit as dr
import mitsuba as mi

from mitsuba_pbrt_tex.texture import PbrtTexture, check_value_update


class Plugin(PbrtTexture):
    NAME = 'pbrt_constant'

    def configure(self, p):
        value = p.float_or_rgb('value', 1.0)
        self.value = mi.Color3f(*value) if isinstance(value, tuple) else mi.Float(value)

    def evaluate(self, si, kind, active):
        if isinstance(self.value, mi.Color3f):
            return kind.from_rgb(self.value)
        return kind.from_float(self.value)

    def mean(self):
        return mi.luminance(self.value) if isinstance(self.value, mi.Color3f) else mi.Float(self.value)

    def is_spatially_varying(self):
        return False

    def max(self):
        """The largest channel, as Mitsuba's ``srgb`` answers."""
        return mi.Float(dr.max(self.value)) if isinstance(self.value, mi.Color3f) else \
            mi.Float(self.value)

    def prepare_differentials(self):
        return False

    def traverse(self, cb):
        cb.put('value', self.value, mi.ParamFlags.Differentiable)

    def on_parameters_changed(self, keys):
        if not keys or 'value' in keys:
            check_value_update(self.NAME, 'value', self.value)

    def to_string(self):
        return f'{self.NAME}[value={self.value}]'
