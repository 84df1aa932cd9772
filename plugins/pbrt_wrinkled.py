"""pbrt_wrinkled — turbulence: a sum of absolute noise octaves (pbrt ``WrinkledTexture``).

| parameter | type | default | meaning | differentiable |
|---|---|---|---|---|
| octaves | integer | 8 | maximum number of octaves (0–30) | no |
| roughness | float | 0.5 | ω, the weight ratio between successive octaves (≥ 0; roughness^octaves ≤ 1e30) | no |
| aamode | string | clamp | `clamp` (pbrt: octaves finer than the footprint replaced by their mean 0.2, each at its own weight: pbrt counts one twice, see Deviations from pbrt) or `none` (all octaves) | no |
| (3D mapping) | | | the texture-space transform, see the mapping table | no |

``Σ_{i < octaves} ωⁱ·|Noise(1.99ⁱ·p)|``; a float texture (grey as colour).
"""

import mitsuba as mi

from mitsuba_pbrt_tex.noise import turbulence
from mitsuba_pbrt_tex.solid import NoiseTexture


class Plugin(NoiseTexture):
    NAME = 'pbrt_wrinkled'

    def value(self, tc):
        return turbulence(tc.p, tc.dpdx, tc.dpdy, self.roughness, self.octaves,
                          self.antialias, self._perm)

    def mean(self):
        w = self.roughness
        k = self.octaves
        return mi.Float(0.2 * (k if w == 1 else (1 - w ** k) / (1 - w)))
