"""Independent numpy references for the image-texture tests (float64, written from pbrt's text).

Nothing here calls the package: the pyramid uses prefix sums of the piecewise-constant image (a
different algorithm from the package's tap weights), the EWA follows pbrt-v3/v4 literally
(bounding-box loop, 128-entry table), and the continuous reference integrates the bilinear
reconstruction of level 0 densely over the footprint.
"""

import math

import numpy as np

LUM = np.array([0.212671, 0.715160, 0.072169])


# ------------------------------------------------------------------------------------ pyramid
def _area_resample_axis(img, n2, axis):
    """Average of the piecewise-constant image over n2 equal intervals along ``axis``."""
    n = img.shape[axis]
    if n2 == n:
        return img
    moved = np.moveaxis(img, axis, 0)
    prefix = np.concatenate([np.zeros((1,) + moved.shape[1:]), np.cumsum(moved, axis=0)], 0)

    def integral(x):          # ∫_0^x of the piecewise-constant function
        i = np.minimum(np.floor(x).astype(int), n - 1)
        frac = (x - i)[(...,) + (None,) * (moved.ndim - 1)]
        return prefix[i] + frac * moved[i]

    edges = np.arange(n2 + 1) * (n / n2)
    out = (integral(edges[1:]) - integral(edges[:-1])) / (n / n2)
    return np.moveaxis(out, 0, axis)


def pyramid(img):
    """Levels: halve (floor) each axis until 1×1; each texel the exact area average."""
    levels = [np.asarray(img, dtype=np.float64)]
    while levels[-1].shape[:2] != (1, 1):
        h, w = levels[-1].shape[:2]
        lv = _area_resample_axis(levels[-1], max(1, w // 2), 1)
        lv = _area_resample_axis(lv, max(1, h // 2), 0)
        levels.append(lv)
    return levels


# ------------------------------------------------------------------------------------ texels
def wrap(i, n, mode):
    """Integer texel index wrap; returns (index, valid)."""
    i = np.asarray(i)
    valid = np.ones(i.shape, bool)
    if mode == 'repeat':
        return np.mod(i, n), valid
    if mode == 'clamp':
        return np.clip(i, 0, n - 1), valid
    if mode == 'black':
        return np.clip(i, 0, n - 1), (i >= 0) & (i < n)
    if mode == 'mirror':
        m = np.mod(i, 2 * n)
        return np.where(m >= n, 2 * n - 1 - m, m), valid
    raise ValueError(mode)


def octahedral(x, y, w, h):
    """pbrt-v4 ``RemapPixelCoords`` for ``OctahedralSphere``, written per lane in plain Python:
    an x outside the image mirrors x and flips y; then a y outside mirrors y and flips x. An
    index still outside after that (more than one image away, or W/H = 1) is clamped — pbrt
    leaves it undefined, the package documents the clamp."""
    xs, ys = [], []
    for a, b in zip(np.ravel(x).tolist(), np.ravel(y).tolist()):
        if a < 0:
            a, b = -a, h - 1 - b
        elif a >= w:
            a, b = 2 * w - 1 - a, h - 1 - b
        if b < 0:
            a, b = w - 1 - a, -b
        elif b >= h:
            a, b = w - 1 - a, 2 * h - 1 - b
        xs.append(min(max(a, 0), w - 1))
        ys.append(min(max(b, 0), h - 1))
    shape = np.shape(x)
    return np.array(xs, np.int64).reshape(shape), np.array(ys, np.int64).reshape(shape)


def texel(level, x, y, mode):
    h, w = level.shape[:2]
    if mode == 'octahedralsphere':
        xi, yi = octahedral(x, y, w, h)
        return level[yi, xi]
    xi, vx = wrap(x, w, mode)
    yi, vy = wrap(y, h, mode)
    v = level[yi, xi]
    return np.where((vx & vy)[..., None], v, 0.0)


def bilinear(level, s, t, mode):
    h, w = level.shape[:2]
    px, py = s * w - 0.5, t * h - 0.5
    x0, y0 = np.floor(px), np.floor(py)
    fx, fy = (px - x0)[..., None], (py - y0)[..., None]
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
    return ((1 - fx) * (1 - fy) * texel(level, x0, y0, mode) + fx * (1 - fy) * texel(level, x0 + 1, y0, mode)
            + (1 - fx) * fy * texel(level, x0, y0 + 1, mode) + fx * fy * texel(level, x0 + 1, y0 + 1, mode))


def trilinear(levels, s, t, width, mode):
    """pbrt-v3 trilinear: level = L-1 + log2(width) (width already in texture units)."""
    out = np.empty(np.shape(s) + (levels[0].shape[2],))
    L = len(levels)
    maxdim = max(levels[0].shape[:2])
    for k in range(len(s)):
        level = math.log2(max(width[k], 1e-8) * maxdim)
        if level <= 0:
            out[k] = bilinear(levels[0], s[k:k + 1], t[k:k + 1], mode)[0]
        elif level >= L - 1:
            out[k] = levels[-1][0, 0]
        else:
            i = int(math.floor(level))
            d = level - i
            out[k] = ((1 - d) * bilinear(levels[i], s[k:k + 1], t[k:k + 1], mode)[0]
                      + d * bilinear(levels[i + 1], s[k:k + 1], t[k:k + 1], mode)[0])
    return out


# ------------------------------------------------------------------------------------ EWA (pbrt)
WEIGHT_LUT = np.exp(-2.0 * np.arange(128) / 127.0) - np.exp(-2.0)


def _ewa_level(levels, lvl, s, t, d0, d1, mode, near):
    if lvl >= len(levels):
        return levels[-1][0, 0]
    img = levels[lvl]
    h, w = img.shape[:2]
    s, t = s * w - 0.5, t * h - 0.5
    ds0, dt0, ds1, dt1 = d0[0] * w, d0[1] * h, d1[0] * w, d1[1] * h
    A = dt0 ** 2 + dt1 ** 2 + 1
    B = -2 * (ds0 * dt0 + ds1 * dt1)
    C = ds0 ** 2 + ds1 ** 2 + 1
    inv_f = 1 / (A * C - B * B / 4)
    A, B, C = A * inv_f, B * inv_f, C * inv_f
    det = -B * B + 4 * A * C
    inv_det = 1 / det
    u_sqrt, v_sqrt = math.sqrt(det * C), math.sqrt(A * det)
    s0, s1 = math.ceil(s - 2 * inv_det * u_sqrt), math.floor(s + 2 * inv_det * u_sqrt)
    t0, t1 = math.ceil(t - 2 * inv_det * v_sqrt), math.floor(t + 2 * inv_det * v_sqrt)
    js, jt = np.meshgrid(np.arange(s0, s1 + 1), np.arange(t0, t1 + 1))
    ss, tt = js - s, jt - t
    r2 = A * ss * ss + B * ss * tt + C * tt * tt
    inside = r2 < 1
    # lookups whose result could depend on float rounding of r² (bucket edges) are flagged
    scaled = r2[inside] * 128
    if np.any(np.abs(scaled - np.round(scaled)) < 3e-4):
        near.append(True)
    idx = np.minimum((r2[inside] * 128).astype(int), 127)
    wts = WEIGHT_LUT[idx]
    vals = texel(img, js[inside], jt[inside], mode)
    return (wts[:, None] * vals).sum(0) / wts.sum()


def ewa(levels, s, t, dst0, dst1, max_aniso, mode):
    """pbrt's EWA, literally. Returns (values, ambiguous) where ambiguous marks lookups with a
    texel within float rounding of a table-bucket edge (where float32 and float64 may differ)."""
    n = len(s)
    out = np.empty((n, levels[0].shape[2]))
    ambiguous = np.zeros(n, bool)
    L = len(levels)
    maxdim = max(levels[0].shape[:2])
    for k in range(n):
        d0, d1 = np.array(dst0[k], float), np.array(dst1[k], float)
        if d0 @ d0 < d1 @ d1:
            d0, d1 = d1, d0
        major, minor = np.linalg.norm(d0), np.linalg.norm(d1)
        if minor * max_aniso < major and minor > 0:
            sc = major / (minor * max_aniso)
            d1 = d1 * sc
            minor *= sc
        if minor == 0:
            out[k] = bilinear(levels[0], s[k:k + 1], t[k:k + 1], mode)[0]
            continue
        raw_lod = math.log2(minor * maxdim)
        lod = min(max(0.0, raw_lod), float(L))
        il = int(math.floor(lod))
        near = []
        if abs(raw_lod - round(raw_lod)) < 1e-5 and 0 < raw_lod < L:
            near.append(True)
        a = _ewa_level(levels, il, s[k], t[k], d0, d1, mode, near)
        b = _ewa_level(levels, il + 1, s[k], t[k], d0, d1, mode, near) if lod - il > 0 else a
        out[k] = (1 - (lod - il)) * a + (lod - il) * b
        ambiguous[k] = bool(near)
    return out, ambiguous


# ------------------------------------------------------------------------------------ continuous
def gaussian_footprint(level0, s, t, dst0, dst1, mode, samples=96, cutoff=1.0, alpha=2.0):
    """∫ w(a,b) f(x + a·dst0 + b·dst1) / ∫ w over a² + b² < cutoff², w = exp(-α r²) - exp(-α c²):
    pbrt's Gaussian over the footprint ellipse, applied to the bilinear reconstruction of level 0,
    integrated with a midpoint rule on a samples×samples grid."""
    g = (np.arange(samples) + 0.5) / samples * 2 - 1
    a, b = np.meshgrid(g * cutoff, g * cutoff)
    r2 = a ** 2 + b ** 2
    keep = r2 < cutoff ** 2
    a, b, r2 = a[keep], b[keep], r2[keep]
    w = np.exp(-alpha * r2) - np.exp(-alpha * cutoff ** 2)
    out = np.empty((len(s), level0.shape[2]))
    for k in range(len(s)):
        ss = s[k] + a * dst0[k][0] + b * dst1[k][0]
        tt = t[k] + a * dst0[k][1] + b * dst1[k][1]
        out[k] = (w[:, None] * bilinear(level0, ss, tt, mode)).sum(0) / w.sum()
    return out
