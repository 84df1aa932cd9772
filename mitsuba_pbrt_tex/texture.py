"""The base of every ``pbrt_*`` texture plugin: evaluation kinds, nesting, traversal, printing.

pbrt has separate Float and Spectrum textures; a Mitsuba texture serves both through ``eval``
(spectrum), ``eval_1`` (float) and ``eval_3`` (RGB). A plugin here writes its math once, in
:meth:`PbrtTexture.evaluate`, generically over a :class:`Kind`: nested textures are evaluated in
the same kind (``eval_1`` of a mix is the mix of the nested ``eval_1`` values — for a nested
Mitsuba texture that is its own ``eval_1``: the mean of the RGB for ``srgb`` constants, the
luminance for ``bitmap``), and values the texture produces itself (an image's RGB, a noise value)
are converted by the kind: RGB → float is the luminance, as for Mitsuba's ``bitmap``.

Plugin classes subclass :class:`PbrtTexture` and are turned into real ``mi.Texture`` subclasses per
variant by :mod:`mitsuba_pbrt_tex.registry` (nanobind classes admit a single base, and
``mi.Texture`` differs per variant).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Callable

import drjit as dr
import mitsuba as mi

from . import render_scope, variants
from .differentials import TextureEvalContext, with_shifting_fields, without_differentials
from .params import Params, PluginError


#: pbrt-v4's bump-mapping offset in u (and v) where the hit has no differentials.
BUMP_DELTA = 0.0005


@dataclass(frozen=True)
class Kind:
    """How values are represented in one evaluation mode: ``nested(tex, si, active)`` evaluates
    a nested texture in it, ``from_rgb`` and ``from_float`` convert a value to it (looked up in
    the current variant when called)."""

    name: str
    nested: Callable
    from_rgb: Callable
    from_float: Callable


def _nested_rgb(tex, si, active):
    if is_pbrt_texture(tex):
        return tex.eval_3(si, active)
    if mi.is_monochromatic:
        return mi.Color3f(tex.eval_1(si, active))
    # In RGB variants eval() is Color3f and, unlike eval_3, every built-in implements it
    # (Mitsuba's checkerboard has no eval_3).
    return mi.Color3f(tex.eval(si, active))


SPECTRUM = Kind('spectrum', lambda tex, si, active: tex.eval(si, active),
                lambda rgb: variants.rgb_to_spectrum(rgb), lambda v: mi.UnpolarizedSpectrum(v))
FLOAT = Kind('float', lambda tex, si, active: tex.eval_1(si, active),
             lambda rgb: mi.luminance(rgb), lambda v: mi.Float(v))
RGB = Kind('rgb', _nested_rgb, lambda rgb: mi.Color3f(rgb), lambda v: mi.Color3f(v))


def finite_gradient(g):
    """An ``eval_1_grad`` result with non-finite components as 0: a mapping's derivatives can
    overflow where its value does not (a spherical mapping scaled by 1e20: |p|² underflows),
    and a bump map must not turn the shading normal into NaN."""
    return dr.select(dr.isfinite(g), g, 0.0)


def is_pbrt_texture(obj) -> bool:
    return getattr(type(obj), '_pbrt_impl', None) is not None


def uses_differentials(tex) -> bool:
    """Does ``tex`` (any texture) read ``si.duv_dx``/``si.duv_dy``?

    Our textures answer for themselves (and prepare for it, e.g. an image texture with the
    ``bilinear`` filter builds its MIP pyramid). Mitsuba's C++ textures never read them. A Python
    texture of the user's that does not say is assumed to read them.
    """
    method = getattr(tex, 'prepare_differentials', None)
    if method is not None:
        return bool(method())
    return type(tex).__module__ not in ('mitsuba', 'builtins') and \
        not type(tex).__module__.startswith('mitsuba.')


def filters_film_kernel(tex) -> bool:
    """Does ``tex`` (any texture) filter the film's own kernel around the pixel centre under
    ``pbrt_path`` ``footprint="pixel"`` with a Gaussian film (``pbrt_imagemap`` ``box``, which
    says so; a nested one is found by the scene's traversal, which lists nested textures too)?
    Only then does such a render draw its camera samples per pixel from the filter
    (:mod:`mitsuba_pbrt_tex.film_view`); other textures keep the sample's footprint there, and
    Mitsuba's own or a user's textures never filter it."""
    method = getattr(tex, 'filters_film_kernel', None)
    return bool(method()) if method is not None else False


@dataclass
class _Shared:
    """A lookup's value and the lanes it was computed on."""
    value: object
    active: object


def _any_literal(value) -> bool:
    """Has ``value`` a component that is a literal (a constant of the kernel)? Such values are
    not shared between a BSDF's queries: Dr.Jit's LLVM backend then emitted the constant inside
    one query's branch and used it in the other's ("Instruction does not dominate all uses",
    aborting the process: a ``pbrt_constant`` or ``pbrt_uv`` with a channel of 0 under
    ``pbrt_path``), and a constant costs nothing to compute again."""
    return any(dr.detail.collect_indices(c) and
               getattr(c, 'state', None) == dr.VarState.Literal for c in _components(value))


def _components(value):
    return [value[i] for i in range(len(value))] if dr.depth_v(value) > 1 else [value]


class PbrtTexture:
    """Shared behaviour of all ``pbrt_*`` textures (flattened into ``mi.Texture`` per variant)."""

    #: plugin name, e.g. ``pbrt_mix``
    NAME = 'pbrt_texture'

    # ------------------------------------------------------------------ construction
    def setup(self, props: mi.Properties) -> None:
        variants.require_supported(self.NAME)
        self._nested: dict[str, mi.Texture] = {}
        self._values: dict[str, object] = {}
        self._describe: dict[str, str] = {}
        self._without_footprint = False
        p = Params(self.NAME, props)
        self.configure(p)
        p.finish()
        self._accepted = self._settable_values()

    def configure(self, p: Params) -> None:
        """Read parameters and build library objects (override)."""

    def nested_texture(self, p: Params, name: str, default: float, *,
                       float_only: bool = False) -> mi.Texture:
        tex = p.texture(name, default, float_only=float_only)
        self._nested[name] = tex
        return tex

    def jit_value(self, name: str, value: float, *, differentiable: bool = True) -> mi.Float:
        """A float parameter held as a JIT value so it can be traversed and optimised."""
        v = mi.Float(value)
        self._values[name] = (v, differentiable)
        return v

    def describe(self, name: str, text) -> None:
        self._describe[name] = str(text)

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, si: mi.SurfaceInteraction3f, kind: Kind, active) -> object:
        raise NotImplementedError

    def context(self, si) -> TextureEvalContext:
        return TextureEvalContext.from_si(si)

    def eval(self, si, active=True):
        return self._lookup(si, SPECTRUM, mi.Bool(active))

    def eval_1(self, si, active=True):
        return self._lookup(si, FLOAT, mi.Bool(active))

    def eval_3(self, si, active=True):
        return self._lookup(si, RGB, mi.Bool(active))

    def eval_1_grad(self, si, active=True):
        """``d eval_1 / d(u, v)`` — what Mitsuba's ``bumpmap`` reads — as pbrt-v4's ``BumpMap``
        takes it: forward differences of ``eval_1`` at the hit moved along u (``p + du·∂p/∂u``,
        ``uv + (du, 0)``, the differentials kept) and along v, with ``du = (|∂u/∂x| +
        |∂u/∂y|)/2`` from the hit's differentials (``dv`` likewise) or :data:`BUMP_DELTA` where
        that is 0 or not finite (Mitsuba's own integrators give none). Image textures override
        it (point, bilinear and trilinear lookups: the exact gradient of their reconstruction).
        A bare interaction (only ``uv`` set) is read with zero differentials, as elsewhere."""
        return self.bump_difference(si, mi.Bool(active), self.eval_1)

    def bump_difference(self, si, active, eval_1) -> mi.Vector2f:
        """:meth:`eval_1_grad`'s difference of the values ``eval_1(si, active)``."""
        si = with_shifting_fields(si)
        f = eval_1(si, active)
        grad = []
        for axis, dp in enumerate((si.dp_du, si.dp_dv)):
            d = 0.5 * (dr.abs(si.duv_dx[axis]) + dr.abs(si.duv_dy[axis]))
            d = dr.select((d > 0) & dr.isfinite(d), d, BUMP_DELTA)
            moved = mi.SurfaceInteraction3f(si)
            moved.p = dr.fma(dp, d, si.p)
            moved.uv = mi.Point2f(si.uv)
            moved.uv[axis] = si.uv[axis] + d
            grad.append((eval_1(moved, active) - f) / d)
        return finite_gradient(mi.Vector2f(*grad))

    def read_without_footprint(self) -> None:
        """From now on every lookup ignores the footprint — the hit's uv partials and, under
        ``pbrt_path`` ``footprint="pixel"``, the pixel's — as pbrt-v4 reads a normal map (a
        bilinear lookup of the full-resolution image: ``pbrt_path`` calls this for the textures
        a ``normalmap`` BSDF reads). A filtered normal map is a smoother one: the shading it
        gives is not the average of the shading of the normals it averages (measured in a user
        trial: a tiled photo normal map on a rough conductor 6% darker than under ``path``, at
        any spp). It stays so for the object's life, also in another scene where it is not a
        normal map (load that scene's textures afresh)."""
        self._without_footprint = True

    def multiplies_varying(self) -> bool:
        """Does this texture multiply spatially varying values together (a composite: override)?
        Then the textures inside it keep the sample's footprint under ``pbrt_path``
        ``footprint="pixel"``: a pixel's average of a product is not the product of the pixel's
        averages, and that bias does not fall with spp (a user trial: ``pbrt_scale`` of two box
        images 42% darker than the reference on a plane's far rows). With the sample's
        footprint it shrinks with the footprint, as in pbrt. (``pbrt_bilerp``'s and
        ``pbrt_directionmix``'s weights are smooth — bilinear in uv, the normal's direction —
        so their covariance with a texture within one pixel is of second order: they keep the
        pixel footprint.)"""
        return False

    def varies(self, *names: str) -> bool:
        """Is any of the nested textures ``names`` spatially varying?"""
        return any(self._nested[n].is_spatially_varying() for n in names)

    def _lookup(self, si, kind: Kind, active):
        """:meth:`evaluate` (without a footprint: :meth:`read_without_footprint`; its children
        with the sample's: :meth:`multiplies_varying`), or within
        :func:`~mitsuba_pbrt_tex.render_scope.shared_lookups` — where a BSDF's ``eval`` and
        ``sample`` ask the same interaction (the same JIT variables) — the first query's value
        on its lanes and :meth:`evaluate` only on the lanes it did not cover, in a symbolic
        branch (packets with none skip it)."""
        if self._without_footprint:
            with render_scope.unpublished():
                return self.evaluate(without_differentials(si), kind, active)
        if self.multiplies_varying() and render_scope.current() is not None:
            with render_scope.unpublished():
                return self._lookup(si, kind, active)
        table = render_scope.lookups()
        if table is None:
            return self.evaluate(si, kind, active)
        key = (id(self), kind.name, tuple(dr.detail.collect_indices(si)))
        first = table.get(key)
        if first is None:
            value = self.evaluate(si, kind, active)
            if not _any_literal(value):         # (a literal is not worth sharing, see below)
                table[key] = _Shared(value, active)
            return value
        rest = active & ~first.active

        def remaining(si, rest):
            with render_scope.unshared():
                return self.evaluate(si, kind, rest)

        more = dr.if_stmt(args=(si, rest), cond=rest, true_fn=remaining,
                          false_fn=lambda si, rest: dr.zeros(type(first.value)),
                          label=f'{self.NAME}: lanes not yet looked up')
        return dr.select(first.active, first.value, more)

    def nested_eval(self, name: str, si, kind: Kind, active):
        return kind.nested(self._nested[name], si, active)

    def blend_nested(self, amount, si, kind: Kind, active):
        """``(1 - amount)·tex1 + amount·tex2`` of the nested textures ``tex1``, ``tex2``, each
        evaluated only where its weight is non-zero, as pbrt-v4's ``MixTexture``: the lookup is
        saved, and a texture that is infinite or NaN where its weight is 0 leaves the blend
        finite. Computed as ``tex1 + amount·(tex2 - tex1)``, exact for equal values whatever the
        amount (pbrt's form is NaN for an amount of 3e38 and two values of 2: -inf + inf), and
        kept within float32's range (:func:`finite_range`). An amount carrying gradients reads
        both textures everywhere: its derivative ``tex2 - tex1`` is needed where pbrt skips one
        (an amount of 0 or 1 had a gradient of 0: an optimiser started there never moved); where
        the skipped one is not finite the value stays finite and the derivative is 0."""
        use1, use2 = amount != 1, amount != 0
        differentiated = dr.grad_enabled(amount)
        t1 = self.nested_eval('tex1', si, kind, active & (use1 | differentiated))
        t2 = self.nested_eval('tex2', si, kind, active & (use2 | differentiated))
        both = dr.fma(amount, t2 - t1, t1)
        out = finite_range(dr.select(use1, dr.select(use2, both, t1), t2))
        return derivative_unskipped(out, both) if differentiated else out

    # ------------------------------------------------------------------ Mitsuba interface
    def mean(self):
        return mi.Float(0.5)

    def is_spatially_varying(self) -> bool:
        return True

    def nested_vary(self) -> bool:
        """Whether any nested texture is spatially varying: a composite's own answer, where its
        value is a function of the nested values alone (so that ``pbrt_scale`` or ``pbrt_mix``
        of constants can be a ``constant`` or ``directional`` emitter's radiance, as ``rgb``
        can)."""
        return any(t.is_spatially_varying() for t in self._nested.values())

    def max(self):
        """Not implemented, as for Mitsuba's own textures (``bitmap``, ``checkerboard``): an error
        saying so, where the unbound method was a raw "pure virtual function" error."""
        raise RuntimeError(f'{self.NAME}: max() is not implemented (nor is it for Mitsuba\'s '
                           f'bitmap or checkerboard)')

    def spectral_resolution(self):
        """Not implemented, as for every Mitsuba texture: the same error in this texture's name
        (the unbound method was a raw "pure virtual function" error)."""
        raise RuntimeError(f'{self.NAME}: spectral_resolution() is not implemented (nor is it '
                           f'for Mitsuba\'s bitmap, checkerboard or srgb)')

    def sample_spectrum(self, si, sample, active=True):
        """RGB and mono variants sample no wavelengths: (empty wavelengths, the value), as
        Mitsuba's ``bitmap`` — what light tracing (``ptracer``) and an emitter's ``sample_ray``
        ask of a radiance texture."""
        return type(si.wavelengths)(), self.eval(si, active)

    def pdf_spectrum(self, si, active=True):
        """RGB and mono variants: no wavelengths are sampled, so the density is empty
        (``bitmap`` raises NotImplementedError here)."""
        return type(si.wavelengths)()

    def prepare_differentials(self) -> bool:
        """Called by ``pbrt_path`` before rendering: does this texture use differentials?"""
        return any(uses_differentials(t) for t in self._nested.values())

    def traverse(self, cb) -> None:
        for name, tex in self._nested.items():
            cb.put(name, tex, mi.ParamFlags.Differentiable)
        for name, (value, diff) in self._values.items():
            cb.put(name, value, mi.ParamFlags.Differentiable if diff
                   else mi.ParamFlags.NonDifferentiable)

    def parameters_changed(self, keys=None) -> None:
        """Check what ``params.update()`` set (Mitsuba has already written it into this
        texture's parameters and its nested constants), then :meth:`on_parameters_changed`. A
        refusal puts back the values this texture last accepted — the one refused and any
        other set in the same update — before it raises: a texture whose parameters were
        refused renders as before (and ``params[key]`` reads the accepted value again), where
        a refused ``data`` shape ended the next render inside Dr.Jit and a refused NaN ``scale``
        rendered NaN (found by a user trial)."""
        keys = list(keys or [])
        try:
            self._check_update(keys)
            self.on_parameters_changed(keys)
        except PluginError:
            self._restore(self._accepted)
            self.on_parameters_changed(keys)        # the state of the values put back
            raise
        self._accepted = self._settable_values()

    def _check_update(self, keys: list[str]) -> None:
        for name in keys or [*self._values, *self._nested]:
            if name in self._values:
                check_value_update(self.NAME, name, self._values[name][0])
            elif name in self._nested and not self._nested[name].is_spatially_varying():
                # a float or rgb value (Mitsuba's uniform/srgb texture): its parameters (not its
                # mean, which overflows for finite channels of 2e38)
                inner = mi.traverse(self._nested[name])
                for key in inner.keys():
                    if dr.is_jit_v(type(inner[key])):
                        check_value_update(self.NAME, f'{name}.{key}', inner[key],
                                           check_width=False)

    def _traversed(self) -> dict:
        """What :meth:`traverse` puts, by name (the objects themselves)."""
        return children(self)

    def _settable_values(self) -> dict:
        """What ``params.update()`` can write in place: this texture's traversed values and
        the parameters of its nested constants (a Mitsuba ``srgb``, ``uniform``), as ``{(name,
        key): copy}`` (``key`` None for the texture's own) — copies that refer to the same
        variables (no memory of their own), which :meth:`_restore` writes back."""
        out = {}
        for name, value in self._traversed().items():
            if name in self._nested:
                if not value.is_spatially_varying():
                    inner = mi.traverse(value)
                    out.update({(name, key): _copy(inner[key]) for key in inner.keys()
                                if dr.is_jit_v(type(inner[key]))})
            else:
                out[(name, None)] = _copy(value)
        return out

    def _restore(self, accepted: dict) -> None:
        """Write the values of :meth:`_settable_values` back where they came from."""
        own = self._traversed()
        nested = {}
        for (name, key), value in accepted.items():
            if key is None:
                mi.set_property(own[name], value)
            else:
                inner = nested.setdefault(name, mi.traverse(own[name]))
                inner[key] = value
        for inner in nested.values():
            inner.update()

    def on_parameters_changed(self, keys: list[str]) -> None:
        """React to changed parameters (override)."""

    def to_string(self) -> str:
        parts = [f'{k}={v}' for k, v in self._describe.items()]
        for name, tex in self._nested.items():
            parts.append(f'{name}={_short(tex)}')
        for name, (value, _) in self._values.items():
            parts.append(f'{name}={_short(value)}')
        return f'{self.NAME}[' + ', '.join(parts) + ']'


def install_update_rollback() -> None:
    """Make a refused ``params.update()`` leave every ``pbrt_*`` texture of the update as it
    was. Mitsuba's ``SceneParameters.update`` writes the values first and then tells the changed
    objects in turn, children before parents, and stops at the first error: a texture of ours
    told before the refusal had accepted its new values, and one never told kept whatever was
    written (a bad ``data`` shape in another texture ended the next render inside Dr.Jit, a NaN
    in a parent ``pbrt_mix``'s amount stayed; found by a review). The wrapper (installed once,
    by :func:`~mitsuba_pbrt_tex.registry.register`; it calls Mitsuba's own ``update`` and acts
    only when that raises) puts back, in each of our textures the update marked, the values it
    had accepted before the update, and rebuilds what those told already had rebuilt, then
    re-raises. Mitsuba's own objects are as Mitsuba leaves them (the marks stay, so the next
    ``update()`` tells them again)."""
    cls = mi.SceneParameters
    if getattr(cls.update, '_pbrt_rollback', False):
        return
    original = cls.update

    def update(self, values=None):
        before = {id(node): getattr(node, '_accepted', None) for node in self.hierarchy
                  if is_pbrt_texture(node)}
        try:
            return original(self, values)
        except Exception:
            for (_, node), keys in self.nodes_to_update.items():
                accepted = before.get(id(node))
                if accepted is None:
                    continue
                told = node._accepted is not accepted
                node._restore(accepted)
                if told:
                    node.on_parameters_changed(list(keys))
                    node._accepted = accepted
            raise

    update.__doc__ = original.__doc__
    update._pbrt_rollback = True
    cls.update = update


@functools.lru_cache(maxsize=None)
def _collector(variant: str) -> type:
    """A traversal callback class of ``variant``'s ``mi.TraversalCallback`` that keeps what it
    is given (made once per variant: a class per call cost 10× the traversal)."""
    class Collect(mi.TraversalCallback):
        def __init__(self):
            super().__init__()
            self.values = {}

        def put(self, name, value, flags, cpptype=None):
            self.values[name] = value

    return Collect


def children(obj) -> dict:
    """The objects and values that ``obj.traverse`` puts, by name (its direct children: a
    composite's nested textures and values, the ``normalmap`` and ``nested_bsdf`` of a
    ``normalmap`` BSDF) — any Mitsuba object, ours or Mitsuba's."""
    collect = _collector(mi.variant())()
    obj.traverse(collect)
    return collect.values


def _copy(value):
    """A new object for the same value (Dr.Jit arrays: the same variable; a transform: its
    matrix)."""
    return type(value)(value)


def check_value_update(plugin: str, name: str, value, check_width: bool = True) -> None:
    """A value set through ``mi.traverse`` must be one number (or colour), as at construction
    (a wider array failed inside Dr.Jit's call of the texture), and finite (a NaN or inf
    parameter would put NaN or inf in every image): else an error naming the fix (the texture
    puts its accepted values back: :meth:`PbrtTexture.parameters_changed`). The finiteness
    check is skipped, as the texels' checks are, for values with gradients (an optimiser's
    step: reading them back would cost a synchronisation per step) and while ``dr.freeze``
    records (which cannot read values back).
    ``check_width`` false: a nested Mitsuba texture's parameter, whose width is its own business
    (a spectrum's table has several values)."""
    if check_width and dr.width(value) != 1:
        raise PluginError(f'{plugin}: parameter "{name}": a value of width {dr.width(value)} '
                          f'set through mi.traverse; accepted values: one number or colour '
                          f'(width 1; set one and call params.update() again)')
    if dr.grad_enabled(value) or dr.flag(dr.JitFlag.FreezingScope):
        return
    v = dr.detach(value)
    if not bool(dr.all(dr.isfinite(v), axis=None)):
        raise PluginError(f'{plugin}: parameter "{name}": value {_short(v)} set through '
                          f'mi.traverse is not finite; accepted values: finite numbers (set one '
                          f'and call params.update() again)')


def _short(obj) -> str:
    try:
        text = str(obj)
    except Exception:  # pragma: no cover - printing must never fail
        text = type(obj).__name__
    text = ' '.join(text.split())
    return text if len(text) < 80 else text[:77] + '...'


#: float32's largest finite value
FLOAT32_MAX = 3.4028234663852886e38


def derivative_unskipped(value, unskipped):
    """``value`` (pbrt's, which skipped a lookup where its weight is 0) differentiated as
    ``unskipped`` (the same formula with every lookup made): the derivative with respect to the
    weight is not 0 where the lookup was skipped. 0 where ``unskipped`` is not finite (a
    skipped texture of inf there: one optimiser step would turn an inf derivative into NaN)."""
    return dr.replace_grad(value, dr.select(dr.isfinite(unskipped), unskipped, value))


def finite_range(x):
    """``x`` with ±inf from an overflowing product or sum made ±FLOAT32_MAX (NaN stays NaN:
    what produces one must avoid it)."""
    return dr.clip(x, -FLOAT32_MAX, FLOAT32_MAX)


def nested_mean(tex: mi.Texture) -> mi.Float:
    """``tex.mean()`` (a Float) of any texture, built-in or ours."""
    return mi.Float(tex.mean())
