"""pbrt_imagemap ``filter="box"``: the exact area average of the bilinear reconstruction over the
footprint parallelogram, against an independent polygon-clipping reference
(``reference_box.py``), at the level the documented rule selects; hard cases; errors; texel
gradients against finite differences.

Tolerances: the package works in float32 (its inputs — uv and the derivatives — are float32 too,
and the references are fed the same float32-rounded values). Each texel weight is computed from
positions at most the footprint's extent plus one texel from an integer origin, so a weight
carries a rounding of ~2^-24 of the extent; the sum is divided by the sum of the same weights
(the area of the polygon actually integrated), so what is left scales as 2^-24 × (position /
short side) × (the texture's variation over the footprint): ≤ 2^-24 × 64 × 1 ≈ 4e-6 for the
64:1 footprints of values in [0, 1] here (measured, 24 random trials per wrap: 2.9e-6 at level 0,
2.3e-6 on coarser levels). ``atol = 1e-5`` keeps a 3× margin and still fails on any wrong
weight (a misplaced texel or band changes results by > 1e-3).
"""

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import reference_box as rbox
import reference_mipmap as ref
from conftest import A, assert_texel_gradients_match_fd, make_si

MAX_BANDS = 16         # documented in mitsuba_pbrt_tex.box: the level rule the test re-derives
MAX_PERIMETER = 128    # (the same module)
WRAPS = ['repeat', 'mirror', 'clamp', 'black']


def imagemap(img, **kw):
    return mi.load_dict({'type': 'pbrt_imagemap', 'data': mi.TensorXf(np.asarray(img, np.float32)),
                         'filter': 'box', **kw})


def f32(x):
    return np.asarray(x, np.float32).astype(np.float64)


def footprints(rng, n, major_texels, ratios, res):
    """Random orientations; major axis lengths in texels, minor = major / ratio."""
    ang = rng.uniform(0, math.pi, n)
    minor = major_texels / ratios
    d0 = np.stack([np.cos(ang), np.sin(ang)], 1) * (major_texels / res)[:, None]
    d1 = np.stack([-np.sin(ang), np.cos(ang)], 1) * (minor / res)[:, None]
    # shear a little, so the footprints are parallelograms, not just rectangles
    d1 = d1 + 0.2 * d0 * rng.uniform(-1, 1, (n, 1))
    return f32(d0), f32(d1)


def expected_level(img_shape, d0, d1, n_levels):
    """The documented rule: the finest level at which the footprint's short side (area /
    longest side) is at most MAX_BANDS texels and its Manhattan perimeter at most MAX_PERIMETER
    texels (level-0 texels halve per level)."""
    h, w = img_shape
    a, b = np.array([d0[0] * w, d0[1] * h]), np.array([d1[0] * w, d1[1] * h])
    area = abs(a[0] * b[1] - a[1] * b[0])
    short = area / max(np.linalg.norm(a), np.linalg.norm(b))
    perimeter = 2 * (np.abs(a).sum() + np.abs(b).sum())
    want = max(math.ceil(math.log2(short / MAX_BANDS)), math.ceil(math.log2(perimeter / MAX_PERIMETER)))
    return int(np.clip(want, 0, n_levels - 1))


@pytest.mark.parametrize('wrap', WRAPS)
@pytest.mark.parametrize('channels', [1, 3])
def test_level0_matches_polygon_clipping(wrap, channels, rng):
    """Footprints with up to 16 texels across (level 0): random orientation and shear, anisotropy
    1–64:1, sub-texel minor axes down to 0.002 texel, lookups across the image edges. (Those 6 to
    16 texels across went to levels 1–2 with the older rule of 6, whose blur of the outline left
    pixel averages of a minified grid image at up to 19× a reference's noise: a user trial.)"""
    img = rng.random((13, 19, channels))
    tex = imagemap(img, wrap=wrap)
    n = 24
    uv = f32(rng.uniform(-0.4, 1.4, (n, 2)))
    major = np.concatenate([rng.uniform(0.05, 1.0, n // 3), rng.uniform(1, 6, n // 3),
                            rng.uniform(6, 16, n - 2 * (n // 3))])
    ratios = rng.choice([1.0, 4.0, 16.0, 64.0], n)
    d0, d1 = footprints(rng, n, major, ratios, 19)
    got = A(tex.eval_3(make_si(uv, d0, d1)) if channels == 3 else tex.eval_1(make_si(uv, d0, d1)))
    want = np.array([rbox.box_average(img, uv[k, 0], uv[k, 1], d0[k], d1[k], wrap)
                     for k in range(n)])
    if channels == 1:
        want = want[:, 0]
    for k in range(n):
        assert expected_level(img.shape[:2], d0[k], d1[k], 5) == 0
    np.testing.assert_allclose(got, want, atol=1e-5)


@pytest.mark.parametrize('wrap', WRAPS)
def test_coarser_levels_match_polygon_clipping(wrap, rng):
    """Minified footprints (20–1920 texels long, up to 64:1): the exact average at the level the
    rule picks (the finest with a short side ≤ MAX_BANDS and a Manhattan perimeter ≤
    MAX_PERIMETER texels), on the reference pyramid's level."""
    img = rng.random((48, 64, 3))
    levels = ref.pyramid(img)
    tex = imagemap(img, wrap=wrap)
    n = 16
    uv = f32(rng.uniform(-0.2, 1.2, (n, 2)))
    ratios = rng.choice([1.0, 2.0, 8.0, 64.0], n)
    major = rng.uniform(20, 120, n) * np.where(ratios > 8, 16, 1)
    d0, d1 = footprints(rng, n, major, ratios, 64)
    got = A(tex.eval_3(make_si(uv, d0, d1)))
    picked = [expected_level(img.shape[:2], d0[k], d1[k], len(levels)) for k in range(n)]
    assert max(picked) >= 2
    want = np.array([rbox.box_average(levels[picked[k]], uv[k, 0], uv[k, 1], d0[k], d1[k], wrap)
                     for k in range(n)])
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_nearly_axis_aligned_footprints_end_and_match_polygon_clipping(rng):
    """Rectangles turned by 0 to 1e-6 rad (either way, either orientation, 0.3–6 texels across,
    squares among them): two corners are computed from the centre (rounded), so a side meant to
    run down the left chain can run an ulp up, and the walk then looked for its next row
    boundary behind it for ever — the first case is a camera hit of a Cornell-box render that
    hung (its uv, partials and tiling, on a 16² image). Every lookup ends and equals polygon
    clipping (atol 1e-5, as above)."""
    img = rng.random((16, 16, 3))
    tex = imagemap(img, to_uv=mi.ScalarTransform4f().scale([3, 3, 1]))
    n = 40
    hit = f32([[0.801102340, 0.527704656]])
    hit_d0, hit_d1 = f32([[1.36390105e-02, -8.20471069e-09]]), f32([[1.02140951e-09, -1.36691350e-02]])
    ang = rng.choice([0.0, 1e-9, 1e-8, 1e-7, 1e-6], n) * rng.choice([-1, 1], n) \
        + rng.choice([0.0, math.pi / 2], n)
    size = rng.uniform(0.3, 6.0, (n, 1)) / 48
    aspect = np.where(rng.random((n, 1)) < 0.5, 1.0, rng.uniform(0.2, 5.0, (n, 1)))
    flip = rng.choice([-1.0, 1.0], (n, 1))
    d0 = f32(np.stack([np.cos(ang), np.sin(ang)], 1) * size)
    d1 = f32(np.stack([-np.sin(ang), np.cos(ang)], 1) * size * aspect * flip)
    uv = f32(np.concatenate([hit, rng.uniform(0, 1, (n, 2))]))
    d0, d1 = np.concatenate([hit_d0, d0]), np.concatenate([hit_d1, d1])
    # and each transposed (the walk's rows run along either texture axis)
    uv, d0, d1 = (np.concatenate([v, v[:, ::-1]]) for v in (uv, d0, d1))
    got = A(tex.eval_3(make_si(uv, d0, d1)))
    want = np.array([rbox.box_average(img, 3 * uv[k, 0], 3 * uv[k, 1], 3 * d0[k], 3 * d1[k],
                                      'repeat') for k in range(len(uv))])
    for k in range(len(uv)):
        assert expected_level(img.shape[:2], 3 * d0[k], 3 * d1[k], 5) == 0
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_power_of_two_repeat_of_a_non_square_image_in_either_frame(rng):
    """A 32×8 image (power-of-two sides: repeat wraps by bit masks, one per axis) with
    footprints both taller and wider than they are across (the walk's frame transposed for
    the tall ones, its masks with it), reaching over the image's edges: equal to polygon
    clipping (atol 1e-5, as above)."""
    img = rng.random((8, 32, 3))
    tex = imagemap(img, wrap='repeat')
    n = 24
    uv = f32(rng.uniform(-0.5, 1.5, (n, 2)))
    d0, d1 = footprints(rng, n, rng.uniform(0.5, 6.0, n), rng.choice([1.0, 4.0, 8.0], n), 32)
    d0[:, 1], d1[:, 1] = 4 * d0[:, 1], 4 * d1[:, 1]           # texel units alike on both axes
    got = A(tex.eval_3(make_si(uv, d0, d1)))
    want = np.array([rbox.box_average(img, uv[k, 0], uv[k, 1], d0[k], d1[k], 'repeat')
                     for k in range(n)])
    for k in range(n):
        assert expected_level(img.shape[:2], d0[k], d1[k], 4) == 0
    taller = np.abs(d0[:, 1] * 8) + np.abs(d1[:, 1] * 8) > np.abs(d0[:, 0] * 32) + np.abs(d1[:, 0] * 32)
    assert 3 <= taller.sum() <= n - 3
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_far_from_the_origin_keeps_float32_digits(rng):
    """A 1024² image, lookups near its far corner (positions up to 1024 texels): each value is an
    integral over texels near the footprint, so nothing grows with the position. With a
    power-of-two size ``s·1024`` is exact in float32 (no position rounding at all; another size
    adds 2^-24 × size texel of it, as for any float32 lookup), so the level-0 tolerance holds:
    ``atol = 1e-5`` (measured: 2e-7). Prefix sums of whole rows in float32 would be off by
    ~2^-24 × 512 (a row's integral) / (the footprint's area per band) ≈ 1e-5 and more."""
    img = rng.random((1024, 1024, 1))
    tex = imagemap(img)
    n = 12
    uv = f32(rng.uniform(0.9, 1.0, (n, 2)))
    d0, d1 = footprints(rng, n, rng.uniform(2, 12, n), np.full(n, 8.0), 1024)
    got = A(tex.eval_1(make_si(uv, d0, d1)))
    want = np.array([rbox.box_average(img, uv[k, 0], uv[k, 1], d0[k], d1[k], 'repeat')[0]
                     for k in range(n)])
    for k in range(n):
        assert expected_level(img.shape[:2], d0[k], d1[k], 11) == 0
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_point_footprints_are_bilinear_and_tiny_ones_converge_to_it(rng):
    """Zero or collinear derivatives (no area): the bilinear lookup at level 0. A 1e-3-texel
    footprint differs from it by at most its size times the largest texel difference."""
    img = rng.random((16, 16, 3))
    tex = imagemap(img)
    n = 40
    uv = f32(rng.uniform(0, 1, (n, 2)))
    bil = ref.bilinear(img, uv[:, 0], uv[:, 1], 'repeat')
    zero = np.zeros((n, 2))
    line = f32(rng.normal(size=(n, 2)) * 0.1)
    np.testing.assert_allclose(A(tex.eval_3(make_si(uv, zero, zero))), bil, atol=1e-5)
    np.testing.assert_allclose(A(tex.eval_3(make_si(uv, line, 2 * line))), bil, atol=1e-5)
    d0, d1 = footprints(rng, n, np.full(n, 1e-3), np.full(n, 1.0), 16)
    np.testing.assert_allclose(A(tex.eval_3(make_si(uv, d0, d1))), bil, atol=2e-3)


@pytest.mark.parametrize('wrap', WRAPS)
def test_footprint_covering_texture(wrap, rng):
    """Repeat/mirror: a footprint of exactly 2×2 (mirror: 2×2 periods of the mirrored image)
    image copies averages to the image mean, by periodicity — exactly, wherever it is."""
    img = rng.random((8, 8, 3))
    tex = imagemap(img, wrap=wrap)
    n = 20
    uv = rng.uniform(-2, 3, (n, 2))
    d0, d1 = np.tile([2.0, 0.0], (n, 1)), np.tile([0.0, 2.0], (n, 1))
    out = A(tex.eval_3(make_si(uv, d0, d1)))
    if wrap in ('repeat', 'mirror'):
        np.testing.assert_allclose(out, np.tile(img.mean((0, 1)), (n, 1)), atol=1e-5)
    else:
        assert np.isfinite(out).all()


@pytest.mark.parametrize('wrap', ['repeat', 'mirror', 'clamp'])
@pytest.mark.parametrize('shape, bound', [((33, 5), 5e-4), ((3, 1000), 5e-4), ((129, 129), 1e-5)])
def test_a_constant_image_averages_to_itself_to_the_sums_rounding(wrap, shape, bound, rng):
    """A constant image returns its value to the float32 rounding of the walk's two sums (texel
    weights and weights alone), whatever the footprint: 1e-4 to 1e3 image widths across,
    1:1 to 64:1, any orientation. The roundings grow with the walk's length and the
    cancellation of its partial weights (both signs, up to ~10× the area): elongated images,
    whose coarse levels are strips a texel or two wide, walk longest — up to ~10³ weights, so
    ~10³·10·6e-8 ≈ 6e-4 at worst, 5e-4 the bound (measured 1.8e-5 on 33×5 and 1.3–1.8e-4 on
    3×1000; the docstring had said "exactly", found by a user trial and a review); square ones
    stay within 1e-5 (measured 3e-6 with a level-0 limit of 6 texels across, 4e-6 with 16)."""
    c = 0.3712
    tex = imagemap(np.full(shape + (1,), c), wrap=wrap)
    n = 4000
    size = np.exp(rng.uniform(np.log(1e-4), np.log(1e3), n))
    theta = rng.uniform(0, np.pi, n)
    ratio = rng.choice([1.0, 4.0, 64.0], n)
    d0 = size[:, None] * np.stack([np.cos(theta), np.sin(theta)], 1)
    d1 = (size / ratio)[:, None] * np.stack([-np.sin(theta), np.cos(theta)], 1)
    out = A(tex.eval_1(make_si(rng.uniform(-3, 3, (n, 2)), d0, d1)))
    assert np.abs(out - np.float32(c)).max() <= bound * c


@pytest.mark.parametrize('shape', [(1, 1), (1, 7), (7, 1), (37, 53)])
@pytest.mark.parametrize('wrap', WRAPS)
def test_hard_cases_stay_finite_and_in_range(shape, wrap, rng):
    img = rng.random(shape + (3,))
    tex = imagemap(img, wrap=wrap)
    inf, nan = float('inf'), float('nan')
    uv = np.array([[0.5, 0.5], [1e6, -1e6], [-1e6, 3e5], [nan, 0.2], [inf, -inf], [0.3, nan],
                   [0.0, 1.0], [1.0 - 1e-7, 1e-7], [2.5, -3.5], [0.25, 0.75]] * 3)
    d0 = np.array([[0, 0], [nan, 1], [inf, 0], [1e-3, 1e-9], [1e8, 1e8], [0.01, 0.0], [1e-6, 0],
                   [0.3, 0.3], [1e30, -1e30], [0.02, 0.01]] * 3)
    d1 = np.array([[0, 0], [0, nan], [0, inf], [0, 0], [1e-8, 0], [0.0, 0.0], [0, 1e-12],
                   [-0.3, 0.3], [0, 1e-30], [-1e-8, 2e-8]] * 3)
    out = A(tex.eval_3(make_si(uv, d0, d1)))          # RGB in every variant
    assert out.shape == (len(uv), 3) and np.isfinite(out).all()
    lo = 0.0 if wrap == 'black' else img.min()
    assert (out >= lo - 1e-5).all() and (out <= img.max() + 1e-5).all()


def test_box_filter_needs_the_tables_of_its_wrap_mode(rng):
    """Called directly, the box filter refuses missing tables or tables of another wrap mode."""
    from mitsuba_pbrt_tex.box import build_box_tables
    from mitsuba_pbrt_tex.filters import TextureFilter
    from mitsuba_pbrt_tex.mapping import TexCoord2D
    from mitsuba_pbrt_tex.mipmap import build_pyramid
    pyr = build_pyramid(mi.TensorXf(rng.random((8, 8, 1)).astype(np.float32)))
    filt = TextureFilter('box', 'repeat', 8.0, 1.0)
    tc = TexCoord2D(mi.Point2f(0.5, 0.5), dsdx=mi.Float(0.1), dsdy=mi.Float(0),
                    dtdx=mi.Float(0), dtdy=mi.Float(0.1))
    for tables in (None, build_box_tables(pyr, 'clamp')):
        with pytest.raises(ValueError, match='prefix tables'):
            filt(pyr, tc, mi.Bool(True), tables)
    assert np.isfinite(A(filt(pyr, tc, mi.Bool(True), build_box_tables(pyr, 'repeat')))).all()


def test_box_refuses_octahedral_wrap():
    with pytest.raises(RuntimeError) as e:
        imagemap(np.ones((4, 4, 1)), wrap='octahedralsphere')
    msg = str(e.value)
    for word in ('pbrt_imagemap', '"filter"', '"box"', 'octahedralsphere', 'repeat, mirror'):
        assert word in msg, (word, msg)


def test_parameter_update_rebuilds_tables(rng):
    """New texels (another shape) through params.update(): lookups read the new image."""
    tex = imagemap(rng.random((8, 8, 3)))
    params = mi.traverse(tex)
    img = rng.random((12, 6, 3))
    params['data'] = mi.TensorXf(img.astype(np.float32))
    params.update()
    uv = f32(rng.uniform(0, 1, (10, 2)))
    d0, d1 = footprints(rng, 10, rng.uniform(0.5, 4, 10), np.full(10, 2.0), 6)
    want = np.array([rbox.box_average(img, uv[k, 0], uv[k, 1], d0[k], d1[k], 'repeat')
                     for k in range(10)])
    np.testing.assert_allclose(A(tex.eval_3(make_si(uv, d0, d1))), want, atol=1e-5)


def test_backward_reaches_texels_and_matches_finite_differences(rng):
    """d(loss)/d(data) by dr.backward equals central differences of the loss, which is linear in
    the texels (exact up to float32 rounding: rtol 1e-3), for footprints at level 0 and above."""
    img = rng.random((8, 12, 3)).astype(np.float32)
    tex = imagemap(img, wrap='mirror')
    n = 48
    uv = rng.uniform(0, 1, (n, 2))
    major = np.concatenate([rng.uniform(0.3, 3, n // 2), rng.uniform(10, 30, n - n // 2)])
    d0, d1 = footprints(rng, n, major, rng.choice([1.0, 8.0], n), 12)
    si = make_si(uv, d0, d1)
    w = mi.Float(rng.random(n))
    assert_texel_gradients_match_fd(tex, img, si, w, rng)


def test_render_gradient_through_box_under_pbrt_path(rng):
    """Texel gradients of a rendered image (pbrt_path, grazing plane) against central finite
    differences at the gradient seed (the project's check_gradient: 2% relative)."""
    from test_gradients import check_gradient, image_tex, scene_with
    scene = scene_with(image_tex(rng, 'box'))
    check_gradient(scene, 'plane.bsdf.reflectance.data', rng)
