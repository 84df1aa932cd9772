"""pbrt_marble — marble veins: a sine of a perturbed coordinate through a colour spline (pbrt).

| parameter | type | default | meaning | differentiable |
|---|---|---|---|---|
| octaves | integer | 8 | maximum number of FBm octaves (0–30) | no |
| roughness | float | 0.5 | ω of the FBm (≥ 0; roughness^octaves ≤ 1e30) | no |
| scale | float | 1 | frequency: p is multiplied by it | no |
| variation | float | 0.2 | amplitude of the FBm perturbation | no |
| aamode | string | clamp | `clamp` (pbrt) or `none` (all octaves) | no |
| (3D mapping) | | | the texture-space transform, see the mapping table | no |

``t = .5 + .5·sin(p.y + variation·FBm(scale·p))`` selects a segment of a cubic Bézier spline
through 9 marble colours; the result is 1.5× the spline colour. The segment index is pbrt-v4's
``min(floor(6t), 5)`` (pbrt-v3's ``min(1, …)`` extrapolates the spline, its issue #252/#341).

The sine's argument is first reduced by whole periods (:func:`_sin`): Dr.Jit's float32 ``sin``
leaves its range beyond |x| ~ 1e5 (-185763 at 3.3e8, -inf at 1e10, NaN at 1e20), where pbrt's
``std::sin`` stays exact; reduced, it agrees with the exact sine of the float32 argument to
1.4e-7 up to |x| = 1e5, 3.5e-7 at 1e8, 4e-6 at 1e9 (``tests/test_procedural.py``). Beyond, a
float32 argument's own spacing is a large part of a period or more: the value there is a finite
colour of the spline, as arbitrary as pbrt's.
"""

import drjit as dr
import mitsuba as mi

from mitsuba_pbrt_tex.noise import device_table, fbm
from mitsuba_pbrt_tex.solid import NoiseTexture

#: 2π as the sum of three float32 numbers, the first with 8 significant bits (Cody–Waite): for
#: a float32 ``x`` and its whole periods ``k``, ``x - k·C₁`` is exact in float32, and the later
#: parts round relative to the small remainder
_TWO_PI = (6.28125, 0.0019350051879882812, 3.019916050561733e-07)


def _sin(x):
    """``sin(x)`` of float32 ``x``, reduced by ``round(x/2π)`` whole periods first (Cody–Waite:
    each product exact in its fma; see the module docstring); in [-1, 1] for every input, 0 for
    non-finite ones."""
    k = dr.round(x * (0.5 / 3.141592653589793))
    for part in _TWO_PI:
        x = dr.fma(-k, part, x)
    s = dr.sin(x)
    return dr.select(dr.isfinite(s), dr.clip(s, -1.0, 1.0), 0.0)


COLORS = [(.58, .58, .6), (.58, .58, .6), (.58, .58, .6), (.5, .5, .5), (.6, .59, .58),
          (.58, .58, .6), (.58, .58, .6), (.2, .2, .33), (.58, .58, .6)]
N_SEGMENTS = len(COLORS) - 3


def _colors():
    """The control points, flat, as a device table
    (:func:`~mitsuba_pbrt_tex.noise.device_table`)."""
    return device_table('marble', lambda: mi.Float([c for rgb in COLORS for c in rgb]))


class Plugin(NoiseTexture):
    NAME = 'pbrt_marble'

    def configure_more(self, p):
        self._colors = _colors()        # made here, a member (see device_table)
        self.scale = p.float('scale', 1.0)
        self.variation = p.float('variation', 0.2)
        self.describe('scale', self.scale)
        self.describe('variation', self.variation)

    def value(self, tc):
        p = tc.p * self.scale
        m = p.y + self.variation * fbm(p, tc.dpdx * self.scale, tc.dpdy * self.scale,
                                       self.roughness, self.octaves, self.antialias, self._perm)
        t = 0.5 + 0.5 * _sin(m)
        first = dr.clip(dr.floor(t * N_SEGMENTS), 0, N_SEGMENTS - 1)
        u = t * N_SEGMENTS - first
        idx = mi.UInt32(first)
        cp = [dr.gather(mi.Color3f, self._colors, idx + k) for k in range(4)]
        # de Casteljau evaluation of the cubic Bézier segment
        a = [dr.lerp(cp[k], cp[k + 1], u) for k in range(3)]
        b = [dr.lerp(a[k], a[k + 1], u) for k in range(2)]
        return 1.5 * dr.lerp(b[0], b[1], u)

    def mean(self):
        return mi.Float(1.5 * 0.55)
