"""Shared fixtures: the test variant (llvm_ad_rgb), plugin registration, small helpers."""

import contextlib
import gc
import glob
import hashlib
import inspect
import os
import sys

import pytest

import mitsuba_pbrt_tex as mpt
import drjit as dr
import mitsuba as mi
import numpy as np

VARIANT = os.environ.get('MITSUBA_PBRT_TEX_TEST_VARIANT', 'llvm_ad_rgb')
mi.set_variant(VARIANT)
mpt.register()


@pytest.fixture(autouse=True)
def _variant():
    """Every test starts in the test variant with the plugins registered, and ends by collecting
    reference cycles (Mitsuba scenes and matplotlib figures form them), so no test inherits the
    AD graph of variables an earlier test left in a cycle."""
    if mi.variant() != VARIANT:
        mi.set_variant(VARIANT)
    mpt.register()
    yield
    gc.collect()


def make_si(uv, duv_dx=None, duv_dy=None, p=None, n=None, dp_du=None, dp_dv=None):
    """A SurfaceInteraction3f with the given per-lane values (numpy arrays or lists)."""
    uv = np.asarray(uv, dtype=np.float64)
    count = uv.shape[0]
    si = dr.zeros(mi.SurfaceInteraction3f, count)
    si.uv = mi.Point2f(uv[:, 0], uv[:, 1])
    if duv_dx is not None:
        d = np.asarray(duv_dx, dtype=np.float64)
        si.duv_dx = mi.Vector2f(d[:, 0], d[:, 1])
    if duv_dy is not None:
        d = np.asarray(duv_dy, dtype=np.float64)
        si.duv_dy = mi.Vector2f(d[:, 0], d[:, 1])
    for name, value, T in (('p', p, mi.Point3f), ('n', n, mi.Normal3f),
                           ('dp_du', dp_du, mi.Vector3f), ('dp_dv', dp_dv, mi.Vector3f)):
        if value is not None:
            v = np.broadcast_to(np.asarray(value, dtype=np.float64), (count, 3))
            setattr(si, name, T(v[:, 0], v[:, 1], v[:, 2]))
    if n is None:
        si.n = mi.Normal3f(0, 0, 1)
    return si


def A(x):
    """Dr.Jit array → numpy with lanes first: Float → (n,), Color3f/Point3f → (n, 3)."""
    a = np.array(x)
    if dr.is_array_v(x) and dr.depth_v(x) > 1 and a.ndim == 2:
        a = a.T
    return a


@contextlib.contextmanager
def wavefront_mode(enabled=True):
    """Within this block, Dr.Jit runs loops and calls in wavefront mode (evaluated, not
    symbolic) when ``enabled``; the previous flags come back afterwards."""
    flags = (dr.JitFlag.SymbolicLoops, dr.JitFlag.SymbolicCalls)
    old = [dr.flag(f) for f in flags]
    try:
        if enabled:
            for f in flags:
                dr.set_flag(f, False)
        yield
    finally:
        for f, v in zip(flags, old):
            dr.set_flag(f, v)


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


#: A folder for slow numpy references (set by ``tests/mutate.sh``, which runs a test once per
#: mutant); unset, every reference is computed afresh.
REFERENCE_CACHE = os.environ.get('MITSUBA_PBRT_TEX_REFERENCE_CACHE')


def numpy_reference(fn, *inputs):
    """``fn(*inputs)`` as a float64 array: a reference computed by numpy from the test's inputs
    alone (``fn`` must not call the package). With ``REFERENCE_CACHE`` set, the result is kept
    there under a hash of the inputs, ``fn``'s name and the source of ``fn``'s module and of
    every ``tests/reference_*.py`` helper, so a mutation run computes each slow reference once
    (in its first, unmutated pass) and a mutant of the package cannot change it."""
    if not REFERENCE_CACHE:
        return np.asarray(fn(*inputs), np.float64)
    h = hashlib.sha256(fn.__qualname__.encode())
    sources = [inspect.getsourcefile(sys.modules[fn.__module__])]
    sources += sorted(glob.glob(os.path.join(os.path.dirname(__file__), 'reference_*.py')))
    for path in sources:
        with open(path, 'rb') as f:
            h.update(f.read())
    for a in inputs:
        a = np.ascontiguousarray(a)
        h.update(f'{a.dtype}{a.shape}'.encode())
        h.update(a.tobytes())
    path = os.path.join(REFERENCE_CACHE, h.hexdigest() + '.npy')
    if os.path.exists(path):
        return np.load(path)
    out = np.asarray(fn(*inputs), np.float64)
    os.makedirs(REFERENCE_CACHE, exist_ok=True)
    tmp = f'{path}.{os.getpid()}.tmp'
    with open(tmp, 'wb') as f:
        np.save(f, out)
    os.replace(tmp, path)
    return out


def adam_steps(load_scene, key, steps, frozen, spp=4, transpose_at=None):
    """Mitsuba's frozen-optimisation pattern (its own test_freeze.py): a function renders and
    back-propagates, ``params.update(opt)`` and ``opt.step()`` run outside it; with ``frozen``
    the function goes through ``dr.freeze``. ``transpose_at``: before that step the texels of
    ``key`` (H, W, C) become their (W, H, C) transpose, given to the optimiser anew. Returns
    ([(loss, gradient of ``key``)] per step, the number of recordings or None)."""
    scene = load_scene()

    def optimize(scene, seed):
        params = mi.traverse(scene)
        params.keep(key)
        image = mi.render(scene, params, spp=spp, seed=seed)
        loss = dr.mean(dr.square(image - 0.25), axis=None)
        dr.backward(loss)
        return loss

    fn = dr.freeze(optimize) if frozen else optimize
    params = mi.traverse(scene)
    params.keep(key)
    opt = mi.ad.Adam(lr=0.05)
    opt[key] = params[key]
    history = []
    for step in range(steps):
        if step == transpose_at:
            texels = np.array(opt[key])
            params[key] = mi.TensorXf(np.ascontiguousarray(texels.transpose(1, 0, 2)))
            opt[key] = params[key]
        params.update(opt)
        loss = fn(scene, mi.UInt32(step))
        history.append((float(np.array(loss).ravel()[0]), np.array(dr.grad(opt[key]))))
        opt.step()
    return history, (fn.n_recordings if frozen else None)


def assert_frozen_steps_equal_unfrozen(load_scene, key, steps, spp=4, transpose_at=None):
    """``adam_steps`` frozen and not: calls were replayed (not all recorded), every step's
    texel gradient is non-zero, and losses and gradients are equal up to float32 rounding of
    the replayed kernels (1e-5 relative, 1e-7 absolute)."""
    plain, _ = adam_steps(load_scene, key, steps, False, spp=spp, transpose_at=transpose_at)
    frozen, recordings = adam_steps(load_scene, key, steps, True, spp=spp,
                                    transpose_at=transpose_at)
    assert recordings < len(frozen)
    for (loss_p, grad_p), (loss_f, grad_f) in zip(plain, frozen):
        assert np.abs(grad_p).sum() > 0
        assert loss_f == pytest.approx(loss_p, rel=1e-5)
        np.testing.assert_allclose(grad_f, grad_p, rtol=1e-5, atol=1e-7)


def assert_texel_gradients_match_fd(tex, img, si, w, rng):
    """``dr.backward`` of ``loss = Σ w·tex.eval_1(si)`` through the ``data`` parameter (set
    from ``img`` with gradients enabled, then ``params.update()``) against central differences
    of the loss (step 1 in one texel) for the 6 largest gradients and one random texel. The
    loss is linear in the texels, so the differences are exact up to float32 rounding: rtol
    1e-3, atol 1e-4."""
    params = mi.traverse(tex)
    data = mi.TensorXf(img)
    dr.enable_grad(data)
    params['data'] = data
    params.update()
    loss = dr.sum(w * tex.eval_1(si))
    dr.backward(loss)
    grad = np.array(dr.grad(params['data']))
    assert np.abs(grad).sum() > 0

    def loss_at(arr):
        params['data'] = mi.TensorXf(arr)
        params.update()
        return float(dr.sum(w * tex.eval_1(si))[0])

    flat = np.argsort(-np.abs(grad).ravel())[:6].tolist() + [int(rng.integers(grad.size))]
    for k in flat:
        e = np.zeros(img.size, np.float32)
        e[k] = 1.0
        e = e.reshape(img.shape)
        fd = (loss_at(img + e) - loss_at(img - e)) / 2
        assert grad.ravel()[k] == pytest.approx(fd, rel=1e-3, abs=1e-4)
