"""Perlin noise, FBm and Turbulence (pbrt section 10.6) in Dr.Jit.

* :func:`noise` — Perlin's gradient noise exactly as pbrt: the 256-entry permutation (stored twice),
  pbrt's 16-direction ``Grad``, the weight ``6t⁵ - 15t⁴ + 10t³`` and trilinear blending of the 8
  corner contributions. pbrt-v4 reduces coordinates with ``fmod(x, 2^30)`` first (commit a4ed0d52)
  so the integer lattice index cannot overflow; we do the same, and also map non-finite
  coordinates to 0 so every permutation-table gather stays in range.
* :func:`fbm` and :func:`turbulence` — pbrt's antialiasing by *clamping* (section 10.1.2): the
  number of octaves is ``n = clamp(-1 - log2(max(|dp/dx|², |dp/dy|²)) / 2, 0, octaves)``, the
  ``floor(n)`` full octaves are summed and the next one is faded in with
  ``smoothstep(.3, .7, n - floor(n))``. Turbulence replaces the clamped octaves by their average
  0.2 (pbrt's constant). Zero differentials give all octaves; infinite ones none. NaN
  differentials are treated as 0.
* **Deviation from pbrt** (its known bug, spec §6.2 and bug 10): pbrt-v3/v4's ``Turbulence`` does
  not advance the octave weight after the partial octave, so its first clamped octave repeats
  octave ``floor(n)``'s weight — one octave too many (``maxOctaves + 1``), and even with all
  octaves resolved it adds ``0.2·ω^maxOctaves``. With pbrt's defaults (8 octaves, ω = 0.5) that
  made the mean over random points 0.598 where every octave is clamped (footprints of half a
  lattice cell or more) against 0.434 with all octaves (+38%; 40–50% too bright in a user trial's
  renders). Here the partial octave is octave ``floor(n)`` and the clamped ones are
  ``floor(n)+1 … maxOctaves-1``, each with its own weight ``ωⁱ``: ``maxOctaves`` octaves in all,
  and no partial octave when ``n = maxOctaves``. The clamped mean is then 0.398 — below 0.434
  only because ``|Noise|`` averages 0.218, not 0.2 (see :func:`turbulence`).

The octave loop is a ``dr.while_loop`` per lane, so lanes far away (few octaves) stop early.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

#: Perlin's reference permutation (pbrt ``NoisePerm``, first half).
PERMUTATION = np.array([
    151, 160, 137, 91, 90, 15, 131, 13, 201, 95, 96, 53, 194, 233, 7, 225, 140, 36, 103, 30, 69,
    142, 8, 99, 37, 240, 21, 10, 23, 190, 6, 148, 247, 120, 234, 75, 0, 26, 197, 62, 94, 252, 219,
    203, 117, 35, 11, 32, 57, 177, 33, 88, 237, 149, 56, 87, 174, 20, 125, 136, 171, 168, 68, 175,
    74, 165, 71, 134, 139, 48, 27, 166, 77, 146, 158, 231, 83, 111, 229, 122, 60, 211, 133, 230,
    220, 105, 92, 41, 55, 46, 245, 40, 244, 102, 143, 54, 65, 25, 63, 161, 1, 216, 80, 73, 209, 76,
    132, 187, 208, 89, 18, 169, 200, 196, 135, 130, 116, 188, 159, 86, 164, 100, 109, 198, 173, 186,
    3, 64, 52, 217, 226, 250, 124, 123, 5, 202, 38, 147, 118, 126, 255, 82, 85, 212, 207, 206, 59,
    227, 47, 16, 58, 17, 182, 189, 28, 42, 223, 183, 170, 213, 119, 248, 152, 2, 44, 154, 163, 70,
    221, 153, 101, 155, 167, 43, 172, 9, 129, 22, 39, 253, 19, 98, 108, 110, 79, 113, 224, 232,
    178, 185, 112, 104, 218, 246, 97, 228, 251, 34, 242, 193, 238, 210, 144, 12, 191, 179, 162,
    241, 81, 51, 145, 235, 249, 14, 239, 107, 49, 192, 214, 31, 181, 199, 106, 157, 184, 84, 204,
    176, 115, 121, 50, 45, 127, 4, 150, 254, 138, 236, 205, 93, 222, 114, 67, 29, 24, 72, 243, 141,
    128, 195, 78, 66, 215, 61, 156, 180], dtype=np.int32)

FMOD_PERIOD = float(2 ** 30)
LACUNARITY = 1.99          # pbrt's frequency step between octaves


_device_tables: dict = {}


def device_table(name: str, make):
    """A constant table as an evaluated device array (``make()``), one per name and variant,
    made on first use — by the constructors of the textures that read it — so that a render
    traced inside ``dr.freeze`` copies nothing from the host (made there, the copy could not be
    recorded: the process aborted, found in a user trial) nor makes an array inside the
    recording (which it refused)."""
    key = (name, mi.variant())
    table = _device_tables.get(key)
    if table is None:
        table = make()
        dr.eval(table)
        _device_tables[key] = table
    return table


def perm_table():
    """The permutation table, stored twice (:func:`device_table`)."""
    return device_table('perm', lambda: mi.Int32(np.concatenate([PERMUTATION, PERMUTATION])))


def _reduce(x):
    """pbrt-v4's ``fmod(x, 2^30)`` (C semantics: sign of x), non-finite → 0."""
    x = dr.select(dr.isfinite(x), x, 0.0)
    return x - dr.trunc(x / FMOD_PERIOD) * FMOD_PERIOD


def _grad(perm, ix, iy, iz, dx, dy, dz):
    h = dr.gather(mi.Int32, perm, dr.gather(mi.Int32, perm, dr.gather(mi.Int32, perm, ix) + iy) + iz) & 15
    u = dr.select((h < 8) | (h == 12) | (h == 13), dx, dy)
    v = dr.select((h < 4) | (h == 12) | (h == 13), dy, dz)
    return dr.select((h & 1) != 0, -u, u) + dr.select((h & 2) != 0, -v, v)


def _weight(t):
    t3 = t * t * t
    return dr.fma(dr.fma(6.0, t, -15.0), t * t3, 10.0 * t3)     # 6t⁵ - 15t⁴ + 10t³


def noise(p: mi.Point3f, perm=None) -> mi.Float:
    """Perlin noise at p (pbrt ``Noise(Point3f)``); 0 at integer lattice points."""
    perm = perm_table() if perm is None else perm
    x, y, z = _reduce(p.x), _reduce(p.y), _reduce(p.z)
    fx, fy, fz = dr.floor(x), dr.floor(y), dr.floor(z)
    dx, dy, dz = x - fx, y - fy, z - fz
    ix, iy, iz = mi.Int32(fx) & 255, mi.Int32(fy) & 255, mi.Int32(fz) & 255
    w = {}
    for a in (0, 1):
        for b in (0, 1):
            for c in (0, 1):
                w[a, b, c] = _grad(perm, ix + a, iy + b, iz + c, dx - a, dy - b, dz - c)
    wx, wy, wz = _weight(dx), _weight(dy), _weight(dz)
    x00 = dr.lerp(w[0, 0, 0], w[1, 0, 0], wx)
    x10 = dr.lerp(w[0, 1, 0], w[1, 1, 0], wx)
    x01 = dr.lerp(w[0, 0, 1], w[1, 0, 1], wx)
    x11 = dr.lerp(w[0, 1, 1], w[1, 1, 1], wx)
    y0 = dr.lerp(x00, x10, wy)
    y1 = dr.lerp(x01, x11, wy)
    return dr.lerp(y0, y1, wz)


def smoothstep(a: float, b: float, x):
    v = dr.clip((x - a) / (b - a), 0.0, 1.0)
    return v * v * (3 - 2 * v)


def octave_count(dpdx: mi.Vector3f, dpdy: mi.Vector3f, max_octaves: int, antialias: bool = True):
    """pbrt's ``n = clamp(-1 - log2(len²)/2, 0, maxOctaves)`` (all octaves without antialiasing)."""
    if not antialias:
        return mi.Float(max_octaves)
    len2 = dr.maximum(dr.squared_norm(dpdx), dr.squared_norm(dpdy))
    len2 = dr.select(dr.isnan(len2), 0.0, len2)
    n = -1 - 0.5 * dr.log2(len2)                     # log2(0) = -inf → n = +inf
    return dr.clip(dr.select(dr.isnan(n), 0.0, n), 0.0, float(max_octaves))


def _octaves(p, n, omega, turbulent: bool, max_octaves: int, perm):
    """Σ_{i < floor(n)} o_i · f(Noise(λ_i p)) with f = identity or |·|; returns (sum, λ, o)."""
    n_int = dr.floor(n)

    def cond(i, lam, o, total):
        return i < n_int

    def body(i, lam, o, total):
        v = noise(lam * p, perm)
        total = dr.fma(o, dr.abs(v) if turbulent else v, total)
        return i + 1, lam * LACUNARITY, o * omega, total

    state = (mi.Float(0), mi.Float(1), mi.Float(1), mi.Float(0))
    _, lam, o, total = dr.while_loop(state, cond, body, max_iterations=max_octaves + 1,
                                     label='pbrt_noise_octaves')
    return total, lam, o, perm


def fbm(p, dpdx, dpdy, omega, max_octaves: int, antialias: bool = True, perm=None):
    """pbrt ``FBm`` (``perm``: the texture's :func:`perm_table`, which a frozen function must
    find among the texture's members)."""
    n = octave_count(dpdx, dpdy, max_octaves, antialias)
    perm = perm_table() if perm is None else perm
    total, lam, o, perm = _octaves(p, n, omega, False, max_octaves, perm)
    partial = smoothstep(0.3, 0.7, n - dr.floor(n))
    return dr.fma(o * partial, noise(lam * p, perm), total)


def turbulence(p, dpdx, dpdy, omega, max_octaves: int, antialias: bool = True, perm=None):
    """pbrt ``Turbulence``: ``Σ_{i < maxOctaves} ωⁱ·|Noise(λᵢ p)|`` with the octaves past the
    footprint's ``n`` replaced by their average 0.2 (``perm`` as for :func:`fbm`).

    Octaves ``i < floor(n)`` are summed; octave ``floor(n)`` (if below ``max_octaves``) is the
    blend ``lerp(smoothstep(.3, .7, n - floor(n)), 0.2, |Noise|)``; octaves ``floor(n)+1 …
    max_octaves-1`` add ``ωⁱ·0.2``. pbrt adds the clamped octaves from ``floor(n)`` on without
    advancing ω, counting octave ``floor(n)`` twice (see the module docstring): a documented
    deviation.

    The mean of ``|Noise|`` over random points is 0.218 (3 × 2·10⁶ points: 0.2180, 0.2178,
    0.2177, standard error 1.1·10⁻⁴ each), not pbrt's 0.2; pbrt's constant is kept, so a fully
    clamped texture averages 8% below the all-octave one (0.398 against 0.434 with 8 octaves,
    ω = 0.5)."""
    n = octave_count(dpdx, dpdy, max_octaves, antialias)
    perm = perm_table() if perm is None else perm
    total, lam, o, perm = _octaves(p, n, omega, True, max_octaves, perm)
    if not antialias:                  # n = max_octaves: every octave summed, none clamped
        return total
    n_int = dr.floor(n)
    # octave n_int, partly resolved (none when n = max_octaves: there is no octave n_int then)
    partial = smoothstep(0.3, 0.7, n - n_int)
    o_partial = dr.select(n_int < max_octaves, o, 0.0)
    total = dr.fma(o_partial, dr.lerp(0.2, dr.abs(noise(lam * p, perm)), partial), total)
    # octaves n_int+1 … max_octaves-1: Σ_{j=1..k} o·ωʲ·0.2, k = max_octaves - 1 - n_int, where
    # Σ_{j=1..k} ωʲ = (ω - ω^(k+1)) / (1 - ω) (k for ω = 1); ω^(k+1) ≤ ω^max_octaves stays finite.
    # k ≤ 0 (k = -1 where n = max_octaves) gives exactly 0: dr.power(ω, 1) is not exactly ω
    # (1e30 → 1.0000012e30), and that difference times o = ω^max_octaves gave 2e23 for
    # roughness 1e30 with one octave.
    k = max_octaves - 1 - n_int
    omega = mi.Float(omega)
    series = dr.select(omega == 1, k, (omega - dr.power(omega, k + 1)) / (1 - omega))
    series = dr.select(k > 0, series, 0.0)
    return dr.fma(0.2 * o, series, total)
