"""pbrt_uv — debug texture showing the texture coordinates (pbrt-v3 ``UVTexture``).

| parameter | type | default | meaning | differentiable |
|---|---|---|---|---|
| (2D mapping) | | | mapping parameters, see the mapping table | no |

RGB ``(s - floor(s), t - floor(t), 0)``; ``eval_1`` is its luminance. NaN coordinates count as 0
and s, t are clamped to ±1e8 (so inf gives 0, not NaN).
"""

import drjit as dr
import mitsuba as mi

from mitsuba_pbrt_tex.mapping import finite_st, mapping_2d
from mitsuba_pbrt_tex.texture import PbrtTexture


class Plugin(PbrtTexture):
    NAME = 'pbrt_uv'

    def configure(self, p):
        self.mapping = mapping_2d(p)
        self.describe('mapping', self.mapping.describe())

    def evaluate(self, si, kind, active):
        st = finite_st(self.mapping.map(self.context(si)).st)
        return kind.from_rgb(mi.Color3f(st.x - dr.floor(st.x), st.y - dr.floor(st.y), 0))

    def mean(self):
        return mi.luminance(mi.Color3f(0.5, 0.5, 0))

    def prepare_differentials(self):
        return False
