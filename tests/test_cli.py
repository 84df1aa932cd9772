"""Command line: render (EXR + PNG, atomic, never over inputs), info, README in sync."""

import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def cli(*args, check=True):
    r = subprocess.run([sys.executable, '-m', 'mitsuba_pbrt_tex', *args], capture_output=True,
                       text=True, cwd=ROOT, timeout=600)
    if check:
        assert r.returncode == 0, r.stdout + r.stderr
    return r


@pytest.fixture
def small_scene(tmp_path):
    """A copy of the demo scene (small) next to a texture input, in a temporary folder."""
    scene = tmp_path / 'scene.xml'
    shutil.copy(os.path.join(ROOT, 'tests', 'data', 'srgb_11x9.png'), tmp_path / 'tex.png')
    scene.write_text('''<scene version="3.0.0">
  <integrator type="pbrt_path"/>
  <sensor type="perspective"><transform name="to_world"><lookat origin="0,1,3" target="0,0,0" up="0,1,0"/></transform>
    <sampler type="independent"><integer name="sample_count" value="8"/></sampler>
    <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="24"/></film></sensor>
  <emitter type="constant"/>
  <shape type="rectangle"><transform name="to_world"><rotate x="1" angle="-90"/></transform>
    <bsdf type="diffuse"><texture name="reflectance" type="pbrt_imagemap">
      <string name="filename" value="tex.png"/><string name="filter" value="ewa"/></texture></bsdf></shape>
</scene>''')
    return scene


def test_render_writes_exr_and_png(small_scene, tmp_path):
    out = tmp_path / 'out' / 'img.exr'
    r = cli('render', str(small_scene), '-o', str(out), '--spp', '16')
    assert out.exists() and (tmp_path / 'out' / 'img.png').exists()
    assert 'wrote' in r.stdout and 'time:' in r.stdout
    assert 'rendering [' in r.stderr                       # the progress display
    import OpenEXR
    with OpenEXR.File(str(out), separate_channels=True) as f:
        ch = f.channels()
        img = np.stack([ch[c].pixels for c in 'RGB'], -1)
    assert img.shape == (24, 32, 3) and np.isfinite(img).all() and img.mean() > 0
    assert not any(p.name.startswith('.tmp-') for p in (tmp_path / 'out').iterdir())


def _exr(path):
    import OpenEXR
    with OpenEXR.File(str(path), separate_channels=True) as f:
        ch = f.channels()
        return list(ch), {n: np.asarray(c.pixels) for n, c in ch.items()}


def test_render_names_every_films_channels_and_converts_them_for_the_png(small_scene, tmp_path):
    """Films that are not RGB, and Mitsuba's aov integrator (whose film also holds its inner
    integrator's channels, RGBA and AOVs, in another order than the tensor mi.render returns):
    the EXR's channels are the film's own, named as the film names them (as Mitsuba's command
    line writes them), and the PNG shows the image — XYZ converted back to RGB equals the RGB
    film's PNG (the same samples: the film converts each sample to XYZ), luminance is grey.
    Before: the aov integrator's render was lost (writing failed), a luminance_alpha film lost
    its PNG, and XYZ, a luminance film's AOVs and the aov integrator's inner channels were
    written under wrong names (a user trial and a review)."""
    text = small_scene.read_text()
    film = '<integer name="height" value="24"/>'
    outputs = {}
    for name, extra, integrator in (
            ('rgb', '', None),
            ('xyz', '<string name="pixel_format" value="xyz"/>', None),
            ('ya', '<string name="pixel_format" value="luminance_alpha"/>', None),
            ('y_aovs', '<string name="pixel_format" value="luminance"/>',
             '<integrator type="pbrt_path"><string name="aovs" value="duv_dx"/></integrator>'),
            ('aov', '', '<integrator type="aov"><string name="aovs" value="dd.y:depth"/>'
                        '<integrator type="pbrt_path"/></integrator>'),
            ('aov_inner', '', '<integrator type="aov"><string name="aovs" value="dd:depth"/>'
                              '<integrator type="pbrt_path"><string name="aovs" '
                              'value="duv_dx"/></integrator></integrator>')):
        scene = tmp_path / f'{name}.xml'
        body = text.replace(film, film + extra)
        if integrator:
            body = body.replace('<integrator type="pbrt_path"/>', integrator)
        scene.write_text(body)
        out = tmp_path / f'{name}.exr'
        cli('render', str(scene), '-o', str(out), '--spp', '4')
        outputs[name] = _exr(out)
    inner = ['_arg_0.R', '_arg_0.G', '_arg_0.B', '_arg_0.A']
    assert [sorted(outputs[k][0]) for k in ('rgb', 'xyz', 'ya', 'y_aovs', 'aov', 'aov_inner')] \
        == [sorted(n) for n in (['R', 'G', 'B'], ['X', 'Y', 'Z'], ['Y', 'A'],
                                ['Y', 'duv_dx.u', 'duv_dx.v'], ['R', 'G', 'B'] + inner + ['dd.y.T'],
                                ['R', 'G', 'B'] + inner + ['_arg_0.duv_dx.u', '_arg_0.duv_dx.v',
                                                           'dd.T'])]       # (EXR sorts names)
    for key in ('aov', 'aov_inner'):
        _, ch = outputs[key]
        depth = ch['dd.y.T' if key == 'aov' else 'dd.T']
        assert np.isfinite(depth).all() and depth.max() > 1               # a depth, not colour
        for c in 'RGB':                     # the inner integrator's colour is the image's
            np.testing.assert_array_equal(ch[f'_arg_0.{c}'], ch[c])
        assert ch['_arg_0.A'].min() >= -1e-6 and ch['_arg_0.A'].max() <= 1 + 1e-6   # coverage
    _, ch = outputs['aov_inner']
    assert 0 < np.abs(ch['_arg_0.duv_dx.u']).max() < 0.1     # a uv differential, not colour
    import mitsuba as mi
    png = {k: np.array(mi.Bitmap(str(tmp_path / f'{k}.png')), dtype=np.int32)
           for k in ('rgb', 'xyz', 'ya')}
    # 8-bit codes of the same image: at most one code apart (float32 round trip through XYZ)
    assert png['xyz'].shape == png['rgb'].shape and np.abs(png['xyz'] - png['rgb']).max() <= 1
    assert (png['ya'][..., 0] == png['ya'][..., 1]).all() and png['ya'][..., 0].std() > 0


@pytest.mark.parametrize('target', ['scene.exr', 'tex.exr'])
def test_render_never_overwrites_scene_or_inputs(small_scene, tmp_path, target):
    if target == 'scene.exr':
        # output whose PNG twin would be the scene? use the scene itself with .exr: refuse .xml
        r = cli('render', str(small_scene), '-o', str(small_scene), check=False)
        assert r.returncode == 2 and 'must end in .exr' in r.stderr
        return
    before = (tmp_path / 'tex.png').read_bytes()
    r = cli('render', str(small_scene), '-o', str(tmp_path / 'tex.exr'), check=False)
    assert r.returncode == 2 and 'refusing to overwrite' in r.stderr
    assert (tmp_path / 'tex.png').read_bytes() == before


def test_render_sets_scene_parameters_and_protects_what_they_name(small_scene, tmp_path):
    """``-D NAME=VALUE`` sets the scene's ``$NAME`` over its ``<default>`` (as Mitsuba's own
    command line; a scene's documented switches could not be chosen — found in a user trial):
    the film size comes from it, an unknown name is Mitsuba's "unused parameters" error, a
    malformed one argparse's, and a file a parameter names is an input the outputs may not
    overwrite (its PNG twin neither)."""
    text = small_scene.read_text().replace(
        'value="tex.png"', 'value="$image"').replace(
        '<scene version="3.0.0">', '<scene version="3.0.0"><default name="w" value="32"/>'
        '<default name="image" value="tex.png"/>').replace(
        '<integer name="width" value="32"/>', '<integer name="width" value="$w"/>')
    small_scene.write_text(text)
    shutil.copy(tmp_path / 'tex.png', tmp_path / 'other.png')
    out = tmp_path / 'out.exr'
    r = cli('render', str(small_scene), '-o', str(out), '-D', 'w=20', '-D', 'image=other.png',
            '--spp', '1', '-q')
    assert '(20x24, 1 spp' in r.stdout
    r = cli('render', str(small_scene), '-o', str(out), '-D', 'nonsense=3', check=False)
    assert r.returncode == 2 and 'unused parameters' in r.stderr and 'nonsense' in r.stderr
    # the output's missing folders are created before the scene loads (a render must not be
    # lost to an unwritable output), and removed again when it then fails (a user trial found
    # them left behind, empty); a folder that holds something is kept
    r = cli('render', str(small_scene), '-o', str(tmp_path / 'new' / 'deeper' / 'out.exr'),
            '-D', 'nonsense=3', check=False)
    assert r.returncode == 2 and not (tmp_path / 'new').exists()
    (tmp_path / 'kept').mkdir()
    (tmp_path / 'kept' / 'mine.txt').write_text('a file of the user')
    r = cli('render', str(small_scene), '-o', str(tmp_path / 'kept' / 'sub' / 'out.exr'),
            '-D', 'nonsense=3', check=False)
    assert r.returncode == 2 and not (tmp_path / 'kept' / 'sub').exists()
    assert (tmp_path / 'kept' / 'mine.txt').read_text() == 'a file of the user'
    r = cli('render', str(small_scene), '-o', str(out), '-D', 'w', check=False)
    assert r.returncode == 2 and 'argument -D: expected NAME=VALUE' in r.stderr
    # Mitsuba's film takes a width of 0; Dr.Jit then failed with an internal size error
    r = cli('render', os.path.join(ROOT, 'scenes', 'demo.xml'), '-o', str(out), '-D', 'width=0',
            check=False)
    assert r.returncode == 2 and "the film's size is 0x270" in r.stderr, r.stderr
    before = (tmp_path / 'other.png').read_bytes()
    r = cli('render', str(small_scene), '-o', str(tmp_path / 'other.exr'), '-D',
            'image=other.png', check=False)
    assert r.returncode == 2 and 'refusing to overwrite' in r.stderr
    assert (tmp_path / 'other.png').read_bytes() == before


def test_scene_parameters_protect_inputs_under_any_name_mitsuba_takes(tmp_path):
    """Mitsuba replaces the text ``$name`` for any parameter name (``1img``, ``my-mode``; and
    ``$wx`` reads ``$w`` when only ``w`` is set), so the input protection substitutes the same
    way: a ``-D 1img=in.exr`` input was not protected, and ``render -o in.exr`` overwrote it
    (found in a review)."""
    from mitsuba_pbrt_tex.cli import definition
    from mitsuba_pbrt_tex.render import scene_inputs
    for name in ('1img', 'my-mode', 'é'):
        assert definition(f'{name}=in.exr') == (name, 'in.exr')
    (tmp_path / 'in.exr').write_text('mine')
    (tmp_path / 'inx.png').write_text('mine')
    scene = tmp_path / 'scene.xml'
    scene.write_text('<scene version="3.0.0"><texture type="bitmap">'
                     '<string name="filename" value="$1img"/></texture>'
                     '<texture type="bitmap"><string name="filename" value="$wx"/></texture>'
                     '</scene>')
    found = scene_inputs(str(scene), {'1img': 'in.exr', 'w': 'inx.png'})
    assert str((tmp_path / 'in.exr').resolve()) in found
    assert str((tmp_path / 'inx.png.png').resolve()) not in found     # (no such file)
    found = scene_inputs(str(scene), {'w': 'in', '1img': 'x'})
    assert str((tmp_path / 'inx.png').resolve()) not in found          # '$wx' -> 'inx'
    (tmp_path / 'inx').write_text('mine')
    assert str((tmp_path / 'inx').resolve()) in scene_inputs(str(scene), {'w': 'in', '1img': 'x'})
    # a <default> whose value names another parameter: Mitsuba substitutes it as it parses it
    chained = tmp_path / 'chained.xml'
    chained.write_text('<scene version="3.0.0"><default name="img" value="$base"/>'
                       '<texture type="bitmap"><string name="filename" value="$img.exr"/>'
                       '</texture></scene>')
    assert str((tmp_path / 'in.exr').resolve()) in scene_inputs(str(chained), {'base': 'in'})


def test_render_errors_are_clear(tmp_path):
    r = cli('render', str(tmp_path / 'missing.xml'), '-o', str(tmp_path / 'x.exr'), check=False)
    assert r.returncode == 2 and 'does not exist' in r.stderr
    r = cli('render', str(tmp_path), '-o', str(tmp_path / 'x.exr'), check=False)
    assert r.returncode == 2 and 'is a directory; give the scene\'s XML file' in r.stderr


@pytest.mark.parametrize('args, message', [
    (('demo', 'inverse', '--iterations', '0'), 'argument --iterations: must be >= 1, got 0'),
    (('demo', 'inverse', '--res', '-4', '--quick'), 'argument --res: must be >= 1, got -4'),
    (('demo', 'inverse', '--lr', 'nan'), 'argument --lr: must be a finite number > 0, got nan'),
    (('demo', 'horizon', '--width', '0'), 'argument --width: must be >= 1, got 0'),
    (('demo', 'horizon', '--repeats', '0'), 'argument --repeats: must be >= 1, got 0')])
def test_demo_options_are_checked(args, message, tmp_path):
    """Found in a user trial: these ran into an IndexError, a raw Dr.Jit error (exit 3), a NaN
    optimisation, or (``--repeats 0``: NaN timings) an equal-time search doubling spp for
    ever. Now argparse's one-line error, exit 2, before anything renders."""
    r = cli(*args, '--out', str(tmp_path / 'out'), check=False)
    assert r.returncode == 2 and message in r.stderr, r.stderr
    assert not (tmp_path / 'out').exists()


@pytest.mark.parametrize('args, message', [
    (('bench', 'lookups', '--size', '0'), 'argument --size: must be >= 1, got 0'),
    (('bench', 'lookups', '--count', '0'), 'argument --count: must be >= 1, got 0'),
    (('bench', 'lookups', '--repeats', '0'), 'argument --repeats: must be >= 1, got 0'),
    (('bench', 'lookups', '--anisotropy', '0'), 'argument --anisotropy: must be a finite'),
    (('bench', 'lookups', '--anisotropy', '0.5'), 'argument --anisotropy: must be in [1, 256]'),
    (('bench', 'lookups', '--minor', '-1'), 'argument --minor: must be a finite number > 0'),
    (('bench', 'lookups', '--sweep', 'abc'), 'argument --sweep: expected a number, got "abc"'),
    (('bench', 'lookups', '--variant', 'foo'), 'argument --variant: unknown variant "foo"'),
    (('bench', 'lookups', '--variant', 'scalar_rgb'), 'scalar variants are not supported'),
    (('bench', 'render', '--repeats', '-1'), 'argument --repeats: must be >= 1, got -1'),
    (('bench', 'render', '--ref-spp', '0'), 'argument --ref-spp: must be >= 1, got 0'),
    (('bench', 'render', '--out', '{file}/x'), 'argument --out: "{file}/x" is below "{file}"'),
    (('bench', 'integrator', '--repeats', '0'), 'argument --repeats: must be >= 1, got 0'),
    (('bench', 'integrator', '--spp', '-4'), 'argument --spp: must be >= 1, got -4'),
    (('bench', 'pyramid', '--lookups', '0'), 'argument --lookups: must be >= 1, got 0'),
    (('bench', 'memory', '--reloads', '-1'), 'argument --reloads: must be >= 0, got -1'),
    (('bench', 'memory', '--out', '{file}/x.md'), 'its folder "{file}" does not exist'),
    (('bench', 'memory', '--out', '{dir}'), 'argument --out: "{dir}" is a folder, not a file'),
    (('demo', 'inverse', '--out', '{file}/x'), 'argument --out: "{file}/x" is below "{file}"'),
    (('demo', 'horizon', '--out', '{file}'), 'argument --out: "{file}" is a file, not a folder'),
    (('demo', 'horizon', '--out', ''), 'argument --out: the folder name is empty'),
    (('demo', 'horizon', '--out', '{dangling}'), '"{dangling}" is a dangling symbolic link'),
    (('demo', 'horizon', '--out', '{file}/../x'), '"{file}/../x" is below "{file}", a file'),
    (('bench', 'memory', '--out', '{dir}/x.md/'), '"{dir}/x.md/" is not a file name'),
    (('bench', 'memory', '--out', '{file}/../x.md'), 'its folder "{file}/.." does not exist'),
    (('bench', 'memory', '--out', '{dangling}'), '"{dangling}" is a dangling symbolic link'),
    (('bench', 'lookups', '--minor', '1e6', '--size', '16'), 'at most --size (16) texels'),
    (('bench', 'lookups', '--sweep', '3,1e38'), 'at most --size (1024) texels, got 1e+38'),
    (('bench', 'lookups', '--anisotropy', '1e6'), 'argument --anisotropy: must be in [1, 256]'),
    (('render', '{file}', '-o', '{dir}/x.exr', '-D', 'a b=1'), 'argument -D: expected NAME=VALUE'),
    (('render', '{file}', '-o', '{dir}/x.exr', '-D', '$a=1'), 'argument -D: expected NAME=VALUE')])
def test_benchmark_options_are_checked(args, message, tmp_path, capsys):
    """Found in a user trial: each of these ended in 'error: unexpected …' (exit 3, which the
    README calls a bug: a ZeroDivisionError, a Dr.Jit size mismatch, an empty median, NaN
    sizes, an ImportError, NotADirectoryError), or was replaced silently (``--repeats 0``,
    ``--ref-spp 0``: the defaults) or accepted (``--minor -1``), or (an empty, dangling or
    ``file/..`` ``--out``; a minor axis of 1e6; anisotropy 1e6) failed or ran for ever after
    the benchmark (found in a review). Now argparse's one-line error, exit 2, before anything
    runs (parsed in this process: nothing is imported or rendered)."""
    from mitsuba_pbrt_tex import cli as ours
    a_file = tmp_path / 'a_file'
    a_file.write_text('mine')
    os.symlink(tmp_path / 'nowhere', tmp_path / 'dangling')
    fill = {'file': str(a_file), 'dir': str(tmp_path), 'dangling': str(tmp_path / 'dangling')}
    with pytest.raises(SystemExit) as e:
        ours.main([a.format(**fill) for a in args])
    assert e.value.code == 2
    assert message.format(**fill) in capsys.readouterr().err
    assert a_file.read_text() == 'mine'


def test_info_markdown_has_the_mapping_tables_its_plugins_refer_to():
    """``info NAME --markdown`` appended both mapping tables to every plugin, also to those
    without a mapping (found in a user trial); each table now comes with the plugins that
    refer to it (all of them: the README's reference)."""
    from mitsuba_pbrt_tex import docs
    assert 'Mappings' not in docs.markdown(['pbrt_path', 'pbrt_constant'])
    image = docs.markdown(['pbrt_imagemap'])
    assert '2D mapping parameters' in image and '3D mapping parameters' not in image
    solid = docs.markdown(['pbrt_fbm'])
    assert '3D mapping parameters' in solid and '2D mapping parameters' not in solid
    both = docs.markdown()
    assert '2D mapping parameters' in both and '3D mapping parameters' in both


def test_readme_summary_is_replaced_only_by_a_full_run(tmp_path):
    """``info --update-readme --bench-results`` replaces the README's benchmark summary only
    with one covering every scene the README's has: a run of some scenes (``--scenes``) is
    refused, the README unchanged (found in a user trial, with a --quick one-scene run)."""
    from mitsuba_pbrt_tex import docs
    readme = tmp_path / 'README.md'
    readme.write_text(open(os.path.join(ROOT, 'README.md'), encoding='utf-8').read())
    before = readme.read_text()
    partial = tmp_path / 'results.md'
    partial.write_text('Benchmark: 320×180\n\n## Summary\n\n- **grazing-checker**: best of '
                       'ours ...\n')
    with pytest.raises(ValueError, match='no summary of .*grazing-zoneplate'):
        docs.update_readme(str(readme), str(partial))
    assert readme.read_text() == before
    # a full run without --mitsuba-data has the look-alike instead of Mitsuba's scene
    nodata = open(os.path.join(ROOT, 'mitsuba_pbrt_tex', 'bench', 'report', 'results.md'),
                  encoding='utf-8').read().replace('matpreview-photo', 'envlit-photo')
    partial.write_text(nodata)
    with pytest.raises(ValueError, match='without --mitsuba-data'):
        docs.update_readme(str(readme), str(partial))
    assert readme.read_text() == before
    full = os.path.join(ROOT, 'mitsuba_pbrt_tex', 'bench', 'report', 'results.md')
    assert docs.update_readme(str(readme), full) is False     # the README is generated from it


def test_info_lists_every_plugin_and_parameter():
    import mitsuba_pbrt_tex as mpt
    out = cli('info').stdout
    for name in mpt.PLUGINS:
        assert f'{name}:' in out
    for param in ('maxanisotropy', 'trilinearwidth', 'aamode', 'spp_scale', 'uscale', 'to_world'):
        assert param in out


def test_every_parameter_a_plugin_reads_is_documented():
    """Each plugin's docstring table (the source of `info` and the README) names every parameter
    its parser accepts (found by loading the plugin and inspecting what it asked for)."""
    import mitsuba as mi

    import mitsuba_pbrt_tex as mpt
    from mitsuba_pbrt_tex import docs
    from mitsuba_pbrt_tex.params import Params
    from plugin_cases import CASES

    seen = {}
    original = Params.finish

    def spy(self):
        seen.setdefault(self.plugin, set()).update(self.known)
        return original(self)

    Params.finish = spy
    try:
        for name, (params, _) in CASES.items():
            mi.load_dict({'type': name, **params})
        mi.load_dict({'type': 'pbrt_path'})
        mi.load_dict({'type': 'pbrt_checkerboard', 'dimension': 3})
        for mapping in ('spherical', 'cylindrical', 'planar'):
            mi.load_dict({'type': 'pbrt_uv', 'mapping': mapping})
        mi.load_dict({'type': 'pbrt_imagemap', 'data': mi.TensorXf(np.zeros((2, 2, 3), np.float32))})
    finally:
        Params.finish = original
    for name in mpt.PLUGINS:
        documented = {n for r in docs.plugin_rows(name) for n in r.names()}
        missing = seen.get(name, set()) - documented
        assert not missing, f'{name}: parameters read but not documented: {sorted(missing)}'
        assert seen.get(name), name


def test_readme_plugin_reference_is_generated_from_docstrings():
    from mitsuba_pbrt_tex import docs
    readme = open(os.path.join(ROOT, 'README.md')).read()
    assert docs.markdown() in readme, 'README plugin reference is stale: regenerate it with ' \
        '`python -m mitsuba_pbrt_tex info --markdown`'


def test_readme_commands_are_the_ci_commands():
    readme = open(os.path.join(ROOT, 'README.md')).read()
    ci = open(os.path.join(ROOT, '.ci', 'run')).read()
    test_cmd = 'bash .ci/setup.sh test && .venv/bin/python -m pytest -q'
    assert test_cmd in readme and test_cmd in ci
    assert 'bash .ci/setup.sh && .venv/bin/python -m mitsuba_pbrt_tex render scenes/demo.xml' in readme
