"""Ray-differential math of pbrt_path against finite differences and closed forms."""


import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from conftest import A
from mitsuba_pbrt_tex import raydiff

T = mi.ScalarTransform4f


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
    """pbrt-v4 writes -η·dwo where the derivative of -wo/η is -dwo/η. The package's
    ``refract_differential`` must agree with finite differences (rtol 2e-3 as above) where
    pbrt-v4's formula, evaluated here in numpy on the same inputs, is off by more than 0.05 —
    so the test fails if the package adopts pbrt-v4's term (or any other η-mis-scaled one)."""
    eta = 1.5
    wo, n, dwo, dn, wo_f, n_f = setup(rng, 50)
    wi = refract(wo, n, eta)
    h = 1e-5
    fd = (refract(wo_f(h), n_f(h), eta) - refract(wo_f(-h), n_f(-h), eta)) / (2 * h)
    got = A(raydiff.refract_differential(V(wo), V(wi), V(n), V(dn), V(dwo), mi.Float(eta))) - wi
    np.testing.assert_allclose(got, fd, rtol=2e-3, atol=2e-4)
    mu = (wo * n).sum(-1, keepdims=True) / eta - np.abs((wi * n).sum(-1, keepdims=True))
    ddn = (dwo * n).sum(-1, keepdims=True) + (wo * dn).sum(-1, keepdims=True)
    dmu = ddn * (1 / eta + 1 / eta ** 2 * (wo * n).sum(-1, keepdims=True) / (wi * n).sum(-1, keepdims=True))
    pbrt_v4 = -eta * dwo + mu * dn + dmu * n
    assert np.max(np.abs(pbrt_v4 - fd)) > 0.05
    assert np.max(np.abs(got - pbrt_v4)) > 0.05


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


def test_offsets_of_rays_along_the_normal_from_either_side():
    """Offset rays exactly along ±n (n·d = ±1, head-on from the front or from behind): valid,
    and the offset is the in-plane displacement of the offset ray's origin, exactly."""
    p, n = mi.Point3f(0, 0, 0), mi.Normal3f(0, 0, 1)
    for z, d in ((1.0, -1.0), (-1.0, 1.0)):
        o_x, o_y = mi.Point3f(0.25, 0, z), mi.Point3f(0, -0.5, z)
        dv = mi.Vector3f(0, 0, d)
        dpdx, dpdy, ok = raydiff.tangent_plane_offsets(p, n, o_x, dv, o_y, dv, mi.Bool(True))
        assert A(ok).all()
        np.testing.assert_array_equal(A(dpdx).ravel(), [0.25, 0, 0])
        np.testing.assert_array_equal(A(dpdy).ravel(), [0, -0.5, 0])


def test_degenerate_cases_give_zero_not_nan():
    p, n = mi.Point3f(0, 0, 0), mi.Normal3f(0, 0, 1)
    o = mi.Point3f(0, 0, 1)
    parallel = mi.Vector3f(1, 0, 0)                    # offset ray parallel to the plane
    dpdx, dpdy, ok = raydiff.tangent_plane_offsets(p, n, o, parallel, o, parallel, mi.Bool(True))
    assert not A(ok).any() and np.all(A(dpdx) == 0) and np.all(A(dpdy) == 0)
    # a uv parametrisation whose normal-equation determinant rounds to 0 in float32 (not
    # exactly rank 1): no partials, rather than garbage from a huge or unit inverse
    duv_dx, duv_dy = raydiff.uv_partials(V([1, 1e-4, 0]), V([1, 0, 0]), V([0, 1, 0]), V([0, 1, 0]))
    assert np.all(A(duv_dx) == 0) and np.all(A(duv_dy) == 0)
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


# ------------------------------------------------------------------------------------ camera approx.
def _true_and_approx_footprints(fov, w, h, scale, rng, n=400):
    """At points a camera ray hits directly (a plane through the hit with a random normal facing
    the camera, |cos| ≥ 0.3, at distance 0.1–10): the true footprint — Mitsuba's own one-pixel
    ray differential of that camera ray, intersected with the plane in numpy — and the camera
    approximation's (``CameraFootprint.dp_dxy``)."""
    T = mi.ScalarTransform4f
    sensor = mi.load_dict({'type': 'perspective', 'fov': fov,
                           'to_world': T().look_at([1, 2, 3], [0, 0, 0], [0, 1, 0]),
                           'film': {'type': 'hdrfilm', 'width': w, 'height': h}})
    pos = rng.uniform(0, 1, (n, 2))
    ray, _ = sensor.sample_ray_differential(0.0, 0.5, mi.Point2f(pos[:, 0], pos[:, 1]),
                                            mi.Point2f(0.5, 0.5))
    o, d, ox, dx, oy, dy = (A(v) for v in (ray.o, ray.d, ray.o_x, ray.d_x, ray.o_y, ray.d_y))
    p = o + np.exp(rng.uniform(np.log(0.1), np.log(10), n))[:, None] * d
    nrm = normalize(rng.normal(size=(n, 3)))
    nrm = np.where(((nrm * d).sum(1) > 0)[:, None], -nrm, nrm)
    keep = (nrm * -d).sum(1) >= 0.3

    def on_plane(oo, dd):
        t = ((p - oo) * nrm).sum(1) / (dd * nrm).sum(1)
        return oo + t[:, None] * dd - p

    true = on_plane(ox, dx), on_plane(oy, dy)
    ax, ay = raydiff.CameraFootprint(sensor).dp_dxy(mi.Point3f(*p.T), mi.Normal3f(*nrm.T),
                                                    scale, mi.Bool(True))
    return true, (A(ax), A(ay)), nrm, keep


def _size(pair):
    return np.sqrt(np.linalg.norm(np.cross(pair[0], pair[1]), axis=1))


def test_camera_approximation_matches_true_footprint_at_visible_points(rng):
    """pbrt-v4's camera approximation (used after diffuse/glossy bounces) at points the camera
    sees directly must have the size of the true camera-ray footprint there. Size = √|dpdx ×
    dpdy| (the approximation rotates the footprint about the view axis, so single vectors may
    differ; the area may not). Bound: fov 30° on 32×24, the film's corner is 18.5° off axis;
    the approximation uses the smallest one-pixel differentials on the film (≥ cos⁴ 18.5° = 0.81
    of the axis pixel's solid angle) where the true pixel has cos³ φ ≥ 0.85 of it, so the size
    ratio lies in [0.90, 1.08]; we allow [0.85, 1.10] for the finite one-pixel offsets on planes
    tilted up to 72° (measured 0.89–1.04). A sign error in the plane intersection (~40× too
    large) or a missing/extra factor breaks it. Both vectors must lie in the tangent plane."""
    (tx, ty), (ax, ay), nrm, keep = _true_and_approx_footprints(30, 32, 24, 1.0, rng)
    ratio = (_size((ax, ay)) / _size((tx, ty)))[keep]
    assert keep.sum() > 200
    assert ratio.min() > 0.85 and ratio.max() < 1.10, (ratio.min(), ratio.max())
    for v in (ax, ay):
        assert np.all(np.abs((v * nrm).sum(1)) <= 1e-5 * np.linalg.norm(v, axis=1))


def test_camera_approximation_is_zero_on_inactive_lanes(rng):
    T = mi.ScalarTransform4f
    sensor = mi.load_dict({'type': 'perspective', 'fov': 30,
                           'to_world': T().look_at([1, 2, 3], [0, 0, 0], [0, 1, 0]),
                           'film': {'type': 'hdrfilm', 'width': 8, 'height': 8}})
    p = rng.normal(size=(10, 3))
    active = np.arange(10) % 2 == 0
    ax, ay = raydiff.CameraFootprint(sensor).dp_dxy(mi.Point3f(*p.T), mi.Normal3f(0, 1, 0), 1.0,
                                                    mi.Bool(active))
    for v in (A(ax), A(ay)):
        assert np.all(v[~active] == 0) and np.all(np.abs(v[active]).sum(1) > 0)


def test_camera_approximation_scales_with_spp_factor(rng):
    """The ``scale`` argument (pbrt-v4: max(1/8, 1/√spp)) multiplies both vectors: at scale 1/4
    the footprint is 1/4 of the true one-pixel footprint's size within the same bounds."""
    (tx, ty), (ax, ay), _, keep = _true_and_approx_footprints(30, 32, 24, 0.25, rng)
    ratio = (_size((ax, ay)) / _size((tx, ty)))[keep] / 0.25
    assert ratio.min() > 0.85 and ratio.max() < 1.10, (ratio.min(), ratio.max())


# ------------------------------------------------------------------------------------ RayDiff
def _specular_case(rng, count, kind):
    """Hits with a curved shading normal (dn/du, dn/dv ⟂ n) and an incoming ray differential:
    ``kind`` 'reflect', 'refract_in' (entering glass, η = 1.5) or 'refract_out' (leaving it:
    wo below the normal, Mitsuba's bs.eta = 1/1.5)."""
    n = normalize(rng.normal(size=(count, 3)) * [0.3, 0.3, 1] + [0, 0, 2])
    # leaving glass: within 1/4 radian or so of the normal, far from total internal reflection
    wo = normalize(n * (4.0 if kind == 'refract_out' else 2.0) + rng.normal(size=(count, 3)) * 0.5)
    if kind == 'refract_out':
        wo = wo - 2 * (wo * n).sum(-1, keepdims=True) * n          # mirrored below the surface
    def perp(v):                                                    # random vectors ⟂ n
        return v - (v * n).sum(-1, keepdims=True) * n
    dn_du, dn_dv = perp(rng.normal(size=(count, 3)) * 0.6), perp(rng.normal(size=(count, 3)) * 0.6)
    duv_dx, duv_dy = rng.normal(size=(count, 2)) * 0.05, rng.normal(size=(count, 2)) * 0.05
    d = -wo
    # offset rays' directions d + δ with δ ⟂ d, so that dwo/dx = -δ is the derivative of the
    # unit direction (a normalised d + δ would add an O(δ²) part along d that the first-order
    # propagation, as pbrt's, carries along and the reference below does not)
    def perp_d(v):
        return v - (v * d).sum(-1, keepdims=True) * d
    d_x = d + perp_d(rng.normal(size=(count, 3))) * 0.01
    d_y = d + perp_d(rng.normal(size=(count, 3))) * 0.01
    p = rng.normal(size=(count, 3))
    dpdx, dpdy = perp(rng.normal(size=(count, 3))) * 0.01, perp(rng.normal(size=(count, 3))) * 0.01
    return dict(n=n, wo=wo, dn_du=dn_du, dn_dv=dn_dv, duv_dx=duv_dx, duv_dy=duv_dy, d_x=d_x,
                d_y=d_y, p=p, dpdx=dpdx, dpdy=dpdy)


def _after_specular(c, kind, sampled_type=None, t=None, valid=None):
    """``RayDiff.after_specular`` on the case ``c`` (the main ray's exact outgoing direction)."""
    count = len(c['n'])
    eta = {'reflect': 1.0, 'refract_in': 1.5, 'refract_out': 1 / 1.5}[kind]
    wi = _exact_direction(c['wo'], c['n'], kind)
    si = dr.zeros(mi.SurfaceInteraction3f, count)
    si.t = mi.Float(np.ones(count) if t is None else t)
    si.p, si.n = mi.Point3f(V(c['p'])), mi.Normal3f(V(c['n']))
    si.sh_frame = mi.Frame3f(V(c['n']))
    si.wi = si.sh_frame.to_local(V(c['wo']))
    si.duv_dx = mi.Vector2f(c['duv_dx'][:, 0], c['duv_dx'][:, 1])
    si.duv_dy = mi.Vector2f(c['duv_dy'][:, 0], c['duv_dy'][:, 1])
    si.dn_du, si.dn_dv = V(c['dn_du']), V(c['dn_dv'])
    bs = dr.zeros(mi.BSDFSample3f, count)
    flag = int(mi.BSDFFlags.DeltaReflection if kind == 'reflect' else mi.BSDFFlags.DeltaTransmission)
    bs.sampled_type = mi.UInt32(np.full(count, flag) if sampled_type is None else sampled_type)
    bs.eta = mi.Float(np.full(count, eta))
    o = c['p'] - c['wo']                                      # the rays came from 1 unit away
    diff = raydiff.RayDiff(mi.Point3f(V(o)), V(c['d_x']), mi.Point3f(V(o)), V(c['d_y']),
                           mi.Bool(np.ones(count, bool) if valid is None else valid))
    out = diff.after_specular(si, bs, V(wi), mi.Point3f(V(c['p'])), V(c['dpdx']), V(c['dpdy']))
    return [A(v) for v in out.fields()], wi, o


def _exact_direction(wo, n, kind):
    if kind == 'reflect':
        return reflect(wo, n)
    if kind == 'refract_in':
        return refract(wo, n, 1.5)
    return refract(wo, -n, 1 / 1.5)


@pytest.mark.parametrize('kind', ['reflect', 'refract_in', 'refract_out'])
def test_after_specular_offsets_follow_the_exact_direction_of_the_offset_rays(kind, rng):
    """``RayDiff.after_specular`` — what ``pbrt_path`` does at a mirror or glass hit — on curved
    surfaces (shading-normal derivatives dn/du, dn/dv combined with du/dx, dv/dx …), reflecting,
    entering and leaving glass (from below the normal: n flipped): the new offset directions are
    the exact outgoing direction plus its derivative along each offset, the derivative taken by
    central differences of the exact reflection/refraction (numpy) of wo(s) = normalize(wo +
    s·dwo/dx) about n(s) = normalize(n + s·dn/dx), dwo/dx = -(d_x - d) from the incoming offset
    ray; the new origins are the spawned origin plus dp/dx, dp/dy; every lane stays valid.
    h = 1e-4 (truncation ~h² · |d³wi| ≲ 1e-7) and float32 directions: atol 1e-4."""
    c = _specular_case(rng, 300, kind)
    (o_x, d_x, o_y, d_y, valid), wi, _ = _after_specular(c, kind)
    n = c['n'] if kind != 'refract_out' else -c['n']
    sign = 1 if kind != 'refract_out' else -1
    h = 1e-4
    for axis, got_o, got_d in (('x', o_x, d_x), ('y', o_y, d_y)):
        duv = c[f'duv_d{axis}']
        dndx = sign * (c['dn_du'] * duv[:, :1] + c['dn_dv'] * duv[:, 1:])
        dwo = -(c[f'd_{axis}'] - (-c['wo']))

        def direction(s):
            return _exact_direction(normalize(c['wo'] + s * dwo),
                                    sign * normalize(n + s * dndx), kind)

        want = wi + (direction(h) - direction(-h)) / (2 * h)
        assert np.isfinite(want).all()
        np.testing.assert_allclose(got_d, want, atol=1e-4)
        np.testing.assert_allclose(got_o, c['p'] + c[f'dp{"d" + axis}'], atol=1e-5)
    assert valid.all()


def test_after_specular_drops_what_pbrt_drops():
    """Lanes where pbrt-v4's ``SpawnRay`` gives up the differential keep the old rays and become
    invalid: an offset direction or origin of squared length beyond 1e16 (each of the four
    alone), a non-finite offset direction (each alone), a sampled lobe that is not specular, a
    missed surface (t = ∞), an incoming differential that was not valid. Origins and offset
    directions of squared length exactly 1e16 (in float32) are kept (pbrt: ``> 1e16``). A dropped
    differential (``dropped()``) is invalid with its rays unchanged."""
    rng = np.random.default_rng(7)
    c = _specular_case(rng, 10, 'reflect')
    c['duv_dx'][:], c['duv_dy'][:] = [0.1, 0.0], [0.0, 0.1]
    c['dn_dv'][:] = 0
    nan = float('nan')
    c['dn_du'][0] *= 1e10                                        # 0: rx beyond 1e16 only
    c['dn_dv'][1] = c['dn_du'][1] * 1e10                          # 1: ry beyond 1e16 only
    c['dpdx'][2] = [2e8, 0, 0]                                    # 2: o_x beyond only
    c['dpdy'][3] = [0, 2e8, 0]                                    # 3: o_y beyond only
    c['duv_dx'][4] = [nan, 0]                                     # 4: rx NaN only
    c['duv_dy'][5] = [0, nan]                                     # 5: ry NaN only
    c['p'][9], c['dpdx'][9], c['dpdy'][9] = 0, [1e8, 0, 0], [0, 1e8, 0]   # 9: |o|² = 1e16
    sampled = np.full(10, int(mi.BSDFFlags.DeltaReflection))
    sampled[6] = int(mi.BSDFFlags.DiffuseReflection)              # 6: not specular
    t = np.ones(10)
    t[7] = np.inf                                                 # 7: no surface
    valid_in = np.ones(10, bool)
    valid_in[8] = False                                           # 8: nothing to propagate
    (o_x, d_x, o_y, d_y, valid), wi, o = _after_specular(c, 'reflect', sampled, t, valid_in)
    dropped = np.arange(10) < 9
    np.testing.assert_array_equal(valid, ~dropped)
    for got, old in ((o_x, o), (o_y, o), (d_x, c['d_x']), (d_y, c['d_y'])):
        np.testing.assert_allclose(got[dropped], old[dropped], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(o_x[9], [1e8, 0, 0], rtol=1e-6)
    np.testing.assert_allclose(o_y[9], [0, 1e8, 0], rtol=1e-6)
    # offset directions of squared length exactly 1e16 in float32 (a head-on mirror hit with
    # d_x = (-1e8, 0, -1): rx = (-1e8, 0, 1), and 1e16 + 1 rounds to 1e16) are kept, as origins
    z = np.array([[0.0, 0, 1]])
    edge = dict(n=z, wo=z, dn_du=0 * z, dn_dv=0 * z, duv_dx=np.zeros((1, 2)),
                duv_dy=np.zeros((1, 2)), d_x=np.array([[-1e8, 0, -1]]),
                d_y=np.array([[0, -1e8, -1]]), p=0 * z, dpdx=0 * z, dpdy=0 * z)
    (_, d_x, _, d_y, valid), _, _ = _after_specular(edge, 'reflect')
    assert valid.all()
    np.testing.assert_array_equal(d_x.reshape(3), [-1e8, 0, 1])
    np.testing.assert_array_equal(d_y.reshape(3), [0, -1e8, 1])
    rays = raydiff.RayDiff(mi.Point3f(1, 2, 3), mi.Vector3f(0, 0, 1), mi.Point3f(4, 5, 6),
                           mi.Vector3f(0, 1, 0), mi.Bool(True))
    gone = [A(v) for v in rays.dropped().fields()]
    assert not gone[4].any()
    for got, want in zip(gone[:4], ([1, 2, 3], [0, 0, 1], [4, 5, 6], [0, 1, 0])):
        np.testing.assert_array_equal(got.reshape(-1, 3)[0], want)


def test_ray_differential_footprint_only_on_active_lanes_with_a_valid_differential():
    """``RayDiff.footprint``: the offsets on the tangent plane (here, rays along -z hitting z = 0:
    the offset rays' in-plane origins, exactly) where the lane is active and the differential
    valid; elsewhere (inactive, or no valid differential, or none at all) zero and not ok."""
    o_x, o_y = mi.Point3f(0.25, 0, 1), mi.Point3f(0, -0.5, 1)
    d = mi.Vector3f(0, 0, -1)
    active, valid = np.array([1, 1, 0, 0], bool), np.array([1, 0, 1, 0], bool)
    rays = raydiff.RayDiff(o_x, d, o_y, d, mi.Bool(valid))
    dpdx, dpdy, ok = rays.footprint(mi.Point3f(0, 0, 0), mi.Normal3f(0, 0, 1), mi.Bool(active))
    np.testing.assert_array_equal(A(ok), [True, False, False, False])
    np.testing.assert_array_equal(A(dpdx), [[0.25, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]])
    np.testing.assert_array_equal(A(dpdy), [[0, -0.5, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]])
    # the differential of a camera ray without one (``RayDiff()``) is not valid: no footprint
    none = raydiff.RayDiff()
    assert not A(none.valid).any()
    dpdx, dpdy, ok = none.footprint(mi.Point3f(0, 0, 0), mi.Normal3f(0, 0, 1), mi.Bool(True))
    assert not A(ok).any() and not A(dpdx).any() and not A(dpdy).any()


def test_camera_approximation_takes_the_smallest_differentials_on_the_film_diagonal():
    """pbrt-v4's ``FindMinimumDifferentials`` takes the smallest one-pixel direction
    differentials over 512 camera rays along the film diagonal, corner to corner (i/511). Their
    length is the chord between the unit ray and its offset ray — frame-independent, so it is
    computed here in float64 from Mitsuba's own rays. The camera's principal point is off
    centre, so one corner is farther off axis than the other and holds the minimum (the
    other corner's chord is 20% longer). Tolerance rtol 2e-4: the float32 chord (~0.014) is
    good to ~1e-5; sampling the diagonal short of or beyond the corner (a spacing of 1/510 or
    1/512) changes it by 8.6e-4 to 1.7e-3."""
    T = mi.ScalarTransform4f
    sensor = mi.load_dict({'type': 'perspective', 'fov': 30, 'principal_point_offset_x': 0.3,
                           'principal_point_offset_y': 0.2,
                           'to_world': T().look_at([1, 2, 3], [0, 0, 0], [0, 1, 0]),
                           'film': {'type': 'hdrfilm', 'width': 32, 'height': 24}})
    t = np.arange(512) / 511.0
    ray, _ = sensor.sample_ray_differential(0.0, 0.5, mi.Point2f(t, t), mi.Point2f(0.5, 0.5))
    d = normalize(A(ray.d).astype(np.float64))
    approx = raydiff.CameraFootprint(sensor)
    for offset, got in ((ray.d_x, approx.min_dir_x), (ray.d_y, approx.min_dir_y)):
        chord = np.linalg.norm(normalize(A(offset).astype(np.float64)) - d, axis=1)
        assert chord[0] > 1.1 * chord[-1]           # the far corner is the minimum
        np.testing.assert_allclose(np.linalg.norm(A(got).reshape(3)), chord.min(), rtol=2e-4)
    for got in (approx.min_pos_x, approx.min_pos_y):   # a pinhole: all rays from one point
        np.testing.assert_array_equal(A(got).reshape(3), 0)


def test_shortest_finite_vector_of_each_array():
    """``CameraFootprint._shortest`` (how the camera's smallest one-pixel differentials are
    picked from its film samples): for each array of vectors, the shortest finite one, the first
    of equally short ones, and 0 where none is finite — against numpy's argmin."""
    rng = np.random.default_rng(4)
    n = 64
    a = rng.normal(size=(n, 3))
    a[[3, 9]] = [0.01, 0.02, 0.0]                   # a tie for the shortest: the first wins
    a[5] = [np.inf, 0, 0]                           # not finite, and would be "shortest" as NaN
    a[6] = [np.nan, 0, 0]
    b = rng.normal(size=(n, 3)) * 3
    c = np.full((n, 3), np.inf)                     # nothing finite
    got = [A(v).reshape(3) for v in raydiff.CameraFootprint._shortest((V(a), V(b), V(c)))]
    for vectors, out in ((a, got[0]), (b, got[1])):
        length = np.where(np.isfinite(vectors).all(1), (vectors ** 2).sum(1), np.inf)
        np.testing.assert_allclose(out, vectors[np.argmin(length)], rtol=1e-6)
    np.testing.assert_array_equal(got[0], np.float32(a[3]))
    np.testing.assert_array_equal(got[2], [0, 0, 0])


class _PartialsProbe(mi.Texture):
    """A texture (a user's Python texture: pbrt_path gives it differentials) whose value is what
    it is given: (du/dx, dv/dx, u) or, with ``which`` 1, (du/dy, dv/dy, v)."""

    def __init__(self, props):
        mi.Texture.__init__(self, props)
        self.which = props.get('which', 0)

    def eval(self, si, active=True):
        if self.which == 0:
            return mi.Color3f(si.duv_dx.x, si.duv_dx.y, si.uv.x)
        return mi.Color3f(si.duv_dy.x, si.duv_dy.y, si.uv.y)

    def mean(self):
        return 1.0

    def is_spatially_varying(self):
        return True

    def traverse(self, cb):
        pass


def test_partials_after_a_curved_mirror_match_finite_differences_of_traced_rays():
    """pbrt_path's uv partials of a floor seen in a mirror sphere against central finite
    differences of the same reflections traced in numpy (float64; the floor's uv as the
    rectangle's). The reflected differential bends with the sphere's curvature: found in a user
    trial, hits computed with RayFlags.All had no shading-normal derivatives (dn/du = 0), so
    curved mirrors and lenses propagated the footprint of a flat one (median 0.36 of the true
    du/dx here, 0.21 of dv/dx). Median over the reflected lanes within 2% per component (measured
    ≤ 0.2%; the differential is a linearisation over 1% of a pixel, single lanes spread)."""
    mi.register_texture('test_partials_probe', lambda p: _PartialsProbe(p))
    centre, radius, eps = np.array([0.0, 1.2, 0.0]), 0.8, 0.01

    def scene(which):
        return mi.load_dict({
            'type': 'scene',
            'sensor': {'type': 'perspective', 'fov': 40,
                       'to_world': T().look_at([0, 1, 5], [0, 1, 0], [0, 1, 0]),
                       'film': {'type': 'hdrfilm', 'width': 48, 'height': 36}},
            'floor': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(4),
                      'bsdf': {'type': 'diffuse', 'reflectance': 0.0},
                      'emitter': {'type': 'area', 'radiance': {'type': 'test_partials_probe',
                                                               'which': which}}},
            'mirror': {'type': 'sphere', 'center': centre.tolist(), 'radius': radius,
                       'bsdf': {'type': 'conductor', 'material': 'none'}}})

    n = 40
    xs, ys = np.meshgrid(np.linspace(0.3, 0.7, n), np.linspace(0.25, 0.75, n))
    sensor = scene(0).sensors()[0]
    ray, _ = sensor.sample_ray_differential(
        0.0, 0.5, mi.Point2f(xs.ravel().astype(np.float32), ys.ravel().astype(np.float32)),
        mi.Point2f(0.5, 0.5))
    o, d, d_x, d_y = (np.array(v, np.float64).T for v in (ray.o, ray.d, ray.d_x, ray.d_y))
    # rays not drawn by pbrt_path's sample_rays come as Mitsuba's SamplingIntegrator passes
    # them, scaled by 1/√spp (here 4: 1/2); pbrt_path scales them the rest of the way
    ray.scale_differential(0.5)
    out = []
    for which in (0, 1):
        integrator = mi.load_dict({'type': 'pbrt_path', 'spp_scale': eps, 'max_depth': 4})
        sampler = mi.load_dict({'type': 'independent', 'sample_count': 4})
        sampler.seed(7, n * n)
        probe_scene = scene(which)          # alive until its lazy result is evaluated
        value = integrator.sample(dr.ADMode.Primal, probe_scene, sampler, ray, None, None,
                                  mi.Bool(True))[0]
        out.append(np.array(value, np.float64).T)
    got_all = np.concatenate([out[0][:, :2], out[1][:, :2]], 1)

    def floor_uv(o, d):
        """uv where the ray, reflected once off the sphere, meets the floor (None: it does not)."""
        d = d / np.linalg.norm(d)
        oc = o - centre
        b, c = oc @ d, oc @ oc - radius ** 2
        if b * b - c < 0:
            return None
        p = o + (-b - np.sqrt(b * b - c)) * d
        nrm = (p - centre) / radius
        r = d - 2 * (d @ nrm) * nrm
        if r[1] >= 0:
            return None
        q = p - p[1] / r[1] * r
        return np.array([(q[0] + 4) / 8, (4 - q[2]) / 8]) if max(abs(q[0]), abs(q[2])) < 4 \
            else None

    h, ratios = 1e-4, []
    for i in range(n * n):
        uv = floor_uv(o[i], d[i])
        if uv is None or np.abs(uv - [out[0][i, 2], out[1][i, 2]]).max() > 1e-3:
            continue                                   # not a reflection seen in both renders
        diffs = []
        for dd in (d_x[i] - d[i], d_y[i] - d[i]):
            plus, minus = floor_uv(o[i], d[i] + h * dd), floor_uv(o[i], d[i] - h * dd)
            diffs.append(None if plus is None or minus is None else (plus - minus) / (2 * h))
        if diffs[0] is None or diffs[1] is None:
            continue
        ref = np.concatenate(diffs) * eps
        ratios.append(got_all[i] / np.where(np.abs(ref) > 1e-9, ref, np.nan))
    ratios = np.array(ratios)
    assert len(ratios) > 300
    assert np.isfinite(got_all).all()
    median = np.nanmedian(ratios, 0)
    print('median got/reference per component', median)
    np.testing.assert_allclose(median, 1.0, atol=0.02)
