"""pbrt_path: same light transport as Mitsuba's path, exact camera partials, propagation through
mirrors, a footprint at every bounce, no NaN on hard cases."""

import math
import sys

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from conftest import A, make_si

T = mi.ScalarTransform4f


class Probe(mi.Texture):
    """A user's Python texture that shows what it receives in si.duv_dx / si.duv_dy.

    mode 'x': RGB = OFFSET + (du/dx, dv/dx, 0); 'y': OFFSET + (du/dy, dv/dy, 0);
    'nonzero': 1 where the partials are finite and not all zero, else 0;
    'size': the world-space footprint size √|dp/dx × dp/dy| (grey)."""
    OFFSET = 0.25

    def __init__(self, props):
        mi.Texture.__init__(self, props)
        self.mode = props.get('mode', 'x')

    def eval(self, si, active=True):
        if self.mode == 'nonzero':
            d = mi.Vector4f(si.duv_dx.x, si.duv_dx.y, si.duv_dy.x, si.duv_dy.y)
            ok = dr.all(dr.isfinite(d)) & dr.any(d != 0)
            return mi.Color3f(dr.select(ok, 1.0, 0.0))
        if self.mode == 'size':
            # world-space footprint size √|dp/dx × dp/dy| rebuilt from the uv partials
            dpdx = si.dp_du * si.duv_dx.x + si.dp_dv * si.duv_dx.y
            dpdy = si.dp_du * si.duv_dy.x + si.dp_dv * si.duv_dy.y
            return mi.Color3f(dr.sqrt(dr.norm(dr.cross(dpdx, dpdy))))
        d = si.duv_dx if self.mode == 'x' else si.duv_dy
        return mi.Color3f(self.OFFSET + d.x, self.OFFSET + d.y, self.OFFSET)

    def eval_1(self, si, active=True):
        return self.eval(si, active).x

    def mean(self):
        return mi.Float(1.0)

    def is_spatially_varying(self):
        return True

    def to_string(self):
        return 'Probe'


@pytest.fixture(autouse=True)
def _probe():
    mi.register_texture('test_probe', lambda props: Probe(props))
    yield


def camera(origin, target, w, h, fov=40, up=(0, 1, 0)):
    return {'type': 'perspective', 'fov': fov, 'to_world': T().look_at(origin, target, up),
            'film': {'type': 'hdrfilm', 'width': w, 'height': h, 'rfilter': {'type': 'box'}},
            'sampler': {'type': 'independent'}}


# ------------------------------------------------------------------------------------ transport
def test_agrees_with_mitsuba_path_within_monte_carlo_error():
    """Differential-free textures; K independent renders per integrator give per-pixel means and
    standard errors; averaged over 4×4 blocks, every block's difference must have |z| < 5
    (64 blocks: a false alarm has probability < 4e-5), and so must the image mean."""
    scene_d = {
        'type': 'scene', 'sensor': camera([0, 2, 5], [0, 0.5, 0], 32, 32),
        'light': {'type': 'rectangle', 'to_world': T().translate([0, 3, 0]).rotate([1, 0, 0], 90),
                  'emitter': {'type': 'area', 'radiance': {'type': 'rgb', 'value': [4, 4, 4]}}},
        'env': {'type': 'constant', 'radiance': {'type': 'rgb', 'value': [0.2, 0.2, 0.3]}},
        'floor': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(4),
                  'bsdf': {'type': 'diffuse', 'reflectance': {
                      'type': 'bitmap', 'filename': 'tests/data/srgb_11x9.png'}}},
        'ball': {'type': 'sphere', 'center': [0.5, 0.7, 0], 'radius': 0.6,
                 'bsdf': {'type': 'roughconductor', 'alpha': 0.2}},
        'glass': {'type': 'sphere', 'center': [-0.9, 0.5, 0.5], 'radius': 0.4,
                  'bsdf': {'type': 'dielectric'}},
    }
    K, spp = 8, 16
    results = {}
    for integ in ('path', 'pbrt_path'):
        scene = mi.load_dict({**scene_d, 'integrator': {'type': integ, 'max_depth': 5}})
        seed0 = 0 if integ == 'path' else 1000
        imgs = np.stack([np.array(mi.render(scene, spp=spp, seed=seed0 + k)) for k in range(K)])
        lum = imgs @ np.array([0.2126, 0.7152, 0.0722])
        blocks = lum.reshape(K, 8, 4, 8, 4).mean(axis=(2, 4))
        results[integ] = (blocks.mean(0), blocks.var(0, ddof=1) / K)
    (m1, v1), (m2, v2) = results['path'], results['pbrt_path']
    z = (m1 - m2) / np.sqrt(v1 + v2 + 1e-12)
    assert np.max(np.abs(z)) < 5, z
    zm = (m1.mean() - m2.mean()) / math.sqrt((v1.sum() + v2.sum()) / 64 ** 2)
    assert abs(zm) < 5


@pytest.mark.parametrize('filter_, spp_scale', [('ewa', None), ('trilinear', 'none')])
def test_textured_area_light_under_mis_has_the_mean_of_mitsuba_path(filter_, spp_scale):
    """An area light with an image texture lights a floor (one bounce, so every pixel's light
    comes through MIS of emitter and BSDF sampling). Emitter sampling evaluates the emitter
    without a footprint; a BSDF ray that hits it must evaluate it the same way, else the two
    strategies estimate different radiances and the MIS sum is biased (with the footprint on
    the BSDF side: +3.9%, z = -13, for EWA at 4 spp; +13%, z = -35, without the spp scaling).
    Reference: Mitsuba's path + bitmap. K independent renders each give the image mean's
    standard error: |z| < 5 (a false alarm has probability < 1e-6)."""
    # a checkerboard of 4×4-texel checks, dark and bright: the light's dark checks are where
    # emitter sampling rarely goes
    check = (np.indices((32, 32)) // 4).sum(0) % 2
    texels = np.repeat(np.where(check, 1.0, 0.02)[..., None], 3, -1).astype(np.float32)
    ours = {'type': 'pbrt_imagemap', 'filter': filter_, 'data': mi.TensorXf(texels)}
    cases = {'path': ({'type': 'path', 'max_depth': 2},
                      {'type': 'bitmap', 'filter_type': 'bilinear', 'raw': True,
                       'data': mi.TensorXf(texels)}),
             'pbrt_path': ({'type': 'pbrt_path', 'max_depth': 2,
                            **({} if spp_scale is None else {'spp_scale': spp_scale})}, ours)}
    K, spp = 16, 4
    means = {}
    for name, (integrator, radiance) in cases.items():
        scene = mi.load_dict({
            'type': 'scene', 'integrator': integrator,
            'sensor': camera([0, 3, 4], [0, 0, 0], 48, 32, fov=50),
            'floor': {'type': 'rectangle', 'to_world': T().scale(5).rotate([1, 0, 0], -90),
                      'bsdf': {'type': 'diffuse'}},
            'light': {'type': 'rectangle',
                      'to_world': T().translate([0, 1.5, 0]).rotate([1, 0, 0], 90),
                      'emitter': {'type': 'area', 'radiance': radiance}}})
        seed0 = 0 if name == 'path' else 1000
        means[name] = np.array([np.array(mi.render(scene, spp=spp, seed=seed0 + k)).mean()
                                for k in range(K)])
    a, b = means['path'], means['pbrt_path']
    z = (a.mean() - b.mean()) / math.sqrt(a.var(ddof=1) / K + b.var(ddof=1) / K)
    assert abs(z) < 5, (a, b, z)


# ------------------------------------------------------------------------------------ camera hits
def _partials(scene, spp):
    img = np.array(mi.render(scene, spp=spp))
    return img[..., 3:7]


@pytest.mark.parametrize('shape', ['plane', 'sphere'])
def test_camera_partials_match_mitsuba_aov(shape):
    """Mitsuba's aov integrator computes si.compute_uv_partials with the sensor's differentials
    scaled by 1/√spp (its render loop); at spp ≤ 64 that is our pbrt scale. Per-pixel averages
    of the two (different pixel jitter) agree within 3% (box filter, smooth uv)."""
    if shape == 'plane':
        obj = {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(3),
               'bsdf': {'type': 'diffuse', 'reflectance': {'type': 'pbrt_checkerboard'}}}
    else:
        obj = {'type': 'sphere', 'radius': 1.0,
               'bsdf': {'type': 'diffuse', 'reflectance': {'type': 'pbrt_checkerboard'}}}
    base = {'type': 'scene', 'sensor': camera([0, 2.5, 4], [0, 0, 0], 40, 30), 'obj': obj}
    ours = mi.load_dict({**base, 'integrator': {'type': 'pbrt_path', 'aovs': 'duv_dx,duv_dy'}})
    aov = mi.load_dict({**base, 'integrator': {'type': 'aov', 'aovs': 'a:duv_dx,b:duv_dy'}})
    spp = 64
    got = _partials(ours, spp)
    want = np.array(mi.render(aov, spp=spp))[..., -4:]
    hit = np.abs(want).sum(-1) > 0
    interior = hit.copy()
    interior[1:-1, 1:-1] &= hit[:-2, 1:-1] & hit[2:, 1:-1] & hit[1:-1, :-2] & hit[1:-1, 2:]
    interior[[0, -1], :] = False
    interior[:, [0, -1]] = False
    assert interior.sum() > 100
    g, w = got[interior], want[interior]
    scale = np.abs(w).max()
    np.testing.assert_allclose(g, w, rtol=0.03, atol=0.03 * scale)


def test_footprint_halves_when_spp_quadruples():
    scene = mi.load_dict({
        'type': 'scene', 'sensor': camera([0, 2, 4], [0, 0, 0], 24, 24),
        'integrator': {'type': 'pbrt_path', 'aovs': 'duv_dx,duv_dy'},
        'floor': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(5),
                  'bsdf': {'type': 'diffuse', 'reflectance': {'type': 'pbrt_checkerboard'}}}})
    a4 = np.abs(_partials(scene, 4)).mean()
    a16 = np.abs(_partials(scene, 16)).mean()
    a64 = np.abs(_partials(scene, 64)).mean()
    a256 = np.abs(_partials(scene, 256)).mean()
    assert a4 / a16 == pytest.approx(2, rel=0.02)
    assert a16 / a64 == pytest.approx(2, rel=0.02)
    assert a64 / a256 == pytest.approx(1, rel=0.02)          # pbrt-v4 clamps at 1/8 pixel


# ------------------------------------------------------------------------------------ mirror
def test_mirror_partials_match_finite_differences():
    """Camera → flat mirror (y = 0) → emitting plane at y = 3 whose radiance shows the partials
    it receives. Reference: one-pixel finite differences of the reflected hit's uv, traced in
    numpy from Mitsuba's own camera rays (spp_scale none: one pixel). Tolerance 3%: the
    renders average 64 jittered samples per pixel, the reference 64 grid positions."""
    W, H = 24, 18
    sensor = camera([0, 2, 4], [0, 0, -1], W, H)
    plane_xf = T().translate([0, 3, 0]).rotate([1, 0, 0], 90).scale(30)
    base = {'type': 'scene', 'sensor': sensor,
            'mirror': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(100),
                       'bsdf': {'type': 'conductor'}},
            'plane': {'type': 'rectangle', 'to_world': plane_xf,
                      'bsdf': {'type': 'diffuse', 'reflectance': 0.0}}}
    out = {}
    for mode in ('x', 'y'):
        scene = mi.load_dict({**base, 'integrator': {'type': 'pbrt_path', 'spp_scale': 'none',
                                                     'max_depth': 3},
                              'plane': {**base['plane'], 'emitter': {
                                  'type': 'area', 'radiance': {'type': 'test_probe', 'mode': mode}}}})
        out[mode] = np.array(mi.render(scene, spp=64))[..., :2] - Probe.OFFSET

    sensor_obj = mi.load_dict(sensor)
    px, py = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)

    def uv_at(fx, fy):
        ray, _ = sensor_obj.sample_ray(0.0, 0.5, mi.Point2f((fx / W).ravel(), (fy / H).ravel()),
                                       mi.Point2f(0.5, 0.5))
        o, d = A(ray.o), A(ray.d)
        t = -o[:, 1] / d[:, 1]                       # mirror y = 0
        p = o + t[:, None] * d
        d = d * [1, -1, 1]                           # reflect
        t2 = (3 - p[:, 1]) / d[:, 1]                 # plane y = 3
        q = p + t2[:, None] * d
        seen = (t > 0) & (t2 > 0) & (np.abs(q[:, 0]) < 29) & (np.abs(q[:, 2]) < 29) \
            & (np.abs(p[:, 0]) < 99) & (np.abs(p[:, 2]) < 99)
        uv = np.stack([(q[:, 0] / 30 + 1) / 2, (q[:, 2] / 30 + 1) / 2], 1)
        return uv.reshape(H, W, 2), seen.reshape(H, W)

    # A ray differential is the offset ray through the next pixel: the reference is the forward
    # difference over one pixel, averaged over the sample positions inside the pixel (8×8 grid).
    fd_x, fd_y, seen = 0.0, 0.0, np.ones((H, W), bool)
    for jx in (np.arange(8) + 0.5) / 8:
        for jy in (np.arange(8) + 0.5) / 8:
            x0, y0 = px - 0.5 + jx, py - 0.5 + jy
            (u0, s0), (ux, s1), (uy, s2) = uv_at(x0, y0), uv_at(x0 + 1, y0), uv_at(x0, y0 + 1)
            fd_x, fd_y = fd_x + (ux - u0) / 64, fd_y + (uy - u0) / 64
            seen &= s0 & s1 & s2
    assert seen.sum() > 200
    np.testing.assert_allclose(out['x'][seen], fd_x[seen], rtol=0.03, atol=1e-3 * np.abs(fd_x).max())
    np.testing.assert_allclose(out['y'][seen], fd_y[seen], rtol=0.03, atol=1e-3 * np.abs(fd_y).max())


# ------------------------------------------------------------------------------------ bounces
def _indirect_scene(integrator, probe):
    """Camera sees a diffuse floor; a ceiling emitter (not sampled by NEE: weight 0) is reached
    only by BSDF-sampled second bounces, where its radiance texture sees the partials."""
    radiance = {'type': 'test_probe', 'mode': 'nonzero'} if probe else 1.0
    return mi.load_dict({
        'type': 'scene', 'sensor': camera([0, 1, 3], [0, 0, 0], 16, 16),
        'integrator': integrator,
        'floor': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(5),
                  'bsdf': {'type': 'diffuse', 'reflectance': 0.8}},
        'ceiling': {'type': 'rectangle', 'to_world': T().translate([0, 2, 0]).rotate([1, 0, 0], 90).scale(5),
                    'emitter': {'type': 'area', 'radiance': radiance, 'sampling_weight': 0.0}},
        # NEE needs an emitter with sampling mass: a dark point light takes all of it
        'dark': {'type': 'point', 'position': [0, 1, 0], 'intensity': 0.0}})


def test_second_bounce_diffuse_hits_get_finite_nonzero_partials():
    integ = {'type': 'pbrt_path', 'max_depth': 3}
    probe = np.array(mi.render(_indirect_scene(integ, True), spp=32, seed=3))
    ones = np.array(mi.render(_indirect_scene(integ, False), spp=32, seed=3))
    assert ones.mean() > 0.1
    np.testing.assert_allclose(probe, ones, rtol=1e-5, atol=1e-6)
    # the same probe under Mitsuba's path sees zero partials (so the test can fail)
    dark = np.array(mi.render(_indirect_scene({'type': 'path', 'max_depth': 3}, True), spp=32))
    assert dark.mean() < 1e-6
    # and texture_differentials=false turns them off
    off = np.array(mi.render(_indirect_scene({**integ, 'texture_differentials': False}, True), spp=8))
    assert off.mean() < 1e-6


def _dome_scene(radiance, card_bsdf, target=(0, 0, -1)):
    """Camera at the centre of an emitting sphere (R = 10, normals inward, not sampled by NEE)
    looking down -z; a diffuse or glossy card at z = -1 covers the left half of the view.
    Pixels on the right see the sphere directly (depth 0: the true camera-ray footprint);
    pixels on the card see it after one bounce (depth 1: pbrt-v4's camera approximation).
    Every sphere point is at distance R with its normal towards the camera, so the
    approximation gives one footprint size everywhere. The sphere's poles are turned to ±x, away from the card's
    bounces."""
    return mi.load_dict({
        'type': 'scene', 'sensor': camera([0, 0, 0], list(target), DOME_RES, DOME_RES, fov=DOME_FOV),
        'integrator': {'type': 'pbrt_path', 'max_depth': 2},
        'dome': {'type': 'sphere', 'radius': DOME_R, 'flip_normals': True,
                 'to_world': T().rotate([0, 1, 0], 90),
                 'emitter': {'type': 'area', 'radiance': radiance, 'sampling_weight': 0.0}},
        'card': {'type': 'rectangle',
                 'to_world': T().translate([-0.1, 0, -1]).scale([0.1, 0.3, 1]),
                 'bsdf': card_bsdf},
        'dark': {'type': 'point', 'position': [0, 0, -0.5], 'intensity': 0.0}})


DOME_R, DOME_FOV, DOME_RES = 10.0, 20.0, 16


CARDS = {'diffuse': {'type': 'diffuse', 'reflectance': 0.5},
         'glossy': {'type': 'roughconductor', 'alpha': 0.3}}


@pytest.mark.parametrize('card', ['diffuse', 'glossy'])
@pytest.mark.parametrize('spp', [1, 16, 64])
def test_bounce_footprints_have_camera_ray_size_and_spp_scale(spp, card):
    """Footprints after a diffuse bounce vs an independent pinhole computation: the axis pixel
    of a 16-pixel, 20° camera subtends α = 2 tan(10°)/16, so a camera ray at distance R facing
    the surface has footprint size R·α; pbrt-v4 scales it by max(1/8, 1/√spp). The probe/ones
    ratio of two renders with the same seed gives the size exactly per pixel (same paths).

    * after the diffuse or glossy bounce (card pixels): the approximation uses the smallest one-pixel
      differentials on the film (corner 14° off axis: ≥ cos² 14° = 0.94 of α per axis), so
      size ∈ [0.93, 1.01]·R·α·scale;
    * direct hits (right pixels): the true footprint R·α·cos^1.5 φ ∈ [0.91, 1.01]·R·α·scale.

    A missing spp scale at bounces (4–8× at 16–64 spp) or a sign error (~40×) breaks them."""
    scale = max(1 / 8, 1 / math.sqrt(spp))
    alpha = 2 * math.tan(math.radians(DOME_FOV / 2)) / DOME_RES
    want = DOME_R * alpha * scale
    probe = np.array(mi.render(_dome_scene({'type': 'test_probe', 'mode': 'size'}, CARDS[card]),
                               spp=spp, seed=5))[..., 0]
    ones = np.array(mi.render(_dome_scene(1.0, CARDS[card]), spp=spp, seed=5))[..., 0]
    card = np.zeros(ones.shape, bool)
    card[:, :DOME_RES // 2 - 1] = True                     # left of the card's edge (x = 0)
    card[[0, -1], :] = False                               # the card spans |y| < 0.3: all rows
    direct = np.zeros(ones.shape, bool)
    direct[:, DOME_RES // 2 + 1:] = True
    assert (ones[card] > 0.05).all() and (ones[direct] > 0.9).all()
    size_card = probe[card] / ones[card] / want
    size_direct = probe[direct] / ones[direct] / want
    assert size_card.min() > 0.93 and size_card.max() < 1.01, (size_card.min(), size_card.max())
    assert size_direct.min() > 0.91 and size_direct.max() < 1.01, (size_direct.min(),
                                                                    size_direct.max())


# ------------------------------------------------------------------------------------ hard cases
@pytest.mark.parametrize('case', ['horizon', 'inside_sphere', 'silhouettes', 'glass'])
def test_no_nan_on_hard_cases(case):
    """Grazing horizon, inside a sphere, silhouettes, glass: finite images and partials
    (≤ 1e8, pbrt-v4's clamp), and first-hit partials equal to Mitsuba's aov integrator's."""
    tex = {'type': 'pbrt_imagemap', 'filename': 'tests/data/srgb_11x9.png', 'filter': 'ewa',
           'uscale': 50.0, 'vscale': 50.0}
    shapes = {
        'horizon': {'floor': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(1e4),
                              'bsdf': {'type': 'diffuse', 'reflectance': tex}}},
        'inside_sphere': {'s': {'type': 'sphere', 'radius': 10, 'flip_normals': True,
                                'bsdf': {'type': 'diffuse', 'reflectance': tex}}},
        'silhouettes': {f's{i}': {'type': 'sphere', 'center': [i - 1.5, 0.5, 0], 'radius': 0.45,
                                  'bsdf': {'type': 'diffuse', 'reflectance': tex}} for i in range(4)},
        'glass': {'g': {'type': 'sphere', 'radius': 0.8, 'bsdf': {'type': 'dielectric'}},
                  'floor': {'type': 'rectangle', 'to_world': T().translate([0, -1, 0]).rotate([1, 0, 0], -90).scale(50),
                            'bsdf': {'type': 'diffuse', 'reflectance': tex}}},
    }[case]
    origin = [0, 0.02, 3] if case == 'horizon' else ([0, 0, 0] if case == 'inside_sphere' else [0, 1, 4])
    base = {'type': 'scene', 'sensor': camera(origin, [0, 0, -1], 48, 32),
            'env': {'type': 'constant'},
            'lamp': {'type': 'point', 'position': [0.5, 2, 0.5], 'intensity': 5.0}, **shapes}
    scene = mi.load_dict({**base, 'integrator': {'type': 'pbrt_path', 'aovs': 'duv_dx,duv_dy',
                                                 'max_depth': 8}})
    img = np.array(mi.render(scene, spp=4))
    assert np.isfinite(img).all()
    assert np.abs(img[..., 3:]).max() <= 1e8
    assert img[..., :3].mean() > 0
    # The value is known at the first hits: Mitsuba's aov integrator computes the same uv
    # partials from the same camera rays (the same sampler dimensions; its 1/√spp scale equals
    # pbrt's at 4 spp). Away from silhouettes (pixels whose 4 neighbours also hit), the two
    # agree to float32 rounding of two least-squares solves: measured ≤ 2.3e-5 of the pixel's
    # largest partial at grazing angles; we allow 1e-3.
    aov = mi.load_dict({**base, 'integrator': {'type': 'aov', 'aovs': 'a:duv_dx,b:duv_dy'}})
    want = np.array(mi.render(aov, spp=4))[..., -4:]
    hit = np.abs(want).sum(-1) > 0
    interior = hit.copy()
    interior[1:-1, 1:-1] &= hit[:-2, 1:-1] & hit[2:, 1:-1] & hit[1:-1, :-2] & hit[1:-1, 2:]
    interior[[0, -1], :] = False
    interior[:, [0, -1]] = False
    assert interior.sum() > 200
    got, ref = img[..., 3:][interior], want[interior]
    scale = np.abs(ref).max(-1, keepdims=True)
    assert np.all(np.abs(got - ref) <= 1e-3 * scale)


def test_integrator_parameter_errors_and_variants():
    for d, words in [({'type': 'pbrt_path', 'spp_scale': 'sqrt'}, ['"spp_scale"', 'pbrt, none']),
                     ({'type': 'pbrt_path', 'spp_scale': -1.0}, ['"spp_scale"', '> 0']),
                     # a number as a string (XML <string>, a <default>) is checked as a number:
                     # '1e39' was accepted and became inf (every footprint then dropped to 0)
                     ({'type': 'pbrt_path', 'spp_scale': '1e39'}, ['"spp_scale"', 'float32']),
                     # and 1e-50 is 0 in float32 (point sampling), not > 0
                     ({'type': 'pbrt_path', 'spp_scale': '1e-50'}, ['"spp_scale"', '> 0']),
                     ({'type': 'pbrt_path', 'spp_scale': 1e-50}, ['"spp_scale"', '0 in float32']),
                     ({'type': 'pbrt_path', 'aovs': 'depth'}, ['"aovs"', 'duv_dx, duv_dy']),
                     # the film refused the repeated channels at render time with a raw error
                     ({'type': 'pbrt_path', 'aovs': 'duv_dx, duv_dx'},
                      ['"aovs"', '"duv_dx" is named twice', 'duv_dx, duv_dy']),
                     ({'type': 'pbrt_path', 'max_depth': -2}, ['"max_depth"', '>= -1']),
                     ({'type': 'pbrt_path', 'maxdepth': 3}, ["unknown parameter 'maxdepth'"])]:
        with pytest.raises(RuntimeError) as e:
            mi.load_dict(d)
        assert 'pbrt_path' in str(e.value)
        for w in words:
            assert w in str(e.value), (w, str(e.value)[-300:])
    mi.set_variant('scalar_rgb')
    try:
        with pytest.raises(Exception, match='pbrt_path.*scalar variants are not supported'):
            mi.load_dict({'type': 'pbrt_path'})
    finally:
        mi.set_variant('llvm_ad_rgb')


def _open_to_the_sky(scene):
    """A Cornell box dict without its back wall, lit through the opening by a sky (an
    environment seen directly by the camera rays that miss) and a sun (a delta emitter)."""
    scene = {k: v for k, v in scene.items() if k != 'back'}
    scene['sky'] = {'type': 'constant', 'radiance': {'type': 'rgb', 'value': [0.3, 0.4, 0.6]}}
    scene['sun'] = {'type': 'directional', 'direction': [0.2, -0.5, 1.0], 'irradiance': 4.0}
    return scene


@pytest.mark.parametrize('params, sky', [({}, False), ({'max_depth': 10}, False),
                                         ({'max_depth': -1}, False),
                                         ({'hide_emitters': True}, False),
                                         ({'max_depth': 3, 'rr_depth': 1}, False),
                                         ({}, True), ({'hide_emitters': True}, True)])
def test_renders_as_mitsuba_prb_with_the_same_parameters(params, sky):
    """Without a texture that reads differentials pbrt_path is Mitsuba's ``prb`` — the same
    helpers and the same order of random numbers (module docstring) — so Mitsuba's Cornell box
    (its light in view; albedos high enough that every bounce and Russian roulette show)
    rendered by both with the same parameters and seed agrees to float32 rounding: measured
    ≤ 2.4e-7 at pixel values up to 16, hence rtol 1e-5 (atol 1e-6 for dark pixels). Parameters
    left out take each integrator's default, which must be prb's: max_depth 6 (``{}``),
    rr_depth 5 (shown at max_depth 10, where roulette runs), hide_emitters false, -1 unbounded.
    One bounce more or less, or roulette a bounce later or earlier, moves pixels by ≥ 0.04;
    hiding the light, by 16. ``sky``: the box open at the back to an environment and a sun —
    the background is the sky unless emitters are hidden (then black, as the hidden light), and
    the sun's delta lobe takes MIS weight 1."""
    scene = mi.cornell_box()
    if sky:
        scene = _open_to_the_sky(scene)
    _renders_as_prb(scene, params)


def _renders_as_prb(scene, params):
    scene['sensor']['film']['width'] = scene['sensor']['film']['height'] = 48
    images = [np.array(mi.render(mi.load_dict({**scene, 'integrator': {'type': kind, **params}}),
                                 spp=16, seed=3))
              for kind in ('prb', 'pbrt_path')]
    np.testing.assert_allclose(images[1], images[0], rtol=1e-5, atol=1e-6)


def test_renders_as_mitsuba_prb_through_glass_with_roulette():
    """As above with the boxes made of glass and roulette from the first bounce: roulette's
    survival probability uses the product of the relative indices of refraction crossed so
    far (1.5 inside the glass, 1 again outside), as prb's does."""
    scene = mi.cornell_box()
    scene['glass'] = {'type': 'dielectric'}
    for box in ('small-box', 'large-box'):
        scene[box]['bsdf'] = {'type': 'ref', 'id': 'glass'}
    _renders_as_prb(scene, {'max_depth': 8, 'rr_depth': 1})


@pytest.mark.parametrize('filter_, footprint', [('bilinear', 'sample'), ('ewa', 'sample'),
                                              ('box', 'pixel')])
def test_normal_maps_are_read_without_footprint(filter_, footprint, rng):
    """A texture a ``normalmap`` BSDF reads is looked up without a footprint, as pbrt-v4 reads
    normal maps (a bilinear lookup of the full image) — also where another texture on the same
    surface makes pbrt_path compute differentials, and under pixel footprints: the image
    equals the one with Mitsuba's ``bitmap`` (bilinear, which never reads a footprint) as the
    normal map, same integrator and seed, to float32 rounding (lookups within 1e-6), for the
    filters that read one (bilinear picks a level). Before, the filtered normals were smoother
    ones: a user trial's tiled photo normal map on a rough conductor rendered 6% darker than
    under ``path``, at any spp; here the old code differs by up to 0.19 (73% of the pixels)."""
    normals = rng.uniform(0, 1, (64, 64, 3)).astype(np.float32)
    normals[..., 2] = 1.0                    # (raw: tilted normals, all facing up)
    white = mi.TensorXf(np.full((4, 4, 3), 0.5, np.float32))
    film = {'type': 'hdrfilm', 'width': 48, 'height': 32, 'rfilter': {'type': 'box'}}

    def render(normal_map):
        return np.array(mi.render(mi.load_dict({
            'type': 'scene', 'integrator': {'type': 'pbrt_path', 'footprint': footprint},
            'sensor': {'type': 'perspective', 'fov': 45, 'film': film,
                       'to_world': T().look_at([0, -2.2, 1.2], [0, 0, 0], [0, 0, 1])},
            'plane': {'type': 'rectangle', 'bsdf': {
                'type': 'normalmap', 'normalmap': normal_map,
                # a texture that reads the footprint (a constant image: filtered, 0.5)
                'bsdf': {'type': 'roughplastic', 'alpha': 0.2, 'diffuse_reflectance': {
                    'type': 'pbrt_imagemap', 'data': white, 'filter': 'trilinear'}}}},
            'sun': {'type': 'directional', 'direction': [0.3, 0.5, -1], 'irradiance': 3.0}}),
            spp=4, seed=3))

    tiled = {'raw': True, 'to_uv': T().scale([8, 8, 1])}
    reference = render({'type': 'bitmap', 'bitmap': mi.Bitmap(normals),
                        'filter_type': 'bilinear', **tiled})
    assert reference.mean() > 0.05
    ours = {'type': 'pbrt_imagemap', 'data': mi.TensorXf(normals), 'filter': filter_, **tiled}
    np.testing.assert_allclose(render(ours), reference, rtol=1e-5, atol=1e-6)
    # nested in a composite (the composite's nested textures are normal-map textures too)
    nested = {'type': 'pbrt_scale', 'tex': ours, 'scale': 1.0}
    np.testing.assert_allclose(render(nested), reference, rtol=1e-5, atol=1e-6)


def test_a_normal_map_shared_with_a_reflectance_is_found():
    """A texture object that is a normal map on one shape and a reflectance on another (a
    traversal records it under one parent: the other BSDF) is still read without a footprint —
    in both slots (README): the image equals the one with Mitsuba's bitmap in both."""
    normals = np.random.default_rng(5).uniform(0, 1, (32, 32, 3)).astype(np.float32)
    normals[..., 2] = 1.0
    film = {'type': 'hdrfilm', 'width': 40, 'height': 30, 'rfilter': {'type': 'box'}}

    def render(tex):
        return np.array(mi.render(mi.load_dict({
            'type': 'scene', 'integrator': {'type': 'pbrt_path'},
            'sensor': {'type': 'perspective', 'fov': 50, 'film': film,
                       'to_world': T().look_at([0, -2.5, 1.5], [0, 0, 0], [0, 0, 1])},
            'textured': {'type': 'sphere', 'center': [1.2, 0, 0.4], 'radius': 0.4,
                         'bsdf': {'type': 'diffuse', 'reflectance': tex}},
            'plane': {'type': 'rectangle', 'bsdf': {
                'type': 'normalmap', 'normalmap': tex,
                'bsdf': {'type': 'roughplastic', 'alpha': 0.2, 'diffuse_reflectance': {
                    'type': 'pbrt_imagemap', 'data': mi.TensorXf(np.full((4, 4, 3), 0.5,
                                                                          np.float32)),
                    'filter': 'trilinear'}}}},
            'sun': {'type': 'directional', 'direction': [0.3, 0.5, -1], 'irradiance': 3.0}}),
            spp=4, seed=3))

    tiled = {'raw': True, 'to_uv': T().scale([8, 8, 1])}
    reference = render(mi.load_dict({'type': 'bitmap', 'bitmap': mi.Bitmap(normals),
                                     'filter_type': 'bilinear', **tiled}))
    ours = render(mi.load_dict({'type': 'pbrt_imagemap', 'data': mi.TensorXf(normals),
                                'filter': 'ewa', **tiled}))
    assert reference.mean() > 0.05
    np.testing.assert_allclose(ours, reference, rtol=1e-5, atol=1e-6)


def test_path_pass_options_load_without_effect_and_say_so(capfd):
    """``samples_per_pass`` and ``timeout`` (Mitsuba's ``SamplingIntegrator`` reads them: a
    ``path`` scene may set them) load — they were refused as unknown parameters — render as
    ``prb`` with them does (which ignores them) and warn that they have no effect; a wrong type
    is still an error."""
    _renders_as_prb(mi.cornell_box(), {'samples_per_pass': 4, 'timeout': 10.0})
    out = ''.join(capfd.readouterr())
    assert 'pbrt_path: samples_per_pass and timeout have no effect' in out
    with pytest.raises(RuntimeError, match='"samples_per_pass": expected an integer'):
        mi.load_dict({'type': 'pbrt_path', 'samples_per_pass': 'four'})


def test_spp_scale_as_an_integer_is_a_number():
    """``spp_scale`` is a string or a number (parameter table): an integer such as 2 is the
    number 2, so the uv partials it gives equal those of the float 2.0 exactly (same seed, same
    rays) and differ from those of 1.0."""
    def partials(scale):
        scene = mi.load_dict({
            'type': 'scene', 'sensor': camera([0, 2, 4], [0, 0, 0], 16, 16),
            'integrator': {'type': 'pbrt_path', 'aovs': 'duv_dx,duv_dy', 'spp_scale': scale},
            'floor': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(5),
                      'bsdf': {'type': 'diffuse', 'reflectance': {'type': 'pbrt_checkerboard'}}}})
        return np.array(mi.render(scene, spp=4, seed=2))[..., 3:7]
    two = partials(2)
    np.testing.assert_array_equal(two, partials(2.0))
    # a number in a string (a <default> substituted into a <string>) is that number too
    np.testing.assert_array_equal(two, partials('2'))
    assert np.abs(two - partials(1.0)).max() > 1e-3


def _count_loop_bodies(monkeypatch):
    """A list to which every recording of a pbrt_path loop body (``dr.while_loop`` labelled
    ``pbrt_path (…)``) appends the loop's label."""
    calls = []
    real_loop = dr.while_loop

    def counting_loop(state, cond, body, *args, **kwargs):
        label = kwargs.get('label') or ''
        if not label.startswith('pbrt_path ('):
            return real_loop(state, cond, body, *args, **kwargs)

        def counted(*s):
            calls.append(label)
            return body(*s)
        return real_loop(state, cond, counted, *args, **kwargs)

    monkeypatch.setattr(dr, 'while_loop', counting_loop)
    return calls


@pytest.mark.parametrize('case', ['diffuse', 'mirror', 'aovs', 'no differentials',
                                  'mirror, no differentials', 'aovs, no differentials'])
def test_primal_renders_record_the_path_loop_once(case, monkeypatch):
    """Tracing the path loop in Python is a large share of a render's cost (``bench
    integrator``), and Dr.Jit records a loop a second time when its state holds something
    constant (the module docstring). A primal render must therefore call the loop body once —
    with a texture that reads differentials, with a mirror that propagates them, with AOVs, and
    without differentials; a variable added to the loop state that never changes (or a rays'
    time left one value wide) makes it twice. Differentiable renders may record twice (they keep
    Dr.Jit's loop optimisation), so only the primal pass is counted. The image is checked
    against Mitsuba's ``prb`` as well: equal where no texture reads differentials, and finite."""
    calls = _count_loop_bodies(monkeypatch)
    plain = case.endswith('no differentials')
    reflectance = 0.5 if plain else {'type': 'pbrt_checkerboard'}
    integrator = {'type': 'pbrt_path', 'max_depth': 4}
    if case.startswith('aovs'):
        integrator['aovs'] = 'duv_dx'
    scene_d = {
        'type': 'scene', 'sensor': camera([0, 2, 4], [0, 0, 0], 16, 16),
        'integrator': integrator,
        'env': {'type': 'constant', 'radiance': {'type': 'rgb', 'value': [1, 1, 1]}},
        'floor': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(5),
                  'bsdf': {'type': 'diffuse', 'reflectance': reflectance}}}
    if case.startswith('mirror'):
        scene_d['ball'] = {'type': 'sphere', 'center': [0, 0.5, 0], 'radius': 0.5,
                           'bsdf': {'type': 'conductor'}}
    scene = mi.load_dict(scene_d)
    image = np.array(mi.render(scene, spp=4, seed=1))
    assert calls == ['pbrt_path (Primal)'], calls
    assert np.all(np.isfinite(image))
    if plain:
        monkeypatch.undo()                          # the real dr.while_loop for prb
        prb = np.array(mi.render(mi.load_dict({**scene_d, 'integrator': {'type': 'prb',
                                                                         'max_depth': 4}}),
                                 spp=4, seed=1))
        np.testing.assert_allclose(image[..., :3], prb[..., :3], rtol=1e-5, atol=1e-6)  # as above
        assert np.all(image[..., 3:] == 0)        # AOV partials: no texture reads them


def test_scene_traversed_once_per_scene(monkeypatch):
    """``scene_needs`` traverses a scene once (keyed by the JIT array of its shapes, which no
    other scene can share while the key is held). Checked three ways: (1) a second render of one scene makes no ``mi.traverse`` call;
    (2) the same integrator object given to another scene, whose only texture does not read
    differentials, traverses that scene and writes zero partials — a stale answer would keep
    computing them; (3) after ``params.update()`` of a bilinear image's texels, the coarse MIP
    levels a render reads are those of the new texels: the image equals that of a scene loaded
    with the new texels from the start (same seed) — the once-per-scene answer must not keep
    an optimisation's renders on the first texels."""
    integrator = mi.load_dict({'type': 'pbrt_path', 'aovs': 'duv_dx', 'max_depth': 2})

    def scene_with(reflectance):
        return mi.load_dict({
            'type': 'scene', 'sensor': camera([0, 2, 4], [0, 0, -6], 16, 16),
            'integrator': integrator,
            'sun': {'type': 'directional', 'direction': [0, -1, -0.2]},
            'floor': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(50),
                      'bsdf': {'type': 'diffuse', 'reflectance': reflectance}}})

    traversals = []
    real_traverse = mi.traverse

    def counting_traverse(obj, *args, **kwargs):
        if isinstance(obj, mi.Scene):           # (the sensor is traversed for another key)
            traversals.append(1)
        return real_traverse(obj, *args, **kwargs)
    monkeypatch.setattr(mi, 'traverse', counting_traverse)

    first = scene_with({'type': 'pbrt_checkerboard', 'uscale': 8, 'vscale': 8})
    partials = [np.array(mi.render(first, spp=2, seed=s))[..., 3:5] for s in (1, 2)]
    assert len(traversals) == 1, traversals
    assert np.abs(partials[0]).max() > 1e-4 and np.abs(partials[1]).max() > 1e-4

    second = scene_with({'type': 'checkerboard'})       # Mitsuba's: reads no differentials
    assert np.abs(np.array(mi.render(second, spp=2, seed=1))[..., 3:5]).max() == 0
    assert len(traversals) == 2, traversals

    rng = np.random.default_rng(5)
    old, new = (rng.random((32, 32, 3)).astype(np.float32) for _ in range(2))

    def image(texels):                  # a fresh tensor each time: params assign in place
        return {'type': 'pbrt_imagemap', 'filter': 'bilinear', 'data': mi.TensorXf(texels),
                'to_uv': T().scale([8, 8, 1])}
    updated = scene_with(image(old))
    before = np.array(mi.render(updated, spp=2, seed=3))[..., :3]
    params = real_traverse(updated)
    key = [k for k in params.keys() if k.endswith('reflectance.data')][0]
    params[key] = mi.TensorXf(new)
    params.update()
    got = np.array(mi.render(updated, spp=2, seed=3))[..., :3]
    want = np.array(mi.render(scene_with(image(new)), spp=2, seed=3))[..., :3]
    assert np.abs(got - before).max() > 1e-2
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)


def test_camera_approximation_found_again_only_when_the_sensor_changes(monkeypatch):
    """The camera approximation (512 sensor rays, a few small kernels) is kept while the
    sensor's parameters are unchanged and found again when one is written through ``params``.
    Checked on the dome scene, where the card's bounce footprints come from it: two renders
    build it once; after ``params.update()`` of the sensor's field of view it is built again, and
    the image equals that of a scene loaded with the new field of view (same seed) — a kept
    approximation of the old camera would give footprints the size of the old pixels (the
    image differs by > 1e-3 between the two fields of view)."""
    from mitsuba_pbrt_tex import raydiff
    built = []
    real = raydiff.CameraFootprint

    class Counting(real):
        def __init__(self, sensor):
            built.append(1)
            super().__init__(sensor)

    monkeypatch.setattr(raydiff, 'CameraFootprint', Counting)
    size = {'type': 'test_probe', 'mode': 'size'}
    scene = _dome_scene(size, CARDS['diffuse'])
    before = [np.array(mi.render(scene, spp=4, seed=s)) for s in (1, 1)]
    assert len(built) == 1 and np.array_equal(before[0], before[1])
    params = mi.traverse(scene)
    key = [k for k in params.keys() if k.endswith('x_fov')][0]
    params[key] = DOME_FOV / 2
    params.update()
    after = np.array(mi.render(scene, spp=4, seed=1))
    assert len(built) == 2
    monkeypatch.setattr(sys.modules[__name__], 'DOME_FOV', DOME_FOV / 2)
    fresh = np.array(mi.render(_dome_scene(size, CARDS['diffuse']), spp=4, seed=1))
    assert np.abs(fresh - before[0]).max() > 1e-3
    np.testing.assert_allclose(after, fresh, rtol=1e-6, atol=1e-8)
    # the camera turned (its to_world, a transform: keyed by its matrix's variables)
    target = [0.3, 0.1, -1]
    key = [k for k in params.keys() if k.endswith('to_world') and 'dome' not in k
           and 'card' not in k][0]
    params[key] = T().look_at([0, 0, 0], target, [0, 1, 0])
    params.update()
    count = len(built)
    turned = np.array(mi.render(scene, spp=4, seed=1))
    assert len(built) == count + 1
    fresh = np.array(mi.render(_dome_scene(size, CARDS['diffuse'], target), spp=4, seed=1))
    np.testing.assert_allclose(turned, fresh, rtol=1e-6, atol=1e-8)
    # a smaller film (not a JIT value: keyed by value) has larger pixels
    for name in ('film.size', 'film.crop_size'):
        params[[k for k in params.keys() if k.endswith(name)][0]] = \
            mi.ScalarVector2u(DOME_RES // 2, DOME_RES // 2)
    params.update()
    count = len(built)
    halved = np.array(mi.render(scene, spp=4, seed=1))
    assert len(built) == count + 1
    monkeypatch.setattr(sys.modules[__name__], 'DOME_RES', DOME_RES // 2)
    fresh = np.array(mi.render(_dome_scene(size, CARDS['diffuse'], target), spp=4, seed=1))
    np.testing.assert_allclose(halved, fresh, rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize('rfilter, extra', [('gaussian', 0), ('box', 4)])
def test_pixel_footprint_renders_record_each_loop_once(rfilter, extra, monkeypatch):
    """As above, with ``footprint="pixel"``: a Gaussian film (the decoded pixel is loop state)
    records the path loop once; silhouette samples record their own loop once, with the one
    path loop inside it (two path-loop recordings in all, one per loop that traces paths)."""
    calls = _count_loop_bodies(monkeypatch)
    sensor = camera([0, 2, 4], [0, 0, 0], 16, 16)
    sensor['film']['rfilter'] = {'type': rfilter}
    texels = mi.TensorXf(np.full((4, 4, 3), 0.5, np.float32))
    scene = mi.load_dict({
        'type': 'scene', 'sensor': sensor,
        'integrator': {'type': 'pbrt_path', 'footprint': 'pixel', 'silhouette_spp': extra},
        'env': {'type': 'constant'},
        'floor': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90),
                  'bsdf': {'type': 'diffuse', 'reflectance': {
                      'type': 'pbrt_imagemap', 'filter': 'box', 'data': texels}}}})
    image = np.array(mi.render(scene, spp=2, seed=1))
    want = ['pbrt_path (Primal)'] + (['pbrt_path (silhouettes)', 'pbrt_path (Primal)']
                                     if extra else [])
    assert calls == want
    assert np.all(np.isfinite(image)) and image.max() > 0.1


def _gating_scene(walls, alpha):
    """A room whose floor has a fine checker image (bilinear: bounce hits read coarse MIP
    levels from their footprint) and whose walls have ``walls`` as reflectance; a glossy ball
    of roughness ``alpha``."""
    texels = (np.indices((16, 16)).sum(0) % 2)[..., None]
    floor = {'type': 'pbrt_imagemap', 'filter': 'bilinear', 'to_uv': T().scale([40, 40, 1]),
             'data': mi.TensorXf(np.repeat(texels, 3, 2).astype(np.float32))}
    wall = lambda xf: {'type': 'rectangle', 'to_world': xf,
                       'bsdf': {'type': 'diffuse', 'reflectance': walls}}
    return mi.load_dict({
        'type': 'scene', 'sensor': camera([0, 1.5, 3], [0, 0.5, -2], 24, 16),
        'integrator': {'type': 'pbrt_path', 'max_depth': 4},
        'sun': {'type': 'directional', 'direction': [0.3, -1, -0.4]},
        'env': {'type': 'constant', 'radiance': {'type': 'rgb', 'value': [0.3, 0.3, 0.3]}},
        'floor': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(4),
                  'bsdf': {'type': 'diffuse', 'reflectance': floor}},
        'back': wall(T().translate([0, 2, -3]).scale(4)),
        'left': wall(T().translate([-3, 2, 0]).rotate([0, 1, 0], 90).scale(4)),
        'ball': {'type': 'sphere', 'center': [0.5, 0.5, -1], 'radius': 0.5,
                 'bsdf': {'type': 'roughconductor', 'alpha': alpha}}})


def _readers(scene):
    from mitsuba_pbrt_tex.texture import uses_differentials
    return [n for n in mi.traverse(scene).hierarchy
            if isinstance(n, mi.Texture) and uses_differentials(n)]


def test_camera_approximation_skipped_on_shapes_without_a_reader_changes_no_pixel():
    """After a bounce, the camera approximation is computed only on shapes with a texture
    that reads it (``scene_needs.reader_shapes``): the walls' plain reflectance and the ball read nothing.
    Reference: the same room whose walls' reflectance and ball's roughness are
    ``pbrt_checkerboard``s of two equal values — the same BSDFs, but textures that read
    differentials on every shape, so no shape is skipped. The
    renders (same seed) must agree to float32 rounding (as the ``prb`` comparison above); a
    floor left out of the mask (its bounce hits then read MIP level 0) changes pixels by far
    more. A mask that is None here would mean nothing was skipped: checked too."""
    from mitsuba_pbrt_tex.scene_needs import reader_shapes as _reader_shapes
    gated = _gating_scene(0.5, 0.3)
    reference = _gating_scene({'type': 'pbrt_checkerboard', 'tex1': 0.5, 'tex2': 0.5},
                              {'type': 'pbrt_checkerboard', 'tex1': 0.3, 'tex2': 0.3})
    mask = _reader_shapes(gated, _readers(gated))
    assert mask is not None and _reader_shapes(reference, _readers(reference)) is None
    # ... and the mask is what the path tracer is given (the images cannot show it)
    integrator = gated.integrator()
    sensor = gated.sensors()[0]
    inputs = integrator.trace_inputs(gated, sensor.sampler(), sensor)
    np.testing.assert_array_equal(np.array(inputs.needs.reader_shapes), np.array(mask))
    a = np.array(mi.render(gated, spp=16, seed=4))
    b = np.array(mi.render(reference, spp=16, seed=4))
    assert a.mean() > 0.05
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test_reader_shapes_are_those_whose_bsdf_or_emitter_holds_a_reader():
    """The mask over shape ids against the scene's description: a reader directly in a BSDF,
    nested in ``twosided`` and ``blendbsdf``, in a ``bumpmap``, and in an area emitter's
    radiance marks its shape; plain BSDFs and emitters, Mitsuba's own textures and a
    ``pbrt_constant`` (which reads no differentials) do not. None when every shape is marked
    or no texture reads differentials."""
    from mitsuba_pbrt_tex.scene_needs import reader_shapes as _reader_shapes
    checker = {'type': 'pbrt_checkerboard'}
    shapes = {
        'direct': {'type': 'diffuse', 'reflectance': checker},
        'twosided': {'type': 'twosided', 'bsdf': {'type': 'diffuse', 'reflectance': checker}},
        'blend': {'type': 'blendbsdf', 'weight': {'type': 'pbrt_checkerboard'},
                  'a': {'type': 'diffuse'}, 'b': {'type': 'conductor'}},
        'bump': {'type': 'bumpmap', 'arbitrary': checker, 'bsdf': {'type': 'diffuse'}},
        'emitter': {'type': 'diffuse'},
        'plain': {'type': 'diffuse', 'reflectance': {'type': 'checkerboard'}},
        'constant': {'type': 'diffuse', 'reflectance': {'type': 'pbrt_constant', 'value': 0.3}},
        'plain_light': {'type': 'diffuse'},
    }
    scene_d = {'type': 'scene'}
    for k, (name, bsdf) in enumerate(shapes.items()):
        scene_d[name] = {'type': 'sphere', 'center': [3 * k, 0, 0], 'bsdf': bsdf}
    scene_d['emitter']['emitter'] = {'type': 'area', 'radiance': checker}
    scene_d['plain_light']['emitter'] = {'type': 'area', 'radiance': 2.0}
    scene = mi.load_dict(scene_d)
    mask = np.array(_reader_shapes(scene, _readers(scene)))
    marked = {s.id(): bool(mask[int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s))[0])])
              for s in scene.shapes()}
    assert marked == {'direct': True, 'twosided': True, 'blend': True, 'bump': True,
                      'emitter': True, 'plain': False, 'constant': False,
                      'plain_light': False}
    assert _reader_shapes(scene, []) is None
    # instances: their shapes are not the scene's (si.shape is the instanced one): no mask
    with_instance = mi.load_dict({
        'type': 'scene', 'a': scene_d['direct'], 'b': scene_d['plain'],
        'group': {'type': 'shapegroup', 'c': {'type': 'sphere', 'bsdf': shapes['plain']}},
        'instance': {'type': 'instance', 'shapegroup': {'type': 'ref', 'id': 'group'},
                     'to_world': T().translate([0, 5, 0])}})
    assert _reader_shapes(with_instance, _readers(with_instance)) is None
    only = mi.load_dict({'type': 'scene', 'a': scene_d['direct'], 'b': scene_d['twosided']})
    assert _reader_shapes(only, _readers(only)) is None


def test_set_total_spp_sets_the_footprint_scale():
    """``set_total_spp(n)`` (the command line's render in passes) makes the footprint that of n
    spp whatever the spp of each ``mi.render``: pbrt-v4's scale max(1/8, 1/√spp) is 1/8 for 64
    spp, so a 4-spp render under ``set_total_spp(64)`` has the uv partials of the numeric
    ``spp_scale`` 0.125 (same seed, same rays: exactly), not those of 4 spp (scale 1/2, partials
    ~4× larger); ``set_total_spp(None)`` goes back to the render's spp (scale 1/2) exactly."""
    def scene(**integrator):
        return mi.load_dict({
            'type': 'scene', 'sensor': camera([0, 2, 4], [0, 0, 0], 16, 16),
            'integrator': {'type': 'pbrt_path', 'aovs': 'duv_dx,duv_dy', **integrator},
            'floor': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(5),
                      'bsdf': {'type': 'diffuse', 'reflectance': {'type': 'pbrt_checkerboard'}}}})

    def partials(s):
        return np.array(mi.render(s, spp=4, seed=2))[..., 3:7]

    eighth, half = partials(scene(spp_scale=0.125)), partials(scene(spp_scale=0.5))
    assert np.abs(half).mean() > 3 * np.abs(eighth).mean()
    ours = scene()
    ours.integrator().set_total_spp(64)
    np.testing.assert_array_equal(partials(ours), eighth)
    ours.integrator().set_total_spp(None)
    np.testing.assert_array_equal(partials(ours), half)


def _small_cornell(integrator, glossy=False, sky=False):
    scene = mi.cornell_box()
    if sky:
        scene = _open_to_the_sky(scene)
    if glossy:          # BSDFs whose value depends on the incident direction
        scene['white'] = {'type': 'roughconductor', 'alpha': 0.3}
        scene['red'] = {'type': 'roughplastic', 'alpha': 0.2,
                        'diffuse_reflectance': scene['red']['reflectance']}
    scene['sensor']['film']['width'] = scene['sensor']['film']['height'] = 24
    scene['sensor']['sampler']['sample_count'] = 4
    return mi.load_dict({**scene, 'integrator': integrator})


def test_direct_render_calls_with_default_arguments_match_prb():
    """The integrator's ``render``, ``render_forward`` and ``render_backward`` called directly,
    with their default sensor, seed and spp (Mitsuba's ``mi.render`` always passes them), are
    those of Mitsuba's ``prb``: on Mitsuba's Cornell box (no texture that reads differentials)
    the image, the forward derivative along the red wall's albedo and the backward gradient of
    Σ w·image agree with prb's to float32 rounding (rtol 1e-5 as in the comparison above; the
    derivatives' sums: 1e-4). Another default seed or spp changes every pixel by the noise
    (~10%), sensor 1 does not exist."""
    key = 'red.reflectance.value'
    w = np.random.default_rng(3).random((24, 24, 3)).astype(np.float32)
    out = {}
    for kind in ('prb', 'pbrt_path'):
        scene = _small_cornell({'type': kind, 'max_depth': 4})
        integrator = scene.integrator()
        image = np.array(integrator.render(scene))
        params = mi.traverse(scene)
        dr.enable_grad(params[key])
        params.update()
        dr.set_grad(params[key], mi.Color3f(1, 0.5, 0.25))
        dr.enqueue(dr.ADMode.Forward, params[key])
        dr.traverse(dr.ADMode.Forward, dr.ADFlag.ClearEdges)
        forward = np.array(integrator.render_forward(scene, params))
        scene = _small_cornell({'type': kind, 'max_depth': 4})
        params = mi.traverse(scene)
        dr.enable_grad(params[key])
        params.update()
        scene.integrator().render_backward(scene, params, mi.TensorXf(w))
        out[kind] = image, forward, np.array(dr.grad(params[key]))
    (image, forward, grad), (image_p, forward_p, grad_p) = out['prb'], out['pbrt_path']
    assert image.mean() > 0.1 and np.abs(forward).mean() > 1e-3 and np.abs(grad).min() > 1e-3
    np.testing.assert_allclose(image_p, image, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(forward_p, forward, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(grad_p, grad, rtol=1e-4)


def test_aovs_are_zero_where_no_texture_reads_differentials():
    """The duv AOVs are the partials the integrator computed; where no texture reads
    differentials it computes none (module docstring), so the four channels are exactly 0 —
    with Mitsuba's textures only, and with texture_differentials false over a checkerboard —
    while the colour is prb's (rtol 1e-5)."""
    prb = np.array(mi.render(_small_cornell({'type': 'prb', 'max_depth': 3}), seed=2))
    img = np.array(mi.render(_small_cornell({'type': 'pbrt_path', 'max_depth': 3,
                                             'aovs': 'duv_dx,duv_dy'}), seed=2))
    assert img.shape[-1] == 7
    np.testing.assert_allclose(img[..., :3], prb, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(img[..., 3:], 0)
    off = mi.load_dict({
        'type': 'scene', 'sensor': camera([0, 2, 4], [0, 0, 0], 16, 16),
        'integrator': {'type': 'pbrt_path', 'aovs': 'duv_dx,duv_dy',
                       'texture_differentials': False},
        'floor': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(5),
                  'bsdf': {'type': 'diffuse', 'reflectance': {'type': 'pbrt_checkerboard'}}}})
    np.testing.assert_array_equal(np.array(mi.render(off, spp=2))[..., 3:], 0)


@pytest.mark.parametrize('sky', [False, True])
def test_geometry_gradients_match_prb(sky):
    """Gradients with respect to vertex positions go through the hits' positions and the
    incident direction re-attached to the previous hit (prb's interior derivative; the
    boundary term is neither's): backward gradients of Σ w·image with respect to the Cornell
    box's red wall and light transforms, with glossy walls (whose value depends on that
    direction), and with respect to the light's radiance (the emission seen by BSDF-sampled
    paths, tracked in the differential phase) agree with Mitsuba's ``prb`` (same seeds) to float32
    rounding of the accumulated sums (rtol 1e-4 of the largest component). ``sky``: the box
    open to an environment and a sun (:func:`_open_to_the_sky`), and the sun's irradiance among
    the parameters — emitters that are not surfaces, whose solid-angle Jacobian is 1 (a
    Jacobian of their far-away sample points would give the wall a gradient of ~2/distance),
    and a delta emitter of pdf 1."""
    keys = ('red-wall.to_world', 'light.to_world', 'light.emitter.radiance.value') + (
        ('sun.irradiance.value',) if sky else ())
    _gradients_match_prb(
        lambda kind: _small_cornell({'type': kind, 'max_depth': 4}, glossy=True, sky=sky),
        keys, seed=4)


def _gradients_match_prb(load, keys, seed):
    """Backward gradients of Σ w·image (w random, fixed) with respect to ``keys`` of the scene
    ``load(kind)`` rendered by ``prb`` and by ``pbrt_path`` with the same seeds: equal to
    float32 rounding of the accumulated sums (rtol 1e-4 of the largest component), non-zero."""
    grads = {}
    for kind in ('prb', 'pbrt_path'):
        scene = load(kind)
        params = mi.traverse(scene)
        params.keep(list(keys))
        for k in keys:
            dr.enable_grad(params[k])
        params.update()
        image = mi.render(scene, params, spp=4, seed=1, seed_grad=2)
        w = np.random.default_rng(seed).random(image.shape).astype(np.float32)
        dr.backward(dr.sum(mi.TensorXf(w) * image, axis=None))
        grads[kind] = [np.array(getattr(dr.grad(params[k]), 'matrix', dr.grad(params[k])))
                       for k in keys]
    for g, g_p in zip(grads['prb'], grads['pbrt_path']):
        scale = np.abs(g).max()
        assert scale > 1e-3
        np.testing.assert_allclose(g_p, g, rtol=1e-4, atol=1e-4 * scale)


def test_gradient_of_a_lone_sun_matches_prb():
    """A scene lit by one directional emitter alone samples it with pdf exactly 1 (one emitter,
    a delta lobe): the gradient of Σ w·image with respect to its irradiance and to the glossy
    floor's transform (the re-attached emitter sample) equals Mitsuba's ``prb``'s (same seeds)
    to float32 rounding of the sums, rtol 1e-4 as above. Dropping the emitter sample's
    derivative where its pdf is 1 — the sun's exact value — zeroes the irradiance's."""
    _gradients_match_prb(lambda kind: mi.load_dict({
        'type': 'scene', 'integrator': {'type': kind, 'max_depth': 3},
        'sensor': camera([0, 2, 4], [0, 0, 0], 16, 16),
        'sun': {'type': 'directional', 'direction': [0.3, -1, -0.2], 'irradiance': 2.0},
        'floor': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(3),
                  'bsdf': {'type': 'roughplastic', 'alpha': 0.3}},
        'ball': {'type': 'sphere', 'center': [0.5, 0.5, 0], 'radius': 0.5,
                 'bsdf': {'type': 'diffuse'}}}), ('sun.irradiance.value', 'floor.to_world'), seed=5)


def test_backward_render_without_a_differentiable_parameter_is_an_error():
    """``render_backward`` when no scene parameter has gradients enabled: the differential
    phase's contribution is then not attached to the AD graph — usually a user's mistake
    (``dr.enable_grad`` or ``params.update()`` forgotten) — and, as Mitsuba's ``prb`` does,
    pbrt_path raises an error that says so instead of returning zero gradients."""
    scene = _small_cornell({'type': 'pbrt_path', 'max_depth': 3})
    with pytest.raises(Exception) as e:
        scene.integrator().render_backward(scene, mi.traverse(scene),
                                           dr.ones(mi.TensorXf, (24, 24, 3)), spp=1)
    chain, c = [], e.value
    while c is not None:
        chain.append(str(c))
        c = c.__cause__
    assert any('pbrt_path' in m and 'not attached to the AD graph' in m for m in chain), chain


def test_sample_called_with_a_ray_without_differentials():
    """``sample()`` called directly (a user's own render loop) with a plain ``Ray3f``: the camera
    hits have no ray differential, so their footprint is the camera approximation's — finite
    and non-zero partials, as pbrt-v4 does when a ray has none — instead of an error."""
    scene = mi.load_dict({
        'type': 'scene', 'sensor': camera([0, 2, 4], [0, 0, 0], 8, 8),
        'integrator': {'type': 'pbrt_path', 'max_depth': 1},
        'floor': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(5),
                  'emitter': {'type': 'area', 'radiance': {'type': 'test_probe',
                                                           'mode': 'nonzero'}}}})
    integrator, sensor = scene.integrator(), scene.sensors()[0]
    sampler = sensor.sampler().clone()
    sampler.seed(0, 64)
    i = dr.arange(mi.Float, 64)
    pos = mi.Point2f(i - 8 * dr.floor(i / 8) + 0.5, dr.floor(i / 8) + 0.5) / 8
    ray, _ = sensor.sample_ray(mi.Float(0), mi.Float(0.5), pos, mi.Point2f(0.5))
    L, valid, _, _ = integrator.sample(dr.ADMode.Primal, scene, sampler, mi.Ray3f(ray), None, None,
                                       mi.Bool(True))
    L, valid = np.array(L.x), np.array(valid)
    assert valid.sum() > 20                             # the floor fills most of the view
    assert np.all(np.isfinite(L)) and L[valid].min() == 1.0


# ---------------------------------------------------------------------------- shared lookups
def _shared_texture_cornell(filter_):
    """Mitsuba's Cornell box, 32×32, whose white (diffuse) and red (rough plastic) walls read one
    image texture and whose green wall its own: two BSDF instances share a texture; the boxes'
    shadows make emitter samples whose value query is masked off while the BSDF sample's is
    not (pdf 0: occluded)."""
    rng = np.random.default_rng(7)
    texels = mi.TensorXf(rng.random((16, 16, 3)).astype(np.float32))
    scene = mi.cornell_box()
    shared = {'type': 'pbrt_imagemap', 'filter': filter_, 'data': texels,
              'to_uv': T().scale([8, 8, 1])}
    scene['tex'] = shared
    scene['white'] = {'type': 'diffuse', 'reflectance': {'type': 'ref', 'id': 'tex'}}
    scene['red'] = {'type': 'roughplastic', 'alpha': 0.2,
                    'diffuse_reflectance': {'type': 'ref', 'id': 'tex'}}
    scene['green'] = {'type': 'diffuse', 'reflectance': {**shared, 'filter': 'bilinear'}}
    scene['sensor']['film']['width'] = scene['sensor']['film']['height'] = 32
    return {**scene, 'integrator': {'type': 'pbrt_path', 'max_depth': 4}}


@pytest.mark.parametrize('filter_', ['ewa', 'box'])
def test_shared_lookups_change_no_pixel(filter_, monkeypatch):
    """A primal bounce asks each BSDF instance for its value towards the emitter sample and for
    a sampled direction in one call, and a texture both queries read computes its value once
    (render_scope.shared_lookups). Against the same render with every lookup computed by its own
    query (sharing switched off): equal to float32 rounding (rtol 1e-5, atol 1e-6, as the prb
    comparisons) — on a scene where two BSDF instances share one texture (a value taken from
    the wrong instance's call would change its walls) and where shadowed lanes are in the BSDF
    sample's query only (left out, they would be black there)."""
    import contextlib

    from mitsuba_pbrt_tex import registry, render_scope
    images, reused = [], []
    unshared = render_scope.unshared

    def counted():
        reused.append(1)            # a lookup that found the first query's value
        return unshared()

    monkeypatch.setattr(render_scope, 'unshared', counted)
    for shared in (True, False):
        if not shared:
            monkeypatch.setattr(registry.plugin_module('pbrt_path'), 'shared_lookups',
                                contextlib.nullcontext)
        scene = mi.load_dict(_shared_texture_cornell(filter_))
        images.append(np.array(mi.render(scene, spp=4, seed=3)))
        if shared:      # white, red, green: each instance's sample reused its eval's lookup
            assert len(reused) == 3
    assert images[1].mean() > 0.05
    np.testing.assert_allclose(images[0], images[1], rtol=1e-5, atol=1e-6)


def test_shared_lookup_evaluates_only_the_lanes_not_yet_looked_up(rng, monkeypatch):
    """Within shared_lookups, a texture asked again at the same interaction returns the first
    value on the first query's lanes and evaluates only the rest (counted by wrapping the
    plugin's evaluate); its value equals an unshared lookup's on every lane asked; outside the
    block nothing is shared."""
    from mitsuba_pbrt_tex import render_scope
    tex = mi.load_dict({'type': 'pbrt_imagemap', 'filter': 'ewa',
                        'data': mi.TensorXf(rng.random((8, 8, 3)).astype(np.float32))})
    n = 400
    si = make_si(rng.random((n, 2)), duv_dx=rng.normal(0, 0.05, (n, 2)),
                 duv_dy=rng.normal(0, 0.05, (n, 2)))
    first = rng.random(n) < 0.6
    second = first | (rng.random(n) < 0.5)
    plain = A(tex.eval(si, mi.Bool(second)))
    counted = []
    evaluate = type(tex).evaluate

    def counting(self, si, kind, active):
        counted.append(int(dr.count(active)[0]))
        return evaluate(self, si, kind, active)

    monkeypatch.setattr(type(tex), 'evaluate', counting)
    with render_scope.shared_lookups():
        tex.eval(si, mi.Bool(first))
        value = A(tex.eval(si, mi.Bool(second)))
    assert counted == [first.sum(), (second & ~first).sum()]
    assert 0 < counted[1] < counted[0]
    np.testing.assert_allclose(value[second], plain[second], rtol=1e-6, atol=1e-7)
    # another texture, or the same one in another kind, at the same interaction: its own value
    other = mi.load_dict({'type': 'pbrt_imagemap', 'filter': 'bilinear',
                          'data': mi.TensorXf(rng.random((8, 8, 3)).astype(np.float32))})
    with render_scope.shared_lookups():
        tex.eval(si, mi.Bool(second))
        others = A(other.eval(si, mi.Bool(second)))
        grey = A(tex.eval_1(si, mi.Bool(second)))
    np.testing.assert_allclose(others, A(other.eval(si, mi.Bool(second))), rtol=1e-6)
    np.testing.assert_allclose(grey[second], A(tex.eval_1(si, mi.Bool(second)))[second],
                               rtol=1e-6, atol=1e-7)
    assert np.abs(others - value).max() > 0.1
    assert render_scope.lookups() is None
    tex.eval(si, mi.Bool(second))
    assert counted[-1] == second.sum()


def test_second_render_of_a_scene_compiles_no_new_kernel():
    """The first render of a scene must record the kernel later renders replay: the camera
    approximation's constants, left lazy, were computed inside the first render's kernel and read
    by every later one — two different kernels, so the one warm-up render of the benchmarks and
    demos still timed a compilation (found in a user trial: 3.3 s on the demo scene's second
    render). Dr.Jit's kernel history: the largest kernel of renders 1 and 2 has the same hash."""
    scene = mi.load_dict({
        'type': 'scene', 'integrator': {'type': 'pbrt_path', 'max_depth': 3},
        'sensor': {'type': 'perspective', 'to_world': T().look_at([0, 1, 3], [0, 0, 0], [0, 1, 0]),
                   'film': {'type': 'hdrfilm', 'width': 16, 'height': 12}},
        'sun': {'type': 'directional', 'direction': [0.2, -1, -0.3]},
        'plane': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(3),
                  'bsdf': {'type': 'diffuse', 'reflectance': {
                      'type': 'pbrt_imagemap', 'filter': 'trilinear',
                      'filename': 'scenes/textures/checker.png'}}}})
    hashes = []
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        for seed in range(2):
            dr.kernel_history_clear()
            dr.eval(mi.render(scene, spp=1, seed=seed))
            kernels = [k for k in dr.kernel_history() if 'hash' in k]
            hashes.append(max(kernels, key=lambda k: k['operation_count'])['hash'])
    assert hashes[0] == hashes[1]


@pytest.mark.parametrize('texture', [
    {'type': 'pbrt_uv'},
    {'type': 'pbrt_constant', 'value': {'type': 'rgb', 'value': [0.3, 0.5, 0.0]}}])
def test_textures_with_a_constant_channel_render_as_under_prb(texture):
    """A texture whose value has a constant channel (pbrt_uv's blue, an rgb constant's 0) as a
    BSDF's reflectance: the primal bounce's two BSDF queries share texture lookups, and sharing
    that constant aborted the process inside Dr.Jit's LLVM backend ("Instruction does not
    dominate all uses"; found in a user trial). Neither reads differentials, so the image is
    prb's with the same seed (float32 rounding: rtol 1e-5)."""
    images = []
    for integrator in ('pbrt_path', 'prb'):
        scene = mi.load_dict({
            'type': 'scene', 'integrator': {'type': integrator, 'max_depth': 3},
            'sensor': {'type': 'perspective',
                       'to_world': T().look_at([0, -2, 2], [0, 0, 0], [0, 0, 1]),
                       'film': {'type': 'hdrfilm', 'width': 8, 'height': 8}},
            'floor': {'type': 'rectangle', 'bsdf': {'type': 'diffuse', 'reflectance': texture}},
            'env': {'type': 'constant'}})
        images.append(np.array(mi.render(scene, spp=2, seed=3)))
    assert images[0].mean() > 0.1
    np.testing.assert_allclose(images[0], images[1], rtol=1e-5, atol=1e-6)


def _textured_light_scene(integrator):
    """A trilinear-textured area light seen from above at a slant, 24×16, 64 spp: its image
    depends on the footprint's scale."""
    return mi.load_dict({
        'type': 'scene', 'integrator': integrator,
        'sensor': {'type': 'perspective', 'fov': 50,
                   'to_world': T().look_at([0, -1.2, 1.0], [0, 0.3, 0], [0, 0, 1]),
                   'film': {'type': 'hdrfilm', 'width': 24, 'height': 16,
                            'rfilter': {'type': 'box'}},
                   'sampler': {'type': 'independent', 'sample_count': 64}},
        'plane': {'type': 'rectangle', 'to_world': T().scale(3),
                  'emitter': {'type': 'area', 'radiance': {
                      'type': 'pbrt_imagemap', 'filename': 'scenes/textures/checker.png',
                      'filter': 'trilinear', 'uscale': 4, 'vscale': 4}}}})


@pytest.mark.parametrize('wrapper', ['moment', 'aov'])
def test_nested_in_moment_or_aov_the_footprint_scale_is_the_same(wrapper):
    """Mitsuba's moment and aov integrators call pbrt_path's sample() with their own camera rays,
    whose differentials Mitsuba's SamplingIntegrator has already scaled by 1/√spp: pbrt_path
    applies the rest of its spp scale, so the footprints — and a trilinear texture's image — are
    those of pbrt_path rendering alone (found in a user trial: nested, the footprint was 1/spp
    instead of max(1/8, 1/√spp): 0.06 apart at 64 spp). Same random numbers: float32 rounding
    (atol 1e-5); the images differ at spp_scale 1/64, so the comparison can fail."""
    scene = _textured_light_scene

    def pbrt_path(**kw):
        return {'type': 'pbrt_path', 'max_depth': 1, **kw}

    nested = {'type': 'moment', 'integrator': pbrt_path()} if wrapper == 'moment' else \
        {'type': 'aov', 'aovs': 'dd.y:depth', 'integrator': pbrt_path()}
    alone = np.array(mi.render(scene(pbrt_path()), seed=1))[..., :3]
    wrapped = scene(nested)
    inside = np.array(mi.render(wrapped, seed=1))[..., :3]
    if wrapper == 'aov':            # the nested integrator's own channels, integrator.R, G, B
        bitmap = wrapped.sensors()[0].film().bitmap()
        names = [f.name for f in bitmap.struct_()]
        first = names.index('integrator.R')
        inside = np.array(bitmap)[..., first:first + 3]
    finer = np.array(mi.render(scene(pbrt_path(spp_scale=1 / 64)), seed=1))[..., :3]
    assert np.abs(alone - finer).max() > 1e-2
    np.testing.assert_allclose(inside, alone, rtol=0, atol=1e-5)


def test_rays_of_an_earlier_sample_rays_do_not_make_foreign_rays_its_own():
    """A user's loop calls pbrt_path's sample_rays and sample() itself; afterwards the same
    integrator, nested in moment, gets moment's rays (already scaled by 1/√spp): it must not
    take them for the rays of that earlier sample_rays (its hand-over is never cleared there),
    so the image equals the one without the user's loop (found in a review: the hand-over alone
    decided whose rays they were). Same random numbers: atol 1e-6."""
    inner = mi.load_dict({'type': 'pbrt_path', 'max_depth': 1})

    scene = _textured_light_scene

    wrapped = scene({'type': 'moment', 'integrator': inner})
    before = np.array(mi.render(wrapped, seed=1))
    direct = scene(inner)                       # the user's own loop on the same integrator
    sensor = direct.sensors()[0]
    sampler, _ = inner.prepare(sensor, 0, 4, [])
    ray, _, _ = inner.sample_rays(direct, sensor, sampler)
    dr.eval(inner.sample(dr.ADMode.Primal, direct, sampler, ray, None, None, mi.Bool(True))[0])
    after = np.array(mi.render(wrapped, seed=1))
    np.testing.assert_allclose(after, before, rtol=0, atol=1e-6)
