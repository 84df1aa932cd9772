"""``python -m mitsuba_pbrt_tex bench render``: error against time for every filtering method.

For each bundled benchmark scene (``scenes/bench``) and each method, the scene is rendered at
increasing sample counts; each render is timed (median of ``--repeats`` runs after a warm-up
render that compiles the kernels — the compile time is reported separately) and compared with
the scene's reference image.

Methods: what Mitsuba users do today — Mitsuba's ``bitmap``/``checkerboard`` (or, where no
built-in can express the texture, our texture without any footprint) under Mitsuba's ``path``
with more samples — and every filter/``aamode`` of ours under ``pbrt_path``; on the grazing image
scenes also ``box`` with ``pbrt_path``'s ``footprint="pixel"`` (camera hits filter their
pixel's footprint).

Reference: the same scene with the textures point-sampled at full resolution (``bitmap`` /
point-sampled procedurals under ``path``, i.e. no prefiltering at all) and the same box pixel
filter, rendered with ``--ref-spp`` samples in two independent halves. The difference of the
halves estimates the reference's own noise (reported; RMSE(half₁ - half₂)/2 is the RMSE of the
full reference), which must be far below the errors compared. References are cached on disk,
keyed by a hash of the scene files, textures, parameters, resolution and sample count.

Errors: RMSE of linear RGB over the image, RMSE over the pixels that depend on the texture (found
by rendering the scene with the texture replaced by two constants), and the mean relative error
``mean(|L - L_ref| / max(L_ref, 0.01))`` of the luminance over the image.

Outputs in ``--out``: ``results.csv``, ``results.md`` (a table and summary lines),
``chart_<scene>.png`` (log-log error against time, one line per method) and ``charts.png``.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import os
import sys
import time
from dataclasses import dataclass

import numpy as np

from ..outputs import save_figure

LUM = np.array([0.212671, 0.715160, 0.072169])
#: the silhouette samples the README recommends with pixel footprints
SILHOUETTE_SPP = 64
#: our image texture in place of ``bitmap`` under Mitsuba's ``path``: the same image, so its
#: equal-error speed-up is a time ratio, also measured render against render (:mod:`.paired`)
DROP_IN = 'pbrt_imagemap bilinear + Mitsuba path'
#: pairs of renders per spp in that measurement
PAIRS = 9
#: the pixel-footprint method whose frame is compared with others' (no silhouette samples)
PIXEL_BOX = 'pbrt_imagemap box, footprint pixel'


@dataclass
class Method:
    name: str
    params: dict
    ours: bool
    group: str = ''                       # e.g. 'trilinear-width' to compare conventions


@dataclass
class Case:
    name: str
    xml: str                              # in scenes/bench, or an absolute path
    description: str
    reference: dict
    methods: list
    mask: tuple | None = None            # two parameter sets giving different constant textures
    inputs: tuple = ()                   # files outside scenes/ the scene reads (cache key)
    at_builtin_spp: tuple = ()           # also report speed-ups at the built-in's errors there
    res: tuple | None = None             # the scene's own image size (full runs)
    far_edge: bool = False               # a plane ending in the image: report error by row


def _checker_cases(cells):
    pbrt = {'texture': 'tex/checker_pbrt.xml', 'cells': str(cells)}
    ours = [Method('pbrt_checkerboard none (point)', {**pbrt, 'aamode': 'none'}, True),
            Method('pbrt_checkerboard box', {**pbrt, 'aamode': 'box'}, True),
            Method('pbrt_checkerboard triangle', {**pbrt, 'aamode': 'triangle'}, True),
            # the exact average over the footprint: around the sample, and the pixel's
            Method('pbrt_checkerboard area', {**pbrt, 'aamode': 'area'}, True, 'footprint'),
            Method('pbrt_checkerboard area, footprint pixel',
                   {**pbrt, 'aamode': 'area', 'footprint': 'pixel'}, True, 'footprint'),
            Method(f'pbrt_checkerboard area, footprint pixel, silhouette_spp {SILHOUETTE_SPP}',
                   {**pbrt, 'aamode': 'area', 'footprint': 'pixel',
                    'silhouette_spp': str(SILHOUETTE_SPP)},
                   True, 'footprint'),
            Method('pbrt_supersample 16 (point checker)', {
                'texture': 'tex/checker_supersample.xml', 'samples': '16', 'cells': str(cells)}, True)]
    # Mitsuba's checkerboard has 2×2 cells per unit of its to_uv
    builtin = [Method('Mitsuba checkerboard + path', {'texture': 'tex/checker_mitsuba.xml',
                                                      'half_cells': str(cells // 2),
                                                      'integrator': 'path'}, False)]
    return builtin, ours


def _image_common(image, tiles, extra):
    """(our image texture's parameters, [Mitsuba's bitmap + path]) for a case."""
    extra = extra or {}
    builtin = [Method('Mitsuba bitmap + path', {'texture': 'tex/image_bitmap.xml', 'image': image,
                                               'tiles': tiles, 'integrator': 'path', **extra},
                      False)]
    return {'texture': 'tex/image_pbrt.xml', 'image': image, 'tiles': tiles, **extra}, builtin


def _image_methods(image, tiles, pixel=False, extra=None):
    common, builtin = _image_common(image, tiles, extra)
    ours = [Method('pbrt_imagemap bilinear', {**common, 'filter': 'bilinear'}, True),
            Method('pbrt_imagemap trilinear v3', {**common, 'filter': 'trilinear', 'trilinearwidth': 'v3'}, True, 'trilinear-width'),
            Method('pbrt_imagemap trilinear v4', {**common, 'filter': 'trilinear', 'trilinearwidth': 'v4'}, True, 'trilinear-width'),
            Method('pbrt_imagemap ewa 8', {**common, 'filter': 'ewa', 'maxanisotropy': '8'}, True, 'ewa-anisotropy'),
            Method('pbrt_imagemap ewa 32', {**common, 'filter': 'ewa', 'maxanisotropy': '32'}, True, 'ewa-anisotropy'),
            Method('pbrt_imagemap box', {**common, 'filter': 'box'}, True, 'footprint')]
    if pixel:           # scenes whose pbrt_path takes "footprint" (int/pbrt_path.xml)
        ours.append(Method(PIXEL_BOX,
                           {**common, 'filter': 'box', 'footprint': 'pixel'}, True, 'footprint'))
        ours.append(Method(f'pbrt_imagemap box, footprint pixel, silhouette_spp {SILHOUETTE_SPP}',
                           {**common, 'filter': 'box', 'footprint': 'pixel',
                            'silhouette_spp': str(SILHOUETTE_SPP)}, True, 'footprint'))
    return builtin, ours


def _gaussian_methods(image, tiles, extra=None):
    """On a Gaussian film: Mitsuba's bitmap + path, and ours — our image texture as a drop-in
    under Mitsuba's path, sample-centred filters and pixel footprints, whose texture filters the
    film's own kernel, with and without silhouette samples."""
    common, builtin = _image_common(image, tiles, extra)
    ours = [Method(DROP_IN, {**common, 'filter': 'bilinear', 'integrator': 'path'}, True,
                   'drop-in'),
            Method('pbrt_imagemap bilinear', {**common, 'filter': 'bilinear'}, True),
            Method('pbrt_imagemap trilinear v3', {**common, 'filter': 'trilinear'}, True),
            Method('pbrt_imagemap ewa 8', {**common, 'filter': 'ewa', 'maxanisotropy': '8'}, True),
            Method(PIXEL_BOX,
                   {**common, 'filter': 'box', 'footprint': 'pixel'}, True, 'footprint'),
            Method(f'pbrt_imagemap box, footprint pixel, silhouette_spp {SILHOUETTE_SPP}',
                   {**common, 'filter': 'box', 'footprint': 'pixel',
                    'silhouette_spp': str(SILHOUETTE_SPP)},
                   True, 'footprint')]
    return builtin, ours


def cases(mitsuba_data=None, work_dir='bench-out') -> list[Case]:
    flat = ({'texture': 'tex/flat.xml', 'flat': '0.2'}, {'texture': 'tex/flat.xml', 'flat': '0.8'})
    out = []
    b, o = _checker_cases(2000)
    out.append(Case('grazing-checker', 'grazing.xml',
                    'plane to the horizon, procedural checkerboard (cells of 0.2 world units)',
                    {'texture': 'tex/checker_pbrt.xml', 'cells': '2000', 'aamode': 'none',
                     'integrator': 'path'}, b + o, flat, far_edge=True))
    b, o = _image_methods('../textures/checker.png', '125', pixel=True)
    out.append(Case('grazing-checker-image', 'grazing.xml',
                    'plane to the horizon, checker image (16×16 checks per tile, 125×125 tiles: '
                    'the same 0.2-unit cells)',
                    {'texture': 'tex/image_bitmap.xml', 'tiles': '125', 'integrator': 'path'},
                    b + o, flat, far_edge=True))
    b, o = _image_methods('../textures/zoneplate.png', '100', pixel=True)
    out.append(Case('grazing-zoneplate', 'grazing.xml',
                    'plane to the horizon, zone-plate image (100×100 tiles)',
                    {'texture': 'tex/image_bitmap.xml', 'image': '../textures/zoneplate.png',
                     'tiles': '100', 'integrator': 'path'}, b + o, flat, far_edge=True))
    b, o = _image_methods('../textures/grid.png', '20', pixel=True)
    out.append(Case('oblique-grid', 'oblique.xml',
                    'plane at a moderate angle to its far edge, grid image minified (20×20 tiles: '
                    'pixel footprints about 10-60 texels long)',
                    {'texture': 'tex/image_bitmap.xml', 'image': '../textures/grid.png',
                     'tiles': '20', 'integrator': 'path'}, b + o, flat, far_edge=True))
    mapping_ours = [Method(f'pbrt_imagemap {f}', {'filter': f.split()[0], **extra}, True, grp)
                    for f, extra, grp in (('bilinear', {}, ''),
                                          ('trilinear v3', {'trilinearwidth': 'v3'}, 'trilinear-width'),
                                          ('trilinear v4', {'trilinearwidth': 'v4'}, 'trilinear-width'),
                                          ('ewa 8', {'maxanisotropy': '8'}, 'ewa-anisotropy'),
                                          ('ewa 32', {'maxanisotropy': '32'}, 'ewa-anisotropy'))]
    out.append(Case('sphere-mappings', 'mappings.xml',
                    'spherical, cylindrical, planar mappings of a grid image on small spheres '
                    '(no built-in has these mappings: the baseline is our lookup without footprint)',
                    {'filter': 'bilinear', 'integrator': 'path'},
                    [Method('no footprint (bilinear level 0) + path', {'filter': 'bilinear',
                                                                       'integrator': 'path'}, False)]
                    + mapping_ours))
    out.append(Case('noise-marble', 'noise.xml',
                    'marble and turbulence on a receding plane (no built-in noise: the baseline is '
                    'all octaves, i.e. aamode none, with more samples)',
                    {'aamode': 'none', 'integrator': 'path'},
                    [Method('aamode none + path', {'aamode': 'none', 'integrator': 'path'}, False),
                     Method('aamode clamp (pbrt)', {'aamode': 'clamp'}, True)]))
    b, o = _image_methods('../textures/checker.png', '25')
    out.append(Case('specular', 'specular.xml',
                    'mirror and glass spheres seeing a textured floor, textured wall lighting a box',
                    {'texture': 'tex/image_bitmap.xml', 'integrator': 'path'}, b + o, flat))
    gauss = {'rfilter': 'gaussian'}
    b, o = _gaussian_methods('../textures/checker.png', '125', gauss)
    out.append(Case('grazing-checker-image-gaussian', 'grazing.xml',
                    'the grazing checker-image plane through Mitsuba\'s default Gaussian film',
                    {'texture': 'tex/image_bitmap.xml', 'tiles': '125', 'integrator': 'path',
                     **gauss}, b + o, flat, far_edge=True))
    out.append(envlit_case(mitsuba_data, work_dir, flat))
    return out


def _usage_error(message: str):
    """A user error, as the command line reports them: one line, exit status 2."""
    print(f'error: {message}', file=sys.stderr)
    raise SystemExit(2)


def envlit_case(mitsuba_data, work_dir, flat) -> Case:
    """A real scene as Mitsuba's users write it: Mitsuba's own ``matpreview`` (from
    ``--mitsuba-data``: Gaussian film, environment light, ``path`` to full depth) with its
    floor's checkerboard replaced by the data's 2048² photo ``floor_tiles.jpg`` tiled 8×8 —
    or, without the data (its repository states no licence, so none of it is shipped), the
    bundled look-alike ``envlit.xml`` with a generated environment map and photo-like texture.
    Compared at the built-in's 4, 16 and 64 spp errors, where lighting noise dominates."""
    if mitsuba_data and work_dir:
        xml, image, inputs = matpreview_scene(mitsuba_data, work_dir)
        name, what = 'matpreview-photo', 'Mitsuba\'s matpreview, floor_tiles.jpg tiled 8×8'
    else:
        # generated where the benchmark keeps its cache (not when only the names are asked)
        image, envmap = lookalike_inputs(work_dir) if work_dir else ('', '')
        xml, inputs = 'envlit.xml', (image, envmap)
        name, what = 'envlit-photo', 'matpreview look-alike, generated photo-like floor 8×8'
    extra = {'max_depth': '-1', **({} if mitsuba_data else {'envmap': envmap})}
    b, o = _gaussian_methods(image, '8', extra)
    return Case(name, xml, f'{what}: Gaussian film, environment light, path to full depth',
                {'texture': 'tex/image_bitmap.xml', 'image': image, 'tiles': '8',
                 'integrator': 'path', **extra}, b + o,
                tuple({**m, **extra} for m in flat), inputs, (4, 16, 64), (240, 180))


def matpreview_scene(data_dir, work_dir):
    """(scene file, photo, inputs): Mitsuba's matpreview.xml rewritten into ``work_dir`` with
    the floor's texture and the integrator taken from the benchmark's includes."""
    folder = os.path.join(data_dir, 'scenes', 'matpreview')
    src = os.path.join(folder, 'matpreview.xml')
    image = os.path.join(data_dir, 'common', 'textures', 'floor_tiles.jpg')
    for f in (src, image):
        if not os.path.isfile(f):
            _usage_error(f'--mitsuba-data: {f} does not exist (expected a checkout of '
                         f'mitsuba-renderer/mitsuba-data)')
    with open(src) as fh:
        text = fh.read()
    start = text.index('<texture type="checkerboard"')
    end = text.index('</texture>', start) + len('</texture>')
    text = text[:start] + '<include filename="$texture"/>' + text[end:]
    text = text.replace('id="texture-checkerboard"', 'id="tex"')
    start = text.index('<integrator')
    end = text.index('</integrator>', start) + len('</integrator>')
    text = text[:start] + '<include filename="int/$integrator.xml"/>' + text[end:]
    text = text.replace('<default name="spp" value="64"/>',
                        '<default name="spp" value="4"/>\n    <default name="integrator" '
                        'value="pbrt_path"/>\n    <default name="texture" '
                        'value="tex/image_bitmap.xml"/>')
    for name in ('envmap.exr', 'matpreview.serialized'):
        text = text.replace(f'value="{name}"', f'value="{os.path.join(folder, name)}"')
    os.makedirs(work_dir, exist_ok=True)
    out = os.path.join(os.path.abspath(work_dir), 'matpreview-bench.xml')
    with open(out, 'w') as fh:
        fh.write(text)
    return out, image, (src, image, os.path.join(folder, 'envmap.exr'))


def lookalike_inputs(work_dir):
    """(photo, environment map) for ``envlit.xml``, generated once into ``work_dir``: a 2048²
    8-bit sRGB texture with a photo's statistics (a 1/f spectrum, grout lines between tiles,
    per-tile tint) and a 512×256 sky with a small bright sun (lighting noise, as museum-like
    maps give)."""
    import mitsuba as mi
    os.makedirs(work_dir, exist_ok=True)
    photo = os.path.join(os.path.abspath(work_dir), 'envlit-photo.png')
    envmap = os.path.join(os.path.abspath(work_dir), 'envlit-envmap.exr')
    if not os.path.exists(photo):
        rng = np.random.default_rng(2024)
        n = 2048
        f = np.fft.fftfreq(n)
        amp = 1.0 / np.maximum(np.hypot(*np.meshgrid(f, f)), 1.0 / n)
        layers = [np.real(np.fft.ifft2(np.fft.fft2(rng.standard_normal((n, n))) * amp))
                  for _ in range(3)]
        noise = np.stack([(x - x.mean()) / x.std() for x in layers], -1)
        y, x = np.mgrid[0:n, 0:n]
        tile = 256
        grout = ((x % tile) < 6) | ((y % tile) < 6)
        tint = rng.uniform(0.8, 1.2, (n // tile, n // tile, 3))[y // tile, x // tile]
        albedo = np.clip((0.35 + 0.08 * noise) * tint, 0.02, 0.9)
        albedo[grout] = 0.08
        bmp = mi.Bitmap(albedo.astype(np.float32), mi.Bitmap.PixelFormat.RGB)
        bmp.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, True).write(photo)
    if not os.path.exists(envmap):
        h, w = 256, 512
        theta = (np.arange(h) + 0.5) / h * np.pi                    # 0: up
        phi = (np.arange(w) + 0.5) / w * 2 * np.pi
        t, p = np.meshgrid(theta, phi, indexing='ij')
        sky = np.where(t[..., None] < np.pi / 2,
                       np.array([0.35, 0.5, 0.9]) * (0.4 + 0.6 * np.cos(t)[..., None]) + 0.3,
                       np.array([0.25, 0.2, 0.15]))
        sun = np.exp(-((t - 0.6) ** 2 + (p - 1.2) ** 2) / (2 * 0.05 ** 2))[..., None] * 60.0
        mi.Bitmap((sky + sun).astype(np.float32), mi.Bitmap.PixelFormat.RGB).write(envmap)
    return photo, envmap


# ---------------------------------------------------------------------------------------- helpers
def scenes_dir() -> str:
    from .. import scenes
    return os.path.join(os.path.dirname(scenes.__file__), 'bench')


def _load(case: Case, params: dict, res):
    import mitsuba as mi
    kw = {'width': str(res[0]), 'height': str(res[1]), **params}
    resolver = mi.file_resolver()
    if scenes_dir() not in [str(p) for p in resolver]:   # includes of scenes elsewhere
        resolver.append(scenes_dir())
    return mi.load_file(os.path.join(scenes_dir(), case.xml), **kw)


def _render(scene, spp, seed, max_pass=64):
    """Average of passes of at most ``max_pass`` spp (box filter: exact), as float64 RGB."""
    import mitsuba as mi
    passes = max(1, int(math.ceil(spp / max_pass)))
    per = spp // passes
    acc = 0.0
    for k in range(passes):
        acc = acc + np.array(mi.render(scene, spp=per, seed=seed * 1000 + k), dtype=np.float64)
    return (acc / passes)[..., :3]


def _case_hash(case: Case, res, spp) -> str:
    h = hashlib.sha256()
    folder = scenes_dir()
    for root in (folder, os.path.join(folder, '..', 'textures')):
        for dirpath, _, files in sorted(os.walk(root)):
            for f in sorted(files):
                if f.endswith(('.xml', '.png', '.exr')):
                    with open(os.path.join(dirpath, f), 'rb') as fh:
                        h.update(f.encode() + fh.read())
    for f in case.inputs:
        with open(f, 'rb') as fh:
            h.update(fh.read())
    h.update(json.dumps([case.xml, case.reference, list(res), spp]).encode())
    h.update(REFERENCE_FORMAT.encode())
    from .. import __version__
    h.update(__version__.encode())
    return h.hexdigest()[:16]


#: What a cached reference file holds (part of its key: older caches are rendered again).
REFERENCE_FORMAT = 'image+noise_sq'


@dataclass
class Reference:
    """A case's reference image and its own error, per pixel and channel: the squared half
    difference of its two independent halves (an unbiased estimate of the mean's squared
    error), so that the noise of any region can be read off."""
    image: np.ndarray
    noise_sq: np.ndarray

    def noise(self, region=None) -> float:
        sq = self.noise_sq if region is None else self.noise_sq[region]
        return float(np.sqrt(np.mean(sq))) if sq.size else 0.0


def reference(case: Case, res, spp, cache_dir, log) -> Reference:
    """The case's reference, from the cache when possible."""
    import mitsuba as mi
    from ..outputs import write_exr
    key = _case_hash(case, res, spp)
    path = os.path.join(cache_dir, f'ref-{case.name}-{key}.npz')
    if os.path.exists(path):
        data = np.load(path)
        return Reference(data['image'], data['noise_sq'])
    log(f'  reference: {spp} spp in two halves (cached afterwards)')
    scene = _load(case, case.reference, res)
    halves = [_render(scene, spp // 2, seed=900 + k) for k in range(2)]
    image = 0.5 * (halves[0] + halves[1])
    noise_sq = ((halves[0] - halves[1]) / 2) ** 2
    os.makedirs(cache_dir, exist_ok=True)
    np.savez_compressed(path, image=image, noise_sq=noise_sq)
    write_exr(os.path.join(cache_dir, f'ref-{case.name}-{key}.exr'), image.astype(np.float32))
    del mi
    return Reference(image, noise_sq)


def texture_mask(case: Case, res):
    if case.mask is None:
        return None
    a = _render(_load(case, {**case.mask[0], 'integrator': 'path'}, res), 4, seed=5)
    b = _render(_load(case, {**case.mask[1], 'integrator': 'path'}, res), 4, seed=5)
    return np.abs(a - b).sum(-1) > 1e-4


#: Rows below a far edge counted as the edge's (they hold its silhouette pixels); the rest of
#: the plane is its interior.
EDGE_ROWS = 3


def rows_below_edge(mask):
    """Per pixel of the textured ``mask``, how many rows it lies below the plane's far edge in
    its column (the column's topmost textured pixel); -1 off the plane."""
    h = mask.shape[0]
    top = np.argmax(mask, axis=0)
    below = np.arange(h)[:, None] - top[None, :]
    return np.where(mask, below, -1)


@dataclass
class EdgeErrors:
    """RMSE next to a far edge: in each of the first :data:`EDGE_ROWS` rows and the reference
    noise there, in the interior below them and that interior's reference noise, and the edge
    rows' share of the squared error over the plane."""
    by_row: list
    interior: float
    interior_noise: float
    edge_share: float
    row_noise: list


def edge_errors(img, ref: Reference, below) -> EdgeErrors:
    sq = ((img - ref.image) ** 2).mean(-1)
    by_row = [float(np.sqrt(sq[below == k].mean())) if (below == k).any() else 0.0
              for k in range(EDGE_ROWS)]
    inner = below >= EDGE_ROWS
    edge = (below >= 0) & ~inner
    total = sq[below >= 0].sum()
    return EdgeErrors(by_row, float(np.sqrt(sq[inner].mean())), ref.noise(inner),
                      float(sq[edge].sum() / total) if total > 0 else 0.0,
                      [ref.noise(below == k) for k in range(EDGE_ROWS)])


def errors(img, ref, mask):
    diff = img - ref
    rmse = float(np.sqrt(np.mean(diff ** 2)))
    rmse_tex = float(np.sqrt(np.mean(diff[mask] ** 2))) if mask is not None and mask.any() else rmse
    li, lr = img @ LUM, ref @ LUM
    rel = float(np.mean(np.abs(li - lr) / np.maximum(lr, 0.01)))
    return rmse, rmse_tex, rel


def _interp_time(points, target):
    """Time at which a (time, error) curve (error decreasing with time) reaches ``target`` error,
    by log-log interpolation; None if it never does."""
    pts = sorted(points)
    for (t0, e0), (t1, e1) in zip(pts, pts[1:]):
        if e0 >= target >= e1 and e0 > e1:
            a = (math.log(e0) - math.log(target)) / (math.log(e0) - math.log(e1))
            return math.exp(math.log(t0) + a * (math.log(t1) - math.log(t0)))
    if pts and pts[0][1] <= target:
        return pts[0][0]
    return None


# ---------------------------------------------------------------------------------------- main
def run(scene_names=None, quick=False, out_dir='bench-out', repeats=None, ref_spp=None,
        variant='llvm_ad_rgb', log=None, mitsuba_data=None):
    import drjit as dr
    import mitsuba as mi

    import mitsuba_pbrt_tex as mpt

    def default_log(msg):
        print(msg, file=sys.stderr, flush=True)

    log = log or default_log
    mi.set_variant(variant)
    mpt.register()
    base_res = (64, 36) if quick else (320, 180)
    # up to 1024 spp: pixel footprints reach errors that 256 spp of point sampling does not
    builtin_spp = [1, 4, 16] if quick else [1, 4, 16, 64, 256, 1024]
    ours_spp = [1, 4] if quick else [1, 4, 16, 64]
    repeats = repeats or (1 if quick else 3)
    ref_spp = ref_spp or (64 if quick else 4096)
    cache_dir = os.path.join(out_dir, 'cache')
    every = cases(mitsuba_data, cache_dir)
    selected = [c for c in every if not scene_names or c.name in scene_names]
    unknown = set(scene_names or []) - {c.name for c in every}
    if unknown:
        hint = ('; matpreview-photo needs --mitsuba-data DIR (without it the real-scene case is '
                'its look-alike, envlit-photo)' if 'matpreview-photo' in unknown else '')
        _usage_error(f'unknown scene(s) {", ".join(sorted(unknown))}; scenes: '
                     f'{", ".join(c.name for c in every)}{hint}')
    os.makedirs(out_dir, exist_ok=True)
    rows, summary, t_start = [], [], time.perf_counter()
    total = sum(len(c.methods) for c in selected)
    done = 0
    for case in selected:
        log(f'[{case.name}] {case.description}')
        res = base_res if quick or case.res is None else case.res
        ref = reference(case, res, ref_spp, cache_dir, log)
        mask = texture_mask(case, res)
        below = rows_below_edge(mask) if case.far_edge else None
        for m in case.methods:
            done += 1
            scene = _load(case, m.params, res)
            t0 = time.perf_counter()
            _render(scene, 1, seed=1)
            first = time.perf_counter() - t0
            compile_s = None
            # next to a far edge pixel footprints reach errors that 1024 spp do not
            deep = [4 * builtin_spp[-1]] if case.far_edge and not quick else []
            for spp in (ours_spp if m.ours else builtin_spp + deep):
                times, errs, edges = [], [], []
                for r in range(repeats):
                    dr.sync_thread()
                    t0 = time.perf_counter()
                    img = _render(scene, spp, seed=10 + r)
                    dr.sync_thread()
                    times.append(time.perf_counter() - t0)
                    errs.append(errors(img, ref.image, mask))
                    if below is not None:
                        edges.append(edge_errors(img, ref, below))
                e = np.mean(np.array(errs), axis=0)
                t = float(np.median(times))
                if compile_s is None:               # first call minus a warm call, both 1 spp
                    compile_s = max(0.0, first - t)
                rows.append(dict(scene=case.name, method=m.name, ours=m.ours, group=m.group,
                                 spp=spp, time_s=t, compile_s=compile_s,
                                 rmse=e[0], rmse_textured=e[1], rel_error=e[2],
                                 reference_noise=ref.noise(), **_edge_columns(edges)))
                log(f'  [{done}/{total}] {m.name:42s} spp {spp:4d}  {t * 1e3:8.1f} ms  '
                    f'RMSE {e[0]:.5f} (textured {e[1]:.5f})  '
                    f'elapsed {time.perf_counter() - t_start:6.0f} s')
        pairs = 1 if quick else PAIRS
        summary += (summarize(case, rows) + far_edge_lines(case, rows)
                    + frame_ratio_lines(case, res, pairs, variant, log)
                    + at_builtin_errors(case, rows)
                    + drop_in_lines(case, res, builtin_spp, pairs, variant, log))
    summary += compare_groups(rows)
    write_outputs(rows, summary, out_dir, base_res, ref_spp, variant, repeats, quick)
    return rows, summary


def _edge_columns(edges) -> dict:
    """The far-edge figures of repeated renders, averaged (empty without a far edge)."""
    if not edges:
        return dict(edge_rows='', edge_noise='', rmse_interior='', interior_noise='',
                    edge_share='')
    return dict(edge_rows=' '.join(f'{np.mean([e.by_row[k] for e in edges]):.4f}'
                                   for k in range(EDGE_ROWS)),
                edge_noise=' '.join(f'{n:.4f}' for n in edges[0].row_noise),
                rmse_interior=float(np.mean([e.interior for e in edges])),
                interior_noise=edges[0].interior_noise,
                edge_share=float(np.mean([e.edge_share for e in edges])))


def far_edge_lines(case: Case, rows) -> list[str]:
    """Where a plane ends in the image: the footprint methods' interior error against the
    reference noise there, and what the edge rows hold, at 1 spp."""
    if not case.far_edge:
        return []
    lines = []
    for r in rows:
        if r['scene'] == case.name and r['spp'] == 1 and r['group'] == 'footprint':
            ratio = r['rmse_interior'] / max(r['interior_noise'], 1e-12)
            lines.append(f'  - *{r["method"]}* at 1 spp: interior (≥ {EDGE_ROWS} rows below the '
                         f'far edge) RMSE {r["rmse_interior"]:.4f} = **{ratio:.1f}×** the '
                         f'reference noise there ({r["interior_noise"]:.4f}); the first '
                         f'{EDGE_ROWS} rows {r["edge_rows"]} (reference noise there '
                         f'{r["edge_noise"]}; {100 * r["edge_share"]:.0f}% of the error²)')
    if lines:
        lines.insert(0, f'- **{case.name}**, by distance from the far edge:')
    return lines


def summarize(case: Case, rows) -> list[str]:
    mine = [r for r in rows if r['scene'] == case.name]
    ours1 = [r for r in mine if r['ours'] and r['spp'] == 1]
    if not ours1:
        return []
    best = min(ours1, key=lambda r: r['rmse_textured'])
    lines = []
    noise = mine[0]['reference_noise']
    for bname in sorted({r['method'] for r in mine if not r['ours']}):
        curve = [(r['time_s'], r['rmse_textured']) for r in mine if r['method'] == bname]
        max_spp = max(r['spp'] for r in mine if r['method'] == bname)
        lines.append(f'- **{case.name}**: best of ours at 1 spp is *{best["method"]}* '
                     f'(RMSE {best["rmse_textured"]:.4f} on the textured pixels, '
                     f'{best["time_s"] * 1e3:.0f} ms); {bname} reaches that error '
                     f'at an equal-error speed-up of **{_speedup(curve, best, max_spp)}** '
                     f'(reference noise RMSE {noise:.5f}).')
        # the footprint methods one by one: with and without silhouette samples
        for r in sorted((r for r in ours1 if r['group'] == 'footprint' and r is not best),
                        key=lambda r: r['method']):
            lines.append(f'  - *{r["method"]}* (RMSE {r["rmse_textured"]:.4f}, '
                         f'{r["time_s"] * 1e3:.0f} ms): equal-error speed-up over {bname} '
                         f'**{_speedup(curve, r, max_spp)}**.')
    return lines


def at_builtin_errors(case: Case, rows) -> list[str]:
    """For scenes where lighting noise dominates: each of our methods' equal-error speed-up at
    the errors the built-in reaches at ``case.at_builtin_spp`` (its time there over the time we
    need for that error, interpolated on our curve; '< x' where we never get there within our
    spp)."""
    mine = [r for r in rows if r['scene'] == case.name]
    lines = []
    for bname in sorted({r['method'] for r in mine if not r['ours']}):
        base = {r['spp']: r for r in mine if r['method'] == bname}
        points = [base[n] for n in case.at_builtin_spp if n in base]
        if not points:
            continue
        for mname in dict.fromkeys(r['method'] for r in mine if r['ours']):
            curve = [(r['time_s'], r['rmse_textured']) for r in mine if r['method'] == mname]
            ratios = []
            for b in points:
                t = _interp_time(curve, b['rmse_textured'])
                ratios.append(f'{b["time_s"] / t:.2f}×' if t else
                              f'< {b["time_s"] / max(tt for tt, _ in curve):.2f}×')
            lines.append(f'  - *{mname}* at the errors of {bname} at '
                         f'{" / ".join(str(b["spp"]) for b in points)} spp: '
                         f'**{" / ".join(ratios)}**')
    if lines:
        lines.insert(0, f'- **{case.name}** (lighting noise dominates): equal-error speed-ups '
                        f'where the built-in\'s samples are spent')
    return lines


def _in_turn(pairs) -> str:
    """How a paired timing was taken (opens a bracket the caller closes)."""
    return (f'one render of each in turn ({pairs} pair{"s" if pairs != 1 else ""}, each '
            f'configuration in a process of its own')


def drop_in_lines(case: Case, res, builtin_spp, pairs, variant, log) -> list[str]:
    """For a case with a drop-in method (the same image as the built-in): the built-in's time
    over the drop-in's, render against render in two processes (:mod:`.paired`), at the spp of
    ``case.at_builtin_spp`` the built-in was run at."""
    drop_in = [m for m in case.methods if m.group == 'drop-in']
    builtin = [m for m in case.methods if not m.ours]
    spp_list = [n for n in case.at_builtin_spp if n in builtin_spp]
    if not drop_in or not builtin or not spp_list:
        return []
    from .paired import paired_ratios
    log(f'  {drop_in[0].name} against {builtin[0].name}: {pairs} pairs of renders per spp')
    ratios = paired_ratios(_load, (case, builtin[0].params, res), (case, drop_in[0].params, res),
                           spp_list, pairs, variant)
    diff = max(r.max_image_diff for r in ratios)
    return [f'  - *{drop_in[0].name}* against {builtin[0].name}, {_in_turn(pairs)} at each spp; '
            f'the images differ by at most {diff:.1e}, so this is the equal-error speed-up): at '
            f'{" / ".join(str(r.spp) for r in ratios)} spp **'
            f'{" / ".join(r.text() for r in ratios)}** (median of the pairs\' time ratios, '
            f'quartiles in brackets)']


def frame_ratio_lines(case: Case, res, pairs, variant, log) -> list[str]:
    """On a far-edge case with pixel footprints: the 1-spp frame of ``PIXEL_BOX`` over
    ``pbrt_path`` + bilinear's, and on a Gaussian film also over the same method's on a box
    film — render against render, each configuration in a process of its own (:mod:`.paired`),
    so that the ratio does not carry the machine's drift between the methods' own timings."""
    by_name = {m.name: m for m in case.methods}
    box, bilinear = by_name.get(PIXEL_BOX), by_name.get('pbrt_imagemap bilinear')
    if not case.far_edge or box is None or bilinear is None:
        return []
    from .paired import paired_ratios
    others = [('`pbrt_path` + bilinear', bilinear.params)]
    if box.params.get('rfilter', 'box') != 'box':
        others.append(('the same on a box film', {**box.params, 'rfilter': 'box'}))
    lines = [f'- **{case.name}**, frame cost:']
    for label, params in others:
        log(f'  {PIXEL_BOX} against {label}: {pairs} pairs of 1-spp renders')
        r, = paired_ratios(_load, (case, box.params, res), (case, params, res), [1], pairs,
                           variant)
        lines.append(f'  - *{PIXEL_BOX}*: its 1-spp frame over {label}\'s, {_in_turn(pairs)}): '
                     f'**{r.text()}** (median of the pairs\' ratios, quartiles in brackets)')
    return lines


def _speedup(curve, row, max_spp) -> str:
    """Time the (time, error) ``curve`` needs for ``row``'s error, over ``row``'s time."""
    t_eq = _interp_time(curve, row['rmse_textured'])
    if t_eq is None:
        tmax = max(t for t, _ in curve)
        return f'> {tmax / row["time_s"]:.1f}× (never reached within {max_spp} spp)'
    return f'{t_eq / row["time_s"]:.1f}×'


def compare_groups(rows) -> list[str]:
    lines = []
    for group in ('trilinear-width', 'ewa-anisotropy'):
        g = [r for r in rows if r['group'] == group]
        if not g:
            continue
        wins, points = {}, 0
        for scene in sorted({r['scene'] for r in g}):
            for spp in sorted({r['spp'] for r in g if r['scene'] == scene}):
                pts = [r for r in g if r['scene'] == scene and r['spp'] == spp]
                if len(pts) < 2:
                    continue
                # equal time: compare error per unit time ratio — these pairs cost about the same,
                # so compare error at the same spp and report the time ratio too
                best = min(pts, key=lambda r: r['rmse_textured'])
                wins[best['method']] = wins.get(best['method'], 0) + 1
                points += 1
        if points:
            ordered = sorted(wins.items(), key=lambda kv: -kv[1])
            times = {}
            for r in g:
                times.setdefault(r['method'], []).append(r['time_s'])
            tmean = {k: float(np.mean(v)) for k, v in times.items()}
            lines.append(f'- **{group}**: lowest error in ' + ', '.join(
                f'*{k}* {v}/{points}' for k, v in ordered) + ' (scene, spp) points; mean times '
                + ', '.join(f'{k} {tmean[k] * 1e3:.0f} ms' for k in sorted(tmean)) + '.')
    return lines


def write_outputs(rows, summary, out_dir, res, ref_spp, variant, repeats, quick=False):
    keys = ['scene', 'method', 'ours', 'group', 'spp', 'time_s', 'compile_s', 'rmse',
            'rmse_textured', 'rel_error', 'reference_noise', 'rmse_interior', 'interior_noise',
            'edge_rows', 'edge_noise', 'edge_share']
    with open(os.path.join(out_dir, 'results.csv'), 'w', newline='') as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: r[k] for k in keys})
    from ..docs import QUICK_MARK
    head = f'{QUICK_MARK}, not a measurement) ' if quick else 'Benchmark: '
    md = [f'{head}{res[0]}×{res[1]}, reference {ref_spp} spp, median of {repeats} timed '
          f'render(s) after a warm-up, variant {variant}, {os.cpu_count()} CPU threads.', '',
          '| scene | method | spp | time (ms) | compile (ms) | RMSE | RMSE textured | rel. error |',
          '|---|---|---|---|---|---|---|---|']
    for r in rows:
        md.append(f'| {r["scene"]} | {r["method"]} | {r["spp"]} | {r["time_s"] * 1e3:.1f} | '
                  f'{r["compile_s"] * 1e3:.0f} | {r["rmse"]:.5f} | {r["rmse_textured"]:.5f} | '
                  f'{r["rel_error"]:.4f} |')
    md += ['', '## Summary', ''] + summary
    with open(os.path.join(out_dir, 'results.md'), 'w') as f:
        f.write('\n'.join(md) + '\n')
    try:
        charts(rows, out_dir)
    except ImportError:
        print('matplotlib is not installed: no charts (pip install "mitsuba-pbrt-tex[bench]")',
              file=sys.stderr)
    print('\n'.join(md))


def charts(rows, out_dir):
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    scenes = list(dict.fromkeys(r['scene'] for r in rows))
    cols = min(3, len(scenes))
    nrows = int(math.ceil(len(scenes) / cols))
    fig_all, axes = plt.subplots(nrows, cols, figsize=(6 * cols, 4.5 * nrows), squeeze=False)
    for i, scene in enumerate(scenes):
        fig, ax = plt.subplots(figsize=(7, 5))
        for target in (ax, axes[i // cols][i % cols]):
            for method in dict.fromkeys(r['method'] for r in rows if r['scene'] == scene):
                pts = [r for r in rows if r['scene'] == scene and r['method'] == method]
                style = '-o' if pts[0]['ours'] else '--s'
                target.loglog([p['time_s'] for p in pts], [p['rmse_textured'] for p in pts],
                              style, label=method, markersize=4)
                for p in pts:
                    target.annotate(str(p['spp']), (p['time_s'], p['rmse_textured']), fontsize=6)
            target.set_title(scene)
            target.set_xlabel('time per render (s)')
            target.set_ylabel('RMSE vs reference (textured pixels)')
            target.grid(True, which='both', alpha=0.3)
            target.legend(fontsize=6)
        save_figure(fig, os.path.join(out_dir, f'chart_{scene}.png'), 110)
    for j in range(len(scenes), nrows * cols):
        axes[j // cols][j % cols].axis('off')
    save_figure(fig_all, os.path.join(out_dir, 'charts.png'), 90)


def main(argv=None) -> int:
    from ..cli import command_parser, output_folder, positive_int, variant_name
    ap = command_parser('bench render', __doc__)
    ap.add_argument('--scenes', nargs='*', default=None,
                    help='subset of: ' + ', '.join(c.name for c in cases(work_dir=None)))
    ap.add_argument('--quick', action='store_true', help='tiny resolution and few spp (smoke test)')
    ap.add_argument('--out', type=output_folder, default='bench-out',
                    help='output folder (default bench-out)')
    ap.add_argument('--repeats', type=positive_int, default=None,
                    help='timed renders per point')
    ap.add_argument('--ref-spp', type=positive_int, default=None,
                    help='reference samples per pixel')
    ap.add_argument('--variant', type=variant_name, default='llvm_ad_rgb',
                    help='Mitsuba variant')
    ap.add_argument('--mitsuba-data', default=None, metavar='DIR',
                    help="a checkout of mitsuba-renderer/mitsuba-data: the real-scene case then "
                         "renders Mitsuba's own matpreview scene with its floor_tiles.jpg (else "
                         "the bundled look-alike)")
    args = ap.parse_args(argv)
    run(args.scenes, args.quick, args.out, args.repeats, args.ref_spp, args.variant,
        mitsuba_data=args.mitsuba_data)
    return 0
