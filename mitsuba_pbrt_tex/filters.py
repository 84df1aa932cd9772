"""The four image filters behind one call: ``TextureFilter(pyramid, tc, active) -> value``.

Each filter reads a :class:`~mitsuba_pbrt_tex.mapping.TexCoord2D` (st and its four derivatives)
and returns a Float (1-channel image) or Color3f (RGB image):

* ``point``/``bilinear`` — one level, chosen by the isotropic footprint width
  (:func:`~mitsuba_pbrt_tex.mipmap.footprint_width`); level 0 when the pyramid holds level 0
  alone (see ``pbrt_imagemap``: the other levels of these two filters are built on request);
* ``trilinear`` — two levels blended;
* ``ewa`` — :class:`~mitsuba_pbrt_tex.ewa.EWAFilter`;
* ``box`` — :func:`~mitsuba_pbrt_tex.box.box`, the exact average over the footprint, which reads
  the pyramid through :func:`~mitsuba_pbrt_tex.box.build_box_tables` (its buffer's AD aliases,
  made by the caller outside any symbolic scope and passed as ``tables``).

:meth:`TextureFilter.gradient` gives d(value)/d(s, t) of the bilinear reconstruction at the level
the footprint selects (blended between two levels like trilinear for ``trilinear`` and ``ewa``;
zero for ``point``, as Mitsuba's ``bitmap`` with ``nearest``; ``box`` as ``trilinear``) — what
``eval_1_grad`` needs.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .box import box
from .ewa import EWAFilter
from .mipmap import MIPMap, Pyramid, footprint_width


class TextureFilter:
    """One filter's options (pbrt's ``MIPMapFilterOptions`` plus the wrap mode); calls are pure
    functions of the pyramid they are given, like pbrt's ``MIPMap::Filter``."""

    def __init__(self, kind: str, wrap: str, max_anisotropy: float, width_convention: float,
                 reorder: bool = True):
        self.kind = kind
        self.wrap = wrap
        self.width_convention = width_convention
        self.ewa = EWAFilter(max_anisotropy, reorder) if kind == 'ewa' else None

    def __call__(self, pyramid: Pyramid, tc, active, tables=None):
        """The filtered value at ``tc``: Float (1 channel) or Color3f (RGB). Gradients reach
        ``pyramid.buffer`` (and through it the texels it was built from) and ``tc.st``.
        ``tables``: what the filter's loops read — the pyramid's
        :class:`~mitsuba_pbrt_tex.box.BoxTables` (``box``, required) or
        :class:`~mitsuba_pbrt_tex.ewa.EWABuffers` (``ewa``, for forward-mode derivatives)."""
        mip = MIPMap(pyramid, self.wrap)
        if self.kind == 'box':
            if tables is None or tables.wrap != self.wrap:
                raise ValueError('the box filter needs the prefix tables of the pyramid for '
                                 'its wrap mode (mitsuba_pbrt_tex.box.build_box_tables)')
            return box(mip, tables, tc.st, mi.Vector2f(tc.dsdx, tc.dtdx),
                       mi.Vector2f(tc.dsdy, tc.dtdy), active)
        if self.kind == 'ewa':
            return self.ewa(mip, tc.st, mi.Vector2f(tc.dsdx, tc.dtdx),
                            mi.Vector2f(tc.dsdy, tc.dtdy), active, tables)
        width = footprint_width(tc, self.width_convention)
        if self.kind == 'trilinear':
            return mip.trilinear(tc.st, width, active)
        return mip.filter_single_level(self.kind, tc.st, width, active)

    def gradient(self, pyramid: Pyramid, tc, active, per_channel: bool = False):
        """(value, d value/ds, d value/dt) of the luminance (or single channel); with
        ``per_channel``, of each channel (Color3f for RGB)."""
        mip = MIPMap(pyramid, self.wrap)
        if self.kind == 'point':
            v = mip.filter_single_level('point', tc.st, footprint_width(tc, 1.0), active)
            v = v if per_channel else _lum(v)
            return v, dr.zeros(type(v)), dr.zeros(type(v))
        if not mip.has_pyramid:
            return mip.bilinear_gradient(0, tc.st, active, per_channel)
        last = len(mip.sizes) - 1
        level = dr.clip(mip.level_of(footprint_width(tc, self.width_convention)), 0, last)
        l0 = dr.floor(level)
        il0 = mi.UInt32(l0)
        g0 = mip.bilinear_gradient(il0, tc.st, active, per_channel)
        if self.kind == 'bilinear':
            return g0
        frac = level - l0
        g1 = mip.bilinear_gradient(dr.minimum(il0 + 1, last), tc.st, active & (frac > 0),
                                   per_channel)
        return tuple(dr.lerp(a, b, frac) for a, b in zip(g0, g1))


def _lum(v):
    return mi.luminance(v) if isinstance(v, mi.Color3f) else v
