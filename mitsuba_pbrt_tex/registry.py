"""Registering the plugins with Mitsuba, once per variant.

Mitsuba keeps a plugin registry per variant, and ``mi.Texture`` is a different (nanobind) class in
each variant; nanobind classes also admit only one base class. So a plugin is written as a plain
Python class (a :class:`~mitsuba_pbrt_tex.texture.PbrtTexture` subclass) and
:func:`variant_class` *flattens* it — copies its methods, base classes first — into a fresh class
whose single base is the current variant's ``mi.Texture`` (or integrator base).
:func:`register` does this for every plugin; after the first call it also re-registers
automatically whenever ``mi.set_variant`` switches variant (calling it again is harmless).

Because methods are copied, plugin code must not use zero-argument ``super()`` (its implicit class
is not in the flattened class's MRO); call the base explicitly, e.g.
``PbrtTexture.prepare_differentials(self)``, or ``self._pbrt_base`` for the Mitsuba base class.
"""

from __future__ import annotations

import importlib
import threading

import mitsuba as mi

from . import variants
from .params import PluginError
from .texture import install_update_rollback
from .variants import UnsupportedVariantError

TEXTURES = (
    'pbrt_constant', 'pbrt_scale', 'pbrt_mix', 'pbrt_directionmix', 'pbrt_bilerp', 'pbrt_uv',
    'pbrt_imagemap', 'pbrt_checkerboard', 'pbrt_dots', 'pbrt_fbm', 'pbrt_wrinkled', 'pbrt_windy',
    'pbrt_marble', 'pbrt_supersample',
)
INTEGRATORS = ('pbrt_path',)
PLUGINS = TEXTURES + INTEGRATORS

_classes: dict[tuple[str, str], type] = {}
_lock = threading.Lock()
_callback_installed = False


def plugin_module(name: str):
    if name not in PLUGINS:
        raise KeyError(f'unknown plugin {name!r}; plugins: {", ".join(PLUGINS)}')
    return importlib.import_module(f'mitsuba_pbrt_tex.plugins.{name}')


def variant_class(impl: type, base: type) -> type:
    """A class with single base ``base`` holding ``impl``'s methods (MRO flattened)."""
    namespace: dict = {}
    for klass in reversed(impl.__mro__[:-1]):          # object excluded, bases first
        namespace.update({k: v for k, v in klass.__dict__.items()
                          if k not in ('__dict__', '__weakref__', '__init__')})

    precheck = getattr(impl, 'precheck', None)

    def __init__(self, props):
        try:
            if precheck is not None:      # errors in our words before the base class reads props
                precheck(props)
            base.__init__(self, props)
            self.setup(props)
        except (PluginError, UnsupportedVariantError) as e:
            # raised afresh here: Mitsuba's parser quotes the traceback of what a Python plugin
            # raises, and the frames inside our plugin say nothing the message does not
            raise type(e)(str(e)) from None

    namespace['__init__'] = __init__
    namespace['_pbrt_impl'] = impl
    namespace['_pbrt_base'] = base
    namespace['__module__'] = impl.__module__
    namespace['__qualname__'] = impl.__qualname__
    return type(impl.__name__, (base,), namespace)


def ad_integrators_common():
    """The current variant's ``common`` module of Mitsuba's AD integrators (``RBIntegrator``,
    ``mis_weight``, …). Mitsuba reloads ``mitsuba.python.ad.integrators`` at every
    ``mi.set_variant`` (before variant callbacks run), while its alias ``mitsuba.ad.integrators``
    stays bound to the first variant imported: classes from there fail in any later variant."""
    return importlib.import_module('mitsuba.python.ad.integrators.common')


def _integrator_base() -> type:
    if variants.support_problem(mi.variant()) is None:
        return ad_integrators_common().RBIntegrator
    return mi.SamplingIntegrator


def plugin_class(name: str) -> type:
    """The current variant's class of plugin ``name`` (built once per variant)."""
    variant = mi.variant()
    key = (variant, name)
    with _lock:
        cls = _classes.get(key)
        if cls is None:
            module = plugin_module(name)
            base = mi.Texture if name in TEXTURES else _integrator_base()
            cls = _classes[key] = variant_class(module.Plugin, base)
    return cls


def register() -> None:
    """Register every ``pbrt_*`` plugin for the current Mitsuba variant.

    In unsupported variants (scalar, spectral) the plugins are still registered, so that using
    one fails with a message explaining why rather than "plugin not found".
    """
    global _callback_installed
    if mi.variant() is None:
        raise RuntimeError('mitsuba_pbrt_tex.register(): no Mitsuba variant is set; call '
                           'mi.set_variant("llvm_ad_rgb") (or another variant) first')
    if variants.support_problem(mi.variant()) is None:
        from .image import srgb8_table
        srgb8_table()            # on this thread, not inside a constructor on a worker thread
    install_update_rollback()
    for name in TEXTURES:
        mi.register_texture(name, plugin_class(name))
    for name in INTEGRATORS:
        mi.register_integrator(name, plugin_class(name))
    if not _callback_installed:
        mi.detail.add_variant_callback(_on_variant_change)
        _callback_installed = True


def _on_variant_change(old, new) -> None:
    if new is not None:
        register()
