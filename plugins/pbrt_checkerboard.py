"""pbrt_checkerboard — 2D or 3D checkerboard with closed-form antialiasing (pbrt ``Checkerboard``).

| parameter | type | default | meaning | differentiable |
|---|---|---|---|---|
| tex1 | float, rgb, texture | 1 | the even cells (floor(s) + floor(t) even) | yes |
| tex2 | float, rgb, texture | 0 | the odd cells | yes |
| dimension | integer | 2 | 2 (uses the 2D mapping) or 3 (solid, uses p in texture space) | no |
| aamode | string | triangle | `none` (point sample), `box` (pbrt-v3 closed form; alias `closedform`), `triangle` (pbrt-v4) or `area` (dimension 2 only: the exact average over the footprint parallelogram, pixel-centred under `pbrt_path` `footprint="pixel"`) | no |
| (2D mapping) | | | dimension 2: mapping parameters, see the mapping table | no |
| (3D mapping) | | | dimension 3: the texture-space transform, see the mapping table | no |

The filter footprint comes from the texture differentials (``pbrt_path``); with zero differentials
(Mitsuba's integrators) every mode is the point sample. Nested textures are evaluated only where
their weight is non-zero. The closed forms and the fix of pbrt-v3's NaN are described in
:mod:`mitsuba_pbrt_tex.checker`.

``area`` opts in to pixel footprints like ``pbrt_imagemap``'s ``box`` filter (see
:mod:`mitsuba_pbrt_tex.pixel`): under ``pbrt_path`` with ``footprint="pixel"`` and a box film
filter a camera hit gets the average over its pixel's footprint (with a Gaussian film, the
sample's footprint: the Gaussian pixel kernel exists for images only), the same for every
sample of the pixel — exact for a
checkerboard that enters the shading linearly (albedo, emission), while a roughness or bump
checkerboard would converge to the shading of the averaged texture. Why not ``box``: pbrt-v3's
``box`` (``closedform``) averages over a square of half-width ``max(|d/dx|, |d/dy|)``, about twice
the pixel; reusing the name would change every scene that uses it.
"""

import drjit as dr
import mitsuba as mi

from mitsuba_pbrt_tex import pixel
from mitsuba_pbrt_tex.checker import AAMODES, area_mean, tex2_weight
from mitsuba_pbrt_tex.mapping import mapping_2d, mapping_3d
from mitsuba_pbrt_tex.texture import PbrtTexture, nested_mean


def _width(a, b):
    return dr.maximum(dr.abs(a), dr.abs(b))


class Plugin(PbrtTexture):
    NAME = 'pbrt_checkerboard'

    def configure(self, p):
        self.nested_texture(p, 'tex1', 1.0)
        self.nested_texture(p, 'tex2', 0.0)
        self.dimension = p.int('dimension', 2)
        if self.dimension not in (2, 3):
            raise p.error('dimension', f'unknown value {self.dimension}; accepted values: 2, 3')
        self.aamode = p.enum('aamode', 'triangle', AAMODES)
        if self.dimension == 3 and self.aamode == 'area':
            raise p.error('aamode', 'value "area" is for dimension 2 (the footprint '
                                    'parallelogram in (s, t)); accepted values with dimension 3: '
                                    + ', '.join(m for m in AAMODES if m != 'area'))
        self.mapping = mapping_2d(p) if self.dimension == 2 else mapping_3d(p)
        for name in ('dimension', 'aamode'):
            self.describe(name, getattr(self, name))
        self.describe('mapping', self.mapping.describe())

    def weight(self, si):
        """Weight of tex2 at each lookup (``area``: the pixel's average, strip by strip, see
        :func:`mitsuba_pbrt_tex.pixel.pixel_average`)."""
        if self.dimension == 2 and self.aamode == 'area':
            return pixel.pixel_average(si, lambda ctx, active: self._weight_2d(ctx), mi.Float)
        if self.dimension == 2:
            return self._weight_2d(self.context(si))
        tc = self.mapping.map(self.context(si))
        return tex2_weight((tc.p.x, tc.p.y, tc.p.z),
                           (_width(tc.dpdx.x, tc.dpdy.x), _width(tc.dpdx.y, tc.dpdy.y),
                            _width(tc.dpdx.z, tc.dpdy.z)), self._closed_form())

    def _closed_form(self) -> str:
        """The closed form of the mode (``area`` falls back to ``box`` where it does not hold)."""
        return 'box' if self.aamode == 'area' else self.aamode

    def _weight_2d(self, ctx):
        tc = self.mapping.map(ctx)
        w = tex2_weight((tc.st.x, tc.st.y),
                        (_width(tc.dsdx, tc.dsdy), _width(tc.dtdx, tc.dtdy)), self._closed_form())
        if self.aamode == 'area':
            mean, ok = area_mean((tc.st.x, tc.st.y), (tc.dsdx, tc.dtdx), (tc.dsdy, tc.dtdy))
            w = dr.select(ok, 0.5 - 0.5 * mean, w)
        return w

    def evaluate(self, si, kind, active):
        w = self.weight(si)
        return self.blend_nested(w, si, kind, active)

    def multiplies_varying(self):
        return self.varies('tex1', 'tex2')      # (times the checks' weight)

    def mean(self):
        return mi.Float(0.5 * (nested_mean(self._nested['tex1']) + nested_mean(self._nested['tex2'])))

    def prepare_differentials(self):
        return self.aamode != 'none' or PbrtTexture.prepare_differentials(self)
