"""Independent numpy implementation of pbrt's Perlin noise, FBm, Turbulence, dots and marble.

Written from pbrt's formulas (pbrt-v4 ``util/noise.cpp``, ``textures.h``). Lattice coordinates are
rounded to float32 exactly where pbrt (a float32 program) rounds them — λ is accumulated in
float32 and ``λ·p`` is a float32 product — so high octaves are compared at the same points;
everything else is float64.
"""

import math

import numpy as np

# Perlin's table, typed in again rather than imported from the package: a slip in either copy
# fails the tests instead of being shared by them.
PERM = np.array([
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
    128, 195, 78, 66, 215, 61, 156, 180])
P2 = np.concatenate([PERM, PERM])


def grad(x, y, z, dx, dy, dz):
    h = P2[P2[P2[x] + y] + z] & 15
    u = np.where((h < 8) | (h == 12) | (h == 13), dx, dy)
    v = np.where((h < 4) | (h == 12) | (h == 13), dy, dz)
    return np.where(h & 1, -u, u) + np.where(h & 2, -v, v)


def weight(t):
    return 6 * t ** 5 - 15 * t ** 4 + 10 * t ** 3


def noise(x, y=0.5, z=0.5):
    x, y, z = (np.broadcast_to(np.asarray(a, np.float64), np.shape(x)).copy() for a in (x, y, z))
    x, y, z = (np.fmod(a, 2.0 ** 30) for a in (x, y, z))
    fx, fy, fz = np.floor(x), np.floor(y), np.floor(z)
    dx, dy, dz = x - fx, y - fy, z - fz
    ix, iy, iz = (f.astype(np.int64) & 255 for f in (fx, fy, fz))
    w = {(a, b, c): grad(ix + a, iy + b, iz + c, dx - a, dy - b, dz - c)
         for a in (0, 1) for b in (0, 1) for c in (0, 1)}
    wx, wy, wz = weight(dx), weight(dy), weight(dz)
    lerp = lambda t, a, b: (1 - t) * a + t * b
    x00 = lerp(wx, w[0, 0, 0], w[1, 0, 0])
    x10 = lerp(wx, w[0, 1, 0], w[1, 1, 0])
    x01 = lerp(wx, w[0, 0, 1], w[1, 0, 1])
    x11 = lerp(wx, w[0, 1, 1], w[1, 1, 1])
    return lerp(wz, lerp(wy, x00, x10), lerp(wy, x01, x11))


def noise3(p):
    return noise(p[:, 0], p[:, 1], p[:, 2])


def smoothstep(a, b, x):
    v = np.clip((x - a) / (b - a), 0, 1)
    return v * v * (3 - 2 * v)


def octaves(dpdx, dpdy, max_octaves):
    len2 = np.maximum((dpdx ** 2).sum(1), (dpdy ** 2).sum(1))
    with np.errstate(divide='ignore'):
        n = -1 - 0.5 * np.log2(len2)
    return np.clip(np.nan_to_num(n, nan=0.0, posinf=max_octaves, neginf=0.0), 0, max_octaves)


def _scaled(p, lam):
    return (np.float32(lam) * p.astype(np.float32)).astype(np.float64)


def _full_octaves(pk, n_int, omega, f):
    """Sum of ``o·f(noise(λ·p))`` over the ``n_int`` whole octaves (λ ×1.99 in float32, o ×ω),
    and the (λ, o) of the next, partial octave."""
    total, lam, o = 0.0, np.float32(1), 1.0
    for _ in range(n_int):
        total += o * f(noise3(_scaled(pk, lam))[0])
        lam = np.float32(lam * np.float32(1.99))
        o *= omega
    return total, lam, o


def fbm(p, dpdx, dpdy, omega, max_octaves, antialias=True):
    n = octaves(dpdx, dpdy, max_octaves) if antialias else np.full(len(p), float(max_octaves))
    out = np.empty(len(p))
    for k in range(len(p)):
        n_int = int(math.floor(n[k]))
        total, lam, o = _full_octaves(p[k:k + 1], n_int, omega, float)
        total += o * smoothstep(.3, .7, n[k] - n_int) * noise3(_scaled(p[k:k + 1], lam))[0]
        out[k] = total
    return out


def turbulence(p, dpdx, dpdy, omega, max_octaves, antialias=True):
    n = octaves(dpdx, dpdy, max_octaves) if antialias else np.full(len(p), float(max_octaves))
    out = np.empty(len(p))
    for k in range(len(p)):
        n_int = int(math.floor(n[k]))
        total, lam, o = _full_octaves(p[k:k + 1], n_int, omega, abs)
        # Octave n_int fades from its mean 0.2 to |noise|; each later octave up to max_octaves - 1
        # is its mean, at its own weight ωⁱ. pbrt restarts the clamped octaves at n_int without
        # advancing o (octave n_int counted twice, max_octaves + 1 octaves): the package deviates
        # from pbrt there on purpose (README "Deviations from pbrt"), and so does this reference.
        for i in range(n_int, max_octaves):
            if i == n_int:
                part = smoothstep(.3, .7, n[k] - n_int)
                total += o * ((1 - part) * 0.2 + part * abs(noise3(_scaled(p[k:k + 1], lam))[0]))
            else:
                total += o * 0.2
            o *= omega
        out[k] = total
    return out


def windy(p, dpdx, dpdy, antialias=True):
    p01 = (np.float32(0.1) * p.astype(np.float32)).astype(np.float64)   # pbrt's float32 .1·p
    strength = fbm(p01, 0.1 * dpdx, 0.1 * dpdy, 0.5, 3, antialias)
    height = fbm(p, dpdx, dpdy, 0.5, 6, antialias)
    return np.abs(strength) * height


MARBLE = np.array([[.58, .58, .6], [.58, .58, .6], [.58, .58, .6], [.5, .5, .5], [.6, .59, .58],
                   [.58, .58, .6], [.58, .58, .6], [.2, .2, .33], [.58, .58, .6]])


def marble(p, dpdx, dpdy, octaves_, omega, scale, variation, antialias=True):
    ps = (p.astype(np.float32) * np.float32(scale)).astype(np.float64)
    m = ps[:, 1] + variation * fbm(ps, scale * dpdx, scale * dpdy, omega, octaves_, antialias)
    t = 0.5 + 0.5 * np.sin(m)
    first = np.minimum(np.floor(t * 6), 5).astype(int)
    u = (t * 6 - first)[:, None]
    cp = [MARBLE[first + i] for i in range(4)]
    a = [(1 - u) * cp[i] + u * cp[i + 1] for i in range(3)]
    b = [(1 - u) * a[i] + u * a[i + 1] for i in range(2)]
    return 1.5 * ((1 - u) * b[0] + u * b[1])


def in_dot(s, t):
    s_cell, t_cell = np.floor(s + .5), np.floor(t + .5)
    has = noise(s_cell + .5, t_cell + .5) > 0
    sc = s_cell + .15 * noise(s_cell + 1.5, t_cell + 2.8)
    tc = t_cell + .15 * noise(s_cell + 4.5, t_cell + 9.8)
    return has & ((s - sc) ** 2 + (t - tc) ** 2 < .35 ** 2)
