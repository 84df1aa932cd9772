"""Find a libLLVM that Dr.Jit's LLVM backend can use, before Dr.Jit starts it.

Dr.Jit 1.5 emits the ``llvm.minimum``/``llvm.maximum`` intrinsics; LLVM 14 and 15 cannot
select them (``LLVM ERROR: Cannot select: fminimum``) and abort the whole process. LLVM 17
and newer work (19 is what we test). Dr.Jit reads ``DRJIT_LIBLLVM_PATH`` when the LLVM backend
is first initialised, i.e. when an ``llvm_*`` variant is set, so importing this package early
is enough.

Policy:

* ``DRJIT_LIBLLVM_PATH`` already set by the user: left alone.
* otherwise: the newest ``libLLVM*`` shared library with major version >= 17 found in the usual
  library folders is exported as ``DRJIT_LIBLLVM_PATH``.
* none found: ``mitsuba.set_variant`` is wrapped so that asking for an ``llvm_*`` variant raises
  :class:`LLVMNotFoundError` naming exactly what to install, instead of letting Dr.Jit load an old
  LLVM and abort later in the middle of a render.

``MITSUBA_PBRT_TEX_LLVM_SEARCH`` (a ``os.pathsep``-separated list of folders) replaces the search
folders; the test-suite uses it to simulate a machine without a usable LLVM.
"""

from __future__ import annotations

import glob
import os
import platform
import re
import warnings

MIN_MAJOR = 17
ENV_VAR = 'DRJIT_LIBLLVM_PATH'
SEARCH_ENV_VAR = 'MITSUBA_PBRT_TEX_LLVM_SEARCH'

INSTALL_HINT = (
    "Dr.Jit's LLVM backend needs libLLVM >= %d (LLVM 14/15 abort with 'Cannot select: "
    "fminimum'). On Debian/Ubuntu run 'sudo apt-get install -y libllvm19' (this is what "
    "'.ci/setup.sh' does), on macOS 'brew install llvm'; or set DRJIT_LIBLLVM_PATH to the path "
    "of a libLLVM.so of version >= %d before importing mitsuba." % (MIN_MAJOR, MIN_MAJOR))


class LLVMNotFoundError(ImportError):
    """No usable libLLVM was found for Dr.Jit's LLVM backend."""


def _default_search_dirs() -> list[str]:
    machine = platform.machine()
    dirs = [f'/usr/lib/{machine}-linux-gnu', '/usr/lib64', '/usr/lib', '/usr/local/lib',
            '/opt/homebrew/opt/llvm/lib', '/usr/local/opt/llvm/lib']
    dirs += sorted(glob.glob('/usr/lib/llvm-*/lib'), reverse=True)
    dirs += sorted(glob.glob('/usr/lib/llvm/*/lib*'), reverse=True)  # Gentoo-like layouts
    conda = os.environ.get('CONDA_PREFIX')
    if conda:
        dirs.insert(0, os.path.join(conda, 'lib'))
    return dirs


def search_dirs() -> list[str]:
    override = os.environ.get(SEARCH_ENV_VAR)
    if override is not None:
        return [d for d in override.split(os.pathsep) if d]
    return _default_search_dirs()


_VERSION_PATTERNS = (
    re.compile(r'^libLLVM-(\d+)(?:[.\d]*)?\.(?:so|dylib)(?:\.[\d.]+)?$'),  # libLLVM-19.so
    re.compile(r'^libLLVM\.so\.(\d+)(?:\.[\d.]+)?$'),                      # libLLVM.so.19.1
    re.compile(r'^libLLVM\.(\d+)(?:\.[\d.]+)?\.dylib$'),                   # libLLVM.19.dylib
)


def llvm_major(filename: str) -> int | None:
    """Major version encoded in a libLLVM file name, or None if the name has none."""
    for pattern in _VERSION_PATTERNS:
        m = pattern.match(filename)
        if m:
            return int(m.group(1))
    return None


def find_libllvm(dirs: list[str] | None = None) -> str | None:
    """Path of the newest libLLVM with major version >= MIN_MAJOR, or None."""
    best = None
    for d in search_dirs() if dirs is None else dirs:
        try:
            names = os.listdir(d)
        except OSError:
            continue
        for name in names:
            major = llvm_major(name)
            path = os.path.join(d, name)
            if major is None or major < MIN_MAJOR or not os.path.isfile(path):
                continue
            if best is None or major > best[0]:
                best = (major, path)
    return None if best is None else best[1]


def _guard_set_variant() -> None:
    """Make ``mitsuba.set_variant('llvm_*')`` fail clearly when no usable LLVM exists."""
    import mitsuba

    original = mitsuba.set_variant
    if getattr(original, '_pbrt_llvm_guard', False):
        return

    def set_variant(*variants):
        names = [v for v in variants if isinstance(v, str)]
        if names and all(v.startswith('llvm') for v in names) and not os.environ.get(ENV_VAR):
            raise LLVMNotFoundError(
                'mitsuba_pbrt_tex: cannot use variant %r: no libLLVM >= %d was found in %s. %s'
                % (names[0], MIN_MAJOR, ', '.join(search_dirs()) or '(no folders)', INSTALL_HINT))
        return original(*variants)

    set_variant._pbrt_llvm_guard = True
    set_variant.__doc__ = original.__doc__
    mitsuba.set_variant = set_variant


def _user_path_problem(path: str) -> str | None:
    """What is wrong with a DRJIT_LIBLLVM_PATH the user set, if we can tell: missing, not a
    file, or a libLLVM whose name says it is older than MIN_MAJOR."""
    if os.sep in path:                  # a bare name is dlopen's to find on the library path
        if not os.path.exists(path):
            return 'does not exist'
        if not os.path.isfile(path):
            return 'is not a file'
    major = llvm_major(os.path.basename(os.path.realpath(path))) or \
        llvm_major(os.path.basename(path))
    if major is not None and major < MIN_MAJOR:
        return f'is LLVM {major}, older than {MIN_MAJOR} (Dr.Jit\'s LLVM backend aborts with it)'
    return None


def bootstrap() -> str | None:
    """Export DRJIT_LIBLLVM_PATH if needed; returns the path in use (or None). A path the user
    set is left alone, with a warning where it cannot work."""
    current = os.environ.get(ENV_VAR)
    if current:
        problem = _user_path_problem(current)
        if problem:
            found = find_libllvm()
            warnings.warn(f'mitsuba_pbrt_tex: {ENV_VAR}={current} {problem}; the LLVM variants '
                          f'will fail. ' + (f'Unset it to use {found}, found on this machine.'
                                            if found else INSTALL_HINT), stacklevel=2)
        return current
    path = find_libllvm()
    if path is not None:
        os.environ[ENV_VAR] = path
        return path
    _guard_set_variant()
    return None
