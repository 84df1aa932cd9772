"""The libLLVM bootstrap: choice of library, respect for the user's setting, clear failure."""

import os
import subprocess
import sys

from mitsuba_pbrt_tex import _llvm


def _touch(d, name):
    path = d / name
    path.write_bytes(b'')
    return str(path)


def test_version_parsing():
    assert _llvm.llvm_major('libLLVM-19.so') == 19
    assert _llvm.llvm_major('libLLVM.so.19.1') == 19
    assert _llvm.llvm_major('libLLVM-17.0.6.so') == 17
    assert _llvm.llvm_major('libLLVM.20.dylib') == 20
    assert _llvm.llvm_major('libLLVMSupport.a') is None
    assert _llvm.llvm_major('libLLVM.so') is None


def test_newest_usable_is_chosen(tmp_path):
    a, b = tmp_path / 'a', tmp_path / 'b'
    a.mkdir()
    b.mkdir()
    _touch(a, 'libLLVM-14.so')
    _touch(a, 'libLLVM-15.so.1')
    want = _touch(b, 'libLLVM-19.so')
    _touch(a, 'libLLVM-17.so')
    assert _llvm.find_libllvm([str(a), str(b)]) == want


def test_only_old_llvm_counts_as_none(tmp_path):
    _touch(tmp_path, 'libLLVM-14.so')
    _touch(tmp_path, 'libLLVM-15.so')
    assert _llvm.find_libllvm([str(tmp_path)]) is None


def _run(code, env_updates):
    env = {k: v for k, v in os.environ.items() if k != 'DRJIT_LIBLLVM_PATH'}
    env.update(env_updates)
    return subprocess.run([sys.executable, '-c', code], env=env, capture_output=True, text=True,
                          timeout=300)


def test_missing_llvm_fails_clearly(tmp_path):
    code = ('import mitsuba_pbrt_tex, mitsuba as mi\n'
            'try:\n'
            '    mi.set_variant("llvm_ad_rgb")\n'
            'except ImportError as e:\n'
            '    print("ERROR:", e)\n'
            'else:\n'
            '    print("no error")\n')
    r = _run(code, {'MITSUBA_PBRT_TEX_LLVM_SEARCH': str(tmp_path)})
    assert 'ERROR:' in r.stdout, r.stdout + r.stderr
    assert 'libllvm19' in r.stdout and '17' in r.stdout


def test_user_setting_is_respected(tmp_path):
    code = 'import os, mitsuba_pbrt_tex; print(os.environ["DRJIT_LIBLLVM_PATH"])'
    r = _run(code, {'DRJIT_LIBLLVM_PATH': '/some/where/libLLVM-18.so'})
    assert r.stdout.strip() == '/some/where/libLLVM-18.so'


def test_found_library_is_exported(tmp_path):
    want = _touch(tmp_path, 'libLLVM-21.so')
    code = 'import os, mitsuba_pbrt_tex; print(os.environ.get("DRJIT_LIBLLVM_PATH"))'
    r = _run(code, {'MITSUBA_PBRT_TEX_LLVM_SEARCH': str(tmp_path)})
    assert r.stdout.strip() == want


def test_user_setting_that_cannot_work_is_left_alone_with_a_warning(tmp_path):
    """A DRJIT_LIBLLVM_PATH of the user's stays as set, but one that is missing, a folder or an
    LLVM older than 17 gets a warning naming the problem and the usable library found (found in
    an installation trial: a missing path led to 'no usable libLLVM on this machine' though
    LLVM 19 was there, and LLVM 15 aborted the process)."""
    good = _touch(tmp_path, 'libLLVM-19.so')
    old = _touch(tmp_path, 'libLLVM-15.so')
    code = 'import os, mitsuba_pbrt_tex; print(os.environ["DRJIT_LIBLLVM_PATH"])'
    for value, words in ((str(tmp_path / 'missing.so'), 'does not exist'),
                         (str(tmp_path), 'is not a file'), (old, 'is LLVM 15, older than 17')):
        r = _run(code, {'DRJIT_LIBLLVM_PATH': value, 'MITSUBA_PBRT_TEX_LLVM_SEARCH': str(tmp_path)})
        assert r.stdout.strip() == value
        assert words in r.stderr and f'Unset it to use {good}' in r.stderr, r.stderr
    r = _run(code, {'DRJIT_LIBLLVM_PATH': good})
    assert r.stdout.strip() == good and 'Warning' not in r.stderr
    # a bare name is the dynamic loader's to find (the library path): not judged by existence
    r = _run(code, {'DRJIT_LIBLLVM_PATH': 'libLLVM.so.19.1'})
    assert r.stdout.strip() == 'libLLVM.so.19.1' and 'Warning' not in r.stderr
    r = _run(code, {'DRJIT_LIBLLVM_PATH': 'libLLVM-15.so'})
    assert 'is LLVM 15, older than 17' in r.stderr, r.stderr
