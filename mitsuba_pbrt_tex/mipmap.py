"""MIP maps (pbrt section 10.4.3): the pyramid, texel fetches, point/bilinear/trilinear filters.

Storage: the pyramid is one value
---------------------------------
:func:`build_pyramid` is a pure function of the texels (the user's ``data`` tensor, float32,
shape (H, W, C)): it returns a :class:`Pyramid` whose levels lie back to back in *one* flat float32
buffer — level 0 first, RGBA-padded for RGB images (Dr.Jit gathers a texel of 4 floats as one
packet load, 3 floats as three gathers: 1.7× faster bilinear lookups, measured by ``bench
lookups``; Mitsuba's ``bitmap`` pads too), then levels 1, 2, … box-filtered from it with Dr.Jit
operations, so gradients reach the base texels through every level. A texture that only ever
reads level 0 (point and bilinear under Mitsuba's integrators, which give a zero footprint) asks
for level 0 alone and never pays for the others. Nothing in a pyramid changes after it is built:
a texture whose texels change builds a new one (``parameters_changed``), and a lookup is a pure
function of (pyramid, wrap mode, coordinates) — :class:`MIPMap` is that pair, made per lookup.

So gradients have one path: from a lookup to the buffer, from the buffer to the tensor it was
built from. A pyramid built while gradients are enabled on the tensor stays in its AD graph (also
when it is built lazily during a render, see ``pbrt_imagemap``). The pyramid is a Dr.Jit struct
(``DRJIT_STRUCT``): frozen functions (``dr.freeze``) see its buffer as an input, so a frozen
render replays with the current texels; its build launches no host → device copy, so a rebuild can
be recorded too.

Memory: the buffer is at most 4/3 of its base level (RGBA for RGB); with the tensor, an RGB
texture takes 1 + 4/3·4/3 ≈ 2.8× the tensor's memory with all levels, 1 + 4/3 ≈ 2.3× with level 0
alone (Mitsuba's ``bitmap``: 2.3×, without a pyramid); a 1-channel texture 1 + 4/3 ≈ 2.3×, and
2× with level 0 alone. The copy into the buffer also replaces non-finite texels by 0 and clamps
the others to ±``TEXEL_LIMIT``, whatever the tensor holds (also after ``params.update()``).

Non-power-of-two images
-----------------------
pbrt resamples such images up to the next power of two with a Lanczos (windowed sinc) filter
before building a 2×2 box pyramid. We instead build the pyramid directly: level ``l+1`` has
``max(1, floor(n/2))`` texels per axis and each of its texels is the exact *area average* of the
level-``l`` texels it covers (a 2-tap box for even sizes, a 3- or 4-tap box with fractional
weights for odd sizes). Reasons, measured by ``python -m mitsuba_pbrt_tex bench pyramid``
(report: ``mitsuba_pbrt_tex/bench/report/pyramid.md``): the base level stays the original image (bilinear lookups match
``bitmap`` exactly, while pbrt's resampled level 0 does not); memory stays ≤ 4/3 of the base
instead of up to 4 × 4/3 (513×513 → 1024×1024); the resampling's ringing (negative lobes, clamped
at 0 by pbrt) is absent; and the filtered-lookup error against a box-filtered reference is not
larger. The mean of every level equals the image mean.

Level selection
---------------
A filter width ``w`` (in [0,1] texture units) selects level ``log2(w · max(W, H))``: level 0 when
the footprint is one base texel. For power-of-two images this is pbrt's ``L - 1 + log2(w)``.
Point and bilinear lookups need only its integer part, which is the float's exponent (exact);
trilinear and EWA blend levels and evaluate the logarithm (:func:`log2_positive`).

Filters here (EWA lives in :mod:`mitsuba_pbrt_tex.ewa`):

* ``point`` — the texel containing (s, t) at the selected level: ``floor(s·w_l)``, Mitsuba's
  ``nearest`` rule (pbrt-v4 rounds ``s·w - 0.5``; the two differ only exactly on texel edges).
* ``bilinear`` — bilinear interpolation at the selected level (pbrt-v4), texel centres at
  ``(i + 0.5)/w``, with Dr.Jit's operation order so level 0 matches ``bitmap`` bit for bit.
* ``trilinear`` — linear blend of bilinear lookups at the two levels around the selected one.
  *Fix of pbrt-v4*: pbrt-v4 returns level 0 unblended for every level < 1 (a jump at level 1); we
  blend between levels 0 and 1 like pbrt-v3.

Footprint width (``trilinearwidth``): pbrt-v3 uses ``w = max(|ds/dx|, |dt/dx|, |ds/dy|, |dt/dy|)``
(after PR #275), pbrt-v4 twice that. The default is chosen by measured error (the
*trilinear-width* scene of ``bench render``, ``mitsuba_pbrt_tex/bench/report/results.md``); both
are available.
"""

from __future__ import annotations

import math
import threading

import drjit as dr
import mitsuba as mi
import numpy as np

from .wrap import adjacent_wrapped, texel_coord, wrap_2d

FILTERS = ('point', 'bilinear', 'trilinear', 'ewa', 'box')
#: Texel values are limited to ±TEXEL_LIMIT: a filter's weighted sums of values near float32's
#: maximum (3.4e38) overflow to inf (odd-sized pyramid levels, luminance, blends of levels),
#: while every weighted average of values within ±1e38 stays finite.
TEXEL_LIMIT = float(np.float32(1e38))
#: A pyramid build whose level 1 takes at least this many bytes returns the memory of its
#: temporaries to the system before it allocates the levels' buffer.
FLUSH_BYTES = 4 << 20
WIDTH_CONVENTIONS = {'v3': 1.0, 'v4': 2.0}


# ------------------------------------------------------------------------------------ levels
def level_sizes(width: int, height: int) -> list[tuple[int, int]]:
    """Sizes of all levels: halve (floor) each axis, never below 1, until 1×1."""
    sizes = [(width, height)]
    while sizes[-1] != (1, 1):
        w, h = sizes[-1]
        sizes.append((max(1, w // 2), max(1, h // 2)))
    return sizes


def _box_taps(i, n: int, n2: int):
    """Area-average taps from ``n`` texels down to ``n2`` for output texels ``i`` (UInt32):
    [(input index, weight)] — output texel i covers ``[a, b) = [i·n/n2, (i+1)·n/n2)`` of the
    input, input texel j weighs ``|[a, b) ∩ [j, j+1)| / (n/n2)`` (0 for taps past the span).
    Computed on the device (so a frozen function can record a rebuild), relative to
    ``floor(a)`` with integer arithmetic, so they stay exact to float32 rounding at any size."""
    count = n // n2 if n % n2 == 0 else min(n, math.ceil(n / n2) + 1)
    first = (i * n) // n2                           # floor(a)
    rem = i * n - first * n2
    a_rel = mi.Float(rem) / n2                      # a - floor(a), in [0, 1)
    b_rel = mi.Float(rem + n) / n2                  # b - floor(a)
    taps = []
    for k in range(count):
        overlap = dr.minimum(b_rel - k, 1) - dr.maximum(a_rel - k, 0)
        weight = dr.maximum(overlap, 0) * (n2 / n)
        taps.append((first + k, dr.select(first + k < n, weight, 0)))
    return taps


def _downsample(src: mi.Float, w: int, h: int, c: int, w2: int, h2: int,
                clean: bool = False) -> mi.Float:
    """Area-average ``src`` (flat (h, w, c)) to ``w2`` × ``h2`` texels, in one pass: each output
    texel is Σ_y wy·(Σ_x wx·texel) over its taps (:func:`_box_taps`), so no half-downsampled
    intermediate is stored, and the same expression evaluated twice gives the same floats.
    ``clean``: read every tap through :func:`sanitized` (for the raw texels of level 0)."""
    o = dr.arange(mi.UInt32, w2 * h2 * c)
    ch = o % c
    texel = o // c
    oy = texel // w2
    ox = texel - oy * w2
    xs = _box_taps(ox, w, w2)
    acc = mi.Float(0)
    for sy, wy in _box_taps(oy, h, h2):
        row = mi.Float(0)
        for sx, wx in xs:
            tap = dr.gather(mi.Float, src, (sy * w + sx) * c + ch, (wx > 0) & (wy > 0))
            row = dr.fma(wx, sanitized(tap) if clean else tap, row)
        acc = dr.fma(wy, row, acc)
    return acc


def build_levels(texels: mi.Float, width: int, height: int, channels: int):
    """Every level of ``texels`` (flat (height, width, channels), level 0) as one flat buffer,
    RGBA-padded for RGB, plus the level sizes.

    Memory (RGB): the buffer is 16/9 of the tensor; besides the tensor, building it needs only
    the unpadded levels from 2 on (1/12 of it): each level is padded and sanitized
    (:func:`sanitized`) in the kernel that copies it into the buffer, so no padded copy of level 0
    exists besides the buffer's, and level 1 — a source for level 2, then dropped — is computed
    again from the texels inside that kernel (the same floats: same expression). About 2.9× the
    image at the peak (``bench memory``), against 4.2× when the levels were built from a padded
    level 0 and kept until the copy."""
    sizes = level_sizes(width, height)

    def level1():
        (w2, h2) = sizes[1]
        return _downsample(texels, width, height, channels, w2, h2, clean=True)

    parts = [texels]
    if len(sizes) > 1:
        cur = level1()
        for (w, h), (w2, h2) in zip(sizes[1:], sizes[2:]):
            dr.eval(cur)                                # a gather source for the next level
            parts.append(cur)
            cur = _downsample(cur, w, h, channels, w2, h2)
        parts.append(cur)
        parts[1] = level1()                             # recomputed inside the copy, see above
        if 4 * channels * sizes[1][0] * sizes[1][1] >= FLUSH_BYTES and may_wait_for_kernels():
            # the dropped level 1 would stay in Dr.Jit's allocation cache while the buffer is
            # allocated: give it back first (large builds only; it waits for the kernels)
            dr.sync_thread()
            dr.flush_malloc_cache()
    pad = pad_rgb if channels == 3 else (lambda x: x)
    return dr.concat([sanitized(pad(part)) for part in parts]), sizes


def may_wait_for_kernels() -> bool:
    """May a build wait for its kernels (``dr.sync_thread()``) to give its temporaries back?
    On the main thread only: a thread waiting for kernels runs other pending tasks meanwhile,
    and on Mitsuba's scene-loading threads those are other plugins' constructions — another
    texture's build run inside this one's then met it in a kernel (``jitc_assemble(): variable
    … (scope 2) depends on … (scope 68)``: 6 of 20 parallel loads of 20 textures of 2048², 0 of
    45 since; found in a user trial). Builds on those threads keep their temporaries in Dr.Jit's
    allocation cache until something reuses them. Nor while ``dr.freeze`` records (a
    ``params.update()`` inside a frozen function): flushing the cache is refused there, which
    ended the recording of any update of a pyramid of 16 MiB or more (found by a review)."""
    return (threading.current_thread() is threading.main_thread()
            and not dr.flag(dr.JitFlag.FreezingScope))


def sanitized(x):
    """Non-finite texels → 0, the others within ±TEXEL_LIMIT (gradients pass where nothing
    changes)."""
    return dr.select(dr.isfinite(x), dr.clip(x, -TEXEL_LIMIT, TEXEL_LIMIT), 0)


# ------------------------------------------------------------------------------------ pyramid
def pad_rgb(flat: mi.Float) -> mi.Float:
    """RGB texels (3 floats each) → RGBA (4 floats each, A = 0), with Dr.Jit gathers (so
    gradients flow back to the RGB texels)."""
    idx = dr.arange(mi.UInt32, dr.width(flat) // 3 * 4)
    ch = idx & 3
    return dr.gather(mi.Float, flat, (idx >> 2) * 3 + dr.minimum(ch, 2), ch < 3)


def ad_alias(buffer):
    """``buffer`` itself, or, where it carries gradients, a new AD variable for the same JIT
    variable with an edge from it — what a filter's symbolic loop reads. Dr.Jit's forward mode
    through a loop follows every edge out of the variables the loop reads; a buffer also read
    elsewhere (another loop, a closed form, another filter on the pyramid) would take it onto
    edges outside the loop's scope, an error. Make it where the pyramid is built: an alias
    cannot be made inside a symbolic loop or call."""
    if not dr.grad_enabled(buffer):
        return buffer
    return dr.replace_grad(dr.detach(buffer), buffer * 1.0)


class Pyramid:
    """The levels of one image in one flat float32 buffer (see the module docstring): level 0
    first, ``stride`` floats per texel (4 for RGB, 1 for 1-channel images), level ``l`` of size
    ``sizes[l]`` starting at texel ``offsets[l]``. Made by :func:`build_pyramid`, never changed.

    A Dr.Jit struct: ``buffer`` is what Dr.Jit traverses (frozen functions); the rest is static
    shape information (kernels use the sizes and offsets as literals, like the image size). A
    frozen function keys its recordings on the arrays it sees — their types and widths, not the
    literals inside its kernels — so ``width_key``, an array of ``width`` zeros (a literal: no
    memory), tells pyramids of one buffer size apart (16×32 and 32×16 texels): a recording made
    for one shape was replayed for the other (found in a user trial)."""

    DRJIT_STRUCT = {'buffer': object, 'width_key': object}

    def __init__(self, buffer=None, width: int = 1, height: int = 1, channels: int = 1,
                 sizes=None):
        self.buffer = buffer
        self.width, self.height, self.channels = width, height, channels
        self.width_key = dr.zeros(mi.UInt32, width)
        self.sizes = list(sizes) if sizes is not None else [(width, height)]
        self.offsets = [0]
        for w, h in self.sizes[:-1]:
            self.offsets.append(self.offsets[-1] + w * h)

    @property
    def stride(self) -> int:
        return 4 if self.channels == 3 else 1

    def level0(self) -> 'Pyramid':
        """The same buffer seen as level 0 alone (lookups that must not pick a level)."""
        if len(self.sizes) == 1:
            return self
        return Pyramid(self.buffer, self.width, self.height, self.channels, self.sizes[:1])

    @property
    def complete(self) -> bool:
        """Does it hold every level (else level 0 alone)?"""
        return len(self.sizes) == len(level_sizes(self.width, self.height))

    def nbytes(self) -> int:
        return 4 * dr.width(self.buffer)

    def level_nbytes(self, level: int = 0) -> int:
        """Bytes of one level in the buffer (held or not: the size it has when built)."""
        w, h = level_sizes(self.width, self.height)[level]
        return 4 * w * h * self.stride


def build_pyramid(tensor: mi.TensorXf, levels: bool = True) -> Pyramid:
    """The :class:`Pyramid` of ``tensor`` (H, W, 1|3): level 0 alone, or every level. A pure
    function of the texels: gradients enabled on ``tensor`` reach every level of the result. The
    buffer is evaluated (a pyramid may be shared by textures built on other threads, and lookups
    then read it as it is)."""
    if len(tensor.shape) != 3 or tensor.shape[2] not in (1, 3) or min(tensor.shape[:2]) < 1:
        raise ValueError(f'expected an (H, W, 1|3) tensor, got shape {tuple(tensor.shape)}')
    height, width, channels = (int(s) for s in tensor.shape)
    if levels:
        buffer, sizes = build_levels(tensor.array, width, height, channels)
    else:
        level0 = pad_rgb(tensor.array) if channels == 3 else tensor.array
        buffer, sizes = sanitized(level0), [(width, height)]
    dr.eval(buffer)
    return Pyramid(buffer, width, height, channels, sizes)


# ------------------------------------------------------------------------------------ lookups
class MIPMap:
    """A :class:`Pyramid` seen through a wrap mode: fetches and point/bilinear/trilinear. Made
    per lookup (it holds no state of its own), so a lookup always reads the pyramid it is
    given."""

    def __init__(self, pyramid: Pyramid, wrap: str):
        self.pyr = pyramid
        self.wrap = wrap
        self.width, self.height = pyramid.width, pyramid.height
        self.channels = pyramid.channels

    # -------------------------------------------------------------------- structure
    @property
    def has_pyramid(self) -> bool:
        return self.pyr.complete

    @property
    def sizes(self):
        return self.pyr.sizes

    def level_nbytes(self, level: int = 0) -> int:
        return self.pyr.level_nbytes(level)

    @property
    def n_levels(self) -> int:
        """Levels a width can select (pbrt's L), whether or not the pyramid holds them."""
        return 1 + int(math.floor(math.log2(max(self.width, self.height))))

    def value_type(self):
        return mi.Color3f if self.channels == 3 else mi.Float

    # -------------------------------------------------------------------- per-lane level data
    def view(self, level) -> 'LevelView':
        return LevelView(self, level)

    def fetch(self, level, x, y, active, buffer=None):
        """Texel (x, y) of ``level`` (float-valued integers, any range: wrapped here), read
        from ``buffer`` (an :func:`ad_alias` of the pyramid's) if given."""
        view = level if isinstance(level, LevelView) else self.view(level)
        if self.wrap == 'repeat' and view.pow2:        # the modulo as a bit mask (exact)
            return view.gather(mi.Int32(y) & view.mask[1], mi.Int32(x) & view.mask[0], active,
                               buffer)
        w, h = view.size
        ix, iy, valid = wrap_2d(x, y, w, h, self.wrap, *view.inv_size)
        return view.gather(iy, ix, active & valid, buffer)

    # -------------------------------------------------------------------- filters at one level
    def point(self, level, st, active):
        view = self.view(level)
        w, h = view.size
        x = dr.floor(texel_coord(st.x, w, self.wrap))
        y = dr.floor(texel_coord(st.y, h, self.wrap))
        return self.fetch(view, x, y, active)

    def corners(self, level, st, active):
        """The 4 texels of ``level`` around st, wrapped (order (0,0), (1,0), (0,1), (1,1)), the
        weights ``(1 - fx, fx)``, ``(1 - fy, fy)`` of the bilinear reconstruction there, and the
        level's size ``(w, h)``."""
        view = self.view(level)
        w, h = view.size
        px = texel_coord(st.x, w, self.wrap, -0.5)
        py = texel_coord(st.y, h, self.wrap, -0.5)
        x0, y0 = dr.floor(px), dr.floor(py)
        wx1, wy1 = px - x0, py - y0
        if self.wrap == 'octahedralsphere':            # couples the axes: wrap per tap
            texels = [self.fetch(view, x0 + bx, y0 + by, active)
                      for by in (0, 1) for bx in (0, 1)]
        elif self.wrap == 'repeat' and view.pow2:
            # power-of-two sides (every level of a power-of-two image): the modulo is a bit
            # mask — exact, and at a per-lane level a few integer operations instead of a float
            # modulo by a per-lane size
            ix0, iy0 = mi.Int32(x0), mi.Int32(y0)
            xs = (ix0 & view.mask[0], (ix0 + 1) & view.mask[0])
            ys = (iy0 & view.mask[1], (iy0 + 1) & view.mask[1])
            texels = [view.gather(ys[by], xs[bx], active) for by in (0, 1) for bx in (0, 1)]
        else:                                           # wrap each axis once per tap column/row
            xs = adjacent_wrapped(x0, w, self.wrap, view.inv_size[0])
            ys = adjacent_wrapped(y0, h, self.wrap, view.inv_size[1])
            texels = [view.gather(ys[by][0], xs[bx][0], active & xs[bx][1] & ys[by][1])
                      for by in (0, 1) for bx in (0, 1)]
        return texels, (1 - wx1, wx1), (1 - wy1, wy1), (w, h)

    def bilinear(self, level, st, active):
        texels, wx, wy, _ = self.corners(level, st, active)
        out = None
        for (bx, by), v in zip(((0, 0), (1, 0), (0, 1), (1, 1)), texels):
            weight = wx[bx] * wy[by]          # Dr.Jit's texture: same products, same fma order
            out = v * weight if out is None else dr.fma(v, weight, out)
        return out

    def bilinear_gradient(self, level, st, active, per_channel: bool = False):
        """(f, df/ds, df/dt) of the bilinear reconstruction of the luminance (or channel);
        with ``per_channel``, of each channel."""
        texels, wx, wy, (w, h) = self.corners(level, st, active)
        f00, f10, f01, f11 = (mi.luminance(v) if self.channels == 3 and not per_channel else v
                              for v in texels)
        f = (f00 * wx[0] + f10 * wx[1]) * wy[0] + (f01 * wx[0] + f11 * wx[1]) * wy[1]
        dfdx = wy[0] * (f10 - f00) + wy[1] * (f11 - f01)
        dfdy = wx[0] * (f01 - f00) + wx[1] * (f11 - f10)
        return f, dfdx * w, dfdy * h

    # -------------------------------------------------------------------- level selection
    def level_of(self, width):
        """Continuous level for a filter width in texture units (pbrt: L-1 + log2 width)."""
        return log2_positive(self._texels_across(width))

    def whole_level_of(self, width):
        """``floor(level_of(width))`` as an Int32, exactly: the float's exponent bits (what
        point and bilinear lookups select; no polynomial)."""
        bits = dr.reinterpret_array(mi.UInt32, self._texels_across(width))
        return mi.Int32(bits >> 23) - 127

    def _texels_across(self, width):
        return dr.maximum(width, 1e-8) * float(max(self.width, self.height))

    def only_where(self, mask, fn):
        """``fn(mask)`` where ``mask`` holds and 0 elsewhere, as a symbolic conditional: a
        packet of lanes none of which needs it skips it (a branch), where a masked computation
        would run it anyway — e.g. the second level of a trilinear lookup under magnification
        (30% faster). While the texels carry gradients it is the masked computation: Dr.Jit's
        forward mode through a BSDF call that reads the texture twice (a ``roughconductor``'s
        ``alpha``: its eval and its pdf) failed on the conditional (the buffer's edges into
        the other read lie outside the conditional's scope)."""
        if dr.grad_enabled(self.pyr.buffer):
            return dr.select(mask, fn(mask), 0)
        return dr.if_stmt(args=(mask,), cond=mask, true_fn=fn,
                          false_fn=lambda m: dr.zeros(self.value_type()), label='pbrt_level')

    def _top_lanes(self, level, last):
        """Lanes whose footprint is beyond the top level: pbrt gives them its single texel. A
        point or bilinear lookup on that 1×1 level returns it anyway — every tap wraps onto it —
        except with ``black`` wrap, whose taps outside are 0: only then are they set apart (and
        read by :meth:`_with_top`)."""
        return level >= last if self.wrap == 'black' else mi.Bool(False)

    def _with_top(self, top, active, value):
        if self.wrap != 'black':
            return value
        return dr.select(top, self.coarsest(active & top), value)

    def coarsest(self, active):
        """The texel of the 1×1 top level — the image mean — read without wrapping, as pbrt
        returns for every footprint that reaches it (also with ``black`` wrap)."""
        last = len(self.sizes) - 1
        return self.view(mi.UInt32(last)).gather(mi.Int32(0), mi.Int32(0), active)

    def filter_single_level(self, kind: str, st, width, active):
        """``point`` or ``bilinear`` at the level ``width`` selects (pbrt-v4)."""
        lookup = self.point if kind == 'point' else self.bilinear
        if not self.has_pyramid:
            return lookup(0, st, active)
        last = len(self.sizes) - 1      # (a 1×1 image too: level 0 is its top)
        level = self.whole_level_of(width)
        top = self._top_lanes(level, last)
        ilevel = mi.UInt32(dr.clip(level, 0, last))
        value = lookup(ilevel, st, active & ~top)
        return self._with_top(top, active, value)

    def trilinear(self, st, width, active):
        if not self.has_pyramid:
            return self.bilinear(0, st, active)
        if len(self.sizes) == 1:        # a 1×1 image: as a single-level lookup (pbrt's top rule)
            return self.filter_single_level('bilinear', st, width, active)
        last = len(self.sizes) - 1
        level = dr.maximum(self.level_of(width), 0)
        top = self._top_lanes(level, last)
        l0 = dr.minimum(dr.floor(level), last - 1)
        frac = dr.clip(level - l0, 0, 1)
        il0 = mi.UInt32(l0)
        run = active & ~top
        v0 = self.bilinear(il0, st, run & (frac < 1))
        v1 = self.only_where(run & (frac > 0), lambda m: self.bilinear(il0 + 1, st, m))
        blend = dr.select(frac <= 0, v0, dr.select(frac >= 1, v1, dr.lerp(v0, v1, frac)))
        return self._with_top(top, active, blend)


class LevelView:
    """One level of the pyramid's buffer: static level 0 (Python constants for its size) or a
    per-lane UInt32 level. Size and offset are computed once and reused by every tap, and each
    tap is a single gather from the one buffer."""

    def __init__(self, mip: MIPMap, level):
        self.mip = mip
        pyr = mip.pyr
        self.static = isinstance(level, int) or len(pyr.sizes) == 1
        if self.static:
            if isinstance(level, int) and level != 0:
                raise ValueError('only level 0 can be static')
            self.size = (float(mip.width), float(mip.height))
            self.inv_size = (1.0 / mip.width, 1.0 / mip.height)
            self.off, self.iw = 0, mip.width
        else:
            # level sizes halve with floor, never below 1: max(1, n >> level)
            level = mi.UInt32(level)
            iw = dr.maximum(mi.UInt32(mip.width) >> level, 1)
            ih = dr.maximum(mi.UInt32(mip.height) >> level, 1)
            self.size = (mi.Float(iw), mi.Float(ih))
            # the level's first texel, from literals (cheaper in a kernel than a gather from a
            # table): for a square power-of-two image n², the sum of (n/2^k)² over k < level,
            # (4n² - 4n²/4^level) / 3 exactly; otherwise a select per level
            a4 = 4 * mip.width * mip.height
            if mip.width == mip.height and not mip.width & (mip.width - 1) and a4 < 2**32:
                self.off = (a4 - (mi.UInt32(a4) >> (2 * level))) // 3
            else:
                self.off = mi.UInt32(0)
                for lvl, offset in enumerate(pyr.offsets[1:], start=1):
                    self.off = dr.select(level >= lvl, offset, self.off)
            self.iw = iw
            self.inv_size = (dr.rcp(self.size[0]), dr.rcp(self.size[1]))
        # every level of a power-of-two image has power-of-two sides: x mod w = x & (w - 1)
        self.pow2 = not (mip.width & (mip.width - 1) or mip.height & (mip.height - 1))
        if self.pow2 and self.static:
            self.mask = (mip.width - 1, mip.height - 1)
        elif self.pow2:
            self.mask = (mi.Int32(iw - 1), mi.Int32(ih - 1))

    def gather(self, iy, ix, active, buffer=None):
        """Texel at wrapped integer (ix, iy), from ``buffer`` (an :func:`ad_alias` of the
        pyramid's) if given."""
        pyr = self.mip.pyr
        buffer = pyr.buffer if buffer is None else buffer
        ix = mi.UInt32(ix) if self.static else mi.UInt32(ix) + self.off
        index = dr.fma(mi.UInt32(iy), self.iw, ix)
        if pyr.stride == 4:
            return _rgb(dr.gather(mi.Array4f, buffer, index, active))
        return dr.gather(mi.Float, buffer, index, active)


def _rgb(v4):
    return mi.Color3f(v4.x, v4.y, v4.z)


def _log2_polynomial(degree: int = 8) -> list[float]:
    """Coefficients of ``P`` with ``log2(1 + t) ≈ t·P(t)`` on [0, 1), least squares: 1.7e-7
    absolute error in float32, and exactly 0 at t = 0 (powers of two give integer levels)."""
    t = np.linspace(0, 1, 4097)[1:-1]
    basis = np.vander(t, degree, increasing=True) * t[:, None]
    return [float(np.float32(c)) for c in np.linalg.lstsq(basis, np.log2(1 + t), rcond=None)[0]]


_LOG2_POLY = _log2_polynomial()


def log2_positive(x):
    """log2 of positive, finite, normal float32 ``x``: the exponent bits plus a polynomial in
    the mantissa — for level selection, where Dr.Jit's general ``log2`` (special values,
    range reduction) was a fifth of a trilinear lookup's time."""
    bits = dr.reinterpret_array(mi.UInt32, x)
    exponent = mi.Float(mi.Int32(bits >> 23) - 127)
    t = dr.reinterpret_array(mi.Float, (bits & 0x7FFFFF) | 0x3F800000) - 1
    value = mi.Float(_LOG2_POLY[-1])
    for coef in _LOG2_POLY[-2::-1]:
        value = dr.fma(value, t, coef)
    return dr.fma(value, t, exponent)


def footprint_width(tc, convention: float):
    """pbrt's isotropic filter width from the four derivatives (times 1 or 2, see module doc)."""
    w = dr.maximum(dr.maximum(dr.abs(tc.dsdx), dr.abs(tc.dtdx)),
                   dr.maximum(dr.abs(tc.dsdy), dr.abs(tc.dtdy)))
    return convention * dr.select(dr.isfinite(w), w, 0.0)
