"""pbrt_bilerp — bilinear interpolation of four values over (s, t) (pbrt ``BilerpTexture``).

| parameter | type | default | meaning | differentiable |
|---|---|---|---|---|
| v00 | float, rgb, texture | 0 | the value at (s, t) = (0, 0) | yes |
| v01 | float, rgb, texture | 1 | the value at (0, 1) | yes |
| v10 | float, rgb, texture | 0 | the value at (1, 0) | yes |
| v11 | float, rgb, texture | 1 | the value at (1, 1) | yes |
| (2D mapping) | | | mapping parameters, see the mapping table | no |

``(1-s)(1-t)·v00 + (1-s)t·v01 + s(1-t)·v10 + st·v11``; no wrapping, so it extrapolates outside
[0,1]² (as pbrt). NaN coordinates count as 0 and s, t are clamped to ±1e8 (pbrt gives NaN/inf for
NaN/inf/1e30 uv, e.g. from an OBJ's bad ``vt`` entries), so the value is always finite.
"""

import drjit as dr
import mitsuba as mi

from mitsuba_pbrt_tex.mapping import finite_st, mapping_2d
from mitsuba_pbrt_tex.texture import FLOAT32_MAX, PbrtTexture, nested_mean


class Plugin(PbrtTexture):
    NAME = 'pbrt_bilerp'

    def configure(self, p):
        for name, default in (('v00', 0.0), ('v01', 1.0), ('v10', 0.0), ('v11', 1.0)):
            self.nested_texture(p, name, default)
        self.mapping = mapping_2d(p)
        self.describe('mapping', self.mapping.describe())

    def evaluate(self, si, kind, active):
        st = finite_st(self.mapping.map(self.context(si)).st)
        s, t = st.x, st.y
        v = {n: self.nested_eval(n, si, kind, active) for n in ('v00', 'v01', 'v10', 'v11')}
        # pbrt's (1-s)(1-t)·v00 + (1-s)t·v01 + s(1-t)·v10 + st·v11 as two lerps of the form
        # a + x·(b - a): the same value, without products s·t that overflow or cancel far
        # outside [0, 1]² (at s = t = 1e8 the expanded sum loses every digit). In float64: the
        # differences of values near float32's maximum (3e38 and -3e38) would overflow to inf,
        # and with s, t within ±1e8 nothing overflows there; the result is then float32's
        # nearest, ±its largest finite value beyond
        T = type(v['v00'])
        v = {n: dr.float64_array_t(T)(x) for n, x in v.items()}
        s, t = mi.Float64(s), mi.Float64(t)
        a = v['v00'] + t * (v['v01'] - v['v00'])
        b = v['v10'] + t * (v['v11'] - v['v10'])
        return T(dr.clip(a + s * (b - a), -FLOAT32_MAX, FLOAT32_MAX))

    def mean(self):
        return mi.Float(0.25 * sum(nested_mean(self._nested[n]) for n in ('v00', 'v01', 'v10', 'v11')))
