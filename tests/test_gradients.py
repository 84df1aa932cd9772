"""Gradients of rendered images with respect to every differentiable texture parameter, through
every filter, under pbrt_path and Mitsuba's prb, against central finite differences.

Method: common random numbers. The AD pass of ``mi.render`` runs with its own seed
``seed_grad`` (Mitsuba requires it to differ from the primal seed); the finite differences render
with ``seed = seed_grad``, so both differentiate the *same* Monte Carlo estimator. The loss is
``Σ w·image`` with fixed random pixel weights w, or the squared error to a target image. All
parameters exposed here enter the image linearly or smoothly (texel values, scales, mixing
amounts, constant values): no discontinuity. Tolerance: relative error ≤ 2% on the directional
derivative along a random direction (the issue's bound for smooth losses); the measured errors
are below 0.1% for the linear loss, since the estimator is then linear in the parameter.
"""

import resource

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

T = mi.ScalarTransform4f
RES = 16
SPP = 8
GRAD_SEED = 8


def scene_with(texture, integrator='pbrt_path', view='grazing'):
    origin, target = ([0, 0.6, 3], [0, 0, -2]) if view == 'grazing' else ([0, 3, 0.01], [0, 0, 0])
    return mi.load_dict({
        'type': 'scene',
        'integrator': {'type': integrator, 'max_depth': 3},
        'sensor': {'type': 'perspective', 'fov': 50,
                   'to_world': T().look_at(origin, target, [0, 1, 0]),
                   'film': {'type': 'hdrfilm', 'width': RES, 'height': RES,
                            'rfilter': {'type': 'box'}},
                   'sampler': {'type': 'independent'}},
        'sun': {'type': 'directional', 'direction': [0.2, -1, -0.3], 'irradiance': 3.0},
        'plane': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(4),
                  'bsdf': {'type': 'diffuse', 'reflectance': texture}}})


def loss_of(image, weights):
    return dr.sum(image * weights, axis=None)


def check_gradient(scene, key, rng, forward=False, rtol=0.02, h=None):
    """Directional derivative along a random direction: AD (backward or forward) vs central FD."""
    params = mi.traverse(scene)
    value = params[key]
    base = np.array(value, dtype=np.float64)
    direction = rng.normal(size=base.shape)
    weights = mi.TensorXf(rng.random((RES, RES, 3)).astype(np.float32))
    T_ = type(value)

    def set_value(arr):
        params[key] = T_(arr.astype(np.float32)) if not isinstance(value, mi.TensorXf) \
            else mi.TensorXf(arr.astype(np.float32))
        params.update()

    def loss_at(arr):
        set_value(arr)
        return float(np.array(loss_of(mi.render(scene, params, spp=SPP, seed=GRAD_SEED),
                                      weights)).ravel()[0])

    # the loss is linear in these parameters, so a large step is exact and keeps float32
    # rounding of the loss (~1e-7 of its value) far below the difference
    h = h or 0.5 * max(1.0, float(np.abs(base).max()))
    fd = (loss_at(base + h * direction) - loss_at(base - h * direction)) / (2 * h)

    set_value(base)
    v = params[key]
    dr.enable_grad(v)
    if forward:
        # Mitsuba's forward-mode recipe: propagate the input derivative through everything
        # computed from the parameter outside the render (here the MIP pyramid) first.
        params.update()
        dr.set_grad(v, T_(direction.astype(np.float32)) if not isinstance(value, mi.TensorXf)
                    else mi.TensorXf(direction.astype(np.float32)))
        dr.enqueue(dr.ADMode.Forward, v)
        dr.traverse(dr.ADMode.Forward, dr.ADFlag.ClearEdges)
        img = mi.render(scene, params, spp=SPP, seed=7, seed_grad=GRAD_SEED)
        loss = loss_of(img, weights)
        dr.forward_to(loss)
        ad = float(np.array(dr.grad(loss)).ravel()[0])
    else:
        params.update()
        img = mi.render(scene, params, spp=SPP, seed=7, seed_grad=GRAD_SEED)
        dr.backward(loss_of(img, weights))
        g = np.array(dr.grad(params[key]), dtype=np.float64)
        ad = float((g * direction).sum())
    assert abs(fd) > 1e-6, 'the loss does not depend on the parameter'
    assert ad == pytest.approx(fd, rel=rtol), (key, ad, fd)
    return ad, fd


def image_tex(rng, filt, size=32, **kw):
    return {'type': 'pbrt_imagemap', 'data': mi.TensorXf(rng.random((size, size, 3)).astype(np.float32)),
            'filter': filt, 'uscale': 3.0, 'vscale': 3.0, **kw}


# ------------------------------------------------------------------------------------ image data
@pytest.mark.parametrize('integrator', ['pbrt_path', 'prb'])
@pytest.mark.parametrize('filt', ['point', 'bilinear', 'trilinear', 'ewa'])
def test_image_data_gradient_every_filter(filt, integrator, rng):
    scene = scene_with(image_tex(rng, filt), integrator)
    check_gradient(scene, 'plane.bsdf.reflectance.data', rng)


def test_image_scale_gradient_backward_and_forward(rng):
    scene = scene_with(image_tex(rng, 'ewa', scale=0.7))
    check_gradient(scene, 'plane.bsdf.reflectance.scale', rng)
    check_gradient(scene, 'plane.bsdf.reflectance.scale', rng, forward=True)


@pytest.mark.parametrize('integrator', ['pbrt_path', 'prb'])
@pytest.mark.parametrize('filt', ['trilinear', 'ewa', 'box'])
def test_forward_mode_on_texels(filt, integrator, rng):
    """Forward mode through every filter's loops: EWA's two level sums read aliases of the
    pyramid's buffer of their own (under pbrt_path, reading the buffer itself, Dr.Jit refused
    to propagate across an edge outside the loop's scope)."""
    scene = scene_with(image_tex(rng, filt), integrator)
    check_gradient(scene, 'plane.bsdf.reflectance.data', rng, forward=True)


def test_gradient_reaches_base_texels_through_coarse_levels_only(rng):
    """The plane far away (footprint ≫ 1 texel): every lookup is at level ≥ 1, so the texels get
    gradients only through the pyramid, which parameters_changed rebuilt in the AD graph."""
    tex = image_tex(rng, 'trilinear', size=64)
    tex['uscale'] = tex['vscale'] = 40.0                      # 40 repeats: ~10 texels per pixel
    scene = scene_with(tex, view='top')
    params = mi.traverse(scene)
    aovs = mi.load_dict({'type': 'pbrt_path', 'aovs': 'duv_dx,duv_dy'})
    part = np.array(mi.render(scene, integrator=aovs, spp=4))[..., 3:]
    footprint_texels = np.abs(part).max(-1) * 40 * 64          # uv partials × uscale × size
    hit = footprint_texels > 0
    assert hit.mean() > 0.9 and footprint_texels[hit].min() > 2.0   # level ≥ 1 everywhere
    check_gradient(scene, 'plane.bsdf.reflectance.data', rng)
    del params


# ------------------------------------------------------------------------------------ other params
@pytest.mark.parametrize('plugin, key, value', [('pbrt_mix', 'amount', 0.0),
                                                 ('pbrt_mix', 'amount', 1.0),
                                                 ('pbrt_scale', 'scale', 0.0)])
@pytest.mark.parametrize('forward', [False, True])
def test_gradient_where_pbrt_skips_a_texture(plugin, key, value, forward):
    """pbrt-v4 skips tex2 where a mix's amount is 0 (tex1 at 1) and tex where a scale is 0; the
    derivative there is tex2 - tex1 (tex) all the same — it was 0, so an optimiser started at
    an amount of 0 never moved (found in a user trial). Reference: central differences (the
    value is linear in the parameter: exact up to float32 rounding)."""
    textures = {'pbrt_mix': {'tex1': 0.2, 'tex2': 0.9}, 'pbrt_scale': {'tex': 0.6}}[plugin]
    tex = mi.load_dict({'type': plugin, key: value, **textures})
    params = mi.traverse(tex)
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.uv = mi.Point2f(0.3, 0.3)

    def at(v):
        params[f'{key}.value'] = v
        params.update()
        return float(tex.eval_1(si)[0])
    fd = (at(value + 0.25) - at(value - 0.25)) / 0.5
    param = mi.Float(value)
    dr.enable_grad(param)
    params[f'{key}.value'] = param
    params.update()
    out = tex.eval_1(si)
    if forward:
        dr.forward(params[f'{key}.value'])
        ad = float(dr.grad(out)[0])
    else:
        dr.backward(out)
        ad = float(dr.grad(params[f'{key}.value'])[0])
    assert abs(fd) > 0.5 and ad == pytest.approx(fd, rel=1e-5)


@pytest.mark.parametrize('case', ['checker_tex1', 'checker_tex2', 'mix_amount', 'constant_value',
                                  'nested_bitmap_in_scale', 'bilerp_corner'])
def test_other_differentiable_parameters(case, rng):
    rgb = lambda *c: {'type': 'rgb', 'value': list(c)}
    tex, key = {
        'checker_tex1': ({'type': 'pbrt_checkerboard', 'tex1': rgb(0.7, 0.6, 0.5), 'tex2': 0.2,
                          'uscale': 6.0, 'vscale': 6.0}, 'plane.bsdf.reflectance.tex1.value'),
        'checker_tex2': ({'type': 'pbrt_checkerboard', 'tex1': 0.9, 'tex2': 0.2, 'aamode': 'box',
                          'uscale': 6.0, 'vscale': 6.0}, 'plane.bsdf.reflectance.tex2.value'),
        'mix_amount': ({'type': 'pbrt_mix', 'tex1': rgb(0.9, 0.1, 0.1), 'tex2': rgb(0.1, 0.1, 0.9),
                        'amount': 0.3}, 'plane.bsdf.reflectance.amount.value'),
        'constant_value': ({'type': 'pbrt_constant', 'value': rgb(0.3, 0.5, 0.7)},
                           'plane.bsdf.reflectance.value'),
        'nested_bitmap_in_scale': ({'type': 'pbrt_scale', 'scale': 0.8, 'tex': {
            'type': 'bitmap', 'data': mi.TensorXf(rng.random((8, 8, 3)).astype(np.float32)),
            'raw': True}}, 'plane.bsdf.reflectance.tex.data'),
        'bilerp_corner': ({'type': 'pbrt_bilerp', 'v00': 0.1, 'v01': 0.9, 'v10': 0.5, 'v11': 0.3},
                          'plane.bsdf.reflectance.v01.value'),
    }[case]
    scene = scene_with(tex)
    check_gradient(scene, key, rng)


@pytest.mark.parametrize('integrator', ['pbrt_path', 'prb'])
@pytest.mark.parametrize('forward', [False, True])
def test_supersampled_texels_gradient(forward, integrator, rng):
    """Texels through pbrt_supersample's loop of nested lookups (a sum: Dr.Jit's reverse mode
    without stored iterations). Found in a user trial: with the loop's state recorded per
    iteration (max_iterations = samples), the backward render under pbrt_path aborted the
    process inside Dr.Jit's LLVM compiler ('use of undefined value %arr_1')."""
    tex = {'type': 'pbrt_supersample', 'samples': 4, 'texture': image_tex(rng, 'bilinear')}
    check_gradient(scene_with(tex, integrator), 'plane.bsdf.reflectance.texture.data', rng,
                   forward=forward)


def test_squared_error_loss_gradient(rng):
    """A nonlinear (quadratic) loss. Its gradient is 2(I₇ - target)·∂I/∂θ with I₇ the primal
    image (seed 7) and ∂I/∂θ from the gradient pass (seed 8): the reference is that product with
    ∂I/∂θ·δ from central differences of seed-8 renders. Same 2% bound."""
    scene = scene_with(image_tex(rng, 'ewa'))
    params = mi.traverse(scene)
    key = 'plane.bsdf.reflectance.data'
    target = mi.render(scene, spp=SPP, seed=3) * 0.5
    base = np.array(params[key], dtype=np.float64)
    direction = rng.normal(size=base.shape)

    def set_value(arr, grad=False):
        t = mi.TensorXf(arr.astype(np.float32))
        if grad:
            dr.enable_grad(t)
        params[key] = t
        params.update()

    h = 1e-2
    set_value(base + h * direction)
    up = np.array(mi.render(scene, params, spp=SPP, seed=GRAD_SEED), dtype=np.float64)
    set_value(base - h * direction)
    down = np.array(mi.render(scene, params, spp=SPP, seed=GRAD_SEED), dtype=np.float64)
    set_value(base)
    primal = np.array(mi.render(scene, params, spp=SPP, seed=7), dtype=np.float64)
    fd = float((2 * (primal - np.array(target)) * (up - down) / (2 * h)).sum())
    set_value(base, grad=True)
    img = mi.render(scene, params, spp=SPP, seed=7, seed_grad=GRAD_SEED)
    dr.backward(dr.sum(dr.square(img - target), axis=None))
    ad = float((np.array(dr.grad(params[key]), dtype=np.float64) * direction).sum())
    assert abs(fd) > 1e-6
    assert ad == pytest.approx(fd, rel=0.02)


def test_backward_through_ewa_memory_stays_bounded(rng):
    """Reverse mode through the EWA loop (max_iterations=-1 hint) at 256×256, 2 spp: the peak
    resident memory of the process grows by less than 2 GiB."""
    tex = image_tex(rng, 'ewa', size=256)
    scene = mi.load_dict({**_dict_scene(tex, 256)})
    params = mi.traverse(scene)
    key = 'plane.bsdf.reflectance.data'
    dr.enable_grad(params[key])
    params.update()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    img = mi.render(scene, params, spp=2, seed=1)
    dr.backward(dr.mean(img, axis=None))
    g = np.array(dr.grad(params[key]))
    after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    assert np.isfinite(g).all() and np.abs(g).sum() > 0
    assert (after - before) / 2 ** 20 < 2.0          # ru_maxrss is in KiB on Linux


def _dict_scene(texture, res):
    return {'type': 'scene', 'integrator': {'type': 'pbrt_path', 'max_depth': 2},
            'sensor': {'type': 'perspective', 'fov': 60,
                       'to_world': T().look_at([0, 0.5, 3], [0, 0, -4], [0, 1, 0]),
                       'film': {'type': 'hdrfilm', 'width': res, 'height': res,
                                'rfilter': {'type': 'box'}}},
            'sun': {'type': 'directional', 'direction': [0.2, -1, -0.3], 'irradiance': 3.0},
            'plane': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(20),
                      'bsdf': {'type': 'diffuse', 'reflectance': texture}}}


def test_gradients_enabled_without_parameter_update_is_an_error_in_a_kernel(rng):
    """Enabling gradients on `data` without params.update(): the lookups read the pyramid, a
    copy built before, and inside a render's kernel it cannot be rebuilt — so the texture raises
    an error naming the fix instead of returning gradients that miss every texel it filtered
    (Mitsuba's ``bitmap`` returns none at all there). Outside a kernel it rebuilds the pyramid
    (tests/test_imagemap.py::test_gradients_enabled_after_pyramid_reach_level0)."""
    scene = scene_with(image_tex(rng, 'bilinear'), 'prb')
    params = mi.traverse(scene)
    dr.enable_grad(params['plane.bsdf.reflectance.data'])             # no params.update()
    with pytest.raises(Exception) as info:
        img = mi.render(scene, params, spp=SPP, seed=7, seed_grad=GRAD_SEED)
        dr.backward(dr.sum(img, axis=None))
    chain, e = [], info.value
    while e is not None:
        chain.append(str(e))
        e = e.__cause__ or e.__context__
    assert any('pbrt_imagemap: parameter "data"' in m and 'params.update()' in m for m in chain)


@pytest.mark.parametrize('integrator', ['pbrt_path', 'prb'])
def test_two_scenes_from_one_data_tensor_differentiate_independently(integrator, rng):
    """A reference scene and an optimisation scene loaded from one dict (the same TensorXf as
    `data`): gradients enabled on the second's texels (and params.update()) stay the second's —
    found in a user trial, the first scene's texture held the same tensor object, was traced in
    the backward render (Dr.Jit traces every BSDF instance of a symbolic call) and raised the
    stale-pyramid error although params.update() had been called. The gradient equals the one
    of the second scene loaded alone (same seeds and numbers: rtol 1e-6), and the caller's
    tensor gets no gradient."""
    data = mi.TensorXf(rng.random((8, 8, 3)).astype(np.float32))

    def grad(scenes):
        scene = scenes[-1]
        params = mi.traverse(scene)
        dr.enable_grad(params['plane.bsdf.reflectance.data'])
        params.update()
        img = mi.render(scene, params, spp=2, seed=1, seed_grad=2)
        dr.backward(dr.sum(img, axis=None))
        return np.array(dr.grad(params['plane.bsdf.reflectance.data']))

    tex = {'type': 'pbrt_imagemap', 'filter': 'bilinear', 'data': data}
    both = grad([scene_with(tex, integrator), scene_with(tex, integrator)])
    alone = grad([scene_with({**tex, 'data': mi.TensorXf(np.array(data))}, integrator)])
    assert not dr.grad_enabled(data)
    np.testing.assert_allclose(both, alone, rtol=1e-6, atol=1e-9)
    assert np.abs(alone).sum() > 0
