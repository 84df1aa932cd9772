"""mitsuba-pbrt-tex: PBRT's texture system as Mitsuba 3 plugins written in Dr.Jit.

Typical use::

    import mitsuba as mi
    import mitsuba_pbrt_tex as mpt      # finds a working libLLVM before Dr.Jit starts
    mi.set_variant('llvm_ad_rgb')
    mpt.register()                       # pbrt_* textures and the pbrt_path integrator
    scene = mi.load_file('scenes/demo.xml')

Importing the package first matters only for the LLVM variants: see :mod:`mitsuba_pbrt_tex._llvm`.
"""

import importlib.util as _importlib_util
import os as _os
import sys as _sys

from ._llvm import bootstrap as _bootstrap_llvm


def _map_checkout_folders() -> None:
    """In a source checkout imported as it is — Python started in the repository — the
    checkout's ``plugins/`` and ``scenes/`` folders are the ``plugins`` and ``scenes``
    subpackages, as an install maps them (pyproject's package-dir), also where another copy is
    installed (plainly, or editable from another checkout, whose import hook would answer with
    its own folders). Without this, ``register()`` there failed to find the plugins."""
    root = _os.path.dirname(_os.path.dirname(_os.path.abspath(__file__)))
    if not _os.path.isfile(_os.path.join(root, 'pyproject.toml')):
        return                                          # an installed copy: its own layout
    for name in ('plugins', 'scenes'):
        full = f'{__name__}.{name}'
        folder = _os.path.join(root, name)
        init = _os.path.join(folder, '__init__.py')
        if full in _sys.modules or not _os.path.isfile(init):
            continue
        found = _importlib_util.find_spec(full)
        if found is not None and [_os.path.realpath(p) for p in
                                  (found.submodule_search_locations or [])] == \
                [_os.path.realpath(folder)]:
            continue                                    # already this checkout's folder
        spec = _importlib_util.spec_from_file_location(full, init,
                                                       submodule_search_locations=[folder])
        module = _importlib_util.module_from_spec(spec)
        _sys.modules[full] = module
        spec.loader.exec_module(module)


_map_checkout_folders()

LIBLLVM_PATH = _bootstrap_llvm()

from .registry import INTEGRATORS, PLUGINS, TEXTURES, register  # noqa: E402
from .params import PluginError  # noqa: E402

__version__ = '0.1.0'

__all__ = ['register', 'PLUGINS', 'TEXTURES', 'INTEGRATORS', 'PluginError', 'LIBLLVM_PATH',
           '__version__']
