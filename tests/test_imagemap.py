"""pbrt_imagemap: parity with Mitsuba's bitmap, filters against independent numpy references,
hard cases, errors, encodings, caching."""

import gc
import math
import os
import threading

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import reference_mipmap as ref
from conftest import A, assert_texel_gradients_match_fd, make_si
from mitsuba_pbrt_tex.image import image_cache
from mitsuba_pbrt_tex.mipmap import build_pyramid, level_sizes
from mitsuba_pbrt_tex.params import PluginError

DATA = os.path.join(os.path.dirname(__file__), 'data')
LUM = ref.LUM


def imagemap(data=None, **kw):
    d = {'type': 'pbrt_imagemap', **kw}
    if data is not None:
        d['data'] = mi.TensorXf(np.asarray(data, np.float32))
    return mi.load_dict(d)


def lookups(rng, n, lo=0.0, hi=1.0, footprint=None):
    """Random uv (float32-representable, so references see the same coordinates)."""
    uv = rng.uniform(lo, hi, (n, 2)).astype(np.float32).astype(np.float64)
    if footprint is None:
        return uv, make_si(uv)
    d0, d1 = footprint
    return uv, make_si(uv, duv_dx=d0, duv_dy=d1)


def aniso_footprints(rng, n, major_texels, minor_texels, res):
    """Derivative pairs of given axis lengths (texels of a res×res image), random orientation."""
    ang = rng.uniform(0, math.pi, n)
    d0 = np.stack([np.cos(ang), np.sin(ang)], 1) * major_texels / res
    d1 = np.stack([-np.sin(ang), np.cos(ang)], 1) * minor_texels / res
    return d0, d1


def smooth_noise(rng, res, channels=1, blur=2.0):
    """Band-limited periodic noise (Gaussian low-pass in frequency), roughly in [0, 1]."""
    f = np.fft.fftfreq(res)
    g = np.exp(-0.5 * (np.hypot(*np.meshgrid(f, f)) * res / (res / (4 * blur))) ** 2)
    out = []
    for _ in range(channels):
        x = np.real(np.fft.ifft2(np.fft.fft2(rng.normal(size=(res, res))) * g))
        out.append(0.5 + 0.15 * x / x.std())
    return np.stack(out, -1)


# ------------------------------------------------------------------------------------ parity
PARITY_FILES = ['rgb_13x17.exr', 'y_16x24.exr', 'srgb_11x9.png', 'gray_8x6.png']


@pytest.mark.parametrize('fname', PARITY_FILES)
@pytest.mark.parametrize('filt', ['nearest', 'bilinear'])
@pytest.mark.parametrize('wrap', ['repeat', 'mirror', 'clamp'])
def test_parity_with_bitmap(fname, filt, wrap, rng):
    """Same uv inside and outside [0,1]², zero differentials: ≤ 1e-6 (float32 rounding).
    The pbrt names (filter/wrap) and the bitmap aliases (filter_type/wrap_mode) both match."""
    path = os.path.join(DATA, fname)
    uv, si = lookups(rng, 4096, -1.5, 2.5)
    b = mi.load_dict({'type': 'bitmap', 'filename': path, 'filter_type': filt, 'wrap_mode': wrap})
    ours = [mi.load_dict({'type': 'pbrt_imagemap', 'filename': path,
                          'filter': 'point' if filt == 'nearest' else 'bilinear', 'wrap': wrap}),
            mi.load_dict({'type': 'pbrt_imagemap', 'filename': path, 'filter_type': filt,
                          'wrap_mode': wrap})]
    for o in ours:
        assert np.max(np.abs(A(b.eval(si)) - A(o.eval(si)))) <= 1e-6
        assert np.max(np.abs(A(b.eval_1(si)) - A(o.eval_1(si)))) <= 1e-6


def test_parity_with_bitmap_to_uv(rng):
    path = os.path.join(DATA, 'srgb_11x9.png')
    to_uv = mi.ScalarTransform4f().translate([0.3, -0.2, 0]) @ mi.ScalarTransform4f().scale([2.5, 1.5, 1])
    b = mi.load_dict({'type': 'bitmap', 'filename': path, 'to_uv': to_uv})
    o = mi.load_dict({'type': 'pbrt_imagemap', 'filename': path, 'to_uv': to_uv})
    _, si = lookups(rng, 2048, -1, 2)
    assert np.max(np.abs(A(b.eval(si)) - A(o.eval(si)))) <= 1e-6
    assert np.max(np.abs(A(b.eval_1_grad(si)) - A(o.eval_1_grad(si)))) <= 1e-4 * 11


def test_eval_1_grad_matches_bitmap_and_finite_differences(rng):
    path = os.path.join(DATA, 'rgb_13x17.exr')
    b = mi.load_dict({'type': 'bitmap', 'filename': path})
    o = mi.load_dict({'type': 'pbrt_imagemap', 'filename': path, 'filter': 'trilinear'})
    uv, si = lookups(rng, 512, 0.02, 0.98)
    np.testing.assert_allclose(A(o.eval_1_grad(si)), A(b.eval_1_grad(si)), rtol=1e-4, atol=1e-3)
    h = 1e-4
    f = lambda du, dv: A(o.eval_1(make_si(uv + [du, dv])))
    fd = np.stack([(f(h, 0) - f(-h, 0)) / (2 * h), (f(0, h) - f(0, -h)) / (2 * h)], 1)
    got = A(o.eval_1_grad(si))
    # away from texel-centre lines, where the bilinear gradient jumps
    px, py = uv[:, 0] * 17 - 0.5, uv[:, 1] * 13 - 0.5
    ok = (np.abs(px - np.round(px)) > 0.01) & (np.abs(py - np.round(py)) > 0.01)
    np.testing.assert_allclose(got[ok], fd[ok], rtol=2e-2, atol=0.05)


def test_rgba_keeps_rgb_and_png_encodings():
    path = os.path.join(DATA, 'rgba_5x7.png')
    bmp = mi.Bitmap(path)
    raw = np.array(bmp)[..., :3].astype(np.float64) / 255.0
    uv = np.stack(np.meshgrid((np.arange(7) + 0.5) / 7, (np.arange(5) + 0.5) / 5), -1).reshape(-1, 2)
    si = make_si(uv)
    srgb = np.where(raw <= 0.04045, raw / 12.92, ((raw + 0.055) / 1.055) ** 2.4).reshape(-1, 3)
    for params, want, tol in [({}, srgb, 1e-6), ({'encoding': 'sRGB'}, srgb, 1e-6),
                              ({'encoding': 'linear'}, raw.reshape(-1, 3), 1e-7),
                              ({'raw': True}, raw.reshape(-1, 3), 1e-7),
                              ({'encoding': 'gamma 2.2'}, raw.reshape(-1, 3) ** 2.2, 1e-6)]:
        o = mi.load_dict({'type': 'pbrt_imagemap', 'filename': path, 'filter': 'point', **params})
        np.testing.assert_allclose(A(o.eval(si)), want, atol=tol)


# ------------------------------------------------------------------------------------ pyramid
@pytest.mark.parametrize('channels', [1, 3])
@pytest.mark.parametrize('shape', [(1, 1), (1, 9), (9, 1), (37, 53), (64, 64), (48, 80)])
def test_pyramid_levels_match_reference(shape, channels, rng):
    img = rng.random(shape + (channels,))
    pyr = build_pyramid(mi.TensorXf(img.astype(np.float32)))
    want = ref.pyramid(img)
    assert pyr.sizes == [(lv.shape[1], lv.shape[0]) for lv in want] == level_sizes(shape[1], shape[0])
    buffer = np.array(pyr.buffer)                            # all levels, level 0 first
    offsets = np.cumsum([0] + [lv.shape[0] * lv.shape[1] for lv in want])  # level after level
    stride = pyr.stride                                      # RGB levels are stored RGBA-padded
    for k, lv in enumerate(want):
        h, w = lv.shape[:2]
        got = buffer[stride * offsets[k]: stride * (offsets[k] + w * h)].reshape(h, w, stride)
        np.testing.assert_allclose(got[..., :channels], lv, atol=2e-6)
        assert abs(got[..., :channels].mean() - img.mean()) < 2e-6  # area averages keep the mean
        assert np.all(got[..., channels:] == 0)
    # the pyramid (padded level 0 + coarser levels) is ≤ 4/3 of its padded base level
    padded_base = img.shape[0] * img.shape[1] * stride * 4
    assert pyr.nbytes() <= 1.34 * padded_base + 64


# ------------------------------------------------------------------------------------ filters
def test_zero_differentials_every_filter_is_bilinear_level0(rng):
    img = rng.random((32, 40, 3))
    uv, si = lookups(rng, 1000, -1, 2)
    bil = ref.bilinear(img, uv[:, 0], uv[:, 1], 'repeat')
    # float32 texel coordinates u·W - 0.5 carry rounding ≈ |u|·W·6e-8 ≈ 5e-6 texel here
    for f in ('bilinear', 'trilinear', 'ewa'):
        np.testing.assert_allclose(A(imagemap(img, filter=f).eval(si)), bil, atol=1e-5)


def test_magnification_equals_bilinear_level0(rng):
    img = rng.random((64, 64, 3))
    uv = rng.uniform(0, 1, (500, 2))
    d0, d1 = aniso_footprints(rng, 500, 0.4, 0.2, 64)          # well below one texel
    si = make_si(uv, d0, d1)
    bil = ref.bilinear(img, uv[:, 0], uv[:, 1], 'repeat')
    for f in ('bilinear', 'trilinear'):
        np.testing.assert_allclose(A(imagemap(img, filter=f).eval(si)), bil, atol=2e-6)


@pytest.mark.parametrize('wrap', ['repeat', 'black', 'clamp', 'mirror', 'octahedralsphere'])
@pytest.mark.parametrize('filt', ['point', 'bilinear', 'trilinear', 'ewa'])
def test_footprint_covering_texture_gives_mean(filt, wrap, rng):
    """Beyond the top level pbrt returns its single texel, the image mean — with every wrap
    (also black) and at any uv, inside [0, 1]² or not."""
    img = rng.random((32, 32, 3))
    tex = imagemap(img, filter=filt, wrap=wrap)
    tex.prepare_differentials()
    uv = rng.uniform(-2, 3, (50, 2))
    si = make_si(uv, np.tile([3.0, 0.0], (50, 1)), np.tile([0.0, 3.0], (50, 1)))
    np.testing.assert_allclose(A(tex.eval(si)), np.tile(img.mean((0, 1)), (50, 1)), atol=2e-6)


@pytest.mark.parametrize('convention,factor', [('v3', 1.0), ('v4', 2.0)])
@pytest.mark.parametrize('wrap', ['repeat', 'clamp', 'black', 'mirror'])
def test_trilinear_matches_reference(convention, factor, wrap, rng):
    img = rng.random((64, 48, 3))
    n = 400
    uv = rng.uniform(-0.5, 1.5, (n, 2))
    scale = np.exp(rng.uniform(np.log(0.1), np.log(80), n)) / 64
    d0, d1 = aniso_footprints(rng, n, 1.0, 0.4, 1.0)
    d0, d1 = d0 * scale[:, None], d1 * scale[:, None]
    tex = imagemap(img, filter='trilinear', trilinearwidth=convention, wrap=wrap)
    got = A(tex.eval(make_si(uv, d0, d1)))
    width = factor * np.max(np.abs(np.concatenate([d0, d1], 1)), axis=1)
    want = ref.trilinear(ref.pyramid(img), uv[:, 0], uv[:, 1], width, wrap)
    np.testing.assert_allclose(got, want, atol=5e-6)


@pytest.mark.parametrize('filt', ['point', 'bilinear'])
def test_single_level_filters_select_level_when_prepared(filt, rng):
    img = rng.random((64, 64, 3))
    tex = imagemap(img, filter=filt)
    uv = rng.uniform(0, 1, (200, 2))
    d = np.tile([[6.0 / 64, 0.0]], (200, 1))                  # width 6 texels → level 2 (v3)
    si = make_si(uv, d, np.zeros((200, 2)))
    lvl2 = ref.pyramid(img)[2]
    before = A(tex.eval(si))                                   # no pyramid yet: level 0
    if filt == 'bilinear':
        np.testing.assert_allclose(before, ref.bilinear(img, uv[:, 0], uv[:, 1], 'repeat'), atol=2e-6)
    assert tex.prepare_differentials()
    after = A(tex.eval(si))
    if filt == 'bilinear':
        np.testing.assert_allclose(after, ref.bilinear(lvl2, uv[:, 0], uv[:, 1], 'repeat'), atol=2e-6)
    else:
        x, y = np.floor(uv[:, 0] * 16).astype(int), np.floor(uv[:, 1] * 16).astype(int)
        np.testing.assert_allclose(after, lvl2[y, x], atol=2e-6)


PARALLEL_LOAD_SCRIPT = """
import numpy as np, mitsuba as mi, mitsuba_pbrt_tex
mi.set_variant('llvm_ad_rgb'); mitsuba_pbrt_tex.register()
texels = mi.TensorXf(np.random.default_rng(0).random((2048, 2048, 3)).astype(np.float32))
for load in range(12):
    scene = {'type': 'scene'}
    for i in range(16):
        scene[f's{i}'] = {'type': 'rectangle', 'bsdf': {'type': 'diffuse', 'reflectance': {
            'type': 'pbrt_imagemap', 'data': texels, 'filter': 'trilinear', 'scale': 1 + i}}}
    mi.load_dict(scene)
print('ok')
"""


def test_scenes_of_many_large_textures_load_in_parallel():
    """Mitsuba builds a scene's plugins on its worker threads. A pyramid build that waited for
    its kernels (to give its temporaries back) let the waiting thread run another texture's
    construction inside its own, and the two met in a kernel: jitc_assemble()'s scope error in
    about one load in five of 16 textures of 2048² (found in a user trial; 0 of 45 loads since
    builds wait only on the main thread). Twelve loads: without the fix this failed in about 9
    runs of 10."""
    import subprocess
    import sys
    r = subprocess.run([sys.executable, '-c', PARALLEL_LOAD_SCRIPT], capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0 and r.stdout.strip().endswith('ok'), r.stderr[-2000:]


@pytest.mark.parametrize('filt', ['point', 'bilinear'])
def test_single_level_filters_stay_at_level_0_whatever_else_builds_levels(filt, rng, tmp_path):
    """Before this texture is prepared for differentials, point and bilinear read level 0 —
    also once its pyramid holds every level because another texture of the same file (here a
    trilinear one) built them, or because gradients on its texels did (params.update()): the
    same lookup changed value with what else the process had loaded, and finite differences
    of fresh textures disagreed with gradients (found in a user trial). Reference: the numpy
    level-0 lookup; after prepare_differentials(), level 2 as above."""
    img = rng.random((64, 64, 3)).astype(np.float32)
    path = str(tmp_path / 'img.exr')
    mi.Bitmap(img).write(path)
    uv = rng.uniform(0, 1, (200, 2))
    si = make_si(uv, np.tile([[6.0 / 64, 0.0]], (200, 1)), np.zeros((200, 2)))
    if filt == 'bilinear':
        want = ref.bilinear(img, uv[:, 0], uv[:, 1], 'repeat')
    else:
        want = img[np.floor(uv[:, 1] * 64).astype(int), np.floor(uv[:, 0] * 64).astype(int)]
    tex = mi.load_dict({'type': 'pbrt_imagemap', 'filename': path, 'filter': filt})
    other = mi.load_dict({'type': 'pbrt_imagemap', 'filename': path, 'filter': 'trilinear'})
    np.testing.assert_allclose(A(tex.eval(si)), want, atol=2e-6)
    del other
    data = imagemap(img, filter=filt)
    params = mi.traverse(data)
    dr.enable_grad(params['data'])
    params.update()
    np.testing.assert_allclose(A(data.eval(si)), want, atol=2e-6)
    assert tex.prepare_differentials()
    assert np.abs(A(tex.eval(si)) - want).max() > 0.05        # level 2 now


@pytest.mark.parametrize('wrap', ['repeat', 'clamp', 'black', 'mirror'])
@pytest.mark.parametrize('max_aniso', [8.0, 32.0])
def test_ewa_matches_pbrt_literal(wrap, max_aniso, rng):
    """Our row-span EWA vs pbrt's bounding-box EWA in float64: ≤ 2e-5 (float32 accumulation of
    up to ~10³ weighted texels); lookups with a texel within rounding of a table-bucket edge,
    where float32 and float64 may pick different table entries, are excluded (a few percent)."""
    img = rng.random((64, 80, 3))
    n = 300
    uv = rng.uniform(-0.3, 1.3, (n, 2))
    major = np.exp(rng.uniform(np.log(0.3), np.log(60), n))
    ratio = np.exp(rng.uniform(0, np.log(40), n))
    ang = rng.uniform(0, math.pi, n)
    d0 = np.stack([np.cos(ang), np.sin(ang)], 1) * (major / 64)[:, None]
    d1 = np.stack([-np.sin(ang), np.cos(ang)], 1) * (major / ratio / 64)[:, None]
    swap = rng.random(n) < 0.5                                  # either vector may be the major
    d0[swap], d1[swap] = d1[swap].copy(), d0[swap].copy()
    tex = imagemap(img, filter='ewa', wrap=wrap, maxanisotropy=max_aniso)
    got = A(tex.eval(make_si(uv, d0, d1)))
    want, ambiguous = ref.ewa(ref.pyramid(img), uv[:, 0], uv[:, 1], d0, d1, max_aniso, wrap)
    assert ambiguous.mean() < 0.25
    np.testing.assert_allclose(got[~ambiguous], want[~ambiguous], atol=2e-5)


def test_filters_against_continuous_gaussian_reference(rng):
    """EWA and trilinear vs pbrt's Gaussian integrated densely over the footprint ellipse of the
    level-0 bilinear reconstruction (band-limited noise, 256², 8×1.5-texel footprints).

    A MIP filter cannot equal the continuous reference: coarse levels are box-prefiltered and
    EWA adds one texel² of blur at its level. For this texture (σ of the reference ≈ 0.035) the
    measured RMSEs are about 0.004 (EWA) and 0.02 (trilinear); we require EWA ≤ 0.01 (less than a
    third of the signal σ) and at least 2× better than trilinear, and both better than a point
    sample at level 0."""
    res = 256
    img = smooth_noise(rng, res, channels=1, blur=1.0)
    n = 300
    uv = rng.uniform(0, 1, (n, 2))
    d0, d1 = aniso_footprints(rng, n, 8.0, 1.5, res)
    gt = ref.gaussian_footprint(img, uv[:, 0], uv[:, 1], d0, d1, 'repeat')[:, 0]
    si = make_si(uv, d0, d1)
    rmse = {}
    for f in ('ewa', 'trilinear', 'bilinear'):
        tex = imagemap(img, filter=f)
        if f == 'bilinear':
            got = A(tex.eval_1(make_si(uv)))                    # point sample of level 0
        else:
            got = A(tex.eval_1(si))
        rmse[f] = float(np.sqrt(np.mean((got - gt) ** 2)))
    assert rmse['ewa'] <= 0.01
    assert rmse['ewa'] * 2 <= rmse['trilinear'] < rmse['bilinear']


def test_ewa_not_worse_than_openimageio_aniso(rng, tmp_path):
    """Against a Gaussian ground truth (pbrt's weight over the pixel footprint), our EWA with
    maxanisotropy 32 is at least as accurate as OpenImageIO's TextureSystem in Aniso mode
    (bilinear probes, same 2×2-box pyramid, anisotropy 32) on 20:1 footprints."""
    oiio = pytest.importorskip('OpenImageIO')
    res = 256
    img = smooth_noise(rng, res, channels=1, blur=0.7)[..., 0]
    buf = oiio.ImageBuf(oiio.ImageSpec(res, res, 1, oiio.FLOAT))
    buf.set_pixels(oiio.ROI(), img.astype(np.float32)[..., None])
    cfg = oiio.ImageSpec()
    cfg.attribute('wrapmodes', 'periodic,periodic')
    tx = str(tmp_path / 'noise.tx')
    assert oiio.ImageBufAlgo.make_texture(oiio.MakeTxTexture, buf, tx, cfg), oiio.geterror()
    ts = oiio.TextureSystem(shared=False)
    opt = oiio.TextureOpt()
    opt.mipmode = oiio.MipMode.Aniso
    opt.interpmode = oiio.InterpMode.Bilinear
    opt.swrap = opt.twrap = oiio.Wrap.Periodic
    opt.anisotropic = 32
    n = 250
    uv = rng.uniform(0, 1, (n, 2))
    d0, d1 = aniso_footprints(rng, n, 20.0, 1.0, res)
    gt = ref.gaussian_footprint(img[..., None], uv[:, 0], uv[:, 1], d0, d1, 'repeat')[:, 0]
    o = np.array([ts.texture(tx, opt, uv[k, 0], uv[k, 1], d0[k, 0], d0[k, 1], d1[k, 0], d1[k, 1], 1)[0]
                  for k in range(n)])
    ours = A(imagemap(img[..., None], filter='ewa', maxanisotropy=32).eval_1(make_si(uv, d0, d1)))
    rmse_o = np.sqrt(np.mean((o - gt) ** 2))
    rmse_us = np.sqrt(np.mean((ours - gt) ** 2))
    print(f'RMSE vs Gaussian GT: ours (EWA, 32) {rmse_us:.5f}, OpenImageIO Aniso {rmse_o:.5f}')
    assert rmse_us <= rmse_o


# ------------------------------------------------------------------------------------ hard cases
@pytest.mark.parametrize('shape', [(1, 1), (1, 7), (7, 1), (37, 53)])
@pytest.mark.parametrize('filt', ['point', 'bilinear', 'trilinear', 'ewa'])
@pytest.mark.parametrize('wrap', ['repeat', 'black', 'clamp', 'mirror', 'octahedralsphere'])
def test_hard_cases_stay_finite_and_in_range(shape, filt, wrap, rng):
    img = rng.random(shape + (3,))
    tex = imagemap(img, filter=filt, wrap=wrap)
    tex.prepare_differentials()
    inf, nan = float('inf'), float('nan')
    uv = np.array([[0.5, 0.5], [1e6, -1e6], [-1e6, 3e5], [nan, 0.2], [inf, -inf], [0.3, nan],
                   [0.0, 1.0], [1.0 - 1e-7, 1e-7], [2.5, -3.5], [0.25, 0.75]] * 3)
    n = len(uv)
    d0 = np.array([[0, 0], [nan, 1], [inf, 0], [1e-3, 1e-9], [1e8, 1e8], [0.01, 0.0], [1e-6, 0],
                   [0.3, 0.3], [1e30, -1e30], [0.02, 0.01]] * 3)
    d1 = np.array([[0, 0], [0, nan], [0, inf], [0, 0], [1e-8, 0], [0.0, 0.0], [0, 1e-12],
                   [-0.3, 0.3], [0, 1e-30], [-1e-8, 2e-8]] * 3)
    out = A(tex.eval(make_si(uv, d0, d1)))
    assert out.shape == (n, 3) and np.isfinite(out).all()
    lo = 0.0 if wrap == 'black' else img.min()
    assert (out >= lo - 1e-6).all() and (out <= img.max() + 1e-6).all()
    # where the value is known: rows 0 (uv (.5, .5), zero footprint) are the level-0 lookup
    # of the numpy reference (point: the texel containing uv; the others: bilinear; 2e-6 as
    # the level-0 tests); rows 4 (footprint 1e8 texture widths at uv ±inf) cover the
    # texture: pbrt's top level, the image mean, with every wrap (2e-6). (Not rows 8: a
    # 1e-30 minor axis squares to 0 in float32, where pbrt-v4's EWA returns a level-0 lookup.)
    h, w = shape
    if filt == 'point':
        zero = ref.texel(img, np.array([int(0.5 * w)]), np.array([int(0.5 * h)]), wrap)[0]
    else:
        zero = ref.bilinear(img, np.array([0.5]), np.array([0.5]), wrap)[0]
    np.testing.assert_allclose(out[0::10], np.tile(zero, (3, 1)), atol=2e-6)
    np.testing.assert_allclose(out[4::10], np.tile(img.mean((0, 1)), (3, 1)), atol=2e-6)


def test_anisotropy_clamp_widens_minor_axis(rng):
    """1e6:1 footprints are clamped to maxanisotropy: the result equals the EWA of the clamped
    footprint (minor lengthened to major / maxanisotropy)."""
    img = rng.random((64, 64, 3))
    n = 50
    uv = rng.uniform(0, 1, (n, 2))
    d0, d1 = aniso_footprints(rng, n, 16.0, 16e-6, 64)
    tex = imagemap(img, filter='ewa', maxanisotropy=8)
    got = A(tex.eval(make_si(uv, d0, d1)))
    clamped = A(tex.eval(make_si(uv, d0, d1 * 1e6 / 8)))
    np.testing.assert_allclose(got, clamped, atol=2e-6)


def test_black_wrap_fades_at_edges():
    img = np.ones((8, 8, 1))
    tex = imagemap(img, filter='bilinear', wrap='black')
    si = make_si([[0.5, 0.5], [0.0, 0.5], [-1.0 / 16, 0.5], [1.5, 0.5]])
    np.testing.assert_allclose(A(tex.eval_1(si)), [1.0, 0.5, 0.0, 0.0], atol=1e-6)


@pytest.mark.parametrize('scale', [1e-30, 1e30, -2.0])
def test_scale_and_invert(scale, rng):
    img = rng.random((8, 8, 3))
    uv, si = lookups(rng, 100)
    base = ref.bilinear(img, uv[:, 0], uv[:, 1], 'repeat')
    np.testing.assert_allclose(A(imagemap(img, scale=scale).eval(si)), scale * base,
                               rtol=1e-5, atol=1e-37)
    inv = A(imagemap(img, scale=scale, invert=True).eval(si))
    np.testing.assert_allclose(inv, np.maximum(0, 1 - scale * base), rtol=1e-5, atol=1e-6)
    assert np.isfinite(inv).all()


def test_nonfinite_texels_replaced_with_warning(capfd, rng):
    img = rng.random((4, 4, 3)).astype(np.float32)
    img[0, 0, 0] = np.nan
    img[1, 2, :] = np.inf
    tex = imagemap(img, filter='point')
    out = A(tex.eval(make_si([[0.125, 0.125], [0.625, 0.375]])))
    np.testing.assert_allclose(out, [[0, img[0, 0, 1], img[0, 0, 2]], [0, 0, 0]], atol=1e-7)
    captured = capfd.readouterr()
    assert '4 non-finite texel value(s) replaced by 0' in captured.out + captured.err


# ------------------------------------------------------------------------------------ errors
@pytest.mark.parametrize('params,words', [
    ({'filename': '/nonexistent/tex.png'}, ['"filename"', 'does not exist']),
    ({'filename': os.path.join(DATA, 'corrupt.png')}, ['"filename"', 'cannot read image file']),
    ({'data': mi.TensorXf(np.zeros((4, 4, 2), np.float32))}, ['"data"', 'shape (4, 4, 2)']),
    ({'data': mi.TensorXf(np.zeros((4, 4), np.float32))}, ['"data"', '(H, W, 3)']),
    ({}, ['exactly one of', '"filename", "bitmap", "data"']),
    ({'filename': os.path.join(DATA, 'srgb_11x9.png'), 'filter': 'cubic'},
     ['"filter"', '"cubic"', 'point, bilinear, trilinear, ewa']),
    ({'filename': os.path.join(DATA, 'srgb_11x9.png'), 'wrap': 'periodic'},
     ['"wrap"', 'repeat, black, clamp, mirror, octahedralsphere']),
    ({'filename': os.path.join(DATA, 'srgb_11x9.png'), 'wrap_mode': 'black'},
     ['"wrap_mode"', 'repeat, mirror, clamp']),
    ({'filename': os.path.join(DATA, 'srgb_11x9.png'), 'encoding': 'gamma'},
     ['"encoding"', 'sRGB, linear, gamma G']),
    ({'filename': os.path.join(DATA, 'srgb_11x9.png'), 'filter': 'ewa', 'filter_type': 'bilinear'},
     ['"filter"', 'alias "filter_type"']),
    ({'filename': os.path.join(DATA, 'srgb_11x9.png'), 'maxanisotropy': 0.5},
     ['"maxanisotropy"', '>= 1.0']),
    ({'filename': os.path.join(DATA, 'srgb_11x9.png'), 'encoding': 'linear', 'raw': True},
     ['"encoding"', 'alias "raw"']),
])
def test_bad_input_errors(params, words):
    with pytest.raises(RuntimeError) as e:
        mi.load_dict({'type': 'pbrt_imagemap', **params})
    msg = str(e.value)
    assert 'pbrt_imagemap' in msg
    for w in words:
        assert w in msg, (w, msg[-300:])


def test_parameter_update_rebuilds_pyramid_with_new_shape(rng):
    tex = imagemap(rng.random((16, 16, 3)), filter='trilinear')
    params = mi.traverse(tex)
    new = rng.random((8, 32, 1)).astype(np.float32)
    params['data'] = mi.TensorXf(new)
    params.update()
    assert tuple(tex.resolution()) == (32, 8)
    si = make_si([[0.3, 0.6]], [[1.0, 0]], [[0, 1.0]])        # covers everything → mean
    np.testing.assert_allclose(A(tex.eval_1(si)), [new.mean()], atol=2e-6)
    params['data'] = mi.TensorXf(np.zeros((4, 4, 2), np.float32))
    with pytest.raises(Exception, match='pbrt_imagemap: parameter "data"'):
        params.update()


# ------------------------------------------------------------------------------------ caching
def test_file_pyramid_shared_and_built_once_across_threads():
    image_cache.clear()
    path = os.path.join(DATA, 'rgb_13x17.exr')
    texs = [None] * 4

    def load(i):
        texs[i] = mi.load_dict({'type': 'pbrt_imagemap', 'filename': path, 'filter': 'ewa'})

    threads = [threading.Thread(target=load, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(image_cache) == 1
    assert len({id(t.pyramid) for t in texs}) == 1            # one pyramid, shared
    # a parameter update on one texture does not affect the others
    p = mi.traverse(texs[0])
    p['data'] = mi.TensorXf(np.zeros((13, 17, 3), np.float32))
    p.update()
    si = make_si([[0.5, 0.5]])
    assert A(texs[0].eval_1(si))[0] == 0 and A(texs[1].eval_1(si))[0] > 0


def test_files_read_records_every_image_file_textures_read(tmp_path):
    """``files_read()`` (which the command line uses to refuse outputs that would overwrite an
    input) collects the real path of each image file a texture reads, cached or not — here
    through a symbolic link, and twice — and nothing outside its block."""
    from mitsuba_pbrt_tex.image import files_read
    image_cache.clear()
    path = os.path.join(DATA, 'srgb_11x9.png')
    link = str(tmp_path / 'link.png')
    os.symlink(path, link)
    with files_read() as found:
        a = mi.load_dict({'type': 'pbrt_imagemap', 'filename': link})
        b = mi.load_dict({'type': 'pbrt_imagemap', 'filename': path})      # cached
    assert found == {os.path.realpath(path)}
    c = mi.load_dict({'type': 'pbrt_imagemap', 'filename': os.path.join(DATA, 'gray_8x6.png')})
    assert found == {os.path.realpath(path)}
    del a, b, c


def test_file_pyramids_are_built_once_and_served_to_later_textures(monkeypatch):
    """A file's pyramid is built on the first request and every later texture of the file gets
    that one: three bilinear textures (level 0 alone), two trilinear ones (every level), one
    more bilinear one (served by the complete pyramid) build two pyramids in all — counted by
    wrapping the package's ``build_pyramid`` — and share them."""
    import mitsuba_pbrt_tex.image as image
    calls, real = [], image.build_pyramid

    def counting(tensor, levels):
        calls.append(levels)
        return real(tensor, levels)

    monkeypatch.setattr(image, 'build_pyramid', counting)
    image_cache.clear()
    path = os.path.join(DATA, 'rgb_13x17.exr')

    def load(filt):
        return mi.load_dict({'type': 'pbrt_imagemap', 'filename': path, 'filter': filt})

    bil = [load('bilinear') for _ in range(3)]
    assert calls == [False] and len({id(t.pyramid) for t in bil}) == 1
    tri = [load('trilinear') for _ in range(2)]
    assert calls == [False, True] and tri[0].pyramid is tri[1].pyramid
    late = load('bilinear')
    assert calls == [False, True] and late.pyramid is tri[0].pyramid


def test_cache_forgets_a_file_when_its_last_texture_dies(tmp_path):
    """The cache holds decoded files weakly and drops a file's entry as its last texture dies,
    by itself: edited versions of a file loaded over a long session leave no entries behind.
    (The stored entries are read directly: ``len()`` and lookups would prune dead ones.)"""
    from mitsuba_pbrt_tex.outputs import write_exr
    image_cache.clear()
    path = str(tmp_path / 'img.exr')
    write_exr(path, np.random.default_rng(2).random((4, 5, 3)).astype(np.float32))
    tex = mi.load_dict({'type': 'pbrt_imagemap', 'filename': path})
    assert len(image_cache._entries) == 1
    del tex
    gc.collect()
    assert len(image_cache._entries) == 0


def test_scene_with_identical_textures_loads_in_parallel():
    """Eight textures of one file built on Mitsuba's worker threads. The load runs on a daemon
    thread that must finish within 120 s (it takes < 1 s): a deadlock fails the test instead of
    hanging the suite. Each loaded texture then equals Mitsuba's ``bitmap`` of the file (zero
    footprint: level-0 bilinear; ≤ 1e-6 as the parity tests), with its own uscale."""
    path = os.path.join(DATA, 'srgb_11x9.png')
    shapes = {f's{i}': {'type': 'sphere', 'center': [i, 0, 0], 'radius': 0.3,
                        'bsdf': {'type': 'diffuse', 'reflectance': {
                            'type': 'pbrt_imagemap', 'filename': path, 'filter': 'trilinear',
                            'uscale': float(1 + i % 2)}}} for i in range(8)}
    out = {}

    def load():
        try:
            out['scene'] = mi.load_dict({'type': 'scene', **shapes}, parallel=True)
        except Exception as e:          # reported below, on the test's thread
            out['error'] = e

    worker = threading.Thread(target=load, daemon=True)
    worker.start()
    worker.join(timeout=120)
    if worker.is_alive():
        pytest.fail('parallel scene load did not finish within 120 s (deadlock?)')
    assert 'error' not in out, out.get('error')
    scene = out['scene']
    assert len(scene.shapes()) == 8
    uv = np.random.default_rng(5).uniform(-1, 2, (64, 2))
    bitmap = mi.load_dict({'type': 'bitmap', 'filename': path})
    for shape in scene.shapes():
        reflectance = [c for c in _children(shape.bsdf()) if isinstance(c, mi.Texture)][0]
        uscale = 1.0 + (int(shape.id()[1:]) % 2)
        want = A(bitmap.eval(make_si(uv * [uscale, 1.0])))
        np.testing.assert_allclose(A(reflectance.eval(make_si(uv))), want, atol=1e-6)


def _children(obj):
    """Mitsuba objects directly referenced by ``obj`` (through its traversal)."""
    found = []

    class Collect(mi.TraversalCallback):
        def put(self, name, value, flags):
            if isinstance(value, mi.Object):
                found.append(value)
    obj.traverse(Collect())
    return found



def test_file_textures_without_pyramid_drop_their_copy_when_another_builds_it():
    """A bilinear and a trilinear texture of the same file share one RGBA copy of level 0: once
    the trilinear one builds the pyramid, whose buffer starts with level 0, the bilinear one
    reads that buffer too (the file's cache serves it; no second copy is kept alive) and matches
    Mitsuba's ``bitmap`` (≤ 1e-6, as in the parity tests) before and after."""
    image_cache.clear()
    path = os.path.join(DATA, 'rgb_13x17.exr')
    bitmap = mi.load_dict({'type': 'bitmap', 'filename': path})
    bil = mi.load_dict({'type': 'pbrt_imagemap', 'filename': path, 'filter': 'bilinear'})
    si = make_si(np.random.default_rng(3).uniform(-1, 2, (40, 2)))
    want = A(bitmap.eval(si))
    np.testing.assert_allclose(A(bil.eval(si)), want, atol=1e-6)
    tri = mi.load_dict({'type': 'pbrt_imagemap', 'filename': path, 'filter': 'trilinear'})
    assert bil.pyramid is tri.pyramid and tri.pyramid.complete
    np.testing.assert_allclose(A(bil.eval(si)), want, atol=1e-6)
    assert bil.pyramid.buffer.index == tri.pyramid.buffer.index

# ------------------------------------------------------------------------------------ gradients
@pytest.mark.parametrize('filt', ['point', 'bilinear', 'trilinear', 'ewa'])
def test_backward_reaches_texels_and_matches_finite_differences(filt, rng):
    """d(loss)/d(data) by dr.backward equals central differences of the loss (which is linear in
    the texels, so the differences are exact up to float32 rounding: rtol 1e-3)."""
    img = rng.random((8, 12, 3)).astype(np.float32)
    tex = imagemap(img, filter=filt)
    tex.prepare_differentials()
    n = 64
    uv = rng.uniform(0, 1, (n, 2))
    d0, d1 = aniso_footprints(rng, n, 3.0, 1.2, 12)
    si = make_si(uv, d0, d1)
    w = mi.Float(rng.random(n))
    assert_texel_gradients_match_fd(tex, img, si, w, rng)


def test_ewa_weight_matches_pbrt_table():
    """The computed weight equals pbrt's float32 table ``exp(-2·i/127) - exp(-2)`` at every r²
    of every bucket: the polynomial's relative error is 3.6e-7, so 1e-6 of the entry (plus
    float32 rounding of the difference) bounds it; entry 127 (r² ≥ 127/128) is excluded by the
    loop's mask and must be exactly where R2_MAX puts it."""
    from mitsuba_pbrt_tex.ewa import R2_MAX, lut_weight
    table = (np.exp(np.float32(-2) * np.arange(128, dtype=np.float32) / np.float32(127))
             - np.exp(np.float32(-2))).astype(np.float32)
    assert table[127] == 0 and R2_MAX == 127 / 128
    r2 = (np.arange(127)[:, None] + np.array([0.0, 0.25, 0.5, 0.999])[None, :]).ravel() / 128
    got = A(lut_weight(mi.Float(r2.astype(np.float32))))
    want = table[np.floor(r2.astype(np.float32) * 128).astype(int)]
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize('channels', [1, 3])
@pytest.mark.parametrize('filt', ['trilinear', 'ewa'])
def test_gradients_enabled_after_pyramid_reach_level0(filt, channels, rng):
    """The pyramid keeps a copy of level 0 in its buffer; gradients enabled on the tensor
    afterwards cannot reach the texels through it. A lookup does not rebuild the texture (it
    reads its state only), so without ``params.update()`` it is an error naming the fix — as
    inside a render's kernel —, and after it the gradient of a lookup with a footprint of 0.01
    texel (level 0) is its filter weights (they sum to 1 per lookup), not zero; the values
    still match the numpy references (bilinear at level 0 for trilinear, pbrt's literal EWA;
    tolerances as in their own tests)."""
    img = rng.random((16, 20, channels)).astype(np.float32)
    tex = imagemap(img, filter=filt)
    tex.prepare_differentials()
    uv = rng.uniform(0, 1, (50, 2))
    d0, d1 = np.tile([0.01 / 20, 0.0], (50, 1)), np.tile([0.0, 0.01 / 16], (50, 1))
    si = make_si(uv, d0, d1)
    img64 = img.astype(np.float64)
    if filt == 'trilinear':
        want, tol = ref.bilinear(img64, uv[:, 0], uv[:, 1], 'repeat'), 2e-6
    else:
        want, _ = ref.ewa(ref.pyramid(img64), uv[:, 0], uv[:, 1], d0, d1, 8.0, 'repeat')
        tol = 2e-5
    params = mi.traverse(tex)
    dr.enable_grad(params['data'])
    with pytest.raises(PluginError, match=r'pbrt_imagemap: parameter "data": gradients were '
                                           r'enabled on it after the texture was built.*'
                                           r'params\.update\(\)'):
        tex.eval(si)
    params.update()
    got = A(tex.eval(si)).reshape(50, -1)[:, :channels]      # 1 channel: grey RGB
    np.testing.assert_allclose(got, want, atol=tol)
    value = tex.eval_1(si)
    dr.backward(dr.sum(value))
    grad = np.array(dr.grad(params['data']))
    total = 50.0 if channels == 1 else 50.0 * float(np.sum(mi.luminance(mi.Color3f(1, 1, 1))))
    assert grad.sum() == pytest.approx(total, rel=1e-4)


def test_level_log2_accuracy():
    """Level selection's log2: within 2e-6 of float64 log2 over 16 decades (Dr.Jit's own
    ``log2`` is within 1e-6 here; float32 spacing at |log2| ≈ 27 is 2e-6), and exact at powers
    of two, where levels switch."""
    from mitsuba_pbrt_tex.mipmap import log2_positive
    x = np.exp(np.random.default_rng(0).uniform(np.log(1e-8), np.log(1e8), 100000)).astype(np.float32)
    np.testing.assert_allclose(A(log2_positive(mi.Float(x))), np.log2(x.astype(np.float64)),
                               rtol=0, atol=2e-6)
    powers = np.arange(-26, 27)
    assert np.array_equal(A(log2_positive(mi.Float((2.0 ** powers).astype(np.float32)))), powers)


# ------------------------------------------------------------------------------------ 16-bit, bitmap
def _texel_centres(w, h):
    uv = np.stack(np.meshgrid((np.arange(w) + 0.5) / w, (np.arange(h) + 0.5) / h), -1)
    return uv.reshape(-1, 2)


@pytest.mark.parametrize('raw', [False, True])
@pytest.mark.parametrize('source', ['file', 'bitmap'])
def test_16bit_png_and_bitmap_parameter_match_mitsuba_bitmap(source, raw, rng, tmp_path):
    """A 16-bit sRGB PNG (a full-range ramp plus noise, so the curve's linear toe and power
    segment are both sampled), given as a file or as an ``mi.Bitmap`` object, with and without
    ``raw``: texel centres and random bilinear lookups equal Mitsuba's ``bitmap`` with
    ``format = variant`` (float32 storage; by default it keeps 16-bit images as half floats,
    5e-4 relative), which decodes 16-bit sRGB with its own rational approximation of the curve
    (≤ 4.2e-7 from exact; float32 rounding of the bilinear weights adds ~1e-7): atol 2e-6.
    Skipping the decode is ≥ 0.1 off."""
    h, w = 9, 13
    px = rng.integers(0, 65536, (h, w, 3)).astype(np.uint16)
    px[0, :, 0] = np.linspace(0, 65535, w).astype(np.uint16)     # dark toe included
    bmp = mi.Bitmap(px, mi.Bitmap.PixelFormat.RGB)
    bmp.set_srgb_gamma(True)
    path = str(tmp_path / 'rgb16.png')
    bmp.write(path)
    assert mi.Bitmap(path).component_format() == mi.Struct.Type.UInt16
    common = {'raw': raw, 'filter_type': 'bilinear'}
    if source == 'file':
        theirs = mi.load_dict({'type': 'bitmap', 'filename': path, 'format': 'variant', **common})
        ours = mi.load_dict({'type': 'pbrt_imagemap', 'filename': path, **common})
    else:
        theirs = mi.load_dict({'type': 'bitmap', 'bitmap': mi.Bitmap(path), 'format': 'variant', **common})
        ours = mi.load_dict({'type': 'pbrt_imagemap', 'bitmap': mi.Bitmap(path), **common})
    uv = np.concatenate([_texel_centres(w, h), rng.uniform(-0.5, 1.5, (300, 2))])
    si = make_si(uv)
    want = A(theirs.eval(si))
    np.testing.assert_allclose(A(ours.eval(si)), want, atol=2e-6)
    # and the decode is the sRGB curve (or none), checked without Mitsuba at the texel centres
    v = px.reshape(-1, 3) / 65535.0
    curve = v if raw else np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)
    np.testing.assert_allclose(A(ours.eval(make_si(_texel_centres(w, h)))), curve, atol=2e-6)


@pytest.mark.parametrize('kind', ['uint8_srgb', 'float32', 'uint8_y'])
def test_bitmap_parameter_matches_mitsuba_bitmap(kind, rng):
    """The ``bitmap`` parameter with 8-bit sRGB RGB, float RGB and 8-bit luminance objects:
    equal to Mitsuba's ``bitmap`` given the same object (≤ 1e-6 as the file parity tests)."""
    h, w = 6, 10
    if kind == 'uint8_srgb':
        bmp = mi.Bitmap(rng.integers(0, 256, (h, w, 3)).astype(np.uint8), mi.Bitmap.PixelFormat.RGB)
        bmp.set_srgb_gamma(True)
    elif kind == 'uint8_y':
        bmp = mi.Bitmap(rng.integers(0, 256, (h, w, 1)).astype(np.uint8), mi.Bitmap.PixelFormat.Y)
        bmp.set_srgb_gamma(True)
    else:
        bmp = mi.Bitmap(rng.random((h, w, 3)).astype(np.float32), mi.Bitmap.PixelFormat.RGB)
    theirs = mi.load_dict({'type': 'bitmap', 'bitmap': bmp})
    ours = mi.load_dict({'type': 'pbrt_imagemap', 'bitmap': bmp})
    si = make_si(np.concatenate([_texel_centres(w, h), rng.uniform(-1, 2, (200, 2))]))
    np.testing.assert_allclose(A(ours.eval(si)), A(theirs.eval(si)), atol=1e-6)
    np.testing.assert_allclose(A(ours.eval_1(si)), A(theirs.eval_1(si)), atol=1e-6)


def _bitmap_of_kind(kind, rng, h, w):
    """An ``mi.Bitmap`` the user might build: pixel format, component type, sRGB flag."""
    PF = mi.Bitmap.PixelFormat
    fmt, comp, srgb = kind.split('_')
    channels = {'y': 1, 'ya': 2, 'rgb': 3, 'rgba': 4, 'xyz': 3}[fmt]
    if comp in ('u8', 'u16', 'u32'):
        bits = int(comp[1:])
        px = rng.integers(0, 2**bits, (h, w, channels), dtype=np.uint64).astype(f'uint{bits}')
    else:
        px = rng.uniform(0.0, 1.0, (h, w, channels)).astype({'f16': np.float16, 'f32': np.float32}[comp])
    bmp = mi.Bitmap(px, {'y': PF.Y, 'ya': PF.YA, 'rgb': PF.RGB, 'rgba': PF.RGBA, 'xyz': PF.XYZ}[fmt])
    bmp.set_srgb_gamma(srgb == 'srgb')
    return bmp


@pytest.mark.parametrize('kind', ['xyz_f32_lin', 'y_f32_lin', 'ya_f32_lin', 'ya_u8_srgb',
                                  'ya_u16_srgb', 'rgba_f16_lin', 'rgba_f32_lin', 'rgba_u8_srgb',
                                  'rgba_u16_srgb', 'rgb_f32_srgb', 'rgba_f32_srgb', 'rgb_u32_lin',
                                  'rgb_u8_lin', 'rgb_u16_lin', 'y_u8_lin', 'ya_u16_lin',
                                  'rgba_u8_lin', 'xyz_u8_srgb', 'xyz_u16_lin'])
def test_bitmap_objects_of_every_format_match_mitsuba_bitmap(kind, rng):
    """The ``bitmap`` parameter with the pixel formats and component types a user's
    ``mi.Bitmap`` may have — XYZ (converted to RGB), Y/YA, RGBA (alpha dropped), float16/32,
    8/16/32-bit integers flagged sRGB or not (``_lin``: ``srgb_gamma()`` False, as
    ``mi.Bitmap`` of a uint16 array is by default; Mitsuba reads them linear, v/255 or v/65535,
    where the package used to apply the sRGB curve: 0.2140 for a uint16 32768, 0.5000 in
    ``bitmap``), and float pixels flagged sRGB (which Mitsuba linearises) — equals
    Mitsuba's ``bitmap`` given the same object, at texel centres and random bilinear lookups
    (``eval`` and ``eval_1``). ``format = variant`` keeps Mitsuba's texels in float32 (by default
    it stores integer images as float16, 5e-4 relative). Mitsuba decodes sRGB codes with its
    rational approximation of the curve (≤ 4.2e-7 from the exact one the package applies to
    16-bit codes), and float32 rounding of the bilinear weights adds ~1e-7: atol 2e-6, as for
    16-bit files; the other kinds go through the same ``Bitmap.convert`` and agree to rounding.
    The wrong conversions are ≥ 1e-3 off (a 16-bit image cut to 8 bits, float texels left in
    sRGB, XYZ read as RGB, 32-bit codes not normalised) or refused (alpha left in).

    The user's bitmap is theirs: constructing the texture leaves its pixels as they were, and
    changing them afterwards does not change the texture."""
    h, w = 5, 7
    bmp = _bitmap_of_kind(kind, rng, h, w)
    before, fmt = np.array(bmp, copy=True), bmp.pixel_format()
    theirs = mi.load_dict({'type': 'bitmap', 'bitmap': bmp, 'format': 'variant'})
    ours = mi.load_dict({'type': 'pbrt_imagemap', 'bitmap': bmp})
    np.testing.assert_array_equal(np.array(bmp, copy=True), before)
    assert bmp.pixel_format() == fmt
    si = make_si(np.concatenate([_texel_centres(w, h), rng.uniform(-1, 2, (200, 2))]))
    got = A(ours.eval(si))
    np.testing.assert_allclose(got, A(theirs.eval(si)), atol=2e-6)
    np.testing.assert_allclose(A(ours.eval_1(si)), A(theirs.eval_1(si)), atol=2e-6)
    view = np.array(bmp, copy=False)            # the user's own pixels, written in place
    view[...] = 0
    assert not np.array(bmp, copy=True).any()
    np.testing.assert_array_equal(A(ours.eval(si)), got)


@pytest.mark.parametrize('raw', [False, True])
@pytest.mark.parametrize('filt', ['nearest', 'bilinear'])
@pytest.mark.parametrize('kind', ['rgb_u8_srgb', 'rgb_u8_lin', 'rgb_u16_srgb', 'rgb_u16_lin',
                                  'rgb_f32_srgb', 'rgb_f32_lin', 'y_u8_lin', 'ya_u16_srgb'])
def test_bitmap_objects_srgb_flag_and_raw_match_mitsuba_bitmap(kind, filt, raw, rng):
    """What a ``mi.Bitmap``'s values mean is its ``srgb_gamma()`` flag, for integer and float
    pixels alike, and ``raw`` keeps the stored values: Mitsuba's ``bitmap`` reads a flagged
    bitmap through the sRGB curve and an unflagged one (or any with ``raw``) as v/255, v/65535
    or the float value. The package decoded every 8/16-bit bitmap as sRGB (0.2159 for a uint8
    128 not flagged, ``bitmap`` 0.5020) and decoded a flagged float bitmap even with ``raw``
    (0.2140 for 0.5, ``bitmap`` 0.5). Reference: ``bitmap`` given an identical bitmap of its
    own (``bitmap`` with ``raw`` clears the flag of the bitmap it is given; ours leaves the
    caller's as it was), ``format = variant`` (float32 texels), nearest and bilinear lookups at
    texel centres and random uv: atol 2e-6, as above (Mitsuba's rational sRGB curve for 16-bit
    codes, ≤ 4.2e-7; float32 rounding of bilinear weights); a wrong decode is ≥ 1e-3 off."""
    h, w = 5, 7
    seed = int(rng.integers(2**31))
    theirs_bmp = _bitmap_of_kind(kind, np.random.default_rng(seed), h, w)
    ours_bmp = _bitmap_of_kind(kind, np.random.default_rng(seed), h, w)
    flag = ours_bmp.srgb_gamma()
    theirs = mi.load_dict({'type': 'bitmap', 'bitmap': theirs_bmp, 'format': 'variant',
                           'raw': raw, 'filter_type': filt})
    ours = mi.load_dict({'type': 'pbrt_imagemap', 'bitmap': ours_bmp, 'raw': raw,
                         'filter_type': filt})
    assert ours_bmp.srgb_gamma() == flag
    si = make_si(np.concatenate([_texel_centres(w, h), rng.uniform(-1, 2, (300, 2))]))
    np.testing.assert_allclose(A(ours.eval(si)), A(theirs.eval(si)), atol=2e-6)
    np.testing.assert_allclose(A(ours.eval_1(si)), A(theirs.eval_1(si)), atol=2e-6)


def test_linear_integer_bitmaps_of_the_user_trial_read_as_bitmap_reads_them():
    """The user trial's values: a uint16 ``mi.Bitmap`` of 32768 (not flagged sRGB, numpy's
    default) reads 32768/65535 and a uint8 128 after ``set_srgb_gamma(False)`` reads 128/255, as
    in ``bitmap`` (before: 0.2140 and 0.2159, the sRGB curve)."""
    b16 = mi.Bitmap(np.full((4, 4, 3), 32768, np.uint16))
    b8 = mi.Bitmap(np.full((4, 4, 3), 128, np.uint8))
    b8.set_srgb_gamma(False)
    si = make_si([[0.5, 0.5]])
    for bmp, want in ((b16, 32768 / 65535), (b8, 128 / 255)):
        got = A(mi.load_dict({'type': 'pbrt_imagemap', 'bitmap': bmp}).eval(si))
        np.testing.assert_allclose(got, want, rtol=1e-6)
        ref = A(mi.load_dict({'type': 'bitmap', 'bitmap': bmp}).eval(si))
        np.testing.assert_allclose(got, ref, rtol=5e-4)    # bitmap keeps 16-bit as float16


def test_bad_texels_of_a_bitmap_object_are_fixed_in_the_texture_not_in_the_bitmap(capfd):
    """A user's float32 RGB bitmap with NaN, ±inf, values beyond ±1e38 (two above, one below)
    and two exactly at ±1e38: the texture reads 0 for the non-finite texels and ±1e38 for the
    clamped ones (numpy's ``where``/``clip`` on the same pixels; nearest lookups at texel
    centres return texels exactly), and warns with the counts (3 non-finite, 3 clamped — the
    texels at the limits are not clamped), while the bitmap keeps every value it had, NaNs
    included: the repairs are made on the package's copy. (Mitsuba's ``bitmap`` is no
    reference here: it keeps the NaNs.)"""
    px = np.random.default_rng(5).uniform(0, 1, (3, 4, 3)).astype(np.float32)
    px[0, 0, 0], px[1, 2, 1], px[2, 3, 2], px[2, 1, 0] = np.nan, np.inf, -np.inf, 3e38
    px[0, 3, 1], px[1, 0, 2], px[2, 2, 1], px[1, 1, 1] = -2e38, 1.5e38, 1e38, -1e38
    bmp = mi.Bitmap(px, mi.Bitmap.PixelFormat.RGB)
    ours = mi.load_dict({'type': 'pbrt_imagemap', 'bitmap': bmp, 'filter': 'point'})
    np.testing.assert_array_equal(np.array(bmp, copy=True), px)    # NaNs compare equal here
    want = np.clip(np.where(np.isfinite(px), px, 0), -1e38, 1e38).reshape(-1, 3)
    np.testing.assert_array_equal(A(ours.eval(make_si(_texel_centres(4, 3)))), want)
    np.testing.assert_array_equal(np.array(mi.traverse(ours)['data']).reshape(-1, 3), want)
    captured = capfd.readouterr()
    log = captured.out + captured.err
    assert '3 non-finite texel value(s) replaced by 0' in log
    assert '3 texel value(s) beyond ±1e38 clamped' in log


@pytest.mark.parametrize('shape, invert', [((1100, 1000, 3), False), ((1100, 1000, 3), True),
                                           ((1500, 1000, 1), False)])
def test_mean_of_images_larger_than_a_reduction_chunk(shape, invert, rng):
    """mean() of images over 2^20 texels, which construction reduces a chunk at a time (so that
    the reduction holds no copy of the image): every chunk counts. Against numpy's float64 mean
    of the luminance (or channel) of the texels, inverted as lookups invert (max(0, 1 - v)).
    float32 sums of ~10^6 values per chunk: rtol 1e-5."""
    img = rng.random(shape).astype(np.float32)
    tex = mi.load_dict({'type': 'pbrt_imagemap', 'data': mi.TensorXf(img), 'invert': invert})
    v = img.astype(np.float64)
    if invert:
        v = np.maximum(0, 1 - v)
    want = (v @ [0.212671, 0.715160, 0.072169]).mean() if shape[2] == 3 else v.mean()
    np.testing.assert_allclose(A(tex.mean())[0], want, rtol=1e-5)


# ------------------------------------------------------------------------------------ eval_1_grad
@pytest.mark.parametrize('filt,convention', [('trilinear', 'v3'), ('trilinear', 'v4'),
                                             ('bilinear', 'v3')])
def test_eval_1_grad_with_footprint_matches_finite_differences(filt, convention, rng):
    """``eval_1_grad`` with non-zero footprints (what ``bumpmap`` gets under ``pbrt_path``): the
    central difference of ``eval_1`` in u and v with the footprint held fixed, through a uv
    mapping with scale and a rotating ``to_uv`` (so the st→uv Jacobian matters). Footprints put
    the level between 1.2 and 3.8, so the trilinear result blends two levels with a fractional
    weight, each level with its own texel size. h = 1e-4 in uv (≤ 0.02 texel at level 0);
    lookups within 0.03 texel of a texel-centre line of any level (where the bilinear gradient
    jumps) are excluded; the difference of a piecewise-bilinear function there is exact up to
    float32 rounding of eval_1 (~6e-8 / 2e-4 ≈ 3e-4 absolute): rtol 1e-2, atol 2e-3."""
    res = 64
    img = rng.random((res, res, 3))
    to_uv = mi.ScalarTransform4f().rotate([0, 0, 1], 25)
    tex = mi.load_dict({'type': 'pbrt_imagemap', 'data': mi.TensorXf(img.astype(np.float32)),
                        'filter': filt, 'trilinearwidth': convention, 'uscale': 1.5,
                        'vscale': 0.75, 'to_uv': to_uv})
    tex.prepare_differentials()
    n = 400
    uv = rng.uniform(0.1, 0.9, (n, 2))
    factor = 2.0 if convention == 'v4' else 1.0
    level = rng.uniform(1.2, 3.8, n)
    width_st = 2.0 ** level / res / factor               # max |d(st)| that selects the level
    # st derivatives (ds/dx, dt/dx) = (width, 0.3 width), (ds/dy, dt/dy) = (-0.4 w, 0.2 w),
    # mapped back to uv through the inverse of the mapping's 2×2 matrix
    M = np.diag([1.5, 0.75]) @ np.array(to_uv.matrix)[:2, :2]
    Minv = np.linalg.inv(M)
    dst_x = np.stack([width_st, 0.3 * width_st], 1)
    dst_y = np.stack([-0.4 * width_st, 0.2 * width_st], 1)
    d0, d1 = dst_x @ Minv.T, dst_y @ Minv.T
    h = 1e-4

    def f(shift):
        return A(tex.eval_1(make_si(uv + shift, d0, d1)))

    fd = np.stack([(f([h, 0]) - f([-h, 0])) / (2 * h), (f([0, h]) - f([0, -h])) / (2 * h)], 1)
    got = A(tex.eval_1_grad(make_si(uv, d0, d1)))
    st = uv @ M.T + np.array(to_uv.matrix)[:2, 3] * [1.5, 0.75]
    ok = np.ones(n, bool)
    for lv in range(0, 7):
        size = res >> lv
        for c in range(2):
            p = st[:, c] * size - 0.5
            ok &= np.abs(p - np.round(p)) > 0.03
    assert ok.sum() > 100
    np.testing.assert_allclose(got[ok], fd[ok], rtol=1e-2, atol=2e-3)


@pytest.mark.parametrize('filt', ['ewa', 'box'])
def test_eval_1_grad_of_ewa_and_box_is_pbrts_bump_difference(filt, rng):
    """``ewa`` and ``box`` values are not smooth on the texel scale (EWA's table weights; the
    box average's slope changes where its outline crosses a texel), so with differentials their
    ``eval_1_grad`` is pbrt-v4's ``BumpMap`` forward difference of the filtered value, computed
    here from the texture's own ``eval_1``: du = (|du/dx| + |du/dy|)/2 (0.0005 where that is 0),
    uv + (du, 0) and p + du·dp/du, the differentials kept; likewise in v. It was trilinear's
    gradient whatever the filter (found in a user trial: a bump map shaded the same through
    trilinear, EWA and box). Lanes without differentials keep the exact level-0 bilinear
    gradient, which is bitmap's (both filters are that bilinear lookup there). The same lookups
    at the same float32 uv (the shift added in float32, as the texture does): equal to float32
    rounding of the quotient (rtol 1e-5)."""
    res = 32
    img = rng.random((res, res, 3)).astype(np.float32)
    tex = mi.load_dict({'type': 'pbrt_imagemap', 'data': mi.TensorXf(img), 'filter': filt,
                        'uscale': 2.0})
    tex.prepare_differentials()
    n = 300
    f32 = np.float32
    uv = rng.uniform(0.05, 0.9, (n, 2)).astype(f32)
    d0 = (rng.uniform(-3, 3, (n, 2)) / res).astype(f32)
    d1 = (rng.uniform(-3, 3, (n, 2)) / res).astype(f32)
    d0[:40] = d1[:40] = 0                       # no differentials
    d0[40:80, 0] = d1[40:80, 0] = 0             # none in u: du = 0.0005 there
    p = np.concatenate([uv, np.zeros((n, 1), f32)], 1)
    dp_du, dp_dv = [1, 0, 0], [0, 1, 0]
    si = make_si(uv, d0, d1, p=p, dp_du=dp_du, dp_dv=dp_dv)
    f = A(tex.eval_1(si))
    want = np.zeros((n, 2))
    for axis in (0, 1):
        d = f32(0.5) * (np.abs(d0[:, axis]) + np.abs(d1[:, axis]))
        d = np.where(d > 0, d, f32(0.0005))
        shift = np.zeros((n, 2), f32)
        shift[:, axis] = d
        moved = make_si(uv + shift, d0, d1, p=p + np.concatenate([shift, np.zeros((n, 1), f32)],
                                                                 1), dp_du=dp_du, dp_dv=dp_dv)
        want[:, axis] = (A(tex.eval_1(moved)) - f) / d
    got = A(tex.eval_1_grad(si))
    np.testing.assert_allclose(got[40:], want[40:], rtol=1e-5, atol=1e-5)
    bitmap = mi.load_dict({'type': 'bitmap', 'data': mi.TensorXf(img), 'raw': True,
                           'to_uv': mi.ScalarTransform4f().scale([2, 1, 1])})
    np.testing.assert_allclose(got[:40], A(bitmap.eval_1_grad(make_si(uv[:40]))), rtol=1e-4,
                               atol=1e-4 * 2 * res)
    # not trilinear's: the filters differ
    tri = mi.load_dict({'type': 'pbrt_imagemap', 'data': mi.TensorXf(img),
                        'filter': 'trilinear', 'uscale': 2.0})
    tri.prepare_differentials()
    assert np.median(np.abs(got[80:] - A(tri.eval_1_grad(si))[80:])) > 0.1


@pytest.mark.parametrize('invert', [False, True])
def test_eval_1_grad_of_point_filter_is_zero_like_bitmap_nearest(invert, rng):
    """``filter="point"`` is piecewise constant: ``eval_1_grad`` is 0 with or without a
    footprint, as Mitsuba's ``bitmap`` with ``filter_type="nearest"`` returns (RGB image, so the
    luminance path runs; ``invert`` reads the value too)."""
    img = mi.TensorXf(rng.random((16, 16, 3)).astype(np.float32))
    ours = mi.load_dict({'type': 'pbrt_imagemap', 'data': img, 'filter': 'point',
                         'invert': invert})
    ours.prepare_differentials()
    theirs = mi.load_dict({'type': 'bitmap', 'data': img, 'filter_type': 'nearest',
                           'raw': True})
    n = 200
    uv = rng.uniform(0, 1, (n, 2))
    d = np.concatenate([np.zeros((n // 2, 2)), rng.uniform(-0.2, 0.2, (n - n // 2, 2))])
    si = make_si(uv, d, d[::-1])
    want = A(theirs.eval_1_grad(make_si(uv)))             # Mitsuba returns a literal 0
    assert np.all(want == 0)
    got = A(ours.eval_1_grad(si))
    np.testing.assert_array_equal(got, np.broadcast_to(want, got.shape))


@pytest.mark.parametrize('filt', ['bilinear', 'trilinear', 'ewa'])
def test_eval_1_grad_beyond_the_top_level_is_zero(filt, rng):
    """A footprint wider than the image selects the 1×1 top level, a constant: its gradient is
    0 (a level below the top — 2×2 texels of random values — would give |grad| ~ 0.1–1)."""
    img = mi.TensorXf(rng.random((32, 32, 3)).astype(np.float32))
    tex = mi.load_dict({'type': 'pbrt_imagemap', 'data': img, 'filter': filt})
    tex.prepare_differentials()
    n = 100
    uv = rng.uniform(0, 1, (n, 2))
    width = rng.uniform(2, 50, n)
    si = make_si(uv, np.stack([width, 0 * width], 1), np.stack([0 * width, width], 1))
    np.testing.assert_allclose(A(tex.eval_1_grad(si)), 0, atol=1e-6)


@pytest.mark.parametrize('convention,factor', [('v3', 1.0), ('v4', 2.0)])
@pytest.mark.parametrize('filt', ['point', 'bilinear'])
def test_single_level_filters_select_level_under_anisotropic_footprints(filt, convention, factor,
                                                                         rng):
    """Random anisotropic footprints (ratio up to 20, any orientation, either vector the major,
    widths 0.3–80 texels) on a non-square 48×80 image: pbrt-v4's single-level rule, written here
    from the text — width = factor·max(|ds/dx|, |dt/dx|, |ds/dy|, |dt/dy|), level
    floor(log2(width·max(W, H))) clamped to [0, L-1] — then a point (Mitsuba's floor rule) or
    bilinear lookup at that level of the reference pyramid. Lookups within 1e-4 of a level
    boundary (float32 log2) are excluded; the rest match to 1e-5 (float32 texel coordinates
    u·W - 0.5 with |u| ≤ 1.5 carry ~1.5·80·6e-8 ≈ 7e-6 texel of rounding, as in
    test_zero_differentials_every_filter_is_bilinear_level0). A rule
    that uses the minor axis, the mean of the axes, or max(W, H) → min, picks other levels."""
    img = rng.random((48, 80, 3))
    tex = imagemap(img, filter=filt, trilinearwidth=convention)
    assert tex.prepare_differentials()
    n = 500
    uv = rng.uniform(-0.5, 1.5, (n, 2))
    major = np.exp(rng.uniform(np.log(0.3), np.log(80), n))
    ratio = np.exp(rng.uniform(0, np.log(20), n))
    ang = rng.uniform(0, math.pi, n)
    d0 = np.stack([np.cos(ang), np.sin(ang)], 1) * (major / 80)[:, None]
    d1 = np.stack([-np.sin(ang), np.cos(ang)], 1) * (major / ratio / 80)[:, None]
    swap = rng.random(n) < 0.5
    d0[swap], d1[swap] = d1[swap].copy(), d0[swap].copy()
    got = A(tex.eval(make_si(uv, d0, d1)))
    levels = ref.pyramid(img)
    width = factor * np.abs(np.concatenate([d0, d1], 1)).max(1)
    level = np.log2(width * 80)
    il = np.clip(np.floor(level), 0, len(levels) - 1).astype(int)
    clear = np.abs(level - np.round(level)) > 1e-4
    want = np.empty((n, 3))
    for k in range(n):
        lv = levels[il[k]]
        if filt == 'bilinear':
            want[k] = ref.bilinear(lv, uv[k:k + 1, 0], uv[k:k + 1, 1], 'repeat')[0]
        else:
            hh, ww = lv.shape[:2]
            want[k] = ref.texel(lv, np.floor(uv[k, 0] * ww).astype(int),
                                np.floor(uv[k, 1] * hh).astype(int), 'repeat')
    assert clear.mean() > 0.95 and len(set(il[clear])) >= 5
    np.testing.assert_allclose(got[clear], want[clear], atol=1e-5)


@pytest.mark.parametrize('mapping', ['planar', 'spherical'])
def test_eval_1_grad_with_3d_mappings_matches_finite_differences(mapping, rng):
    """``eval_1_grad`` through a mapping of p (not of uv): on a surface p(u, v) = p0 + u·dp_du +
    v·dp_dv, the gradient in (u, v) is the central difference of ``eval_1`` as u, v move (and
    p with them). h = 1e-4; lookups within 0.1 texel of a texel-centre line are excluded (the
    bilinear gradient jumps there, and a step of h moves the spherical st by up to ~0.05
    texel); float32 rounding of eval_1 gives ~6e-8/2e-4 ≈ 3e-4 absolute: rtol 1e-2 and atol
    1e-3 of the largest gradient (~10 here)."""
    res = 32
    img = rng.random((res, res, 3))
    kw = ({'v1': mi.ScalarVector3f(1.0, 0.5, 0.0), 'v2': mi.ScalarVector3f(-0.3, 1.0, 0.2)}
          if mapping == 'planar' else {})
    tex = mi.load_dict({'type': 'pbrt_imagemap', 'data': mi.TensorXf(img.astype(np.float32)),
                        'filter': 'bilinear', 'mapping': mapping, **kw})
    n = 300
    p0 = np.array([0.3, -0.2, 0.9])
    dp_du, dp_dv = np.array([0.8, 0.1, -0.2]), np.array([-0.1, 0.7, 0.3])
    uv = rng.uniform(0, 1, (n, 2))

    def si_at(uv_):
        p = p0 + uv_[:, :1] * dp_du + uv_[:, 1:] * dp_dv
        return make_si(uv_, p=p, dp_du=dp_du, dp_dv=dp_dv)

    h = 1e-4
    f = lambda shift: A(tex.eval_1(si_at(uv + shift)))
    fd = np.stack([(f([h, 0]) - f([-h, 0])) / (2 * h), (f([0, h]) - f([0, -h])) / (2 * h)], 1)
    got = A(tex.eval_1_grad(si_at(uv)))
    # texel-centre lines: from the mapping's own st, recomputed in numpy
    p = p0 + uv[:, :1] * dp_du + uv[:, 1:] * dp_dv
    if mapping == 'planar':
        s_, t_ = p @ [1.0, 0.5, 0.0], p @ [-0.3, 1.0, 0.2]
    else:
        r = np.linalg.norm(p, axis=1)
        s_ = np.arccos(p[:, 2] / r) / math.pi
        t_ = np.mod(np.arctan2(p[:, 1], p[:, 0]), 2 * math.pi) / (2 * math.pi)
    ok = np.ones(n, bool)
    for c in (s_, t_):
        q = c * res - 0.5
        ok &= np.abs(q - np.round(q)) > 0.1
    assert ok.sum() > 80 and np.abs(fd[ok]).max() > 1
    np.testing.assert_allclose(got[ok], fd[ok], rtol=1e-2, atol=1e-3 * np.abs(fd[ok]).max())


def test_gamma_encodings_of_one_file_stay_apart():
    """Textures of one PNG with ``gamma 2.2``, ``gamma 0.5`` and ``sRGB`` (cached per file and
    encoding): each decodes with its own curve, (v/255)^G or sRGB, computed here from the raw
    bytes (1e-6, float32 rounding); ``gamma 0`` is refused."""
    image_cache.clear()
    path = os.path.join(DATA, 'rgba_5x7.png')
    raw = np.array(mi.Bitmap(path))[..., :3].astype(np.float64).reshape(-1, 3) / 255.0
    uv = np.stack(np.meshgrid((np.arange(7) + 0.5) / 7, (np.arange(5) + 0.5) / 5), -1).reshape(-1, 2)
    si = make_si(uv)
    srgb = np.where(raw <= 0.04045, raw / 12.92, ((raw + 0.055) / 1.055) ** 2.4)
    texs = {enc: mi.load_dict({'type': 'pbrt_imagemap', 'filename': path, 'filter': 'point',
                               'encoding': enc}) for enc in ('gamma 2.2', 'gamma 0.5', 'sRGB')}
    for enc, want in (('gamma 2.2', raw ** 2.2), ('gamma 0.5', raw ** 0.5), ('sRGB', srgb)):
        np.testing.assert_allclose(A(texs[enc].eval(si)), want, atol=1e-6, err_msg=enc)
    with pytest.raises(RuntimeError, match='"encoding"'):
        mi.load_dict({'type': 'pbrt_imagemap', 'filename': path, 'encoding': 'gamma 0'})


def test_8bit_srgb_texels_are_identical_to_bitmap():
    """The package decodes 8-bit sRGB through the table Mitsuba's ``bitmap`` uses, so texel
    values are bit-identical to ``bitmap``'s (the exact curve differs by up to 4.2e-7, which
    the 1e-6 parity tests cannot see): point lookups at every texel centre, exact equality."""
    path = os.path.join(DATA, 'srgb_11x9.png')
    b = mi.load_dict({'type': 'bitmap', 'filename': path, 'filter_type': 'nearest'})
    o = mi.load_dict({'type': 'pbrt_imagemap', 'filename': path, 'filter': 'point'})
    h, w = np.array(mi.Bitmap(path)).shape[:2]
    si = make_si(_texel_centres(w, h))
    np.testing.assert_array_equal(A(o.eval(si)), A(b.eval(si)))


@pytest.mark.parametrize('ext', ['exr', 'pfm'])
def test_nonfinite_texels_of_a_file_replaced_with_warning(ext, capfd, rng, tmp_path):
    """NaN and ±inf texels read from a float file (OpenEXR through the OpenEXR package, PFM
    through ``mi.Bitmap``) become 0, with a warning giving their count; the others are the
    file's values (point lookups at texel centres, exact)."""
    img = rng.random((4, 6, 3)).astype(np.float32)
    img[0, 1, 0], img[2, 3, :], img[3, 5, 2] = np.nan, np.inf, -np.inf
    path = str(tmp_path / f'bad.{ext}')
    mi.Bitmap(img, mi.Bitmap.PixelFormat.RGB).write(path)
    tex = mi.load_dict({'type': 'pbrt_imagemap', 'filename': path, 'filter': 'point'})
    got = A(tex.eval(make_si(_texel_centres(6, 4)))).reshape(4, 6, 3)
    np.testing.assert_array_equal(got, np.where(np.isfinite(img), img, 0))
    # the texels the texture exposes (``params['data']``, what an optimisation starts from)
    # are the repaired ones too, not only what the filters read
    np.testing.assert_array_equal(np.array(mi.traverse(tex)['data']), np.where(np.isfinite(img), img, 0))
    captured = capfd.readouterr()
    assert '5 non-finite texel value(s) replaced by 0' in captured.out + captured.err


def _write_exr_channels(path, channels):
    import OpenEXR
    header = {'compression': OpenEXR.ZIP_COMPRESSION, 'type': OpenEXR.scanlineimage}
    with OpenEXR.File(header, channels) as f:
        f.write(path)


@pytest.mark.parametrize('kind', ['RGBA', 'RGBA_half', 'YA'])
def test_exr_files_with_alpha_match_bitmap(kind, rng, tmp_path):
    """OpenEXR files with an alpha channel (float and half) and luminance with alpha: the
    texture is Mitsuba's ``bitmap`` of the same file with ``format = variant`` (float32 texels,
    alpha dropped as ``bitmap`` drops it), at texel centres and random bilinear lookups. Both
    read the same float texels and filter them alike: atol 1e-6 (float32 rounding of the
    bilinear weights). Alpha taken as a colour channel is refused (4 channels)."""
    h, w = 5, 6
    dtype = np.float16 if kind.endswith('half') else np.float32
    plane = lambda: rng.uniform(0, 1, (h, w)).astype(dtype)
    names = {'RGBA': 'RGBA', 'RGBA_half': 'RGBA', 'YA': 'YA'}[kind]
    path = str(tmp_path / 'img.exr')
    _write_exr_channels(path, {n: plane() for n in names})
    theirs = mi.load_dict({'type': 'bitmap', 'filename': path, 'format': 'variant'})
    ours = mi.load_dict({'type': 'pbrt_imagemap', 'filename': path})
    si = make_si(np.concatenate([_texel_centres(w, h), rng.uniform(-1, 2, (200, 2))]))
    np.testing.assert_allclose(A(ours.eval(si)), A(theirs.eval(si)), atol=1e-6)


def _xyz_exr(path, rng, h, w, dtype=np.float32, alpha=False):
    """An XYZ OpenEXR file as Mitsuba's ``hdrfilm`` writes one (``pixel_format="xyz"``: channels
    X, Y, Z through ``mi.Bitmap.write``), of random linear sRGB colours."""
    rgb = rng.uniform(0, 1, (h, w, 3))
    m = np.array([[0.412453, 0.357580, 0.180423], [0.212671, 0.715160, 0.072169],
                  [0.019334, 0.119193, 0.950227]])
    xyz = rgb @ m.T
    if alpha:
        xyz = np.concatenate([xyz, rng.uniform(0, 1, (h, w, 1))], -1)
    pf = mi.Bitmap.PixelFormat.XYZA if alpha else mi.Bitmap.PixelFormat.XYZ
    mi.Bitmap(xyz.astype(dtype), pf).write(path)
    return rgb


#: Mitsuba's XYZ -> linear sRGB matrix (``xyz_to_srgb``, which ``Bitmap.convert`` applies).
XYZ_TO_SRGB = np.array([[3.240479, -1.537150, -0.498535], [-0.969256, 1.875991, 0.041556],
                        [0.055648, -0.204043, 1.057311]])


@pytest.mark.parametrize('filt', ['nearest', 'bilinear'])
@pytest.mark.parametrize('kind', ['xyz', 'xyz_half', 'xyza', 'xyz_openexr', 'layer', 'layer_y',
                                  'lowercase', 'chroma_xyz', 'chroma_ap1', 'luma_chroma'])
def test_exr_colour_layouts_match_bitmap(kind, filt, rng, tmp_path):
    """OpenEXR files whose colour is not plain R,G,B / Y channels, read as Mitsuba's ``bitmap``
    reads them: X,Y,Z (``hdrfilm``'s ``pixel_format="xyz"``; float, half, with alpha, and
    written by the OpenEXR package) converted to linear sRGB — the package read Y alone, grey
    0.2126 for the XYZ of pure red, where ``bitmap`` gives (1.0, -8e-5, -2e-5); the one layer of
    a single-layer file (``diffuse.R,G,B``, ``depth.Y``; refused before); lower-case channel
    names; RGB with the chromaticities of the XYZ primaries or ACES AP1 (Mitsuba converts them
    to Rec. 709; the package read them as Rec. 709); luminance/chroma Y,RY,BY (the package read
    Y alone). Reference: ``bitmap`` of the same file with ``format = variant`` (float32 texels),
    nearest and bilinear at texel centres and random uv inside and outside [0, 1]². Both read
    the same float texels through the same conversion (``Bitmap.convert`` for XYZ, Mitsuba's
    reader for the others), so only float32 rounding of the bilinear weights remains: atol
    1e-6, as the parity tests. XYZ is also checked against Mitsuba's matrix applied in float64
    at texel centres (atol 2e-6: the float32 matrix product)."""
    import OpenEXR
    h, w = 5, 6
    path = str(tmp_path / 'img.exr')
    plane = lambda: rng.uniform(0.05, 1, (h, w)).astype(np.float32)
    ap1 = (0.713, 0.293, 0.165, 0.830, 0.128, 0.044, 0.32168, 0.33767)
    rgb = None
    if kind in ('xyz', 'xyz_half', 'xyza'):
        rgb = _xyz_exr(path, rng, h, w, np.float16 if kind == 'xyz_half' else np.float32,
                       alpha=kind == 'xyza')
    elif kind == 'xyz_openexr':
        _write_exr_channels(path, {'X': plane(), 'Y': plane(), 'Z': plane()})
    elif kind == 'layer':
        _write_exr_channels(path, {'diffuse.R': plane(), 'diffuse.G': plane(),
                                   'diffuse.B': plane()})
    elif kind == 'layer_y':
        _write_exr_channels(path, {'depth.Y': plane()})
    elif kind == 'lowercase':
        _write_exr_channels(path, {'r': plane(), 'g': plane(), 'b': plane()})
    elif kind == 'luma_chroma':
        _write_exr_channels(path, {'Y': plane(), 'RY': plane() - 0.5, 'BY': plane() - 0.5})
    else:
        chroma = (1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1 / 3, 1 / 3) if kind == 'chroma_xyz' else ap1
        header = {'compression': OpenEXR.ZIP_COMPRESSION, 'type': OpenEXR.scanlineimage,
                  'chromaticities': chroma}
        with OpenEXR.File(header, {'R': plane(), 'G': plane(), 'B': plane()}) as f:
            f.write(path)
    theirs = mi.load_dict({'type': 'bitmap', 'filename': path, 'format': 'variant',
                           'filter_type': filt})
    ours = mi.load_dict({'type': 'pbrt_imagemap', 'filename': path, 'filter_type': filt})
    si = make_si(np.concatenate([_texel_centres(w, h), rng.uniform(-1, 2, (300, 2))]))
    np.testing.assert_allclose(A(ours.eval(si)), A(theirs.eval(si)), atol=1e-6)
    np.testing.assert_allclose(A(ours.eval_1(si)), A(theirs.eval_1(si)), atol=1e-6)
    if rgb is not None and mi.is_rgb:
        stored = np.array(mi.Bitmap(path), dtype=np.float64)[..., :3]      # the file's XYZ
        want = (stored @ XYZ_TO_SRGB.T).reshape(-1, 3)
        got = A(ours.eval(make_si(_texel_centres(w, h)))).reshape(-1, 3)
        np.testing.assert_allclose(got, want, atol=2e-6)
        # and that is the colour written, to the rounding of Mitsuba's 6-digit matrices (and
        # of half floats)
        np.testing.assert_allclose(got, rgb.reshape(-1, 3), atol=2e-3 if 'half' in kind else 2e-5)


@pytest.mark.parametrize('case', ['png_named_exr', 'exr_named_png', 'exr_named_upper'])
def test_file_format_is_found_from_the_content_not_the_name(case, rng, tmp_path):
    """The reader is chosen by the file's first bytes, as ``mi.Bitmap`` (and so ``bitmap``)
    chooses: a PNG named ``.exr`` is read as the PNG it is (it failed with "cannot read OpenEXR
    file"), an OpenEXR file named ``.png`` or ``.EXR`` through the OpenEXR reader. Reference:
    ``bitmap`` of the same file (8-bit sRGB through Mitsuba's own table, or float32 texels:
    atol 1e-6, as the parity tests)."""
    h, w = 4, 5
    if case == 'png_named_exr':
        path = str(tmp_path / 'img.exr')
        bmp = mi.Bitmap(rng.integers(0, 256, (h, w, 3)).astype(np.uint8), mi.Bitmap.PixelFormat.RGB)
        bmp.set_srgb_gamma(True)
        bmp.write(str(tmp_path / 'img.png'))
        os.rename(str(tmp_path / 'img.png'), path)
    else:
        path = str(tmp_path / ('img.png' if case == 'exr_named_png' else 'img.EXR'))
        _write_exr_channels(path, {c: rng.uniform(0, 1, (h, w)).astype(np.float32) for c in 'RGB'})
    theirs = mi.load_dict({'type': 'bitmap', 'filename': path, 'format': 'variant'})
    ours = mi.load_dict({'type': 'pbrt_imagemap', 'filename': path})
    si = make_si(np.concatenate([_texel_centres(w, h), rng.uniform(-1, 2, (200, 2))]))
    np.testing.assert_allclose(A(ours.eval(si)), A(theirs.eval(si)), atol=1e-6)


@pytest.mark.parametrize('types', ['float_rgb_half_a', 'half_r_float_gb', 'rgb_and_depth'])
def test_exr_files_mixing_channel_types_or_with_depth_load_exactly(types, rng, tmp_path):
    """An OpenEXR file whose R, G, B (and A) channels do not share one pixel type — float colour
    with a half alpha, say — is valid; the OpenEXR package cannot interleave such channels, and
    the texture reads them one by one. A file with a depth channel Z next to R, G, B: the colour
    channels. Reference: the planes written (half values are float32 values exactly), by point
    lookups at texel centres, exact. (Mitsuba's ``bitmap`` is no reference here: it stores the
    first image as half floats and refuses the second.)"""
    h, w = 4, 5
    f32, f16 = np.float32, np.float16
    kinds = {'float_rgb_half_a': dict(R=f32, G=f32, B=f32, A=f16),
             'half_r_float_gb': dict(R=f16, G=f32, B=f32),
             'rgb_and_depth': dict(R=f32, G=f32, B=f32, Z=f32)}[types]
    planes = {n: rng.uniform(0, 1, (h, w)).astype(t) for n, t in kinds.items()}
    path = str(tmp_path / 'mixed.exr')
    _write_exr_channels(path, dict(planes))     # (the writer replaces the dict's values)
    tex = mi.load_dict({'type': 'pbrt_imagemap', 'filename': path, 'filter': 'point'})
    got = A(tex.eval(make_si(_texel_centres(w, h)))).reshape(h, w, 3)
    want = np.stack([planes[n].astype(np.float32) for n in 'RGB'], -1)
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize('shape', [(1, 7), (5, 1), (1, 1)])
def test_one_texel_wide_files_load_and_match_bitmap(shape, rng, tmp_path):
    """Files one texel wide or high (or a single texel) are valid images: equal to Mitsuba's
    ``bitmap`` of the same file (8-bit sRGB, nearest; ≤ 1e-6 as the parity tests)."""
    path = str(tmp_path / 'thin.png')
    px = rng.integers(0, 256, shape + (3,)).astype(np.uint8)
    bmp = mi.Bitmap(px, mi.Bitmap.PixelFormat.RGB)
    bmp.set_srgb_gamma(True)
    bmp.write(path)
    si = make_si(rng.uniform(-1, 2, (50, 2)))
    b = mi.load_dict({'type': 'bitmap', 'filename': path, 'filter_type': 'nearest'})
    o = mi.load_dict({'type': 'pbrt_imagemap', 'filename': path, 'filter': 'point'})
    np.testing.assert_allclose(A(o.eval(si)), A(b.eval(si)), atol=1e-6)


def test_ewa_with_a_zero_minor_axis_is_a_level0_bilinear_lookup(rng):
    """pbrt: a footprint whose minor axis is exactly 0 (a line) is not clamped to the maximum
    anisotropy but looked up bilinearly at level 0 — the numpy transcription does the same;
    1e-5 (float32 texel coordinates, as test_zero_differentials_every_filter_is_bilinear_level0)."""
    img = rng.random((32, 48, 3))
    n = 100
    uv = rng.uniform(0, 1, (n, 2))
    ang = rng.uniform(0, math.pi, n)
    d0 = np.stack([np.cos(ang), np.sin(ang)], 1) * 5.0 / 48
    d1 = np.zeros((n, 2))
    got = A(imagemap(img, filter='ewa').eval(make_si(uv, d0, d1)))
    want, _ = ref.ewa(ref.pyramid(img), uv[:, 0], uv[:, 1], d0, d1, 8.0, 'repeat')
    np.testing.assert_allclose(got, want, atol=1e-5)


# ------------------------------------------------------------------------------------ pyramid details
def _levels_of(pyr):
    """The pyramid's levels read back from its buffer, at offsets summed from the level sizes."""
    buf = np.array(pyr.buffer, dtype=np.float64)
    out, off = [], 0
    for w, h in pyr.sizes:
        out.append(buf[pyr.stride * off: pyr.stride * (off + w * h)]
                   .reshape(h, w, pyr.stride)[..., :pyr.channels])
        off += w * h
    return out


def test_pyramid_of_non_finite_texels_averages_them_as_zero(rng):
    """Non-finite texels count as 0 in every level (the levels are averages of the sanitized
    texels, not sanitized averages: one NaN must not zero a whole coarse texel), and the buffer
    holds exactly 4 (RGB: RGBA) floats per texel of all levels: ``nbytes``."""
    from mitsuba_pbrt_tex.mipmap import build_pyramid
    img = rng.random((12, 10, 3))
    img[3, 4, 1] = np.nan
    img[7, 2, 0] = np.inf
    img[0, 9, 2] = -np.inf
    pyr = build_pyramid(mi.TensorXf(img.astype(np.float32)))
    want = ref.pyramid(np.where(np.isfinite(img), img, 0.0))
    for got, lv in zip(_levels_of(pyr), want):
        np.testing.assert_allclose(got, lv, atol=2e-6)
    texels = sum(w * h for w, h in pyr.sizes)
    assert pyr.nbytes() == 4 * 4 * texels


@pytest.mark.parametrize('shape', [(2, 3), (3, 2), (2, 2), (1, 2)])
def test_two_level_pyramids(shape, rng):
    """Images whose pyramid has exactly two levels: level 1 is the image mean, and a footprint
    covering the image reads it (point, bilinear and trilinear)."""
    from mitsuba_pbrt_tex.mipmap import build_pyramid
    img = rng.random(shape + (3,))
    pyr = build_pyramid(mi.TensorXf(img.astype(np.float32)))
    assert len(pyr.sizes) == 2
    np.testing.assert_allclose(_levels_of(pyr)[1][0, 0], img.mean((0, 1)), atol=2e-6)
    uv = rng.uniform(0, 1, (20, 2))
    d = np.full((20, 2), 1.0)
    for filt in ('point', 'bilinear', 'trilinear'):
        tex = imagemap(img, filter=filt)
        tex.prepare_differentials()
        got = A(tex.eval(make_si(uv, d * [1, 0], d * [0, 1])))
        np.testing.assert_allclose(got, np.tile(img.mean((0, 1)), (20, 1)), atol=2e-6)


def test_build_pyramid_refuses_other_shapes():
    from mitsuba_pbrt_tex.mipmap import build_pyramid
    for shape in ((4, 4), (4, 4, 2), (4, 4, 4)):
        with pytest.raises(ValueError, match='expected an'):
            build_pyramid(mi.TensorXf(np.zeros(shape, np.float32)))


@pytest.mark.parametrize('shape', [(16, 64), (64, 16), (48, 48), (15, 15), (32, 32)])
@pytest.mark.parametrize('filt', ['point', 'bilinear'])
def test_single_level_lookups_at_every_level_of_square_and_power_of_two_images(shape, filt, rng):
    """Per-lane levels (where a level's offset has a closed form for square power-of-two images
    and wrapping is a bit mask for power-of-two sides) against the reference pyramid: lookups
    with isotropic footprints selecting each level in turn, repeat wrap, uv in [-1, 2]."""
    img = rng.random(shape + (3,))
    levels = ref.pyramid(img)
    tex = imagemap(img, filter=filt)
    tex.prepare_differentials()
    n = 400
    uv = rng.uniform(-1, 2, (n, 2))
    lvl = rng.integers(0, len(levels), n)
    width = (2.0 ** (lvl + 0.5)) / max(shape)               # mid-level: floor(log2) = lvl
    got = A(tex.eval(make_si(uv, np.stack([width, 0 * width], 1), np.stack([0 * width, width], 1))))
    want = np.empty((n, 3))
    for k in range(n):
        lv = levels[min(lvl[k], len(levels) - 1)]
        h, w = lv.shape[:2]
        if filt == 'bilinear':
            want[k] = ref.bilinear(lv, uv[k:k + 1, 0], uv[k:k + 1, 1], 'repeat')[0]
        else:
            want[k] = ref.texel(lv, np.floor(uv[k:k + 1, 0] * w).astype(int),
                                np.floor(uv[k:k + 1, 1] * h).astype(int), 'repeat')[0]
    ok = np.ones(n, bool)
    if filt == 'point':                      # exclude lookups within rounding of a texel edge
        for k in range(n):
            h, w = levels[lvl[k]].shape[:2]
            for c, size in ((0, w), (1, h)):
                p = uv[k, c] * size
                ok[k] &= abs(p - np.round(p)) > 1e-4
    np.testing.assert_allclose(got[ok], want[ok], atol=1e-5)


def test_black_wrap_point_lookups_outside_are_zero_and_the_top_level_is_the_mean(rng):
    """``black``: a point lookup outside the image is 0, at any level; a footprint that selects
    exactly the top level (or beyond) reads its one texel, the image mean, as pbrt does — not a
    bilinear blend of it with the black outside."""
    img = rng.random((16, 16, 3)) + 0.1
    tex = imagemap(img, filter='point', wrap='black')
    tex.prepare_differentials()
    uv = np.array([[-0.3, 0.5], [1.2, 0.5], [0.5, -0.01], [0.5, 1.5]])
    for width in (0.0, 1 / 16, 1 / 4):
        d = np.full((4, 2), width)
        assert np.all(A(tex.eval(make_si(uv, d * [1, 0], d * [0, 1]))) == 0)
    lin = imagemap(img, filter='bilinear', wrap='black')
    lin.prepare_differentials()
    uv = rng.uniform(0, 1, (50, 2))
    for width in (1.0, 1.5, 8.0):                    # level log2(16·width) ≥ 4, the top
        d = np.full((50, 2), width)
        np.testing.assert_allclose(A(lin.eval(make_si(uv, d * [1, 0], d * [0, 1]))),
                                   np.tile(img.mean((0, 1)), (50, 1)), atol=2e-6)


@pytest.mark.parametrize('channels', [1, 3])
def test_eval_1_grad_with_invert_matches_finite_differences(channels, rng):
    """``invert`` (1 - scale·v, clamped at 0) makes ``eval_1_grad`` read the value: its
    derivative is -scale·grad where 1 - scale·v > 0 and 0 where clamped — for RGB channel by
    channel, as eval_1 is the luminance of the inverted channels (found in a user trial: the
    clamp was decided from the luminance, (0.06, -0.55) against finite differences of
    (-0.31, -0.98) where only red clipped). With scale 2 and texels in [0, 1] all cases occur;
    lookups within 0.02 of a clamp or 0.03 texel of a texel-centre line are excluded. Central
    differences, h = 1e-4 in uv (0.0016 texel): rtol 1e-2, atol 2e-3 as in the footprint test
    above."""
    res = 16
    img = rng.random((res, res, channels))
    tex = mi.load_dict({'type': 'pbrt_imagemap', 'data': mi.TensorXf(img.astype(np.float32)),
                        'filter': 'bilinear', 'scale': 2.0, 'invert': True})
    n = 400
    uv = rng.uniform(0.05, 0.95, (n, 2))
    h = 1e-4

    def f(shift):
        return A(tex.eval_1(make_si(uv + shift)))

    fd = np.stack([(f([h, 0]) - f([-h, 0])) / (2 * h), (f([0, h]) - f([0, -h])) / (2 * h)], 1)
    got = A(tex.eval_1_grad(make_si(uv)))
    v = ref.bilinear(img, uv[:, 0], uv[:, 1], 'repeat').reshape(n, channels)
    ok = (np.abs(1 - 2 * v) > 0.02).all(1)
    for c in range(2):
        p = uv[:, c] * res - 0.5
        ok &= np.abs(p - np.round(p)) > 0.03
    live = (1 - 2 * v > 0).all(1) & ok
    assert live.sum() > (50 if channels == 1 else 10) and (ok & ~live).sum() > 50
    np.testing.assert_allclose(got[ok], fd[ok], rtol=1e-2, atol=2e-3)


def test_level_offsets_of_large_pyramids():
    """The per-lane level view's texel offsets (a closed form for square power-of-two images
    below 2³² texels·4, selects otherwise) equal the running sum of the level sizes, for sizes
    up to 65536 × 32768 (offsets near 2³², the most a UInt32 texel index can address) — checked
    on the view alone (no buffer is allocated)."""
    from mitsuba_pbrt_tex.mipmap import LevelView, MIPMap, Pyramid, level_sizes
    for w, h in ((1, 1), (2, 2), (5, 5), (64, 64), (4096, 4096), (16384, 16384), (32768, 32768),
                 (65536, 32768), (300, 7)):
        sizes = level_sizes(w, h)
        pyr = Pyramid(None, w, h, 3, sizes)
        want = np.cumsum([0] + [a * b for a, b in sizes[:-1]])
        assert pyr.offsets == list(want)
        if len(sizes) == 1:
            continue
        view = LevelView(MIPMap(pyr, 'repeat'), mi.UInt32(np.arange(len(sizes))))
        np.testing.assert_array_equal(np.array(view.off, dtype=np.int64), want)


def test_overflowing_footprints_are_point_lookups(rng):
    """A mapping scale that overflows the (finite, clamped) partials to inf gives a footprint
    width that is not finite: it counts as 0 (the finest level), as non-finite partials do."""
    img = rng.random((16, 16, 3))
    tex = imagemap(img, filter='bilinear', uscale=1e31, vscale=1e31)
    tex.prepare_differentials()
    uv = rng.uniform(0, 1e-30, (20, 2))
    d = np.full((20, 2), 1e8)
    np.testing.assert_array_equal(A(tex.eval(make_si(uv, d * [1, 0], d * [0, 1]))),
                                  A(tex.eval(make_si(uv))))


def test_ewa_non_finite_derivatives_count_as_zero(rng):
    """The EWA filter reads a NaN or infinite derivative component as 0 (``ewa.py``,
    ``EWAFilter.axes``). The plugin's differentials are already finite (``differentials.py``),
    so such values reach the filter only through a mapping that overflows them; the filter is
    called directly here. The lookup equals pbrt's EWA (numpy transcription) of the footprint
    with those components zeroed — a zero footprint is a level-0 bilinear lookup, one finite
    axis keeps its own level. Tolerance 2e-5 and bucket-edge lookups excluded as in
    test_ewa_matches_pbrt_literal."""
    from mitsuba_pbrt_tex.ewa import EWAFilter
    from mitsuba_pbrt_tex.mipmap import MIPMap
    img = rng.random((32, 48, 3))
    n = 120
    uv = rng.uniform(0, 1, (n, 2))
    nan, inf = float('nan'), float('inf')
    d0 = np.tile(np.array([[inf, 0.0], [nan, 3.0 / 48], [-inf, nan], [6.0 / 48, inf]]), (n // 4, 1))
    d1 = np.tile(np.array([[0.0, nan], [1.5 / 48, -inf], [nan, 0.0], [inf, 2.5 / 48]]), (n // 4, 1))
    mip = MIPMap(build_pyramid(mi.TensorXf(img.astype(np.float32))), 'repeat')
    vec = lambda d: mi.Vector2f(d[:, 0], d[:, 1])
    got = A(EWAFilter(8.0)(mip, mi.Point2f(uv[:, 0], uv[:, 1]), vec(d0), vec(d1), mi.Bool(True)))
    zeroed = [np.where(np.isfinite(d), d, 0.0) for d in (d0, d1)]
    want, ambiguous = ref.ewa(ref.pyramid(img), uv[:, 0], uv[:, 1], *zeroed, 8.0, 'repeat')
    assert ambiguous.mean() < 0.25
    np.testing.assert_allclose(got[~ambiguous], want[~ambiguous], atol=2e-5)


@pytest.mark.parametrize('shape', [(1, 1), (2, 2), (3, 2), (5, 4)])
@pytest.mark.parametrize('wrap', ['black', 'repeat'])
@pytest.mark.parametrize('max_aniso', [8.0, 32.0])
def test_ewa_matches_pbrt_literal_on_images_a_few_texels_wide(shape, wrap, max_aniso, rng):
    """On an image a few texels wide the level cannot grow with the footprint: a minor axis of
    0.3–1 texel at the largest anisotropy gives ellipses up to 32 texels long at level 0, many
    times the image, and pbrt sums all of their taps (numpy transcription). A cap on the loop's
    extents once cut them (up to 0.06 off for texels in [0, 1]). 1e-4: float32 accumulation
    over up to ~10³ taps (n·6e-8 relative); bucket-edge lookups excluded as in
    test_ewa_matches_pbrt_literal."""
    img = rng.random(shape + (1,))
    n = 200
    uv = rng.uniform(0, 1, (n, 2))
    minor = rng.uniform(0.3, 1.0, n) / max(shape)
    ang = rng.uniform(0, math.pi, n)
    d0 = np.stack([np.cos(ang), np.sin(ang)], 1) * (minor * max_aniso)[:, None]
    d1 = np.stack([-np.sin(ang), np.cos(ang)], 1) * minor[:, None]
    tex = imagemap(img, filter='ewa', wrap=wrap, maxanisotropy=max_aniso)
    got = A(tex.eval_1(make_si(uv, d0, d1)))
    want, ambiguous = ref.ewa(ref.pyramid(img), uv[:, 0], uv[:, 1], d0, d1, max_aniso, wrap)
    assert ambiguous.mean() < 0.25
    np.testing.assert_allclose(got[~ambiguous], want[~ambiguous, 0], atol=1e-4)


@pytest.mark.parametrize('tex', [
    {'type': 'pbrt_imagemap', 'data': 'random', 'mapping': 'spherical',
     'to_world': mi.ScalarTransform4f().scale(1e20)},
    {'type': 'pbrt_imagemap', 'data': 'random', 'mapping': 'cylindrical'},
    {'type': 'pbrt_imagemap', 'data': 'random', 'mapping': 'planar'},
    {'type': 'pbrt_fbm'}])
def test_eval_1_grad_is_finite_where_the_mapping_overflows(tex, rng):
    """A bump map must not turn a normal into NaN. A spherical mapping scaled by 1e20 (which
    passes the invertibility check: equal singular values) has |p|² underflow, and partials
    near float32's limit or non-finite overflow the mappings' derivatives: eval_1_grad was NaN
    there (found in a user trial) while eval_1 was finite. Non-finite components are 0."""
    if tex.get('data') == 'random':
        tex = dict(tex, data=mi.TensorXf(rng.random((8, 8, 3)).astype(np.float32)))
    t = mi.load_dict(tex)
    p = np.array([[0, 0, 1], [0.6, 0, 0.8], [1e-4, 0, 1], [0.3, 0.4, 0.1], [2, 1, 0]])
    n = len(p)
    for dp in ([1, 0, 0], [3e38, 3e38, 0], [np.inf, 0, 0], [np.nan, 1, 0]):
        si = make_si(np.full((n, 2), 0.3), p=p, n=[0, 0, 1], dp_du=dp, dp_dv=[0, 1, 0])
        assert np.isfinite(A(t.eval_1(si))).all(), (tex['type'], dp)
        assert np.isfinite(A(t.eval_1_grad(si))).all(), (tex['type'], dp)


def test_pbrt_v4_spelling_EWA_is_ewa(rng):
    """pbrt-v4's ParseFilter reads "ewa" and "EWA" (found in a user trial: pbrt scenes spelling
    it in capitals were refused). Same lookups, bit for bit; other capitalisations stay errors."""
    data = mi.TensorXf(rng.random((16, 16, 3)).astype(np.float32))
    si = make_si(rng.random((32, 2)), duv_dx=[[0.05, 0.01]] * 32, duv_dy=[[-0.01, 0.2]] * 32)
    got = []
    for name in ('ewa', 'EWA'):
        tex = mi.load_dict({'type': 'pbrt_imagemap', 'filter': name, 'data': data})
        tex.prepare_differentials()
        got.append(A(tex.eval_3(si)))
    np.testing.assert_array_equal(got[0], got[1])
    with pytest.raises(RuntimeError, match='unknown value "Ewa"'):
        mi.load_dict({'type': 'pbrt_imagemap', 'filter': 'Ewa', 'data': data})


@pytest.mark.parametrize('channels', [1, 3])
def test_mean_with_invert_is_the_mean_of_the_inverted_texels(channels, rng):
    """mean() (a plastic's weight, an emitter's power) of an inverted image is the average over
    texels of what lookups return there: the luminance of max(0, 1 - scale·v) channel by
    channel (found in a user trial: the luminance was inverted instead — 0.4928 for 0.5204 on a
    2×2 image). numpy reference with Mitsuba's luminance weights; float32 sums: rtol 1e-5."""
    img = rng.uniform(0, 1.5, (8, 8, channels)).astype(np.float32)
    tex = mi.load_dict({'type': 'pbrt_imagemap', 'data': mi.TensorXf(img), 'scale': 1.5,
                        'invert': True})
    inverted = np.maximum(0, 1 - 1.5 * img.astype(np.float64))
    want = inverted[..., 0] if channels == 1 else \
        inverted @ np.array([0.212671, 0.715160, 0.072169])
    assert A(tex.mean())[0] == pytest.approx(want.mean(), rel=1e-5)


@pytest.mark.parametrize('context', ['dispatch', 'loop'])
def test_mean_inside_symbolic_calls_and_loops(context, rng):
    """mean() asked inside a symbolic call (a user's BSDF, dr.dispatch) or loop: the mean is
    computed where the texels change, as bitmap keeps its own — a reduction over the image there
    aborted the process inside Dr.Jit (found in a user trial). The value is the texels' mean
    (numpy; float32 sums: rtol 1e-5), also after params.update() of data and scale."""
    img = rng.random((8, 8, 3)).astype(np.float32)
    tex = mi.load_dict({'type': 'pbrt_imagemap', 'data': mi.TensorXf(img)})
    other = mi.load_dict({'type': 'pbrt_constant', 'value': 0.25})
    lum = np.array([0.212671, 0.715160, 0.072169])

    def read():
        x = dr.arange(mi.Float, 8)
        if context == 'dispatch':
            ptr = dr.gather(mi.TexturePtr, mi.TexturePtr([tex, other]),
                            dr.arange(mi.UInt32, 8) % 2)
            return A(dr.dispatch(ptr, lambda self, x: x * 0 + self.mean(), x))[0]
        _, r = dr.while_loop((mi.UInt32(0), x * 0), lambda i, r: i < 1,
                             lambda i, r: (i + 1, r + tex.mean()))
        return A(r)[0]

    assert read() == pytest.approx((img.astype(np.float64) @ lum).mean(), rel=1e-5)
    p = mi.traverse(tex)
    p['data'] = mi.TensorXf(img * 0.5)
    p['scale'] = mi.Float(3.0)
    p.update()
    assert read() == pytest.approx(1.5 * (img.astype(np.float64) @ lum).mean(), rel=1e-5)
