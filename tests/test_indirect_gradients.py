"""Gradients through indirect light, against central finite differences.

``test_gradients.py`` lights one plane with a directional sun only, so the path-replay term
that carries a BSDF's gradient to light arriving from *later* vertices (``Lr_ind`` in
``pbrt_path``, as in Mitsuba's ``prb``) is never checked there. Here:

* ``env``: a textured floor lit only by a constant environment — half of its light (by MIS)
  arrives by BSDF sampling, whose gradient flows through the replay term;
* ``wall``: the camera sees a textured floor and a white diffuse wall; a nearly horizontal sun
  (from slightly below the floor's plane) lights the wall only, so the floor is lit only by
  light the wall returns: every derivative of the floor's texture goes through a second
  surface (floor pixels: floor → wall → sun; wall pixels: wall → floor → wall → sun).

Method as ``test_gradients.py``: common random numbers (finite differences render with the
gradient pass's seed ``seed_grad``), a loss Σ w·image with fixed random weights, directional
derivative along a random direction; here in the user's call order (load → traverse →
``dr.enable_grad`` → ``params.update()`` → first render is the gradient render; finite
differences after). The loss is linear in these parameters, so the differences are exact up to
float32 rounding, and the AD and FD estimators share their samples: rtol 2% (the bound of the
gradient tests; measured errors are below 0.01%), while dropping the replay term changes the
derivative by more than 80% here. Mitsuba's ``prb`` runs the same checks (it validates the
scenes and the method).
"""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

T = mi.ScalarTransform4f
RES = 16
SPP = 16
SEED, GRAD_SEED = 7, 8


def scene_of(kind, texture, integrator):
    camera = {'type': 'perspective', 'fov': 55,
              'film': {'type': 'hdrfilm', 'width': RES, 'height': RES, 'rfilter': {'type': 'box'}},
              'sampler': {'type': 'independent'}}
    floor = {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(2),
             'bsdf': {'type': 'diffuse', 'reflectance': texture}}
    if kind == 'env':
        return mi.load_dict({
            'type': 'scene', 'integrator': {'type': integrator, 'max_depth': 3},
            'sensor': {**camera, 'to_world': T().look_at([0, 1.5, 2.5], [0, 0, 0], [0, 1, 0])},
            'env': {'type': 'constant', 'radiance': {'type': 'rgb', 'value': [0.8, 0.9, 1.0]}},
            'floor': floor})
    # the wall at z = -1 faces +z; the sun comes from +z, 3° below the floor's plane: it lights
    # the wall's front, and the floor (one-sided, facing +y) gets none of it directly
    return mi.load_dict({
        'type': 'scene', 'integrator': {'type': integrator, 'max_depth': 4},
        'sensor': {**camera, 'to_world': T().look_at([0, 1.0, 3.0], [0, 0.6, -1], [0, 1, 0])},
        'sun': {'type': 'directional', 'direction': [0.2, 0.05, -1], 'irradiance': 4.0},
        'floor': floor,
        'wall': {'type': 'rectangle', 'to_world': T().translate([0, 1, -1]).scale([2, 1, 1]),
                 'bsdf': {'type': 'diffuse', 'reflectance': 0.9}}})


def image_tex(rng, filt):
    return {'type': 'pbrt_imagemap', 'filter': filt, 'uscale': 2.0, 'vscale': 2.0,
            'data': mi.TensorXf(rng.random((16, 16, 3)).astype(np.float32))}


def check_indirect_gradient(scene, key, rng, mask=None):
    """AD (first render, user call order) vs central FD with the gradient seed; returns both."""
    params = mi.traverse(scene)
    value = params[key]
    base = np.array(value, dtype=np.float64)
    direction = rng.normal(size=base.shape)
    weights = rng.random((RES, RES, 3))
    if mask is not None:
        weights = weights * mask[..., None]
    w = mi.TensorXf(weights.astype(np.float32))
    Tv = type(value)

    dr.enable_grad(params[key])
    params.update()
    img = mi.render(scene, params, spp=SPP, seed=SEED, seed_grad=GRAD_SEED)
    dr.backward(dr.sum(img * w, axis=None))
    ad = float((np.array(dr.grad(params[key]), dtype=np.float64) * direction).sum())

    def loss_at(arr):
        params[key] = Tv(arr.astype(np.float32))
        params.update()
        out = np.array(mi.render(scene, params, spp=SPP, seed=GRAD_SEED), dtype=np.float64)
        return float((out * weights).sum())

    h = 0.5 * max(1.0, float(np.abs(base).max()))       # exact: the loss is linear
    fd = (loss_at(base + h * direction) - loss_at(base - h * direction)) / (2 * h)
    assert abs(fd) > 1e-4, 'the loss does not depend on the parameter'
    return ad, fd


def wall_pixels():
    """Pixels that see the wall (upper part of the frame), found by tracing the camera rays."""
    scene = scene_of('wall', 0.5, 'path')
    sensor = scene.sensors()[0]
    px = (np.stack(np.meshgrid(np.arange(RES), np.arange(RES)), -1).reshape(-1, 2) + 0.5) / RES
    ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(px[:, 0], px[:, 1]), mi.Point2f(0.5, 0.5))
    si = scene.ray_intersect(ray)
    return (np.array(si.p.z) < -0.99).reshape(RES, RES) & np.array(si.is_valid()).reshape(RES, RES)


CASES = [('env', 'trilinear'), ('env', 'ewa'), ('wall', 'trilinear'), ('wall', 'ewa'),
         ('env', 'bilinear'), ('wall', 'bilinear')]


@pytest.mark.parametrize('integrator,kind,filt',
                         [(i, k, f) for i in ('pbrt_path', 'prb') for k, f in CASES])
def test_texel_gradient_through_indirect_light(integrator, kind, filt, rng):
    scene = scene_of(kind, image_tex(rng, filt), integrator)
    ad, fd = check_indirect_gradient(scene, 'floor.bsdf.reflectance.data', rng)
    print(f'{integrator} {kind} ad/fd = {ad / fd:.5f}')
    assert ad == pytest.approx(fd, rel=0.02), (ad, fd)


@pytest.mark.parametrize('integrator', ['pbrt_path', 'prb'])
def test_gradient_reaches_wall_pixels_only_through_the_floor(integrator, rng):
    """Only the wall's pixels in the loss: the floor's value changes them only through light
    the floor returns to the wall (wall → floor → wall → sun), a depth-1 replay term."""
    mask = wall_pixels()
    assert 20 < mask.sum() < RES * RES - 20
    scene = scene_of('wall', {'type': 'pbrt_constant', 'value': {'type': 'rgb',
                                                                 'value': [0.4, 0.5, 0.6]}},
                     integrator)
    ad, fd = check_indirect_gradient(scene, 'floor.bsdf.reflectance.value', rng, mask=mask)
    print(f'{integrator} wall pixels ad/fd = {ad / fd:.5f}')
    assert ad == pytest.approx(fd, rel=0.02), (ad, fd)
