"""Shared base of the noise textures (pbrt section 10.6.2-10.6.4): 3D mapping and noise options.

A noise texture maps the shading point to texture space (``to_world``), reads ``octaves``,
``roughness`` (pbrt's ω) and ``aamode``, and computes one float (or, for marble, one RGB) per
lookup from :class:`~mitsuba_pbrt_tex.mapping.TexCoord3D`. Float results serve ``eval_1`` and, as
grey, ``eval``/``eval_3``.

``aamode = clamp`` (default) is pbrt's antialiasing of section 10.1.2 (octaves chosen from the
footprint); ``none`` always sums every octave, so the benefit of the clamp can be measured.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from .mapping import mapping_3d
from .noise import perm_table
from .texture import PbrtTexture

NOISE_AAMODES = ('clamp', 'none')

#: roughness^octaves at most this: the octave weights (and their sums) stay finite in float32
MAX_OCTAVE_WEIGHT = 1e30


class NoiseTexture(PbrtTexture):
    #: which of the noise parameters the texture has (octaves/roughness defaults, or None)
    OCTAVES: int | None = 8
    ROUGHNESS: float | None = 0.5

    def configure(self, p):
        # made here, outside any render, and a member a frozen function finds (device_table)
        self._perm = perm_table()
        self.mapping = mapping_3d(p)
        self.octaves = p.int('octaves', self.OCTAVES, lo=0, hi=30) if self.OCTAVES else None
        self.roughness = p.float('roughness', self.ROUGHNESS, lo=0.0) if self.ROUGHNESS else None
        if self.roughness and self.octaves and \
                self.octaves * math.log10(self.roughness) > math.log10(MAX_OCTAVE_WEIGHT):
            largest = MAX_OCTAVE_WEIGHT ** (1.0 / self.octaves)
            weight = self.octaves * math.log10(self.roughness)       # log10 of roughness^octaves
            mantissa, exponent = 10 ** (weight - math.floor(weight)), math.floor(weight)
            raise p.error('roughness', f'{self.roughness:g} with {self.octaves} octaves weights '
                                       f'the last octave by roughness^octaves = '
                                       f'{mantissa:.3g}e+{exponent} (above 1e+30), '
                                       f'which overflows float32 sums; accepted for '
                                       f'{self.octaves} octaves: roughness <= {largest:.6g}')
        self.antialias = p.enum('aamode', 'clamp', NOISE_AAMODES) == 'clamp'
        self.configure_more(p)
        for name in ('octaves', 'roughness'):
            if getattr(self, name) is not None:
                self.describe(name, getattr(self, name))
        self.describe('aamode', 'clamp' if self.antialias else 'none')
        self.describe('mapping', self.mapping.describe())

    def configure_more(self, p) -> None:
        """Extra parameters (override)."""

    def value(self, tc):
        """Float (or Color3f) from texture-space p and its derivatives (override)."""
        raise NotImplementedError

    def evaluate(self, si, kind, active):
        tc = self.mapping.map(self.context(si))
        tc.p = dr.select(dr.isfinite(tc.p), tc.p, 0.0)        # no NaN/inf can reach the math
        v = self.value(tc)
        v = dr.select(dr.isfinite(v), v, 0.0)
        return kind.from_rgb(v) if isinstance(v, mi.Color3f) else kind.from_float(v)

    def prepare_differentials(self):
        return self.antialias
