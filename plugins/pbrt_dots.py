"""pbrt_dots — polka dots: one randomly placed dot per cell, or none (pbrt ``DotsTexture``).

| parameter | type | default | meaning | differentiable |
|---|---|---|---|---|
| inside | float, rgb, texture | 1 | the value inside the dots | yes |
| outside | float, rgb, texture | 0 | the value elsewhere | yes |
| (2D mapping) | | | mapping parameters, see the mapping table | no |

Cells are unit squares centred on integer (s, t); ``Noise(cell + .5) > 0`` decides whether the
cell has a dot, whose centre is jittered by up to 0.15 (two more noise lookups) and whose radius
is 0.35. No antialiasing (as in pbrt); wrap it in ``pbrt_supersample`` for that.
"""

import math

import drjit as dr
import mitsuba as mi

from mitsuba_pbrt_tex.mapping import mapping_2d
from mitsuba_pbrt_tex.noise import noise, perm_table
from mitsuba_pbrt_tex.texture import PbrtTexture, nested_mean

RADIUS = 0.35
MAX_SHIFT = 0.5 - RADIUS


def _noise2(x, y, perm):
    return noise(mi.Point3f(x, y, 0.5), perm)


#: The fraction of cells that hold a dot (``Noise(cell + .5) > 0``) over the noise's period of
#: 256 × 256 cells: 25832 of 65536 (tests/test_procedural.py counts them again).
DOT_FRACTION = 25832 / 65536


class Plugin(PbrtTexture):
    NAME = 'pbrt_dots'

    def configure(self, p):
        # made here, outside any render, and a member a frozen function finds (device_table)
        self._perm = perm_table()
        self.nested_texture(p, 'inside', 1.0)
        self.nested_texture(p, 'outside', 0.0)
        self.mapping = mapping_2d(p)
        self.describe('mapping', self.mapping.describe())

    def in_dot(self, si):
        st = self.mapping.map(self.context(si)).st
        s = dr.select(dr.isfinite(st.x), st.x, 0.0)
        t = dr.select(dr.isfinite(st.y), st.y, 0.0)
        s_cell, t_cell = dr.floor(s + 0.5), dr.floor(t + 0.5)
        has_dot = _noise2(s_cell + 0.5, t_cell + 0.5, self._perm) > 0
        s_c = s_cell + MAX_SHIFT * _noise2(s_cell + 1.5, t_cell + 2.8, self._perm)
        t_c = t_cell + MAX_SHIFT * _noise2(s_cell + 4.5, t_cell + 9.8, self._perm)
        ds, dt = s - s_c, t - t_c
        return has_dot & (ds * ds + dt * dt < RADIUS * RADIUS)

    def evaluate(self, si, kind, active):
        inside = self.in_dot(si)
        a = self.nested_eval('inside', si, kind, active & inside)
        b = self.nested_eval('outside', si, kind, active & ~inside)
        return dr.select(inside, a, b)

    def multiplies_varying(self):
        return self.varies('inside', 'outside')     # (times the dots' indicator)

    def mean(self):
        """The average over the noise's period (256 × 256 cells): the fraction of cells that
        hold a dot (of area π·0.35², inside its cell) weighs the two means."""
        f = DOT_FRACTION * math.pi * RADIUS * RADIUS
        return mi.Float(f * nested_mean(self._nested['inside']) + (1 - f) * nested_mean(self._nested['outside']))

    def prepare_differentials(self):
        return PbrtTexture.prepare_differentials(self)
