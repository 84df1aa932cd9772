"""Gradients in the order a user's optimisation runs them, and frozen optimisation steps.

Every test here starts from a freshly loaded scene and follows Mitsuba's tutorials: load →
traverse → ``dr.enable_grad`` → ``params.update()`` → the *first* render (no warm-up render), so a
texture that builds its MIP pyramid lazily does so inside the gradient render's primal pass. The
references are independent of the code under test: central finite differences rendered with the
gradient pass's seed (``seed_grad``: the same Monte Carlo estimator the gradient pass
differentiates), and Mitsuba's own ``prb`` on the same scene and seeds.
"""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from conftest import assert_frozen_steps_equal_unfrozen

T = mi.ScalarTransform4f
RES = 16
SPP = 16
SEED, SEED_GRAD = 7, 8
DATA_KEY = 'plane.bsdf.reflectance.data'


def textured_scene(integrator, filt, rng, size=32, height=None):
    """A plane at a grazing angle (footprints of several texels: pbrt_path reads coarse levels)
    lit by a sun and by an environment, so part of the light reaches the camera after a bounce
    off a second, diffuse wall (indirect light)."""
    texels = rng.random((height or size, size, 3)).astype(np.float32)
    return mi.load_dict({
        'type': 'scene',
        'integrator': {'type': integrator, 'max_depth': 3},
        'sensor': {'type': 'perspective', 'fov': 50,
                   'to_world': T().look_at([0, 0.6, 3], [0, 0, -2], [0, 1, 0]),
                   'film': {'type': 'hdrfilm', 'width': RES, 'height': RES,
                            'rfilter': {'type': 'box'}}},
        'sun': {'type': 'directional', 'direction': [0.2, -1, -0.3], 'irradiance': 3.0},
        'sky': {'type': 'constant', 'radiance': 0.3},
        'plane': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(4),
                  'bsdf': {'type': 'diffuse', 'reflectance': {
                      'type': 'pbrt_imagemap', 'data': mi.TensorXf(texels), 'filter': filt,
                      'uscale': 3.0, 'vscale': 3.0}}},
        'wall': {'type': 'rectangle', 'to_world': T().translate([0, 1, -3]).scale(4),
                 'bsdf': {'type': 'diffuse', 'reflectance': {'type': 'rgb', 'value': 0.8}}}})


def weighted(image, weights):
    return dr.sum(image * weights, axis=None)


def scalar(x):
    return float(np.array(x).ravel()[0])


def fd_along(scene, key, base, direction, h, loss):
    """Central difference of ``loss(render)`` along ``direction``, renders with the gradient seed."""
    params = mi.traverse(scene)
    values = []
    for sign in (1, -1):
        params[key] = type(params[key])((base + sign * h * direction).astype(np.float32))
        params.update()
        values.append(scalar(loss(mi.render(scene, params, spp=SPP, seed=SEED_GRAD))))
    return (values[0] - values[1]) / (2 * h)


# ------------------------------------------------------------------------------------ texels
@pytest.mark.parametrize('integrator', ['pbrt_path', 'prb'])
@pytest.mark.parametrize('filt', ['point', 'bilinear', 'trilinear', 'ewa'])
def test_texel_gradients_in_the_users_call_order(filt, integrator, rng):
    """d(Σ w·image)/d(data) along a random direction. The image is linear in the texels (diffuse
    reflectance, direct and indirect light), so the central difference is exact up to float32
    rounding of the loss; measured agreement is better than 0.1%, so 1% catches the 10–14% error
    a pyramid built outside the AD graph gave (point/bilinear under pbrt_path)."""
    scene = textured_scene(integrator, filt, rng)
    params = mi.traverse(scene)
    base = np.array(params[DATA_KEY], dtype=np.float64)
    direction = rng.normal(size=base.shape)
    weights = mi.TensorXf(rng.random((RES, RES, 3)).astype(np.float32))
    dr.enable_grad(params[DATA_KEY])
    params.update()
    image = mi.render(scene, params, spp=SPP, seed=SEED, seed_grad=SEED_GRAD)
    dr.backward(weighted(image, weights))
    ad = float((np.array(dr.grad(params[DATA_KEY]), dtype=np.float64) * direction).sum())
    fd = fd_along(scene, DATA_KEY, base, direction, 0.5, lambda img: weighted(img, weights))
    assert abs(fd) > 1e-3
    assert ad == pytest.approx(fd, rel=0.01)


def test_texel_gradient_forward_mode_in_the_users_call_order(rng):
    """Forward mode under pbrt_path with trilinear filtering, Mitsuba's recipe: enable and set
    the input's gradient, params.update(), then propagate it through everything computed from it
    outside the render (the pyramid) before rendering; same reference and bound as above."""
    scene = textured_scene('pbrt_path', 'trilinear', rng)
    params = mi.traverse(scene)
    base = np.array(params[DATA_KEY], dtype=np.float64)
    direction = rng.normal(size=base.shape)
    weights = mi.TensorXf(rng.random((RES, RES, 3)).astype(np.float32))
    data = params[DATA_KEY]
    dr.enable_grad(data)
    dr.set_grad(data, mi.TensorXf(direction.astype(np.float32)))
    params.update()
    dr.enqueue(dr.ADMode.Forward, data)
    dr.traverse(dr.ADMode.Forward, dr.ADFlag.ClearEdges)
    image = mi.render(scene, params, spp=SPP, seed=SEED, seed_grad=SEED_GRAD)
    loss = weighted(image, weights)
    dr.forward_to(loss)
    ad = scalar(dr.grad(loss))
    fd = fd_along(scene, DATA_KEY, base, direction, 0.5, lambda img: weighted(img, weights))
    assert ad == pytest.approx(fd, rel=0.01)


@pytest.mark.parametrize('filt', ['trilinear', 'ewa', 'box'])
def test_texel_gradient_forward_mode_after_the_render(filt, rng):
    """Forward mode in the order of Mitsuba's forward-mode tutorial: enable gradients,
    params.update(), render, then ``dr.forward(params[key])`` (a derivative of 1 on every
    texel). Dr.Jit hands the render the texels' derivative but not the pyramid's: the gradient
    image was zero under pbrt_path (found in a user trial); pbrt_path now carries it into the
    pyramid. Same reference and bound as above (direction: all ones)."""
    scene = textured_scene('pbrt_path', filt, rng)
    params = mi.traverse(scene)
    base = np.array(params[DATA_KEY], dtype=np.float64)
    weights = mi.TensorXf(rng.random((RES, RES, 3)).astype(np.float32))
    dr.enable_grad(params[DATA_KEY])
    params.update()
    image = mi.render(scene, params, spp=SPP, seed=SEED, seed_grad=SEED_GRAD)
    dr.forward(params[DATA_KEY])
    ad = float((np.array(dr.grad(image), dtype=np.float64) * np.array(weights)).sum())
    fd = fd_along(scene, DATA_KEY, base, np.ones_like(base), 0.5,
                  lambda img: weighted(img, weights))
    assert abs(fd) > 1e-3
    assert ad == pytest.approx(fd, rel=0.01)


# ------------------------------------------------------------------------------------ BSDF sampling
def glossy_scene(integrator, alpha):
    """A Beckmann rough conductor whose roughness is one of our textures, seen in the glossy
    reflection of a small spherical area light: alpha changes the sampling densities, so the
    MIS weights depend on it (and must be detached, as in Mitsuba's prb)."""
    return mi.load_dict({
        'type': 'scene', 'integrator': {'type': integrator, 'max_depth': 2},
        'sensor': {'type': 'perspective', 'fov': 40,
                   'to_world': T().look_at([0, -2.5, 2.5], [0, 0, 0], [0, 0, 1]),
                   'film': {'type': 'hdrfilm', 'width': 24, 'height': 24,
                            'rfilter': {'type': 'box'}}},
        'plane': {'type': 'rectangle', 'bsdf': {'type': 'roughconductor',
                                                'distribution': 'beckmann', 'alpha': alpha}},
        'light': {'type': 'sphere', 'center': [0, 1.5, 1.5], 'radius': 0.4,
                  'emitter': {'type': 'area', 'radiance': 30.0}}})


ALPHAS = {       # fresh tensors for each scene: Mitsuba assigns parameter updates in place
    'constant': (lambda: {'type': 'pbrt_constant', 'value': 0.2}, 'plane.bsdf.alpha.value'),
    'imagemap': (lambda: {'type': 'pbrt_imagemap', 'filter': 'bilinear',
                          'data': mi.TensorXf(np.full((8, 8, 1), 0.2, np.float32))},
                 'plane.bsdf.alpha.data'),
    # read twice in one BSDF call (roughconductor's eval and pdf) through trilinear's two
    # levels: forward mode failed inside Dr.Jit while the second level was a symbolic
    # conditional (found in a user trial); with gradients on the texels it is a masked lookup
    'imagemap_trilinear': (lambda: {'type': 'pbrt_imagemap', 'filter': 'trilinear',
                                    'data': mi.TensorXf(np.full((8, 8, 1), 0.2, np.float32))},
                           'plane.bsdf.alpha.data'),
}


@pytest.mark.parametrize('source', list(ALPHAS))
@pytest.mark.parametrize('mode', ['backward', 'forward'])
def test_sampling_parameter_gradient_matches_prb_and_finite_differences(source, mode):
    """d(mean image)/d(alpha) along "all alpha texels +1" (the 1-channel image is uniform, so
    its levels are too and pbrt_path's footprints change no value): pbrt_path must equal
    Mitsuba's prb with the same seeds (same estimator, same random numbers: 1e-3 allows float
    reordering; the undetached MIS weight was 43% off), and both must match central
    differences of 64-spp renders with the gradient seed (the estimator's sample directions move
    with alpha, so FD carries Monte Carlo noise: measured 1–3%, bound 6%)."""
    tex, key = ALPHAS[source]
    grads = {}
    for integrator in ('pbrt_path', 'prb'):
        scene = glossy_scene(integrator, tex())
        params = mi.traverse(scene)
        value = params[key]
        dr.enable_grad(value)
        if mode == 'forward':
            dr.set_grad(value, dr.ones(type(value), dr.shape(value)))
        params.update()
        if mode == 'forward':
            dr.enqueue(dr.ADMode.Forward, value)
            dr.traverse(dr.ADMode.Forward, dr.ADFlag.ClearEdges)
        image = mi.render(scene, params, spp=64, seed=1, seed_grad=2)
        loss = dr.mean(image, axis=None)
        if mode == 'forward':
            dr.forward_to(loss)
            grads[integrator] = scalar(dr.grad(loss))
        else:
            dr.backward(loss)
            grads[integrator] = float(np.sum(np.array(dr.grad(params[key]))))
    assert grads['pbrt_path'] == pytest.approx(grads['prb'], rel=1e-3)
    scene = glossy_scene('prb', tex())
    base = np.array(mi.traverse(scene)[key], dtype=np.float64)
    h = 0.02
    params = mi.traverse(scene)
    values = []
    for sign in (1, -1):
        params[key] = type(params[key])((base + sign * h).astype(np.float32))
        params.update()
        values.append(scalar(dr.mean(mi.render(scene, params, spp=64, seed=2), axis=None)))
    fd = (values[0] - values[1]) / (2 * h)
    assert abs(fd) > 0.1
    assert grads['pbrt_path'] == pytest.approx(fd, rel=0.06)


# ------------------------------------------------------------------------------------ dr.freeze
@pytest.mark.parametrize('filt', ['point', 'bilinear', 'trilinear', 'ewa'])
def test_frozen_optimisation_steps_equal_unfrozen_ones(filt):
    """Mitsuba's frozen-optimisation pattern (its own test_freeze.py): dr.freeze a function
    that renders with pbrt_path and back-propagates; params.update(opt) and opt.step() run
    outside it, so the pyramid is rebuilt from the new texels before each call. Six Adam steps,
    frozen and not: the losses and texel gradients are equal (the replay runs the recorded
    kernels on the new inputs: float32 rounding, 1e-5), and calls were replayed, not all
    recorded (Dr.Jit records such a step up to 3 times here, as for bitmap + prb)."""
    assert_frozen_steps_equal_unfrozen(
        lambda: textured_scene('pbrt_path', filt, np.random.default_rng(3), size=16),
        DATA_KEY, 6)


@pytest.mark.parametrize('filt', ['bilinear', 'ewa'])
def test_frozen_steps_follow_a_texture_transposed_between_them(filt):
    """The same, with the 8×16 texels replaced by their 16×8 transpose before step 3: the
    pyramid's buffer keeps its size, and a recording made for one shape was replayed for the
    other (its sizes are literals in the kernels: losses 4-10× the unfrozen ones, found in a
    user trial); the pyramid's width is now part of what the frozen function sees."""
    assert_frozen_steps_equal_unfrozen(
        lambda: textured_scene('pbrt_path', filt, np.random.default_rng(3), size=16, height=8),
        DATA_KEY, 7, transpose_at=3)


def test_frozen_forward_mode_steps_equal_unfrozen_ones():
    """A frozen function propagating forward mode before the render (the recipe prb needs too)
    and rendering with pbrt_path: its gradient images equal the unfrozen ones. pbrt_path's
    carrying of a forward derivative into the pyramid reads values back, which recording
    forbids: it stays out of frozen functions (recording failed, found in a review)."""
    scene = textured_scene('pbrt_path', 'trilinear', np.random.default_rng(1), size=16)
    params = mi.traverse(scene)
    params.keep(DATA_KEY)

    def forward_image(scene, params, seed):
        data = params[DATA_KEY]
        dr.enable_grad(data)
        params.update()
        dr.set_grad(data, 1.0)
        dr.enqueue(dr.ADMode.Forward, data)
        dr.traverse(dr.ADMode.Forward, dr.ADFlag.ClearEdges)
        image = mi.render(scene, params, spp=4, seed=seed)
        dr.forward_to(image)
        return dr.grad(image)

    frozen = dr.freeze(forward_image)
    for step in range(4):
        got = np.array(frozen(scene, params, mi.UInt32(step)))
        want = np.array(forward_image(scene, params, mi.UInt32(step)))
        assert np.abs(want).sum() > 0
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-7)
    assert frozen.n_recordings < 4


@pytest.mark.parametrize('texture, key', [
    ({'type': 'pbrt_constant', 'value': 0.5}, 'value'),
    ({'type': 'pbrt_checkerboard', 'tex1': 0.7, 'tex2': 0.2, 'uscale': 4, 'vscale': 4}, 'tex1.value')])
def test_whole_step_frozen_with_parameter_updates_inside(texture, key):
    """dr.freeze around the whole step — render, backward, opt.step() and params.update(opt) —
    optimising a value of ours (a pbrt_constant's, a float nested in a checkerboard): the
    update's finiteness check must not read the value back (found in a review: recording failed
    with "reading from evaluated variables while recording a frozen function"); it skips
    values with gradients, as the texels' checks do. Losses equal the unfrozen loop's (float32
    rounding of the replayed kernels: rtol 1e-5)."""
    full = 'rect.bsdf.reflectance.' + key

    def run(frozen):
        scene = mi.load_dict({
            'type': 'scene', 'integrator': {'type': 'pbrt_path', 'max_depth': 2},
            'sensor': {'type': 'perspective', 'to_world': T().look_at([0, 0, 3], [0, 0, 0], [0, 1, 0]),
                       'film': {'type': 'hdrfilm', 'width': 8, 'height': 8}},
            'rect': {'type': 'rectangle', 'bsdf': {'type': 'diffuse', 'reflectance': texture}},
            'light': {'type': 'constant'}})
        params = mi.traverse(scene)
        params.keep(full)
        opt = mi.ad.Adam(lr=0.01)
        opt[full] = params[full]
        params.update(opt)

        def step(scene, params, opt, seed):
            image = mi.render(scene, params, spp=1, seed=seed)
            loss = dr.mean(image, axis=None)
            dr.backward(loss)
            opt.step()
            params.update(opt)
            return loss

        fn = dr.freeze(step) if frozen else step
        return [float(np.array(fn(scene, params, opt, mi.UInt32(i))).ravel()[0])
                for i in range(4)]

    np.testing.assert_allclose(run(True), run(False), rtol=1e-5)


@pytest.mark.parametrize('case', ['large data', 'inverted scale'])
def test_params_updates_of_an_image_inside_a_frozen_function(case):
    """params.update() of a pbrt_imagemap inside dr.freeze (found by a review): the data of a
    texture whose pyramid is 16 MiB or more (its build gave its temporaries back by flushing
    Dr.Jit's allocation cache, which a recording refuses), and the scale of an inverted one
    (read back for its emitter density, which a recording cannot do; the density keeps the
    scale read last). Both failed to record; their mean() equals the unfrozen steps' (float32
    rounding of the replayed kernels: rtol 1e-5)."""
    rng = np.random.default_rng(4)
    shape = (1025, 1024, 3) if case == 'large data' else (16, 16, 3)
    img = rng.random(shape).astype(np.float32)
    base = mi.TensorXf(img)

    def run(frozen):
        tex = mi.load_dict({'type': 'pbrt_imagemap', 'data': mi.TensorXf(img), 'filter': 'box',
                            'invert': case == 'inverted scale'})
        params = mi.traverse(tex)

        def step(tex, params, base, k):             # (a frozen function's inputs: arguments)
            if case == 'large data':
                params['data'] = base * k
            else:
                params['scale'] = k
            params.update()
            return tex.mean()

        fn = dr.freeze(step) if frozen else step
        out = []
        for k in (1.0, 0.5, 0.3, 2.0):
            x = mi.Float(k)
            dr.make_opaque(x)
            out.append(float(np.array(fn(tex, params, base, x)).ravel()[0]))
        return out

    np.testing.assert_allclose(run(True), run(False), rtol=1e-5)
