"""Every bundled scene loads (XML, in parallel) and renders without NaN; the bundled textures are
what their generator writes."""

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


def test_bundled_textures_match_their_generator(tmp_path):
    from mitsuba_pbrt_tex.bench import textures
    for path in textures.write_all(str(tmp_path)):
        name = os.path.basename(path)
        a = np.array(mi.Bitmap(path))
        b = np.array(mi.Bitmap(os.path.join(SCENES, 'textures', name)))
        np.testing.assert_array_equal(a, b)


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
