"""One ``pbrt_path`` render as one value: the hand-off between the integrator and the textures.

A render of ``pbrt_path`` needs a few things that live exactly as long as the render: the sensor
(for the camera approximation and for pixel footprints), with ``footprint="pixel"`` and a
Gaussian film the render's shared sample offsets (:class:`~mitsuba_pbrt_tex.film_view.
FilterPixels`), the film positions of the camera samples, and — after the first hits — the
position each sample counts at. :class:`RenderScope` holds them; nothing else of a render is
kept.

Who makes and reads it:

* ``pbrt_path.render``/``render_forward``/``render_backward`` create it where the render starts
  and hand Mitsuba's ``render`` methods the sensor view that carries it
  (``pbrt_path``'s ``begin``); ``sample_rays`` fills in the camera samples'
  positions. Mitsuba then calls ``sample()`` without the sensor, so ``sample_rays`` leaves the
  scope in the integrator's one hand-over attribute, which ``sample()`` reads and passes
  explicitly to ``trace``;
* ``trace`` returns the pixel each camera hit decoded to (Gaussian film), and ``sample()``
  records it as :attr:`RenderScope.counted`; the film view's image blocks splat each sample
  there (:class:`~mitsuba_pbrt_tex.film_view.CountingBlock`) — Mitsuba's own positions are never
  written to;
* textures read the scope through :func:`published`: a texture sees only the
  ``SurfaceInteraction3f`` its BSDF passes on, and a symbolic BSDF call admits no per-lane input
  besides its arguments, so while ``sample()`` traces (or, in wavefront mode, runs) its path loop
  the scope is published on the thread, and opting-in textures (:mod:`mitsuba_pbrt_tex.pixel`)
  read the sensor and the offsets from it;
* while ``pbrt_path`` traces the extra paths of pixels that cross a silhouette
  (:mod:`mitsuba_pbrt_tex.silhouettes`), :func:`silhouette_paths` says so on the thread:
  textures whose exact filter would repeat one pixel's walk for each of those paths read a
  cheaper filter over the same footprint there;
* while ``pbrt_path`` asks one BSDF instance for its value towards the emitter sample and for a
  sampled direction (both read the hit's textures), :func:`shared_lookups` lets a texture asked
  twice at the same interaction compute its value once (:meth:`~mitsuba_pbrt_tex.texture.
  PbrtTexture.eval`).
"""

from __future__ import annotations

import contextlib
import threading
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

_STATE = threading.local()


@dataclass
class RenderScope:
    """One render (see the module docstring)."""

    #: the scene's sensor (never the film view Mitsuba's ``render`` is given)
    sensor: object
    #: ``footprint="pixel"`` with a Gaussian film: the render's FilterPixels; else None
    pixels: object = None
    #: the camera samples' film positions (``sample_rays``): the sample's pixel (box film)
    #: or the pixel centre it was drawn for (Gaussian film)
    positions: object = None
    #: Gaussian film: where each sample counts — the pixel its first hit decoded to
    counted: object = None
    #: the JIT variables of the camera rays ``sample_rays`` returned: ``sample()`` given those
    #: rays knows them for its own (one pixel wide, this render's)
    rays: tuple = ()

    def count_at_decoded(self, pixel, ok):
        """Record ``pixel`` (crop coordinates; ``ok`` per lane) as where each sample counts —
        the pixel its textures centred on; lanes not ``ok`` count where they were drawn."""
        self.counted = mi.Vector2f(dr.select(ok, mi.Vector2f(pixel) + self.pixels.offset + 0.5,
                                             mi.Vector2f(self.positions)))


@contextlib.contextmanager
def _on_thread(name: str, value):
    """``value`` as this thread's ``name`` within the block, the previous one after it."""
    previous = getattr(_STATE, name, None)
    setattr(_STATE, name, value)
    try:
        yield
    finally:
        setattr(_STATE, name, previous)


def published(scope: RenderScope | None):
    """Within this block (on this thread), opting-in textures centre camera hits on the pixels
    of ``scope`` (None: nothing published, every texture keeps the sample's footprint)."""
    return _on_thread('scope', scope)


def unpublished():
    """Within this block (on this thread) no render is published: every texture keeps the
    sample's footprint — a texture read without one (a normal map, :meth:`~mitsuba_pbrt_tex.
    texture.PbrtTexture.read_without_footprint`), and the textures inside one that multiplies
    spatially varying values (:meth:`~mitsuba_pbrt_tex.texture.PbrtTexture.multiplies_varying`)."""
    return _on_thread('scope', None)


def current() -> RenderScope | None:
    """The published scope, or None (no ``pbrt_path`` render with pixel footprints)."""
    return getattr(_STATE, 'scope', None)


def silhouette_paths():
    """Within this block (on this thread) the paths traced are the extra paths through pixels
    that cross a silhouette."""
    return _on_thread('silhouette', True)


def in_silhouette_paths() -> bool:
    """Whether the paths being traced are silhouette paths (:func:`silhouette_paths`)."""
    return bool(getattr(_STATE, 'silhouette', False))


def shared_lookups():
    """Within this block (on this thread) a texture asked again at an interaction it was asked
    at before in the block reuses its first value on that query's lanes (see
    :meth:`~mitsuba_pbrt_tex.texture.PbrtTexture.eval`). The block must hold one recording:
    ``pbrt_path`` wraps the two queries of one BSDF instance in it, inside ``dr.dispatch``, so
    no value crosses from one instance's symbolic call to another's."""
    return _on_thread('lookups', {})


def lookups() -> dict | None:
    """The :func:`shared_lookups` table of this thread, or None outside one."""
    return getattr(_STATE, 'lookups', None)


def unshared():
    """Within this block no lookup is shared (a query's own remaining lanes)."""
    return _on_thread('lookups', None)
