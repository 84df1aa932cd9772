"""``python -m mitsuba_pbrt_tex bench pyramid``: MIP pyramids for non-power-of-two images.

Compares, by error and memory, the two ways to build a pyramid for an image whose sides are not
powers of two:

* ``lanczos-pow2`` — pbrt: resample up to the next power of two per axis with the separable
  4-tap windowed sinc ``sinc(x)·sinc(x/2)`` (repeat wrap, clamped at 0), then 2×2 boxes;
* ``area-box`` — ours (:mod:`mitsuba_pbrt_tex.mipmap`): halve each axis (floor) and average the
  exact area each coarse texel covers.

Error: trilinear lookups (the same code for both pyramids; level ``log2(width · maxres)``) at
random uv with square footprints of 2–16 texels, against the box average of the original image's
bilinear reconstruction over the same footprint (dense quadrature). Also reported: the error of a
plain bilinear lookup at level 0 (pbrt's resampled level 0 is not the original image; ours is),
and the memory of each pyramid relative to the original image.
"""

from __future__ import annotations

import math

import numpy as np


def _wrap(i, n):
    return np.mod(i, n)


def bilinear(img, s, t):
    h, w = img.shape[:2]
    px, py = s * w - 0.5, t * h - 0.5
    x0, y0 = np.floor(px).astype(int), np.floor(py).astype(int)
    fx, fy = (px - x0)[..., None], (py - y0)[..., None]
    g = lambda x, y: img[_wrap(y, h), _wrap(x, w)]
    return ((1 - fx) * (1 - fy) * g(x0, y0) + fx * (1 - fy) * g(x0 + 1, y0)
            + (1 - fx) * fy * g(x0, y0 + 1) + fx * fy * g(x0 + 1, y0 + 1))


def _lanczos_axis(img, n2, axis):
    n = img.shape[axis]
    if n2 == n:
        return img
    moved = np.moveaxis(img, axis, 0)
    out = np.zeros((n2,) + moved.shape[1:])
    for i in range(n2):
        center = (i + 0.5) * n / n2
        first = int(math.floor(center - 2 + 0.5))
        pos = first + np.arange(4) + 0.5
        x = pos - center
        wts = np.sinc(x) * np.sinc(x / 2)
        wts = wts / wts.sum()
        out[i] = np.tensordot(wts, moved[_wrap(first + np.arange(4), n)], axes=1)
    return np.moveaxis(out, 0, axis)


def lanczos_pow2_pyramid(img):
    h, w = img.shape[:2]
    W, H = 1 << max(0, math.ceil(math.log2(w))), 1 << max(0, math.ceil(math.log2(h)))
    base = np.maximum(_lanczos_axis(_lanczos_axis(img, W, 1), H, 0), 0)
    levels = [base]
    while levels[-1].shape[:2] != (1, 1):
        lv = levels[-1]
        hh, ww = lv.shape[:2]
        if ww > 1:
            lv = 0.5 * (lv[:, 0::2] + lv[:, 1::2])
        if hh > 1:
            lv = 0.5 * (lv[0::2] + lv[1::2])
        levels.append(lv)
    return levels


def area_box_pyramid(img):
    """Ours, via the package (Dr.Jit), read back as numpy levels."""
    import mitsuba as mi
    from ..mipmap import build_pyramid
    pyr = build_pyramid(mi.TensorXf(img.astype(np.float32)))
    upper = np.array(pyr.buffer, dtype=np.float64)
    off = pyr.offsets
    c, stride = img.shape[2], pyr.stride
    levels = [img.astype(np.float64)]
    for k, (w, h) in enumerate(pyr.sizes[1:], start=1):
        levels.append(upper[stride * off[k]: stride * (off[k] + w * h)].reshape(h, w, stride)[..., :c])
    return levels


def trilinear(levels, s, t, width):
    maxres = max(levels[0].shape[:2])
    out = np.empty((len(s), levels[0].shape[2]))
    for k in range(len(s)):
        level = math.log2(max(width[k], 1e-8) * maxres)
        if level <= 0:
            out[k] = bilinear(levels[0], s[k:k + 1], t[k:k + 1])[0]
        elif level >= len(levels) - 1:
            out[k] = levels[-1][0, 0]
        else:
            i = int(level)
            d = level - i
            out[k] = (1 - d) * bilinear(levels[i], s[k:k + 1], t[k:k + 1])[0] \
                + d * bilinear(levels[i + 1], s[k:k + 1], t[k:k + 1])[0]
    return out


def box_reference(img, s, t, width_uv, samples=40):
    g = (np.arange(samples) + 0.5) / samples - 0.5
    a, b = np.meshgrid(g, g)
    out = np.empty((len(s), img.shape[2]))
    for k in range(len(s)):
        out[k] = bilinear(img, s[k] + a.ravel() * width_uv[k], t[k] + b.ravel() * width_uv[k]).mean(0)
    return out


def test_images(rng):
    def smooth_noise(h, w, cycles):
        f = np.zeros((h, w), complex)
        ky, kx = np.meshgrid(np.fft.fftfreq(h) * h, np.fft.fftfreq(w) * w, indexing='ij')
        mask = np.hypot(kx, ky) < cycles
        f[mask] = rng.normal(size=mask.sum()) + 1j * rng.normal(size=mask.sum())
        x = np.real(np.fft.ifft2(f))
        return (0.5 + 0.2 * x / x.std())[..., None]

    def zone(h, w):
        y, x = np.mgrid[0:h, 0:w]
        r2 = ((x - w / 2) ** 2 + (y - h / 2) ** 2) / max(h, w)
        return (0.5 + 0.5 * np.cos(math.pi * r2 * 0.5))[..., None]

    return {'noise 37x53': smooth_noise(37, 53, 8), 'noise 300x200': smooth_noise(200, 300, 40),
            'zoneplate 384x384': zone(384, 384), 'noise 513x513': smooth_noise(513, 513, 60)}


def run(lookups=300, seed=3, out=print):
    import mitsuba as mi
    import mitsuba_pbrt_tex  # noqa: F401  (LLVM bootstrap)
    mi.set_variant('llvm_ad_rgb')
    rng = np.random.default_rng(seed)
    out('| image | pyramid | memory / image | trilinear RMSE (2-16 texel box footprints) '
        '| level-0 bilinear RMSE vs the original |')
    out('|---|---|---|---|---|')
    rows = []
    for name, img in test_images(rng).items():
        h, w = img.shape[:2]
        s, t = rng.random(lookups), rng.random(lookups)
        width_texels = np.exp(rng.uniform(math.log(2), math.log(16), lookups))
        width_uv = width_texels / max(h, w)
        ref = box_reference(img, s, t, width_uv)
        exact0 = bilinear(img, s, t)
        for kind, build in (('area-box (ours)', area_box_pyramid),
                            ('lanczos-pow2 (pbrt)', lanczos_pow2_pyramid)):
            levels = build(img)
            # memory of the pyramid relative to the image, with the same texel layout
            mem = sum(lv.size for lv in levels) / img.size
            rmse = float(np.sqrt(np.mean((trilinear(levels, s, t, width_uv) - ref) ** 2)))
            rmse0 = float(np.sqrt(np.mean((bilinear(levels[0], s, t) - exact0) ** 2)))
            out(f'| {name} | {kind} | {mem:.2f}× | {rmse:.4f} | {rmse0:.4f} |')
            rows.append(dict(image=name, pyramid=kind, memory=mem, rmse=rmse, rmse_level0=rmse0))
    return rows


def main(argv=None) -> int:
    from ..cli import command_parser, positive_int
    ap = command_parser('bench pyramid', __doc__)
    ap.add_argument('--lookups', type=positive_int, default=300,
                    help='random lookups per test image for the RMSE columns')
    args = ap.parse_args(argv)
    run(args.lookups)
    return 0
