"""pbrt_imagemap as a drop-in for Mitsuba's bitmap beyond reflectances (issue #15): position
sampling for textured emitters, light tracing, bare surface interactions, ``to_uv`` through
``mi.traverse``, 1-channel ``eval_3`` and integer data. Mitsuba's ``bitmap`` is the reference."""

import math
import os

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from conftest import A, make_si
from mitsuba_pbrt_tex.sampling import LUMINANCE

T = mi.ScalarTransform4f
FILTERS = ['point', 'bilinear', 'trilinear', 'ewa']
WRAPS = ['repeat', 'black', 'clamp', 'mirror', 'octahedralsphere']


def imagemap(img, **kw):
    return mi.load_dict({'type': 'pbrt_imagemap', 'data': mi.TensorXf(np.asarray(img, np.float32)),
                         **kw})


def test_image(rng, h=6, w=7, channels=3):
    """Random texels with a black block (density 0 must appear exactly there) and a bright one."""
    img = rng.uniform(0.05, 1.0, (h, w, channels))
    img[1:3, 2:4] = 0.0
    img[4, 5] = 20.0
    return img


test_image.__test__ = False


def uv_grid(n, lo=0.0, hi=1.0):
    """n×n points strictly inside [lo, hi]² (cell midpoints), lanes first."""
    c = lo + (np.arange(n) + 0.5) / n * (hi - lo)
    uu, vv = np.meshgrid(c, c)
    return np.stack([uu.ravel(), vv.ravel()], 1)


def lum(x):
    """Luminance of eval's result: RGB lanes (n, 3), mono lanes (n, 1) or (n,)."""
    x = np.asarray(x)
    if x.ndim == 2:
        return x @ LUMINANCE if x.shape[1] == 3 else x[:, 0]
    return x


# ------------------------------------------------------------------------------ bare interactions
@pytest.mark.parametrize('filt', ['nearest', 'bilinear'])
def test_bare_surface_interaction_matches_bitmap(filt, rng):
    """A bare mi.SurfaceInteraction3f() with only uv set (other fields of width 0): every eval
    works and equals bitmap's (≤ 1e-6: float32 rounding, as the parity tests)."""
    img = rng.random((9, 11, 3)).astype(np.float32)
    b = mi.load_dict({'type': 'bitmap', 'bitmap': mi.Bitmap(img), 'filter_type': filt, 'raw': True})
    ours = [mi.load_dict({'type': 'pbrt_imagemap', 'bitmap': mi.Bitmap(img), 'filter_type': filt})]
    if filt == 'bilinear':          # without a footprint EWA and box are that bilinear lookup
        ours += [mi.load_dict({'type': 'pbrt_imagemap', 'bitmap': mi.Bitmap(img),
                               'filter': other}) for other in ('ewa', 'box')]
    for n in (1, 257):
        si = mi.SurfaceInteraction3f()
        uv = rng.uniform(-0.5, 1.5, (n, 2))
        si.uv = mi.Point2f(uv[:, 0], uv[:, 1])
        assert dr.width(si.duv_dx) == 0 and dr.width(si.p) == 0
        for o in ours:
            for method in ('eval', 'eval_1', 'eval_3', 'eval_1_grad'):
                want, got = A(getattr(b, method)(si)), A(getattr(o, method)(si))
                assert got.shape == want.shape
                # eval_1_grad: texel-scaled differences of float32 values (11 texels/unit)
                tol = 1e-6 if method != 'eval_1_grad' else 1e-4 * 11
                assert np.max(np.abs(got - want)) <= tol, (method, o)


def test_bare_surface_interaction_every_texture():
    """Every pbrt_* texture evaluates a bare interaction (finite values, no size error)."""
    si = mi.SurfaceInteraction3f()
    si.uv = mi.Point2f(0.3, 0.7)
    for d in ({'type': 'pbrt_checkerboard', 'uscale': 4}, {'type': 'pbrt_checkerboard',
              'dimension': 3}, {'type': 'pbrt_dots'}, {'type': 'pbrt_fbm'}, {'type': 'pbrt_marble'},
              {'type': 'pbrt_uv'}, {'type': 'pbrt_bilerp'}, {'type': 'pbrt_directionmix'},
              {'type': 'pbrt_imagemap', 'data': mi.TensorXf(np.ones((2, 2, 1), np.float32)),
               'mapping': 'spherical'},
              {'type': 'pbrt_supersample', 'texture': {'type': 'pbrt_checkerboard'}},
              {'type': 'pbrt_mix', 'tex2': {'type': 'pbrt_fbm'}}, {'type': 'pbrt_scale'},
              {'type': 'pbrt_constant'}, {'type': 'pbrt_wrinkled'}, {'type': 'pbrt_windy'}):
        tex = mi.load_dict(d)
        # eval_1_grad too (pbrt's bump difference of the procedural and composite textures
        # failed with a Dr.Jit size error: the bare record's p, dp_du, duv_dx are empty)
        for method in ('eval', 'eval_1', 'eval_3', 'eval_1_grad'):
            assert np.isfinite(A(getattr(tex, method)(si))).all(), (d, method)


# ------------------------------------------------------------------------------ position density
@pytest.mark.parametrize('wrap', WRAPS)
@pytest.mark.parametrize('filt', FILTERS)
def test_pdf_position_is_proportional_to_eval(filt, wrap, rng):
    """pdf_position(uv) = luminance(eval(uv)) / ∫ luminance(eval) for every filter and wrap, at
    points inside texels and within half a texel of every edge, where the lookup mixes in the
    wrap mode's neighbours; 0 exactly where eval is 0; and 0 outside [0, 1]²."""
    img = test_image(rng)
    tex = imagemap(img, filter=filt, wrap=wrap)
    uv = uv_grid(168)
    si = make_si(uv)
    value = lum(A(tex.eval(si)))
    pdf = A(tex.pdf_position(mi.Point2f(uv[:, 0], uv[:, 1])))
    # ∫ eval over [0, 1]² by the midpoint rule on this grid, which is aligned with the texel
    # edges and centres (168 = 2·12·7: 24 or 28 points per texel): exact for piecewise-constant
    # and piecewise-bilinear functions, so only float32 rounding (~1e-6) remains; 1e-4 relative
    integral = value.mean()
    live = value > 1e-4 * value.max()
    np.testing.assert_allclose(pdf[live] * integral, value[live], rtol=1e-4)
    assert np.all(pdf[value == 0] == 0) and np.any(value == 0)
    outside = mi.Point2f([-0.01, 1.01, 0.5, 0.5], [0.5, 0.5, -0.2, 1.3])
    assert np.all(A(tex.pdf_position(outside)) == 0)
    # the closed square's edges are inside: a constant image has density 1 there too
    edges = mi.Point2f([0, 1, 0.5, 0.5, 0, 1], [0.5, 0.5, 0, 1, 0, 1])
    flat = imagemap(np.ones((5, 6, 3)), filter=filt, wrap=wrap, uscale=2, vscale=3)
    np.testing.assert_allclose(A(flat.pdf_position(edges)), 1, rtol=1e-6)


@pytest.mark.parametrize('filt,wrap', [('bilinear', 'repeat'), ('bilinear', 'black'),
                                       ('ewa', 'octahedralsphere'), ('point', 'clamp'),
                                       ('trilinear', 'mirror')])
def test_sample_position_follows_pdf_position(filt, wrap, rng):
    """A histogram of 2^18 sample_position points over 14×12 bins matches the integral of
    pdf_position over each bin (within 5 binomial standard deviations + 1 count: a false alarm
    has probability < 1e-4 over all bins), and the returned pdf equals pdf_position at the point
    (relative 1e-4: float32 rounding of the cell position)."""
    img = test_image(rng)
    tex = imagemap(img, filter=filt, wrap=wrap)
    n = 2 ** 18
    sample = rng.random((n, 2))
    uv, pdf = tex.sample_position(mi.Point2f(sample[:, 0], sample[:, 1]))
    uv, pdf = A(uv), A(pdf)
    assert np.all((uv >= 0) & (uv <= 1))
    np.testing.assert_allclose(pdf, A(tex.pdf_position(mi.Point2f(uv[:, 0], uv[:, 1]))),
                               rtol=1e-4, atol=1e-6)
    bx, by = 14, 12
    counts = np.histogram2d(uv[:, 1], uv[:, 0], bins=[by, bx], range=[[0, 1], [0, 1]])[0]
    # expected: pdf integrated over each bin by a 10×10 midpoint rule per bin
    sub = 10
    gx = (np.arange(bx * sub) + 0.5) / (bx * sub)
    gy = (np.arange(by * sub) + 0.5) / (by * sub)
    uu, vv = np.meshgrid(gx, gy)
    dens = A(tex.pdf_position(mi.Point2f(uu.ravel(), vv.ravel()))).reshape(by * sub, bx * sub)
    prob = dens.reshape(by, sub, bx, sub).mean((1, 3)) / (bx * by)
    assert abs(prob.sum() - 1) < 2e-3              # normalised (midpoint rule error)
    expected = n * prob
    sigma = np.sqrt(n * prob * (1 - prob))
    assert np.all(np.abs(counts - expected) <= 5 * sigma + 1 + 2e-3 * expected), \
        np.max(np.abs(counts - expected) / (sigma + 1))


@pytest.mark.parametrize('wrap', WRAPS)
@pytest.mark.parametrize('filt', FILTERS)
def test_sample_position_passes_mitsubas_chi2_test(filt, wrap, rng):
    """Mitsuba's own test of bitmap's position sampling (v3.9.1 test_bitmap.py test01: its
    chi-square harness, 201² cells, significance 1%) with pbrt_imagemap substituted, on every
    filter and wrap (its image, carrot.png, is in Mitsuba's data repository: ours here)."""
    tex = imagemap(test_image(rng), filter=filt, wrap=wrap)
    chi2 = mi.chi2.ChiSquareTest(
        domain=mi.chi2.PlanarDomain(mi.ScalarBoundingBox2f([0, 0], [1, 1])),
        sample_func=lambda s: tex.sample_position(s)[0],
        pdf_func=lambda p: tex.pdf_position(p), sample_dim=2, res=201, ires=8)
    assert chi2.run(), chi2.messages


@pytest.mark.parametrize('wrap', ['repeat', 'clamp', 'mirror'])
@pytest.mark.parametrize('filt', ['point', 'bilinear'])
def test_sampled_pdf_equals_pdf_position_on_texel_edges(filt, wrap, rng):
    """Samples on a regular grid that includes 0 and 1 (so points land exactly on texel edges
    and on the far edge; a 61×43 image makes (i + frac)/W round across edges): the pdf
    sample_position returns equals pdf_position at the returned point, which MIS relies on:
    exactly for point (the same texel); for bilinear to 1e-4 relative (the returned density is
    interpolated at the cell-local warped point, pdf_position re-derives that point from uv·W:
    float32 rounding of the position times the interpolant's slope; measured ≤ 2e-5). (Mitsuba's
    test07 of bitmap checks the same.)"""
    g = np.linspace(0, 1, 301)
    u, v = np.meshgrid(g, g)
    # random float texels, and an 8-bit sRGB image (as Mitsuba's test: there the sample 1 gives
    # the last texel with fraction 1, and repeat would wrap (W-1 + 1)/W = 1 onto texel 0)
    codes = np.random.default_rng(3).integers(0, 256, (40, 60, 3)).astype(np.uint8)
    codes[:, :10] = 5
    for img in (rng.uniform(0.01, 1.0, (43, 61, 3)), codes):
        tex = imagemap(img, filter=filt, wrap=wrap) if img.dtype != np.uint8 else \
            mi.load_dict({'type': 'pbrt_imagemap', 'filter': filt, 'wrap': wrap,
                          'bitmap': mi.Bitmap(img, pixel_format=mi.Bitmap.PixelFormat.RGB)})
        uv, pdf = tex.sample_position(mi.Point2f(u.ravel(), v.ravel()))
        assert np.all((A(uv) >= 0) & (A(uv) <= 1))
        np.testing.assert_allclose(A(pdf), A(tex.pdf_position(uv)),
                                   rtol=1e-4 if filt != 'point' else 0)


SPARSE_LIGHT_MAPPINGS = [
    ('3x3 tiles', {'uscale': 3, 'vscale': 3}),
    ('7x7 tiles', {'uscale': 7, 'vscale': 7}),
    ('7x7 point', {'uscale': 7, 'vscale': 7, 'filter': 'point'}),
    ('rotated 90, 7x7', {'to_uv': T().scale([7, 7, 1]) @ T().translate([1, 0, 0])
                         @ T().rotate([0, 0, 1], 90)}),
    ('mirrored 3x3', {'uscale': 3, 'vscale': -3, 'vdelta': 1, 'wrap': 'mirror'}),
]


@pytest.mark.parametrize('name,mapping', SPARSE_LIGHT_MAPPINGS,
                         ids=[m[0] for m in SPARSE_LIGHT_MAPPINGS])
def test_sampled_weight_is_flat_on_a_tiled_sparse_light(name, mapping, rng):
    """value / pdf of sample_position (what a light tracer weights a sample by) is the same
    for every sample of a tiled light that is mostly black: two lit texels on a 2048×4 image
    and on its transpose, tiled, rotated, mirrored. The returned density was the texture-space
    sampler's at the point it drew; mapped to uv and back that point moves by a few ulps, and
    next to a black texel's corner, where the density vanishes, the value there was up to
    1.85× (here) the density's share — on a mask light from a user trial one sample weighed 4e12
    where 0.44 was due. And the density at a uv must be read where the lookup reads the value:
    a 90° rotation's rounding term (cos = -4e-8) and a mirror wrap applied to the position
    before the lookup put them up to 4e-3 texel apart (weights 0.70–1.17× and 0.96–1.02× their
    median). Tolerance 1e-4 relative: float32 rounding (measured: 0)."""
    for shape in ((4, 2048), (2048, 4)):
        img = np.zeros(shape + (1,))
        h, w = shape
        img[h // 2, w // 3], img[h // 4, 2 * w // 3] = 1.0, 0.5
        tex = imagemap(img, **mapping)
        s = rng.random((2 ** 18, 2))
        uv, pdf = tex.sample_position(mi.Point2f(s[:, 0], s[:, 1]))
        value, pdf = A(tex.eval_1(make_si(A(uv)))), A(pdf)
        live = value > 0
        assert live.mean() > 0.99 and np.all(pdf[live] > 0)
        weight = value[live] / pdf[live]
        assert np.all(np.abs(weight / np.median(weight) - 1) < 1e-4), \
            (shape, weight.min() / np.median(weight), weight.max() / np.median(weight))


# (to_uv, uscale/vscale, ...) combinations whose density is exact (see mitsuba_pbrt_tex.sampling)
EXACT_MAPPINGS = [
    ('flip u', {'to_uv': T().translate([1, 0, 0]) @ T().scale([-1, 1, 1])}, 'clamp'),
    ('rotate 90', {'to_uv': T().translate([1, 0, 0]) @ T().rotate([0, 0, 1], 90)}, 'black'),
    ('3x2 tiles, offset', {'uscale': 3, 'vscale': 2, 'udelta': 0.3, 'vdelta': -0.45}, 'repeat'),
    ('2x mirrored', {'uscale': 2, 'vscale': -3, 'vdelta': 1}, 'mirror'),
]


@pytest.mark.parametrize('name,mapping,wrap', EXACT_MAPPINGS, ids=[m[0] for m in EXACT_MAPPINGS])
def test_position_density_follows_the_uv_mapping(name, mapping, wrap, rng):
    """With flips, 90° rotations and integer tilings the surface-uv density is still
    eval / ∫ eval (the emitter evaluates the mapped texture at the sampled uv), and samples
    follow it (mean of a test function: 5 standard errors)."""
    img = test_image(rng)
    tex = imagemap(img, filter='bilinear', wrap=wrap, **mapping)
    uv = uv_grid(336)
    value = lum(A(tex.eval(make_si(uv))))
    pdf = A(tex.pdf_position(mi.Point2f(uv[:, 0], uv[:, 1])))
    live = value > 1e-4 * value.max()
    # proportional: the ratio is flat to float32 rounding (1e-4 relative)
    ratio = pdf[live] / value[live]
    assert ratio.max() / ratio.min() - 1 < 1e-4
    assert np.all(pdf[value == 0] == 0)
    # normalised: midpoint rule on 336² points; with the offsets the grid is not aligned with
    # the texel centres, where the interpolant has kinks: error ≲ 1e-3 (measured 2e-4)
    assert abs(pdf.mean() - 1) < 1e-3
    # E[g(X)] under the sampler = ∫ g·pdf, for g = a smooth function of uv
    n = 2 ** 17
    s = rng.random((n, 2))
    x, p = tex.sample_position(mi.Point2f(s[:, 0], s[:, 1]))
    x = A(x)
    g = lambda q: np.sin(5 * q[:, 0]) + q[:, 1] ** 2
    want = np.mean(g(uv) * pdf)
    got = g(x)
    assert abs(got.mean() - want) < 5 * got.std() / math.sqrt(n) + 2e-3 * abs(want)


def test_unsupported_mapping_falls_back_to_uniform_with_warning(capfd, rng):
    """A rotation by 30° has no per-texel surface density: uniform sampling (pdf 1 on [0, 1]²,
    unbiased) and a warning naming the plugin and the mapping parameters."""
    img = test_image(rng)
    tex = imagemap(img, to_uv=T().rotate([0, 0, 1], 30))
    uv, pdf = tex.sample_position(mi.Point2f([0.2, 0.7], [0.4, 0.9]))
    np.testing.assert_array_equal(A(uv), np.float32([[0.2, 0.4], [0.7, 0.9]]))
    np.testing.assert_array_equal(A(pdf), [1, 1])
    np.testing.assert_array_equal(A(tex.pdf_position(mi.Point2f([0.5, 2], [0.5, 0.5]))), [1, 0])
    out = ''.join(capfd.readouterr())
    assert 'pbrt_imagemap' in out and '"to_uv"' in out and 'uniformly' in out


def test_position_density_with_invert_scale_and_one_channel(rng):
    """invert: the density is positive wherever the inverted texture is (it is the interpolant
    of the inverted texels, ≥ the inverted interpolant); 1-channel images and an all-black image
    (uniform density) work."""
    img = test_image(rng, channels=1)
    tex = imagemap(img, invert=True, scale=0.9)
    uv = uv_grid(100)
    value = A(tex.eval_1(make_si(uv)))
    pdf = A(tex.pdf_position(mi.Point2f(uv[:, 0], uv[:, 1])))
    assert np.all(pdf[value > 0] > 0)
    plain = imagemap(img)
    v1 = A(plain.eval_1(make_si(uv)))
    p1 = A(plain.pdf_position(mi.Point2f(uv[:, 0], uv[:, 1])))
    np.testing.assert_allclose(p1 * v1.mean(), v1, rtol=2e-3, atol=1e-6)
    black = imagemap(np.zeros((3, 4, 3)))
    np.testing.assert_array_equal(A(black.pdf_position(mi.Point2f([0.1, 0.6], [0.3, 0.2]))), 1)


def test_position_density_follows_parameter_updates(rng):
    """New data, scale (with invert) or to_uv written through params rebuild the density."""
    img = test_image(rng)
    tex = imagemap(img, invert=True)
    params = mi.traverse(tex)
    uv = uv_grid(60)
    q = mi.Point2f(uv[:, 0], uv[:, 1])

    def check():
        value = lum(A(tex.eval(make_si(uv))))
        pdf = A(tex.pdf_position(q))
        live = value > 1e-3 * value.max()
        ratio = pdf[live] / value[live]
        # invert clamps at 0 near the 20.0 texel only; elsewhere exactly proportional
        assert np.median(np.abs(ratio / np.median(ratio) - 1)) < 1e-4
        assert np.all(pdf[value > 0] > 0)
        return pdf

    before = check()
    params['data'] = mi.TensorXf(np.flip(img, 1).astype(np.float32))
    params.update()
    after_data = check()
    assert np.max(np.abs(after_data - before)) > 0.1
    params['scale'] = 0.5
    params.update()
    after_scale = check()
    assert np.max(np.abs(after_scale - after_data)) > 0.01
    params['to_uv'] = mi.ScalarAffineTransform3f().scale(mi.ScalarPoint2f(2, 1))
    params.update()
    after_to_uv = check()
    assert np.max(np.abs(after_to_uv - after_scale)) > 0.1


# ------------------------------------------------------------------------------ textured emitters
EMITTER_IMG = np.full((32, 32, 3), 0.05, np.float32)
EMITTER_IMG[20:22, 8:10] = [100.0, 80.0, 60.0]      # a small bright patch on a dim rectangle


def emitter_scene(radiance, integrator='direct', emitter=None, **kw):
    """A floor lit by a textured rectangle above it (seen from below the light, which is hidden)."""
    light = {'type': 'rectangle', 'to_world': T().translate([0, 0, 1]) @ T().rotate([1, 0, 0], 180)
             @ T().scale(0.6), 'emitter': {'type': 'area', 'radiance': radiance}}
    d = {'type': 'scene',
         'integrator': {'type': integrator, 'hide_emitters': True, **kw},
         'sensor': {'type': 'perspective', 'fov': 40,
                    'to_world': T().look_at([0, -4, 0.6], [0, 0, 0], [0, 0, 1]),
                    'sampler': {'type': 'independent'},
                    'film': {'type': 'hdrfilm', 'width': 48, 'height': 48,
                             'rfilter': {'type': 'box'}}},
         'floor': {'type': 'rectangle', 'to_world': T().scale(3), 'bsdf': {'type': 'diffuse'}}}
    if emitter is None:
        d['light'] = light
    else:
        d['light'] = emitter
    return mi.load_dict(d)


def bitmap_tex(img, **kw):
    return {'type': 'bitmap', 'bitmap': mi.Bitmap(np.asarray(img, np.float32)), 'raw': True, **kw}


def ours_tex(img, **kw):
    return {'type': 'pbrt_imagemap', 'bitmap': mi.Bitmap(np.asarray(img, np.float32)), 'raw': True,
            **kw}


def rmse(a, b):
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


# Equivalent emitters: (ours, bitmap) textures with the same radiance on the surface. bitmap
# (Mitsuba 3.9.1) ignores to_uv when it samples positions, so its to_uv cases are given to it as
# transformed data instead.
EMITTERS = [
    ('bilinear', ours_tex(EMITTER_IMG), bitmap_tex(EMITTER_IMG)),
    ('point', ours_tex(EMITTER_IMG, filter='point'),
     bitmap_tex(EMITTER_IMG, filter_type='nearest')),
    ('ewa clamp', ours_tex(EMITTER_IMG, filter='ewa', wrap='clamp'),
     bitmap_tex(EMITTER_IMG, wrap_mode='clamp')),
    ('to_uv flip', ours_tex(EMITTER_IMG, to_uv=T().translate([1, 0, 0]) @ T().scale([-1, 1, 1])),
     bitmap_tex(EMITTER_IMG[:, ::-1])),
    ('tiled 2x2', ours_tex(EMITTER_IMG, uscale=2, vscale=2),
     bitmap_tex(np.tile(EMITTER_IMG, (2, 2, 1)))),
]


@pytest.mark.parametrize('name,ours,bitmap', EMITTERS, ids=[e[0] for e in EMITTERS])
def test_textured_area_emitter_noise_and_mean_match_bitmap(name, ours, bitmap):
    """Issue #15's criterion: at equal spp (16) the noise of a high-contrast textured emitter
    (a 2×2-texel patch 2000× brighter than the rest) is within 1.2× of bitmap's, with the same
    mean. Noise = RMSE against a 512-spp render of the same emitter by bitmap (its own noise is
    ≤ 1/5 of the errors measured), averaged over 4 seeds (the RMSE of one 48×48 render varies
    by a few %). Measured ratios 0.99–1.01 (uniform sampling, what Mitsuba did before: ~35×).
    Mean: the 512-spp images of both agree within 0.5% (the estimated standard error of the
    mean is < 0.05%, so 0.5% only allows for the MIS-weight differences)."""
    scenes = {'ours': emitter_scene(ours), 'bitmap': emitter_scene(bitmap)}
    refs = {k: np.array(mi.render(s, spp=512, seed=99)) for k, s in scenes.items()}
    assert abs(refs['ours'].mean() / refs['bitmap'].mean() - 1) < 5e-3
    noise = {k: np.mean([rmse(mi.render(s, spp=16, seed=seed), refs['bitmap'])
                         for seed in range(4)]) for k, s in scenes.items()}
    assert noise["ours"] <= 1.2 * noise["bitmap"], noise


# ------------------------------------------------------------------------------ light tracing
def projector(tex):
    return {'type': 'projector', 'irradiance': tex, 'fov': 45, 'scale': 5,
            'to_world': T().look_at([0.3, 0.2, 2.0], [0, 0, 0], [0, 1, 0])}


def spot(tex):
    return {'type': 'spot', 'texture': tex, 'intensity': 5, 'cutoff_angle': 30,
            'to_world': T().look_at([0.0, -0.3, 2.0], [0, 0, 0], [0, 1, 0])}


LIGHTS = [('area', None), ('projector', projector)]


def welch_t(a, b):
    """Welch's t statistic of two samples (axis 0: independent renders)."""
    va, vb = a.var(0, ddof=1) / len(a), b.var(0, ddof=1) / len(b)
    se = np.sqrt(va + vb)
    return np.where(se > 0, (a.mean(0) - b.mean(0)) / np.where(se > 0, se, 1), 0.0)


@pytest.mark.parametrize('name,make', LIGHTS, ids=[x[0] for x in LIGHTS])
def test_light_tracing_matches_bitmap(name, make):
    """ptracer calls the emitter's sample_ray, which calls the texture's sample_position (area
    light, projector) and sample_spectrum. Its images with our texture equal bitmap's within
    noise, from 16 independent 64-spp renders each (independent seeds):

    * on every 8×8-pixel block the means differ by less than 5 standard errors (Welch's t, ~30
      degrees of freedom: a false alarm has probability < 1e-3 over the 36 blocks; measured max
      |t| 2.2 area, 2.7 projector);
    * the noise — median over the lit pixels of the per-pixel standard deviation across renders
      relative to the pixel's mean (the RMSE is dominated by the few pixels of the bright patch
      and varies ±15% between sets of 16 renders; this median varies ±3%) — is within 1.2× of
      bitmap's (measured 0.96 area, 0.98 projector).
    """
    ours, bitmap = ours_tex(EMITTER_IMG), bitmap_tex(EMITTER_IMG)
    scene = (lambda tex: emitter_scene(tex, 'ptracer', max_depth=2)) if make is None else \
        (lambda tex: emitter_scene(None, 'ptracer', emitter=make(tex), max_depth=2))
    blocks, noise = {}, {}
    for key, tex, seed0 in (('ours', ours, 0), ('bitmap', bitmap, 100)):
        sc = scene(tex)
        imgs = np.array([np.array(mi.render(sc, spp=64, seed=seed0 + k)) for k in range(16)])
        blocks[key] = imgs.reshape(16, 6, 8, 6, 8, -1).mean((2, 4))     # RGB or mono
        mean, std = imgs.mean(0), imgs.std(0, ddof=1)
        lit = mean > 1e-3 * mean.max()
        noise[key] = np.median(std[lit] / mean[lit])
    t = welch_t(blocks['ours'], blocks['bitmap'])
    assert blocks['bitmap'].mean() > 0 and np.abs(t).max() < 5, np.abs(t).max()
    assert noise['ours'] <= 1.2 * noise['bitmap'], noise


def test_spot_light_tracing_equals_bitmap():
    """A spot light's sample_ray samples its cone uniformly and asks the texture only for
    sample_spectrum: with the same seed the ptracer image equals bitmap's (≤ 1e-6 relative:
    float32 rounding of the same lookups)."""
    imgs = [np.array(mi.render(emitter_scene(None, 'ptracer', emitter=spot(tex), max_depth=2),
                               spp=32, seed=3))
            for tex in (ours_tex(EMITTER_IMG), bitmap_tex(EMITTER_IMG))]
    assert imgs[1].max() > 0
    assert np.max(np.abs(imgs[0] - imgs[1])) <= 1e-6 * imgs[1].max()


@pytest.mark.parametrize('tex', [
    {'type': 'pbrt_constant', 'value': 0.7},
    {'type': 'pbrt_scale', 'tex': 1.4, 'scale': 0.5},
    {'type': 'pbrt_mix', 'tex1': 0.7, 'tex2': 0.7, 'amount': 0.3},
    {'type': 'pbrt_checkerboard', 'tex1': 0.7, 'tex2': 0.7, 'aamode': 'none'},
    {'type': 'pbrt_bilerp', 'v00': 0.7, 'v01': 0.7, 'v10': 0.7, 'v11': 0.7},
], ids=['constant', 'scale', 'mix', 'checkerboard', 'bilerp'])
def test_every_texture_lights_under_light_tracing(tex):
    """Every pbrt_* texture answers sample_spectrum (light tracing asks an area light's
    radiance texture for it; ``pbrt_constant`` raised a pure-virtual error there): an area light
    whose texture is 0.7 everywhere gives the ptracer image of Mitsuba's uniform 0.7 within
    noise — 8 independent renders each, every 8×8-pixel block's mean within 5 standard errors
    (Welch's t; 36 blocks: a false alarm has probability < 1e-3)."""
    blocks = []
    for t, seed0 in ((tex, 0), ({'type': 'rgb', 'value': 0.7}, 100)):
        scene = emitter_scene(t, 'ptracer', max_depth=2)
        imgs = np.array([np.array(mi.render(scene, spp=16, seed=seed0 + k)) for k in range(8)])
        assert np.isfinite(imgs).all()
        blocks.append(imgs.reshape(8, 6, 8, 6, 8, -1).mean((2, 4)))
    t = welch_t(*blocks)
    assert blocks[1].mean() > 0 and np.abs(t).max() < 5, np.abs(t).max()


def test_emitter_texel_gradients_match_bitmap():
    """prb differentiates through the sampled emitter (the density is a constant of the
    texels, as bitmap's): d(mean image)/d(texels) summed over all texels and over the bright
    patch agree with bitmap's within 1% and 2% (64 spp, different position samples; measured
    0.03% and 0.07%)."""
    grads = {}
    for key, tex in (('ours', ours_tex(EMITTER_IMG)), ('bitmap', bitmap_tex(EMITTER_IMG))):
        scene = emitter_scene(tex, 'prb', max_depth=2)
        params = mi.traverse(scene)
        k = 'light.emitter.radiance.data'
        dr.enable_grad(params[k])
        params.update()
        dr.backward(dr.mean(mi.render(scene, params, spp=64, seed=1), axis=None))
        grads[key] = dr.grad(params[k]).numpy()
    g, b = grads['ours'], grads['bitmap']
    assert b.sum() > 0 and abs(g.sum() / b.sum() - 1) < 0.01
    assert abs(g[20:22, 8:10].sum() / b[20:22, 8:10].sum() - 1) < 0.02


def test_emitter_to_uv_is_sampled_consistently():
    """An emitter texture with a to_uv flip renders the same image as bitmap given the flipped
    data: RMSE ≤ 4e-4 at 512 spp (two independent renders differ by ≈ 2.5e-4 from noise alone;
    measured 2.7e-4) and the same mean within 0.5% (standard error < 0.05%). For scale: bitmap
    with the same to_uv, in Mitsuba 3.9.1, samples positions ignoring its to_uv and is off by
    RMSE 0.011, +4% in the mean."""
    flip = T().translate([1, 0, 0]) @ T().scale([-1, 1, 1])
    ours = np.array(mi.render(emitter_scene(ours_tex(EMITTER_IMG, to_uv=flip)), spp=512, seed=1))
    want = np.array(mi.render(emitter_scene(bitmap_tex(EMITTER_IMG[:, ::-1])), spp=512, seed=2))
    assert rmse(ours, want) <= 4e-4
    assert abs(ours.mean() / want.mean() - 1) < 5e-3


# ------------------------------------------------------------------------------ to_uv in traverse
def floor_scene(tex):
    """A plane textured with `tex` under constant light, seen at an angle."""
    return mi.load_dict({
        'type': 'scene', 'integrator': {'type': 'path', 'max_depth': 2},
        'sensor': {'type': 'perspective', 'fov': 50,
                   'to_world': T().look_at([0, -2.5, 1.5], [0, 0, 0], [0, 0, 1]),
                   'sampler': {'type': 'independent'},
                   'film': {'type': 'hdrfilm', 'width': 32, 'height': 32,
                            'rfilter': {'type': 'box'}}},
        'light': {'type': 'constant'},
        'floor': {'type': 'rectangle', 'bsdf': {'type': 'diffuse', 'reflectance': tex}}})


def test_to_uv_update_through_params_changes_render_like_bitmap(rng):
    """params['...to_uv'] exists as with bitmap (a ScalarAffineTransform3f, non-differentiable),
    and writing it changes the render exactly as it does with bitmap: with the same seed the two
    images agree to 1e-5 relative (float32 rounding of equal lookups) before and after the
    update, and the update changes the image (mean absolute change > 5% of the mean)."""
    img = rng.random((8, 8, 3)).astype(np.float32)
    scenes = {'ours': floor_scene(ours_tex(img)), 'bitmap': floor_scene(bitmap_tex(img))}
    params = {k: mi.traverse(s) for k, s in scenes.items()}
    key = 'floor.bsdf.reflectance.to_uv'
    assert type(params['ours'][key]) is type(params['bitmap'][key]) is mi.ScalarAffineTransform3f
    assert params['ours'].flags(key) == params['bitmap'].flags(key)

    def render():
        return {k: np.array(mi.render(s, spp=8, seed=5)) for k, s in scenes.items()}

    before = render()
    new = mi.ScalarAffineTransform3f().translate(mi.ScalarPoint2f(0.25, 0.1)) @ \
        mi.ScalarAffineTransform3f().rotate(30) @ mi.ScalarAffineTransform3f().scale(
            mi.ScalarPoint2f(3, 2))
    for p in params.values():
        p[key] = new
        p.update()
    after = render()
    for images in (before, after):
        assert np.max(np.abs(images['ours'] - images['bitmap'])) <= 1e-5 * images['bitmap'].max()
    assert np.mean(np.abs(after['ours'] - before['ours'])) > 0.05 * before['ours'].mean()


def test_bad_to_uv_update_is_an_error(rng):
    tex = imagemap(rng.random((4, 4, 3)))
    params = mi.traverse(tex)
    params['to_uv'] = mi.ScalarAffineTransform3f(mi.ScalarMatrix3f(1, 0, 0, 0, 1, 0, 0, 1, 1))
    with pytest.raises(Exception, match=r'pbrt_imagemap: parameter "to_uv": expected a finite '
                                        r'affine 2D transform \(last row 0, 0, 1\), got'):
        params.update()


# ------------------------------------------------------------------------------ channels, types
def test_eval_3_of_a_one_channel_image_is_grey(rng):
    """Deliberate difference: bitmap raises in eval_3 on a 1-channel image; ours returns the grey
    colour (v, v, v) — bitmap's eval of that image in RGB variants, its value in mono (≤ 1e-6)."""
    img = rng.random((5, 7, 1)).astype(np.float32)
    b = mi.load_dict(bitmap_tex(img))
    o = mi.load_dict(ours_tex(img))
    si = make_si(rng.random((100, 2)))
    with pytest.raises(Exception, match='monochromatic'):
        b.eval_3(si)
    got = A(o.eval_3(si))
    np.testing.assert_allclose(got, np.repeat(A(o.eval_1(si))[:, None], 3, 1), atol=0)
    want = A(b.eval(si)).reshape(len(got), -1)          # (v, v, v) in RGB, (v) in mono
    np.testing.assert_allclose(got, np.broadcast_to(want, got.shape), atol=1e-6)


@pytest.mark.parametrize('tensor', ['TensorXu8', 'TensorXi', 'TensorXu'])
def test_integer_data_is_rejected_with_the_decoding_hint(tensor):
    """bitmap's data of an 8-bit image holds uint8 sRGB codes; ours is linear float32. An integer
    tensor given as data is refused with plugin, parameter, value and what is accepted."""
    value = getattr(mi, tensor)(np.full((2, 3, 3), 200, np.uint32).astype(
        {'TensorXu8': np.uint8, 'TensorXi': np.int32, 'TensorXu': np.uint32}[tensor]))
    with pytest.raises(RuntimeError) as e:
        mi.load_dict({'type': 'pbrt_imagemap', 'data': value})
    msg = str(e.value)
    for words in ('pbrt_imagemap: parameter "data"', f'{tensor} of shape (2, 3, 3)',
                  'accepted: a TensorXf of linear float32 values', 'sRGB'):
        assert words in msg, (words, msg[-400:])


def test_codes_written_through_params_warn(capfd, rng):
    """Mitsuba converts a TensorXu8 written into params['...data'] to TensorXf before the
    plugin hears of it, so there it can only warn: all-integer texels in [0, 255] above 1 (what
    bitmap-style codes leave) warn with the decoding hint; ordinary float data does not."""
    tex = imagemap(rng.random((4, 4, 3)))
    params = mi.traverse(tex)
    params['data'] = mi.TensorXf(rng.random((4, 4, 3)).astype(np.float32))
    params.update()
    assert 'integers in [0, 255]' not in ''.join(capfd.readouterr())
    params['data'] = mi.TensorXu8(np.full((4, 4, 3), 200, np.uint8))
    params.update()
    out = ''.join(capfd.readouterr())
    assert type(params['data']) is mi.TensorXf and np.array(params['data']).max() == 200
    for words in ('pbrt_imagemap: parameter "data"', 'integers in [0, 255] (max 200)',
                  'linear float32', 'sRGB'):
        assert words in out, (words, out)


def test_data_is_linear_float32_where_bitmap_holds_srgb_codes():
    """What params['...data'] holds for an 8-bit sRGB PNG: bitmap's uint8 codes, our linear
    floats (decoded with Mitsuba's own sRGB table: ≤ 1e-6 from bitmap's lookups)."""
    path = os.path.join(os.path.dirname(__file__), 'data', 'srgb_11x9.png')
    b = mi.traverse(mi.load_dict({'type': 'bitmap', 'filename': path}))['data']
    o = mi.traverse(mi.load_dict({'type': 'pbrt_imagemap', 'filename': path}))['data']
    assert type(b) is mi.TensorXu8 and type(o) is mi.TensorXf
    codes = np.array(b, np.float64) / 255.0
    srgb = np.where(codes <= 0.04045, codes / 12.92, ((codes + 0.055) / 1.055) ** 2.4)
    np.testing.assert_allclose(np.array(o), srgb, atol=1e-6)


def test_sample_spectrum_equals_bitmaps(rng):
    """RGB/mono variants: sample_spectrum returns no wavelengths and the value, as bitmap's
    (≤ 1e-6); pdf_spectrum returns no wavelengths either (bitmap raises there)."""
    img = rng.random((5, 6, 3)).astype(np.float32)
    b, o = mi.load_dict(bitmap_tex(img)), mi.load_dict(ours_tex(img))
    si = make_si(rng.random((64, 2)))
    wb, vb = b.sample_spectrum(si, dr.zeros(type(si.wavelengths)))
    wo, vo = o.sample_spectrum(si, dr.zeros(type(si.wavelengths)))
    assert type(wo) is type(wb) and len(wo) == len(wb) == 0
    np.testing.assert_allclose(A(vo), A(vb), atol=1e-6)
    assert len(o.pdf_spectrum(si)) == 0
