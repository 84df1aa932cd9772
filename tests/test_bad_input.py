"""Bad input and hard cases (issue #13): every case gets a clear error or a finite, correct value.

Tables, one row per case:

* ``ERRORS`` — plugin parameters that must be refused at construction, with the fragments the
  message must contain (plugin, parameter, the value, what is accepted);
* ``ACCEPTED`` — the neighbours of those bounds, which must still load;
* value tests — NaN/inf/huge coordinates, footprints and texels, each against an independently
  computed expected value;
* CLI cases — run as subprocesses (a driver process runs many ``cli.main`` calls in a row, to pay
  Python's and Mitsuba's start-up once; cases that need their own process get one): exit status,
  the one ``error:`` line, no traceback, and no file lost or left behind;
* memory — the image cache keeps only what live textures use; builds give their temporaries back.
"""

import gc
import json
import os
import signal
import subprocess
import sys
import time

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from conftest import A, make_si

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DATA = os.path.join(ROOT, 'tests', 'data')


def xml_texture(name, body):
    return mi.load_string(f'<texture version="3.0.0" type="{name}">{body}</texture>')


def rgb(*v):
    return {'type': 'rgb', 'value': list(v)}


def scale_xml(value):
    return f'<transform name="to_world"><scale value="{value}"/></transform>'


def tensor(a):
    return mi.TensorXf(np.asarray(a, dtype=np.float32))


ONE_TEXEL = lambda: tensor(np.full((2, 2, 1), 0.5))     # noqa: E731

# ---------------------------------------------------------------------------------- errors
# (plugin, parameters as a dict, or XML body as a string) → fragments of the error message
ERRORS = [
    # 1e39 overflows float32: refused where it is read, instead of inf everywhere
    ('pbrt_constant', {'value': 1e39}, ['"value"', "float32's range", '1e+39']),
    ('pbrt_constant', {'value': rgb(1e39, 0, 0)}, ['"value"', "float32's range"]),
    ('pbrt_uv', {'uscale': 1e39}, ['"uscale"', "float32's range", '1e+39']),
    ('pbrt_uv', {'vdelta': -1e39}, ['"vdelta"', "float32's range", '-1e+39']),
    ('pbrt_imagemap', {'data': ONE_TEXEL, 'scale': 1e39}, ['"scale"', "float32's range"]),
    ('pbrt_mix', {'amount': 1e39}, ['"amount"', "float32's range", '1e+39']),
    ('pbrt_mix', {'tex1': rgb(0, 1e39, 0)}, ['"tex1"', "float32's range"]),
    ('pbrt_directionmix', {'dir': [1e39, 0, 0]}, ['"dir"', "float32's range"]),
    ('pbrt_uv', '<transform name="to_uv"><scale value="1e39"/></transform>',
     ['"to_uv"', "beyond float32's range"]),
    # singular to_world: refused (planar gave NaN, spherical and 3D textures a constant)
    ('pbrt_uv', '<string name="mapping" value="planar"/>' + scale_xml(0),
     ['"to_world"', 'singular', 'singular values of its 3x3 part: 0, 0, 0', '>= 1e-09']),
    ('pbrt_uv', '<string name="mapping" value="spherical"/>' + scale_xml('1e-30'),
     ['"to_world"', 'singular', '1e-30, 1e-30, 1e-30']),
    ('pbrt_uv', '<string name="mapping" value="cylindrical"/>'
                '<transform name="to_world"><scale x="1" y="1" z="0"/></transform>',
     ['"to_world"', 'singular', '1, 1, 0']),
    ('pbrt_fbm', scale_xml(0), ['"to_world"', 'singular']),
    ('pbrt_marble', scale_xml('1e-30'), ['"to_world"', 'singular']),
    ('pbrt_checkerboard', '<integer name="dimension" value="3"/>' + scale_xml(0),
     ['"to_world"', 'singular']),
    ('pbrt_uv', '<string name="mapping" value="planar"/>'
                '<transform name="to_world"><scale x="1" y="1e-8" z="1"/></transform>',
     ['"to_world"', 'singular', 'largest / 1e+07']),
    # pbrt_directionmix: to_world is blamed, not dir
    ('pbrt_directionmix', scale_xml(0), ['"to_world"', 'singular']),
    # rgb for a float texture: refused instead of its grey mean 0.333
    ('pbrt_scale', {'scale': rgb(1, 0, 0)},
     ['"scale"', 'got an rgb value ([1, 0, 0])', 'float texture']),
    ('pbrt_mix', {'amount': rgb(0.2, 0.5, 0.9)},
     ['"amount"', 'got an rgb value ([0.2, 0.5, 0.9])', 'float texture']),
    # octave weights that overflow float32 (roughness 1e30 gave all zeros)
    ('pbrt_fbm', {'roughness': 1e30},
     ['"roughness"', '1e+30 with 8 octaves', 'roughness <= 5623.41']),
    ('pbrt_wrinkled', {'roughness': 1e30, 'octaves': 3},
     ['"roughness"', '1e+30 with 3 octaves', 'roughness <= 1e+10']),
    ('pbrt_marble', {'roughness': 1e20, 'octaves': 30}, ['"roughness"', 'roughness <= 10']),
    # counts that failed later inside Dr.Jit
    ('pbrt_supersample', {'texture': {'type': 'pbrt_uv'}, 'samples': 2**32},
     ['"samples"', 'must be <= 65536', '4294967296']),
    ('pbrt_path', {'max_depth': 10**10}, ['"max_depth"', 'must be <= 2147483647', '10000000000']),
    ('pbrt_path', '<float name="max_depth" value="1e10"/>', ['"max_depth"', 'must be <= 2147483647']),
    ('pbrt_path', {'rr_depth': 2**40}, ['"rr_depth"', 'must be <= 2147483647']),
    ('pbrt_path', {'silhouette_spp': 2**32}, ['"silhouette_spp"', 'must be <= 65536']),
    ('pbrt_path', {'silhouette_spp': -1}, ['"silhouette_spp"', 'must be >= 0']),
    ('pbrt_path', '<string name="spp_scale" value="-1"/>',
     ['"spp_scale"', 'unknown value "-1"', 'pbrt, none, or a number > 0']),
    # a projective transform reached the plugin as "a any" (a trial)
    ('pbrt_fbm', {'to_world': mi.ScalarProjectiveTransform4f().perspective(60, 0.1, 10)},
     ['"to_world"', 'expected an affine transform', 'got a projective transform']),
    # file names that are not files (an empty name "did not exist" as the scene's folder)
    ('pbrt_imagemap', {'filename': ''}, ['"filename"', 'value "" is empty', 'image file']),
    ('pbrt_imagemap', {'filename': DATA}, ['"filename"', f'"{DATA}" is a directory',
                                           'image file']),
    # a misspelt source: named by the source check, which comes before the unknown-parameter one
    ('pbrt_imagemap', {'filenam': 'x.png'}, ['"filenam": unknown; did you mean "filename"?',
                                             'exactly one of']),
    # Mitsuba's base class read hide_emitters first, with its own message
    ('pbrt_path', {'hide_emitters': 'yes'},
     ['"hide_emitters"', 'expected a boolean (true or false)', "'yes'"]),
]


def _load(name, params):
    if isinstance(params, str):
        if name == 'pbrt_path':
            return mi.load_string(f'<integrator version="3.0.0" type="{name}">{params}'
                                  f'</integrator>')
        return xml_texture(name, params)
    params = {k: (v() if callable(v) else v) for k, v in params.items()}
    return mi.load_dict({'type': name, **params})


@pytest.mark.parametrize('name, params, fragments', ERRORS,
                         ids=[f'{c[0]}-{i}' for i, c in enumerate(ERRORS)])
def test_bad_parameter_is_refused_with_a_clear_message(name, params, fragments):
    with pytest.raises(RuntimeError) as e:
        _load(name, params)
    message = str(e.value)
    for f in [f'{name}: parameter '] + fragments:
        assert f in message, (f, message[-500:])
    if name == 'pbrt_directionmix' and 'to_world' in fragments[0]:
        assert '"dir"' not in message


def _image_file(kind, path):
    """Image files that neither ``bitmap`` nor ``pbrt_imagemap`` can use (a user trial's)."""
    import OpenEXR
    plane = np.random.default_rng(0).uniform(0, 1, (4, 5)).astype(np.float32)
    channels = {'layers': {f'{layer}.{c}': plane for layer in ('diffuse', 'specular')
                           for c in 'RGB'},
                'rg': {'R': plane, 'G': plane}}.get(kind)
    if channels is not None:
        header = {'compression': OpenEXR.ZIP_COMPRESSION, 'type': OpenEXR.scanlineimage}
        with OpenEXR.File(header, channels) as f:
            f.write(path)
    elif kind == 'text':
        with open(path, 'w') as f:
            f.write('not an image\n')
    else:                                           # an OpenEXR file cut short
        mi.Bitmap(np.ones((16, 16, 3), np.float32)).write(path)
        with open(path, 'rb') as f:
            data = f.read()
        with open(path, 'wb') as f:
            f.write(data[:len(data) // 2])


@pytest.mark.parametrize('kind, fragments', [
    ('layers', ['has 2 layers with colour channels (diffuse, specular)',
                'expected R,G,B, X,Y,Z or Y at the top level or in one layer']),
    ('rg', ["has channels ['G', 'R']", 'expected R,G,B, X,Y,Z or Y']),
    ('text', ['cannot read image file', 'its content is not OpenEXR',
              'expected OpenEXR or a format mi.Bitmap reads (PNG, JPEG']),
    ('truncated', ['cannot read OpenEXR file']),
])
def test_image_files_without_a_usable_image_are_refused_with_a_clear_message(kind, fragments,
                                                                               tmp_path):
    """Files that Mitsuba's ``bitmap`` refuses too: several colour layers (the package named
    only R,G,B or Y before; a single layer is read, as ``bitmap`` reads it), R and G alone, a
    text file named ``.exr`` (the reader is chosen by content: the message says the content is
    not OpenEXR where it used to say "cannot read OpenEXR file"), an OpenEXR file cut short.
    The error names the plugin, the parameter, the file and what is accepted; the file is left
    as it was."""
    path = str(tmp_path / 'img.exr')
    _image_file(kind, path)
    with open(path, 'rb') as f:
        before = f.read()
    with pytest.raises(RuntimeError):
        mi.load_dict({'type': 'bitmap', 'filename': path})
    with pytest.raises(RuntimeError) as e:
        mi.load_dict({'type': 'pbrt_imagemap', 'filename': path})
    message = ' '.join(str(e.value).split())
    for f in ['pbrt_imagemap: parameter "filename"', path] + fragments:
        assert f in message, (f, message[-500:])
    with open(path, 'rb') as f:
        assert f.read() == before


def _every_float_parameter():
    """(plugin, parameter) for every parameter whose documented type includes float (the
    docstring tables, the same source as ``info`` and the README)."""
    from mitsuba_pbrt_tex import docs
    from mitsuba_pbrt_tex.registry import PLUGINS
    return [(name, param) for name in PLUGINS for row in docs.plugin_rows(name)
            if 'float' in row.type for param in row.names()]


# what a plugin needs besides the parameter under test
_REQUIRED = {'pbrt_imagemap': {'data': ONE_TEXEL}, 'pbrt_supersample': {'texture': 0.5}}


@pytest.mark.parametrize('value, fragment', [(1e39, "float32's range"), (-3.5e38, "float32's range"),
                                             (float('nan'), 'must be finite'),
                                             (float('inf'), 'must be finite')],
                         ids=['1e39', '-3.5e38', 'nan', 'inf'])
def test_every_float_parameter_refuses_non_float32_values(value, fragment):
    """1e39 passed the finite check and became inf in float32; NaN/inf were refused already.
    Every documented float parameter of every plugin, from its table."""
    cases = _every_float_parameter()
    assert len(cases) >= 30
    for name, param in cases:
        with pytest.raises(RuntimeError) as e:
            _load(name, {**_REQUIRED.get(name, {}), param: value})
        message = str(e.value)
        assert f'{name}: parameter "{param}"' in message and fragment in message, \
            (name, param, message[-300:])


ACCEPTED = [
    ('pbrt_constant', {'value': 3e38}),
    ('pbrt_uv', '<string name="mapping" value="planar"/>' + scale_xml('1e-3')),
    ('pbrt_fbm', {'roughness': 5000.0}),                 # 5000^8 = 3.9e29 ≤ 1e30
    ('pbrt_fbm', {'roughness': 1e30, 'octaves': 1}),
    ('pbrt_supersample', {'texture': {'type': 'pbrt_uv'}, 'samples': 65536}),
    ('pbrt_path', {'max_depth': 2**31 - 1, 'hide_emitters': True}),
    ('pbrt_path', {'max_depth': -1}),
    ('pbrt_mix', {'amount': {'type': 'pbrt_uv'}}),     # a nested texture: its eval_1
    ('pbrt_mix', '<spectrum name="amount" value="0.25"/>'),   # a uniform spectrum is a float
]


@pytest.mark.parametrize('name, params', ACCEPTED, ids=[c[0] for c in ACCEPTED])
def test_values_at_the_bounds_are_accepted(name, params):
    assert _load(name, params) is not None


# ---------------------------------------------------------------------------------- values
BAD_UV = [[np.nan, 0.25], [np.inf, 0.25], [-np.inf, 0.75], [1e30, 1e30], [-1e30, 0.5],
          [0.25, np.nan], [3.0, -2.5]]


def _clamped(x):
    """The documented treatment of coordinates used as values: NaN → 0, clamp to ±1e8."""
    return np.clip(np.nan_to_num(np.asarray(x, np.float64), nan=0.0), -1e8, 1e8)


def test_bilerp_is_finite_and_exact_at_bad_uv():
    corners = {'v00': 0.1, 'v01': 0.7, 'v10': 0.3, 'v11': 2.0}
    t = mi.load_dict({'type': 'pbrt_bilerp', **corners})
    uv = np.array(BAD_UV)
    s, tt = _clamped(uv[:, 0]), _clamped(uv[:, 1])
    want = ((1 - s) * (1 - tt) * 0.1 + (1 - s) * tt * 0.7 + s * (1 - tt) * 0.3 + s * tt * 2.0)
    got = A(t.eval_1(make_si(uv)))
    assert np.isfinite(got).all()
    # float32 evaluation of values up to ~1e16: a few roundings of 6e-8 relative each
    np.testing.assert_allclose(got, want, rtol=1e-6)


def test_bilerp_of_values_near_float32_max_is_finite_and_exact():
    """Corner values up to float32's largest (accepted at construction) at bad uv too: the
    lerps' differences (3e38 - -3e38) overflowed to -inf (found in a user trial). Against the
    float64 formula at the clamped (s, t), rounded to float32 and beyond its range its largest
    finite value of that sign (rtol 1e-6: float32's rounding of the float64 result)."""
    fmax = float(np.finfo(np.float32).max)
    corners = {'v00': 3e38, 'v01': 3e38, 'v10': -3e38, 'v11': -fmax}
    t = mi.load_dict({'type': 'pbrt_bilerp', **corners})
    uv = np.array(BAD_UV + [[0.5, 0.5], [0.25, 0.75], [1.0, 0.0]])
    s, tt = _clamped(uv[:, 0]), _clamped(uv[:, 1])
    a = 3e38 + tt * (3e38 - 3e38)
    b = -3e38 + tt * (-fmax + 3e38)
    want = np.clip(a + s * (b - a), -fmax, fmax).astype(np.float32)
    got = A(t.eval_1(make_si(uv)))
    assert np.isfinite(got).all()
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e32)


@pytest.mark.parametrize('length', [1e-45, 1e-40, 1e-20, 1.0, 1e20, 3e38])
def test_directionmix_direction_of_any_nonzero_length(length):
    """dir is a direction: any non-zero length gives the same texture (float32's squared norm
    of a subnormal vector is 0: dir (0, 0, 1e-40) gave NaN, found in a user trial). With dir
    along the normal the value is tex1's, at 45° the blend's (exact: amount = √½)."""
    t = mi.load_dict({'type': 'pbrt_directionmix', 'tex1': 0.2, 'tex2': 0.8,
                      'dir': mi.ScalarVector3f(0, length, length)})
    si = make_si([[0.5, 0.5]] * 2)
    si.n = mi.Normal3f(mi.Float([0, 0]), mi.Float([0.6, 1]), mi.Float([0.8, 0]))
    got = A(t.eval_1(si))
    amount = np.array([1.4 / np.sqrt(2), 1 / np.sqrt(2)])
    np.testing.assert_allclose(got, 0.2 + (1 - amount) * 0.6, rtol=1e-6)


@pytest.mark.parametrize('d, to_world', [((3e38, 3e38, 0), ('rotate', 45)),
                                         ((0, 1e-44, 0), ('scale', 1e-3)),
                                         ((0, 3e37, 0), ('scale', 100))])
def test_directionmix_transforms_dir_without_overflow(d, to_world):
    """dir through to_world in float64 (found in a review: in float32, (3e38, 3e38, 0) rotated
    by 45° became (0, nan, 0) and was accepted; (0, 1e-44, 0) scaled by 1e-3 was refused as a
    zero vector). Every case points along +y: with the normal along +y the value is tex1's."""
    kind, amount = to_world
    T = mi.ScalarTransform4f
    tw = T().rotate([0, 0, 1], amount) if kind == 'rotate' else T().scale(amount)
    t = mi.load_dict({'type': 'pbrt_directionmix', 'tex1': 0.2, 'tex2': 0.8,
                      'dir': mi.ScalarVector3f(*d), 'to_world': tw})
    si = make_si([[0.5, 0.5]])
    si.n = mi.Normal3f(0, 1, 0)
    np.testing.assert_allclose(A(t.eval_1(si)), [0.2], rtol=1e-6)


def test_uv_texture_is_finite_and_exact_at_bad_uv():
    t = mi.load_dict({'type': 'pbrt_uv'})
    uv = np.array(BAD_UV)
    st = _clamped(uv)
    want = st - np.floor(st)                          # exact in float32 for these inputs
    got = A(t.eval_3(make_si(uv)))
    assert np.isfinite(got).all()
    np.testing.assert_array_equal(got[:, :2], want.astype(np.float32))
    np.testing.assert_array_equal(got[:, 2], 0)


def test_obj_with_huge_vt_renders_finite_pixels(tmp_path):
    """An OBJ whose ``vt`` entries are 1e30 gave NaN pixels through pbrt_bilerp."""
    obj = tmp_path / 'quad.obj'
    obj.write_text('v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\n'
                   'vt 1e30 1e30\nvt 1e30 1e30\nvt 1e30 1e30\nvt 1e30 1e30\n'
                   'f 1/1 2/2 3/3\nf 1/1 3/3 4/4\n')
    scene = mi.load_dict({
        'type': 'scene', 'integrator': {'type': 'pbrt_path', 'max_depth': 2},
        'sensor': {'type': 'perspective', 'to_world': mi.ScalarTransform4f().look_at(
            origin=[0, 0, 3], target=[0, 0, 0], up=[0, 1, 0]),
            'film': {'type': 'hdrfilm', 'width': 8, 'height': 8}},
        'light': {'type': 'constant'},
        'quad': {'type': 'obj', 'filename': str(obj), 'bsdf': {
            'type': 'diffuse', 'reflectance': {'type': 'pbrt_bilerp', 'v00': 0.0, 'v01': 1.0,
                                               'v10': 0.0, 'v11': 1.0}}}})
    img = np.array(mi.render(scene, spp=4))
    # finite (the value is the bilerp far outside [0, 1]²: t = 1 - 1e30 after the OBJ loader's
    # v flip, clamped to -1e8, so the reflectance is -1e8: finite, if not physical)
    assert np.isfinite(img).all() and np.abs(img).max() > 0


def test_supersample_around_bitmap_with_huge_differentials():
    """Mitsuba's bitmap is undefined where uv·resolution overflows an int; the sub-samples stay
    within 1024 texture units of the centre. The offsets are then whole multiples of 128 texture
    units (1024 × the strata centres ±1/8, ±3/8), so on a repeating image every sub-sample
    lands on the centre's texel position: the average equals bitmap at the centre."""
    img = np.array([[0.1, 0.9], [0.4, 0.6]], np.float32)[..., None]
    nested = {'type': 'bitmap', 'bitmap': mi.Bitmap(img), 'raw': True}
    t = mi.load_dict({'type': 'pbrt_supersample', 'texture': nested, 'samples': 16})
    b = mi.load_dict(nested)
    n = 4
    si = make_si([[0.3, 0.7]] * n, duv_dx=[[1e30, 0], [np.inf, 1e9], [1e8, 1e8], [np.nan, 2e3]],
                 duv_dy=[[0, 1e30], [np.nan, 1e9], [1e8, -1e8], [-5e4, np.inf]])
    got = A(t.eval_1(si))
    want = A(b.eval_1(make_si([[0.3, 0.7]])))[0]
    assert np.isfinite(got).all()
    # uv ≈ 0.3 + 384 in float32: spacing 3e-5, times the bilinear slope (≤ 2 per unit · 2 texels)
    np.testing.assert_allclose(got, want, atol=2e-4)


@pytest.mark.parametrize('params, want', [
    ({'type': 'pbrt_mix', 'amount': 3e38, 'tex1': 2.0, 'tex2': 2.0}, 2.0),   # was NaN
    ({'type': 'pbrt_mix', 'amount': 3e38, 'tex1': 0.0, 'tex2': 2.0}, 3.4028235e38),  # was inf
    ({'type': 'pbrt_mix', 'amount': -3e38, 'tex1': 0.0, 'tex2': 2.0}, -3.4028235e38),
    ({'type': 'pbrt_mix', 'amount': 3e38, 'tex1': 0.2, 'tex2': 0.6}, 1.2e38),
    ({'type': 'pbrt_scale', 'scale': 3e38, 'tex': 2.0}, 3.4028235e38),            # was inf
    ({'type': 'pbrt_scale', 'scale': -3e38, 'tex': 3e38}, -3.4028235e38),
], ids=['mix-equal', 'mix-over', 'mix-under', 'mix-finite', 'scale-over', 'scale-under'])
def test_products_of_accepted_values_stay_finite(params, want):
    """Accepted (finite, float32) parameters whose lerp or product leaves float32's range: the
    documented value is float32's largest finite value of the sign; a lerp of equal values is
    that value, whatever the amount. In eval, eval_1, eval_3 and mean (rtol 1e-6: the lerp's
    fma, the 0.6 - 0.2 difference rounded once)."""
    t = mi.load_dict(params)
    si = make_si([[0.3, 0.3], [0.8, 0.1]])
    for got in (A(t.eval(si)), A(t.eval_1(si)), A(t.eval_3(si)), A(t.mean())):
        assert np.isfinite(got).all()
        np.testing.assert_allclose(got, want, rtol=1e-6)


def test_supersample_around_bitmap_at_bad_coordinates():
    """Every combination of bad uv (NaN, ±inf, ±1e30) and bad differentials (huge, NaN, inf) —
    the probe that gave NaN on 576 of 864 lanes, where ``bitmap`` itself is NaN (uv times its
    resolution overflows an int32) — is finite in eval, eval_1 and eval_3; with zero
    differentials the value is bitmap's at the documented coordinate (NaN → 0, uv clamped to
    ±2^17), to the rounding of averaging 16 equal lookups (rtol 1e-6: ≤ 16 roundings)."""
    import itertools
    img = np.array([[0.1, 0.9], [0.4, 0.6]], np.float32)[..., None]
    nested = {'type': 'bitmap', 'bitmap': mi.Bitmap(img), 'raw': True}
    t = mi.load_dict({'type': 'pbrt_supersample', 'texture': nested, 'samples': 16})
    b = mi.load_dict(nested)
    coords = [0.3, np.nan, np.inf, -np.inf, 1e30, -1e30, 1e8]
    parts = [0.0, 1e30, np.inf, np.nan, 2e3]
    rows = np.array([(u, v, dx, dy) for u, v in itertools.product(coords, [0.7, np.nan, 1e30])
                     for dx, dy in itertools.product(parts, parts)])
    si = make_si(rows[:, :2], duv_dx=rows[:, 2:4], duv_dy=rows[:, [3, 2]],
                 p=rows[:, [0, 1, 2]], dp_du=[1, 0, 0], dp_dv=[0, 1, 0])
    assert (~np.isfinite(A(b.eval_1(make_si(rows[:, :2]))))).sum() > 100   # bitmap's NaN lanes
    for method in ('eval', 'eval_1', 'eval_3'):
        assert np.isfinite(A(getattr(t, method)(si))).all(), method
    zero = (rows[:, 2] == 0) & (rows[:, 3] == 0)
    at = np.clip(np.nan_to_num(rows[zero, :2], nan=0.0, posinf=2.0**17, neginf=-2.0**17),
                 -2.0**17, 2.0**17)
    np.testing.assert_allclose(A(t.eval_1(make_si(rows[zero, :2]))), A(b.eval_1(make_si(at))),
                               rtol=1e-6)


def test_nan_texels_through_params_update_become_zero():
    """Construction replaces non-finite texels by 0; the update path does the same."""
    rng = np.random.default_rng(7)
    data = rng.random((8, 8, 3)).astype(np.float32)
    bad = data.copy()
    bad[1, 2, 0], bad[3, 3] = np.nan, np.inf
    bad[7, 0, 2] = -np.inf
    si = make_si(rng.uniform(0, 1, (64, 2)), duv_dx=[[0.2, 0.0]] * 64, duv_dy=[[0.0, 0.05]] * 64)
    for filt in ('bilinear', 'trilinear', 'ewa'):
        tex = mi.load_dict({'type': 'pbrt_imagemap', 'data': tensor(data), 'filter': filt})
        ref = mi.load_dict({'type': 'pbrt_imagemap', 'filter': filt,
                            'data': tensor(np.where(np.isfinite(bad), bad, 0))})
        p = mi.traverse(tex)
        p['data'] = tensor(bad)
        p.update()
        got = A(tex.eval_3(si))
        assert np.isfinite(got).all(), filt
        np.testing.assert_array_equal(got, A(ref.eval_3(si)))
        # the mean (a plastic's or an emitter's weight) is the sanitized texels' too (was NaN)
        np.testing.assert_allclose(A(tex.mean()), A(ref.mean()), rtol=1e-6)


NONFINITE_UPDATES = [   # (texture, key under it, parameter the error names)
    ({'type': 'pbrt_imagemap', 'data': mi.TensorXf(np.full((4, 4, 3), 0.5, np.float32))},
     'scale', 'scale'),
    ({'type': 'pbrt_constant', 'value': 0.5}, 'value', 'value'),
    # a float or rgb value nested in ours: Mitsuba's uniform/srgb texture, checked by its own
    # parameter (its mean overflowed for finite channels of 2e38: refused as inf)
    ({'type': 'pbrt_checkerboard', 'tex1': 0.3}, 'tex1.value', 'tex1.value'),
    ({'type': 'pbrt_scale', 'tex': 0.5, 'scale': 2.0}, 'scale.value', 'scale.value'),
    ({'type': 'pbrt_bilerp'}, 'v00.value', 'v00.value'),
    ({'type': 'pbrt_dots', 'inside': 0.5}, 'inside.value', 'inside.value'),
    ({'type': 'pbrt_mix', 'tex1': {'type': 'rgb', 'value': [0.1, 0.2, 0.3]}}, 'tex1.value',
     'tex1.value'),
    # a pbrt_constant nested in ours: its own check names it
    ({'type': 'pbrt_scale', 'tex': {'type': 'pbrt_constant', 'value': 0.5}}, 'tex.value',
     'value'),
]


@pytest.mark.parametrize('case', range(len(NONFINITE_UPDATES)))
@pytest.mark.parametrize('bad', [float('nan'), float('inf')])
def test_nonfinite_parameters_through_params_update_are_refused(case, bad):
    """NaN and inf are refused at construction; set through mi.traverse they are refused by
    params.update() with the plugin and parameter named (found in a user trial: accepted
    silently, they rendered NaN/inf pixels). Texels are the exception: they become 0 with a
    warning (above)."""
    tex, key, name = NONFINITE_UPDATES[case]
    scene = mi.load_dict({'type': 'scene', 'shape': {'type': 'rectangle', 'bsdf': {
        'type': 'diffuse', 'reflectance': tex}}})
    p = mi.traverse(scene)
    full = 'shape.bsdf.reflectance.' + key
    value, before = p[full], A(p[full])
    p[full] = mi.Color3f(0.2, bad, 0.3) if isinstance(value, mi.Color3f) else type(value)(bad)
    with pytest.raises(Exception) as e:
        p.update()
    plugin = tex['type'] if key == name or name != 'value' else 'pbrt_constant'
    text = str(e.value)
    for word in (f'{plugin}: parameter "{name}"', 'set through mi.traverse is not finite',
                 'accepted values: finite numbers'):
        assert word in text, (word, text)
    # the refused value is not kept: the texture has the value it had (it stayed, and a render
    # after the refusal was NaN or inf everywhere)
    np.testing.assert_array_equal(A(p[full]), before)
    np.testing.assert_array_equal(A(mi.traverse(scene)[full]), before)


@pytest.mark.parametrize('tex, key, width', [
    ({'type': 'pbrt_constant', 'value': 0.5}, 'value', 2),
    ({'type': 'pbrt_constant', 'value': 0.5}, 'value', 0),
    ({'type': 'pbrt_imagemap', 'data': mi.TensorXf(np.full((4, 4, 3), 0.5, np.float32))},
     'scale', 1000)])
def test_parameters_of_another_width_through_params_update_are_refused(tex, key, width):
    """A value of width 2 or 1000 passed params.update() and failed inside Dr.Jit's call of the
    texture at render time; width 0 failed in the finiteness check with a raw Dr.Jit error
    (found in a user trial): refused at the update, naming plugin, parameter and width."""
    scene = mi.load_dict({'type': 'scene', 'shape': {'type': 'rectangle', 'bsdf': {
        'type': 'diffuse', 'reflectance': tex}}})
    p = mi.traverse(scene)
    full = 'shape.bsdf.reflectance.' + key
    before = A(p[full])
    p[full] = dr.full(mi.Float, 0.5, width)
    with pytest.raises(Exception) as e:
        p.update()
    assert f'{tex["type"]}: parameter "{key}": a value of width {width} set through ' \
        f'mi.traverse; accepted values: one number or colour' in str(e.value)
    np.testing.assert_array_equal(A(p[full]), before)      # put back (see below)


@pytest.mark.parametrize('filt, footprint, film', [('bilinear', 'sample', 'gaussian'),
                                                   ('ewa', 'sample', 'gaussian'),
                                                   ('box', 'pixel', 'box'),
                                                   ('box', 'pixel', 'gaussian')])
def test_refused_updates_leave_the_texture_as_it_was(filt, footprint, film):
    """params.update() refuses a data tensor of a shape other than (H, W, 1|3) and a NaN scale;
    the texture then puts back what it last accepted — also a valid value set in the same
    update — so the next render is the one before. Found in a user trial: the refused tensor
    stayed in the texture and the next render ended inside Dr.Jit ('tuple index out of range',
    a loop state changing type) or, for box + pixel footprints, whatever the shape; a NaN scale
    rendered NaN everywhere."""
    texels = np.random.default_rng(3).random((8, 8, 3)).astype(np.float32)
    # renders through a Gaussian film are the same up to the film's multithreaded accumulation
    # order (1e-7 here; the same render twice differs so, with bitmap too); a box film's exactly
    same = dict(rtol=0, atol=0) if film == 'box' else dict(rtol=1e-5, atol=1e-6)

    def load(scale):
        return mi.load_dict({
            'type': 'scene', 'integrator': {'type': 'pbrt_path', 'footprint': footprint},
            'sensor': {'type': 'perspective', 'fov': 40, 'to_world': mi.ScalarTransform4f()
                       .look_at([0, -2, 1], [0, 0, 0], [0, 0, 1]),
                       'film': {'type': 'hdrfilm', 'width': 12, 'height': 8,
                                'rfilter': {'type': film}}},
            'light': {'type': 'constant'},
            'plane': {'type': 'rectangle', 'bsdf': {'type': 'diffuse', 'reflectance': {
                'type': 'pbrt_imagemap', 'filter': filt, 'scale': scale,
                'data': mi.TensorXf(texels)}}}})

    scene = load(1.0)
    before = mi.render(scene, spp=2, seed=1).numpy()
    p = mi.traverse(scene)
    data, scale = 'plane.bsdf.reflectance.data', 'plane.bsdf.reflectance.scale'
    shape = p[data].shape
    for bad in ((192,), (8, 8), (8, 8, 2), (8, 8, 4)):
        p[data] = mi.TensorXf(np.full(bad, 0.5, np.float32))
        p[scale] = mi.Float(0.5)                    # valid, but in the refused update
        with pytest.raises(Exception, match='parameter "data": expected shape'):
            p.update()
        assert p[data].shape == shape and A(p[scale])[0] == 1.0, bad
        np.testing.assert_allclose(mi.render(scene, spp=2, seed=1).numpy(), before, **same)
    p[scale] = mi.Float(float('nan'))
    with pytest.raises(Exception, match='parameter "scale"'):
        p.update()
    np.testing.assert_allclose(mi.render(scene, spp=2, seed=1).numpy(), before, **same)
    p[scale] = mi.Float(0.5)                        # and a valid update still works
    p.update()
    np.testing.assert_allclose(mi.render(scene, spp=2, seed=1).numpy(),
                               mi.render(load(0.5), spp=2, seed=1).numpy(), rtol=1e-6, atol=1e-7)


def test_large_finite_rgb_values_through_params_update_are_accepted():
    """An rgb value of 1.2e38–3e38 per channel is finite and accepted at construction; through
    params.update() it was refused as "value [inf] (its mean)" — the check read the srgb
    texture's mean, which overflows (found in a user trial)."""
    tex = mi.load_dict({'type': 'pbrt_mix', 'tex1': 0.0, 'amount': 0.0,
                        'tex2': {'type': 'rgb', 'value': [0.5, 0.5, 0.5]}})
    p = mi.traverse(tex)
    for v in (1.2e38, 3e38):
        p['tex2.value'] = mi.Color3f(v, v, v)
        p.update()


@pytest.mark.parametrize('filt', ['bilinear', 'trilinear', 'ewa', 'box'])
@pytest.mark.parametrize('source', ['data', 'file'])
def test_texels_near_float32_max_stay_finite(filt, source, tmp_path):
    """Texels beyond ±1e38 are clamped to ±1e38 (with a warning), so every weighted average the
    filters compute stays finite: odd-sized pyramid levels, EWA sums of ~100 taps, the blend of
    two levels, the luminance and the mean overflowed to inf/NaN for values near 3.4e38. A
    uniform image of 3.3e38 or float32's maximum then filters to 1e38 everywhere."""
    fmax = np.finfo(np.float32).max
    img = np.full((9, 11, 3), fmax, np.float32)
    img[::2] = np.float32(3.3e38)
    tex_params = {'type': 'pbrt_imagemap', 'filter': filt}
    if source == 'data':
        tex_params['data'] = tensor(img)
    else:
        from mitsuba_pbrt_tex.outputs import write_exr
        write_exr(str(tmp_path / 'huge.exr'), img)
        tex_params['filename'] = str(tmp_path / 'huge.exr')
    tex = mi.load_dict(tex_params)
    tex.prepare_differentials()
    si = make_si([[0.3, 0.3], [0.7, 0.1], [0.5, 0.5], [0.2, 0.9]],
                 duv_dx=[[0.1, 0], [0.5, 0.2], [0.02, 0], [3.0, 0]],
                 duv_dy=[[0, 0.01], [0, 0.5], [0, 0.02], [0, 3.0]])
    got = A(tex.eval_3(si))
    # normalised weights sum to 1 within float32 rounding (a few ulps; the box filter's walk
    # sums partial weights of both signs, so a constant is itself within its documented 1e-5
    # on a square-ish image — 1.8e-6 measured on the 3-image-width footprint here)
    tol = 1e-5 if filt == 'box' else 1e-6
    np.testing.assert_allclose(got, 1e38, rtol=tol)
    np.testing.assert_allclose(A(tex.eval_1(si)), 1e38, rtol=tol)     # luminance
    np.testing.assert_allclose(A(tex.mean()), 1e38, rtol=1e-6)         # plastic's weight
    assert np.isfinite(np.array(tex.pyramid.buffer)).all()
    if source == 'data':                                                # the update path too
        p = mi.traverse(tex)
        p['data'] = tensor(-img)
        p.update()
        np.testing.assert_allclose(A(tex.eval_3(si)), -1e38, rtol=tol)


@pytest.mark.parametrize('filt', ['trilinear', 'ewa', 'box'])
def test_filters_of_texels_at_the_limit_are_the_scaled_filters_of_small_ones(filt):
    """Filtering is linear: a checker of ±1e38 texels (the limit texels are clamped to) filters
    to 1e38 × the same checker of ±1 — finite, where the box filter's single-cell twist term
    (f00 - f10 - f01 + f11 = 4e38) and its level sums (up to ~10³ texel² of weight) overflowed
    to NaN in a render (found in a user trial). Footprints from inside one cell to a few cells
    across, at lanes the kernel cannot fold to constants. rtol 1e-5: the two lookups round
    alike up to the scale (powers of two in the sums), 1e38 itself is not one."""
    chk = (np.indices((8, 8)).sum(0) % 2 * 2 - 1).astype(np.float32)[..., None].repeat(3, 2)
    sizes = [0.005, 0.01, 0.02, 0.05, 0.2, 0.6]
    si = make_si([[0.3, 0.4]] * len(sizes), duv_dx=[[d, 0.3 * d] for d in sizes],
                 duv_dy=[[0, d] for d in sizes])
    out = []
    for scale in (1.0, 1e38):
        tex = mi.load_dict({'type': 'pbrt_imagemap', 'filter': filt,
                            'data': tensor(chk * np.float32(scale))})
        tex.prepare_differentials()
        out.append(A(tex.eval_3(si)))
    assert np.isfinite(out[1]).all(), out[1]
    np.testing.assert_allclose(out[1], out[0] * 1e38, rtol=1e-5, atol=1e32)


def test_texels_within_the_limit_are_unchanged():
    img = np.array([[[9.9e37], [-1e38]], [[1.0], [-2.5e-30]]], np.float32)
    tex = mi.load_dict({'type': 'pbrt_imagemap', 'filter': 'point', 'data': tensor(img)})
    si = make_si([[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75]])
    np.testing.assert_array_equal(A(tex.eval_1(si)), img.reshape(-1))


@pytest.mark.parametrize('filt', ['point', 'bilinear', 'trilinear'])
def test_black_wrapped_1x1_image_follows_pbrts_top_level_rule(filt):
    """pbrt-v4's MIPMap::Filter returns the top level's texel for footprints whose level is at
    or beyond it: on a 1×1 image any width ≥ 1 (uv units), wherever the lookup is — with
    ``black`` wrap too, whose taps outside the image are 0 (found in a user trial against a port
    of pbrt-v4: 0.48 instead of 0.8 at u = 0.9, 0 at u = 3, while 2×2 images followed the
    rule). Narrower footprints are the level-0 lookup: bilinear at u = 0.9 weighs the texel
    0.6 and black 0.4; point reads the texel inside the image."""
    tex = mi.load_dict({'type': 'pbrt_imagemap', 'filter': filt, 'wrap': 'black',
                        'data': tensor(np.full((1, 1, 1), 0.8, np.float32))})
    tex.prepare_differentials()
    uv = [[0.9, 0.5], [3.0, 0.5], [0.9, 0.5], [3.0, 0.5]]
    d = [1.0, 1.0, 0.4, 0.4]
    got = A(tex.eval_1(make_si(uv, duv_dx=[[w, 0] for w in d], duv_dy=[[0, w] for w in d])))
    narrow = 0.8 if filt == 'point' else 0.8 * 0.6
    np.testing.assert_allclose(got, [0.8, 0.8, narrow, 0.0], rtol=1e-6, atol=1e-7)


def test_ewa_on_a_1x1_image_returns_its_texel_at_any_footprint():
    tex = mi.load_dict({'type': 'pbrt_imagemap', 'filter': 'ewa',
                        'data': tensor(np.full((1, 1, 1), 0.7))})
    fp = [1e8, 1e9, 1e30, np.inf, 1e3, 1.0, 0.3]
    si = make_si([[0.3, 0.6]] * len(fp), duv_dx=[[f, 0] for f in fp],
                 duv_dy=[[0, f] for f in fp])
    got = A(tex.eval_1(si))
    # footprints beyond the image: the single texel, exactly (pbrt returns the top level's
    # texel); inf counts as 0 (a bilinear lookup) and the smaller footprints run the EWA sum
    # over repeated copies of the texel, normalised: both within float32 rounding
    np.testing.assert_array_equal(got[:3], np.float32(0.7))
    np.testing.assert_allclose(got[3:], 0.7, rtol=1e-6)


# ---------------------------------------------------------------------------------- CLI
DRIVER = r'''
import contextlib, io, json, sys
from mitsuba_pbrt_tex.cli import main
results = []
for argv in json.loads(sys.argv[1]):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = main(argv)
        except SystemExit as e:
            rc = e.code
    results.append([rc, out.getvalue(), err.getvalue()])
print('RESULTS ' + json.dumps(results))
'''


def run_cli_batch(argvs, cwd=ROOT):
    """Run ``cli.main(argv)`` for each argv in one subprocess; [(rc, stdout, stderr), ...]."""
    r = subprocess.run([sys.executable, '-c', DRIVER, json.dumps(argvs)], capture_output=True,
                       text=True, cwd=cwd, timeout=600)
    line = [x for x in r.stdout.splitlines() if x.startswith('RESULTS ')]
    assert line, r.stdout[-2000:] + r.stderr[-3000:]
    return json.loads(line[0][8:])


def cli(*args, **kw):
    return subprocess.run([sys.executable, '-m', 'mitsuba_pbrt_tex', *args], capture_output=True,
                          text=True, cwd=ROOT, timeout=600, **kw)


SCENE = '''<scene version="3.0.0">
  {head}
  <integrator type="pbrt_path"/>
  <sensor type="perspective"><transform name="to_world"><lookat origin="0,0,3" target="0,0,0" up="0,1,0"/></transform>
    <sampler type="independent"><integer name="sample_count" value="4"/></sampler>
    <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="12"/></film></sensor>
  <emitter type="constant"/>
  {body}
</scene>'''


def textured(filename, plugin='pbrt_imagemap', extra=''):
    return (f'<shape type="rectangle"><bsdf type="diffuse"><texture name="reflectance" '
            f'type="{plugin}"><string name="filename" value="{filename}"/>{extra}</texture>'
            f'</bsdf></shape>')


@pytest.fixture
def scenes(tmp_path):
    """Scenes that name their texture in the ways the raw-XML check missed, and broken ones."""
    tex = os.path.join(DATA, 'srgb_11x9.png')
    (tmp_path / 'textures').mkdir()
    (tmp_path / 'assets').mkdir()
    for d in ('textures', 'assets', '.'):
        with open(tex, 'rb') as src, open(tmp_path / d / 'tex.png', 'wb') as dst:
            dst.write(src.read())
    w = lambda name, text: (tmp_path / name).write_text(text)       # noqa: E731
    w('default.xml', SCENE.format(head='<default name="f" value="textures/tex.png"/>',
                                  body=textured('$f')))
    w('inc_part.xml', '<scene version="3.0.0">' + textured('textures/tex.png', 'bitmap')
      + '</scene>')
    w('include.xml', SCENE.format(head='', body='<include filename="inc_part.xml"/>'))
    w('resolver.xml', SCENE.format(head='<path value="assets"/>', body=textured('tex.png')))
    w('ok.xml', SCENE.format(head='', body=textured('tex.png')))
    w('plugin_error.xml', SCENE.format(head='', body=textured(
        'tex.png', extra='<string name="filter" value="cubic"/>')))
    w('missing_texture.xml', SCENE.format(head='', body=textured('nowhere.png')))
    w('syntax.xml', SCENE.format(head='', body=textured('tex.png'))[:-30])
    w('no_sensor.xml', '<scene version="3.0.0"><emitter type="constant"/></scene>')
    (tmp_path / 'plain_file').write_text('not a folder')
    (tmp_path / 'outdir.png').mkdir()          # the PNG twin of outdir.exr is a directory
    return tmp_path


def _one_error_line(rc, err, fragments, status=2):
    assert rc == status, (rc, err)
    assert 'Traceback' not in err, err
    lines = [x for x in err.splitlines() if x.strip() and 'WARN' not in x]
    assert len(lines) == 1 and lines[0].startswith('error: '), err
    for f in fragments:
        assert f in lines[0], (f, lines[0])


def test_cli_render_time_errors_name_their_cause(scenes):
    """An error raised inside mi.render reaches Python as the cause of Dr.Jit's custom-operation
    error, which says only "(see above)": the CLI's one line is the cause's (found in a user
    trial: pixel footprints with a tent film filter printed 'rendering failed: drjit.custom(...)
    ... (see above)', with nothing above)."""
    tent = SCENE.format(head='', body=textured('tex.png')).replace(
        '<integrator type="pbrt_path"/>',
        '<integrator type="pbrt_path"><string name="footprint" value="pixel"/></integrator>'
    ).replace('<film type="hdrfilm">', '<film type="hdrfilm"><rfilter type="tent"/>')
    (scenes / 'tent.xml').write_text(tent)
    (rc, _, err), = run_cli_batch([['render', str(scenes / 'tent.xml'), '-o',
                                    str(scenes / 'out' / 'img.exr')]])
    _one_error_line(rc, err, ['rendering failed: pbrt_path: parameter "footprint": value "pixel" '
                              'needs the film filter "box" or "gaussian", got TentFilter; with '
                              'this filter use "sample" (accepted values: sample, pixel)'])


def test_cli_png_twin_replaces_only_earlier_renders(scenes):
    """-o X.exr also writes X.png: an existing X.png of the user's is refused (found in a user
    trial: a holiday photo was replaced silently); an earlier render's PNG (marked when written)
    is replaced; and a marked PNG the scene reads under another name (a hard link) is still an
    input (the path comparison missed hard links)."""
    d = scenes
    (d / 'mine.png').write_bytes(b'my own file')
    first = run_cli_batch([['render', str(d / 'ok.xml'), '-o', str(d / 'mine.exr')],
                           ['render', str(d / 'ok.xml'), '-o', str(d / 'prev.exr')],
                           ['render', str(d / 'ok.xml'), '-o', str(d / 'prev.exr')]])
    _one_error_line(first[0][0], first[0][2], ['refusing to overwrite', 'mine.png',
                                               'not an earlier render'])
    assert (d / 'mine.png').read_bytes() == b'my own file'
    assert not (d / 'mine.exr').exists()
    assert first[1][0] == 0 and first[2][0] == 0, (first[1][2], first[2][2])   # re-render
    os.link(d / 'prev.png', d / 'linked.png')
    (d / 'reads_linked.xml').write_text(SCENE.format(head='', body=textured('linked.png')))
    (rc, _, err), = run_cli_batch([['render', str(d / 'reads_linked.xml'), '-o',
                                    str(d / 'prev.exr')]])
    _one_error_line(rc, err, ['refusing to overwrite', 'prev.png', 'one of its inputs'])


def test_cli_bad_input_battery(scenes):
    """Every user error: one ``error:`` line, exit status 2, nothing rendered or overwritten."""
    d = str(scenes)
    out = os.path.join(d, 'out', 'img.exr')
    cases = [
        # data loss: inputs named through <default>/$f, <include>, the <path> resolver
        (['render', f'{d}/default.xml', '-o', f'{d}/textures/tex.exr'],
         ['refusing to overwrite', 'textures/tex.png', 'one of its inputs']),
        (['render', f'{d}/include.xml', '-o', f'{d}/textures/tex.exr'],
         ['refusing to overwrite', 'textures/tex.png']),
        (['render', f'{d}/resolver.xml', '-o', f'{d}/assets/tex.exr'],
         ['refusing to overwrite', 'assets/tex.png']),
        # unwritable outputs, found before loading and rendering
        (['render', f'{d}/ok.xml', '-o', f'{d}/plain_file/img.exr'],
         ['cannot write', 'plain_file/img.exr', 'a part of the folder path is a file']),
        (['render', f'{d}/ok.xml', '-o', f'{d}/outdir.exr'],
         ['cannot write', 'outdir.png', 'it is a directory']),
        (['render', f'{d}/ok.xml', '-o', '/proc/img.exr'],      # no permission, even for root
         ['cannot write "/proc/img.exr"', 'cannot create a file in "/proc"']),
        (['render', f'{d}/ok.xml', '-o', f'{d}/img.png'], ['must end in .exr']),
        # scene errors
        (['render', f'{d}/plugin_error.xml', '-o', out],
         ['plugin_error.xml (line', 'pbrt_imagemap: parameter "filter": unknown value "cubic"',
          'accepted values: point, bilinear, trilinear, ewa']),
        (['render', f'{d}/missing_texture.xml', '-o', out],
         ['missing_texture.xml (line', 'parameter "filename"', 'nowhere.png" does not exist']),
        (['render', f'{d}/syntax.xml', '-o', out], ['Parsing of XML file', 'syntax.xml', 'failed']),
        (['render', f'{d}/no_sensor.xml', '-o', out], ['has no sensor']),
        (['render', f'{d}/missing.xml', '-o', out], ['missing.xml" does not exist']),
        # variants
        (['render', f'{d}/ok.xml', '-o', out, '--variant', 'scalar_rgb'],
         ['--variant scalar_rgb', 'scalar variants are not supported', 'llvm_ad_rgb']),
        (['render', f'{d}/ok.xml', '-o', out, '--variant', 'llvm_ad_spectral'],
         ['--variant llvm_ad_spectral', 'spectral variants are not supported']),
        (['render', f'{d}/ok.xml', '-o', out, '--variant', 'nonsense'],
         ['--variant nonsense: unknown variant "nonsense"', 'llvm_ad_rgb']),
        # sample counts
        (['render', f'{d}/ok.xml', '-o', out, '--spp', str(2**32)], ['--spp must be <= 4294967295']),
        (['render', f'{d}/ok.xml', '-o', out, '--spp', str(2**31)],
         ['is too many for one image of 16x12', '2^32 - 1']),
        # bench render: the real scene's name without the data it needs (found in a user
        # trial: no "error:" line, exit status 1)
        (['bench', 'render', '--scenes', 'matpreview-photo', '--quick', '--out', f'{d}/bench'],
         ['unknown scene(s) matpreview-photo', 'needs --mitsuba-data DIR', 'envlit-photo']),
        # info --bench-results alone was ignored silently (found in a user trial)
        (['info', '--bench-results', f'{d}/ok.xml'], ['--bench-results is read by --update-readme']),
        # info --update-readme on a file without the markers
        (['info', '--update-readme', f'{d}/ok.xml'],
         ['has no section between the lines <!-- BEGIN PLUGIN REFERENCE -->', 'nothing was changed']),
    ]
    before = {p: (scenes / p).read_bytes() for p in ('textures/tex.png', 'assets/tex.png',
                                                    'tex.png', 'ok.xml', 'inc_part.xml')}
    results = run_cli_batch([c[0] for c in cases])
    for (argv, fragments), (rc, stdout, err) in zip(cases, results):
        _one_error_line(rc, err, fragments)
        assert 'rendering [' not in err, argv                  # refused before rendering
    for p, data in before.items():
        assert (scenes / p).read_bytes() == data, p
    assert not (scenes / 'out').exists() or not any((scenes / 'out').iterdir())
    assert not any(p.name.startswith('.tmp-') for p in scenes.rglob('*'))


def test_cli_spp_zero_and_cuda_without_gpu(scenes):
    r = cli('render', f'{scenes}/ok.xml', '-o', f'{scenes}/o.exr', '--spp', '0')
    _one_error_line(r.returncode, r.stderr, ['argument --spp: must be >= 1, got 0',
                                             'python -m mitsuba_pbrt_tex render --help'])
    import drjit as dr
    if dr.has_backend(dr.JitBackend.CUDA):
        pytest.skip('this machine has a CUDA device')
    r = cli('render', f'{scenes}/ok.xml', '-o', f'{scenes}/o.exr', '--variant', 'cuda_ad_rgb')
    # says what is missing and what works instead (it printed Dr.Jit's jit_init_thread_state text)
    _one_error_line(r.returncode, r.stderr, [
        '--variant cuda_ad_rgb: Dr.Jit finds no CUDA device (GPU and driver) on this machine; '
        'variants that work here: llvm_ad_rgb, llvm_ad_mono'])
    assert 'jit_init' not in r.stderr
    assert not (scenes / 'o.exr').exists()


def test_cli_outputs_follow_the_umask(scenes):
    """Outputs are created as a new file would be under the user's umask (mkstemp gave 0600);
    the texture named through <default>/$f is read, and the missing folder is created."""
    out = scenes / 'new' / 'deeper' / 'img.exr'
    r = cli('render', f'{scenes}/default.xml', '-o', str(out), '-q',
            preexec_fn=lambda: os.umask(0o027))
    assert r.returncode == 0, r.stderr
    for p in (out, out.with_suffix('.png')):
        assert (os.stat(p).st_mode & 0o777) == 0o640, oct(os.stat(p).st_mode)


SLOW_WRITER = r'''
import sys, time
import mitsuba_pbrt_tex.outputs as o
def slow_exr(path, image, names=None):
    def write(tmp):
        with open(tmp, 'wb') as f:
            f.write(b'partial')
        print('WRITING', flush=True)
        time.sleep(60)
    o._atomic(path, write)
o.write_exr = slow_exr
from mitsuba_pbrt_tex.cli import main
sys.exit(main(sys.argv[1:]))
'''


@pytest.mark.parametrize('name, params, words', [
    ('pbrt_imagemap', {'gamma': True},
     ["unknown parameter 'gamma'", 'encoding="sRGB", "linear" or "gamma G"']),
    ('pbrt_imagemap', {'trilinear': True}, ["unknown parameter 'trilinear'", 'filter="trilinear"']),
    ('pbrt_scale', {'tex1': 0.5, 'tex2': 2.0},
     ["unknown parameters 'tex1', 'tex2'", 'take "tex" and "scale"'])])
def test_pbrt_v3_names_get_pbrt_v4s(name, params, words):
    """A parameter pbrt-v4 renamed, given by its pbrt-v3 name, is unknown — and the error says
    what pbrt-v4 (whose names the plugins take) calls it (a pbrt-v4 port trial asked for it);
    said once for two such names."""
    if name == 'pbrt_imagemap':
        params = {'filename': os.path.join(DATA, 'srgb_11x9.png'), **params}
    with pytest.raises(RuntimeError) as e:
        mi.load_dict({'type': name, **params})
    for w in words:
        assert w in str(e.value), str(e.value)[-300:]
    assert str(e.value).count('pbrt-v3') == 1


def test_sigterm_while_writing_leaves_no_temporary_file(scenes):
    out = scenes / 'sig' / 'img.exr'
    proc = subprocess.Popen([sys.executable, '-c', SLOW_WRITER, 'render', f'{scenes}/ok.xml',
                             '-o', str(out), '-q'], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        deadline = time.time() + 300
        for line in proc.stdout:
            if 'WRITING' in line or time.time() > deadline:
                break
        assert any(p.name.startswith('.tmp-') for p in out.parent.iterdir())   # mid-write
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143, err
    assert 'terminated (SIGTERM)' in err and 'Traceback' not in err
    # no temporary file left, and the folder the render created for its output is gone too
    assert not out.parent.exists()


# ---------------------------------------------------------------------------------- memory
def test_image_cache_holds_only_what_live_textures_use(tmp_path):
    from mitsuba_pbrt_tex.image import image_cache
    from mitsuba_pbrt_tex.outputs import write_exr
    image_cache.clear()
    path = str(tmp_path / 'img.exr')
    img = np.random.default_rng(3).random((32, 48, 3)).astype(np.float32)
    write_exr(path, img)
    kept = mi.load_dict({'type': 'pbrt_imagemap', 'filename': path, 'filter': 'ewa'})
    for i in range(5):                           # edited file: a new key each time
        st = os.stat(path)
        os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + (i + 1) * 10**9))
        tex = mi.load_dict({'type': 'pbrt_imagemap', 'filename': path, 'filter': 'ewa'})
        assert len(image_cache) == 2             # the live one from before, and this one
        del tex
        gc.collect()
        assert len(image_cache) == 1
    twin = mi.load_dict({'type': 'pbrt_imagemap', 'filename': path, 'filter': 'trilinear'})
    assert len(image_cache) == 2 and twin.pyramid is not kept.pyramid
    del kept, twin
    gc.collect()
    assert len(image_cache) == 0


def test_image_edited_with_its_modification_time_restored_is_read_again(tmp_path):
    """A file rewritten with the same size and its modification time set back (as ``cp -p``,
    ``rsync -t`` or ``tar x`` leave an edited file) while a texture of the old contents is still
    alive (``scene = mi.load_file(...)`` again): the new texture reads the new texels. Found in a
    user trial: the cache, keyed by path, size and modification time, returned the old ones."""
    path = str(tmp_path / 'img.pfm')

    def write(value):                 # in place (same inode), always the same size
        with open(path, 'wb') as f:
            f.write(b'PF\n8 8\n-1.0\n' + np.full((8, 8, 3), value, '<f4').tobytes())

    write(0.25)
    old = mi.load_dict({'type': 'pbrt_imagemap', 'filename': path})
    st = os.stat(path)
    time.sleep(0.02)                  # a status-change time the rewrite moves on any clock
    write(0.75)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    after = os.stat(path)
    assert (after.st_ino, after.st_size, after.st_mtime_ns) == \
        (st.st_ino, st.st_size, st.st_mtime_ns)
    new = mi.load_dict({'type': 'pbrt_imagemap', 'filename': path})
    si = make_si([[0.3, 0.3]])
    assert A(old.eval_1(si))[0] == pytest.approx(0.25)
    assert A(new.eval_1(si))[0] == pytest.approx(0.75)


MEMORY_CHILD = r'''
import gc, os, sys
import drjit as dr, mitsuba as mi, mitsuba_pbrt_tex as mpt
def rss():
    with open('/proc/self/statm') as f:
        return int(f.read().split()[1]) * os.sysconf('SC_PAGE_SIZE')
mi.set_variant('llvm_ad_rgb'); mpt.register()
tex = mi.load_dict({'type': 'pbrt_imagemap', 'filename': sys.argv[1], 'filter': 'ewa'})
dr.sync_thread(); gc.collect()
held = rss()
dr.flush_malloc_cache()
print('RELEASED', held - rss())
'''


def test_ewa_build_gives_its_temporaries_back(tmp_path):
    """After building an EWA texture's pyramid nothing is left in Dr.Jit's allocation cache:
    flushing it afterwards frees (almost) nothing. Before, it kept the RGBA copy of level 0 and
    half-downsampled levels: 1.4× the image (here 17 MiB of a 12 MiB image)."""
    from mitsuba_pbrt_tex.outputs import write_exr
    path = str(tmp_path / 'big.exr')
    img = np.random.default_rng(0).random((1024, 1024, 3), dtype=np.float32)   # 12 MiB
    write_exr(path, img)
    r = subprocess.run([sys.executable, '-c', MEMORY_CHILD, path], capture_output=True,
                       text=True, timeout=600)
    released = [int(x.split()[1]) for x in r.stdout.splitlines() if x.startswith('RELEASED')]
    assert released, r.stderr[-2000:]
    # small allocations come and go; a leftover build temporary would be ≥ 4 MiB
    assert released[0] < 0.1 * img.nbytes, released[0] / img.nbytes


PARALLEL_CHILD = r'''
import sys
import mitsuba as mi, mitsuba_pbrt_tex as mpt
mi.set_variant('llvm_ad_rgb'); mpt.register()
paths = sys.argv[1:]
shapes = {f's{i}': {'type': 'sphere', 'center': [i, 0, 0], 'radius': 0.3,
                    'bsdf': {'type': 'diffuse', 'reflectance': {
                        'type': 'pbrt_imagemap', 'filename': paths[i % len(paths)],
                        'filter': 'ewa', 'uscale': float(1 + i // len(paths))}}}
          for i in range(2 * len(paths))}
scene = mi.load_dict({'type': 'scene', **shapes}, parallel=True)
print('LOADED', len(scene.shapes()))
'''


def test_parallel_load_of_large_ewa_textures_completes(tmp_path):
    """Large builds wait for their kernels and flush Dr.Jit's allocation cache inside plugin
    constructors, which Mitsuba runs on the worker pool that also runs the kernels: a scene of
    such textures, loaded in parallel, must not deadlock (in a subprocess, with a timeout)."""
    from mitsuba_pbrt_tex.outputs import write_exr
    rng = np.random.default_rng(5)
    paths = []
    for i in range(3):                     # each 12 MiB: its pyramid is above RELEASE_BYTES
        paths.append(str(tmp_path / f'big{i}.exr'))
        write_exr(paths[-1], rng.random((1024, 1024, 3), dtype=np.float32))
    r = subprocess.run([sys.executable, '-c', PARALLEL_CHILD, *paths], capture_output=True,
                       text=True, timeout=300)
    assert 'LOADED 6' in r.stdout, r.stderr[-2000:]


def test_a_refused_update_leaves_every_texture_of_the_update_as_it_was(rng):
    """Mitsuba's params.update() tells the changed objects one by one, children first, and
    stops at the first error: another texture of ours in the same update was never told (its
    bad data shape ended the next render inside Dr.Jit; a NaN amount of a parent pbrt_mix
    stayed), or had already accepted its new value (found by a review). Every pbrt_* texture
    the update marked is put back as it was before the update."""
    def image(shape=(8, 8, 3)):
        return mi.TensorXf(rng.random(shape).astype(np.float32))

    scene = mi.load_dict({
        'type': 'scene', 'integrator': {'type': 'pbrt_path', 'footprint': 'pixel'},
        'sensor': {'type': 'perspective', 'fov': 40,
                   'to_world': mi.ScalarTransform4f().look_at([0, -2, 1.5], [0, 0, 0],
                                                              [0, 0, 1]),
                   'film': {'type': 'hdrfilm', 'width': 12, 'height': 8,
                            'rfilter': {'type': 'box'}}},
        'floor': {'type': 'rectangle', 'bsdf': {'type': 'diffuse', 'reflectance': {
            'type': 'pbrt_imagemap', 'filter': 'box', 'data': image()}}},
        # facing down, in view, lighting the floor and the ball
        'lamp': {'type': 'rectangle', 'to_world': mi.ScalarTransform4f().translate([0, 0.6, 2])
                 @ mi.ScalarTransform4f().rotate([1, 0, 0], 180),
                 'emitter': {'type': 'area', 'radiance': {
                     'type': 'pbrt_imagemap', 'filter': 'box', 'data': image()}}},
        'ball': {'type': 'sphere', 'radius': 0.4, 'bsdf': {'type': 'diffuse', 'reflectance': {
            'type': 'pbrt_mix', 'amount': 0.25, 'tex2': 0.7,
            'tex1': {'type': 'pbrt_imagemap', 'data': image()}}}}})
    before = mi.render(scene, spp=2, seed=1).numpy()
    # every texture shows: the image changes with each (a black render compared nothing)
    p = mi.traverse(scene)
    for key in ('floor.bsdf.reflectance.scale', 'lamp.emitter.radiance.scale',
                'ball.bsdf.reflectance.tex1.scale'):
        p[key] = mi.Float(0.5)
        p.update()
        assert np.abs(mi.render(scene, spp=2, seed=1).numpy() - before).max() > 0.01, key
        p[key] = mi.Float(1.0)
        p.update()
    np.testing.assert_array_equal(mi.render(scene, spp=2, seed=1).numpy(), before)
    p = mi.traverse(scene)
    floor, lamp = 'floor.bsdf.reflectance.', 'lamp.emitter.radiance.'
    mix = 'ball.bsdf.reflectance.'
    cases = [{floor + 'data': image((4, 4, 2)), lamp + 'data': image((4, 4, 2))},
             {floor + 'data': image((4, 4, 2)), lamp + 'scale': mi.Float(float('nan'))},
             {lamp + 'data': image((4, 4, 2)), floor + 'scale': mi.Float(float('nan'))},
             # a child refuses: the parent's NaN amount is never checked
             {mix + 'tex1.data': image((4, 4, 2)), mix + 'amount.value': mi.Float(float('nan'))},
             # the parent refuses after a child accepted a valid scale: that is put back too
             {mix + 'tex1.scale': mi.Float(0.5), mix + 'amount.value': mi.Float(float('nan'))},
             # ... or new texels, whose pyramid it had rebuilt: rebuilt again from the old ones
             {mix + 'tex1.data': image(), mix + 'amount.value': mi.Float(float('nan'))},
             # and a second refusal puts back the values before it, not those of the first
             {mix + 'tex1.scale': mi.Float(0.5), mix + 'amount.value': mi.Float(float('nan'))}]
    for values in cases:
        with pytest.raises(Exception, match='pbrt_(imagemap|mix): parameter'):
            p.update(values)
        assert p[floor + 'data'].shape == p[lamp + 'data'].shape == (8, 8, 3), values
        for key in (floor + 'scale', lamp + 'scale', mix + 'tex1.scale'):
            assert A(p[key])[0] == 1.0, (values, key)
        assert A(p[mix + 'amount.value'])[0] == 0.25, values
        np.testing.assert_array_equal(mi.render(scene, spp=2, seed=1).numpy(), before)
