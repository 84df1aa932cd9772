"""What a scene asks of ``pbrt_path``, found once per scene rather than at every render.

Before it traces, ``pbrt_path`` needs to know which of its stages a scene can use
(:class:`SceneNeeds`): whether any texture reads differentials (none: nothing is computed, and the
cost is that of a plain path tracer), whether any BSDF has an ideal specular lobe (only then is a
ray differential carried from bounce to bounce), and on which shapes the camera approximation
after a bounce has a reader. It also needs pbrt-v4's camera approximation
(:class:`~mitsuba_pbrt_tex.raydiff.CameraFootprint`) for the sensor. Both are kept in a
:class:`SceneCache` that the integrator owns, because finding them costs more than tracing the
rest (a traversal is 10 ms for a thousand shapes; the camera approximation, 512 sensor rays and
a few kernels).

Keys: Mitsuba objects admit no weak references and an ``id()`` can be reused, so a scene is
recognised by the JIT array of its shapes (``shapes_dr()``), and a sensor by its parameters (JIT
arrays by variable index, the rest by value: :func:`state_key`) — each key holds the arrays it
names, so that no later object can take their indices.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from . import raydiff
from .texture import children, filters_film_kernel, is_pbrt_texture, uses_differentials


@dataclass(frozen=True)
class SceneNeeds:
    """What ``pbrt_path`` computes for a scene."""

    #: some texture reads differentials (each was prepared: ``prepare_differentials()``)
    differentials: bool = False
    #: some BSDF has an ideal specular lobe to propagate a ray differential through
    specular: bool = False
    #: a Bool mask over Mitsuba's shape ids: the shapes whose textures read the camera
    #: approximation after a bounce (None: every shape, or nothing to skip; :func:`reader_shapes`)
    reader_shapes: object = None
    #: some texture filters a Gaussian film's kernel (``texture.filters_film_kernel``): only
    #: then does ``footprint="pixel"`` with such a film draw the camera samples per pixel
    film_kernel: bool = False


@dataclass(frozen=True)
class TraceInputs:
    """What one ``sample()`` hands its path loop, computed outside the loop."""

    needs: SceneNeeds
    #: the camera differential's scale (``spp_scale``), an opaque Float
    scale: object = None
    #: pbrt-v4's camera approximation, when some texture reads differentials
    camera: raydiff.CameraFootprint | None = None


class SceneCache:
    """The integrator's memory of the last scene and sensor it rendered (see the module
    docstring). A Dr.Jit struct, so that ``dr.freeze`` sees the arrays it holds (the shape
    mask) as inputs of a frozen function."""

    DRJIT_STRUCT = {'_scene': object, '_camera': object}

    def __init__(self):
        self._scene = None          # (shapes_dr held, readers held, SceneNeeds)
        self._camera = None         # (sensor key, arrays held, CameraFootprint)

    def needs(self, scene) -> SceneNeeds:
        """The scene's :class:`SceneNeeds`. A texture, once prepared, stays so (an image rebuilds
        every MIP level it had when its texels change). A scene without shapes is traversed
        every time (nothing to key on, little to traverse)."""
        shapes = scene.shapes_dr()
        if self._scene is not None and shapes.index != 0 and \
                self._scene[0].index == shapes.index:
            return self._scene[2]
        nodes = list(mi.traverse(scene).hierarchy.keys())
        plain = normal_maps(nodes)
        for tex in plain.values():
            if is_pbrt_texture(tex):
                tex.read_without_footprint()
        readers = [n for n in nodes if isinstance(n, mi.Texture) and id(n) not in plain and
                   uses_differentials(n)]
        delta = int(mi.BSDFFlags.DeltaReflection | mi.BSDFFlags.DeltaTransmission)
        specular = any(int(n.flags()) & delta for n in nodes if isinstance(n, mi.BSDF))
        kernel = [t for t in readers if filters_film_kernel(t)]
        if kernel:                  # (the walk over every object only where it can matter)
            direct = pixel_readers(nodes)
            kernel = [t for t in kernel if id(t) in direct]
        needs = SceneNeeds(bool(readers), specular, reader_shapes(scene, readers), bool(kernel))
        self._scene = (shapes, readers, needs)
        return needs

    def camera(self, sensor) -> raydiff.CameraFootprint:
        """The camera approximation of ``sensor``: found again when any of its parameters has
        changed, and always while ``dr.freeze`` records (the frozen function must record its
        kernels)."""
        key, held = state_key(sensor)
        if self._camera is not None and self._camera[0] == key and \
                not dr.flag(dr.JitFlag.FreezingScope):
            return self._camera[2]
        with dr.suspend_grad():
            camera = raydiff.CameraFootprint(sensor)
        self._camera = (key, held, camera)
        return camera


def _textures_below(start) -> dict:
    """The textures in ``start`` and those nested in them (``{id: texture}``)."""
    found, stack = {}, list(start)
    while stack:
        tex = stack.pop()
        if not isinstance(tex, mi.Texture) or id(tex) in found:
            continue
        found[id(tex)] = tex
        stack.extend(children(tex).values())
    return found


def normal_maps(nodes) -> dict:
    """The textures that ``normalmap`` BSDFs among ``nodes`` read as their normal map, and those
    nested in them (``{id: texture}``): pbrt-v4 reads a normal map without a footprint, and so
    do our textures there (:meth:`~mitsuba_pbrt_tex.texture.PbrtTexture.read_without_footprint`).
    Found from each BSDF's own children, so also a texture object that the normal map shares
    with another slot (a traversal's ``hierarchy`` records one parent per object); it is then
    read without a footprint there too."""
    return _textures_below(children(n).get('normalmap') for n in nodes
                           if isinstance(n, mi.BSDF) and n.class_name() == 'NormalMap')


def pixel_readers(nodes) -> dict:
    """The textures that can read a pixel's footprint where they are used (``{id: texture}``):
    those a BSDF, emitter or other object among ``nodes`` reads, and those nested in them —
    not a normal map (read without a footprint) and not what a composite that multiplies
    spatially varying values nests (its textures keep the sample's footprint:
    :meth:`~mitsuba_pbrt_tex.texture.PbrtTexture.multiplies_varying`)."""
    found, stack = {}, []
    for node in nodes:
        if isinstance(node, mi.Texture):
            continue
        slots = children(node)
        if isinstance(node, mi.BSDF) and node.class_name() == 'NormalMap':
            slots.pop('normalmap', None)
        stack.extend(v for v in slots.values() if isinstance(v, mi.Texture))
    while stack:
        tex = stack.pop()
        if id(tex) in found:
            continue
        found[id(tex)] = tex
        if not (is_pbrt_texture(tex) and tex.multiplies_varying()):
            stack.extend(v for v in children(tex).values() if isinstance(v, mi.Texture))
    return found


def reader_shapes(scene, readers):
    """Which shapes have a texture that reads differentials in their BSDF or emitter (nested
    ones included): a mask over Mitsuba's shape registry ids (``si.shape``) — or None where
    there is nothing to skip: every shape has one, no texture reads differentials, or the scene
    has instances (the shapes hit inside them are not the scene's). The camera approximation
    after a bounce is computed only on the shapes it marks; a propagated ray differential is
    never affected (specular hits use the ray's own, on any shape)."""
    shapes = scene.shapes()
    if not readers or not shapes or any(s.class_name() == 'Instance' for s in shapes):
        return None
    wanted = {id(t) for t in readers}               # the readers are held by the caller
    seen = {}                                       # id → (object held, holds a reader)

    def holds(obj):
        if obj is None:
            return False
        if id(obj) not in seen:
            nodes = mi.traverse(obj).hierarchy.keys()
            seen[id(obj)] = (obj, any(id(n) in wanted for n in nodes))
        return seen[id(obj)][1]

    ids = [int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s))[0]) for s in shapes]
    marked = [i for i, s in zip(ids, shapes) if holds(s.bsdf()) or holds(s.emitter())]
    if len(marked) == len(shapes):
        return None
    table = dr.zeros(mi.Bool, max(ids) + 1)
    if marked:
        dr.scatter(table, True, mi.UInt32(marked))
    dr.eval(table)
    return table


def state_key(obj) -> tuple:
    """(key, held): what ``obj``'s parameters are now (``mi.traverse``) — each JIT array by
    its variable indices, the others by value — and the JIT arrays themselves, to be kept with
    the key: while they live no other value can take their indices, and writing a parameter
    through ``params`` makes a new variable."""
    params = mi.traverse(obj)
    key, held = [obj.class_name()], []
    for name in params.keys():
        value = params[name]
        value = getattr(value, 'matrix', value)             # transforms: their matrix
        if dr.is_jit_v(type(value)):
            held.append(value)
            key.append((name, tuple(int(v.index) for v in _leaves(value))))
        else:
            key.append((name, repr(value)))
    return tuple(key), held


def _leaves(value):
    """The one-dimensional JIT arrays inside a (nested) Dr.Jit array."""
    if dr.depth_v(type(value)) <= 1:
        return [value]
    return [leaf for entry in value for leaf in _leaves(entry)]
