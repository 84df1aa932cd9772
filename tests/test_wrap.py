"""Wrap modes against the numpy transcription of pbrt's rules in ``reference_mipmap`` (which
shares no code with the package): the integer remap itself, for every mode, and image lookups
with the ``octahedralsphere`` wrap through every filter (its remap couples the two axes, so it
has its own code paths in the taps of point/bilinear and in EWA)."""

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import reference_mipmap as ref
from conftest import A, make_si
from mitsuba_pbrt_tex.wrap import WRAP_MODES, wrap_1d, wrap_2d


def _ref_wrap_2d(x, y, w, h, mode):
    if mode == 'octahedralsphere':
        xi, yi = ref.octahedral(x, y, w, h)
        return xi, yi, np.ones(x.shape, bool)
    xi, vx = ref.wrap(x, w, mode)
    yi, vy = ref.wrap(y, h, mode)
    return xi, yi, vx & vy


@pytest.mark.parametrize('mode', WRAP_MODES)
@pytest.mark.parametrize('size', [(1, 1), (1, 5), (6, 1), (7, 4), (16, 16)])
def test_wrap_2d_matches_reference(mode, size):
    """Every integer pair within two image sizes of the image, on a rectangular image (so x/y
    or w/h swaps show): exact equality of the indices and of the validity mask."""
    w, h = size
    xs, ys = np.meshgrid(np.arange(-2 * w - 1, 3 * w + 1), np.arange(-2 * h - 1, 3 * h + 1))
    x, y = xs.ravel().astype(np.float64), ys.ravel().astype(np.float64)
    gx, gy, gv = wrap_2d(mi.Float(x), mi.Float(y), w, h, mode)
    rx, ry, rv = _ref_wrap_2d(xs.ravel(), ys.ravel(), w, h, mode)
    if mode == 'octahedralsphere':
        # pbrt defines one reflection per axis: compare where that suffices (and W, H > 1, where
        # pbrt pins the index to 0 — the clamp gives the same), i.e. within one image.
        one = (xs.ravel() >= -w) & (xs.ravel() < 2 * w) & (ys.ravel() >= -h + 1) & (ys.ravel() < 2 * h - 1)
        keep = one
    else:
        keep = np.ones(x.shape, bool)
    np.testing.assert_array_equal(A(gx)[keep], rx[keep])
    np.testing.assert_array_equal(A(gy)[keep], ry[keep])
    np.testing.assert_array_equal(np.broadcast_to(A(gv), x.shape)[keep], rv[keep])
    # everything stays a valid index, whatever the input
    assert (A(gx) >= 0).all() and (A(gx) < w).all() and (A(gy) >= 0).all() and (A(gy) < h).all()


def test_octahedral_remap_is_the_sphere_seam():
    """An octahedral map's edges are seams of the sphere: crossing the left edge at row y lands
    at column 0 of row H-1-y (the texel that is its neighbour on the sphere), crossing the top
    edge at column x lands at column W-1-x of row 0 — two hand-worked cases, independent of the
    reference's code."""
    w, h = 8, 6
    gx, gy, _ = wrap_2d(mi.Float([-1, 8, 2, 5, -1]), mi.Float([1, 4, -1, 6, -1]), w, h,
                        'octahedralsphere')
    # (-1, 1) → (1, 4); (8, 4) → (7, 1); (2, -1) → (5, 1); (5, 6) → (2, 5);
    # corner (-1, -1) → x: (1, 6) → y outside: (6, 5)
    np.testing.assert_array_equal(A(gx), [1, 7, 5, 2, 6])
    np.testing.assert_array_equal(A(gy), [4, 1, 1, 5, 5])


def imagemap(img, **kw):
    return mi.load_dict({'type': 'pbrt_imagemap', 'data': mi.TensorXf(img.astype(np.float32)),
                         'wrap': 'octahedralsphere', **kw})


def edge_lookups(rng, n, w, h):
    """uv within ~2 texels of an edge or corner (where the remap matters), inside or outside."""
    uv = rng.uniform(0, 1, (n, 2))
    side = rng.integers(0, 4, n)
    band = rng.uniform(-2.0, 2.0, n)
    uv[side == 0, 0] = band[side == 0] / w
    uv[side == 1, 0] = 1 + band[side == 1] / w
    uv[side == 2, 1] = band[side == 2] / h
    uv[side == 3, 1] = 1 + band[side == 3] / h
    return uv.astype(np.float32).astype(np.float64)


@pytest.mark.parametrize('filt', ['point', 'bilinear'])
def test_octahedral_point_and_bilinear_lookups(filt, rng):
    """Level-0 lookups near every edge of a 12×7 RGB image vs the reference's taps: ≤ 2e-6
    (float32 texel coordinates, as in the other level-0 tests)."""
    img = rng.random((7, 12, 3))
    uv = edge_lookups(rng, 600, 12, 7)
    got = A(imagemap(img, filter=filt).eval(make_si(uv)))
    if filt == 'bilinear':
        want = ref.bilinear(img, uv[:, 0], uv[:, 1], 'octahedralsphere')
    else:
        want = ref.texel(img, np.floor(uv[:, 0] * 12).astype(int),
                         np.floor(uv[:, 1] * 7).astype(int), 'octahedralsphere')
    np.testing.assert_allclose(got, want, atol=2e-6)


def test_octahedral_trilinear_lookups(rng):
    """Footprints of 0.5–12 texels near the edges: the blend of two levels, each wrapped with
    the octahedral rule at its own size (tolerance as test_trilinear_matches_reference)."""
    img = rng.random((24, 40, 3))
    n = 300
    uv = edge_lookups(rng, n, 40, 24)
    width = np.exp(rng.uniform(np.log(0.5), np.log(12), n)) / 40
    d0 = np.stack([width, 0.3 * width], 1)
    d1 = np.stack([-0.2 * width, 0.5 * width], 1)
    got = A(imagemap(img, filter='trilinear').eval(make_si(uv, d0, d1)))
    want = ref.trilinear(ref.pyramid(img), uv[:, 0], uv[:, 1], width, 'octahedralsphere')
    np.testing.assert_allclose(got, want, atol=5e-6)


def test_octahedral_ewa_matches_pbrt_literal(rng):
    """EWA near the edges (anisotropic footprints up to 20 texels that reach across the seams)
    vs pbrt's bounding-box EWA whose texel fetch applies the reference remap: ≤ 2e-5 as in
    test_ewa_matches_pbrt_literal, bucket-edge lookups excluded the same way."""
    img = rng.random((32, 48, 3))
    n = 200
    uv = edge_lookups(rng, n, 48, 32)
    major = np.exp(rng.uniform(np.log(1.0), np.log(20), n))
    ratio = np.exp(rng.uniform(0, np.log(8), n))
    ang = rng.uniform(0, math.pi, n)
    d0 = np.stack([np.cos(ang), np.sin(ang)], 1) * (major / 48)[:, None]
    d1 = np.stack([-np.sin(ang), np.cos(ang)], 1) * (major / ratio / 48)[:, None]
    got = A(imagemap(img, filter='ewa').eval(make_si(uv, d0, d1)))
    want, ambiguous = ref.ewa(ref.pyramid(img), uv[:, 0], uv[:, 1], d0, d1, 8.0,
                              'octahedralsphere')
    assert ambiguous.mean() < 0.25
    np.testing.assert_allclose(got[~ambiguous], want[~ambiguous], atol=2e-5)


@pytest.mark.parametrize('mode', ['repeat', 'mirror'])
def test_modulo_wraps_are_exact_over_the_whole_coordinate_range(mode):
    """Far from the image (texel coordinates up to the ±2^22 clamp), ``x·(1/n)`` rounds, and
    the floor can miss the quotient by one: the result must still be numpy's exact modulo,
    with the reciprocal computed inside or passed in (float32, as the filters pass it). Sizes
    include ones whose float32 reciprocal is below 1/n (where multiples of n need the
    correction), and multiples of n and their neighbours: the 100 nearest each limit and 20000
    drawn between (about a fifth of the multiples need the correction)."""
    rng = np.random.default_rng(3)
    for n in (3, 10, 11, 37, 100, 333, 1000, 1023, 4097, 12345):
        k = np.arange(-(2 ** 22) // n, (2 ** 22) // n + 1)
        k = np.unique(np.concatenate([k[:100], k[-100:], rng.choice(k, min(len(k), 20000))]))
        x = np.concatenate([k * n, k * n - 1, k * n + 1])
        x = x[np.abs(x) <= 2 ** 22]
        if mode == 'repeat':
            want = np.mod(x, n)
        else:
            m = np.mod(x, 2 * n)
            want = np.where(m >= n, 2 * n - 1 - m, m)
        for inv in (None, mi.Float(np.float32(1.0 / n))):
            got = A(wrap_1d(mi.Float(x.astype(np.float64)), n, mode, inv))
            np.testing.assert_array_equal(got, want, err_msg=f'n={n}')


@pytest.mark.parametrize('wrap', ['repeat', 'clamp', 'mirror', 'octahedralsphere'])
def test_non_finite_coordinates_read_texel_zero(wrap, rng):
    """NaN and ±inf texture coordinates are replaced by texel coordinate 0 (documented in
    wrap.py): a point lookup then reads column 0 (or row 0) of the image, exactly."""
    img = rng.random((5, 7, 3))
    tex = imagemap(img, filter='point', wrap=wrap)
    nan, inf = float('nan'), float('inf')
    got = A(tex.eval(make_si([[nan, 0.5], [inf, 0.3], [0.5, -inf], [-inf, nan]])))
    want = np.stack([img[2, 0], img[1, 0], img[0, 3], img[0, 0]])
    np.testing.assert_array_equal(got.astype(np.float32), want.astype(np.float32))


@pytest.mark.parametrize('mode', ['black', 'octahedralsphere'])
def test_wrap_1d_refuses_modes_that_do_not_wrap_one_axis_alone(mode):
    """``wrap_1d`` is for the modes that wrap each axis on its own (repeat, clamp, mirror):
    ``black`` needs a validity mask and ``octahedralsphere`` couples the axes, so every caller
    (``wrap_2d``, ``adjacent_wrapped``, the box filter's tables) handles them before calling it,
    and ``wrap_1d`` refuses them instead of returning an index without its mask."""
    with pytest.raises(ValueError):
        wrap_1d(mi.Float([-1.0, 2.0, 5.0]), 4, mode)


@pytest.mark.parametrize('mode', ['repeat', 'mirror'])
def test_lookups_keep_tiling_beyond_the_coordinate_clamp(mode, rng):
    """Texture coordinates whose texel coordinate lies beyond ±2^22 (a 64×8 image at u = 65536
    + …, v = 2^19 + …) read what the same lookup reads whole periods (65536, 2^19: even, so
    for mirror too) nearer the image — the wrap's own symmetry, for every filter (with
    footprints at level 0 and at level 1; and at u, v beyond 2^22 themselves) and the Gaussian
    pixel kernel; point and bilinear
    also equal Mitsuba's ``bitmap`` there. Every such lookup read one texel before (the clamp
    came before the wrap; found in a user trial). The coordinates are exact in float32 (u a
    multiple of 1/128, v of 1/16), so the two lookups see the same position: equal to float32
    rounding of the weights (1e-6 of texels in [0, 1])."""
    from mitsuba_pbrt_tex import gauss
    from mitsuba_pbrt_tex.mipmap import MIPMap, build_pyramid
    img = rng.random((8, 64, 3)).astype(np.float32)
    n = 256
    fu = rng.integers(0, 128, n) / 128.0
    fv = rng.integers(0, 16, n) / 16.0
    near = np.stack([fu, fv], 1)
    far = np.stack([65536.0 + fu, 2.0 ** 19 + fv], 1)
    assert (np.abs(far[:, 0] * 64) >= 2 ** 22).all() and (np.abs(far[:, 1] * 8) >= 2 ** 22).all()

    def lookup(tex, uv, d):
        si = make_si(uv)
        si.duv_dx = mi.Vector2f(d / 64, 0.3 * d / 8)
        si.duv_dy = mi.Vector2f(-0.2 * d / 64, d / 8)
        return A(tex.eval(si))

    # and beyond ±2^22 in texture coordinates themselves (the box filter clamped those; there
    # float32 holds halves: u, v = 2^22 + 0 or 1/2)
    half = rng.integers(0, 2, (n, 2)) / 2.0
    for filt in ('point', 'bilinear', 'trilinear', 'ewa', 'box'):
        tex = mi.load_dict({'type': 'pbrt_imagemap', 'data': mi.TensorXf(img), 'raw': True,
                            'filter': filt, 'wrap': mode})
        tex.prepare_differentials()
        for d in (0.0, 0.7, 2.5):
            np.testing.assert_allclose(lookup(tex, far, d), lookup(tex, near, d), atol=1e-6,
                                       err_msg=f'{filt}, footprint {d}')
            np.testing.assert_allclose(lookup(tex, 2.0 ** 22 + half, d), lookup(tex, half, d),
                                       atol=1e-6, err_msg=f'{filt}, footprint {d}, u ≥ 2^22')
    for filt, kind in (('point', 'nearest'), ('bilinear', 'bilinear')):
        ours = mi.load_dict({'type': 'pbrt_imagemap', 'data': mi.TensorXf(img), 'raw': True,
                             'filter': filt, 'wrap': mode})
        theirs = mi.load_dict({'type': 'bitmap', 'data': mi.TensorXf(img), 'raw': True,
                               'filter_type': kind, 'wrap_mode': mode})
        np.testing.assert_allclose(lookup(ours, far, 0.0), A(theirs.eval(make_si(far))),
                                   atol=1e-6, err_msg=filt)
    mip = MIPMap(build_pyramid(mi.TensorXf(img), True), mode)
    rfilter = mi.load_dict({'type': 'gaussian'})

    def kernel(uv):
        return A(gauss.pixel_filter(
            mip, mi.Point2f(uv[:, 0], uv[:, 1]), mi.Vector2f(1.5 / 64, 0.2 / 8),
            mi.Vector2f(-0.3 / 64, 1.2 / 8), mi.Float(0.02), mi.Float(-0.03),
            gauss.FilmKernel(0.5, 2.0, rfilter), True))
    np.testing.assert_allclose(kernel(far), kernel(near), atol=1e-6)
