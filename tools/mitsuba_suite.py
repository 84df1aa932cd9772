"""Mitsuba 3.9.1's own tests, run on Mitsuba's own data with ``bitmap`` replaced by
``pbrt_imagemap`` (README, "Use").

    python tools/mitsuba_suite.py --mitsuba-src MI3 --mitsuba-data DATA [options]

``MI3`` is a Mitsuba 3.9.1 source tree (only ``src/conftest.py``,
``src/render/tests/test_renders.py``, ``src/textures/tests/test_bitmap.py`` and
``src/integrators/tests/test_ptracer.py`` are read),
``DATA`` a checkout of mitsuba-data (the commit Mitsuba 3.9.1 pins as its
``resources/data`` submodule). Neither is changed, and nothing of either is part of this
project: the harness builds a Mitsuba-like tree in a temporary folder at run time,

    ROOT/ext, ROOT/include                  (empty: Mitsuba's test utilities look for them)
    ROOT/src/conftest.py                    Mitsuba's, as it is
    ROOT/src/render/tests/test_renders.py   Mitsuba's, as it is
    ROOT/src/textures/tests/test_bitmap.py  Mitsuba's, as it is
    ROOT/src/integrators/tests/test_ptracer.py  Mitsuba's, as it is
    ROOT/resources/data/...                 DATA: XML files copied with every
                                            <texture type="bitmap"> made type="pbrt_imagemap",
                                            everything else linked

and runs pytest there, once per variant (``--variants``), texture (``--textures``; ``bitmap``
runs the same tests unmodified, as the control) and integrator (``--integrators``):

* ``scene``: test_renders.py's own configurations (the scene's integrator under its 4 JIT flag
  settings, plus Mitsuba's extra integrators for it: prb and prb_projective for path,
  direct_projective for direct), test_bitmap.py and test_ptracer.py;
* ``pbrt_path``: test_renders.py's path configurations, with the test's
  ``mi.load_file(..., integrator='path')`` given ``'pbrt_path'`` instead.

Only scenes that use ``bitmap`` (in their file or an included one) are run, unless
``--all-scenes``. How the tests are pointed at the copy, without editing them (this file is
also the pytest plugin, loaded with ``-p``):

* ``mi.variants()`` returns only the run's variant, before Mitsuba's conftest builds its
  variant fixtures and test_renders.py its configurations from it (so each variant is a
  separate pytest process, and a test whose variant group has no member there, e.g. an RGB-only
  test in a mono run, or a ``scalar_rgb`` one, is reported as skipped);
* ``find_resource`` (test_renders.py's way to its scenes) looks in ROOT;
* in the test modules only, ``mi.load_dict`` gets ``"type": "bitmap"`` replaced (test_bitmap.py
  and test_ptracer.py build their textures from dicts) and ``mi.load_file`` the integrator
  (``pbrt_path`` runs).

Results are collected per test item, summarised per scene/test, variant, texture and
integrator, and written as JSON (``--json``). ``--compare`` instead renders every selected scene
with ``bitmap`` and with ``pbrt_imagemap`` under the scene's own integrator with the test's
seed (0) and sample budget, and prints the largest absolute and relative pixel differences.
Run times on 2 CPU threads are in the README.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections import OrderedDict

HERE = os.path.dirname(os.path.abspath(__file__))
PLUGIN = os.path.splitext(os.path.basename(__file__))[0]
CONFIG_ENV = 'MITSUBA_PBRT_TEX_SUITE_CONFIG'

TEST_FILES = {
    'renders': 'src/render/tests/test_renders.py',
    'bitmap': 'src/textures/tests/test_bitmap.py',
    'ptracer': 'src/integrators/tests/test_ptracer.py',
}
MITSUBA_CONFTEST = 'src/conftest.py'
SCENE_DIR = os.path.join('tests', 'scenes')
SAMPLE_BUDGET = int(2e6)            # test_renders.py: spp = 2e6 // pixel count

# <texture ... type="bitmap" ...>: the type attribute of a texture element, either quote
_TEXTURE_TYPE = re.compile(r'''(<texture\b[^>]*?\btype\s*=\s*)(["'])bitmap\2''', re.S)
_INCLUDE = re.compile(r'''<include\b[^>]*?\bfilename\s*=\s*(["'])(.*?)\1''', re.S)


# ---- the temporary Mitsuba-like tree --------------------------------------------------------------

def substitute(text: str, texture: str) -> tuple[str, int]:
    """``text`` with every ``<texture type="bitmap">`` made ``texture``; and how many."""
    if texture == 'bitmap':
        return text, len(_TEXTURE_TYPE.findall(text))
    return _TEXTURE_TYPE.subn(lambda m: f'{m.group(1)}{m.group(2)}{texture}{m.group(2)}', text)


def uses_bitmap(xml_path: str, seen=None) -> bool:
    """Whether a scene file or a file it includes (recursively) has a bitmap texture."""
    seen = set() if seen is None else seen
    xml_path = os.path.realpath(xml_path)
    if xml_path in seen or not os.path.exists(xml_path):
        return False
    seen.add(xml_path)
    with open(xml_path, encoding='utf-8') as f:
        text = f.read()
    if _TEXTURE_TYPE.search(text):
        return True
    return any(uses_bitmap(os.path.join(os.path.dirname(xml_path), inc), seen)
               for _, inc in _INCLUDE.findall(text))


def scene_files(data: str) -> list[str]:
    """Test scenes as test_renders.py lists them (``tests/scenes/*/*.xml``), relative paths."""
    root = os.path.join(data, SCENE_DIR)
    return sorted(os.path.join(d, f) for d in os.listdir(root)
                  if os.path.isdir(os.path.join(root, d))
                  for f in os.listdir(os.path.join(root, d)) if f.endswith('.xml'))


def _integrator(scene: str) -> str:
    """The integrator test_renders.py reads from a scene's file name (``*_path.xml``: path)."""
    return os.path.splitext(scene)[0].rsplit('_', 1)[-1]


def textured_scenes(data: str) -> list[str]:
    return [s for s in scene_files(data) if uses_bitmap(os.path.join(data, SCENE_DIR, s))]


def build_tree(root: str, src: str, data: str, texture: str) -> int:
    """Lay out ROOT (see the module docstring); returns how many textures were substituted."""
    for d in ('ext', 'include'):
        os.makedirs(os.path.join(root, d), exist_ok=True)
    for rel in [MITSUBA_CONFTEST, *TEST_FILES.values()]:
        os.makedirs(os.path.dirname(os.path.join(root, rel)), exist_ok=True)
        shutil.copyfile(os.path.join(src, rel), os.path.join(root, rel))
    with open(os.path.join(root, 'pytest.ini'), 'w') as f:
        # pytest 9 would name long scene paths scene_fname0, scene_fname1...: keep the paths
        f.write('[pytest]\nparametrize_long_str_id_strategy = legacy\n')
    count = 0
    dst_data = os.path.join(root, 'resources', 'data')
    for dirpath, dirnames, filenames in os.walk(data):
        dirnames[:] = [d for d in dirnames if d != '.git']
        rel = os.path.relpath(dirpath, data)
        out = os.path.normpath(os.path.join(dst_data, rel))
        os.makedirs(out, exist_ok=True)          # real folders: error images land in ROOT
        for name in filenames:
            s, t = os.path.join(dirpath, name), os.path.join(out, name)
            if name.endswith('.xml'):
                with open(s, encoding='utf-8') as f:
                    text, n = substitute(f.read(), texture)
                with open(t, 'w', encoding='utf-8') as f:
                    f.write(text)
                count += n
            else:
                os.symlink(os.path.abspath(s), t)
    return count


# ---- the pytest plugin (active only inside the harness's pytest runs) --------------------------

_CFG = None
_RECORDS = OrderedDict()


def _config():
    global _CFG
    if _CFG is None and os.environ.get(CONFIG_ENV):
        with open(os.environ[CONFIG_ENV]) as f:
            _CFG = json.load(f)
    return _CFG


class _MitsubaProxy:
    """The ``mi`` a test module sees: Mitsuba, but load_dict/load_file substituted."""

    def __init__(self, cfg):
        self._cfg = cfg

    def __getattr__(self, name):
        import mitsuba as mi
        return getattr(mi, name)

    def _retype(self, obj):
        if isinstance(obj, dict):
            return {k: (self._cfg['texture'] if k == 'type' and v == 'bitmap' else self._retype(v))
                    for k, v in obj.items()}
        return obj

    def load_dict(self, d, *args, **kwargs):
        import mitsuba as mi
        return mi.load_dict(self._retype(d), *args, **kwargs)

    def load_file(self, path, *args, **kwargs):
        import mitsuba as mi
        if self._cfg['integrator'] != 'scene' and kwargs.get('integrator') == 'path':
            kwargs['integrator'] = self._cfg['integrator']
        return mi.load_file(path, *args, **kwargs)


def _set_up():
    """Run when pytest imports this plugin (``-p``), before it imports any conftest."""
    cfg = _config()
    if cfg is None:
        return
    import mitsuba_pbrt_tex as mpt          # first: it locates libLLVM
    import mitsuba as mi
    import mitsuba.scalar_rgb.test.util as util
    variant = cfg['variant']
    mi.set_variant(variant)
    mpt.register()                          # and again after every set_variant
    # Before Mitsuba's conftest and test_renders.py read them:
    mi.variants = lambda: [variant]

    def find_resource(fname):
        full = os.path.join(cfg['root'], fname)
        if not os.path.exists(full):
            raise Exception('find_resource(): could not find "%s"' % fname)
        return full
    util.find_resource = find_resource


_set_up()


def _describe(item):
    params = dict(getattr(getattr(item, 'callspec', None), 'params', {}) or {})
    rec = {'file': os.path.basename(str(item.fspath)), 'test': item.originalname or item.name,
           'nodeid': item.nodeid}
    if 'scene_fname' in params:
        rec['scene'] = os.path.relpath(params['scene_fname'], os.path.join(
            _config()['root'], 'resources', 'data', SCENE_DIR))
        rec['integrator'] = params['integrator_type']
        rec['flags'] = params['jit_flags_key']
    else:
        rec['params'] = '-'.join(f'{k}={v}' for k, v in params.items()
                                 if not k.startswith('variant'))
    return rec


def pytest_collection_modifyitems(session, config, items):
    cfg = _config()
    if cfg is None:
        return
    keep, drop, scenes = [], [], set()
    proxy = _MitsubaProxy(cfg)
    for item in items:
        rec = _describe(item)
        if 'scene' in rec:
            if (cfg['scenes'] is not None and rec['scene'] not in cfg['scenes']) or \
                    (cfg['integrator'] != 'scene' and rec['integrator'] != 'path'):
                drop.append(item)
                continue
            scenes.add(rec['scene'])
        elif cfg['integrator'] != 'scene':
            drop.append(item)               # pbrt_path runs: test_renders.py only
            continue
        if getattr(item.module, 'mi', None) is not None:
            item.module.mi = proxy
        rec.update(variant=cfg['variant'], texture=cfg['texture'],
                   run_integrator=cfg['integrator'])
        _RECORDS[item.nodeid] = dict(rec, outcome=None, message='')
        keep.append(item)
    if drop:
        config.hook.pytest_deselected(items=drop)
        items[:] = keep
    print(f'\n[{PLUGIN}] {cfg["variant"]}, texture {cfg["texture"]}, integrator '
          f'{cfg["integrator"]}: {len(keep)} tests, {len(scenes)} scenes of test_renders.py '
          f'({len(drop)} deselected)')


def pytest_runtest_logreport(report):
    rec = _RECORDS.get(report.nodeid)
    if rec is None:
        return
    if report.failed:
        outcome = 'error' if report.when != 'call' else 'failed'
        crash = getattr(report.longrepr, 'reprcrash', None)
        msg = crash.message if crash is not None else str(report.longrepr).strip().splitlines()[-1]
        if rec['outcome'] not in ('failed', 'error'):
            rec['outcome'], rec['message'] = outcome, msg.strip()
    elif report.skipped and rec['outcome'] is None:
        rec['outcome'] = 'skipped'
        rec['message'] = report.longrepr[2] if isinstance(report.longrepr, tuple) else ''
    elif report.passed and report.when == 'call' and rec['outcome'] is None:
        rec['outcome'] = 'passed'
    if report.when == 'call' or report.failed or report.skipped:
        rec['seconds'] = rec.get('seconds', 0.0) + report.duration


def pytest_sessionfinish(session, exitstatus):
    cfg = _config()
    if cfg is None:
        return
    with open(cfg['results'], 'w') as f:
        json.dump(list(_RECORDS.values()), f, indent=1)


# ---- the harness ------------------------------------------------------------------------------------

def run_pytest(root, cfg, files, extra, log):
    cfg_path = os.path.join(root, f'config-{cfg["variant"]}-{cfg["texture"]}-{cfg["integrator"]}.json')
    with open(cfg_path, 'w') as f:
        json.dump(cfg, f)
    env = dict(os.environ)
    env[CONFIG_ENV] = cfg_path
    env['PYTHONPATH'] = HERE + os.pathsep + env.get('PYTHONPATH', '')
    cmd = [sys.executable, '-m', 'pytest', '-p', PLUGIN, '-p', 'no:cacheprovider', '-q', '-rfE',
           '--rootdir', root, '-c', os.path.join(root, 'pytest.ini'),
           *[os.path.join(root, TEST_FILES[t]) for t in files], *extra]
    log(f'$ {CONFIG_ENV}={cfg_path} ' + ' '.join(cmd))
    t0 = time.time()
    proc = subprocess.run(cmd, cwd=root, env=env, stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, text=True)
    log(proc.stdout.rstrip())
    log(f'(exit status {proc.returncode}, {time.time() - t0:.0f} s)')
    if not os.path.exists(cfg['results']):
        raise SystemExit(f'pytest wrote no results (exit status {proc.returncode}); see above')
    with open(cfg['results']) as f:
        return json.load(f)


def summarise(records):
    """Rows: one per (file, scene or test, integrator as run, variant, texture)."""
    rows = OrderedDict()
    for r in records:
        if 'scene' in r:
            integ = r['run_integrator'] if r['run_integrator'] != 'scene' else r['integrator']
            key = (r['file'], r['scene'], integ, r['variant'], r['texture'])
        else:
            key = (r['file'], r['test'], '', r['variant'], r['texture'])
        row = rows.setdefault(key, {'passed': 0, 'failed': 0, 'error': 0, 'skipped': 0,
                                    'not run': 0, 'seconds': 0.0, 'messages': OrderedDict()})
        outcome = r['outcome'] or 'not run'
        row[outcome] += 1
        row['seconds'] += r.get('seconds', 0.0)
        if outcome in ('failed', 'error', 'skipped'):
            what = r.get('flags') or r.get('params') or ''
            row['messages'].setdefault(f'{outcome}: {r["message"]}', []).append(what)
    return rows


def print_table(rows, out=print):
    out('| file | scene / test | integrator | variant | texture | passed | failed | skipped | s |')
    out('|---|---|---|---|---|---|---|---|---|')
    for (file, what, integ, variant, texture), row in rows.items():
        out(f'| {file} | {what} | {integ} | {variant} | {texture} | {row["passed"]} | '
            f'{row["failed"] + row["error"] + row["not run"]} | {row["skipped"]} | '
            f'{row["seconds"]:.0f} |')
    for key, row in rows.items():
        for msg, which in row['messages'].items():
            if msg.startswith('skipped'):
                continue
            out(f'- {key[1]} {key[2]} {key[3]} {key[4]} [{", ".join(w for w in which if w)}]: '
                f'{msg[:300]}')


# ---- --compare: bitmap against pbrt_imagemap, same seed -----------------------------------------

def _image(scene):
    import numpy as np
    bmp = scene.sensors()[0].film().bitmap(raw=False)
    layers = bmp.split()
    img = np.array(layers[1][1] if len(layers) > 1 else layers[0][1], copy=True)
    return img.reshape(img.shape[0], img.shape[1], -1)


def _stats(a, b):
    """Largest |a - b|, and relative to the larger of |a|, |b|, with b's value where they are."""
    import numpy as np
    diff = np.abs(a - b)
    big = np.maximum(np.abs(a), np.abs(b))
    rel = np.where(big > 0, diff / np.where(big > 0, big, 1), 0)
    i = np.unravel_index(np.argmax(diff), diff.shape)
    j = np.unravel_index(np.argmax(rel), rel.shape)
    return dict(max_abs=float(diff[i]), at_abs=float(b[i]), max_rel=float(rel[j]),
                at_rel=float(b[j]), rms=float(np.sqrt(np.mean(diff ** 2))),
                pixels_differing=int(np.count_nonzero(diff.max(axis=2) > 0)))


COMPARE_HEADER = (
    '| scene | integrator | variant | spp | max abs diff (bitmap there) | max rel diff '
    '(bitmap there) | pixels differing | bitmap rerun: max rel diff | RMS diff / RMS of bitmap '
    'seed 1 vs 0 |\n|---|---|---|---|---|---|---|---|---|')


def compare(root_bitmap, root_pbrt, scenes, variants, log):
    """pbrt_imagemap against bitmap per scene and variant, test_renders.py's seed (0) and spp.

    Two baselines: bitmap rendered again with seed 0 (the run-to-run rounding of the image
    block's multi-threaded accumulation) and with seed 1 (Monte Carlo noise: a ratio near 1 in
    the last column means the two images differ by noise, not by rounding)."""
    import mitsuba_pbrt_tex as mpt
    import mitsuba as mi
    rows = []
    for variant in variants:
        mi.set_variant(variant)
        mpt.register()
        mi.set_log_level(mi.LogLevel.Error)   # not the mono film's pixel-format notice
        for scene in scenes:
            integ = _integrator(scene)
            fname = {r: os.path.join(r, 'resources', 'data', SCENE_DIR, scene)
                     for r in (root_bitmap, root_pbrt)}
            size = mi.load_file(fname[root_bitmap], integrator=integ).sensors()[0].film().crop_size()
            spp = SAMPLE_BUDGET // int(size[0] * size[1])

            def render(root, seed):
                s = mi.load_file(fname[root], spp=spp, integrator=integ)
                s.integrator().render(s, seed=seed, spp=spp, develop=True)
                return _image(s)
            ref = render(root_bitmap, 0)
            ours = _stats(render(root_pbrt, 0), ref)
            rerun = _stats(render(root_bitmap, 0), ref)
            noise = _stats(render(root_bitmap, 1), ref)
            row = dict(scene=scene, integrator=integ, variant=variant, spp=spp, **ours,
                       pixels=int(ref.shape[0] * ref.shape[1]), rerun_max_rel=rerun['max_rel'],
                       noise_rms=noise['rms'])
            rows.append(row)
            log(f'| {scene} | {integ} | {variant} | {spp} | {row["max_abs"]:.2g} '
                f'({row["at_abs"]:.3g}) | {row["max_rel"]:.2g} ({row["at_rel"]:.3g}) | '
                f'{row["pixels_differing"]}/{row["pixels"]} | {row["rerun_max_rel"]:.2g} | '
                f'{row["rms"] / row["noise_rms"]:.2g} |')
    return rows


def _compare_main(args):
    """Child process for --compare (a fresh process: no plugin state from pytest runs)."""
    rows = compare(args.compare_roots[0], args.compare_roots[1], args.scenes.split(','),
                   args.variants.split(','), lambda s: print(s, flush=True))
    with open(args.compare_out, 'w') as f:
        json.dump(rows, f, indent=1)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--mitsuba-src', required=True,
                    help='Mitsuba 3.9.1 source tree (src/render/tests, src/textures/tests)')
    ap.add_argument('--mitsuba-data', required=True,
                    help="mitsuba-data checkout (Mitsuba 3.9.1's resources/data)")
    ap.add_argument('--variants', default='llvm_ad_rgb,llvm_ad_mono')
    ap.add_argument('--textures', default='pbrt_imagemap',
                    help='comma-separated; "bitmap" runs the unmodified tests (the control)')
    ap.add_argument('--integrators', default='scene,pbrt_path',
                    help='"scene": the tests\' own configurations; "pbrt_path": path replaced')
    ap.add_argument('--tests', default='renders,bitmap,ptracer',
                    help='comma-separated: renders, bitmap, ptracer')
    ap.add_argument('--scenes', default=None,
                    help='comma-separated scene paths under tests/scenes (default: every scene '
                         'that uses bitmap)')
    ap.add_argument('--all-scenes', action='store_true', help='also scenes without bitmap')
    ap.add_argument('--compare', action='store_true',
                    help='instead of the tests: bitmap vs pbrt_imagemap image differences')
    ap.add_argument('--work', default=None, help='build the tree here and keep it (error images)')
    ap.add_argument('--json', default=None, help='write every test result (or comparison) here')
    ap.add_argument('--compare-roots', nargs=2, help=argparse.SUPPRESS)
    ap.add_argument('--compare-out', help=argparse.SUPPRESS)
    ap.add_argument('pytest_args', nargs='*', help='passed to pytest (after --)')
    args = ap.parse_args(argv)
    if args.compare_roots:
        return _compare_main(args)

    src, data = os.path.abspath(args.mitsuba_src), os.path.abspath(args.mitsuba_data)
    for rel in [MITSUBA_CONFTEST, *TEST_FILES.values()]:
        if not os.path.isfile(os.path.join(src, rel)):
            raise SystemExit(f'--mitsuba-src: {os.path.join(src, rel)} does not exist')
    if not os.path.isdir(os.path.join(data, SCENE_DIR)):
        raise SystemExit(f'--mitsuba-data: {os.path.join(data, SCENE_DIR)} does not exist')
    variants = args.variants.split(',')
    textures = args.textures.split(',')
    integrators = args.integrators.split(',')
    tests = args.tests.split(',')
    if args.scenes:
        scenes = args.scenes.split(',')
        unknown = sorted(set(scenes) - set(scene_files(data)))
        if unknown:
            raise SystemExit(f'--scenes: not in {os.path.join(data, SCENE_DIR)}: {", ".join(unknown)}')
    elif args.all_scenes:
        scenes = scene_files(data)
    else:
        scenes = textured_scenes(data)
    work = os.path.abspath(args.work) if args.work else tempfile.mkdtemp(prefix='mitsuba-suite-')
    os.makedirs(work, exist_ok=True)

    def log(s):
        print(s, flush=True)

    git = subprocess.run(['git', '-C', data, 'rev-parse', '--show-toplevel', 'HEAD'],
                         stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True).stdout.split()
    commit = git[1] if len(git) == 2 and os.path.realpath(git[0]) == os.path.realpath(data) else ''
    log(f'[{PLUGIN}] data {data} (commit {commit or "unknown: not a git checkout"}); '
        f'{len(scenes)} scenes: {", ".join(scenes)}')
    roots = {}
    needed = set(textures) | ({'bitmap', 'pbrt_imagemap'} if args.compare else set())
    for texture in sorted(needed):
        root = os.path.join(work, texture)
        if os.path.exists(root):
            shutil.rmtree(root)
        n = build_tree(root, src, data, texture)
        roots[texture] = root
        log(f'[{PLUGIN}] {root}: {n} bitmap textures '
            f'{"kept" if texture == "bitmap" else "made " + texture}')
    try:
        if args.compare:
            out = os.path.join(work, 'compare.json')
            log(COMPARE_HEADER)
            proc = subprocess.run([sys.executable, os.path.abspath(__file__),
                                   '--mitsuba-src', src, '--mitsuba-data', data,
                                   '--compare-roots', roots['bitmap'], roots['pbrt_imagemap'],
                                   '--compare-out', out, '--scenes', ','.join(scenes),
                                   '--variants', ','.join(variants)])
            if proc.returncode:
                return proc.returncode
            if args.json:
                shutil.copyfile(out, args.json)
            return 0
        records = []
        for variant in variants:
            for texture in textures:
                for integ in integrators:
                    files = [t for t in tests if integ == 'scene' or t == 'renders']
                    if not files:
                        continue
                    cfg = dict(variant=variant, texture=texture, integrator=integ,
                               root=roots[texture], scenes=scenes,
                               results=os.path.join(work, f'results-{variant}-{texture}-{integ}.json'))
                    records += run_pytest(roots[texture], cfg, files, args.pytest_args, log)
        rows = summarise(records)
        log('')
        print_table(rows, log)
        # A scene the tests did not list (or one pytest dropped) shows here, not as a pass:
        missing = []
        if 'renders' in tests:
            for variant in variants:
                for texture in textures:
                    for integ in integrators:
                        ran = {r['scene'] for r in records if 'scene' in r and r['variant'] ==
                               variant and r['texture'] == texture and r['run_integrator'] == integ}
                        missing += [f'{s} ({variant}, {texture}, {integ})' for s in scenes
                                    if s not in ran and (integ == 'scene' or _integrator(s) == 'path')]
        for m in missing:
            log(f'[{PLUGIN}] NOT RUN: {m}')
        if args.json:
            with open(args.json, 'w') as f:
                json.dump(records, f, indent=1)
        n_scenes = len({r['scene'] for r in records if 'scene' in r})
        log(f'\n[{PLUGIN}] {len(records)} tests, {n_scenes} scenes; '
            + ', '.join(f'{k} {sum(1 for r in records if (r["outcome"] or "not run") == k)}'
                        for k in ('passed', 'failed', 'error', 'skipped', 'not run')))
        return 1 if missing or any(r['outcome'] in ('failed', 'error', None) for r in records) else 0
    finally:
        if not args.work:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == '__main__':
    sys.exit(main())
