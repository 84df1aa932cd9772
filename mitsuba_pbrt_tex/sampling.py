"""Importance sampling of positions in proportion to an image texture's value.

An area emitter whose radiance varies over its surface asks its texture for ``sample_position``
(a uv point and its density) and ``pdf_position``; a projector asks for the same to pick a film
position. Mitsuba's ``bitmap`` samples a texel in proportion to its luminance and then a tent (or a
uniform offset for ``nearest``) around it; here the density is built so that it is *exactly*
proportional to what :class:`~mitsuba_pbrt_tex.filters.TextureFilter` returns with a zero
footprint — the value the emitter evaluates — for every filter and wrap mode:

* ``point``: the texels' weights, piecewise constant over the texels;
* ``bilinear``, ``trilinear``, ``ewa`` (all a bilinear lookup at level 0 without a footprint): the
  bilinear interpolant of the texel weights, *with the wrap mode's neighbours at the edges*. The
  unit square is cut at the texel centres into (W+1)×(H+1) cells (half cells along the edges); on
  each cell the interpolant is bilinear in the values at the cell's corners, so a cell is chosen
  in proportion to its integral and a point inside it by Mitsuba's ``warp.square_to_bilinear``.
  Along the edges the corner values are the lookup's own mix of the edge texel and its wrapped
  neighbour (the other side for ``repeat``, nothing for ``black``, the flipped row for
  ``octahedralsphere``), so no part of the emitter where the lookup is non-zero gets density 0.

A texel's weight is the luminance of the absolute value (RGB) or the absolute value (1 channel) of
``scale`` · texel, or of ``max(0, 1 - scale · texel)`` with ``invert``. With ``invert`` the density
is proportional to the bilinear interpolant of the inverted texels, which is ≥ the inverted
interpolant (so it is positive wherever the texture is), and equal to it away from texels that
the clamp at 0 cuts.

The texture's uv mapping carries the density from texture space (s, t) to the surface's (u, v):
exact when each of s, t is ``±m·(u or v) + offset`` with an integer m, for ``repeat`` (m periods,
any offset) and ``mirror`` (integer offset), and for the other wraps when the unit square maps
onto itself (m = 1: flips, transposes, 90° rotations — the rule of Mitsuba's ``bitmap`` after
v3.9.1, which ignores ``to_uv`` when sampling in v3.9.1 itself). Any other mapping (a non-integer
scale, a rotation by another angle, the spherical/cylindrical/planar mappings) has no per-texel
surface density: positions are then sampled uniformly in uv (unbiased, not importance-sampled)
and a warning says so.

Densities are per unit uv area and 0 outside ``[0, 1]²`` (no sample lands there). The tables are
built on the CPU with numpy from the texels (``TensorXf.numpy()``: the data is already evaluated,
so this is allowed while Mitsuba traces a kernel) the first time an emitter asks.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from .mipmap import MIPMap, Pyramid
from .wrap import octahedral_remap

LUMINANCE = np.array([0.212671, 0.715160, 0.072169])


# ------------------------------------------------------------------------------ texel weights
def texel_weights(texels: np.ndarray, scale: float, invert: bool) -> np.ndarray:
    """(H, W) non-negative float32 sampling weights of an (H, W, C) array of texels."""
    v = np.asarray(texels, np.float32)
    if scale != 1.0 or invert:
        v = v * np.float32(scale)
    if invert:
        v = np.maximum(np.float32(0), np.float32(1) - v)
    v = np.abs(v)
    w = v @ LUMINANCE.astype(np.float32) if v.shape[2] == 3 else v[..., 0]
    return np.where(np.isfinite(w), w, np.float32(0))


def _wrap_np(x, y, w, h, mode):
    """numpy twin of :func:`mitsuba_pbrt_tex.wrap.wrap_2d` (integer indices → index, valid).

    A twin, not a call: the tables are built the first time an emitter asks, which may be while
    Mitsuba traces a kernel, where no new Dr.Jit computation can be evaluated (reading the
    already evaluated texels is allowed). ``tests/test_dropin.py`` checks the resulting density
    against the lookups for every wrap mode."""
    valid = np.ones(np.broadcast(x, y).shape, bool)
    x, y = np.broadcast_to(x, valid.shape).copy(), np.broadcast_to(y, valid.shape).copy()
    if mode == 'repeat':
        x, y = np.mod(x, w), np.mod(y, h)
    elif mode in ('clamp', 'black'):
        if mode == 'black':
            valid = (x >= 0) & (x < w) & (y >= 0) & (y < h)
        x, y = np.clip(x, 0, w - 1), np.clip(y, 0, h - 1)
    elif mode == 'mirror':
        x, y = np.mod(x, 2 * w), np.mod(y, 2 * h)
        x, y = np.where(x >= w, 2 * w - 1 - x, x), np.where(y >= h, 2 * h - 1 - y, y)
    elif mode == 'octahedralsphere':
        x, y = octahedral_remap(x, y, w, h, np.where, np.clip)
    else:
        raise ValueError(mode)
    return x, y, valid


def corner_values(weights: np.ndarray, wrap: str) -> np.ndarray:
    """The bilinear lookup of ``weights`` (with ``wrap`` at the edges) at the corners of the
    sampling cells: texel-unit positions 0, 0.5, 1.5, ..., W - 0.5, W (and the same in y).

    At a texel centre the lookup is the texel; on an edge it is the mean of the edge texel and
    its wrapped neighbour (in both axes at a corner). So: pad the texels by their one-texel wrapped
    ring, and average neighbouring pairs at the edges. Shape (H + 2, W + 2).
    """
    h, w = weights.shape
    padded = np.empty((h + 2, w + 2), np.float32)
    padded[1:-1, 1:-1] = weights
    # the ring: rows -1 and H (all columns, corners included), columns -1 and W
    xs, ys = np.arange(-1, w + 1), np.arange(-1, h + 1)
    for rows, cols, sl in (([-1], xs, np.s_[:1, :]), ([h], xs, np.s_[-1:, :]),
                           (ys[1:-1], [-1], np.s_[1:-1, :1]), (ys[1:-1], [w], np.s_[1:-1, -1:])):
        ix, iy, ok = _wrap_np(np.asarray(cols)[None, :], np.asarray(rows)[:, None], w, h, wrap)
        padded[sl] = np.where(ok, weights[iy, ix], np.float32(0))
    cols = np.concatenate([0.5 * (padded[:, :1] + padded[:, 1:2]), padded[:, 1:-1],
                           0.5 * (padded[:, -2:-1] + padded[:, -1:])], 1)
    return np.concatenate([0.5 * (cols[:1] + cols[1:2]), cols[1:-1],
                           0.5 * (cols[-2:-1] + cols[-1:])], 0)


# ------------------------------------------------------------------------------ texture space
class TextureSpaceSampler:
    """Samples (s, t) ∈ [0, 1]² with density ∝ the zero-footprint lookup of texel weights."""

    def __init__(self, weights: np.ndarray, nearest: bool, wrap: str):
        h, w = weights.shape
        self.w, self.h, self.nearest = w, h, nearest
        if nearest:
            cells = weights
        else:
            # corners at the texel centres, plus the edges: 0, 0.5, 1.5, ..., W - 0.5, W
            xs = np.concatenate([[0.0], np.arange(w) + 0.5, [float(w)]]).astype(np.float32)
            ys = np.concatenate([[0.0], np.arange(h) + 0.5, [float(h)]]).astype(np.float32)
            corners = corner_values(weights, wrap)
            area = np.diff(ys)[:, None] * np.diff(xs)[None, :]
            cells = area * 0.25 * (corners[:-1, :-1] + corners[:-1, 1:] + corners[1:, :-1]
                                   + corners[1:, 1:])
            self.corners = mi.Float(corners.ravel().astype(np.float32))
        total = float(cells.sum(dtype=np.float64))
        self.uniform = not (total > 0 and math.isfinite(total))
        if self.uniform:
            return
        # density per unit (s, t) area = value · W · H / (sum of the cells' integrals in texels)
        self.norm = w * h / total
        self.distr = mi.DiscreteDistribution2D(np.ascontiguousarray(cells, np.float32))
        # the weights as a 1-channel image, read by the image lookups' own code (pdf)
        flat = mi.Float(np.ascontiguousarray(weights, np.float32).ravel())
        self.weights = MIPMap(Pyramid(flat, w, h, 1), wrap)

    def sample(self, sample: mi.Point2f, active) -> tuple[mi.Point2f, mi.Float]:
        if self.uniform:
            return mi.Point2f(sample), dr.full(mi.Float, 1.0, dr.width(sample))
        idx, _, rem = self.distr.sample(sample, active)
        w, h = self.w, self.h
        if self.nearest:
            st = mi.Point2f(_inside_texel(idx.x, rem.x, w), _inside_texel(idx.y, rem.y, h))
            return st, self.pdf(st, active)
        a, b = mi.Float(idx.x), mi.Float(idx.y)
        c00, c10, c01, c11 = self._corner_values(idx.x, idx.y, active)
        p, _ = mi.warp.square_to_bilinear(c00, c10, c01, c11, rem)
        x0, x1 = dr.maximum(a - 0.5, 0.0), dr.minimum(a + 0.5, w)
        y0, y1 = dr.maximum(b - 0.5, 0.0), dr.minimum(b + 0.5, h)
        st = mi.Point2f(dr.fma(p.x, x1 - x0, x0) / w, dr.fma(p.y, y1 - y0, y0) / h)
        st = dr.clip(st, 0.0, 1.0)
        value = dr.lerp(dr.lerp(c00, c10, p.x), dr.lerp(c01, c11, p.x), p.y)
        return st, value * self.norm

    def _corner_values(self, a, b, active):
        stride = self.w + 2
        base = b * stride + a
        return (dr.gather(mi.Float, self.corners, base, active),
                dr.gather(mi.Float, self.corners, base + 1, active),
                dr.gather(mi.Float, self.corners, base + stride, active),
                dr.gather(mi.Float, self.corners, base + stride + 1, active))

    def pdf(self, st: mi.Point2f, active) -> mi.Float:
        """Density at texture coordinates ``(s, t)`` (any range: wrapped as lookups wrap them):
        the texel weights looked up at level 0 by the image's own code — point or bilinear, as
        a zero-footprint lookup of the texture reads its texels — so that a value and its
        density are read at the same texel position to the last bit (with the positions
        wrapped here first, mirror's rounding differed from the lookup's by up to ~5e-4 texel,
        and next to a black texel's corner the weights of a sparse light spread by ±4%)."""
        if self.uniform:
            return dr.full(mi.Float, 1.0, dr.width(st))
        lookup = self.weights.point if self.nearest else self.weights.bilinear
        return lookup(0, st, active) * self.norm


def _inside_texel(i, frac, n: int) -> mi.Float:
    """(i + frac) / n, nudged by an ulp where float32 rounding would put it in the next or
    previous texel (frac = 1 exactly, or large i): pdf() must find texel i there again."""
    fi = mi.Float(i)
    x = (fi + frac) / n
    bits = dr.reinterpret_array(mi.UInt32, x)
    for _ in range(2):
        cell = dr.floor(x * n)
        x = dr.select(cell > fi, dr.reinterpret_array(mi.Float, bits - 1),
                      dr.select((cell < fi) & (x >= 0), dr.reinterpret_array(mi.Float, bits + 1), x))
        bits = dr.reinterpret_array(mi.UInt32, x)
    return x


# ------------------------------------------------------------------------------ uv ↔ (s, t)
class _Axis:
    """One texture axis r: coordinate = a·uv[col] + b, the image of [0, 1] covering m units."""

    def __init__(self, col: int, a: float, b: float, m: int, wrap: str):
        self.col, self.a, self.b, self.m, self.wrap = col, a, b, m, wrap
        self.lo = min(b, b + a)                 # texture-space start of the surface's [0, 1]
        if wrap != 'repeat':
            self.lo = float(round(self.lo))     # integer here (checked by uv_axes)


def _near_int(x: float, tol: float = 1e-5) -> bool:
    return abs(x - round(x)) <= tol * max(1.0, abs(x))


def uv_axes(mapping, wrap: str) -> tuple[list[_Axis] | None, str]:
    """The per-axis description of a uv mapping that admits exact sampling, or (None, why)."""
    a, b = getattr(mapping, 'a', None), getattr(mapping, 'b', None)
    if getattr(mapping, 'name', None) != 'uv' or a is None:
        return None, f'mapping "{getattr(mapping, "name", "?")}" (accepted: uv)'
    axes = []
    for r in range(2):
        # (the mapping has set the rounding of rotations by 90° to 0: mapping.ROUNDING)
        cols = [c for c in range(2) if a[r][c] != 0]
        if len(cols) != 1:
            return None, ('a uv transform that mixes u and v (accepted: scales, flips, transposes '
                          'and 90° rotations)')
        col = cols[0]
        m = abs(a[r][col])
        if not (_near_int(m) and round(m) >= 1):
            return None, (f'a scale of {m:g} along {"st"[r]} (accepted: an integer number of '
                          'repetitions)')
        m = int(round(m))
        lo = min(b[r], b[r] + a[r][col])
        if wrap == 'repeat':
            pass
        elif wrap == 'mirror' and _near_int(lo):
            pass
        elif m != 1 or abs(lo) > 1e-5:
            return None, (f'wrap "{wrap}" with the surface\'s [0, 1] mapped to [{lo:g}, '
                          f'{lo + m:g}] along {"st"[r]} (accepted with this wrap: onto [0, 1]'
                          + (', or integer bounds for mirror' if wrap == 'mirror' else '')
                          + '; wrap repeat accepts any integer number of periods)')
        axes.append(_Axis(col, float(a[r][col]), float(b[r]), m, wrap))
    if axes[0].col == axes[1].col:
        return None, 'a uv transform that maps u and v onto one axis'
    return axes, ''


class PositionSampler:
    """Surface-uv sampling for one texture: texture-space sampler + the uv mapping.

    The density returned with a sample is :meth:`pdf` at the returned uv — what
    ``pdf_position`` gives there and what the emitter's value there is divided by — not the
    texture-space sampler's density at the point it drew: mapping that point to uv and back
    moves it by a few ulps, and next to a texel corner of weight 0, where the density vanishes
    quadratically, the two differed without bound (a tiled mask light: density 6e-18 returned
    for a uv where the value is 2.6e-5, one light-traced sample weighted 4e12)."""

    def __init__(self, tex_sampler: TextureSpaceSampler | None, axes: list[_Axis] | None):
        self.tex = tex_sampler
        self.axes = axes            # None: uniform in uv

    def sample(self, sample: mi.Point2f, active) -> tuple[mi.Point2f, mi.Float]:
        if self.axes is None:
            return mi.Point2f(sample), dr.full(mi.Float, 1.0, dr.width(sample))
        # pick which repetition (per axis) first, then rescale that sample dimension
        comps = [mi.Float(sample.x), mi.Float(sample.y)]
        tiles = []
        for r, ax in enumerate(self.axes):
            if ax.m > 1:
                scaled = comps[r] * ax.m
                k = dr.clip(dr.floor(scaled), 0, ax.m - 1)
                comps[r] = dr.clip(scaled - k, 0.0, 1.0 - 2 ** -24)
                tiles.append(k)
            else:
                tiles.append(mi.Float(0))
        st, _ = self.tex.sample(mi.Point2f(comps[0], comps[1]), active)
        uv = [None, None]
        for r, ax in enumerate(self.axes):
            s0 = st.x if r == 0 else st.y
            origin = ax.lo + tiles[r]
            if ax.wrap == 'repeat':
                d = s0 - origin
                s = origin + (d - dr.floor(d))
            elif ax.wrap == 'mirror':
                odd = (origin - 2.0 * dr.floor(origin * 0.5)) > 0.5     # mirrored unit
                s = origin + dr.select(odd, 1.0 - s0, s0)
            else:
                s = s0
            uv[ax.col] = dr.clip((s - ax.b) / ax.a, 0.0, 1.0)
        uv = mi.Point2f(uv[0], uv[1])
        return uv, self.pdf(uv, active)

    def pdf(self, uv: mi.Point2f, active) -> mi.Float:
        inside = (uv.x >= 0) & (uv.x <= 1) & (uv.y >= 0) & (uv.y <= 1)
        if self.axes is None:
            return dr.select(inside, 1.0, 0.0)
        # (s, t) as the uv mapping computes it (its matrix has one non-zero entry per row)
        st = [dr.fma(ax.a, uv.x if ax.col == 0 else uv.y, ax.b) for ax in self.axes]
        value = self.tex.pdf(mi.Point2f(st[0], st[1]), active & inside)
        return dr.select(inside, value, 0.0)
