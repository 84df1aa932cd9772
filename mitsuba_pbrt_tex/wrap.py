"""Wrap modes: map integer texel indices outside ``[0, res)`` back inside (pbrt section 10.4.1).

pbrt and Mitsuba both wrap *integer texel indices per tap* (not the continuous coordinate), so a
bilinear tap straddling the edge reads the texel on the other side (repeat), the edge texel
(clamp), its mirror image (mirror) or zero (black). We do the same for every filter and level.

Modes: ``repeat`` (Euclidean modulo), ``clamp``, ``black`` (zero outside; returned as a validity
mask), ``mirror`` (reflection with the edge texel repeated — Mitsuba's/OpenImageIO's mirror:
…, 1, 0, 0, 1, …, w-1, w-1, w-2, …) and ``octahedralsphere`` (pbrt-v4: crossing the left/right edge
flips y, crossing the top/bottom edge flips x, for octahedral environment maps; indices still
outside after that one reflection are clamped, which pbrt leaves undefined).

The arithmetic is done on float-valued integers (exact below 2^24, guaranteed by the callers'
coordinate clamp) because per-lane integer division does not vectorise on CPUs.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

WRAP_MODES = ('repeat', 'black', 'clamp', 'mirror', 'octahedralsphere')

#: Texel coordinates are clamped to this magnitude before wrapping (keeps every integer exact
#: in float32 and in int32); ``repeat`` and ``mirror`` coordinates beyond it are first taken
#: from the texture coordinate moved by whole periods (:func:`texel_coord`).
COORD_LIMIT = float(2 ** 22)


def _mod(x, n, inv_n=None):
    """Euclidean ``x mod n`` for float-valued integers x and n > 0 (``inv_n`` ≈ 1/n: a
    multiplication instead of a division; the two corrections absorb its rounding)."""
    m = x - dr.floor(x * (dr.rcp(n) if inv_n is None else inv_n)) * n
    m = dr.select(m < 0, m + n, m)
    return dr.select(m >= n, m - n, m)


def wrap_1d(x, n, mode: str, inv_n=None):
    """Wrap float-valued integer ``x`` into ``[0, n)`` for the modes that wrap each axis on its
    own: ``repeat``, ``clamp``, ``mirror``. ``black`` (which also needs a validity mask) and
    ``octahedralsphere`` (which couples the axes) are handled by every caller before it, and
    refused here."""
    if mode == 'repeat':
        return _mod(x, n, inv_n)
    if mode == 'clamp':
        return dr.clip(x, 0, n - 1)
    if mode == 'mirror':
        m = _mod(x, 2 * n, None if inv_n is None else 0.5 * inv_n)
        return dr.select(m >= n, 2 * n - 1 - m, m)
    raise ValueError(mode)


def wrap_2d(x, y, w, h, mode: str, inv_w=None, inv_h=None):
    """Wrap float-valued integer texel coordinates; returns ``(x, y, valid)`` as Int32/Int32/Bool.

    ``valid`` is False only for ``black`` taps outside the image (their value is 0).
    ``inv_w``, ``inv_h``: precomputed reciprocals of the size (optional).
    """
    valid = mi.Bool(True)
    if mode == 'black':
        valid = (x >= 0) & (x < w) & (y >= 0) & (y < h)
        x, y = dr.clip(x, 0, w - 1), dr.clip(y, 0, h - 1)
    elif mode == 'octahedralsphere':
        x, y = octahedral_remap(x, y, w, h, dr.select, dr.clip)
    else:
        x, y = wrap_1d(x, w, mode, inv_w), wrap_1d(y, h, mode, inv_h)
    return mi.Int32(x), mi.Int32(y), valid


def octahedral_remap(x, y, w, h, select, clip):
    """pbrt-v4's ``RemapPixelCoords`` for the octahedral sphere: integer texel coordinates one
    step outside the image folded back across the edge they crossed, then clamped; ``select``
    and ``clip`` are Dr.Jit's (lookups) or numpy's (``np.where``, ``np.clip``: the sampling
    tables), so both use one rule."""
    left, right = x < 0, x >= w
    x = select(left, -x, select(right, 2 * w - 1 - x, x))
    y = select(left | right, h - 1 - y, y)
    top, bottom = y < 0, y >= h
    x = select(top | bottom, w - 1 - x, x)
    y = select(top, -y, select(bottom, 2 * h - 1 - y, y))
    return clip(x, 0, w - 1), clip(y, 0, h - 1)


def adjacent_wrapped(x0, n, mode: str, inv_n=None):
    """Wrapped ``x0`` and ``x0 + 1`` as ((index, valid), (index, valid)) for a separable mode
    (the bilinear taps of one axis; repeat derives the second from the first)."""
    if mode == 'black':
        return tuple((dr.clip(x, 0, n - 1), (x >= 0) & (x < n)) for x in (x0, x0 + 1))
    ok = mi.Bool(True)
    a = wrap_1d(x0, n, mode, inv_n)
    if mode == 'repeat':
        b = dr.select(a + 1 >= n, 0, a + 1)
    else:
        b = wrap_1d(x0 + 1, n, mode, inv_n)
    return (a, ok), (b, ok)


def sanitize_coord(x):
    """NaN/inf → 0, and clamp to ±COORD_LIMIT (texel units)."""
    return dr.clip(dr.select(dr.isfinite(x), x, 0.0), -COORD_LIMIT, COORD_LIMIT)


def texel_coord(st, n, mode: str, offset=0.0):
    """The texel coordinate ``st·n + offset`` of texture coordinate ``st`` (``n`` texels or
    lattice points per unit), sanitized (:func:`sanitize_coord`). Where it lies beyond
    ±COORD_LIMIT, ``repeat`` and ``mirror`` take it from ``st`` moved by whole periods (1, 2)
    first, so that the wrap still tiles there: the clamp alone sent every lookup beyond it to
    the same texel (a 64-texel-wide image at u = 65536 + …; found in a user trial). Within the
    limit the coordinate is the product itself, rounded as Mitsuba's ``bitmap`` rounds it."""
    x = dr.fma(st, n, offset)
    if mode in PERIODIC:
        x = dr.select(dr.abs(x) > COORD_LIMIT, dr.fma(first_period(st, mode), n, offset), x)
    return sanitize_coord(x)


#: The modes under which the texture repeats, with their periods in texture coordinates.
PERIODIC = {'repeat': 1.0, 'mirror': 2.0}


def first_period(st, mode: str):
    """Texture coordinate ``st`` moved by whole periods of ``mode`` (one of :data:`PERIODIC`)
    into ``[0, period]`` (exact: the period is a power of two; a tiny negative ``st`` rounds to
    the period itself, the same place once wrapped)."""
    period = PERIODIC[mode]
    return st - dr.floor(st * (1.0 / period)) * period
