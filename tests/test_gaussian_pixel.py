"""pbrt_path ``footprint="pixel"`` with Mitsuba's ``gaussian`` film filter (issue #14): the
film positions drawn from the filter and the pixel encoded in them (round trip, distribution);
the texture kernel (the filter around the pixel centre, warped by the perspective) against numpy
integration of the bilinear texture; 1-spp renders equal between seeds on interior pixels
(symbolic loop, symbolic BSDF call, wavefront mode); the image against an independent
Gaussian-weighted reference (Mitsuba's ``path`` + ``bitmap`` with the Gaussian film); errors;
texel gradients against finite differences."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from conftest import A, wavefront_mode
from test_pixel_footprint import RES, box_texture, interior_pixels, scene_dict

from mitsuba_pbrt_tex.film_view import FilterPixels
from mitsuba_pbrt_tex.render_scope import RenderScope, published

T = mi.ScalarTransform4f


def gaussian_film(width=24, height=16, border=False):
    return mi.load_dict({'type': 'hdrfilm', 'width': width, 'height': height,
                         'sample_border': border, 'rfilter': {'type': 'gaussian'}})


def filter_1d(x, stddev=0.5, radius=2.0):
    """Mitsuba's windowed Gaussian (its LLVM polynomial approximates this to ~1e-7)."""
    v = np.exp(-x * x / (2 * stddev ** 2)) - np.exp(-radius * radius / (2 * stddev ** 2))
    return np.where(np.abs(x) < radius, np.maximum(v, 0), 0)


# ----------------------------------------------------------------------------- film positions
@pytest.mark.parametrize('n', [1, 2, 5, 16, 64])
def test_film_positions_decode_to_their_pixel(n, rng):
    """Every film position of sample s of pixel c decodes to c, also moved by up to 0.2 of the
    decoding margin (half a cell of the a × b grid in ψ: 1/(2a) of ψ, at least 1/(2a·max G/∫G)
    pixel), in any direction (grids of 1 × 1, 2 × 1, 3 × 2 with a cell unused, 4 × 4, 8 × 8);
    non-finite positions decode to nothing."""
    pixels = FilterPixels(gaussian_film(), seed=7)
    pixels.draw(n)
    count = 20000
    c = rng.integers(0, [24, 16], size=(count, 2)).astype(np.float32)
    index = rng.integers(0, n, size=count).astype(np.uint32)
    x = A(pixels.film_positions(mi.Point2f(c[:, 0], c[:, 1]), mi.UInt32(index)))
    margin = 0.2 * 0.5 / pixels.a * 0.95
    for shift in ([0, 0], [margin, -margin], [-margin, margin]):
        xs = x + np.array(shift, np.float32)
        pix, ok = pixels.decode(mi.Point2f(xs[:, 0], xs[:, 1]))
        assert A(ok).all()
        np.testing.assert_array_equal(A(pix), c)
    _, ok = pixels.decode(mi.Point2f([np.nan, 3.25, np.inf], [2.5, -np.inf, 1.5]))
    assert not A(ok).any()


def test_film_offsets_follow_the_filter():
    """The offsets v = φ + m - 1/2 drawn on the device (2000 renders of 1 sample per pixel, 250
    of 16) have the filter's distribution per axis: Kolmogorov–Smirnov distance to the numpy
    CDF of exp(-x²/2σ²) - exp(-8) below 0.045 and 0.03 (the 99.9% bounds for 2000 and 4000
    independent samples are 0.044 and 0.031; the 16 of a render are stratified, which only
    lowers it); the lattice CDF and its inverse agree; within one render the 16 samples' cells
    are distinct."""
    film = gaussian_film()
    grid = np.linspace(-2, 2, 40001)
    cdf = np.cumsum(filter_1d(grid))
    cdf /= cdf[-1]
    for n, renders, bound in ((1, 2000, 0.045), (16, 250, 0.03)):
        v = []
        for seed in range(renders):
            pixels = FilterPixels(film, seed)
            pixels.draw(n)
            v.append((A(pixels.phi) + A(pixels.m) - 0.5)[:n])
        v = np.concatenate(v)
        for axis in range(2):
            d = np.sort(v[:, axis])
            ks = np.abs(np.interp(d, grid, cdf) - np.arange(1, len(d) + 1) / len(d)).max()
            assert ks < bound, (n, axis, ks)
    lattice = FilterPixels(film).lattice
    psi = np.linspace(0, 1, 1001, dtype=np.float32)[:-1]
    np.testing.assert_allclose(A(lattice.cdf(lattice.inverse(mi.Float(psi)))), psi, atol=1e-6)
    pixels = FilterPixels(film, 1)
    pixels.draw(16)
    phi = A(pixels.phi)[:16]
    assert len({tuple(np.round(p, 6)) for p in phi}) == 16


def test_camera_hits_decode_to_the_pixel_their_ray_was_drawn_for(rng):
    """The round trip the textures make: rays through the encoded film positions of every pixel
    (16 per pixel), their hits projected back to the film (pixel.sample_pixel, what pbrt_path
    and the textures call) — every hit decodes to its ray's pixel."""
    from mitsuba_pbrt_tex import pixel
    scene = mi.load_dict(scene_dict(box_texture(rng), rfilter='gaussian'))
    sensor = scene.sensors()[0]
    pixels = FilterPixels(sensor.film(), seed=5)
    pixels.draw(16)
    w, h = RES
    ys, xs = np.mgrid[0:h, 0:w]
    c = np.repeat(np.stack([xs.ravel(), ys.ravel()], 1), 16, 0).astype(np.float32)
    index = np.tile(np.arange(16, dtype=np.uint32), w * h)
    x = pixels.film_positions(mi.Point2f(c[:, 0], c[:, 1]), mi.UInt32(index))
    ray, _ = sensor.sample_ray_differential(0.0, 0.5, x / mi.ScalarVector2f(w, h),
                                            mi.Point2f(0.5), True)
    si = scene.ray_intersect(mi.Ray3f(ray))
    pix, ok = pixel.sample_pixel(sensor, si, pixels)
    ok, pix = A(ok), A(pix)
    assert ok.sum() > 0.5 * len(ok)
    assert (ok == A(si.is_valid())).all()
    np.testing.assert_array_equal(pix[ok], c[ok])


def test_box_pixel_context_is_for_box_films_only(rng):
    """``pixel.context`` (the box film's pixel parallelogram, which ``pbrt_checkerboard``
    ``aamode="area"`` filters) gives camera hits their pixel's partials under a box film, and
    the sample's own context (here: zero partials, rays without differentials) while a
    Gaussian film's pixels are published — a box average would be the wrong kernel there."""
    from mitsuba_pbrt_tex import pixel
    scene = mi.load_dict(scene_dict(box_texture(rng), rfilter='gaussian'))
    sensor = scene.sensors()[0]
    pixels = FilterPixels(sensor.film(), seed=5)
    pixels.draw(4)
    w, h = RES
    pos = np.stack([rng.uniform(0.3, 0.7, 64), rng.uniform(0.6, 0.9, 64)], 1)
    ray, _ = sensor.sample_ray_differential(0.0, 0.5, mi.Point2f(pos[:, 0], pos[:, 1]),
                                            mi.Point2f(0.5), True)
    si = scene.ray_intersect(mi.Ray3f(ray))
    assert A(si.is_valid()).mean() > 0.9
    with published(RenderScope(sensor)):
        box = pixel.context(si)
    with published(RenderScope(sensor, pixels)):
        gaussian = pixel.context(si)
    assert np.abs(A(box.dudx)).max() > 0
    assert np.all(A(gaussian.dudx) == 0) and np.all(A(gaussian.dvdy) == 0)


# ----------------------------------------------------------------------------- texture kernel
def bilinear_repeat(img, s, t):
    h, w = img.shape[:2]
    px, py = s * w - 0.5, t * h - 0.5
    x0, y0 = np.floor(px).astype(int), np.floor(py).astype(int)
    fx, fy = (px - x0)[..., None], (py - y0)[..., None]

    def tex(x, y):
        return img[y % h, x % w]
    return ((1 - fy) * ((1 - fx) * tex(x0, y0) + fx * tex(x0 + 1, y0))
            + fy * ((1 - fx) * tex(x0, y0 + 1) + fx * tex(x0 + 1, y0 + 1)))


def reference_kernel(img, st, d0, d1, g, h, n=801):
    """∫∫ f(a) f(b) T(st(a, b)) / ∫∫ f f over the film offsets (a, b) ∈ [-2, 2]² (trapezoid-like
    grid of n² points), st(a, b) = st + (a·d0 + b·d1)/(1 + a·g + b·h), T bilinear (repeat)."""
    a = np.linspace(-2, 2, n)
    A_, B_ = np.meshgrid(a, a, indexing='ij')
    wgt = filter_1d(A_) * filter_1d(B_)
    den = 1 + A_ * g + B_ * h
    s = st[0] + (A_ * d0[0] + B_ * d1[0]) / den
    t = st[1] + (A_ * d0[1] + B_ * d1[1]) / den
    v = bilinear_repeat(img, s, t)
    return (v * wgt[..., None]).sum((0, 1)) / wgt.sum()


def _kernel_and_reference(mip, img, st, d0, d1, g, h, rfilter):
    """(the package's pixel kernel, numpy integration) at the points ``st`` (n×2) for film
    partials ``d0``, ``d1`` (uv per pixel) and perspective terms ``g``, ``h``."""
    from mitsuba_pbrt_tex import gauss
    n = len(st)
    out = A(gauss.pixel_filter(
        mip, mi.Point2f(st[:, 0], st[:, 1]), mi.Vector2f(*[mi.Float(np.full(n, v)) for v in d0]),
        mi.Vector2f(*[mi.Float(np.full(n, v)) for v in d1]), mi.Float(np.full(n, g)),
        mi.Float(np.full(n, h)), gauss.FilmKernel(0.5, 2.0, rfilter), True))
    ref = np.array([reference_kernel(img.astype(np.float64), st[k], d0, d1, g, h)
                    for k in range(n)])
    return out, ref


KERNEL_CASES = [
    # (d0, d1 in texels per pixel, g, h, tolerance): magnification, isotropic, anisotropic,
    # rotated, perspective (level 0 or finer), then minification onto MIP levels 1–2
    ((0.05, 0.0), (0.0, 0.05), 0.0, 0.0, 2e-3),
    ((0.4, 0.1), (-0.1, 0.3), 0.0, 0.0, 2e-3),
    ((1.5, 0.0), (0.0, 1.5), 0.05, -0.08, 2e-3),
    ((3.0, 1.0), (-0.5, 0.8), 0.1, 0.05, 2e-3),
    ((6.0, 0.0), (0.0, 0.7), -0.1, 0.1, 2e-3),
    ((5.0, 2.0), (-2.0, 5.0), 0.0, 0.0, 2e-3),
    ((12.0, 3.0), (-1.0, 6.0), 0.05, 0.1, 2e-3),
    ((20.0, 0.0), (0.0, 16.0), 0.0, 0.0, 5e-3),
    ((24.0, 6.0), (-4.0, 10.0), 0.08, -0.05, 5e-3),
]


@pytest.mark.parametrize('case', range(len(KERNEL_CASES)))
def test_kernel_against_numpy_integration(case, rng):
    """The pixel-centred Gaussian kernel of a 64² RGB white-noise image (the hardest content for
    a MIP level) against numpy integration of its bilinear reconstruction over the film filter's
    support (exact projective map). On level 0 or a finer lattice (smaller deviation up to ~4
    texels, cases 0–6): within 2e-3 of texels in [0, 1] (measured ≤ 1.4e-3, the largest with
    perspective: the second-moment correction goes through the centre's Jacobian, which the
    perspective changes across the support; ≤ 7e-5 without, cases 0, 1, 5); on MIP levels 1–2 (cases 7–8):
    within 5e-3 (measured ≤ 2.4e-3: white-noise detail below a MIP texel, which any MIP
    filter loses)."""
    from mitsuba_pbrt_tex import gauss
    from mitsuba_pbrt_tex.mipmap import MIPMap, build_pyramid
    d0, d1, g, h, tol = KERNEL_CASES[case]
    size = 64
    img = rng.random((size, size, 3)).astype(np.float32)
    mip = MIPMap(build_pyramid(mi.TensorXf(img), True), 'repeat')
    rfilter = mi.load_dict({'type': 'gaussian'})
    n = 6
    st = rng.random((n, 2)).astype(np.float32)
    d0s = np.array(d0, np.float32) / size
    d1s = np.array(d1, np.float32) / size
    out, ref = _kernel_and_reference(mip, img, st, d0s, d1s, g, h, rfilter)
    err = np.abs(out - ref).max()
    print(f'case {case}: max error {err:.2e}')
    assert err < tol, err


def test_kernel_of_texels_at_the_limit_is_the_scaled_kernel_of_small_ones(rng):
    """The lattice sum is linear in the texels: an image of texels up to 1e38 (the limit texels
    are clamped to) gives 1e38 × the kernel of the same image scaled to [0, 1] — finite, where
    sums of hundreds of points (weights up to the perspective's Jacobian) overflowed to inf.
    rtol 1e-5: the same sums up to the scale (a power of two in the sums; 1e38 itself is not)."""
    from mitsuba_pbrt_tex.mipmap import MIPMap, build_pyramid
    img = (0.5 + 0.5 * rng.random((64, 64, 3))).astype(np.float32)
    rfilter = mi.load_dict({'type': 'gaussian'})
    st = rng.random((4, 2)).astype(np.float32)
    for d0, d1, g, h, _ in KERNEL_CASES[1::2]:
        out = []
        for scale in (1.0, 1e38):
            mip = MIPMap(build_pyramid(mi.TensorXf(img * np.float32(scale)), True), 'repeat')
            out.append(_kernel_and_reference(mip, img, st, np.array(d0, np.float32) / 64,
                                             np.array(d1, np.float32) / 64, g, h, rfilter)[0])
        assert np.isfinite(out[1]).all(), (d0, d1, out[1])
        np.testing.assert_allclose(out[1], out[0] * 1e38, rtol=1e-5)


def test_kernel_on_a_coarsened_lattice_does_not_alias(rng):
    """A footprint near the horizon of a grazing plane (measured on the bench's: 10 × 350
    texels per pixel, perspective h = 0.12) has a larger deviation so far beyond the smaller
    one that the lattice is coarsened for it (MAX_SIGMA): the smaller deviation then spans a
    fraction of a lattice unit, and the lattice sum sampled a few points on a line — on 16-texel
    checks of 0.1 and 0.9 it returned 0.8 where the exact kernel averages 0.5. Widened to one
    lattice unit (a blur along the shorter axis), it matches numpy integration of the exact
    kernel within 0.03 at random positions (measured 1.8e-3; without the widening 0.40)."""
    from mitsuba_pbrt_tex import gauss
    from mitsuba_pbrt_tex.mipmap import MIPMap, build_pyramid
    size = 256
    y, x = np.mgrid[0:size, 0:size]
    img = np.where(((x // 16) + (y // 16)) % 2 == 0, 0.9, 0.1).astype(np.float32)[..., None]
    img = np.repeat(img, 3, axis=2)
    mip = MIPMap(build_pyramid(mi.TensorXf(img), True), 'repeat')
    rfilter = mi.load_dict({'type': 'gaussian'})
    n = 6
    st = rng.random((n, 2)).astype(np.float32)
    d0 = np.array([10.0, 0.0], np.float32) / size
    d1 = np.array([110.0, -330.0], np.float32) / size
    g, h = 0.0, 0.12
    out, ref = _kernel_and_reference(mip, img, st, d0, d1, g, h, rfilter)
    err = np.abs(out - ref).max()
    print(f'coarsened lattice: max error {err:.2e}')
    assert err < 0.03, (out[:, 0], ref[:, 0])


# ----------------------------------------------------------------------------- renders
def gaussian_interior(scene):
    """Interior pixels (centre and corners on the plane) whose whole filter support (±2 pixels)
    is interior too."""
    ok = interior_pixels(scene)
    er = ok.copy()
    h, w = ok.shape
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            shifted = np.zeros_like(ok)
            ys = slice(max(0, dy), h + min(0, dy))
            yd = slice(max(0, -dy), h + min(0, -dy))
            xs = slice(max(0, dx), w + min(0, dx))
            xd = slice(max(0, -dx), w + min(0, -dx))
            shifted[yd, xd] = ok[ys, xs]
            er &= shifted
    return er


@pytest.mark.parametrize('mode', ['symbolic', 'symbolic-one-bsdf', 'wavefront'])
def test_one_spp_interior_pixels_equal_between_seeds(mode, rng):
    """Every sample counts in the pixel its texture lookup centred on, so two 1-spp renders of a
    plane under constant lighting agree on interior pixels: < 1e-4 (float32 rounding); the
    sample-centred box differs by > 1e-2 — the test can fail."""
    tex = box_texture(rng)
    scene = mi.load_dict(scene_dict(tex, rfilter='gaussian',
                                    second_bsdf=mode != 'symbolic-one-bsdf'))
    mask = gaussian_interior(scene)
    with wavefront_mode(mode == 'wavefront'):
        a, b = [np.array(mi.render(scene, spp=1, seed=s)) for s in (1, 2)]
    assert mask.sum() > 60, mask.sum()
    diff = np.abs(a - b)[mask]
    assert diff.max() < 1e-4, diff.max()
    sample = mi.load_dict(scene_dict(tex, footprint='sample', rfilter='gaussian'))
    c = np.array(mi.render(sample, spp=1, seed=1)) - np.array(mi.render(sample, spp=1, seed=2))
    assert np.abs(c[mask]).max() > 1e-2


def test_image_converges_to_gaussian_filtered_reference(rng):
    """Interior pixels at 1 spp against an independent Gaussian-weighted reference: Mitsuba's
    ``path`` with ``bitmap`` (bilinear, the same texels) and the same Gaussian film, 2 × 2048
    spp. If the pixel-mode image is the Gaussian-filtered one, the RMSE equals the reference's
    own noise (measured: 1.00× at 2 × 512 spp, 0.95× at 2 × 4096, 1.03× at 2 × 16384, where the
    noise is 3.3e-4); asserted: within 1.3× the noise plus 2e-4 (a bias of about 1e-3 fails).
    Sample-centred filtering (``footprint="sample"``, box) is > 10× further at 1 spp."""
    size, tiles = 16, 2.0
    tex = box_texture(rng, size=size, tiles=tiles)
    scene = mi.load_dict(scene_dict(tex, rfilter='gaussian'))
    mask = gaussian_interior(scene)
    img = np.array(mi.render(scene, spp=1, seed=3))
    bitmap = {'type': 'bitmap', 'data': mi.TensorXf(np.array(tex['data'])), 'raw': True,
              'to_uv': T().scale([tiles, tiles, 1])}
    ref_scene = mi.load_dict({**scene_dict(bitmap, footprint='sample', rfilter='gaussian'),
                              'integrator': {'type': 'path', 'max_depth': 2}})
    halves = [np.array(mi.render(ref_scene, spp=2048, seed=10 + k)) for k in range(2)]
    ref = 0.5 * (halves[0] + halves[1])
    noise = np.sqrt(np.mean((halves[0] - halves[1])[mask] ** 2)) / 2
    err = np.sqrt(np.mean((img - ref)[mask] ** 2))
    sample = mi.load_dict(scene_dict(tex, footprint='sample', rfilter='gaussian'))
    err_sample = np.sqrt(np.mean((np.array(mi.render(sample, spp=1, seed=3)) - ref)[mask] ** 2))
    print(f'gaussian pixel-mode 1 spp RMSE {err:.5f} (sample-centred {err_sample:.5f}), '
          f'reference noise {noise:.5f}, {mask.sum()} pixels')
    assert err < 1.3 * noise + 2e-4, (err, noise)
    assert err < 0.1 * err_sample, (err, err_sample)


def test_frozen_steps_equal_unfrozen():
    """dr.freeze over render + backward (Mitsuba's frozen-optimisation pattern, as for the box
    film in test_pixel_footprint): the per-render offsets are drawn on the device from the
    seed, so the frozen steps replay them — losses and texel gradients equal the unfrozen ones
    (float32 rounding: 1e-5 relative, 5e-5 of the largest gradient)."""
    from conftest import adam_steps
    key = 'plane.bsdf.reflectance.data'
    texels = np.random.default_rng(3).random((8, 8, 3)).astype(np.float32)

    def load():
        return mi.load_dict(scene_dict({'type': 'pbrt_imagemap', 'filter': 'box',
                                        'data': mi.TensorXf(texels), 'uscale': 3.0,
                                        'vscale': 3.0}, rfilter='gaussian', second_bsdf=False))

    plain, _ = adam_steps(load, key, 4, False, spp=2)
    frozen, recordings = adam_steps(load, key, 4, True, spp=2)
    assert recordings < len(frozen)
    for (loss_p, grad_p), (loss_f, grad_f) in zip(plain, frozen):
        assert np.abs(grad_p).sum() > 0
        assert loss_f == pytest.approx(loss_p, rel=1e-5)
        np.testing.assert_allclose(grad_f, grad_p, rtol=0, atol=5e-5 * np.abs(grad_p).max())


def _filter_edge_pixels(scene):
    """Pixels whose rays through the centre and the corners of the square ±1.5 pixels around it
    disagree about the surface (plane, ball or nothing) — the rule for Gaussian films, computed
    here with Mitsuba's own rays and numpy."""
    from test_pixel_footprint import cast
    w, h = RES
    ys, xs = np.mgrid[0:h, 0:w]
    keys = []
    for ox, oy in ((0, 0), (-1.5, -1.5), (1.5, -1.5), (-1.5, 1.5), (1.5, 1.5)):
        pos = np.stack([(xs.ravel() + 0.5 + ox) / w, (ys.ravel() + 0.5 + oy) / h], 1)
        si = cast(scene, pos)
        on_plane = A(si.is_valid()) & (np.abs(A(si.p)[:, 1]) < 1e-4)
        keys.append(np.where(A(si.is_valid()), np.where(on_plane, 1, 2), 0))
    keys = np.array(keys)
    return (keys != keys[0]).any(0).reshape(h, w)


def test_silhouette_samples_on_a_gaussian_film(rng):
    """With a Gaussian film, silhouette_spp adds paths through film offsets drawn from the
    filter in the pixels whose filter support crosses a silhouette (the render's shared offsets
    make all of them sample the same side of an edge at 1 spp: they alias). Elsewhere the image
    is unchanged (same random numbers: identical), and the edge pixels' error against Mitsuba's
    path + bitmap with the same Gaussian film (2 × 1024 spp) falls by more than half (measured
    0.101 → 0.032 with 16 paths: the remaining error is the 17 paths' noise)."""
    size, tiles = 16, 2.0
    tex = box_texture(rng, size=size, tiles=tiles)
    base = scene_dict(tex, rfilter='gaussian')
    plain = mi.load_dict(base)
    extra = mi.load_dict({**base, 'integrator': {**base['integrator'], 'silhouette_spp': 16}})
    edge = _filter_edge_pixels(plain)
    assert 20 < edge.sum() < edge.size / 2, edge.sum()
    a = np.array(mi.render(plain, spp=1, seed=4))
    b = np.array(mi.render(extra, spp=1, seed=4))
    np.testing.assert_array_equal(a[~edge], b[~edge])
    bitmap = {'type': 'bitmap', 'data': mi.TensorXf(np.array(tex['data'])), 'raw': True,
              'to_uv': T().scale([tiles, tiles, 1])}
    ref_scene = mi.load_dict({**scene_dict(bitmap, footprint='sample', rfilter='gaussian'),
                              'integrator': {'type': 'path', 'max_depth': 2}})
    ref = 0.5 * sum(np.array(mi.render(ref_scene, spp=1024, seed=20 + k)) for k in range(2))
    err_a = np.sqrt(np.mean((a - ref)[edge] ** 2))
    err_b = np.sqrt(np.mean((b - ref)[edge] ** 2))
    print(f'gaussian edge pixels: RMSE {err_a:.4f} without, {err_b:.4f} with 16 silhouette '
          f'paths ({edge.sum()} pixels)')
    assert err_b < 0.5 * err_a, (err_a, err_b)


@pytest.mark.parametrize('forward', [False, True])
def test_texel_gradients_through_gaussian_pixel_footprint(forward, rng):
    """Backward- and forward-mode texel gradients (Mitsuba's render_backward/render_forward on
    the non-splatting film view) against central finite differences (the project's
    check_gradient, 2%)."""
    import test_gradients as tg
    d = scene_dict(box_texture(rng, size=16), rfilter='gaussian', second_bsdf=False)
    d['sensor']['film'].update(width=tg.RES, height=tg.RES)
    d['integrator']['max_depth'] = 3
    tg.check_gradient(mi.load_dict(d), 'plane.bsdf.reflectance.data', rng, forward=forward)


def test_differentiable_renders_with_uint32_seeds_reuse_their_kernels(rng):
    """An optimisation loop passes ``seed=mi.UInt32(step)`` (a literal): the render's offsets
    are drawn from an opaque copy of it, so every step runs the same kernels. Found in a user
    trial: the literal became a constant of two kernels, compiled anew at every step (1 MiB of
    memory and ~1 s a step). Dr.Jit's kernel history: steps 1 and 2 launch the same kernels."""
    d = scene_dict(box_texture(rng, size=16), rfilter='gaussian', second_bsdf=False)
    d['sensor']['film'].update(width=12, height=8)
    scene = mi.load_dict(d)
    params = mi.traverse(scene)
    key = 'plane.bsdf.reflectance.data'
    dr.enable_grad(params[key])
    params.update()
    launched = []
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        for step in range(3):
            dr.kernel_history_clear()
            seed = mi.UInt32(step)
            img = mi.render(scene, params, spp=1, seed=seed)
            dr.backward(dr.mean(img, axis=None))
            dr.eval(dr.grad(params[key]))
            launched.append(sorted(k['hash'] for k in dr.kernel_history() if 'hash' in k))
            assert seed.state == dr.VarState.Literal        # the caller's seed is untouched
    assert launched[1] == launched[2]


# ------------------------------------------------------------------ found by mutation testing
def test_second_sensor_counts_samples_in_its_own_pixels(rng):
    """``mi.render(scene, sensor=1)`` with the Gaussian film: samples are decoded to pixels of
    the sensor rendered (its film positions, its projection), so two 1-spp renders of that
    sensor agree on interior pixels as with a single sensor (< 1e-4, float32 rounding);
    decoding through the scene's first sensor (elsewhere, another film) counts them in wrong
    pixels or none."""
    from test_pixel_footprint import two_sensor_scene
    tex = box_texture(rng)
    scene = mi.load_dict(two_sensor_scene(tex, rfilter='gaussian'))
    mask = gaussian_interior(mi.load_dict(scene_dict(tex, rfilter='gaussian')))
    a, b = [np.array(mi.render(scene, sensor=1, spp=1, seed=s)) for s in (1, 2)]
    assert a.shape[:2] == (RES[1], RES[0]) and mask.sum() > 60
    assert np.abs(a - b)[mask].max() < 1e-4


def test_second_sensor_in_the_first_ones_place_counts_samples_in_its_own_pixels(rng):
    """As above, with the scene's first sensor where the second is (same pose, another field of
    view and film): the second sensor's hits are camera hits of the first too, and its film
    positions decode through the first to pixels of another film — so only the sensor rendered
    gives its pixels. The render of sensor 1 equals that of the same sensor as a scene's only
    one with the same seed (atol 1e-5: the same kernels on the same numbers; measured equal).
    Decoding through the first sensor counts samples in other pixels, ~0.1 per pixel."""
    from test_pixel_footprint import two_sensor_scene
    tex = box_texture(rng)
    scene = mi.load_dict(two_sensor_scene(tex, rfilter='gaussian', same_place=True))
    a = np.array(mi.render(scene, sensor=1, spp=2, seed=3))
    b = np.array(mi.render(mi.load_dict(scene_dict(tex, rfilter='gaussian')), spp=2, seed=3))
    assert a.shape[:2] == (RES[1], RES[0]) and b.mean() > 0.05
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-5)


def test_direct_render_forward_and_backward_draw_the_render_seeds_offsets(rng):
    """The integrator's own ``render_forward``/``render_backward`` (Mitsuba's entry points, here
    called directly with a seed) use the film offsets of that seed, as ``render`` does. With
    direct light only (max_depth 2, one diffuse plane) the image is linear in the texels, so
    the forward derivative along the texels themselves is the image of the same seed, and
    Σ texels·(backward gradient of Σ w·image) = Σ w·image — equal up to float32 rounding of
    the derivative's sums (rtol 1e-4, atol 1e-6). The offsets of another seed put every
    sample elsewhere (~0.05 per pixel)."""
    texels = rng.random((16, 16, 3)).astype(np.float32)

    def load():          # a fresh tensor per scene: no gradient state carried between modes
        return mi.load_dict(scene_dict({'type': 'pbrt_imagemap', 'filter': 'box',
                                        'data': mi.TensorXf(texels), 'uscale': 3.0,
                                        'vscale': 3.0}, rfilter='gaussian', second_bsdf=False))

    key, seed = 'plane.bsdf.reflectance.data', 5
    scene = load()
    integrator = scene.integrator()
    image = np.array(integrator.render(scene, seed=seed, spp=2))
    assert image.mean() > 0.05
    other = np.array(integrator.render(scene, seed=seed + 1, spp=2))
    assert np.abs(other - image).max() > 1e-2          # the seed matters
    params = mi.traverse(scene)
    dr.enable_grad(params[key])
    params.update()
    dr.set_grad(params[key], mi.TensorXf(texels))
    dr.enqueue(dr.ADMode.Forward, params[key])
    dr.traverse(dr.ADMode.Forward, dr.ADFlag.ClearEdges)
    forward = np.array(integrator.render_forward(scene, params, seed=seed, spp=2))
    np.testing.assert_allclose(forward, image, rtol=1e-4, atol=1e-6)
    scene = load()
    params = mi.traverse(scene)
    dr.enable_grad(params[key])
    params.update()
    w = rng.random(image.shape).astype(np.float32)
    scene.integrator().render_backward(scene, params, mi.TensorXf(w), seed=seed, spp=2)
    g = np.array(dr.grad(params[key]), dtype=np.float64)
    assert (g * texels).sum() == pytest.approx((w * image).sum(), rel=1e-4)


def test_crop_window_counts_samples_in_their_pixels(rng):
    """A film with a crop window: pixels keep their full-film coordinates (Mitsuba's
    ``crop_offset``), so an interior pixel of the window has the value it has in the uncropped
    render — the filter-weighted texture average, the same for every sample — up to float32
    rounding (< 1e-4, as between seeds). Counting a sample at a pixel off by the window's
    offset drops it or moves it to another pixel."""
    tex = box_texture(rng)
    full_d = scene_dict(tex, rfilter='gaussian')
    mask = gaussian_interior(mi.load_dict(full_d))
    (ox, oy), (cw, ch) = (6, 3), (14, 10)
    crop_d = scene_dict(tex, rfilter='gaussian')
    crop_d['sensor']['film'].update(crop_offset_x=ox, crop_offset_y=oy, crop_width=cw,
                                    crop_height=ch)
    full = np.array(mi.render(mi.load_dict(full_d), spp=1, seed=1))
    crop = np.array(mi.render(mi.load_dict(crop_d), spp=1, seed=2))
    window = mask[oy:oy + ch, ox:ox + cw]
    assert crop.shape[:2] == (ch, cw) and window.sum() > 20
    assert np.abs(crop - full[oy:oy + ch, ox:ox + cw])[window].max() < 1e-4


@pytest.mark.parametrize('texture', ['checker_area', 'ewa', 'nested_box'])
def test_gaussian_film_samples_per_pixel_only_for_a_texture_that_filters_its_kernel(texture,
                                                                                     rng):
    """With a Gaussian film, ``footprint="pixel"`` draws the camera samples per pixel from the
    filter and counts each in one pixel only where some texture filters the film's kernel
    (``pbrt_imagemap`` ``box``, also nested): a scene whose footprint readers do not (a
    checkerboard's ``area`` mode, EWA) renders as ``footprint="sample"``, the same image —
    it paid that sampling's extra noise and aliasing for nothing (found in a user trial) —
    while a nested box still gets it (the image differs)."""
    textures = {
        'checker_area': {'type': 'pbrt_checkerboard', 'aamode': 'area', 'uscale': 6.0,
                         'vscale': 6.0},
        'ewa': dict(box_texture(rng), filter='ewa'),
        'nested_box': {'type': 'pbrt_scale', 'tex': box_texture(rng), 'scale': 0.8}}
    images = {}
    for footprint in ('pixel', 'sample'):
        d = scene_dict(textures[texture], footprint=footprint, rfilter='gaussian')
        images[footprint] = np.array(mi.render(mi.load_dict(d), spp=2, seed=5))
    difference = np.abs(images['pixel'] - images['sample']).max()
    if texture == 'nested_box':
        assert difference > 1e-2
    else:
        assert difference <= 1e-6, difference       # float32 rounding of the same paths


def test_moment_around_pbrt_path_says_pixel_footprints_do_not_apply(rng, capfd):
    """Mitsuba's ``moment`` hands ``pbrt_path.sample()`` rays of its own: with a Gaussian film
    pixel footprints cannot apply (they need the render's own camera samples), so camera hits
    keep the sample's footprint — the image equals ``footprint="sample"``'s — and a warning
    says so (it was silent; found in a user trial)."""
    tex = box_texture(rng)
    images = {}
    for footprint in ('pixel', 'sample'):
        d = scene_dict(tex, footprint=footprint, rfilter='gaussian')
        d['integrator'] = {'type': 'moment', 'inner': d['integrator']}
        images[footprint] = np.array(mi.render(mi.load_dict(d), spp=1, seed=2))[..., :3]
    np.testing.assert_allclose(images['pixel'], images['sample'], rtol=1e-6, atol=1e-7)
    said = capfd.readouterr()               # Mitsuba's logger writes to the console's stdout
    said = said.out + said.err
    assert 'footprint="pixel" with a gaussian film' in said and 'moment' in said, said


def test_sample_called_without_render_keeps_the_sample_footprint(rng):
    """``sample()`` is the interface a user's own render loop calls (Mitsuba's ``prepare``,
    ``sample_rays``, ``sample``): without ``render()`` the rays are not drawn from the Gaussian
    filter per pixel, so pixel footprints do not apply and the textures keep the sample's
    footprint — the radiance equals that of ``footprint="sample"`` on the same rays and random
    numbers (float32 rounding: rtol 1e-6), and differs from the pixel-centred lookup (which a
    render gives: the test can fail)."""
    tex = box_texture(rng)
    out = {}
    for footprint in ('pixel', 'sample'):
        scene = mi.load_dict(scene_dict(tex, footprint=footprint, rfilter='gaussian'))
        integrator, sensor = scene.integrator(), scene.sensors()[0]
        sampler, _ = integrator.prepare(sensor, 3, 1, [])
        ray, _, _ = integrator.sample_rays(scene, sensor, sampler)
        L, valid, _, _ = integrator.sample(dr.ADMode.Primal, scene, sampler, ray, None, None,
                                           mi.Bool(True))
        out[footprint] = np.array(L), np.array(valid)
    assert out['pixel'][1].mean() > 0.5
    np.testing.assert_allclose(out['pixel'][0], out['sample'][0], rtol=1e-6, atol=1e-7)
    pixel = np.array(mi.render(mi.load_dict(scene_dict(tex, rfilter='gaussian')), spp=1, seed=3))
    sample = np.array(mi.render(mi.load_dict(scene_dict(tex, footprint='sample',
                                                        rfilter='gaussian')), spp=1, seed=3))
    assert np.abs(pixel - sample).max() > 1e-2


def test_sample_called_without_render_in_backward_mode(rng):
    """The same user's loop differentiated as Mitsuba's ``render_backward`` does it (derivatives
    suspended): a primal ``sample()`` on a clone of the sampler, then ``sample()`` in backward
    mode with the per-sample image gradient ``δL`` and the primal radiance as ``state_in``.
    Without ``render()`` the Gaussian film's rays are not ours, so the texel gradient equals that of
    ``footprint="sample"`` on the same rays (float32 rounding of the scattered sums: rtol 1e-5
    of the largest texel's) — and it is not zero: the backward pass must receive ``δL`` and
    the primal radiance (``state_in``) that the path replay reads."""
    texels = rng.random((32, 32, 3)).astype(np.float32)
    key = 'plane.bsdf.reflectance.data'
    grads = {}
    for footprint in ('pixel', 'sample'):
        tex = {'type': 'pbrt_imagemap', 'filter': 'box', 'data': mi.TensorXf(texels),
               'uscale': 3.0, 'vscale': 3.0}       # a fresh tensor per scene
        scene = mi.load_dict(scene_dict(tex, footprint=footprint, rfilter='gaussian',
                                        second_bsdf=False))
        integrator, sensor = scene.integrator(), scene.sensors()[0]
        params = mi.traverse(scene)
        dr.enable_grad(params[key])
        params.update()
        with dr.suspend_grad():                    # as render_backward
            sampler, _ = integrator.prepare(sensor, 3, 1, [])
            ray, _, _ = integrator.sample_rays(scene, sensor, sampler)
            L, _, _, _ = integrator.sample(dr.ADMode.Primal, scene, sampler.clone(), ray, None,
                                           None, mi.Bool(True))
            δL = mi.Spectrum(dr.linspace(mi.Float, 0.5, 1.5, dr.width(L)))
            integrator.sample(dr.ADMode.Backward, scene, sampler, ray, δL, L, mi.Bool(True))
        grads[footprint] = np.array(dr.grad(params[key]))
    scale = np.abs(grads['sample']).max()
    assert scale > 1e-3
    np.testing.assert_allclose(grads['pixel'], grads['sample'], rtol=0, atol=1e-5 * scale)
