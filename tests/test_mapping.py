"""Texture-coordinate mappings: (s, t) against independent formulas, derivatives against central
finite differences of the mapping itself (seams, poles and the origin included)."""

import math

import mitsuba as mi
import numpy as np
import pytest

from mitsuba_pbrt_tex.differentials import TextureEvalContext
from mitsuba_pbrt_tex.mapping import (CylindricalMapping, PlanarMapping, PointTransformMapping,
                                      SphericalMapping, UVMapping)

from conftest import A, make_si


def ctx_from(p=None, dpdx=None, dpdy=None, uv=None, duv=None):
    n = len(p if p is not None else uv)
    z3 = np.zeros((n, 3))
    p = z3 if p is None else np.asarray(p, float)
    dpdx = z3 if dpdx is None else np.asarray(dpdx, float)
    dpdy = z3 if dpdy is None else np.asarray(dpdy, float)
    uv = np.zeros((n, 2)) if uv is None else np.asarray(uv, float)
    duv = np.zeros((n, 4)) if duv is None else np.asarray(duv, float)
    V = lambda a, T: T(a[:, 0], a[:, 1], a[:, 2])
    return TextureEvalContext(p=V(p, mi.Point3f), dpdx=V(dpdx, mi.Vector3f),
                              dpdy=V(dpdy, mi.Vector3f), n=mi.Normal3f(0, 0, 1),
                              uv=mi.Point2f(uv[:, 0], uv[:, 1]), dudx=mi.Float(duv[:, 0]),
                              dudy=mi.Float(duv[:, 1]), dvdx=mi.Float(duv[:, 2]),
                              dvdy=mi.Float(duv[:, 3]))


def st_of(mapping, p):
    tc = mapping.map(ctx_from(p=p))
    return A(tc.st)


def check_fd(mapping, p, dirs, h, rtol=2e-3, atol=2e-4):
    """Mapping derivatives along dirs vs central differences of the mapping's own (s, t).

    Angular coordinates are periodic with period 1; a difference across the seam is taken
    modulo 1 (the derivative of φ is continuous there, only its representative jumps)."""
    tc = mapping.map(ctx_from(p=p, dpdx=dirs, dpdy=-0.5 * dirs))
    got = np.stack([A(tc.dsdx), A(tc.dtdx)], axis=1)
    got_y = np.stack([A(tc.dsdy), A(tc.dtdy)], axis=1)
    diff = st_of(mapping, p + h * dirs) - st_of(mapping, p - h * dirs)
    periodic = {'spherical': [False, True], 'cylindrical': [True, False]}.get(
        getattr(mapping, 'name', ''), [False, False])
    for c in range(2):
        if periodic[c]:
            diff[:, c] -= np.round(diff[:, c])
    fd = diff / (2 * h)
    np.testing.assert_allclose(got, fd, rtol=rtol, atol=atol)
    np.testing.assert_allclose(got_y, -0.5 * fd, rtol=rtol, atol=atol)
    assert np.isfinite(got).all()


def random_points(rng, n, avoid_axis=0.2):
    p = rng.normal(size=(n, 3))
    rho = np.hypot(p[:, 0], p[:, 1])
    p[rho < avoid_axis, 0] += avoid_axis
    return p


# ---------------------------------------------------------------------------------------- uv
def test_uv_mapping_formula_and_derivatives(rng):
    n = 64
    uv = rng.uniform(-2, 3, (n, 2))
    duv = rng.normal(size=(n, 4))
    m = UVMapping(2.0, 3.0, 0.25, -0.5)
    tc = m.map(ctx_from(uv=uv, duv=duv))
    np.testing.assert_allclose(A(tc.st), np.stack([2 * uv[:, 0] + .25, 3 * uv[:, 1] - .5], 1),
                               rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(A(tc.dsdx), 2 * duv[:, 0], rtol=1e-6)
    np.testing.assert_allclose(A(tc.dsdy), 2 * duv[:, 1], rtol=1e-6)
    np.testing.assert_allclose(A(tc.dtdx), 3 * duv[:, 2], rtol=1e-6)
    np.testing.assert_allclose(A(tc.dtdy), 3 * duv[:, 3], rtol=1e-6)


def test_uv_mapping_drops_only_the_rounding_of_rotations():
    """A rotation by a multiple of 90° leaves rounding (cos = -4e-8) on one diagonal, whose
    product is then below 1e-12 of the other's: that diagonal becomes 0, whatever the scale on
    either side; very different scales stay, also with other rotations — comparisons with the
    largest entry had made vscale 1 next to uscale 1e7 a 0 (every lookup along v then read
    v = 0), and row/column ones did so again after a 30° rotation (a review)."""
    T = mi.ScalarTransform4f
    assert UVMapping(1e7, 1.0).a == [[1e7, 0.0], [0.0, 1.0]]
    assert UVMapping(2000.0, 1e-3).a == [[2000.0, 0.0], [0.0, 1e-3]]
    for to_uv in (T().rotate([0, 0, 1], 30), T().rotate([0, 0, 1], 30) @ T().scale([1, 1e7, 1])):
        a = UVMapping(1e7, 1.0, to_uv=to_uv).a
        assert all(x != 0 for row in a for x in row), a
    a = UVMapping(to_uv=T().rotate([0, 0, 1], 180)).a
    assert a[0][1] == 0 and a[1][0] == 0 and a[0][0] == pytest.approx(-1), a
    for to_uv in (T().scale([1e6, 1, 1]) @ T().rotate([0, 0, 1], 90),
                  T().rotate([0, 0, 1], 90) @ T().scale([1e6, 1, 1])):
        a = UVMapping(to_uv=to_uv).a
        assert a[0][0] == 0 and a[1][1] == 0 and a[0][1] != 0 and a[1][0] != 0, a
    shear = UVMapping(to_uv=T(mi.ScalarMatrix4f(1, 1e-3, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0,
                                                0, 0, 0, 1))).a
    assert shear[0][1] == pytest.approx(1e-3)           # a small but real shear stays


def test_uv_mapping_composes_to_uv_first(rng):
    """(s, t) = S · to_uv · (u, v); derivatives follow the same 2x2 matrix."""
    to_uv = mi.ScalarTransform4f().translate([0.1, 0.2, 0]) @ mi.ScalarTransform4f().rotate([0, 0, 1], 30)
    m = UVMapping(2.0, 0.5, 1.0, 0.0, to_uv)
    uv = rng.uniform(0, 1, (16, 2))
    duv = rng.normal(size=(16, 4))
    tc = m.map(ctx_from(uv=uv, duv=duv))
    M = np.array(to_uv.matrix)[:2][:, [0, 1, 3]]
    S = np.diag([2.0, 0.5])
    lin = S @ M[:, :2]
    b = S @ M[:, 2] + np.array([1.0, 0.0])
    np.testing.assert_allclose(A(tc.st), uv @ lin.T + b, rtol=1e-5, atol=1e-6)
    dx = np.stack([duv[:, 0], duv[:, 2]], 1) @ lin.T
    np.testing.assert_allclose(A(tc.dsdx), dx[:, 0], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(A(tc.dtdx), dx[:, 1], rtol=1e-5, atol=1e-6)
    dy = np.stack([duv[:, 1], duv[:, 3]], 1) @ lin.T
    np.testing.assert_allclose(A(tc.dsdy), dy[:, 0], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(A(tc.dtdy), dy[:, 1], rtol=1e-5, atol=1e-6)


def test_uv_mapping_derivatives_match_finite_differences_with_shear(rng):
    """Independent of the matrix bookkeeping above: each of the four derivatives is the central
    difference of the mapping's own (s, t) when (u, v) moves along (du/dx, dv/dx) or
    (du/dy, dv/dy), with a to_uv that rotates, shears and scales unequally (so every entry of
    the 2×2 matrix differs and a swapped partial or entry changes the result). The mapping is
    affine, so the difference is exact up to float32 rounding of st (|st| ≲ 10, h = 1e-2:
    ~1e-4 relative); rtol 1e-3."""
    T = mi.ScalarTransform4f
    to_uv = (T().translate([0.3, -0.1, 0]) @ T().rotate([0, 0, 1], 35)
             @ mi.ScalarTransform4f(mi.ScalarMatrix4f([[1, 0.6, 0, 0], [0, 1, 0, 0],
                                                        [0, 0, 1, 0], [0, 0, 0, 1]]))
             @ T().scale([1.7, 0.4, 1]))
    m = UVMapping(2.5, 1.5, 0.2, -0.3, to_uv)
    n = 32
    uv = rng.uniform(-1, 2, (n, 2))
    duv = rng.normal(size=(n, 4))            # (du/dx, du/dy, dv/dx, dv/dy)
    tc = m.map(ctx_from(uv=uv, duv=duv))
    h = 1e-2
    st = lambda x: A(m.map(ctx_from(uv=x)).st)
    for dirn, got_s, got_t in (([0, 2], tc.dsdx, tc.dtdx), ([1, 3], tc.dsdy, tc.dtdy)):
        step = duv[:, dirn]
        fd = (st(uv + h * step) - st(uv - h * step)) / (2 * h)
        np.testing.assert_allclose(A(got_s), fd[:, 0], rtol=1e-3, atol=1e-3)
        np.testing.assert_allclose(A(got_t), fd[:, 1], rtol=1e-3, atol=1e-3)


# ---------------------------------------------------------------------------------------- spherical
def spherical_st(p):
    r = np.linalg.norm(p, axis=1)
    theta = np.arccos(np.clip(p[:, 2] / r, -1, 1))
    phi = np.arctan2(p[:, 1], p[:, 0])
    phi = np.where(phi < 0, phi + 2 * math.pi, phi)
    return np.stack([theta / math.pi, phi / (2 * math.pi)], 1)


def test_spherical_st_matches_formula(rng):
    p = random_points(rng, 200)
    np.testing.assert_allclose(st_of(SphericalMapping(), p), spherical_st(p), atol=2e-6)


def test_spherical_derivatives_match_finite_differences(rng):
    p = random_points(rng, 200)
    dirs = rng.normal(size=p.shape)
    check_fd(SphericalMapping(), p, dirs, h=1e-3)


def test_spherical_derivatives_are_not_swapped():
    """pbrt-v4 pairs s = θ/π with ∇(φ/2π). At p = (.3,.4,.5) moving along +z changes θ only."""
    tc = SphericalMapping().map(ctx_from(p=[[.3, .4, .5]], dpdx=[[0, 0, 1]]))
    assert abs(float(tc.dsdx[0])) > 0.1          # s = θ/π changes with z
    assert abs(float(tc.dtdx[0])) < 1e-7         # t = φ/2π does not


def test_spherical_near_seam_and_pole(rng):
    # near the φ = 0 seam (y slightly positive) and near the poles (ρ = 1e-2)
    seam = np.array([[1.0, 1e-2, 0.3], [2.0, 5e-3, -0.7]])
    pole = np.array([[1e-2, 0.0, 1.0], [0.0, -1e-2, -2.0], [7e-3, 7e-3, 0.5]])
    dirs = np.array([[0.1, 0.2, 0.3], [-0.2, 0.1, 0.05]])
    check_fd(SphericalMapping(), seam, dirs, h=1e-4, rtol=5e-3, atol=1e-3)
    check_fd(SphericalMapping(), pole, np.array([[1e-3, 0, 1], [0, 0, 1], [1, 0, 0.2]]),
             h=1e-5, rtol=2e-2, atol=5e-2)


def test_spherical_phi_starts_at_zero_on_the_positive_x_half_plane():
    """φ ∈ [0, 2π): points with y = 0, x > 0 have t = 0 exactly (not 1), just below them
    t → 1, just above t → 0."""
    p = np.array([[1.0, 0.0, 0.3], [2.0, 0.0, -1.0], [1.0, -1e-4, 0.0], [1.0, 1e-4, 0.0]])
    t = st_of(SphericalMapping(), p)[:, 1]
    assert t[0] == 0.0 and t[1] == 0.0
    assert t[2] == pytest.approx(1.0, abs=1e-4) and t[3] == pytest.approx(0.0, abs=1e-4)


def test_spherical_finite_at_poles_and_origin():
    p = np.array([[0, 0, 1.0], [0, 0, -3.0], [0, 0, 0.0]])
    tc = SphericalMapping().map(ctx_from(p=p, dpdx=np.ones((3, 3)), dpdy=np.ones((3, 3))))
    for a in (tc.st, tc.dsdx, tc.dsdy, tc.dtdx, tc.dtdy):
        assert np.isfinite(A(a)).all()
    # the documented values (mapping.py, deviation 4): where ∇θ or ∇φ is undefined the terms
    # are 0 — at the poles and the origin every derivative is 0; θ = 0, π at the poles
    for a in (tc.dsdx, tc.dsdy, tc.dtdx, tc.dtdy):
        np.testing.assert_array_equal(A(a), 0.0)
    np.testing.assert_allclose(A(tc.st), [[0, 0], [1, 0], [0, 0]], atol=1e-7)
    cyl = CylindricalMapping().map(ctx_from(p=p, dpdx=np.ones((3, 3)), dpdy=np.ones((3, 3))))
    np.testing.assert_array_equal(A(cyl.dsdx), 0.0)
    np.testing.assert_array_equal(A(cyl.dtdx), 1.0)


def test_uv_mapping_defaults_are_identity(rng):
    uv = rng.uniform(-1, 2, (8, 2))
    duv = rng.normal(size=(8, 4))
    tc = UVMapping().map(ctx_from(uv=uv, duv=duv))
    np.testing.assert_allclose(A(tc.st), uv, atol=1e-7)
    np.testing.assert_allclose(np.stack([A(tc.dsdx), A(tc.dsdy), A(tc.dtdx), A(tc.dtdy)], 1), duv,
                               atol=1e-7)


def test_spherical_uses_inverse_of_to_world(rng):
    to_world = mi.ScalarTransform4f().translate([1, 2, 3]) @ mi.ScalarTransform4f().scale(2.0)
    p_tex = random_points(rng, 20)
    p_world = p_tex * 2.0 + np.array([1, 2, 3])
    np.testing.assert_allclose(st_of(SphericalMapping(to_world), p_world), spherical_st(p_tex),
                               atol=5e-6)
    check_fd(SphericalMapping(to_world), p_world, rng.normal(size=p_world.shape), h=1e-3)


# ---------------------------------------------------------------------------------------- cylindrical
def test_cylindrical_formula_and_derivatives(rng):
    p = random_points(rng, 200)
    want = np.stack([(math.pi + np.arctan2(p[:, 1], p[:, 0])) / (2 * math.pi), p[:, 2]], 1)
    np.testing.assert_allclose(st_of(CylindricalMapping(), p), want, atol=2e-6)
    check_fd(CylindricalMapping(), p, rng.normal(size=p.shape), h=1e-3)


def test_cylindrical_uses_inverse_of_to_world(rng):
    """A rotation that moves the cylinder's axis and a translation: (s, t) are the formula at
    the texture-space point (inverse transform, numpy), derivatives as central differences."""
    to_world = mi.ScalarTransform4f().translate([0.5, -1, 2]) @ mi.ScalarTransform4f().rotate([1, 0, 0], 70)
    p = random_points(rng, 100)
    inv = np.array(to_world.inverse().matrix)
    pt = p @ inv[:3, :3].T + inv[:3, 3]
    keep = np.hypot(pt[:, 0], pt[:, 1]) > 0.2                    # away from the axis
    want = np.stack([(math.pi + np.arctan2(pt[:, 1], pt[:, 0])) / (2 * math.pi), pt[:, 2]], 1)
    np.testing.assert_allclose(st_of(CylindricalMapping(to_world), p)[keep], want[keep], atol=5e-6)
    check_fd(CylindricalMapping(to_world), p[keep], rng.normal(size=p[keep].shape), h=1e-3)


def test_cylindrical_near_seam_and_axis():
    # the seam is at atan2 = ±π (x < 0, y ≈ 0): pbrt-v3 fixed the wrong component there
    seam = np.array([[-1.0, 1e-2, 0.3], [-2.0, -5e-3, 1.7]])
    check_fd(CylindricalMapping(), seam, np.array([[0.1, 0.2, 0.3], [0.3, -0.1, 1.0]]), h=1e-4,
             rtol=5e-3, atol=1e-3)
    axis = np.array([[0.0, 0.0, 1.0]])
    tc = CylindricalMapping().map(ctx_from(p=axis, dpdx=np.ones((1, 3))))
    assert np.isfinite(A(tc.dsdx)).all() and np.isfinite(A(tc.st)).all()
    assert float(tc.dtdx[0]) == pytest.approx(1.0)


# ---------------------------------------------------------------------------------------- planar / 3D
def test_planar_formula_and_derivatives(rng):
    to_world = mi.ScalarTransform4f().rotate([1, 1, 0], 40).translate([0.5, 0, -1])
    v1, v2 = [1.0, 0.5, 0.0], [0.0, 0.3, 2.0]
    m = PlanarMapping(v1, v2, 0.25, -0.75, to_world)
    p = rng.normal(size=(50, 3))
    inv = np.array(to_world.inverse().matrix)
    p_tex = p @ inv[:3, :3].T + inv[:3, 3]
    want = np.stack([0.25 + p_tex @ v1, -0.75 + p_tex @ v2], 1)
    np.testing.assert_allclose(st_of(m, p), want, atol=1e-5)
    check_fd(m, p, rng.normal(size=p.shape), h=1e-2, rtol=1e-3, atol=1e-4)


def test_planar_defaults_have_no_offset(rng):
    """``PlanarMapping(v1, v2)`` without offsets: s = v1·p, t = v2·p exactly (float32)."""
    p = rng.normal(size=(10, 3))
    want = np.stack([p @ [1.0, 2.0, 0.0], p @ [0.0, -1.0, 0.5]], 1)
    np.testing.assert_allclose(st_of(PlanarMapping([1, 2, 0], [0, -1, 0.5]), p), want, atol=1e-5)


def test_point_transform_mapping(rng):
    to_world = mi.ScalarTransform4f().scale([2, 1, 0.5]).translate([1, 0, 0])
    m = PointTransformMapping(to_world)
    p = rng.normal(size=(20, 3))
    d = rng.normal(size=(20, 3))
    tc = m.map(ctx_from(p=p, dpdx=d, dpdy=2 * d))
    inv = np.array(to_world.inverse().matrix)
    np.testing.assert_allclose(A(tc.p), p @ inv[:3, :3].T + inv[:3, 3], atol=1e-5)
    np.testing.assert_allclose(A(tc.dpdx), d @ inv[:3, :3].T, atol=1e-5)
    np.testing.assert_allclose(A(tc.dpdy), 2 * d @ inv[:3, :3].T, atol=1e-5)


# ---------------------------------------------------------------------------------------- via plugins
@pytest.mark.parametrize('mapping', ['uv', 'spherical', 'cylindrical', 'planar'])
def test_pbrt_uv_plugin_shows_mapped_coordinates(mapping, rng):
    n = 100
    p = random_points(rng, n)
    uv = rng.uniform(-3, 3, (n, 2))
    si = make_si(uv, p=p)
    tex = mi.load_dict({'type': 'pbrt_uv', 'mapping': mapping})
    got = A(tex.eval_3(si))
    if mapping == 'uv':
        st = uv
    elif mapping == 'spherical':
        st = spherical_st(p)
    elif mapping == 'cylindrical':
        st = np.stack([(math.pi + np.arctan2(p[:, 1], p[:, 0])) / (2 * math.pi), p[:, 2]], 1)
    else:
        st = p[:, :2]
    want = st - np.floor(st)
    # frac() jumps at integers: skip lanes within float precision of one
    ok = (np.abs(want - np.round(want)) > 1e-4).all(axis=1)
    np.testing.assert_allclose(got[ok, :2], want[ok], atol=1e-5)
    assert np.all(got[:, 2] == 0)


def test_parameters_of_other_mappings_are_errors():
    with pytest.raises(RuntimeError, match=r'pbrt_uv: parameter "uscale": does not apply to mapping "spherical"'):
        mi.load_dict({'type': 'pbrt_uv', 'mapping': 'spherical', 'uscale': 2.0})
    with pytest.raises(RuntimeError, match=r'pbrt_bilerp: parameter "v1": does not apply to mapping "uv"'):
        mi.load_dict({'type': 'pbrt_bilerp', 'v1': mi.ScalarVector3f(1, 0, 0)})


def test_unknown_mapping_names_plugin_parameter_and_choices():
    with pytest.raises(RuntimeError) as e:
        mi.load_dict({'type': 'pbrt_uv', 'mapping': 'sphere'})
    msg = str(e.value)
    assert 'pbrt_uv' in msg and '"mapping"' in msg and '"sphere"' in msg
    assert 'uv, spherical, cylindrical, planar' in msg


# ---------------------------------------------------------------------------------------- plugins
def test_mapping_parameters_reach_the_mapping_through_plugins(rng):
    """The factory (``mapping_2d``) as plugins use it: ``to_uv`` on a plugin is applied (pbrt_uv
    shows the fractional part of (s, t) = S·to_uv·(u, v) + d, formula in numpy), ``to_world`` is
    accepted by spherical, cylindrical and planar and applied (texture space moved and scaled
    3×: the formulas at (p - t)/3; planar with its v1, v2 and offsets), and the plugin's
    description names the values it was given. 1e-5: float32
    (s, t) of magnitude ≤ 5."""
    T = mi.ScalarTransform4f
    to_uv = T().translate([0.25, -0.5, 0]) @ T().scale([2.0, 3.0, 1])
    tex = mi.load_dict({'type': 'pbrt_uv', 'uscale': 2.0, 'vscale': 0.5, 'udelta': 0.125,
                        'vdelta': 0.5, 'to_uv': to_uv})
    uv = rng.uniform(0, 1, (16, 2))
    got = A(tex.eval(make_si(uv)))[:, :2]
    want = np.stack([2.0 * (2.0 * uv[:, 0] + 0.25) + 0.125, 0.5 * (3.0 * uv[:, 1] - 0.5) + 0.5], 1)
    np.testing.assert_allclose(got, np.mod(want, 1.0), atol=1e-5)
    assert 'uv(uscale=2, vscale=0.5, udelta=0.125, vdelta=0.5, to_uv=custom)' in str(tex)
    assert 'to_uv' not in str(mi.load_dict({'type': 'pbrt_uv'}))
    p = rng.normal(size=(16, 3))
    to_world = T().translate([0.5, -0.25, 0.75]) @ T().scale(3.0)
    planar = {'v1': mi.ScalarVector3f(1, 0.5, 0), 'v2': mi.ScalarVector3f(0, -0.5, 2),
              'udelta': 0.25, 'vdelta': -0.125}
    for kind in ('spherical', 'cylindrical', 'planar'):
        t = mi.load_dict({'type': 'pbrt_uv', 'mapping': kind, 'to_world': to_world,
                          **(planar if kind == 'planar' else {})})
        assert f'mapping={kind}' in str(t)
        st = A(t.eval(make_si(p[:, :2], p=p)))[:, :2]
        pt = (p - [0.5, -0.25, 0.75]) / 3.0
        if kind == 'planar':
            want = np.stack([0.25 + pt @ [1, 0.5, 0], -0.125 + pt @ [0, -0.5, 2]], 1)
        elif kind == 'cylindrical':
            want = np.stack([(math.pi + np.arctan2(pt[:, 1], pt[:, 0])) / (2 * math.pi), pt[:, 2]], 1)
        else:
            want = spherical_st(pt)
        np.testing.assert_allclose(st, np.mod(want, 1.0), atol=1e-5)


@pytest.mark.parametrize('kind,param,value,allowed', [
    ('spherical', 'to_uv', mi.ScalarTransform4f().scale(2.0), 'to_world'),
    ('uv', 'to_world', mi.ScalarTransform4f().scale(2.0), 'uscale, vscale, to_uv, udelta, vdelta'),
    ('planar', 'uscale', 2.0, 'v1, v2, udelta, vdelta, to_world'),
    ('cylindrical', 'v2', mi.ScalarVector3f(0, 1, 0), 'to_world')])
def test_parameters_of_another_mapping_are_errors_listing_the_right_ones(kind, param, value,
                                                                          allowed):
    with pytest.raises(RuntimeError) as e:
        mi.load_dict({'type': 'pbrt_uv', 'mapping': kind, param: value})
    msg = str(e.value)
    assert f'parameter "{param}": does not apply to mapping "{kind}"' in msg
    assert f'parameters of "{kind}": {allowed}' in msg
