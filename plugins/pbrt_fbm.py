"""pbrt_fbm — fractional Brownian motion: a sum of noise octaves (pbrt ``FBmTexture``).

| parameter | type | default | meaning | differentiable |
|---|---|---|---|---|
| octaves | integer | 8 | maximum number of octaves (0–30) | no |
| roughness | float | 0.5 | ω, the weight ratio between successive octaves (≥ 0; roughness^octaves ≤ 1e30) | no |
| aamode | string | clamp | `clamp` (pbrt: octaves from the footprint) or `none` (all octaves) | no |
| (3D mapping) | | | the texture-space transform, see the mapping table | no |

``Σ ωⁱ·Noise(1.99ⁱ·p)``; a float texture (grey as colour). Values lie roughly in [-1, 1].
"""

import mitsuba as mi

from mitsuba_pbrt_tex.noise import fbm
from mitsuba_pbrt_tex.solid import NoiseTexture


class Plugin(NoiseTexture):
    NAME = 'pbrt_fbm'

    def value(self, tc):
        return fbm(tc.p, tc.dpdx, tc.dpdy, self.roughness, self.octaves, self.antialias,
                   self._perm)

    def mean(self):
        return mi.Float(0.0)
