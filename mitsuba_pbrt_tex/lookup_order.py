"""Batched lookups in memory order: evaluate a batch sorted by texture tile, return it unsorted.

An EWA lookup reads ~90 texels on ~40 cache lines (8:1 footprints, ``bench lookups``). When the
lookups of a batch land at random places of a large level, nearly every one of those lines comes
from DRAM and the filter waits on memory (3–4× slower than on a level that stays in cache, at
the same number of texels). Sorting the batch by the texture tile its centre falls in, filtering
in that order and putting the results back in the caller's order makes neighbouring lanes read
neighbouring texels — the lines are then mostly cache hits — and gives bit-identical results
(each lane's arithmetic does not depend on the others). Measured at random uv on a 1024² RGB
texture: EWA 2.5–3.5× faster including the sort; at coherent uv it is skipped (see below).

It is only possible where a batch exists as evaluated arrays — a call such as ``tex.eval(si)``
from Python, or Mitsuba's wavefront mode — not inside a symbolic loop or call (a render's
megakernel, whose lanes cannot be permuted mid-kernel), in a frozen function, or where
synchronisation is forbidden: there the lookups run in the order given. It also needs a batch
large enough to pay for the sort (:data:`MIN_BATCH`) with enough lookups on levels too large to
stay in cache (:data:`MIN_LEVEL_BYTES`, :data:`MIN_WORTH_FRACTION`), and is skipped when the
batch is already coherent: when at least half of the lanes fall in the same tile as the lane
before them (a raster of a render, for example). Finding out costs one small reduction.

Gradients pass through: the permutation is a gather (its adjoint a scatter-add), its inverse
another gather.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

#: Tiles of this many level-0 texels per side: a tile's lines of the two levels an EWA lookup
#: blends (~24 KB of RGBA float32 texels) stay in a core's L2 cache while its lookups run.
TILE_TEXELS = 32
#: Smaller batches are filtered as given (sorting them would cost more than it saves).
MIN_BATCH = 1 << 14
#: Levels smaller than this stay in cache whatever the order (measured on a 2-core EPYC with
#: 32 MB of L3: EWA on levels 1–2 of a 1024² RGB texture, 5 MB, ran as fast unsorted as sorted;
#: on levels 0–1, 20 MB, 3× slower), so lookups there need no sorting.
MIN_LEVEL_BYTES = 8 << 20
#: Sort only when at least this fraction of the batch reads such a large level ...
MIN_WORTH_FRACTION = 0.25
#: ... and fewer than this fraction of lanes share the previous lane's tile (else: coherent).
COHERENT_FRACTION = 0.5


def can_reorder(width: int) -> bool:
    """Is a batch of ``width`` lanes evaluated here as a whole, and large enough?"""
    return (width >= MIN_BATCH and not dr.flag(dr.JitFlag.SymbolicScope)
            and not dr.flag(dr.JitFlag.FreezingScope)
            and not dr.flag(dr.JitFlag.ForbidSynchronization))


def tile_key(st, width: int, height: int) -> mi.UInt32:
    """Index of the ``TILE_TEXELS``² tile of a ``width``×``height`` level that ``st`` falls in,
    after a repeat wrap (only the order depends on it, so any wrap mode may share it; non-finite
    coordinates go to tile 0)."""
    tiles_x = max(1, -(-width // TILE_TEXELS))
    tiles_y = max(1, -(-height // TILE_TEXELS))

    def tile(x, n):
        x = dr.select(dr.isfinite(x), x, 0.0)
        return dr.minimum(mi.UInt32((x - dr.floor(x)) * n), n - 1)

    return tile(st.y, tiles_y) * tiles_x + tile(st.x, tiles_x)


def worth_sorting(key: mi.UInt32, worth: mi.Bool | None = None) -> bool:
    """Is the batch incoherent (fewer than ``COHERENT_FRACTION`` of the lanes share the previous
    lane's tile) with at least ``MIN_WORTH_FRACTION`` of its lanes marked ``worth`` (lanes whose
    lookups read memory that order helps with; all when None)? One reduction kernel."""
    n = dr.width(key)
    prev = dr.gather(mi.UInt32, key, dr.maximum(dr.arange(mi.UInt32, n), 1) - 1)
    same = dr.count(key == prev)
    counts = [same] if worth is None else [same, dr.count(worth & dr.full(mi.Bool, True, n))]
    dr.eval(counts)
    if int(counts[0][0]) >= COHERENT_FRACTION * n:
        return False
    return worth is None or int(counts[1][0]) >= MIN_WORTH_FRACTION * n


def in_tile_order(fn, st, *args, width: int, height: int, worth=None):
    """``fn(st, *args)`` over the batch, evaluated in tile order where that pays (see the module
    docstring and :func:`worth_sorting`; ``worth``: None or a function returning the lanes that
    count, called only where the batch can be reordered); the result is in the caller's lane
    order either way. ``args`` may hold arrays of the batch's width or of width 1 (broadcast,
    left as they are)."""
    n = dr.width(st)
    if not can_reorder(n):
        return fn(st, *args)
    key = tile_key(st, width, height)
    if not worth_sorting(key, None if worth is None else worth()):
        return fn(st, *args)
    perm = dr.argsort(key)
    inverse = dr.empty(mi.UInt32, n)
    dr.scatter(inverse, dr.arange(mi.UInt32, n), perm)

    def permuted(x):
        return x if dr.width(x) == 1 else dr.gather(type(x), x, perm)

    # Evaluated explicitly, each in one kernel: gathering the channels of a lazy colour one by
    # one would evaluate them one by one — the whole filter once per channel (measured: 3
    # kernel launches, no faster than unsorted); the permuted inputs likewise in one pass.
    inputs = (permuted(st), *(permuted(a) for a in args))
    dr.eval(inputs)
    out = fn(*inputs)
    dr.eval(out)
    return dr.gather(type(out), out, inverse)
