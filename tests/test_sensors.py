"""pbrt_path under every sensor Mitsuba's path renders: the light transport of Mitsuba's ``prb``
(the same random numbers) with a texture that reads differentials but whose value does not
depend on them; camera-hit partials against finite differences of the sensor's own rays where
the sensor defines differentials; a zero footprint, without an error, where it does not."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from test_pbrt_path import _probe  # noqa: F401  (the fixture that registers test_probe)

T = mi.ScalarTransform4f
BOX1 = {'type': 'hdrfilm', 'width': 1, 'height': 1, 'rfilter': {'type': 'box'}}


def _film(w=12, h=8):
    return {'type': 'hdrfilm', 'width': w, 'height': h, 'rfilter': {'type': 'box'}}


def _look(origin=(0.3, 0.8, 3.0)):
    return T().look_at(origin=list(origin), target=[0, 0, 0], up=[0, 1, 0])


def sensors():
    """Each kind of sensor Mitsuba 3.9 has, looking at the unit square z = 0 from +z; the meters
    see it too (the irradiance meter on a disk above it, facing down)."""
    return {
        'perspective': {'type': 'perspective', 'fov': 50, 'to_world': _look(), 'film': _film()},
        'thinlens': {'type': 'thinlens', 'fov': 50, 'aperture_radius': 0.05,
                     'focus_distance': 3.0, 'to_world': _look(), 'film': _film()},
        'orthographic': {'type': 'orthographic', 'to_world': _look() @ T().scale([1.5, 1.5, 1]),
                         'film': _film()},
        'radiancemeter': {'type': 'radiancemeter', 'origin': [0, 0.4, 2],
                          'direction': [0, -0.2, -1], 'film': BOX1},
        'distant': {'type': 'distant', 'direction': [0.1, 0.2, -1], 'film': BOX1,
                    'target': {'type': 'rectangle', 'to_world': T().scale(0.5)}},
        'batch': {'type': 'batch', 'film': _film(24, 8),
                  'a': {'type': 'perspective', 'fov': 50, 'to_world': _look()},
                  'b': {'type': 'orthographic', 'to_world': _look((-1, 0.5, 3))}},
        'irradiancemeter': None,
    }


def _with_sensor(d, kind):
    """The scene ``d`` loaded with a sensor of ``kind`` (the irradiance meter on a disk above
    the plane, facing down)."""
    if kind == 'irradiancemeter':
        d['meter'] = {'type': 'disk', 'to_world': T().translate([0, 0, 1]).rotate([1, 0, 0], 180)
                      .scale(0.2), 'sensor': {'type': 'irradiancemeter', 'film': BOX1}}
    else:
        d['sensor'] = sensors()[kind]
    return mi.load_dict(d)


def _scene(kind, integrator, texture):
    plane = {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -20),
             'bsdf': {'type': 'diffuse', 'reflectance': texture}}
    d = {'type': 'scene', 'integrator': integrator, 'plane': plane,
         'sky': {'type': 'constant', 'radiance': {'type': 'rgb', 'value': [0.6, 0.7, 0.9]}},
         'wall': {'type': 'rectangle', 'to_world': T().translate([0, 1, 0.5]).rotate([1, 0, 0], 90),
                  'bsdf': {'type': 'diffuse', 'reflectance': texture}}}
    return _with_sensor(d, kind)


KINDS = list(sensors())
DEFINED = ('perspective', 'thinlens', 'orthographic', 'batch')    # sensors with differentials


@pytest.mark.parametrize('kind', KINDS)
def test_renders_as_prb_under_every_sensor(kind):
    """A checkerboard whose two cells are equal reads differentials (its ``closedform``
    antialiasing filters the footprint) but has one value, so pbrt_path — computing every
    footprint — must render as Mitsuba's ``prb`` with the same seed, to float32 rounding
    (pbrt_path is prb's transport with the same random numbers; a footprint changes no sample).
    Before, orthographic and irradiance-meter renders raised inside ``mi.render``."""
    checker = {'type': 'pbrt_checkerboard', 'tex1': 0.6, 'tex2': 0.6, 'uscale': 8, 'vscale': 8}
    images = [np.array(mi.render(_scene(kind, {'type': t, 'max_depth': 4}, checker),
                                 spp=64, seed=5)) for t in ('prb', 'pbrt_path')]
    assert np.all(np.isfinite(images[1])) and images[0].max() > 0.05
    np.testing.assert_allclose(images[1], images[0], rtol=1e-5, atol=1e-6)


def _emitting_plane(kind, radiance):
    """The plane, scaled to fill every view, emitting ``radiance``: each camera hit shows it."""
    d = {'type': 'scene', 'integrator': {'type': 'pbrt_path', 'max_depth': 1},
         'plane': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -20).scale(3),
                   'emitter': {'type': 'area', 'radiance': radiance}}}
    return _with_sensor(d, kind)


@pytest.mark.parametrize('kind', KINDS)
def test_camera_hits_have_a_footprint_exactly_where_the_sensor_defines_differentials(kind):
    """The plane emits a probe that is 1 where its partials are finite and non-zero, 0
    elsewhere, and fills every view: sensors with ray differentials see 1 in every pixel; the
    meters and ``distant`` define none, and their hits see exactly zero partials — no NaN,
    no error (the same plane emitting 1 shows that their rays do reach it)."""
    seen = np.array(mi.render(_emitting_plane(kind, {'type': 'test_probe', 'mode': 'nonzero'}),
                              spp=16))
    lit = np.array(mi.render(_emitting_plane(kind, {'type': 'rgb', 'value': 1.0}), spp=16))
    assert lit.min() > 0.1
    if kind in DEFINED:
        np.testing.assert_array_equal(seen, 1.0)
    else:
        np.testing.assert_array_equal(seen, 0.0)


def _uv(scene, sensor, pos):
    """uv of the first hit of the sensor's own rays through film positions ``pos`` (n×2, in
    [0, 1]²)."""
    ray, _ = sensor.sample_ray(mi.Float(0), mi.Float(0.5), mi.Point2f(pos[:, 0], pos[:, 1]),
                               mi.Point2f(0.5))
    si = scene.ray_intersect(ray)
    assert np.all(np.array(si.is_valid()))
    return np.array(si.uv).T


@pytest.mark.parametrize('kind', ['orthographic', 'batch'])
def test_camera_hit_partials_match_finite_differences_of_the_sensors_rays(kind):
    """Orthographic rays are parallel, so on a plane uv is affine in the film position and a
    one-pixel difference of the hits of the sensor's own rays is the exact partial: the AOVs
    (``spp_scale="none"``: one pixel) must equal it to float32 rounding in every pixel (rtol
    1e-4 of the largest partial; the uv differences are ~0.03, rounded at ~1e-7). ``batch``: two
    orthographic sub-sensors side by side, each with its own view and half the film, each half
    against its own sensor's rays."""
    views = [_look(), _look((-1, 0.5, 3))]
    ortho = [{'type': 'orthographic', 'to_world': v @ T().scale([1.5, 1.5, 1]),
              'film': _film()} for v in views]
    sensor = ortho[0] if kind == 'orthographic' else \
        {'type': 'batch', 'film': _film(24, 8), 'a': {**ortho[0], 'film': _film()},
         'b': {**ortho[1], 'film': _film()}}
    plane = {'type': 'rectangle', 'to_world': T().rotate([1, 0.3, 0], -35).scale(4),
             'bsdf': {'type': 'diffuse', 'reflectance': {'type': 'pbrt_checkerboard'}}}
    scene = mi.load_dict({'type': 'scene', 'plane': plane, 'sensor': sensor, 'integrator': {
        'type': 'pbrt_path', 'aovs': 'duv_dx,duv_dy', 'spp_scale': 'none'}})
    img = np.array(mi.render(scene, spp=4))[..., -4:]
    halves = [img] if kind == 'orthographic' else [img[:, :12], img[:, 12:]]
    for half, d in zip(halves, ortho):
        own = mi.load_dict({'type': 'scene', 'plane': plane, 'sensor': d})
        c = np.array([[0.5, 0.5]])
        u0 = _uv(own, own.sensors()[0], c)
        want = np.concatenate([_uv(own, own.sensors()[0], c + [[1 / 12, 0]]) - u0,
                               _uv(own, own.sensors()[0], c + [[0, 1 / 8]]) - u0], axis=1)[0]
        assert np.abs(want).max() > 0.02
        np.testing.assert_allclose(half.reshape(-1, 4), np.broadcast_to(want, (96, 4)),
                                   rtol=0, atol=1e-4 * np.abs(want).max())


@pytest.mark.parametrize('kind', KINDS)
def test_camera_approximation_after_bounces(kind):
    """pbrt-v4's camera approximation (the footprint after a non-specular bounce) for each
    sensor: for an orthographic camera on its axis it is exact — the one-pixel offsets of its
    parallel rays placed on the tangent plane at the point, i.e. finite differences of the hits
    of the sensor's own rays on that plane (to 1e-4 of the largest offset); for perspective
    cameras non-zero and finite; zero for sensors that define no differentials, and for ``batch`` (no common camera frame)."""
    from mitsuba_pbrt_tex.raydiff import CameraFootprint
    scene = _emitting_plane(kind, {'type': 'rgb', 'value': 1.0})   # a sensor inside its scene
    sensor = scene.sensors()[0]
    camera = CameraFootprint(sensor)
    # points on the camera's axis (the ray through the film's centre), where pbrt's rotation of
    # the offsets towards the point is the identity (off the axis it is pbrt's approximation)
    ray, _ = sensor.sample_ray_differential(0.0, 0.5, mi.Point2f(0.5), mi.Point2f(0.5))
    o, d = np.array(ray.o)[:, 0], np.array(ray.d)[:, 0]
    axis = o[:, None] + d[:, None] * np.array([2.5, 3.5])
    p = mi.Point3f(axis[0], axis[1], axis[2])
    n = mi.Vector3f(dr.normalize(mi.Vector3f([0.1, -0.2], [0.3, 0.1], [1.0, 1.0])))
    dpdx, dpdy = camera.dp_dxy(p, n, 1.0, mi.Bool(True))
    got = np.concatenate([np.array(dpdx).T, np.array(dpdy).T], axis=1)
    assert np.all(np.isfinite(got))
    if kind in ('perspective', 'thinlens'):
        assert np.all(np.linalg.norm(got[:, :3], axis=1) > 1e-4)
        assert np.all(np.linalg.norm(got[:, 3:], axis=1) > 1e-4)
    elif kind != 'orthographic':
        np.testing.assert_array_equal(got, 0.0)
    else:
        want = []
        for pi, ni in zip(np.array(p).T, np.array(n).T):
            def hit(pos):
                ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(*map(float, pos)), mi.Point2f(0.5))
                o, d = np.array(ray.o)[:, 0], np.array(ray.d)[:, 0]
                return o + d * np.dot(pi - o, ni) / np.dot(d, ni)
            c = np.array([0.3, 0.6])
            want.append(np.concatenate([hit(c + [1 / 12, 0]) - hit(c),
                                        hit(c + [0, 1 / 8]) - hit(c)]))
        want = np.array(want)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-4 * np.abs(want).max())


def test_pixel_footprints_are_refused_clearly_without_a_perspective_sensor():
    """(Where a texture reads the footprint: with Mitsuba's textures only the setting changes
    nothing and renders as prb, tests/test_pixel_footprint.py.)"""
    tex = {'type': 'pbrt_imagemap', 'filename': 'scenes/textures/checker.png', 'filter': 'box'}
    scene = _scene('orthographic', {'type': 'pbrt_path', 'footprint': 'pixel'}, tex)
    with pytest.raises(RuntimeError) as e:
        mi.render(scene, spp=1)
    # mi.render raises from inside its dr.custom operation: our error is the cause
    assert 'pbrt_path: parameter "footprint": value "pixel" needs a perspective sensor, got ' \
        'OrthographicCamera; with this sensor use "sample" (accepted values: sample, pixel)' \
        in str(e.value.__cause__)
