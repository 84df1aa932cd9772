"""Every bundled scene loads (XML, in parallel) and renders without NaN; the bundled textures are
what their description says (read by OpenImageIO, recomputed from the description)."""

import os
import subprocess
import sys

import mitsuba as mi
import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENES = os.path.join(ROOT, 'scenes')


@pytest.mark.parametrize('name', ['demo.xml', 'gallery.xml', 'imagemap_filters.xml',
                                  'bench/grazing.xml', 'bench/mappings.xml', 'bench/noise.xml',
                                  'bench/specular.xml'])
def test_scene_renders_without_nan(name):
    kw = {'width': '48', 'height': '27'}
    scene = mi.load_file(os.path.join(SCENES, name), **kw)
    img = np.array(mi.render(scene, spp=2))
    assert np.isfinite(img).all() and img.mean() > 0


@pytest.mark.parametrize('texture', ['tex/checker_mitsuba.xml', 'tex/checker_pbrt.xml', 'tex/image_bitmap_footprint.xml',
                                     'tex/checker_supersample.xml', 'tex/image_bitmap.xml',
                                     'tex/image_pbrt.xml', 'tex/flat.xml'])
def test_bench_texture_variants_load(texture):
    scene = mi.load_file(os.path.join(SCENES, 'bench', 'grazing.xml'), texture=texture,
                         width='16', height='9')
    assert np.isfinite(np.array(mi.render(scene, spp=1))).all()


def _read_oiio(path):
    oiio = pytest.importorskip('OpenImageIO')
    buf = oiio.ImageBuf(path)
    spec = buf.spec()
    return np.asarray(buf.get_pixels(oiio.UINT8)), spec


def test_bundled_textures_are_what_their_description_says():
    """The committed textures against their documented content, read by OpenImageIO (not
    Mitsuba) and recomputed here from the description in ``bench/textures.py``'s docstring —
    not from the generator:

    * checker.png: 512×512 RGB, 16×16 checks of 32 texels, exactly two colours, the light one
      where floor(x/32) + floor(y/32) is even;
    * zoneplate.png: 512×512 grey, round(255·(0.5 + 0.5·cos(π r²/512))) with r from the centre
      to the texel centre — equal within one code value (the rounding of the cosine);
    * grid.png: 256×256 RGB, value 10 on every 16th row and column, elsewhere the ramp
      (30 + 200·x/256, 30 + 200·y/256, 120) within one code value."""
    tex = os.path.join(SCENES, 'textures')
    px, spec = _read_oiio(os.path.join(tex, 'checker.png'))
    assert (spec.width, spec.height, spec.nchannels) == (512, 512, 3)
    y, x = np.mgrid[0:512, 0:512]
    even = ((x // 32) + (y // 32)) % 2 == 0
    colours = np.unique(px.reshape(-1, 3), axis=0)
    assert len(colours) == 2
    light, dark = px[0, 0], px[0, 32]
    assert light.sum() > dark.sum()
    assert np.all(px[even] == light) and np.all(px[~even] == dark)

    px, spec = _read_oiio(os.path.join(tex, 'zoneplate.png'))
    assert (spec.width, spec.height, spec.nchannels) == (512, 512, 1)
    yc, xc = np.mgrid[0:512, 0:512] + 0.5
    want = 255 * (0.5 + 0.5 * np.cos(np.pi * ((xc - 256) ** 2 + (yc - 256) ** 2) / 512))
    assert np.abs(px[..., 0].astype(float) - want).max() <= 1.0

    px, spec = _read_oiio(os.path.join(tex, 'grid.png'))
    assert (spec.width, spec.height, spec.nchannels) == (256, 256, 3)
    y, x = np.mgrid[0:256, 0:256]
    line = (x % 16 == 0) | (y % 16 == 0)
    ramp = np.stack([30 + 200 * x / 256, 30 + 200 * y / 256, np.full(x.shape, 120.0)], -1)
    assert np.all(px[line] == 10)
    assert np.abs(px[~line].astype(float) - ramp[~line]).max() <= 1.0


def test_parallel_load_in_a_fresh_process_does_not_deadlock():
    """Several image textures of one file, trilinear and EWA, constructed on Mitsuba's worker
    threads in a fresh process (nothing cached): this used to deadlock the thread pool."""
    code = ('import mitsuba_pbrt_tex as m, mitsuba as mi\n'
            'mi.set_variant("llvm_ad_rgb"); m.register()\n'
            f's = mi.load_file(r"{os.path.join(SCENES, "bench", "mappings.xml")}", width="16", '
            'height="9", parallel=True)\n'
            'import numpy as np; print(np.isfinite(np.array(mi.render(s, spp=1))).all())\n')
    r = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=240)
    assert r.returncode == 0 and r.stdout.strip() == 'True', r.stderr
