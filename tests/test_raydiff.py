"""Ray-differential math of pbrt_path against finite differences and closed forms."""


import mitsuba as mi
import numpy as np
import pytest

from conftest import A
from mitsuba_pbrt_tex import raydiff


def V(a):
    a = np.atleast_2d(np.asarray(a, float))
    return mi.Vector3f(a[:, 0], a[:, 1], a[:, 2])


def normalize(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def reflect(wo, n):
    return -wo + 2 * (wo * n).sum(-1, keepdims=True) * n


def refract(wo, n, eta):
    """pbrt's Refract: wo and n on the same side, eta = η_t/η_i; returns wi (NaN at TIR)."""
    cos_i = (wo * n).sum(-1, keepdims=True)
    sin2_t = np.maximum(0, 1 - cos_i ** 2) / eta ** 2
    with np.errstate(invalid='ignore'):
        cos_t = np.sqrt(1 - sin2_t)
    return -wo / eta + (cos_i / eta - cos_t) * n


def setup(rng, count):
    """wo(x) = normalize(wo0 + x·a), n(x) = normalize(n0 + x·b): derivatives at x = 0."""
    n0 = normalize(rng.normal(size=(count, 3)) * [0.3, 0.3, 1] + [0, 0, 2])
    wo0 = normalize(n0 * 1.5 + rng.normal(size=(count, 3)) * 0.4)
    a = rng.normal(size=(count, 3)) * 0.2
    b = rng.normal(size=(count, 3)) * 0.2
    def wo(x): return normalize(wo0 + x * a)
    def n(x): return normalize(n0 + x * b)
    h = 1e-6
    dwo = (wo(h) - wo(-h)) / (2 * h)
    dn = (n(h) - n(-h)) / (2 * h)
    return wo(0), n(0), dwo, dn, wo, n


@pytest.mark.parametrize('eta', [1.5, 1 / 1.5, 1.33, 2.4])
def test_refraction_differential_matches_finite_differences(eta, rng):
    wo, n, dwo, dn, wo_f, n_f = setup(rng, 200)
    wi = refract(wo, n, eta)
    h = 1e-5
    fd = (refract(wo_f(h), n_f(h), eta) - refract(wo_f(-h), n_f(-h), eta)) / (2 * h)
    # pbrt's convention: the offset ray's direction is d + dd with wo = -d, so dwodx = -d_x - wo
    # and the returned value is the offset direction wi + dwi.
    got = A(raydiff.refract_differential(V(wo), V(wi), V(n), V(dn), V(dwo), mi.Float(eta))) - wi
    # lanes near total internal reflection (η < 1) have no (or an unbounded) derivative
    cos_i = (wo * n).sum(-1)
    ok = (1 - cos_i ** 2) / eta ** 2 < 0.9
    assert ok.mean() > 0.5 and np.isfinite(fd[ok]).all()
    np.testing.assert_allclose(got[ok], fd[ok], rtol=2e-3, atol=2e-4)


def test_pbrt_v4_transmission_formula_is_wrong(rng):
    """pbrt-v4's -η·dwo instead of -dwo/η: with η = 1.5 the error is far above FD noise."""
    eta = 1.5
    wo, n, dwo, dn, wo_f, n_f = setup(rng, 50)
    wi = refract(wo, n, eta)
    h = 1e-5
    fd = (refract(wo_f(h), n_f(h), eta) - refract(wo_f(-h), n_f(-h), eta)) / (2 * h)
    mu = (wo * n).sum(-1, keepdims=True) / eta - np.abs((wi * n).sum(-1, keepdims=True))
    ddn = (dwo * n).sum(-1, keepdims=True) + (wo * dn).sum(-1, keepdims=True)
    dmu = ddn * (1 / eta + 1 / eta ** 2 * (wo * n).sum(-1, keepdims=True) / (wi * n).sum(-1, keepdims=True))
    pbrt_v4 = -eta * dwo + mu * dn + dmu * n
    assert np.max(np.abs(pbrt_v4 - fd)) > 0.05


def test_reflection_differential_matches_finite_differences(rng):
    wo, n, dwo, dn, wo_f, n_f = setup(rng, 200)
    wi = reflect(wo, n)
    h = 1e-5
    fd = (reflect(wo_f(h), n_f(h)) - reflect(wo_f(-h), n_f(-h))) / (2 * h)
    got = A(raydiff.reflect_differential(V(wo), V(wi), V(n), V(dn), V(dwo))) - wi
    np.testing.assert_allclose(got, fd, rtol=2e-3, atol=2e-4)


def test_tangent_plane_offsets_and_least_squares(rng):
    count = 100
    p = rng.normal(size=(count, 3))
    n = normalize(rng.normal(size=(count, 3)))
    o = p + normalize(rng.normal(size=(count, 3))) * 3
    o[(o - p).__mul__(n).sum(1) < 0] *= 1       # any side
    d_x = normalize(p + rng.normal(size=(count, 3)) * 0.01 - o)
    d_y = normalize(p + rng.normal(size=(count, 3)) * 0.01 - o)
    dpdx, dpdy, ok = raydiff.tangent_plane_offsets(mi.Point3f(*p.T), mi.Normal3f(*n.T),
                                                   mi.Point3f(*o.T), V(d_x), mi.Point3f(*o.T),
                                                   V(d_y), mi.Bool(True))
    dpdx = A(dpdx)
    assert A(ok).all()
    np.testing.assert_allclose((dpdx * n).sum(1), 0, atol=1e-5)          # in the plane
    # o + t d_x reproduces p + dpdx
    cross = np.cross(p + dpdx - o, d_x)
    np.testing.assert_allclose(cross, 0, atol=1e-4)
    # least squares: dp_du, dp_dv spanning the plane reproduce an in-plane vector exactly
    t1 = normalize(np.cross(n, [0.3, 0.5, 0.7]))
    t2 = np.cross(n, t1)
    dp_du, dp_dv = 2 * t1 + 0.3 * t2, -0.5 * t1 + 1.5 * t2
    duv_dx, _ = raydiff.uv_partials(V(dp_du), V(dp_dv), V(dpdx), V(dpdx))
    duv = A(duv_dx)
    np.testing.assert_allclose(duv[:, :1] * dp_du + duv[:, 1:] * dp_dv, dpdx, atol=1e-4)


def test_degenerate_cases_give_zero_not_nan():
    p, n = mi.Point3f(0, 0, 0), mi.Normal3f(0, 0, 1)
    o = mi.Point3f(0, 0, 1)
    parallel = mi.Vector3f(1, 0, 0)                    # offset ray parallel to the plane
    dpdx, dpdy, ok = raydiff.tangent_plane_offsets(p, n, o, parallel, o, parallel, mi.Bool(True))
    assert not A(ok).any() and np.all(A(dpdx) == 0)
    duv_dx, duv_dy = raydiff.uv_partials(V([0, 0, 0]), V([0, 0, 0]), V([1, 0, 0]), V([0, 1, 0]))
    assert np.all(A(duv_dx) == 0) and np.all(A(duv_dy) == 0)
    huge = raydiff.uv_partials(V([1e-20, 0, 0]), V([0, 1e-20, 0]), V([1, 0, 0]), V([0, 1, 0]))
    assert np.all(np.abs(A(huge[0])) <= 1e8)


def test_spp_scale():
    assert raydiff.spp_scale(1, 'pbrt') == 1
    assert raydiff.spp_scale(16, 'pbrt') == 0.25
    assert raydiff.spp_scale(1024, 'pbrt') == 0.125
    assert raydiff.spp_scale(1024, 'none') == 1
    assert raydiff.spp_scale(4, 0.3) == 0.3
