"""pbrt_windy — wind-blown waves: FBm modulated by a low-frequency FBm (pbrt ``WindyTexture``).

| parameter | type | default | meaning | differentiable |
|---|---|---|---|---|
| aamode | string | clamp | `clamp` (pbrt) or `none` (all octaves) | no |
| (3D mapping) | | | the texture-space transform, see the mapping table | no |

``|FBm(0.1·p, ω = .5, 3 octaves)| · FBm(p, ω = .5, 6 octaves)`` (the first with 0.1× the
footprint); a float texture (grey as colour).
"""

import drjit as dr
import mitsuba as mi

from mitsuba_pbrt_tex.noise import fbm
from mitsuba_pbrt_tex.solid import NoiseTexture


class Plugin(NoiseTexture):
    NAME = 'pbrt_windy'
    OCTAVES = None
    ROUGHNESS = None

    def value(self, tc):
        strength = fbm(0.1 * tc.p, 0.1 * tc.dpdx, 0.1 * tc.dpdy, 0.5, 3, self.antialias,
                       self._perm)
        height = fbm(tc.p, tc.dpdx, tc.dpdy, 0.5, 6, self.antialias, self._perm)
        return dr.abs(strength) * height

    def mean(self):
        return mi.Float(0.0)
