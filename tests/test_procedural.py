"""Procedural and noise textures (pbrt 10.5, 10.6) against independent numpy implementations and
numerical integration; the supersampling wrapper; hard cases."""

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import reference_noise as rn
from conftest import A, make_si, numpy_reference
from mitsuba_pbrt_tex import noise as noise_lib
from mitsuba_pbrt_tex import registry

LUM = np.array([0.212671, 0.715160, 0.072169])


def solid_si(p, dpdx, dpdy):
    """Lookups on the z = const plane with dp_du = x, dp_dv = y, so dp/dx = duv/dx (in xy)."""
    return make_si(p[:, :2], duv_dx=dpdx[:, :2], duv_dy=dpdy[:, :2], p=p,
                   dp_du=[1, 0, 0], dp_dv=[0, 1, 0], n=[0, 0, 1])


def footprints(rng, n, lo=1e-4, hi=10.0):
    """In-plane differentials of log-uniform length, random directions (z component 0)."""
    out = []
    for _ in range(2):
        ang = rng.uniform(0, 2 * math.pi, n)
        length = np.exp(rng.uniform(math.log(lo), math.log(hi), n))
        out.append(np.stack([np.cos(ang) * length, np.sin(ang) * length, np.zeros(n)], 1))
    return out


def f32(a):
    return np.asarray(a, np.float32).astype(np.float64)


# ------------------------------------------------------------------------------------ noise
def test_perlin_noise_matches_reference(rng):
    p = f32(rng.uniform(-300, 300, (20000, 3)))
    p[:100] = np.round(p[:100])                          # lattice points (noise is 0 there)
    p[100:200, 0] = np.floor(p[100:200, 0]) + 1e-3      # next to lattice planes
    got = A(noise_lib.noise(mi.Point3f(p[:, 0], p[:, 1], p[:, 2])))
    want = rn.noise3(p)
    assert np.max(np.abs(got - want)) <= 1e-5
    assert np.max(np.abs(got[:100])) <= 1e-6


def test_perlin_noise_far_and_non_finite_coordinates(rng):
    """pbrt-v4 reduces each coordinate with C's fmod(x, 2^30) (keeping the sign) before the
    lattice arithmetic: noise at ±(k·2^30 + r) equals noise at ±r (r = 768 or 384, exactly
    representable at those magnitudes in float32; without the reduction the lattice index of
    2^30 + 384 would overflow int32 differently); a non-finite coordinate is replaced by 0
    (the package's guard) — compared exactly, same float32 operations after the reduction."""
    n = 20
    yz = f32(rng.uniform(-5, 5, (n, 2)))
    P = lambda x: mi.Point3f(mi.Float(x), mi.Float(yz[:, 0]), mi.Float(yz[:, 1]))
    for big, small in ((3 * 2.0 ** 30 + 768, 768.0), (-(3 * 2.0 ** 30 + 768), -768.0),
                       (2.0 ** 30 + 384, 384.0)):
        assert np.fmod(big, 2.0 ** 30) == small and float(np.float32(big)) == big
        np.testing.assert_array_equal(A(noise_lib.noise(P(np.full(n, big)))),
                                      A(noise_lib.noise(P(np.full(n, small)))))
    for bad in (np.nan, np.inf, -np.inf):
        np.testing.assert_array_equal(A(noise_lib.noise(P(np.full(n, bad)))),
                                      A(noise_lib.noise(P(np.zeros(n)))))


@pytest.mark.parametrize('kind', ['fbm', 'turbulence'])
@pytest.mark.parametrize('omega,octaves', [(0.5, 8), (0.8, 5), (0.3, 12)])
def test_fbm_and_turbulence_match_reference(kind, omega, octaves, rng):
    n = 400
    p = f32(rng.uniform(-20, 20, (n, 3)))
    dpdx, dpdy = footprints(rng, n)
    dpdx[:20] = dpdy[:20] = 0                            # all octaves
    dpdx[20:40] = [np.inf, 0, 0]                         # none (inf differentials)
    # exact octave boundaries: len² = 2^-(2k+2) gives n = k
    k = np.arange(40) % octaves
    dpdx[40:80] = np.stack([2.0 ** -(k + 1), np.zeros(40), np.zeros(40)], 1)
    dpdy[40:80] = 0
    fn = noise_lib.fbm if kind == 'fbm' else noise_lib.turbulence
    ref = rn.fbm if kind == 'fbm' else rn.turbulence
    V = lambda a: mi.Vector3f(a[:, 0], a[:, 1], a[:, 2])
    got = A(fn(mi.Point3f(p[:, 0], p[:, 1], p[:, 2]), V(dpdx), V(dpdy), omega, octaves))
    want = ref(p, dpdx, dpdy, omega, octaves)
    assert np.max(np.abs(got - want)) <= 1e-5
    assert np.all(np.isfinite(got))


@pytest.mark.parametrize('omega,octaves', [(1.0, 8), (2.0, 8), (1e10, 3)])
def test_turbulence_with_roughness_one_and_above(omega, octaves, rng):
    """ω = 1 (the clamped octaves' geometric series degenerates to k terms), ω = 2 and the
    largest ω a 3-octave texture accepts: the reference sums the clamped octaves' 0.2·ωⁱ one by
    one. 1e-5 relative to the largest value (sums of up to 8 terms growing as ωⁱ). Most lanes
    resolve every octave with 3 octaves: the empty series must be exactly 0 there (dr.power(ω, 1)
    is not exactly ω, and times ω³ that gave 2e29 against values below 1e21)."""
    n = 200
    p = f32(rng.uniform(-20, 20, (n, 3)))
    dpdx, dpdy = footprints(rng, n, lo=1e-3, hi=1.0)
    V = lambda a: mi.Vector3f(a[:, 0], a[:, 1], a[:, 2])
    got = A(noise_lib.turbulence(mi.Point3f(p[:, 0], p[:, 1], p[:, 2]), V(dpdx), V(dpdy), omega,
                                 octaves))
    want = rn.turbulence(p, dpdx, dpdy, omega, octaves)
    np.testing.assert_allclose(got, want, atol=1e-5 * np.abs(want).max())


@pytest.mark.parametrize('octaves,omega', [(8, 0.5), (5, 0.8)])
def test_wrinkled_clamping_replaces_octaves_by_their_mean(octaves, omega, rng):
    """Clamping replaces the octaves finer than the footprint by their mean, so it must not move
    the texture's average. pbrt's Turbulence counts octave floor(n) twice (spec bug 10; found in
    a user trial: with pbrt's defaults the clamped mean was 0.598 against 0.434 with all
    octaves); we deviate (README "Deviations from pbrt").

    Over N = 10⁵ random points, (clamped − all octaves) averages Σ_clamped wᵢ·(0.2 − |Noiseᵢ|)
    — pbrt's constant 0.2 against the measured mean μ of |Noise| (independent numpy reference,
    2·10⁵ other points) — whose expectation is −(μ − 0.2)·W, W the clamped octaves' weight
    ((1 − s)·ω^⌊n⌋ for the partial octave, s its smoothstep, plus ωⁱ for i = ⌊n⌋+1 … octaves−1).
    Tolerance: 5 standard errors of the per-point difference plus 5 of μ (3.5·10⁻⁴) times W, both
    measured: 6·10⁻⁴ – 1·10⁻² here; the deviations seen are below 0.2 of it. pbrt's extra
    0.2·ω^⌊n⌋ is 20–40 times the tolerance (the mean moved by +0.16 for 8 octaves at n = 0)."""
    N = 100_000
    p = f32(rng.uniform(-128, 128, (N, 3)))
    q = rng.uniform(-128, 128, (200_000, 3))
    a = np.abs(rn.noise3(q))
    mu, mu_se = a.mean(), a.std() / math.sqrt(len(a))
    assert 0.2 < mu < 0.23                               # 0.218: pbrt's 0.2 is 8% low
    zero = np.zeros((N, 3))
    full = A(mi.load_dict({'type': 'pbrt_wrinkled', 'aamode': 'none', 'octaves': octaves,
                           'roughness': omega}).eval_1(solid_si(p, zero, zero)))
    tex = mi.load_dict({'type': 'pbrt_wrinkled', 'octaves': octaves, 'roughness': omega})
    for n in (0.0, 0.5, 1.0, 1.6, 2.0, 3.0, 3.45):
        length = 2.0 ** (-1 - n)                         # n = -1 - log2(length)
        dpdx, dpdy = np.tile([length, 0, 0], (N, 1)), np.tile([0, length, 0], (N, 1))
        clamped = A(tex.eval_1(solid_si(p, dpdx, dpdy)))
        n_int = math.floor(n)
        s = rn.smoothstep(.3, .7, n - n_int)
        weight = (1 - s) * omega ** n_int + sum(omega ** i for i in range(n_int + 1, octaves))
        diff = clamped - full
        tol = 5 * diff.std() / math.sqrt(N) + 5 * mu_se * weight
        assert abs(diff.mean() + (mu - 0.2) * weight) <= tol, (n, diff.mean(), weight, tol)


def test_noise_nan_footprint_is_a_point_sample(rng):
    """NaN differentials (both) count as a zero footprint — every octave — like pbrt-v4's
    sanitised partials elsewhere (non-finite → 0); pbrt itself leaves this undefined."""
    n = 50
    p = f32(rng.uniform(-20, 20, (n, 3)))
    V = lambda a: mi.Vector3f(a[:, 0], a[:, 1], a[:, 2])
    P = mi.Point3f(p[:, 0], p[:, 1], p[:, 2])
    nan = V(np.full((n, 3), np.nan))
    zero = V(np.zeros((n, 3)))
    for fn in (noise_lib.fbm, noise_lib.turbulence):
        np.testing.assert_array_equal(A(fn(P, nan, nan, 0.5, 8)), A(fn(P, zero, zero, 0.5, 8)))


@pytest.mark.parametrize('name', ['pbrt_fbm', 'pbrt_wrinkled', 'pbrt_windy', 'pbrt_marble'])
@pytest.mark.parametrize('aamode', ['clamp', 'none'])
def test_noise_plugins_match_reference(name, aamode, rng):
    n = 300
    p = f32(rng.uniform(-10, 10, (n, 3)))
    p[:, 2] = f32(np.full(n, 0.37))
    dpdx, dpdy = footprints(rng, n, 1e-3, 3.0)
    dpdx, dpdy = f32(dpdx), f32(dpdy)
    dpdx[:10] = dpdy[:10] = 0
    params = {'type': name, 'aamode': aamode}
    if name == 'pbrt_marble':
        params.update(scale=2.0, variation=0.4, octaves=6, roughness=0.6)
    tex = mi.load_dict(params)
    si = solid_si(p, dpdx, dpdy)
    aa = aamode == 'clamp'
    if name == 'pbrt_fbm':
        want = rn.fbm(p, dpdx, dpdy, 0.5, 8, aa)
    elif name == 'pbrt_wrinkled':
        want = rn.turbulence(p, dpdx, dpdy, 0.5, 8, aa)
    elif name == 'pbrt_windy':
        want = rn.windy(p, dpdx, dpdy, aa)
    else:
        want = rn.marble(p, dpdx, dpdy, 6, 0.6, 2.0, 0.4, aa)
    if name == 'pbrt_marble':
        np.testing.assert_allclose(A(tex.eval_3(si)), want, atol=1e-5)
        np.testing.assert_allclose(A(tex.eval_1(si)), want @ LUM, atol=1e-5)
    else:
        np.testing.assert_allclose(A(tex.eval_1(si)), want, atol=1e-5)
        np.testing.assert_allclose(A(tex.eval(si)), np.repeat(want[:, None], 3, 1), atol=1e-5)


def test_marble_sine_is_exact_where_float32_allows_and_finite_beyond(rng):
    """Dr.Jit's float32 sin leaves [-1, 1] beyond |x| ~ 1e5 (-185763 at 3.3e8, NaN at 1e20);
    marble reduces the argument by whole periods first. Reference: math.sin of the same float32
    argument (libm reduces exactly). Bounds: float32 rounding of the sine (1.2e-7) and of the
    reduced argument, which grows with |x|/2^24 periods — measured 1.4e-7 up to 1e5, 3.5e-7 at
    1e8, 4e-6 at 1e9. Beyond, values stay finite and in [-1, 1] (0 for non-finite arguments);
    marble's colours then stay on its spline (1.5 × [0.2, 0.6]) at scales up to 1e30."""
    sin = registry.plugin_module('pbrt_marble')._sin
    for mag, tol in ((1e2, 3e-7), (1e5, 3e-7), (1e8, 1e-6), (1e9, 1e-5)):
        x = f32(rng.uniform(-mag, mag, 2000))
        want = np.array([math.sin(float(v)) for v in x])
        np.testing.assert_allclose(A(sin(mi.Float(x))), want, atol=tol, err_msg=str(mag))
    # (the first two: reduced, Dr.Jit's sine is still -2.3e11 and 1.8e7 there)
    wild = A(sin(mi.Float(f32([2.2511141e16, -1.6923679e16, 1e10, 1e20, 3.4e38]))))
    assert np.all(np.abs(wild) <= 1), wild
    np.testing.assert_array_equal(A(sin(mi.Float(f32([np.inf, -np.inf, np.nan])))), 0)
    p = f32(rng.uniform(-3, 3, (200, 3)))
    for scale in (1e8, 1e10, 1e20, 1e30):
        v = A(mi.load_dict({'type': 'pbrt_marble', 'scale': scale}).eval(
            solid_si(p, np.zeros((200, 3)), np.zeros((200, 3)))))
        assert np.all(v >= 1.5 * 0.2 - 1e-6) and np.all(v <= 1.5 * 0.6 + 1e-6), (scale, v.min(),
                                                                                 v.max())


@pytest.mark.parametrize('with_differentials', [False, True])
def test_bump_gradient_is_pbrts_forward_difference(with_differentials, rng):
    """eval_1_grad (what Mitsuba's bumpmap reads) of a procedural texture is pbrt-v4's BumpMap
    difference: (f(p + du·dp/du) - f(p)) / du, du = (|du/dx| + |du/dy|)/2 or 0.0005 without
    differentials (likewise v). Reference: the numpy FBm at the same float32 points. Bound: the
    shifted points' float32 rounding (p ≤ 10: 1e-6) over du, and the noise's (1e-6) over du."""
    n = 300
    p = f32(rng.uniform(-10, 10, (n, 3)))
    p[:, 2] = 0.37
    if with_differentials:
        dx, dy = footprints(rng, n, 1e-3, 1e-1)
    else:
        dx = dy = np.zeros((n, 3))
    tex = mi.load_dict({'type': 'pbrt_fbm', 'aamode': 'none'})
    got = A(tex.eval_1_grad(solid_si(p, dx, dy)))
    zero = np.zeros((n, 3))
    f = rn.fbm(p, zero, zero, 0.5, 8, False)
    for axis in (0, 1):
        d = 0.5 * (np.abs(f32(dx)[:, axis]) + np.abs(f32(dy)[:, axis]))
        d = np.where(d > 0, d, 0.0005).astype(np.float32)
        moved = p.copy()
        moved[:, axis] = (p[:, axis].astype(np.float32) + d).astype(np.float64)
        want = (rn.fbm(moved, zero, zero, 0.5, 8, False) - f) / d
        np.testing.assert_allclose(got[:, axis], want, atol=4e-6 / d.min() + 1e-4)


def test_bump_gradient_of_a_bilinear_patch_is_its_slope():
    """pbrt_bilerp is linear in u (and in v): the forward difference is its exact slope,
    (1-v)(v10-v00) + v(v11-v01) — up to float32 rounding of values ~0.5 over du = 0.0005."""
    uv = np.array([[0.1, 0.2], [0.5, 0.5], [0.9, 0.3], [0.25, 0.8]])
    tex = mi.load_dict({'type': 'pbrt_bilerp', 'v00': 0.1, 'v10': 0.9, 'v01': 0.5, 'v11': 0.2})
    got = A(tex.eval_1_grad(make_si(uv, dp_du=[1, 0, 0], dp_dv=[0, 1, 0])))
    u, v = uv[:, 0], uv[:, 1]
    want = np.stack([(1 - v) * (0.9 - 0.1) + v * (0.2 - 0.5),
                     (1 - u) * (0.5 - 0.1) + u * (0.2 - 0.9)], 1)
    np.testing.assert_allclose(got, want, atol=5e-4)


def test_bumpmap_of_procedural_textures_renders():
    """Mitsuba's bumpmap over pbrt's procedurals (pbrt's classic bump-mapped wrinkles): a
    finite image that differs from the unbumped one; a constant bumps nothing. A checkerboard
    bumps only where its filtered edges have a slope: under pbrt_path (differentials: du of a
    pixel), not under path (du = 0.0005, the edges' steps fall between the pixels' hits)."""
    def render(nested, integrator='path'):
        bsdf = {'type': 'diffuse'} if nested is None else {
            'type': 'bumpmap', 'arbitrary': nested, 'bsdf': {'type': 'diffuse'}}
        scene = mi.load_dict({
            'type': 'scene', 'integrator': {'type': integrator},
            'sensor': {'type': 'perspective', 'fov': 40,
                       'to_world': mi.ScalarTransform4f().look_at([0, -2.5, 2.5], [0, 0, 0],
                                                                  [0, 0, 1]),
                       'film': {'type': 'hdrfilm', 'width': 24, 'height': 24,
                                'rfilter': {'type': 'box'}}},
            'obj': {'type': 'rectangle', 'bsdf': bsdf},
            'sun': {'type': 'directional', 'direction': [0.3, 0.2, -1], 'irradiance': 2.0}})
        return np.array(mi.render(scene, spp=4, seed=1))
    flat = render(None)
    checker = {'type': 'pbrt_checkerboard', 'aamode': 'box', 'uscale': 4, 'vscale': 4}
    for nested, integrator in (({'type': 'pbrt_wrinkled',
                                 'to_world': mi.ScalarTransform4f().scale(0.2)}, 'path'),
                               ({'type': 'pbrt_fbm'}, 'path'), ({'type': 'pbrt_marble'}, 'path'),
                               (checker, 'pbrt_path')):
        img = render(nested, integrator)
        assert np.isfinite(img).all(), nested
        assert np.abs(img - flat).max() > 1e-3, nested
    np.testing.assert_allclose(render({'type': 'pbrt_constant', 'value': 0.5}), flat, atol=1e-6)


def test_noise_texture_uses_to_world(rng):
    n = 100
    p = f32(rng.uniform(-3, 3, (n, 3)))
    to_world = mi.ScalarTransform4f().scale(0.25)        # texture space = 4 × world
    tex = mi.load_dict({'type': 'pbrt_fbm', 'to_world': to_world, 'aamode': 'none'})
    got = A(tex.eval_1(solid_si(p, np.zeros((n, 3)), np.zeros((n, 3)))))
    want = rn.fbm(f32(p.astype(np.float32) * np.float32(4)), np.zeros((n, 3)), np.zeros((n, 3)), .5, 8)
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_clamping_reduces_variance_at_distance(rng):
    """With a footprint of 2 noise periods, clamping leaves ~no octave (value ≈ 0), all-octave
    noise keeps its full variance: the clamp is doing its job."""
    n = 2000
    p = f32(rng.uniform(-50, 50, (n, 3)))
    d = np.tile([2.0, 0, 0], (n, 1))
    clamp = A(mi.load_dict({'type': 'pbrt_fbm'}).eval_1(solid_si(p, d, d)))
    full = A(mi.load_dict({'type': 'pbrt_fbm', 'aamode': 'none'}).eval_1(solid_si(p, d, d)))
    assert clamp.std() < 0.01 < 0.1 < full.std()


# ------------------------------------------------------------------------------------ dots
FROZEN_NOISE_SCRIPT = """
import numpy as np, drjit as dr, mitsuba as mi, mitsuba_pbrt_tex
mi.set_variant('llvm_ad_rgb'); mitsuba_pbrt_tex.register()
T = mi.ScalarTransform4f
for name in ('pbrt_dots', 'pbrt_fbm', 'pbrt_wrinkled', 'pbrt_windy', 'pbrt_marble'):
    scene = mi.load_dict({'type': 'scene', 'integrator': {'type': 'pbrt_path', 'max_depth': 2},
        'sensor': {'type': 'perspective', 'to_world': T().look_at([0, 2, 2.5], [0, 0, 0], [0, 1, 0]),
                   'film': {'type': 'hdrfilm', 'width': 16, 'height': 16}},
        'floor': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90),
                  'bsdf': {'type': 'diffuse', 'reflectance': {'type': name}}},
        'light': {'type': 'constant'}})
    frozen = dr.freeze(lambda scene, seed: mi.render(scene, spp=2, seed=seed))
    for seed in range(5):
        got = np.array(frozen(scene, mi.UInt32(seed)))
        want = np.array(mi.render(scene, spp=2, seed=mi.UInt32(seed)))
        assert np.abs(got - want).max() <= 1e-6 * np.abs(want).max(), name
    assert frozen.n_recordings < 5, name           # (Dr.Jit records up to 3 times)
print('ok')
"""


def test_noise_textures_render_inside_frozen_functions():
    """A render inside dr.freeze of every noise texture replays equal to the unfrozen render
    (float32 rounding; five calls, some replayed). Their tables were copied from the host at each lookup, which a frozen
    function cannot record: the process aborted (found in a user trial), hence a process of its
    own here."""
    import subprocess
    import sys
    r = subprocess.run([sys.executable, '-c', FROZEN_NOISE_SCRIPT], capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0 and r.stdout.strip().endswith('ok'), r.stdout + r.stderr[-2000:]


def test_dots_match_reference(rng):
    n = 5000
    uv = f32(rng.uniform(-20, 20, (n, 2)))
    tex = mi.load_dict({'type': 'pbrt_dots', 'inside': {'type': 'rgb', 'value': [1, 0, 0]},
                        'outside': 0.25})
    got = A(tex.eval(make_si(uv)))
    inside = rn.in_dot(uv[:, 0], uv[:, 1])
    want = np.where(inside[:, None], [1, 0, 0], [0.25, 0.25, 0.25])
    # a lookup within float rounding of a dot's rim may fall either way
    assert np.mean(np.all(np.abs(got - want) < 1e-6, axis=1)) > 0.999
    assert 0.1 < inside.mean() < 0.3


# ------------------------------------------------------------------------------------ checkerboard
def _odd(x):
    return np.floor(x) % 2


def _axis_expectation(x, r, kernel, samples=200001):
    """E[c(x + u)] of the square wave c = ±1 under the kernel (numerical midpoint quadrature)."""
    if r == 0:
        return 1 - 2 * _odd(x)
    u = (np.arange(samples) + 0.5) / samples * 2 - 1          # in units of r, [-1, 1]
    w = np.ones_like(u) if kernel == 'box' else 1 - np.abs(u)
    c = 1 - 2 * _odd(x + r * u)
    return float((w * c).sum() / w.sum())


def checker_reference(coords, widths, kernel):
    """Weight of tex2 by quadrature: the separable kernel makes E[Π c] = Π E[c]."""
    prod = 1.0
    for x, r in zip(coords, widths):
        prod *= _axis_expectation(x, r if kernel == 'box' else 1.5 * r, kernel)
    return 0.5 - 0.5 * prod


def checker_references(coords, widths, triangle):
    """``checker_reference`` of each lane (rows of ``coords``, ``widths``)."""
    kernel = 'triangle' if triangle else 'box'
    return [checker_reference(x, r, kernel) for x, r in zip(coords, widths)]


@pytest.mark.parametrize('aamode', ['box', 'closedform', 'triangle'])
@pytest.mark.parametrize('dimension', [2, 3])
def test_checkerboard_against_quadrature(aamode, dimension, rng):
    n = 150
    p = f32(rng.uniform(-5, 5, (n, 3)))
    dpdx, dpdy = footprints(rng, n, 1e-3, 0.6)
    dpdx, dpdy = f32(dpdx), f32(dpdy)
    dpdx[:10, 1] = 0                                  # one axis of zero width (pbrt-v3 NaN case)
    dpdy[:10, 1] = 0
    tex = mi.load_dict({'type': 'pbrt_checkerboard', 'aamode': aamode, 'dimension': dimension,
                        'tex1': 0.0, 'tex2': 1.0})
    si = solid_si(p, dpdx, dpdy)
    got = A(tex.eval_1(si))
    axes = 2 if dimension == 2 else 3
    widths = np.maximum(np.abs(dpdx[:, :axes]), np.abs(dpdy[:, :axes]))
    want = numpy_reference(checker_references, p[:, :axes], widths, np.array(aamode == 'triangle'))
    assert np.isfinite(got).all()
    np.testing.assert_allclose(got, want, atol=1e-4)


def test_checkerboard_box_wide_footprint_is_half_and_none_is_parity(rng):
    n = 500
    uv = f32(rng.uniform(-10, 10, (n, 2)))
    wide = mi.load_dict({'type': 'pbrt_checkerboard', 'aamode': 'box', 'tex1': 0.0, 'tex2': 1.0})
    got = A(wide.eval_1(make_si(uv, np.tile([1.5, 0], (n, 1)), np.zeros((n, 2)))))
    np.testing.assert_allclose(got, 0.5)
    none = mi.load_dict({'type': 'pbrt_checkerboard', 'aamode': 'none',
                         'tex1': {'type': 'rgb', 'value': [1, 0, 0]}, 'tex2': 0.0})
    out = A(none.eval(make_si(uv, np.full((n, 2), 0.3), np.full((n, 2), 0.3))))
    even = (np.floor(uv[:, 0]) + np.floor(uv[:, 1])) % 2 == 0
    np.testing.assert_allclose(out, np.where(even[:, None], [1, 0, 0], 0.0))


def test_checkerboard_zero_differentials_are_point_samples(rng):
    uv = f32(rng.uniform(-10, 10, (500, 2)))
    even = (np.floor(uv[:, 0]) + np.floor(uv[:, 1])) % 2 == 0
    for aamode in ('none', 'box', 'triangle', 'area'):
        tex = mi.load_dict({'type': 'pbrt_checkerboard', 'aamode': aamode})
        np.testing.assert_allclose(A(tex.eval_1(make_si(uv))), np.where(even, 1.0, 0.0))


def test_checkerboard_box_with_two_edges_in_the_footprint(rng):
    """Box half-widths 0.5–1 (up to two cell edges inside the footprint, the closed form's
    general case) along s, t point-sampled at a cell centre: tex2's weight is (1 - E[c(s)])/2
    with E the exact mean of the square wave, (F(s + r) - F(s - r)) / 2r, F(x) = 1 - |x mod 2
    - 1| its integral. Float32 closed form with r ≥ 1/2: 1e-5."""
    n = 400
    s = f32(rng.uniform(-6, 6, n))
    r = f32(rng.uniform(0.5, 1.0, n))
    F = lambda x: 1 - np.abs(np.mod(x, 2) - 1)
    want = (1 - (F(s + r) - F(s - r)) / (2 * r)) / 2
    tex = mi.load_dict({'type': 'pbrt_checkerboard', 'aamode': 'box', 'tex1': 0.0, 'tex2': 1.0})
    uv = np.stack([s, np.full(n, 0.5)], 1)
    got = A(tex.eval_1(make_si(uv, np.stack([r, np.zeros(n)], 1), np.zeros((n, 2)))))
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_checkerboard_non_finite_coordinates_and_widths_count_as_zero():
    """Non-finite coordinates and footprint widths are replaced by 0 before filtering (NaN
    would otherwise reach the weight): a NaN or infinite s or t lies in the even cell at 0, a
    NaN width is a point sample. Values: tex1 = 1 there, for every AA mode."""
    nan, inf = float('nan'), float('inf')
    uv = np.array([[nan, 0.5], [0.5, inf], [-inf, nan], [0.5, 0.5]])
    d = np.array([[0, 0], [0, 0], [0, 0], [nan, nan]])
    for aamode in ('none', 'box', 'triangle', 'area'):
        tex = mi.load_dict({'type': 'pbrt_checkerboard', 'aamode': aamode})
        np.testing.assert_array_equal(A(tex.eval_1(make_si(uv, d, d))), 1.0)


def checker_area_reference(c, d0, d1):
    """Weight of tex2 averaged over the parallelogram c + a·d0 + b·d1 (a, b ∈ [-1/2, 1/2]) by
    clipping it against every unit cell it touches (float64 polygons, reference_box's cell clipper):
    Σ cells sign·area / total area. Shares nothing with the package's Green's-theorem loop."""
    from reference_box import _area, clipped_cells
    c, d0, d1 = (np.asarray(v, np.float64) for v in (c, d0, d1))
    quad = [c - d0 / 2 - d1 / 2, c + d0 / 2 - d1 / 2, c + d0 / 2 + d1 / 2, c - d0 / 2 + d1 / 2]
    acc = sum((1 if (i + j) % 2 == 0 else -1) * abs(_area(poly))
              for i, j, poly in clipped_cells(quad))
    return 0.5 - 0.5 * acc / abs(_area(quad))


def checker_area_references(c, d0, d1):
    """``checker_area_reference`` of each lane."""
    return [checker_area_reference(*lane) for lane in zip(c, d0, d1)]


def test_checkerboard_area_is_the_exact_parallelogram_average(rng):
    """``aamode="area"``: the average over the footprint parallelogram, against polygon clipping.
    Random orientations, footprints from 1/1000 of a cell to 15 cells across the shorter axis,
    anisotropy up to 64:1, centres up to ±1000 cells away. Tolerance 2e-4: float32 coordinates
    1000 cells out carry 6e-5 of rounding, and the float32 sums over up to 4×17 pieces add a few
    1e-6 relative; a wrong sign, corner or piece moves the average by far more."""
    n = 300
    c = f32(rng.uniform(-1000, 1000, (n, 2)))
    c[:100] = f32(rng.uniform(-4, 4, (100, 2)))
    ang = rng.uniform(0, 2 * math.pi, n)
    minor = np.exp(rng.uniform(math.log(1e-3), math.log(15), n))
    aniso = np.exp(rng.uniform(0, math.log(64), n))
    skew = rng.uniform(-0.4, 0.4, n)
    d0 = np.stack([np.cos(ang), np.sin(ang)], 1) * (minor * aniso)[:, None]
    d1 = np.stack([-np.sin(ang + skew), np.cos(ang + skew)], 1) * minor[:, None]
    d0, d1 = f32(d0), f32(d1)
    swap = rng.random(n) < 0.5                     # both corner orders (signs of the area)
    d0[swap], d1[swap] = d1[swap].copy(), d0[swap].copy()
    tex = mi.load_dict({'type': 'pbrt_checkerboard', 'aamode': 'area', 'tex1': 0.0, 'tex2': 1.0})
    got = A(tex.eval_1(make_si(c, d0, d1)))
    want = numpy_reference(checker_area_references, c, d0, d1)
    # footprints wider than the package's row limit: its Fourier series (the test below)
    from mitsuba_pbrt_tex.checker import AREA_MAX_ROWS
    rows = np.minimum(np.abs(d0[:, 0]) + np.abs(d1[:, 0]), np.abs(d0[:, 1]) + np.abs(d1[:, 1]))
    exact = rows <= AREA_MAX_ROWS * 0.999
    assert exact.sum() > 250
    np.testing.assert_allclose(got[exact], want[exact], atol=2e-4)
    np.testing.assert_allclose(got[~exact], want[~exact], atol=2e-2)


def test_checkerboard_area_beyond_the_walks_rows(rng):
    """Footprints crossing more than 16 cell rows get the checkerboard's Fourier series
    averaged over the parallelogram (odd harmonics up to 7), against polygon clipping. Thin ones
    along a diagonal of the cells, where cells of one colour line up and the average can be
    anywhere in [0, 1], got pbrt-v3's box form, 1/2, before (a user trial: 0.5 for 0.895); also
    along the (1, 3) and (3, 1) directions, and at random ones. Widths 0.05–3 cells across,
    lengths 25–200 cells, and very long ones (10⁸–10³⁰ cells: float32's sin fails there; a
    diagonal strip through (0.3, 0.7) averages 0.4 at any length). Tolerance 0.02 (the series'
    tail for thin footprints along a diagonal, ≤ (4/π²)·Σ_{m ≥ 9} 1/m² ≈ 0.025 in the weight
    for lines; measured ≤ 0.011 from 0.05 cell wide, ≤ 5e-4 at 0.3)."""
    n = 120
    dirs = np.concatenate([np.tile([[1, 1], [1, -1], [1, 3], [3, 1]], (20, 1)),
                           rng.normal(size=(40, 2))]).astype(np.float64)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    length = rng.uniform(25, 200, n)
    width = np.exp(rng.uniform(math.log(0.05), math.log(3), n))
    c = f32(rng.uniform(-50, 50, (n, 2)))
    d0 = f32(dirs * length[:, None])
    d1 = f32(np.stack([-dirs[:, 1], dirs[:, 0]], 1) * width[:, None])
    tex = mi.load_dict({'type': 'pbrt_checkerboard', 'aamode': 'area', 'tex1': 0.0, 'tex2': 1.0})
    got = A(tex.eval_1(make_si(c, d0, d1)))
    want = numpy_reference(checker_area_references, c, d0, d1)
    assert np.abs(np.asarray(want)[:80] - 0.5).max() > 0.3       # far from the box form's 1/2
    np.testing.assert_allclose(got, want, atol=2e-2)
    length = np.array([1e8, 1e10, 1e20, 1e30])
    d0 = f32(np.stack([length, length], 1) / math.sqrt(2))
    d1 = f32(np.tile([[-0.3 / math.sqrt(2), 0.3 / math.sqrt(2)]], (4, 1)))
    far = A(tex.eval_1(make_si(np.tile([[0.3, 0.7]], (4, 1)), d0, d1)))
    np.testing.assert_allclose(far, 0.4, atol=2e-2)                # (tex2 = 1: its weight)


def test_checkerboard_area_on_lattice_aligned_footprints():
    """``aamode="area"`` where the random test never lands: parallelograms whose corners lie on
    cell lines or lattice points, edges exactly one or two cells tall (an edge that ends exactly
    where a row does, in either direction), axis-aligned squares and strips, both corner
    orders, tiny thin slivers across a cell edge, footprints at the row limit — against the
    same polygon clipping. All coordinates are small dyadic numbers, exact in float32:
    tolerance 1e-5 (float32 sums of a few pieces)."""
    cases = [  # centre, d0, d1
        ((0.25, 0.25), (3.0, 0.0), (0.5, 1.0)),      # slanted edges exactly 1 cell tall
        ((0.25, 0.25), (0.5, 1.0), (3.0, 0.0)),      # the same, other corner order
        ((1.5, 0.5), (3.0, 0.0), (0.5, 2.0)),        # 2 cells tall, corners on cell lines
        ((0.5, 0.5), (1.0, 0.0), (0.0, 1.0)),        # one whole cell
        ((1.0, 1.0), (1.0, 0.0), (0.0, 1.0)),        # a cell's worth centred on a lattice point
        ((0.0, 0.5), (2.0, 0.0), (0.0, 1.0)),        # a strip along a row, ends on cell lines
        ((0.75, -0.25), (0.5, -1.0), (2.5, 0.0)),    # edges going down by exactly 1
        ((3.0, 2.0), (1.5, 1.5), (-1.5, 1.5)),       # a diamond with corners on lattice points
        # a sliver 1/1000 of a cell long, 64:1, across a cell edge off-centre: its own (exact)
        # mean, not the box over its bounding square (0.05 apart here)
        ((1 + 2 ** -12, 0.5), (2 ** -10, 2 ** -10), (-2 ** -16, 2 ** -16)),
        # one 2^-22 cell long (area 2^-49), across both axes near the origin: still exact
        # (its area is far above the degeneracy threshold, 1e-12 of its extent squared)
        ((2 ** -26, 2 ** -25), (2 ** -22, 2 ** -22), (-2 ** -28, 2 ** -28)),
        # exactly AREA_MAX_ROWS = 16 rows along the shorter axis: still exact (the box form is
        # 0.25 off): a one-cell-wide strip along the diagonal, mostly on cells of one colour
        ((0.5, 0.5), (16.0, 16.0), (1.0, 0.0)),
        # 16.5 cells along x but 15.5 rows along y, whose edge vectors' x parts nearly cancel:
        # the rows are counted along y (the shorter extent), so it is exact
        ((0.25, 0.5), (15.5, 15.5), (1.0, 0.0)),
    ]
    c, d0, d1 = (np.array([case[k] for case in cases]) for k in range(3))
    tex = mi.load_dict({'type': 'pbrt_checkerboard', 'aamode': 'area', 'tex1': 0.0, 'tex2': 1.0})
    got = A(tex.eval_1(make_si(c, d0, d1)))
    want = checker_area_references(c, d0, d1)
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_checkerboard_area_of_footprints_much_smaller_than_a_cell(rng):
    """``aamode="area"`` on footprints 10⁻⁴ and 10⁻⁵ cells across (a checkerboard magnified
    until a cell covers 10⁴–10⁵ pixels) that straddle a cell edge — near the origin, near an odd
    column, 1000 cells out; anisotropy up to 8 — against polygon clipping. The float32 inputs
    themselves are exact for the reference; what remains is the package's float32 arithmetic,
    whose error grows as the footprint shrinks (~2·10⁻⁸ cell / its width, measured 1.5–2.8e-4
    at 10⁻⁴ and 1.7–2.3e-3 at 10⁻⁵): tolerance 5·10⁻⁸ / width. Computing the footprint's corners
    and S far from the origin, or S as 1 - |x mod 2 - 1| (rounded to multiples of 2⁻²⁴ near
    even columns), is off by 6·10⁻⁴–0.6 here."""
    from mitsuba_pbrt_tex.checker import area_mean
    n = 200
    for base in (0.0, 1.0, 1000.0):
        for width in (1e-4, 1e-5):
            c = f32(np.stack([base + rng.uniform(-width, width, n), rng.uniform(0.1, 0.9, n)], 1))
            ang = rng.uniform(0, 2 * math.pi, n)
            aniso = rng.uniform(1, 8, n)
            d0 = f32(np.stack([np.cos(ang), np.sin(ang)], 1) * (width * aniso)[:, None])
            d1 = f32(np.stack([-np.sin(ang), np.cos(ang)], 1) * width)
            mean, ok = area_mean(*[(mi.Float(v[:, 0]), mi.Float(v[:, 1])) for v in (c, d0, d1)])
            assert A(ok).all()
            want = np.array(checker_area_references(c, d0, d1))
            np.testing.assert_allclose(0.5 - 0.5 * A(mean), want, rtol=0, atol=5e-8 / width,
                                       err_msg=f'base {base}, width {width}')


def test_checkerboard_area_inside_a_cell_is_the_cells_value(rng):
    """A footprint inside one cell averages to that cell's value exactly, however small
    (1e-3 down to 1e-30 cell, anisotropy up to 8, at least 0.05 cell from every edge, cells up
    to 3 away from the origin). Reference: the cell's parity. The walk, taken relative to a
    lattice point half a cell away, returned 0.96 at 1e-6 cell, 0.5 at 1e-8, the other colour
    at 1e-20 (found in a user trial)."""
    from mitsuba_pbrt_tex.checker import area_mean
    n = 400
    for width in (1e-3, 1e-6, 1e-8, 1e-20, 1e-30):
        c = f32(rng.uniform(0.05, 0.95, (n, 2)) + rng.integers(-3, 3, (n, 2)))
        ang = rng.uniform(0, math.pi, n)
        aniso = rng.uniform(1, 8, n)
        d0 = f32(np.stack([np.cos(ang), np.sin(ang)], 1) * (width * aniso)[:, None])
        d1 = f32(np.stack([-np.sin(ang), np.cos(ang)], 1) * width)
        mean, ok = area_mean(*[(mi.Float(v[:, 0]), mi.Float(v[:, 1])) for v in (c, d0, d1)])
        assert A(ok).all()
        parity = (np.floor(c[:, 0]) + np.floor(c[:, 1])) % 2
        np.testing.assert_array_equal(A(mean), 1 - 2 * parity, err_msg=f'width {width}')


def test_checkerboard_area_fallbacks():
    """Zero footprints are point samples; degenerate (zero-area) footprints use the box closed
    form, very wide ones the Fourier series (values by hand: a 1-cell-wide segment along s
    centred on a cell edge averages to 1/2; a 40×40-cell square to 1/2)."""
    tex = mi.load_dict({'type': 'pbrt_checkerboard', 'aamode': 'area', 'tex1': 0.0, 'tex2': 1.0})
    uv = np.array([[0.5, 0.5], [1.5, 0.5], [1.0, 0.5], [3.3, 7.1]])
    d0 = np.array([[0, 0], [0, 0], [1.0, 0], [40, 0]])
    d1 = np.array([[0, 0], [0, 0], [2.0, 0], [0, 40]])
    np.testing.assert_allclose(A(tex.eval_1(make_si(uv, d0, d1))), [0, 1, 0.5, 0.5], atol=1e-6)


def test_checkerboard_nested_only_where_needed(rng):
    """A nested texture that is infinite never leaks where its weight is 0."""
    inf_tex = {'type': 'pbrt_scale', 'tex': 3e38, 'scale': 10.0}
    tex = mi.load_dict({'type': 'pbrt_checkerboard', 'tex1': 0.5, 'tex2': inf_tex})
    uv = np.array([[0.5, 0.5], [2.5, 4.5]])                 # even cells, zero footprint
    np.testing.assert_allclose(A(tex.eval_1(make_si(uv))), [0.5, 0.5])


# ------------------------------------------------------------------------------------ supersample
def test_supersample_converges_to_box_integral(rng):
    """The midpoint rule over n×n strata converges to the box average of the point-sampled
    checkerboard over the pixel parallelogram (here axis-aligned, so the exact average is
    pbrt-v3's closed form, checked against quadrature above)."""
    n = 200
    uv = f32(rng.uniform(-5, 5, (n, 2)))
    dx = np.stack([rng.uniform(0.2, 0.9, n), np.zeros(n)], 1)
    dy = np.stack([np.zeros(n), rng.uniform(0.2, 0.9, n)], 1)
    exact = numpy_reference(checker_references, uv, np.stack([dx[:, 0], dy[:, 1]], 1) / 2,
                            np.array(False))
    errors = []
    for samples in (4, 64, 1024):
        tex = mi.load_dict({'type': 'pbrt_supersample', 'samples': samples,
                            'texture': {'type': 'pbrt_checkerboard', 'aamode': 'none',
                                        'tex1': 0.0, 'tex2': 1.0}})
        got = A(tex.eval_1(make_si(uv, dx, dy)))
        errors.append(np.mean(np.abs(got - exact)))
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 0.01


def test_supersample_zero_differentials_equals_wrapped(rng):
    uv = rng.uniform(-3, 3, (300, 2))
    for inner in ({'type': 'checkerboard', 'to_uv': mi.ScalarTransform4f().scale(3)},
                  {'type': 'pbrt_dots'}, {'type': 'bitmap', 'filename': 'tests/data/srgb_11x9.png'}):
        wrapped = mi.load_dict(inner)
        ss = mi.load_dict({'type': 'pbrt_supersample', 'texture': inner, 'samples': 9})
        si = make_si(uv)
        np.testing.assert_allclose(A(ss.eval(si)), A(wrapped.eval(si)), atol=1e-6)


def test_supersample_of_mitsuba_checkerboard_averages(rng):
    uv = rng.uniform(0, 1, (100, 2))
    ss = mi.load_dict({'type': 'pbrt_supersample', 'samples': 256,
                       'texture': {'type': 'checkerboard', 'color0': 1.0, 'color1': 0.0,
                                   'to_uv': mi.ScalarTransform4f().scale(8)}})
    got = A(ss.eval_1(make_si(uv, np.tile([1.0, 0], (100, 1)), np.tile([0, 1.0], (100, 1)))))
    np.testing.assert_allclose(got, 0.5, atol=0.02)


def test_supersample_of_values_near_float32s_maximum_stays_finite():
    """A nested value of 3e38 (accepted at construction and through params.update) averages to
    itself: the n² values were summed first and the sum overflowed to inf for n² > 1 (a trial:
    3e38 with 4 or 16 samples, and 1e38 with 4, gave inf). Tolerance 4e-3: a float32 sum of
    n² terms is within n²·2^-24 of exact (65536 terms: 3.9e-3; measured 3.9e-4)."""
    si = make_si(np.array([[0.3, 0.6]]), np.array([[0.1, 0.0]]), np.array([[0.0, 0.1]]))
    for inner in ({'type': 'pbrt_constant', 'value': 3e38},
                  {'type': 'pbrt_bilerp', 'v00': 3e38, 'v01': 3e38, 'v10': 3e38, 'v11': 3e38}):
        for samples in (1, 4, 16, 65536):
            ss = mi.load_dict({'type': 'pbrt_supersample', 'samples': samples, 'texture': inner})
            np.testing.assert_allclose(A(ss.eval_1(si)), 3e38, rtol=4e-3)
            np.testing.assert_allclose(A(ss.eval_3(si)), 3e38, rtol=4e-3)


def test_supersample_footprint_limit_holds_for_3d_textures(rng):
    """The sub-samples spread over at most 1024 texture units per differential (docs) for
    3D textures too: their positions came from the unlimited partials (a footprint of 1e6 put
    fbm's sub-samples 5e5 units out). A footprint of 1e4 or 1e6 in u gives the value of a
    footprint of exactly 1024 (p = (u, v, 0) on this plane: dp/du = x, dp/dv = y)."""
    uv = rng.uniform(0, 1, (20, 2))
    fbm = {'type': 'pbrt_fbm', 'aamode': 'none'}
    ss = mi.load_dict({'type': 'pbrt_supersample', 'samples': 16, 'texture': fbm})

    def value(du):
        si = make_si(uv, np.tile([du, 0.0], (20, 1)), np.tile([0.0, 0.5], (20, 1)),
                     p=np.concatenate([uv, np.zeros((20, 1))], 1), dp_du=[1, 0, 0],
                     dp_dv=[0, 1, 0])
        return A(ss.eval_1(si))

    limited = value(1024.0)
    for du in (1e4, 1e6):
        np.testing.assert_allclose(value(du), limited, atol=1e-6)


def test_supersample_errors():
    with pytest.raises(RuntimeError, match='pbrt_supersample: parameter "samples": must be a perfect square'):
        mi.load_dict({'type': 'pbrt_supersample', 'texture': {'type': 'pbrt_dots'}, 'samples': 8})
    with pytest.raises(RuntimeError, match='pbrt_supersample: parameter "texture": is required'):
        mi.load_dict({'type': 'pbrt_supersample'})


# ------------------------------------------------------------------------------------ hard cases
@pytest.mark.parametrize('name', ['pbrt_checkerboard', 'pbrt_dots', 'pbrt_fbm', 'pbrt_wrinkled',
                                  'pbrt_windy', 'pbrt_marble'])
def test_hard_cases_finite(name):
    inf, nan = float('inf'), float('nan')
    p = np.array([[1e7, -1e7, 3.0], [-1e7, 1e7, 1e7], [0, 0, 0], [1, 2, 3], [0.5, 0.5, 0.5],
                  [nan, 1, 1], [inf, -inf, 0], [2.0, 3.0, 0], [1e30, 1, 1], [0.35, 0.0, 0]])
    d = np.array([[0, 0, 0], [nan, 0, 0], [inf, inf, 0], [1e-30, 0, 0], [1e30, 0, 0],
                  [1, 1, 1], [0.1, 0, 0], [nan, nan, nan], [0, 0, 0], [0.2, 0.1, 0]])
    si = make_si(p[:, :2], duv_dx=d[:, :2], duv_dy=d[::-1, :2], p=p, dp_du=[1, 0, 0],
                 dp_dv=[0, 1, 0])
    for params in ({}, {'aamode': 'none'} if name != 'pbrt_dots' else {}):
        if name == 'pbrt_checkerboard':
            params = dict(params, aamode=params.get('aamode', 'triangle'))
        tex = mi.load_dict({'type': name, **params})
        for out in (tex.eval(si), tex.eval_1(si)):
            assert np.isfinite(A(out)).all(), (name, params, A(out))
        if name not in ('pbrt_fbm', 'pbrt_wrinkled', 'pbrt_windy'):
            continue
        # Where the value is known: lanes with a finite p below 1e8 (rows 0-4, 7, 9) equal the
        # numpy reference given the partials as pbrt-v4 sanitises them (non-finite → 0, clamp
        # to ±1e8); dp/dx = (du/dx, dv/dx, 0) here. 1e-5 as test_fbm_and_turbulence_match_...
        rows = np.array([0, 1, 2, 3, 4, 7, 9])
        sane = lambda a: np.clip(np.where(np.isfinite(a), a, 0.0), -1e8, 1e8)
        dx = np.concatenate([sane(d[:, :2]), np.zeros((len(d), 1))], 1)
        dy = np.concatenate([sane(d[::-1, :2]), np.zeros((len(d), 1))], 1)
        pf = f32(p)
        aa = params.get('aamode', 'clamp') != 'none'
        if name == 'pbrt_fbm':
            want = rn.fbm(pf[rows], dx[rows], dy[rows], 0.5, 8, aa)
        elif name == 'pbrt_wrinkled':
            want = rn.turbulence(pf[rows], dx[rows], dy[rows], 0.5, 8, aa)
        else:
            want = rn.windy(pf[rows], dx[rows], dy[rows], aa)
        np.testing.assert_allclose(A(tex.eval_1(si))[rows], want, atol=1e-5)


def test_marble_segment_edges_finite():
    """t = 0.5 + 0.5 sin(m) reaches exactly 1 (segment index clamped to 5, pbrt-v4)."""
    m = np.array([math.pi / 2, -math.pi / 2, 0.0, math.pi / 2 + 2 * math.pi])
    p = np.stack([np.zeros(4), m, np.zeros(4)], 1)
    tex = mi.load_dict({'type': 'pbrt_marble', 'variation': 0.0})
    out = A(tex.eval_3(make_si(p[:, :2], p=p)))
    assert np.isfinite(out).all()
    np.testing.assert_allclose(out[0], 1.5 * np.array([.58, .58, .6]), atol=1e-5)


def test_noise_parameter_errors():
    for d, words in [({'type': 'pbrt_fbm', 'octaves': -1}, ['"octaves"', '>= 0']),
                     ({'type': 'pbrt_fbm', 'roughness': -0.5}, ['"roughness"', '>= 0']),
                     ({'type': 'pbrt_wrinkled', 'aamode': 'box'}, ['"aamode"', 'clamp, none']),
                     ({'type': 'pbrt_checkerboard', 'dimension': 4}, ['"dimension"', '2, 3']),
                     ({'type': 'pbrt_checkerboard', 'aamode': 'gauss'},
                      ['"aamode"', 'none, box, closedform, triangle'])]:
        with pytest.raises(RuntimeError) as e:
            mi.load_dict(d)
        assert d['type'] in str(e.value)
        for w in words:
            assert w in str(e.value)


def test_dots_mean_is_the_average_over_the_noise_period():
    """mean() (a plastic's sampling weight) of pbrt_dots: the texture's average over one period
    of its noise (256 × 256 cells), here a 2048² grid of lookups (64 per cell; the grid's own
    error for the dots' discs is ~0.8%: rtol 1.5%). Found in a user trial: "about half of the
    cells hold a dot" made it 32% high (0.192 for 0.152); 39.4% of the cells do."""
    tex = mi.load_dict({'type': 'pbrt_dots', 'uscale': 256, 'vscale': 256,
                        'inside': 0.9, 'outside': 0.1})
    n, rows, total = 2048, 256, 0.0
    u = ((np.arange(n) + 0.5) / n).astype(np.float32)
    for r0 in range(0, n, rows):
        uu, vv = np.meshgrid(u, u[r0:r0 + rows])
        si = dr.zeros(mi.SurfaceInteraction3f, uu.size)
        si.uv = mi.Point2f(uu.ravel(), vv.ravel())
        total += float(np.array(tex.eval_1(si), np.float64).sum())
    assert float(A(tex.mean())[0]) == pytest.approx(total / n ** 2, rel=0.015)


def test_dots_fraction_of_cells_with_a_dot_over_the_noise_period():
    """pbrt_dots.DOT_FRACTION, the constant mean() uses, counted again: cells whose
    Noise(cell + .5) (the numpy reference noise, at z = 0.5 as the texture asks) is positive,
    over the 256 × 256 cells of the noise's period."""
    from mitsuba_pbrt_tex.plugins import pbrt_dots
    i, j = np.meshgrid(np.arange(256) + 0.5, np.arange(256) + 0.5)
    values = rn.noise(i.ravel(), j.ravel(), np.full(i.size, 0.5))
    assert pbrt_dots.DOT_FRACTION == np.count_nonzero(values > 0) / i.size


def test_dots_mean_asked_first_inside_a_symbolic_call():
    """mean() asked for the first time inside dr.dispatch (a user's BSDF): nothing is computed
    there (a reduction counted at the first call aborted the process, found in a review)."""
    tex = mi.load_dict({'type': 'pbrt_dots', 'inside': 0.9, 'outside': 0.1})
    other = mi.load_dict({'type': 'pbrt_constant', 'value': 0.25})
    ptr = dr.gather(mi.TexturePtr, mi.TexturePtr([tex, other]), dr.arange(mi.UInt32, 4) % 2)
    got = A(dr.dispatch(ptr, lambda self, x: x * 0 + self.mean(), dr.arange(mi.Float, 4)))
    np.testing.assert_allclose(got[::2], A(tex.mean())[0], rtol=1e-7)
