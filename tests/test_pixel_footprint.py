"""pbrt_path ``footprint="pixel"``: the pixel-centred footprint of camera hits against
brute-force ray casts through the pixel's centre and corners; 1-spp renders equal between seeds
on fully covered pixels (symbolic loop, symbolic BSDF call, wavefront mode) and close to a
high-spp pixel average; errors; texel gradients against finite differences."""

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from conftest import A, assert_frozen_steps_equal_unfrozen, wavefront_mode

T = mi.ScalarTransform4f
RES = (24, 16)


def scene_dict(texture, footprint='pixel', rfilter='box', second_bsdf=True, spp=1):
    d = {
        'type': 'scene',
        'integrator': {'type': 'pbrt_path', 'max_depth': 2, 'footprint': footprint},
        'sensor': {'type': 'perspective', 'fov': 45,
                   'to_world': T().look_at([0.3, 1.2, 3.0], [0, 0, -0.5], [0, 1, 0]),
                   'film': {'type': 'hdrfilm', 'width': RES[0], 'height': RES[1],
                            'rfilter': {'type': rfilter}},
                   'sampler': {'type': 'independent', 'sample_count': spp}},
        'sun': {'type': 'directional', 'direction': [0.2, -1, -0.3], 'irradiance': 3.0},
        'plane': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(2.5),
                  'bsdf': {'type': 'diffuse', 'reflectance': texture}}}
    if second_bsdf:       # a second BSDF makes si.bsdf() a real symbolic call
        d['ball'] = {'type': 'sphere', 'center': [1.6, 0.3, 0.8], 'radius': 0.25,
                     'bsdf': {'type': 'roughplastic'}}
    return d


def box_texture(rng, size=32, tiles=3.0, **kw):
    return {'type': 'pbrt_imagemap', 'filter': 'box',
            'data': mi.TensorXf(rng.random((size, size, 3)).astype(np.float32)),
            'uscale': tiles, 'vscale': tiles, **kw}


def cast(scene, pos):
    sensor = scene.sensors()[0]
    ray, _ = sensor.sample_ray_differential(0.0, 0.5, mi.Point2f(pos[:, 0], pos[:, 1]),
                                            mi.Point2f(0.5), True)
    return scene.ray_intersect(mi.Ray3f(ray))


def interior_pixels(scene):
    """Pixels whose centre and four corners all hit the plane (a mask of shape (H, W))."""
    w, h = RES
    ok = np.ones((h, w), bool)
    ys, xs = np.mgrid[0:h, 0:w]
    for ox, oy in ((0, 0), (1, 0), (0, 1), (1, 1), (0.5, 0.5)):
        pos = np.stack([(xs.ravel() + ox) / w, (ys.ravel() + oy) / h], 1)
        si = cast(scene, pos)
        hit = A(si.is_valid()) & (np.abs(A(si.p)[:, 1]) < 1e-4)
        ok &= hit.reshape(h, w)
    return ok


def test_footprint_matches_ray_casts_through_pixel_corners(rng):
    """uv of the centre ray and of the four corner rays against the footprint's formula
    uv_c + (a·D0 + b·D1)/(1 + a·g + b·h), a, b = ±1/2 — exact for a plane under a pinhole, so
    the tolerance is float32 rounding of uv (1e-5 of the uv range, against footprints of
    ~1e-2)."""
    from mitsuba_pbrt_tex import pixel
    scene = mi.load_dict(scene_dict(box_texture(rng)))
    sensor = scene.sensors()[0]
    mask = interior_pixels(scene)
    ys, xs = np.nonzero(mask)
    n = len(xs)
    assert n > 100
    jitter = rng.uniform(0.02, 0.98, (n, 2))
    pos = np.stack([(xs + jitter[:, 0]) / RES[0], (ys + jitter[:, 1]) / RES[1]], 1)
    si = cast(scene, pos)
    fp = pixel.pixel_footprint(sensor, si)
    assert A(fp.ok).all()
    centre = A(cast(scene, np.stack([(xs + 0.5) / RES[0], (ys + 0.5) / RES[1]], 1)).uv)
    np.testing.assert_allclose(A(fp.uv_c), centre, atol=1e-5)
    d0, d1, g, h = A(fp.d0), A(fp.d1), A(fp.g), A(fp.h)
    assert np.abs(h).max() > 0.02          # perspective is visible in this view
    for a, b in ((-0.5, -0.5), (0.5, -0.5), (-0.5, 0.5), (0.5, 0.5)):
        corner = A(cast(scene, np.stack([(xs + 0.5 + a) / RES[0], (ys + 0.5 + b) / RES[1]], 1)).uv)
        predicted = centre + (a * d0 + b * d1) / (1 + a * g + b * h)[:, None]
        np.testing.assert_allclose(predicted, corner, atol=1e-5)
    # secondary rays (not from the camera) are not pixel hits
    ray = mi.Ray3f(mi.Point3f(0.5, 2.0, 0.5), dr.normalize(mi.Vector3f(0.1, -1, 0.05)))
    assert not A(pixel.pixel_footprint(sensor, scene.ray_intersect(ray)).ok).any()


@pytest.mark.parametrize('mode', ['symbolic', 'symbolic-one-bsdf', 'wavefront'])
def test_one_spp_interior_pixels_equal_between_seeds(mode, rng):
    """With footprint=pixel every sample of a fully covered pixel sees the same texture value
    (the lighting of the plane is constant), so two 1-spp renders agree there: < 1e-4 (float32
    rounding of the pixel reconstruction; the sample-centred box differs by ~0.05)."""
    scene = mi.load_dict(scene_dict(box_texture(rng), second_bsdf=mode != 'symbolic-one-bsdf'))
    mask = interior_pixels(scene)
    with wavefront_mode(mode == 'wavefront'):
        a = np.array(mi.render(scene, spp=1, seed=1))
        b = np.array(mi.render(scene, spp=1, seed=2))
    assert mask.sum() > 100
    diff = np.abs(a - b)[mask]
    assert diff.max() < 1e-4, diff.max()
    sample = mi.load_dict(scene_dict(box_texture(rng), footprint='sample'))
    c = np.array(mi.render(sample, spp=1, seed=1)) - np.array(mi.render(sample, spp=1, seed=2))
    assert np.abs(c[mask]).max() > 1e-2          # the test can fail: sampling differs


def pixel_average_error(img, ref_scene, mask):
    """(RMSE of ``img`` on ``mask`` against ``ref_scene`` at 1024 spp, that reference's own
    noise there): the reference is rendered in two halves of 512 spp (seeds 10, 11), whose
    difference estimates its noise."""
    halves = [np.array(mi.render(ref_scene, spp=512, seed=10 + k)) for k in range(2)]
    ref = 0.5 * (halves[0] + halves[1])
    noise = np.sqrt(np.mean((halves[0] - halves[1])[mask] ** 2)) / 2
    return np.sqrt(np.mean((img - ref)[mask] ** 2)), noise


def test_pixel_values_equal_high_spp_pixel_average(rng):
    """Interior pixels at 1 spp against the pixel average of the same texture point-sampled
    (bilinear at level 0, no footprint) under pbrt_path at 1024 spp, estimated in two halves:
    the difference is within 4× the reference's own noise plus 2e-3 (the parallelogram
    approximation of the pixel's projective footprint, second order in g, h ≈ 0.05)."""
    tex = box_texture(rng, size=16, tiles=2.0)
    scene = mi.load_dict(scene_dict(tex))
    mask = interior_pixels(scene)
    img = np.array(mi.render(scene, spp=1, seed=3))
    ref_tex = dict(tex, filter='bilinear')
    ref_scene = mi.load_dict({**scene_dict(ref_tex, footprint='sample'),
                              'integrator': {'type': 'pbrt_path', 'max_depth': 2,
                                             'texture_differentials': False}})
    err, noise = pixel_average_error(img, ref_scene, mask)
    print(f"pixel-mode 1 spp RMSE {err:.5f}, reference noise {noise:.5f}")
    assert err < 4 * noise + 2e-3, (err, noise)


def test_checkerboard_area_filters_the_pixel(rng):
    """``pbrt_checkerboard`` ``aamode="area"`` opts in like ``box``: two 1-spp renders agree on
    interior pixels (< 1e-4, as above), and they match the pixel average of the point-sampled
    checkerboard (``aamode="none"``, 1024 spp in two halves) within 4× the reference's noise
    plus 2e-3 (the parallelogram approximation, as above)."""
    cells = {'tex1': 0.1, 'tex2': 0.9, 'uscale': 6.0, 'vscale': 6.0}
    scene = mi.load_dict(scene_dict({'type': 'pbrt_checkerboard', 'aamode': 'area', **cells}))
    mask = interior_pixels(scene)
    a = np.array(mi.render(scene, spp=1, seed=1))
    b = np.array(mi.render(scene, spp=1, seed=2))
    assert mask.sum() > 100
    assert np.abs(a - b)[mask].max() < 1e-4
    ref_scene = mi.load_dict(scene_dict({'type': 'pbrt_checkerboard', 'aamode': 'none', **cells},
                                        footprint='sample'))
    err, noise = pixel_average_error(a, ref_scene, mask)
    print(f"checkerboard area, pixel mode 1 spp RMSE {err:.5f}, reference noise {noise:.5f}")
    assert err < 4 * noise + 2e-3, (err, noise)


def test_products_of_varying_textures_keep_the_sample_footprint(rng):
    """A pixel's average of a product is not the product of the pixel's averages: inside a
    composite that multiplies spatially varying values (pbrt_scale of two images, pbrt_mix
    with a varying amount and a varying end, a checkerboard with a varying tex1, dots with a
    varying inside) the textures
    keep the sample's footprint — the 1-spp image equals footprint="sample"'s (same seed; up to
    the box film's camera samples kept 1e-3 pixel inside their pixel under pixel footprints,
    which moves a few hits onto other texels: ≤ 4e-4 in a trial, 0 here; tolerance 1e-3, where
    the old code was up to 0.15 off, 0.025 on average) — where the pixel averages used to be
    multiplied (a user trial: two box
    images in pbrt_scale 42% darker than the reference on a grazing plane's far rows, at any
    spp). Where the composite is linear in the one varying texture (a constant scale, constant
    ends, constant checks) pixel footprints stay: two 1-spp seeds agree to < 1e-4 there."""
    a, b, c = box_texture(rng), box_texture(rng), box_texture(rng, tiles=5.0)
    checks = {'type': 'pbrt_checkerboard', 'aamode': 'area', 'uscale': 6.0, 'vscale': 6.0}
    products = [{'type': 'pbrt_scale', 'tex': a, 'scale': b},
                {'type': 'pbrt_mix', 'tex1': a, 'tex2': b, 'amount': c},
                {**checks, 'tex1': a, 'tex2': 0.2},
                {'type': 'pbrt_dots', 'inside': a, 'outside': 0.3, 'uscale': 8.0, 'vscale': 8.0}]
    linear = [{'type': 'pbrt_scale', 'tex': a, 'scale': 0.5},
              {'type': 'pbrt_mix', 'tex1': 0.1, 'tex2': 0.9, 'amount': b},
              {**checks, 'tex1': 0.1, 'tex2': 0.9}]
    for tex in products + linear:
        scene = mi.load_dict(scene_dict(tex))
        mask = interior_pixels(scene)
        assert mask.sum() > 100
        one = np.array(mi.render(scene, spp=1, seed=1))
        if tex in products:
            sample = mi.load_dict(scene_dict(tex, footprint='sample'))
            np.testing.assert_allclose(one, np.array(mi.render(sample, spp=1, seed=1)),
                                       rtol=0, atol=1e-3)
        else:
            other = np.array(mi.render(scene, spp=1, seed=2))
            assert np.abs(one - other)[mask].max() < 1e-4
    # on a Gaussian film a box texture inside a product does not make the render draw its
    # camera samples per pixel from the film's filter (only a texture that filters the film's
    # kernel needs that; the shared sample offsets alias silhouettes and count each sample in
    # one pixel): the render is footprint="sample"'s, splatted by the film (it was not)
    scene = mi.load_dict(scene_dict(products[0], rfilter='gaussian'))
    sample = mi.load_dict(scene_dict(products[0], footprint='sample', rfilter='gaussian'))
    np.testing.assert_array_equal(np.array(mi.render(scene, spp=4, seed=1)),
                                  np.array(mi.render(sample, spp=4, seed=1)))


@pytest.mark.parametrize('normal_map', [False, True])
@pytest.mark.parametrize('rfilter', ['box', 'gaussian'])
def test_back_side_hits_through_a_twosided_bsdf_get_the_pixel_footprint(rfilter, normal_map,
                                                                        rng):
    """A plane seen from its back (``flip_normals``) through a ``twosided`` BSDF: the BSDF hands
    the textures the hit with its local wi mirrored in the tangent plane, which the camera-hit
    test did not recognise — pixel footprints were silently off on the box film and, on the
    Gaussian film, worse than the sample's (a trial: 1-spp seeds 0.0915 / 0.0976 apart); with
    a normal map inside the ``twosided`` that mirror image is in the original frame, which the
    map replaces (a review: 0.24 / 0.31 apart). Two 1-spp seeds agree to < 1e-4 on interior
    pixels, as on the front side."""
    d = scene_dict(box_texture(rng), rfilter=rfilter)
    d['plane']['flip_normals'] = True
    inner = d['plane']['bsdf']
    if normal_map:
        tilted = mi.Bitmap(np.full((4, 4, 3), (0.7, 0.5, 1.0), np.float32))
        inner = {'type': 'normalmap', 'bsdf': inner,
                 'normalmap': {'type': 'bitmap', 'bitmap': tilted, 'raw': True}}
    d['plane']['bsdf'] = {'type': 'twosided', 'bsdf': inner}
    scene = mi.load_dict(d)
    mask = interior_pixels(scene)
    a = np.array(mi.render(scene, spp=1, seed=1))
    b = np.array(mi.render(scene, spp=1, seed=2))
    assert mask.sum() > 100 and a[mask].mean() > 0.05
    assert np.abs(a - b)[mask].max() < 1e-4


def _smooth_quad(bsdf, tilt):
    """The scene_dict plane (y = 0, 5 × 5), facing away from the camera, as a two-triangle mesh
    whose vertex normals lean ±``tilt`` radians from the face normal (smooth shading)."""
    props = mi.Properties()
    props['bsdf'] = mi.load_dict(bsdf)
    mesh = mi.Mesh('quad', 4, 2, props, has_vertex_normals=True, has_vertex_texcoords=True)
    params = mi.traverse(mesh)
    params['vertex_positions'] = [-2.5, 0, -2.5, 2.5, 0, -2.5, 2.5, 0, 2.5, -2.5, 0, 2.5]
    params['faces'] = [0, 1, 2, 0, 2, 3]
    params['vertex_normals'] = [c for k in range(4)
                                for c in (math.sin(tilt if k % 2 else -tilt), -math.cos(tilt), 0)]
    params['vertex_texcoords'] = [0, 0, 1, 0, 1, 1, 0, 1]
    params.update()
    return mesh


def test_back_sides_of_smooth_shaded_meshes_through_twosided(rng):
    """A smooth-shaded mesh seen from its back through ``twosided``: the shading-frame mirror
    finds the camera ray (1-spp seeds within the shading's own variation inside a pixel,
    measured 0.005, where the sample's footprint leaves 0.2-0.5). Under a normal map inside the
    ``twosided`` that frame is gone and the geometric-plane mirror is off by the normals'
    lean: beyond the frames' rounding it is refused (it named film positions up to 0.7 pixel
    off within the looser camera tolerance, a review) — those back sides keep the sample's
    footprint, even for a lean of 3e-5."""
    tilted = mi.Bitmap(np.full((4, 4, 3), (0.7, 0.5, 1.0), np.float32))
    for normal_map, tilt, converged in ((False, 0.2, True), (True, 3e-5, False)):
        d = scene_dict(box_texture(rng))
        inner = d.pop('plane')['bsdf']
        if normal_map:
            inner = {'type': 'normalmap', 'bsdf': inner,
                     'normalmap': {'type': 'bitmap', 'bitmap': tilted, 'raw': True}}
        d['quad'] = _smooth_quad({'type': 'twosided', 'bsdf': inner}, tilt)
        scene = mi.load_dict(d)
        mask = interior_pixels(scene)
        a = np.array(mi.render(scene, spp=1, seed=1))
        b = np.array(mi.render(scene, spp=1, seed=2))
        assert mask.sum() > 100
        spread = np.abs(a - b)[mask].max()
        assert (spread < 0.02) if converged else (spread > 0.05), (normal_map, spread)


def test_pixel_footprint_errors(rng):
    with pytest.raises(RuntimeError) as e:
        mi.render(mi.load_dict(scene_dict(box_texture(rng), rfilter='tent')), spp=1)
    text = str(e.value) + str(getattr(e.value, '__cause__', ''))
    import traceback
    text += ''.join(traceback.format_exception(e.value))
    for word in ('pbrt_path', '"footprint"', '"pixel"', '"box"', '"gaussian"', 'TentFilter',
                 'sample, pixel'):
        assert word in text, word
    with pytest.raises(RuntimeError) as e:
        mi.load_dict({'type': 'pbrt_path', 'footprint': 'centre'})
    for word in ('pbrt_path', '"footprint"', 'centre', 'sample, pixel'):
        assert word in str(e.value), word


def test_texel_gradients_through_pixel_footprint(rng):
    """Backward-mode texel gradients of a footprint=pixel render against central finite
    differences at the gradient seed (the project's check_gradient, 2%)."""
    import test_gradients as tg
    d = scene_dict(box_texture(rng, size=16), second_bsdf=False)
    d['sensor']['film'].update(width=tg.RES, height=tg.RES)
    d['integrator']['max_depth'] = 3
    tg.check_gradient(mi.load_dict(d), 'plane.bsdf.reflectance.data', rng)


def _edge_pixels(scene):
    """Pixels whose centre and corner rays disagree about the surface (independent of the
    integrator's test: shapes compared through the hit's y = 0 plane and validity)."""
    w, h = RES
    ys, xs = np.mgrid[0:h, 0:w]
    keys = []
    for ox, oy in ((0.5, 0.5), (0, 0), (1, 0), (0, 1), (1, 1)):
        pos = np.stack([(xs.ravel() + ox) / w, (ys.ravel() + oy) / h], 1)
        si = cast(scene, pos)
        on_plane = A(si.is_valid()) & (np.abs(A(si.p)[:, 1]) < 1e-4)
        keys.append(np.where(A(si.is_valid()), np.where(on_plane, 1, 2), 0))
    keys = np.array(keys)
    return (keys != keys[0]).any(0).reshape(h, w)


@pytest.mark.parametrize('wavefront', [False, True])
def test_silhouette_samples_only_in_edge_pixels(wavefront, rng):
    """silhouette_spp adds paths only where a pixel crosses a silhouette: elsewhere the image is
    unchanged (same random numbers: identical), and the edge pixels' error against a 512-spp
    pixel average drops by more than half (1 path → 17 per edge pixel)."""
    tex = box_texture(rng, size=16, tiles=2.0)
    base = scene_dict(tex)
    plain = mi.load_dict(base)
    extra = mi.load_dict({**base, 'integrator': {**base['integrator'], 'silhouette_spp': 16}})
    edge = _edge_pixels(plain)
    assert 10 < edge.sum() < edge.size / 3
    with wavefront_mode(wavefront):
        a = np.array(mi.render(plain, spp=1, seed=4))
        b = np.array(mi.render(extra, spp=1, seed=4))
    np.testing.assert_array_equal(a[~edge], b[~edge])
    # and every edge pixel gets them: 16 more paths through other points of a pixel that
    # crosses a silhouette change its value (the 5 rays of _edge_pixels find the same pixels)
    assert np.all((a != b).any(-1)[edge])
    ref_scene = mi.load_dict({**scene_dict(dict(tex, filter='bilinear'), footprint='sample'),
                              'integrator': {'type': 'pbrt_path', 'max_depth': 2,
                                             'texture_differentials': False}})
    ref = np.array(mi.render(ref_scene, spp=512, seed=11))
    err_a = np.sqrt(np.mean((a - ref)[edge] ** 2))
    err_b = np.sqrt(np.mean((b - ref)[edge] ** 2))
    assert err_b < 0.5 * err_a, (err_a, err_b)


def test_silhouette_samples_refuse_gradients(rng):
    d = scene_dict(box_texture(rng, size=8))
    d['integrator']['silhouette_spp'] = 4
    scene = mi.load_dict(d)
    params = mi.traverse(scene)
    dr.enable_grad(params['plane.bsdf.reflectance.data'])
    params.update()
    with pytest.raises(Exception) as e:
        img = mi.render(scene, params, spp=1, seed=1, seed_grad=2)
        dr.backward(dr.sum(img, axis=None))
    import traceback
    text = ''.join(traceback.format_exception(e.value))
    assert '"silhouette_spp"' in text and 'primal' in text


@pytest.mark.parametrize('footprint', ['sample', 'pixel'])
def test_frozen_steps_with_box_equal_unfrozen(footprint, rng):
    """dr.freeze over render + backward (Mitsuba's frozen-optimisation pattern, as
    test_gradient_workflows does for the other filters): the box tables are rebuilt by
    params.update() outside the frozen function and reach the replayed kernels — losses and
    texel gradients equal the unfrozen ones (float32 rounding: 1e-5)."""
    key = 'plane.bsdf.reflectance.data'
    texels = rng.random((8, 8, 3)).astype(np.float32)

    def load():         # a fresh tensor per scene: the optimiser updates the texels in place
        return mi.load_dict(scene_dict({'type': 'pbrt_imagemap', 'filter': 'box',
                                        'data': mi.TensorXf(texels), 'uscale': 3.0,
                                        'vscale': 3.0}, footprint=footprint, second_bsdf=False))

    assert_frozen_steps_equal_unfrozen(load, key, 4, spp=2)


@pytest.mark.parametrize('height', [0.0, 1e-4, 0.05])
def test_hard_cases_camera_in_or_near_the_plane_stay_finite(height, rng):
    """Camera in the plane (every hit grazing or none), a hair above it, and low over it, with
    silhouette samples: finite images, within [0, 3/π] (texels in [0, 1], a diffuse plane under a
    sun of irradiance 3, no other light)."""
    d = scene_dict(box_texture(rng, size=8, tiles=50.0))
    d['sensor']['to_world'] = T().look_at([0.2, height, 2.4], [0, height * 0.5, -3], [0, 1, 0])
    d['integrator']['silhouette_spp'] = 4
    img = np.array(mi.render(mi.load_dict(d), spp=1, seed=1))
    assert np.isfinite(img).all()
    assert img.min() >= 0 and img.max() <= 3 / np.pi + 1e-4


def test_silhouette_samples_follow_the_render_seed(rng):
    """The extra paths of edge pixels draw from a sampler seeded from the render's: renders with
    two seeds give different extra paths. Their sum is recovered per pixel from the two images
    of a seed, with and without silhouette_spp (L = (L_sample + Σ extra) / 17); the sums of the
    two seeds differ by far more than float32 rounding of that recovery (~1e-5) in edge pixels
    (the same seed inside would give equal sums). Not in all: the extra paths' points are a
    shifted (0, 2)-sequence, and where this scene's straight edges cut a pixel on a stratum
    boundary every shift puts the same number of points on either side (measured: 3 of 24
    pixels differ)."""
    tex = box_texture(rng, size=16, tiles=2.0)
    base = scene_dict(tex)
    plain = mi.load_dict(base)
    extra = mi.load_dict({**base, 'integrator': {**base['integrator'], 'silhouette_spp': 16}})
    edge = _edge_pixels(plain)
    sums = []
    for seed in (4, 5):
        a = np.array(mi.render(plain, spp=1, seed=seed))
        b = np.array(mi.render(extra, spp=1, seed=seed))
        sums.append(17 * b[edge] - a[edge])
    differ = (np.abs(sums[0] - sums[1]) > 1e-3).any(-1)
    assert differ.sum() >= 2, differ.sum()


def test_silhouette_paths_read_box_textures_once_per_pixel(rng):
    """In silhouette paths (render_scope.silhouette_paths) a box-filtered image texture reads
    EWA over its pixel's footprint: two hits at different points of the same pixel get the
    same value (float32 rounding of each hit's pixel footprint, through EWA's weight table:
    < 5e-5, measured 1.4e-5); it equals what an
    ``ewa`` texture of the same image returns for a hit carrying that pixel's centroid and
    partials (5e-6: the same filter reached through the other plugin path), and differs from
    both the exact box average (outside silhouette paths) and the sample-centred EWA by
    ≥ 1e-3 somewhere (the filter and the footprint both matter on this noise)."""
    from mitsuba_pbrt_tex import pixel
    from mitsuba_pbrt_tex.render_scope import RenderScope, published, silhouette_paths
    spec = box_texture(rng, size=64, tiles=6.0, maxanisotropy=16)
    box_tex = mi.load_dict(spec)
    ewa_tex = mi.load_dict({**spec, 'filter': 'ewa'})
    scene = mi.load_dict(scene_dict(spec))
    sensor = scene.sensors()[0]
    w, h = RES
    n = 24
    pixels = np.stack([rng.integers(2, w - 2, n), rng.integers(h // 2, h - 1, n)], 1)
    scope = RenderScope(sensor)
    seen = []
    for jitter in (0.2, 0.8):
        pos = (pixels + jitter) / np.array([w, h])
        ray, _ = sensor.sample_ray_differential(0.0, 0.5, mi.Point2f(pos[:, 0], pos[:, 1]),
                                                mi.Point2f(0.5), True)
        si = scene.ray_intersect(ray)
        si.compute_uv_partials(ray)
        assert A(si.is_valid()).all()
        with published(scope), silhouette_paths():
            extra = A(box_tex.eval(si))
        with published(scope):
            exact = A(box_tex.eval(si))
            ctx = pixel.context(si)
        sample_ewa = A(ewa_tex.eval(si))
        at_pixel = mi.SurfaceInteraction3f(si)
        at_pixel.uv = ctx.uv
        at_pixel.duv_dx = mi.Vector2f(ctx.dudx, ctx.dvdx)
        at_pixel.duv_dy = mi.Vector2f(ctx.dudy, ctx.dvdy)
        pixel_ewa = A(ewa_tex.eval(at_pixel))
        np.testing.assert_allclose(extra, pixel_ewa, rtol=0, atol=5e-6)
        assert np.abs(extra - exact).max() > 1e-3
        assert np.abs(extra - sample_ewa).max() > 1e-3
        seen.append(extra)
    np.testing.assert_allclose(seen[0], seen[1], rtol=0, atol=5e-5)


def test_silhouette_points_are_a_shifted_02_sequence(rng):
    """The extra paths' points (silhouettes.net_point) for random digital shifts: the first 16
    of a lane have exactly one point in each elementary interval of area 1/16 (16×1, 8×2, 4×4,
    2×8, 1×16 boxes) — what makes a straight edge's coverage error fall faster than
    independent points' — the first 8 likewise at 1/8, and over many shifts a point is uniform
    in the square (mean 1/2, variance 1/12 per axis within 3 standard errors)."""
    from mitsuba_pbrt_tex.silhouettes import net_point
    lanes = 200
    shifts = [mi.UInt32(rng.integers(0, 2 ** 32, lanes, dtype=np.uint64).astype(np.uint32))
              for _ in range(2)]
    pts = np.stack([A(net_point(mi.UInt32(np.full(lanes, k, np.uint32)), *shifts, 5))
                    for k in range(16)], 1)              # lanes × 16 × 2
    assert pts.min() >= 0 and pts.max() < 1
    for n, m in ((16, 4), (8, 3)):
        for a in range(m + 1):
            cells = (np.floor(pts[:, :n, 0] * 2 ** a) * 2 ** (m - a)
                     + np.floor(pts[:, :n, 1] * 2 ** (m - a)))
            counts = np.stack([(cells == c).sum(1) for c in range(2 ** m)], 1)
            assert (counts == 1).all(), (n, a)
    x = pts[:, 3, 0]
    assert abs(x.mean() - 0.5) < 3 * np.sqrt(1 / 12 / lanes)
    assert abs(x.var() - 1 / 12) < 3 * np.sqrt(1 / 180 / lanes)


def test_silhouette_shifts_are_uniform_and_independent():
    """The lanes' digital shifts (silhouettes.digital_shift, from a sampler) as points of
    [0, 1)²: uniform in each coordinate (mean 1/2, variance 1/12, and a quarter of them in each
    half of [0, 1/2) within 4 standard errors) and uncorrelated (|r| < 4/√n), over 4096 lanes —
    a shift confined to a corner, or one coordinate's reused, would bias the coverage
    estimate."""
    from mitsuba_pbrt_tex.silhouettes import digital_shift
    n = 4096
    sampler = mi.load_dict({'type': 'independent'})
    sampler.seed(7, n)
    sx, sy = digital_shift(sampler)
    pts = np.stack([A(sx), A(sy)], 1).astype(np.float64) / 2.0 ** 32
    for c in range(2):
        v = pts[:, c]
        assert abs(v.mean() - 0.5) < 4 * np.sqrt(1 / 12 / n)
        assert abs(v.var() - 1 / 12) < 4 * np.sqrt(1 / 180 / n)
        quarter = ((v >= 0.25) & (v < 0.5)).mean()
        assert abs(quarter - 0.25) < 4 * np.sqrt(0.25 * 0.75 / n)
    assert abs(np.corrcoef(pts[:, 0], pts[:, 1])[0, 1]) < 4 / np.sqrt(n)


def test_silhouette_spp_has_no_effect_with_the_sample_footprint(rng):
    """silhouette_spp belongs to footprint="pixel" (parameter table): with the sample footprint
    it changes nothing — the same image bit for bit (same seed), and gradient renders, which
    refuse it with the pixel footprint, run."""
    tex = box_texture(rng, size=8)
    d = scene_dict(tex, footprint='sample')
    with_extra = mi.load_dict({**d, 'integrator': {**d['integrator'], 'silhouette_spp': 4}})
    plain = mi.load_dict(d)
    np.testing.assert_array_equal(np.array(mi.render(with_extra, spp=1, seed=3)),
                                  np.array(mi.render(plain, spp=1, seed=3)))
    d = scene_dict(box_texture(rng, size=8), footprint='sample')       # texels of its own
    scene = mi.load_dict({**d, 'integrator': {**d['integrator'], 'silhouette_spp': 4}})
    params = mi.traverse(scene)
    dr.enable_grad(params['plane.bsdf.reflectance.data'])
    params.update()
    img = mi.render(scene, params, spp=1, seed=1, seed_grad=2)
    dr.backward(dr.sum(img, axis=None))
    assert np.abs(np.array(dr.grad(params['plane.bsdf.reflectance.data']))).sum() > 0


# ------------------------------------------------------------------ found by mutation testing
def two_sensor_scene(tex, rfilter='box', same_place=False):
    """``scene_dict`` with a first sensor that looks at the plane from elsewhere (or, with
    ``same_place``, from the second's pose) with another field of view and film size; the
    scene's own sensor is the second."""
    d = scene_dict(tex, rfilter=rfilter)
    first = {'type': 'perspective', 'fov': 60,
             'to_world': T().look_at([-1.8, 2.2, 1.0], [0.4, 0, -0.8], [0, 1, 0]),
             'film': {'type': 'hdrfilm', 'width': 20, 'height': 20,
                      'rfilter': {'type': rfilter}},
             'sampler': {'type': 'independent', 'sample_count': 1}}
    if same_place:
        first['to_world'] = d['sensor']['to_world']
    return {'type': 'scene', 'first': first,
            **{k: v for k, v in d.items() if k != 'type'}}


def test_rays_of_another_integrator_in_a_scene_of_two_sensors_keep_the_sample_footprint(
        rng, capfd):
    """Mitsuba's ``moment`` hands ``pbrt_path.sample()`` rays of its own, and in a scene of two
    sensors nothing tells which one they come from: camera hits keep the sample's footprint
    (the image equals ``footprint="sample"``'s, to float32 rounding) and a warning says so —
    the first sensor was assumed (a render of the second through ``moment`` took pixel
    footprints of the wrong camera; found in a review)."""
    tex = box_texture(rng, size=16, tiles=2.0)
    images = {}
    for footprint in ('pixel', 'sample'):
        d = two_sensor_scene(tex)
        d['integrator'] = {'type': 'moment', 'inner': dict(d['integrator'], footprint=footprint)}
        images[footprint] = np.array(mi.render(mi.load_dict(d), spp=1, seed=4, sensor=1))
    np.testing.assert_allclose(images['pixel'], images['sample'], rtol=1e-6, atol=1e-7)
    said = capfd.readouterr()               # Mitsuba's logger writes to the console's stdout
    assert 'needs to know the sensor of the camera rays' in said.out + said.err


def test_second_sensor_gets_its_own_pixel_footprint(rng):
    """``mi.render(scene, sensor=1)``: the textures must see the pixel of the sensor rendered,
    not the scene's first one. The second sensor is the one of the other tests, so the checks
    are theirs: two 1-spp renders agree on interior pixels (< 1e-4), and they match the
    high-spp pixel average of the point-sampled texture seen through that sensor alone
    (4× the reference's noise + 2e-3). Publishing the first sensor makes no hit a camera hit
    of it (its centre of projection is elsewhere): every lane falls back to the sample's
    footprint, and the seeds disagree by ~0.05."""
    tex = box_texture(rng, size=16, tiles=2.0)
    scene = mi.load_dict(two_sensor_scene(tex))
    assert len(scene.sensors()) == 2
    alone = mi.load_dict(scene_dict(tex))            # the second sensor as the only one
    mask = interior_pixels(alone)
    a = np.array(mi.render(scene, sensor=1, spp=1, seed=1))
    b = np.array(mi.render(scene, sensor=1, spp=1, seed=2))
    assert a.shape[:2] == (RES[1], RES[0]) and mask.sum() > 100
    assert np.abs(a - b)[mask].max() < 1e-4
    ref_scene = mi.load_dict({**scene_dict(dict(tex, filter='bilinear'), footprint='sample'),
                              'integrator': {'type': 'pbrt_path', 'max_depth': 2,
                                             'texture_differentials': False}})
    err, noise = pixel_average_error(a, ref_scene, mask)
    assert err < 4 * noise + 2e-3, (err, noise)


PROBES = ((0.5, 0.5), (0, 0), (1, 0), (0, 1), (1, 1))        # pixel centre, then the corners


def silhouette_scene(crop=None):
    """Camera looking down -z at: a background rectangle covering the right of the view (the
    left misses: a straight silhouette against nothing), a sphere half over it (a disk: every
    pixel corner alone crosses it somewhere), a rotated cube (creases: one shape, normals 90°
    apart), a thin vertical cylinder (0.35 pixel wide: pixels whose centre alone hits it).
    ``crop``: (offset, size) of the film's crop window."""
    film = {'type': 'hdrfilm', 'width': RES[0], 'height': RES[1], 'rfilter': {'type': 'box'}}
    if crop is not None:
        (ox, oy), (cw, ch) = crop
        film.update(crop_offset_x=ox, crop_offset_y=oy, crop_width=cw, crop_height=ch)
    grey = {'type': 'diffuse', 'reflectance': 0.5}
    return mi.load_dict({
        'type': 'scene',
        'integrator': {'type': 'pbrt_path', 'max_depth': 2, 'footprint': 'pixel',
                       'silhouette_spp': 4},
        'sensor': {'type': 'perspective', 'fov': 45, 'to_world': T().look_at([0, 0, 0], [0, 0, -1],
                                                                            [0, 1, 0]),
                   'film': film, 'sampler': {'type': 'independent', 'sample_count': 1}},
        'back': {'type': 'rectangle', 'to_world': T().translate([1.6, 0, -4]).scale([2.1, 3, 1]),
                 'bsdf': {'type': 'diffuse', 'reflectance': box_texture(np.random.default_rng(0),
                                                                        size=8)}},
        'ball': {'type': 'sphere', 'center': [-0.55, 0.15, -2.5], 'radius': 0.6, 'bsdf': grey},
        'cube': {'type': 'cube', 'bsdf': grey,
                 'to_world': T().translate([0.85, -0.25, -2.6]).rotate([1, 0, 0], 25)
                 .rotate([0, 1, 0], 35).scale(0.3)},
        'stick': {'type': 'cylinder', 'p0': [0.27, -2, -2], 'p1': [0.27, 2, -2], 'radius': 0.012,
                  'bsdf': grey}})


def film_window(scene):
    film = scene.sensors()[0].film()
    (ox, oy), (w, h) = film.crop_offset(), film.crop_size()
    ys, xs = np.mgrid[oy:oy + h, ox:ox + w]
    return xs.ravel().astype(np.float64), ys.ravel().astype(np.float64), (ox, oy), (w, h)


def probe_hits(scene):
    """(valid, shape id, normal) of Mitsuba's camera rays through each probe of every pixel of
    the film's crop window: arrays of shape (5, pixels[, 3])."""
    sensor = scene.sensors()[0]
    xs, ys, (ox, oy), (w, h) = film_window(scene)
    valid, shape, normal = [], [], []
    for px, py in PROBES:
        pos = mi.Point2f((xs + px - ox) / w, (ys + py - oy) / h)
        ray, _ = sensor.sample_ray_differential(0.0, 0.5, pos, mi.Point2f(0.5), True)
        si = scene.ray_intersect(mi.Ray3f(ray))
        valid.append(A(si.is_valid()))
        shape.append(A(dr.reinterpret_array(mi.UInt32, si.shape)))
        normal.append(A(si.n))
    return np.array(valid), np.array(shape), np.array(normal)


@pytest.mark.parametrize('crop', [None, ((5, 3), (14, 10))])
def test_silhouette_pixels_match_ray_casts_through_centre_and_corners(crop):
    """The pixels that get silhouette paths (``silhouettes.edge_pixels``, with every pixel of
    the film) against Mitsuba's rays through each pixel's centre and four corners compared in
    numpy: a pixel crosses a silhouette where a corner ray and the centre ray disagree about
    hitting, about the shape, or about the normal (cos < 0.9) — the rule of the parameter
    table. Exact equality: both cast the same rays. The scene makes every part of the rule
    decide some pixel: each corner alone, the centre alone, the normal alone; with a crop
    window, the window's pixels (full-film coordinates, as Mitsuba's ``sample_rays`` gives)."""
    scene = silhouette_scene(crop)
    valid, shape, normal = probe_hits(scene)
    differs = (valid != valid[0]) | (valid & ((shape != shape[0]) |
                                              (np.einsum('kpc,pc->kp', normal, normal[0]) < 0.9)))
    want = differs[1:].any(0)
    if crop is None:
        # the scene decides each part of the rule in some pixel
        for k in range(1, 5):
            only = differs[k] & (differs[1:].sum(0) == 1)
            assert only.sum() >= 2, (PROBES[k], only.sum())
        corners_agree = np.all([(valid[k] == valid[1]) & (shape[k] == shape[1])
                                for k in range(2, 5)], axis=0)
        assert (want & corners_agree).sum() >= 2          # the centre alone disagrees
        same = (valid.all(0) & (shape == shape[0]).all(0))
        assert (want & same).sum() >= 2                    # the normal alone disagrees
    assert 20 < want.sum() < want.size / 2
    from mitsuba_pbrt_tex.silhouettes import edge_pixels
    xs, ys, _, _ = film_window(scene)
    got = A(edge_pixels(scene, scene.sensors()[0], mi.Vector2f(xs, ys), mi.Bool(True)))
    np.testing.assert_array_equal(got, want)


def test_silhouette_paths_are_averaged_with_the_sample(rng):
    """An edge pixel's value is the mean of the sample's path and its ``silhouette_spp`` extra
    paths, all through uniform points of the pixel: with a texture that is one constant
    (nothing depends on the footprint) the edge pixels are an unbiased estimate of the pixel
    average. Their mean over the edge pixels (6 renders of 4 spp, silhouette_spp 3: 16 paths
    per pixel and render) against Mitsuba's ``path`` with the constant reflectance (512 spp in
    two halves): within 4 standard errors of the difference (measured: ~1σ; ~0.0035 on a mean of
    0.19). A weight of 1/5 or 1/2 instead of 1/4 moves the mean by -20% or +100% (≥ 10σ)."""
    tex = {'type': 'pbrt_imagemap', 'filter': 'box',
           'data': mi.TensorXf(np.full((4, 4, 3), 0.6, np.float32))}
    base = scene_dict(tex)
    scene = mi.load_dict({**base, 'integrator': {**base['integrator'], 'silhouette_spp': 3}})
    edge = _edge_pixels(scene)
    assert edge.sum() >= 20
    means = [np.array(mi.render(scene, spp=4, seed=s))[edge].mean() for s in range(6)]
    mean, se = np.mean(means), np.std(means, ddof=1) / np.sqrt(len(means))
    ref_scene = mi.load_dict({**scene_dict(0.6, footprint='sample'),
                              'integrator': {'type': 'path', 'max_depth': 2}})
    halves = [np.array(mi.render(ref_scene, spp=512, seed=20 + k))[edge] for k in range(2)]
    ref = 0.5 * (halves[0] + halves[1]).mean()
    se_ref = np.sqrt(np.mean((halves[0] - halves[1]) ** 2) / (4 * halves[0].size))
    print(f"edge mean {mean:.4f} ± {se:.4f}, path {ref:.4f} ± {se_ref:.4f}")
    assert abs(mean - ref) < 4 * np.hypot(se, se_ref), (mean, se, ref, se_ref)


def test_silhouette_spp_bounds(rng):
    """silhouette_spp is an integer ≥ 0 (parameter table): 0 given explicitly is accepted and
    adds nothing — the image equals the one without the parameter bit for bit (same seed) —,
    -1 is refused naming the plugin, the parameter, the bound and the value."""
    d = scene_dict(box_texture(rng, size=8))
    zero = mi.load_dict({**d, 'integrator': {**d['integrator'], 'silhouette_spp': 0}})
    plain = mi.load_dict(d)
    np.testing.assert_array_equal(np.array(mi.render(zero, spp=1, seed=3)),
                                  np.array(mi.render(plain, spp=1, seed=3)))
    with pytest.raises(RuntimeError) as e:
        mi.load_dict({'type': 'pbrt_path', 'footprint': 'pixel', 'silhouette_spp': -1})
    for word in ('pbrt_path', '"silhouette_spp"', '>= 0', '-1'):
        assert word in str(e.value), word


@pytest.mark.parametrize('case', ['tent', 'orthographic', 'perspective, box film'])
def test_pixel_footprint_without_differential_textures_renders_as_prb(case):
    """footprint="pixel" concerns textures that use differentials: with none in the scene
    (Mitsuba's ``bitmap``) nothing is published and no sensor or film check applies — a tent
    filter or an orthographic sensor, both refused when a texture opts in, render — and the
    camera rays are prb's (the box film's rays moved 1e-3 pixel inside their pixel even then:
    1% off prb in a few pixels, found in a README check). The image is Mitsuba's ``prb`` with
    the same parameters and seed (float32 rounding: rtol 1e-5, as in test_pbrt_path's
    comparison with prb). The bitmap is tiled 40 times, several texels a pixel: the inset moves
    ~0.4% of the samples (those within 1e-3 pixel of their pixel's border), each by a visible
    change of value."""
    d = scene_dict({'type': 'bitmap', 'filename': 'tests/data/srgb_11x9.png',
                    'to_uv': T().scale([40, 40, 1])})
    if case == 'tent':
        d['sensor']['film']['rfilter'] = {'type': 'tent'}
    elif case == 'orthographic':
        d['sensor'] = {**d['sensor'], 'type': 'orthographic',
                       'to_world': d['sensor']['to_world'] @ T().scale([1.5, 1.5, 1])}
        del d['sensor']['fov']
    images = []
    for integrator in ({'type': 'prb', 'max_depth': 2}, d['integrator']):
        scene = mi.load_dict({**d, 'integrator': integrator})
        images.append(np.array(mi.render(scene, spp=16, seed=5)))
    assert images[0].mean() > 0.05
    np.testing.assert_allclose(images[1], images[0], rtol=1e-5, atol=1e-6)


def far_edge_scene(tex):
    """A plane seen nearly edge-on, its far edge in the image: pixels just below the edge see a
    strongly perspective footprint (|h| up to ~0.5)."""
    d = scene_dict(tex, second_bsdf=False)
    d['sensor']['to_world'] = T().look_at([0, 0.25, 2.4], [0, 0.05, -2.5], [0, 1, 0])
    return d


def test_pixels_next_to_a_far_edge_equal_ray_casts_through_the_pixel(rng, monkeypatch):
    """Fully covered pixels next to a plane's far edge (|h| > 0.15) at 1 spp against the
    average of 32×32 stratified ray casts through each pixel looking up the bilinear texture at
    level 0 (the quantity the box filter integrates exactly), times the shading of a white
    plane. The parallelogram misses the projective footprint at second order in the
    perspective terms: one parallelogram for the whole pixel (MAX_STRIPS = 1) is off by ~0.03;
    the default strips (terms ≤ 1/32, at most 2: these pixels' terms, up to 0.37, are halved —
    second-order error ≤ (0.37/2)² of the texels' contrast, 0.0125 measured; 3 strips: 0.0085)
    must be 2× closer and within 1.5e-2; strips of terms ≤ 0.03 converge to the casts' own
    quadrature error (1.5e-3 measured): within 3e-3."""
    from mitsuba_pbrt_tex import pixel
    tex = box_texture(rng, size=16, tiles=4.0)
    scene = mi.load_dict(far_edge_scene(tex))
    white = mi.load_dict(far_edge_scene({'type': 'pbrt_constant', 'value': 1.0}))
    shade = np.array(mi.render(white, spp=1, seed=1))
    mask = interior_pixels(scene)
    ys, xs = np.nonzero(mask)
    w, h = RES
    si = cast(scene, np.stack([(xs + 0.5) / w, (ys + 0.5) / h], 1))
    hh = np.abs(A(pixel.pixel_footprint(scene.sensors()[0], si).h))
    pick = hh > 0.15
    assert pick.sum() >= 10, hh.max()
    ys, xs = ys[pick], xs[pick]
    n = 32
    sub = (np.arange(n) + 0.5) / n
    ox, oy = [a.ravel() for a in np.meshgrid(sub, sub)]
    pos = np.stack([((xs[:, None] + ox) / w).ravel(), ((ys[:, None] + oy) / h).ravel()], 1)
    hits = cast(scene, pos)
    assert A(hits.is_valid()).all()
    bilinear = mi.load_dict(dict(tex, filter='bilinear'))
    want = A(bilinear.eval(hits)).reshape(len(xs), n * n, 3).mean(1) * shade[ys, xs]
    errors = {}
    for term, strips in ((pixel.STRIP_PERSPECTIVE, 1), (pixel.STRIP_PERSPECTIVE,
                                                         pixel.MAX_STRIPS), (0.03, 16)):
        monkeypatch.setattr(pixel, 'STRIP_PERSPECTIVE', term)
        monkeypatch.setattr(pixel, 'MAX_STRIPS', strips)
        img = np.array(mi.render(mi.load_dict(far_edge_scene(tex)), spp=1, seed=2))
        errors[term, strips] = float(np.abs(img[ys, xs] - want).max())
    print(f'{len(xs)} pixels, |h| up to {hh.max():.2f}: max errors {errors}')
    one, default, fine = errors.values()
    assert default < 1.5e-2 and default * 2 < one
    assert fine < 3e-3


def test_box_film_samples_stay_in_the_pixel_they_were_drawn_in(rng):
    """A camera sample drawn within float32 rounding of its pixel's edge finds, from its hit
    point, the neighbouring pixel (its texture then filters that pixel's footprint; ~2 pixels
    of a 320×180 frame, off by the neighbour's value): among rays through film positions
    1e-6 pixel inside the pixels' edges, some do — and none after ``inset_camera_rays``, which
    moves them ``EDGE_MARGIN`` inside."""
    from mitsuba_pbrt_tex import pixel
    scene = mi.load_dict(far_edge_scene(box_texture(rng)))
    sensor = scene.sensors()[0]
    w, h = RES
    ys, xs = np.mgrid[0:h, 0:w]
    corner = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)
    u = rng.random((50, corner.shape[0], 2))
    u[..., 0] = np.where(u[..., 0] < 0.5, 1e-6, 1 - 1e-6)       # at the left or right edge
    pos = (corner[None] + u).reshape(-1, 2)
    corners = np.repeat(corner[None], 50, 0).reshape(-1, 2)
    ray, _ = sensor.sample_ray_differential(0.0, 0.5, mi.Point2f((pos / [w, h]).T.astype(np.float32)),
                                            mi.Point2f(0.5), True)
    for moved in (False, True):
        r = pixel.inset_camera_rays(sensor, ray, mi.Vector2f(corners.T)) if moved else ray
        si = scene.ray_intersect(mi.Ray3f(r))
        hit, uv = pixel._film_position(sensor, si)
        wrong = A(hit) & np.any(np.floor(A(uv)) != corners, axis=1)
        print(f'inset {moved}: {wrong.sum()} of {A(hit).sum()} hits decode to another pixel')
        assert (wrong.sum() == 0) == moved


def test_camera_hits_on_a_large_plane_find_their_film_position(rng):
    """The bench's grazing geometry (a rectangle scaled 200, seen from 1 unit above it, 320×180):
    a hit point there carries ~1e-5 units of float32 rounding a few units from the camera, and
    its film position computed from it was off by up to 7e-3 pixel — past the 1e-3-pixel inset,
    so 296 of 744686 inset samples found the neighbouring pixel (a pixel off by its neighbour's
    value in 1-spp renders). From the ray's direction instead: within 5e-4 pixel of the drawn
    position (measured 9.4e-5, including the float32 rounding of the drawn position itself), and
    every inset sample drawn 1e-6 pixel inside its pixel's edge finds its pixel."""
    from mitsuba_pbrt_tex import pixel
    w, h = 320, 180
    d = scene_dict(box_texture(rng), second_bsdf=False)
    d['plane']['to_world'] = T().scale(200).rotate([1, 0, 0], -90)
    d['sensor'].update(fov=60, to_world=T().look_at([0, 1, 6], [0, -0.6, -10], [0, 1, 0]))
    d['sensor']['film'].update(width=w, height=h)
    scene = mi.load_dict(d)
    sensor = scene.sensors()[0]
    ys, xs = np.mgrid[h // 2:h, 0:w]
    corner = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)
    u = rng.random((4, corner.shape[0], 2))
    u[1:3, :, 0] = np.where(u[1:3, :, 0] < 0.5, 1e-6, 1 - 1e-6)      # at a left or right edge
    u[3, :, 1] = np.where(u[3, :, 1] < 0.5, 1e-6, 1 - 1e-6)          # at a top or bottom edge
    pos = (corner[None] + u).reshape(-1, 2)
    corners = np.repeat(corner[None], 4, 0).reshape(-1, 2)
    ray, _ = sensor.sample_ray_differential(
        0.0, 0.5, mi.Point2f((pos / [w, h]).T.astype(np.float32)), mi.Point2f(0.5), True)
    hit, uv = pixel._film_position(sensor, scene.ray_intersect(mi.Ray3f(ray)))
    hit, uv = A(hit), A(uv)
    assert hit.mean() > 0.9
    assert np.abs(uv[hit] - pos[hit]).max() < 5e-4
    inset = pixel.inset_camera_rays(sensor, ray, mi.Vector2f(corners.T.astype(np.float32)))
    hit, uv = pixel._film_position(sensor, scene.ray_intersect(mi.Ray3f(inset)))
    hit, uv = A(hit), A(uv)
    assert not np.any(np.floor(uv[hit]) != corners[hit])


@pytest.mark.parametrize('forward', [False, True])
def test_texel_gradients_through_pixel_strips(forward, rng):
    """Texel gradients where pixels are looked up as strips (next to a far edge: the strips'
    symbolic loop, a sum, in Dr.Jit's reverse and forward modes) against central finite
    differences at the gradient seed (the project's check_gradient, 2%); the scene must have
    pixels with more than one strip for the test to mean anything."""
    import test_gradients as tg
    from mitsuba_pbrt_tex import pixel
    d = far_edge_scene(box_texture(rng, size=16, tiles=4.0))
    d['sensor']['film'].update(width=tg.RES, height=tg.RES)
    scene = mi.load_dict(d)
    ys, xs = np.mgrid[0:tg.RES, 0:tg.RES]
    si = cast(scene, np.stack([(xs.ravel() + 0.5) / tg.RES, (ys.ravel() + 0.5) / tg.RES], 1))
    fp = pixel.pixel_footprint(scene.sensors()[0], si)
    assert (A(fp.ok) & (np.abs(A(fp.h)) > pixel.STRIP_PERSPECTIVE)).sum() >= 5
    tg.check_gradient(scene, 'plane.bsdf.reflectance.data', rng, forward=forward)


@pytest.mark.parametrize('rfilter', ['box', 'gaussian'])
def test_bump_map_of_a_box_texture_under_pixel_footprints(rfilter):
    """A bump map of a ``box`` texture under ``footprint="pixel"``: its gradient is pbrt's
    difference of sample-centred lookups, as under ``footprint="sample"`` — at camera hits the
    difference took the pixel's average at the hit and a sample-centred value at the hit moved
    by half a footprint (no longer a camera hit), an error as large as the bump's whole effect
    (found by a review). Reference: the same render with ``trilinear`` (exact gradient), whose
    bump shading a smooth height field shares to within the noise; the bug put the box render
    |box - trilinear| ≈ |trilinear - no bump|, here it must stay below a quarter of that."""
    n = 64
    y, x = np.mgrid[0:n, 0:n] / n
    height = (0.5 + 0.5 * np.sin(2 * np.pi * 3 * x) * np.cos(2 * np.pi * 2 * y)).astype(
        np.float32)

    def render(filt, bump=True):
        tex = {'type': 'pbrt_imagemap', 'data': mi.TensorXf(height[..., None]), 'filter': filt}
        bsdf = {'type': 'bumpmap', 'arbitrary': tex, 'scale': 0.3,
                'bsdf': {'type': 'diffuse'}} if bump else {'type': 'diffuse'}
        scene = mi.load_dict({
            'type': 'scene', 'integrator': {'type': 'pbrt_path', 'footprint': 'pixel'},
            'sensor': {'type': 'perspective', 'fov': 40, 'to_world': mi.ScalarTransform4f()
                       .look_at([0, -2.5, 2.5], [0, 0, 0], [0, 0, 1]),
                       'film': {'type': 'hdrfilm', 'width': 32, 'height': 32,
                                'rfilter': {'type': rfilter}}},
            'obj': {'type': 'rectangle', 'bsdf': bsdf},
            'sun': {'type': 'directional', 'direction': [0.3, 0.2, -1], 'irradiance': 2.0}})
        return np.array(mi.render(scene, spp=16, seed=1))

    tri = render('trilinear')
    effect = np.abs(tri - render('trilinear', bump=False)).mean()
    assert effect > 0.02
    assert np.abs(render('box') - tri).mean() < 0.25 * effect
