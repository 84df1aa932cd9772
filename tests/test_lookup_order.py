"""EWA over batches sorted by texture tile (mitsuba_pbrt_tex.lookup_order): the same values and
gradients as in the order given, taken only where it can and should be."""

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import reference_mipmap as ref
from conftest import A, make_si, wavefront_mode
from mitsuba_pbrt_tex import ewa as ewa_module
from mitsuba_pbrt_tex import lookup_order


def ewa_texture(texels, **kw):
    return mi.load_dict({'type': 'pbrt_imagemap', 'data': mi.TensorXf(texels), 'filter': 'ewa',
                         **kw})


@pytest.fixture
def argsort_calls(monkeypatch):
    """The widths of the batches sorted (``dr.argsort`` calls) while the test runs."""
    calls = []
    real = lookup_order.dr.argsort

    def counting(x, *a, **k):
        calls.append(dr.width(x))
        return real(x, *a, **k)

    monkeypatch.setattr(lookup_order.dr, 'argsort', counting)
    return calls


@pytest.fixture
def sorts(monkeypatch, argsort_calls):
    """Small batches and textures take the sorted path; the sorts actually done."""
    monkeypatch.setattr(lookup_order, 'MIN_BATCH', 64)
    monkeypatch.setattr(lookup_order, 'TILE_TEXELS', 4)
    monkeypatch.setattr(ewa_module, 'MIN_LEVEL_BYTES', 1024)
    return argsort_calls


def random_batch(rng, n, res):
    """Random uv (some far outside, NaN, ±1e6), 8:1 footprints of 0.3–12 texels (random
    orientation), some zero, NaN or huge derivatives."""
    uv = rng.uniform(-2, 3, (n, 2))
    uv[:8] = [[np.nan, 0.5], [0.5, np.inf], [1e6, -1e6], [-1e6, 0.25], [0, 0], [1, 1],
              [0.999999, 1e-7], [-0.5, 7.25]]
    ang = rng.uniform(0, math.pi, n)
    minor = np.exp(rng.uniform(np.log(0.3), np.log(12), n)) / res
    d0 = np.stack([np.cos(ang), np.sin(ang)], 1) * (8 * minor)[:, None]
    d1 = np.stack([-np.sin(ang), np.cos(ang)], 1) * minor[:, None]
    d0[8:12], d1[8:12] = 0, 0
    d0[12], d1[13] = np.nan, np.inf
    d0[14], d1[14] = [1e9, 0], [0, 1e9]
    return uv, d0, d1


@pytest.mark.parametrize('channels', [1, 3])
@pytest.mark.parametrize('wrap', ['repeat', 'black', 'clamp', 'mirror', 'octahedralsphere'])
def test_sorted_equals_given_order(channels, wrap, rng, sorts):
    """Bit for bit: each lane's arithmetic is the same whatever the order of the lanes."""
    res = 32
    texels = rng.random((res, res, channels)).astype(np.float32)
    uv, d0, d1 = random_batch(rng, 3000, res)
    si = make_si(uv, duv_dx=d0, duv_dy=d1)
    active = mi.Bool(rng.random(len(uv)) < 0.8)
    sorted_tex = ewa_texture(texels, wrap=wrap)
    given_tex = ewa_texture(texels, wrap=wrap, sortlookups=False)
    for method in ('eval', 'eval_1', 'eval_3'):
        a = A(getattr(sorted_tex, method)(si, active))
        b = A(getattr(given_tex, method)(si, active))
        assert np.all(np.isfinite(a))
        np.testing.assert_array_equal(a, b)
    assert len(sorts) == 3                      # the sorted path was taken, once per call
    assert all(w == len(uv) for w in sorts)


@pytest.mark.parametrize('shape', [(1, 1), (1, 7), (9, 1), (37, 53)])
def test_sorted_against_numpy_pbrt(shape, rng, sorts, monkeypatch):
    """The sorted path against the independent numpy transcription of pbrt's EWA (see
    test_imagemap: 2e-5, lookups at table-bucket edges excluded), on tiny and odd images with uv
    far outside [0, 1]. A one-tile image is coherent whatever the order and is not sorted; 37×53
(10×14 tiles of the test's 4 texels) is."""
    monkeypatch.setattr(ewa_module, 'MIN_LEVEL_BYTES', 1)
    h, w = shape
    img = rng.random((h, w, 3))
    n = 300
    uv = rng.uniform(-3, 4, (n, 2))
    ang = rng.uniform(0, math.pi, n)
    minor = np.exp(rng.uniform(np.log(0.2), np.log(4), n)) / max(h, w)
    d0 = np.stack([np.cos(ang), np.sin(ang)], 1) * (8 * minor)[:, None]
    d1 = np.stack([-np.sin(ang), np.cos(ang)], 1) * minor[:, None]
    got = A(ewa_texture(img.astype(np.float32)).eval(make_si(uv, duv_dx=d0, duv_dy=d1)))
    want, ambiguous = ref.ewa(ref.pyramid(img), uv[:, 0], uv[:, 1], d0, d1, 8.0, 'repeat')
    assert np.all(np.isfinite(got)) and ambiguous.mean() < 0.25
    np.testing.assert_allclose(got[~ambiguous], want[~ambiguous], atol=2e-5)
    if shape == (37, 53):
        assert sorts == [n]
    if shape == (1, 1):
        assert sorts == []


def test_gradients_match_given_order(rng, sorts):
    """Reverse mode through the permutation: d(sum of lookups)/d(texels) and d/d(uv) as in the
    given order (texel gradients are sums in another order: 1e-5 relative). pbrt's EWA weights
    are a table indexed by int(r²·128), piecewise constant in uv, so uv gradients come from the
    zero-footprint lanes (bilinear at level 0)."""
    res = 16
    texels = rng.random((res, res, 3)).astype(np.float32)
    uv, d0, d1 = random_batch(rng, 500, res)
    uv[:16] = rng.uniform(0, 1, (16, 2))          # finite, zero footprints: bilinear
    d0[:16], d1[:16] = 0, 0
    grads = []
    for sort in (True, False):
        tex = ewa_texture(texels, sortlookups=sort)
        params = mi.traverse(tex)
        dr.enable_grad(params['data'])
        params.update()
        si = make_si(uv, duv_dx=d0, duv_dy=d1)
        dr.enable_grad(si.uv)
        dr.backward(dr.sum(dr.sum(tex.eval(si))))
        grads.append((A(dr.grad(params['data'])).ravel(), A(dr.grad(si.uv))))
    assert len(sorts) == 1
    (gd_s, gu_s), (gd_g, gu_g) = grads
    assert np.abs(gd_g).max() > 0
    np.testing.assert_allclose(gd_s, gd_g, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(gu_s, gu_g)
    assert np.abs(gu_g[:16]).max() > 0            # (n, 2)


def test_not_sorted_inside_symbolic_loop(rng, sorts):
    """A render's kernel: the lookups of a symbolic loop cannot be reordered, and are not."""
    res = 32
    texels = rng.random((res, res, 3)).astype(np.float32)
    uv, d0, d1 = random_batch(rng, 2000, res)
    si = make_si(uv, duv_dx=d0, duv_dy=d1)
    tex = ewa_texture(texels)
    want = A(ewa_texture(texels, sortlookups=False).eval(si))
    sorts.clear()

    def body(i, acc):
        return i + 1, acc + tex.eval(si)

    _, got = dr.while_loop((mi.UInt32(0), dr.zeros(mi.Color3f, len(uv))),
                           lambda i, acc: i < 1, body)
    assert sorts == []
    np.testing.assert_array_equal(A(got), want)


def test_when_sorting_pays():
    """Coherent batches (most lanes in the previous lane's tile) and batches mostly on levels
    that stay in cache are left in their order; a random batch is sorted."""
    n = 1 << 12
    k = np.arange(n)
    raster = mi.Point2f(((k % 64 + 0.5) / 64).astype(np.float32),
                        ((k // 64 + 0.5) / 64).astype(np.float32))
    rnd = np.random.default_rng(3).random((2, n)).astype(np.float32)
    scattered = mi.Point2f(rnd[0], rnd[1])
    key = lambda st: lookup_order.tile_key(st, 256, 256)          # 8×8 tiles
    assert not lookup_order.worth_sorting(key(raster))
    assert lookup_order.worth_sorting(key(scattered))
    few = mi.Bool(np.arange(n) % 5 == 0)                          # 20% < 25% on large levels
    many = mi.Bool(np.arange(n) % 3 == 0)                         # 33%
    assert not lookup_order.worth_sorting(key(scattered), few)
    assert lookup_order.worth_sorting(key(scattered), many)


def test_tile_key_range():
    """Keys of any coordinate (wrapped, non-finite → 0) lie in [0, tiles) for odd sizes too."""
    st = mi.Point2f([-1e6, 0, 0.5, 0.9999999, 1, 7.3, float('nan'), float('inf')],
                    [1e6, 0, 0.5, 0.9999999, -3.2, 0.1, 0.2, float('-inf')])
    key = A(lookup_order.tile_key(st, 37, 65))                   # 2 × 3 tiles of 32
    assert key.min() >= 0 and key.max() < 6
    assert key[2] == 1 * 2 + 1 and key[3] == 2 * 2 + 1


def test_default_sorts_large_random_batch(rng, argsort_calls):
    """Without any test hooks: a 1024² RGB texture (16 MB level 0) and 2^15 random lookups on
    levels 0–1 take the sorted path (the benchmark's case), with the same values."""
    res = 1024
    texels = rng.random((res, res, 3)).astype(np.float32)
    n = 1 << 15
    uv = rng.random((n, 2))
    ang = rng.uniform(0, math.pi, n)
    d0 = np.stack([np.cos(ang), np.sin(ang)], 1) * 12 / res
    d1 = np.stack([-np.sin(ang), np.cos(ang)], 1) * 1.5 / res
    si = make_si(uv, duv_dx=d0, duv_dy=d1)
    got = A(ewa_texture(texels).eval(si))
    assert argsort_calls == [n]
    np.testing.assert_array_equal(got, A(ewa_texture(texels, sortlookups=False).eval(si)))


def test_sortlookups_must_be_boolean():
    with pytest.raises(Exception, match=r'pbrt_imagemap.*sortlookups.*true or false'):
        mi.load_dict({'type': 'pbrt_imagemap', 'data': mi.TensorXf(np.ones((4, 4, 1))),
                      'filter': 'ewa', 'sortlookups': 'yes'})


def test_wavefront_render_sorts_and_matches_megakernel(rng, sorts):
    """Mitsuba's path tracer in wavefront mode (loops and calls evaluated, not symbolic) hands
    the texture evaluated batches: they are sorted, and the image is the megakernel's."""
    data = mi.TensorXf(rng.random((64, 64, 3)).astype(np.float32))
    scene = mi.load_dict({
        'type': 'scene', 'integrator': {'type': 'path'},
        'sensor': {'type': 'perspective', 'fov': 60,
                   'to_world': mi.ScalarTransform4f().look_at(origin=[0, -2, 1.5],
                                                              target=[0, 0, 0], up=[0, 0, 1]),
                   'film': {'type': 'hdrfilm', 'width': 32, 'height': 32,
                            'rfilter': {'type': 'box'}},
                   'sampler': {'type': 'independent', 'sample_count': 4}},
        'rect': {'type': 'rectangle', 'to_world': mi.ScalarTransform4f().scale(3),
                 'bsdf': {'type': 'diffuse', 'reflectance': {
                     'type': 'pbrt_imagemap', 'data': data, 'filter': 'ewa', 'uscale': 4,
                     'vscale': 4}}},
        'light': {'type': 'constant'}})
    megakernel = A(mi.render(scene, seed=1))
    assert sorts == []
    with wavefront_mode():
        wavefront = A(mi.render(scene, seed=1))
    assert len(sorts) >= 1
    np.testing.assert_array_equal(wavefront, megakernel)
