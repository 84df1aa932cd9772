"""tools/mitsuba_suite.py (the harness running Mitsuba's own tests with pbrt_imagemap): what it
substitutes, which scenes it finds, the tree it builds. Mitsuba's tests and data are not here;
the harness itself is run by hand (README, "Use")."""

import importlib.util
import os

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def load_suite():
    spec = importlib.util.spec_from_file_location(
        'mitsuba_suite_under_test', os.path.join(ROOT, 'tools', 'mitsuba_suite.py'))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)           # inert: no harness configuration in the environment
    return mod


def test_substitute_only_texture_types():
    ms = load_suite()
    text = ('<texture name="a" type="bitmap"/>\n'
            "<texture type='bitmap' name='b'>\n"
            '<texture\n    name="c"\n    type="bitmap">\n'
            '<texture type="checkerboard"/>\n'
            '<string name="filename" value="bitmap.png"/>\n'
            '<emitter type="bitmap"/>\n')
    out, n = ms.substitute(text, 'pbrt_imagemap')
    assert n == 3
    assert out == ('<texture name="a" type="pbrt_imagemap"/>\n'
                   "<texture type='pbrt_imagemap' name='b'>\n"
                   '<texture\n    name="c"\n    type="pbrt_imagemap">\n'
                   '<texture type="checkerboard"/>\n'
                   '<string name="filename" value="bitmap.png"/>\n'
                   '<emitter type="bitmap"/>\n')
    assert ms.substitute(text, 'bitmap') == (text, 3)


def write(path, text):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, 'w') as f:
        f.write(text)


def fake_data(tmp_path):
    data = tmp_path / 'data'
    scenes = data / 'tests' / 'scenes'
    write(str(scenes / 'a' / 'test_direct_path.xml'), '<scene><texture type="bitmap"/></scene>')
    write(str(scenes / 'a' / 'test_included_path.xml'),
          '<scene><include filename="fragments/f.xml"/></scene>')
    write(str(scenes / 'a' / 'fragments' / 'f.xml'),
          '<scene><include filename="g.xml"/><include filename="f.xml"/></scene>')
    write(str(scenes / 'a' / 'fragments' / 'g.xml'), "<scene><texture type='bitmap'/></scene>")
    write(str(scenes / 'b' / 'test_plain_direct.xml'),
          '<scene><include filename="missing.xml"/><texture type="checkerboard"/></scene>')
    write(str(scenes / 'a' / 'refs' / 'test_direct_ref_rgb.exr'), 'not an image')
    write(str(data / 'common' / 'textures' / 't.png'), 'not an image')
    return data


def test_textured_scenes_follow_includes(tmp_path):
    ms = load_suite()
    data = fake_data(tmp_path)
    assert ms.scene_files(str(data)) == ['a/test_direct_path.xml', 'a/test_included_path.xml',
                                         'b/test_plain_direct.xml']
    # through an include of an include, with an include cycle and a missing include
    assert ms.textured_scenes(str(data)) == ['a/test_direct_path.xml', 'a/test_included_path.xml']


def test_build_tree(tmp_path):
    ms = load_suite()
    data = fake_data(tmp_path)
    src = tmp_path / 'mi3'
    for rel in [ms.MITSUBA_CONFTEST, *ms.TEST_FILES.values()]:
        write(str(src / rel), f'# {rel}\n')
    root = tmp_path / 'root'
    assert ms.build_tree(str(root), str(src), str(data), 'pbrt_imagemap') == 2
    for d in ('ext', 'include'):
        assert (root / d).is_dir()
    for rel in [ms.MITSUBA_CONFTEST, *ms.TEST_FILES.values()]:
        assert (root / rel).read_text() == f'# {rel}\n'
    copy = root / 'resources' / 'data'
    scene = copy / 'tests' / 'scenes' / 'a'
    assert (scene / 'test_direct_path.xml').read_text() == \
        '<scene><texture type="pbrt_imagemap"/></scene>'
    assert (scene / 'fragments' / 'g.xml').read_text() == \
        "<scene><texture type='pbrt_imagemap'/></scene>"
    assert not (scene / 'test_direct_path.xml').is_symlink()
    # everything else linked, folders real (the tests write error images next to the scene)
    ref = scene / 'refs' / 'test_direct_ref_rgb.exr'
    assert ref.is_symlink() and os.path.realpath(ref) == \
        os.path.realpath(data / 'tests' / 'scenes' / 'a' / 'refs' / 'test_direct_ref_rgb.exr')
    assert not (scene / 'refs').is_symlink() and (copy / 'common' / 'textures' / 't.png').is_symlink()
    # the data itself is left as it was
    assert (data / 'tests' / 'scenes' / 'a' / 'test_direct_path.xml').read_text() == \
        '<scene><texture type="bitmap"/></scene>'


def test_load_dict_retyping_and_summary():
    ms = load_suite()
    proxy = ms._MitsubaProxy({'texture': 'pbrt_imagemap', 'integrator': 'scene'})
    d = {'type': 'diffuse', 'reflectance': {'type': 'bitmap', 'filename': 'bitmap'},
         'nested': {'type': 'mask', 'opacity': {'type': 'bitmap'}}, 'data': [1, 2]}
    assert proxy._retype(d) == {
        'type': 'diffuse', 'reflectance': {'type': 'pbrt_imagemap', 'filename': 'bitmap'},
        'nested': {'type': 'mask', 'opacity': {'type': 'pbrt_imagemap'}}, 'data': [1, 2]}
    assert d['reflectance']['type'] == 'bitmap'          # the test's own dict is not changed
    rec = dict(file='test_renders.py', scene='a/s_path.xml', integrator='path', variant='v',
               texture='t')
    rows = ms.summarise([
        dict(rec, run_integrator='scene', flags='f0', outcome='passed'),
        dict(rec, run_integrator='scene', flags='f1', outcome='failed', message='m'),
        dict(rec, run_integrator='pbrt_path', flags='f0', outcome=None),
        dict(file='test_bitmap.py', test='test01', params='x=1', variant='v', texture='t',
             outcome='skipped', message='s')])
    assert [(k, r['passed'], r['failed'], r['not run'], r['skipped']) for k, r in rows.items()] == [
        (('test_renders.py', 'a/s_path.xml', 'path', 'v', 't'), 1, 1, 0, 0),
        (('test_renders.py', 'a/s_path.xml', 'pbrt_path', 'v', 't'), 0, 0, 1, 0),
        (('test_bitmap.py', 'test01', '', 'v', 't'), 0, 0, 0, 1)]
    assert list(rows[('test_renders.py', 'a/s_path.xml', 'path', 'v', 't')]['messages'].items()) \
        == [('failed: m', ['f1'])]
