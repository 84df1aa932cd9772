"""Reading plugin parameters from ``mi.Properties`` with pbrt's names, defaults and clear errors.

Every error is a :class:`PluginError` whose message names the plugin, the parameter, the bad value
and what would have been accepted, e.g.::

    pbrt_imagemap: parameter "filter": unknown value "cubic"; accepted values: point, bilinear,
    trilinear, ewa

:meth:`Params.finish` rejects parameters the plugin does not know (typos such as ``amout``) with the
list of the plugin's parameters, instead of Mitsuba's generic "unreferenced property" message.
"""

from __future__ import annotations

import math
from typing import Iterable

import drjit as dr
import mitsuba as mi
import numpy as np

#: The largest finite float32. Mitsuba reads numbers as doubles; larger values would silently
#: become inf once they reach a float32 variant's arrays.
FLOAT32_MAX = float(np.finfo(np.float32).max)

#: Bounds on a texture space's ``to_world`` (singular values of its 3×3 part): lookups apply
#: its inverse in float32, so the inverse must exist and be representable with some precision.
TO_WORLD_MIN_SCALE = 1e-9          # a point at distance 1 lands at most 1e9 texture units away
TO_WORLD_MAX_CONDITION = 1e7       # float32 has 24 bits: a worse-conditioned inverse is noise


class PluginError(ValueError):
    """A plugin parameter has a bad value (the message names plugin, parameter and choices)."""


_TYPE_NAMES = {
    'Float': 'float', 'Integer': 'integer', 'Bool': 'boolean', 'String': 'string',
    'Color': 'rgb', 'Spectrum': 'spectrum', 'Transform': 'transform', 'Vector': 'vector',
    'Object': 'nested object', 'Tensor': 'tensor', 'Any': 'Python object',
}


def _type_name(props: mi.Properties, name: str) -> str:
    t = str(props.type(name)).split('.')[-1]
    return _TYPE_NAMES.get(t, t.lower())


#: the type names that take "an" (``an integer``, ``an rgb``); every other takes "a"
_AN = ('integer', 'rgb')


def _a_type(props: mi.Properties, name: str) -> str:
    """``a float``, ``an integer``, ``an rgb`` … for error messages."""
    kind = _type_name(props, name)
    return f'{"an" if kind in _AN else "a"} {kind}'


def _value_text(props: mi.Properties, name: str) -> str:
    """``an rgb value ([1, 0, 0])`` etc. for error messages."""
    kind = _type_name(props, name)
    if kind == 'rgb':
        c = props[name]
        return f'an rgb value ([{float(c[0]):g}, {float(c[1]):g}, {float(c[2]):g}])'
    return f'a {kind} value'


#: pbrt-v3 parameters that pbrt-v4 (whose names the plugins take) renamed: the unknown-parameter
#: error says what to write instead.
PBRT_V3_NAMES = {
    ('pbrt_imagemap', 'gamma'): '"gamma" is pbrt-v3\'s: pbrt-v4 (and this plugin) take '
                                'encoding="sRGB", "linear" or "gamma G"',
    ('pbrt_imagemap', 'trilinear'): '"trilinear" is pbrt-v3\'s: pbrt-v4 (and this plugin) take '
                                    'filter="trilinear"',
    ('pbrt_scale', 'tex1'): '"tex1"/"tex2" are pbrt-v3\'s: pbrt-v4 (and this plugin) take '
                            '"tex" and "scale"',
    ('pbrt_scale', 'tex2'): '"tex1"/"tex2" are pbrt-v3\'s: pbrt-v4 (and this plugin) take '
                            '"tex" and "scale"',
}


class Params:
    """Typed access to one plugin's properties; remembers what it read."""

    def __init__(self, plugin: str, props: mi.Properties):
        self.plugin = plugin
        self.props = props
        self.known: list[str] = []

    # ------------------------------------------------------------------ helpers
    def error(self, name: str, message: str) -> PluginError:
        return PluginError(f'{self.plugin}: parameter "{name}": {message}')

    def _note(self, *names: str) -> None:
        for n in names:
            if n not in self.known:
                self.known.append(n)

    def has(self, name: str) -> bool:
        self._note(name)
        return name in self.props

    def _kind(self, name: str) -> str:
        return str(self.props.type(name)).split('.')[-1]

    def _pick(self, name: str, alias: str | None) -> str | None:
        """Which of ``name``/``alias`` the user gave (error if both)."""
        self._note(name)
        if alias is not None:
            self._note(alias)
        has_name = name in self.props
        has_alias = alias is not None and alias in self.props
        if has_name and has_alias:
            raise self.error(name, f'given together with its alias "{alias}"; give only one of them')
        return name if has_name else (alias if has_alias else None)

    # ------------------------------------------------------------------ scalars
    def float(self, name: str, default: float, *, lo: float | None = None,
              hi: float | None = None, lo_open: bool = False, alias: str | None = None) -> float:
        key = self._pick(name, alias)
        if key is None:
            return float(default)
        if self._kind(key) not in ('Float', 'Integer'):
            raise self.error(key, f'expected a float, got {_a_type(self.props, key)} '
                                  f'({self.props[key]!r})')
        value = float(self.props[key])
        self.check_range(key, value, lo=lo, hi=hi, lo_open=lo_open)
        return value

    def int(self, name: str, default: int, *, lo: int | None = None,
            hi: int | None = None, strict: bool = False) -> int:
        """An integer; a float with an integer value too (3.0), unless ``strict`` (for what
        Mitsuba's C++ base classes read themselves: a float there is their type error)."""
        key = self._pick(name, None)
        if key is None:
            return int(default)
        if not strict and self._kind(key) == 'Float' and float(self.props[key]).is_integer():
            value = int(self.props[key])
        elif self._kind(key) != 'Integer':
            raise self.error(key, f'expected an integer, got {_a_type(self.props, key)} '
                                  f'({self.props[key]!r})')
        else:
            value = int(self.props[key])
        self.check_range(key, value, lo=lo, hi=hi)
        return value

    def bool(self, name: str, default: bool, *, alias: str | None = None) -> bool:
        key = self._pick(name, alias)
        if key is None:
            return bool(default)
        if self._kind(key) != 'Bool':
            raise self.error(key, f'expected a boolean (true or false), got '
                                  f'{_a_type(self.props, key)} ({self.props[key]!r})')
        return bool(self.props[key])

    def string(self, name: str, default: str | None, *, alias: str | None = None) -> str | None:
        key = self._pick(name, alias)
        if key is None:
            return default
        if self._kind(key) != 'String':
            raise self.error(key, f'expected a string, got {_a_type(self.props, key)}')
        return str(self.props[key])

    def enum(self, name: str, default: str, choices: Iterable[str], *, alias: str | None = None,
             alias_choices: dict[str, str] | None = None,
             spellings: dict[str, str] | None = None) -> str:
        """A string from ``choices`` (or another spelling of one, ``spellings``: pbrt's "EWA");
        the alias (if any) maps through ``alias_choices``."""
        choices = list(choices)
        key = self._pick(name, alias)
        if key is None:
            return default
        if self._kind(key) != 'String':
            raise self.error(key, f'expected a string, got {_a_type(self.props, key)}; '
                                  f'accepted values: {", ".join(choices)}')
        value = str(self.props[key])
        if key == alias and alias_choices is not None:
            if value not in alias_choices:
                raise self.error(key, f'unknown value "{value}"; accepted values: '
                                      f'{", ".join(alias_choices)}')
            return alias_choices[value]
        value = (spellings or {}).get(value, value)
        if value not in choices:
            raise self.error(key, f'unknown value "{value}"; accepted values: {", ".join(choices)}')
        return value

    def check_range(self, key: str, value, *, lo=None, hi=None, lo_open: bool = False) -> None:
        """``value`` (of parameter ``key``) within ``[lo, hi]`` (``(lo, hi]`` with ``lo_open``);
        a float also finite and within float32's range. An open bound holds for the value as a
        float32 variant stores it: 1e-50 is not > 0 there."""
        if isinstance(value, float):
            self._check_finite(key, value)
        stored = float(np.float32(value)) if isinstance(value, float) else value
        if lo is not None and (value < lo or (lo_open and stored <= lo)):
            bound = f'> {lo}' if lo_open else f'>= {lo}'
            rounded = f' ({stored:g} in float32)' if stored != value else ''
            raise self.error(key, f'must be {bound}, got {value}{rounded}')
        if hi is not None and value > hi:
            raise self.error(key, f'must be <= {hi}, got {value}')

    def _check_finite(self, key, *values) -> None:
        """Every value finite and within float32's range (1e39 would become inf)."""
        shown = values[0] if len(values) == 1 else list(values)
        if not all(math.isfinite(v) for v in values):
            raise self.error(key, f'must be finite, got {shown}')
        if any(abs(v) > FLOAT32_MAX for v in values):
            raise self.error(key, f'must be within float32\'s range (magnitude at most '
                                  f'{FLOAT32_MAX:.8g}), got {shown}')

    def float_or_rgb(self, name: str, default: float) -> float | tuple[float, float, float]:
        """A float, or an ``rgb`` value as a tuple of three floats."""
        key = self._pick(name, None)
        if key is None:
            return float(default)
        kind = self._kind(key)
        if kind in ('Float', 'Integer'):
            return self.float(name, default)
        if kind != 'Color':
            raise self.error(key, f'expected a float or an rgb value, got '
                                  f'{_a_type(self.props, key)}')
        c = self.props[key]
        rgb = (float(c[0]), float(c[1]), float(c[2]))
        self._check_finite(key, *rgb)
        return rgb

    # ------------------------------------------------------------------ vectors and transforms
    def vector(self, name: str, default) -> mi.ScalarVector3f:
        key = self._pick(name, None)
        if key is None:
            return mi.ScalarVector3f(default)
        if self._kind(key) not in ('Vector', 'Color'):
            raise self.error(key, f'expected a 3D vector (e.g. <vector name="{key}" x="1" y="0" '
                                  f'z="0"/>), got {_a_type(self.props, key)}')
        v = self.props[key]
        xyz = (float(v[0]), float(v[1]), float(v[2]))
        self._check_finite(key, *xyz)
        return mi.ScalarVector3f(*xyz)

    def transform(self, name: str, *, alias: str | None = None,
                  invertible: bool = False) -> mi.ScalarTransform4f | None:
        """A transform; ``invertible``: one whose inverse lookups apply (a texture space's
        ``to_world``), so it must not be singular or too close to it (see the bounds above)."""
        key = self._pick(name, alias)
        if key is None:
            return None
        if self._kind(key) != 'Transform':
            got = _a_type(self.props, key)
            if 'Projective' in type(self.props[key]).__name__:
                got = f'a projective transform ({type(self.props[key]).__name__})'
            raise self.error(key, f'expected an affine transform (mi.ScalarTransform4f, or '
                                  f'<transform> in XML), got {got}')
        m = self.props[key].matrix
        values = [float(m[i][j]) for i in range(4) for j in range(4)]
        if not all(math.isfinite(x) for x in values):
            raise self.error(key, 'the matrix has non-finite entries')
        if any(abs(x) > FLOAT32_MAX for x in values):
            raise self.error(key, f'the matrix has entries beyond float32\'s range (magnitude at '
                                  f'most {FLOAT32_MAX:.8g})')
        if invertible:
            linear = np.array(values, dtype=np.float64).reshape(4, 4)[:3, :3]
            sv = np.linalg.svd(linear, compute_uv=False)
            if not (sv[-1] >= TO_WORLD_MIN_SCALE and sv[-1] >= sv[0] / TO_WORLD_MAX_CONDITION):
                raise self.error(key, f'is singular or nearly so (singular values of its 3x3 '
                                      f'part: {", ".join(f"{x:.3g}" for x in sv)}); lookups use '
                                      f'its inverse, so accepted: smallest singular value >= '
                                      f'{TO_WORLD_MIN_SCALE:g} and >= largest / '
                                      f'{TO_WORLD_MAX_CONDITION:g}')
        return mi.ScalarTransform4f(dr.scalar.Matrix4f(m))

    # ------------------------------------------------------------------ textures
    def texture(self, name: str, default: float, *, float_only: bool = False) -> mi.Texture:
        """A float, an ``rgb``/``spectrum`` value, or a nested texture (as pbrt allows).

        ``float_only``: a parameter pbrt declares as a *float* texture (evaluated with
        ``eval_1``) refuses rgb and spectrum values, which would silently become their grey
        mean; nested textures are accepted (their ``eval_1``)."""
        key = self._pick(name, None)
        if key is None:
            return self.props.get_unbounded_texture(name, float(default))
        kind = self._kind(key)
        if float_only and (kind == 'Color' or (kind == 'Spectrum'
                                               and not self.props[key].is_uniform())):
            raise self.error(key, f'expected a float or a texture, got {_value_text(self.props, key)}'
                                  f'; this parameter is a float texture (an rgb or spectrum value '
                                  f'would be used as its grey mean)')
        if kind == 'Object':
            obj = self.props[key]
            if not isinstance(obj, mi.Texture):
                raise self.error(key, f'expected a float, an rgb value or a nested texture, got '
                                      f'a nested {type(obj).__name__}')
            return obj
        if kind in ('Float', 'Integer', 'Color', 'Spectrum'):
            if kind in ('Float', 'Integer'):
                self._check_finite(key, float(self.props[key]))
            elif kind == 'Color':
                c = self.props[key]
                self._check_finite(key, float(c[0]), float(c[1]), float(c[2]))
            return self.props.get_unbounded_texture(key)
        raise self.error(key, f'expected a float, an rgb value or a nested texture, got '
                              f'{_a_type(self.props, key)}')

    def raw(self, name: str):
        """Any value (used for runtime-only objects such as tensors)."""
        key = self._pick(name, None)
        return None if key is None else self.props[key]

    # ------------------------------------------------------------------ end
    def finish(self) -> None:
        """Reject unknown parameters (with pbrt-v4's name for a pbrt-v3 one:
        :data:`PBRT_V3_NAMES`), then mark everything as read for Mitsuba."""
        unknown = [k for k in self.props.keys() if k not in self.known]
        if unknown:
            known = ', '.join(self.known) if self.known else '(none)'
            hints = ''.join(f'; {h}' for h in dict.fromkeys(
                PBRT_V3_NAMES[self.plugin, u] for u in unknown if (self.plugin, u) in PBRT_V3_NAMES))
            raise PluginError(f'{self.plugin}: unknown parameter{"s" if len(unknown) > 1 else ""} '
                              f'{", ".join(repr(u) for u in unknown)}; accepted parameters: '
                              f'{known}{hints}')
        for k in self.props.keys():
            self.props.mark_queried(k)
