"""mitsuba-pbrt-tex: PBRT's texture system as Mitsuba 3 plugins written in Dr.Jit.

Typical use::

    import mitsuba as mi
    import mitsuba_pbrt_tex as mpt      # finds a working libLLVM before Dr.Jit starts
    mi.set_variant('llvm_ad_rgb')
    mpt.register()                       # pbrt_* textures and the pbrt_path integrator
    scene = mi.load_file('scenes/demo.xml')

Importing the package first matters only for the LLVM variants: see :mod:`mitsuba_pbrt_tex._llvm`.
"""

from ._llvm import bootstrap as _bootstrap_llvm

LIBLLVM_PATH = _bootstrap_llvm()

from .registry import INTEGRATORS, PLUGINS, TEXTURES, register  # noqa: E402
from .params import PluginError  # noqa: E402

__version__ = '0.1.0'

__all__ = ['register', 'PLUGINS', 'TEXTURES', 'INTEGRATORS', 'PluginError', 'LIBLLVM_PATH',
           '__version__']
