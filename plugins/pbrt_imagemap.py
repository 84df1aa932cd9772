"""pbrt_imagemap — MIP-mapped image texture: point, bilinear, trilinear, EWA and box filtering.

A drop-in upgrade of Mitsuba's ``bitmap`` (its parameter names are accepted as aliases) with
pbrt-v4's filters (pbrt section 10.4).

| parameter | type | default | meaning | differentiable |
|---|---|---|---|---|
| filename | string | — | image file: OpenEXR (via the OpenEXR package: channels R,G,B, X,Y,Z — converted to linear sRGB as ``bitmap`` converts them — or Y, plus A, at the top level or in one layer such as ``diffuse.R``) or anything ``mi.Bitmap`` reads (PNG, JPEG, HDR, PFM, ...); the format is found from the file's content, not its name | no |
| bitmap | Bitmap | — | an ``mi.Bitmap`` object instead of a file (runtime only); read as ``bitmap`` reads it: sRGB-decoded where its ``srgb_gamma()`` is set, linear where not | no |
| data | tensor | — | texels as a ``TensorXf`` of shape (H, W, 1 or 3), linear float32 (runtime only; integer tensors are refused; ``params['...data']`` is this linear tensor for every source, where ``bitmap`` exposes 8-bit images as uint8 sRGB codes) | yes |
| filter | string | bilinear | `point`, `bilinear`, `trilinear`, `ewa` (also `EWA`, as pbrt-v4) or `box` (exact average over the footprint; not with wrap `octahedralsphere`) | no |
| filter_type | string | — | Mitsuba ``bitmap`` alias of filter: `nearest` (= point) or `bilinear` | no |
| maxanisotropy | float | 8 | `ewa`: the longest axis is at most this many times the shortest (≥ 1) | no |
| sortlookups | boolean | true | `ewa`: filter a large batch of scattered lookups sorted by texture tile, results in the caller's order (identical values, less waiting on memory; not inside symbolic loops/calls, where lookups cannot be reordered) | no |
| wrap | string | repeat | `repeat`, `black`, `clamp`, `mirror` or `octahedralsphere` | no |
| wrap_mode | string | — | Mitsuba ``bitmap`` alias of wrap: `repeat`, `mirror` or `clamp` | no |
| scale | float | 1 | factor applied to every texel value | yes |
| invert | boolean | false | return ``max(0, 1 - scale·value)`` | no |
| encoding | string | sRGB (8/16-bit files), linear (float files); a ``bitmap`` object's ``srgb_gamma()`` flag | decoding of integer images and of ``bitmap`` objects flagged sRGB: `sRGB`, `linear` or `gamma G` | no |
| raw | boolean | false | Mitsuba ``bitmap`` alias: true = encoding `linear` (a flagged ``bitmap`` object's stored values, as ``bitmap``'s ``raw``) | no |
| trilinearwidth | string | v3 | footprint width of point/bilinear/trilinear: `v3` = max abs derivative (pbrt-v3), `v4` = twice that (pbrt-v4) | no |
| format | string | auto | Mitsuba ``bitmap`` storage option, accepted for drop-in use; storage is always float32 | no |
| accel | boolean | true | Mitsuba ``bitmap`` option, accepted for drop-in use; no effect | no |
| (2D mapping) | | | mapping parameters (``to_uv`` included; with the `uv` mapping ``to_uv`` is in ``mi.traverse`` as with ``bitmap``), see the mapping table | no |

Exactly one of ``filename``, ``bitmap``, ``data``. A pbrt name and its ``bitmap`` alias together
are an error.

Orientation: as Mitsuba's ``bitmap`` and OpenImageIO — ``v = 0`` is the first row of the file (the
top), texel centres at ``((i + 0.5)/W, (j + 0.5)/H)``, no flip. pbrt-v4 instead evaluates at
``t' = 1 - t`` (its texture space has t up) but forgets to negate ``dt/dx, dt/dy``, which mirrors
anisotropic EWA footprints; we do not flip, so nothing needs negating (Mitsuba's OBJ loader already
flips v, so images appear upright on OBJ meshes).

Channels: 1-channel images give grey colours (``eval``, and ``eval_3``, where ``bitmap`` raises)
and their value as float; RGB images give colours, and their luminance as float (``eval_1``, as
``bitmap``). Alpha is dropped. ``invert`` clamps at 0 like pbrt; otherwise values are not clamped
(parity with ``bitmap``, negative EXR texels survive).

Filters and footprints: ``point`` and ``bilinear`` look up the level the footprint selects, as
pbrt-v4 does, once the texture is prepared for differentials (``pbrt_path`` calls
``tex.prepare_differentials()``, which builds the other levels); before that they read level 0
whatever the footprint and whatever levels the pyramid holds (``params.update()`` builds them
once gradients are enabled on ``data``, and so may another texture of the same file). Under
Mitsuba's own integrators the footprint is always 0 (they compute no texture differentials), so
they behave exactly as ``bitmap`` ``nearest``/``bilinear``. ``trilinear`` and
``ewa`` build every level at once. With zero differentials every filter is a bilinear lookup at
level 0 (``point``: the nearest texel).

Storage: the texture holds ``data`` (the tensor ``traverse`` exposes) and its pyramid, one value
built from it by :func:`~mitsuba_pbrt_tex.mipmap.build_pyramid` (level 0 RGBA-padded in the same
buffer as the other levels). Textures of the same file share the file's cached pyramid until
their ``data`` is updated.

``box``: the exact area average of the bilinear reconstruction over the footprint parallelogram
(one pixel around the lookup: ``st ± dst/dx/2 ± dst/dy/2``), with no minimum width under
magnification; a float32 walk of the footprint's boundary over the texels of the finest level
where its short side is at most :data:`~mitsuba_pbrt_tex.box.MAX_BANDS` texels and its perimeter
at most :data:`~mitsuba_pbrt_tex.box.MAX_PERIMETER` (see :mod:`mitsuba_pbrt_tex.box`), with no
table beside the pyramid (the "tables" are AD aliases of its buffer). ``eval_1_grad``: see
*Gradients* below. ``box`` opts in to ``pbrt_path``'s ``footprint="pixel"``: camera hits then filter
their pixel's footprint (every sample of a pixel sees its average; right for albedo and
emission, not for roughness, whose shading is not linear in the texture — use another filter
there; a bump map's gradient is taken from sample-centred lookups, see *Gradients*). With a
Gaussian film filter they filter the film filter's own kernel around the pixel centre instead
(:mod:`mitsuba_pbrt_tex.gauss`).

Lookup order (``sortlookups``): an EWA lookup reads ~40 cache lines, so a batch of lookups at
random places of a large texture waits on memory. Where the batch exists as evaluated arrays — a
call such as ``tex.eval(si)`` from Python, or Mitsuba's wavefront mode — ``ewa`` sorts it by the
32×32-texel tile each lookup falls in, filters it in that order and returns the results in the
caller's order: the same values, 2.5–3.5× faster at random uv on a 1024² texture (``bench
lookups``). Batches under 16384 lookups, batches with fewer than a quarter of their lookups on
levels of 8 MB or more, batches already in coherent order, and lookups traced inside a symbolic
loop or call (a render's kernel) run in the order given. See :mod:`mitsuba_pbrt_tex.lookup_order`.

Emitters and light tracing (the rest of ``bitmap``'s interface): ``sample_position`` /
``pdf_position`` importance-sample uv positions for area emitters and projectors, with a density
exactly proportional to the zero-footprint lookup for every filter and wrap mode, carried through
uv flips, 90° rotations and integer tilings (other mappings: uniform, with a warning); the tables
are built the first time an emitter asks and again after ``data``, ``to_uv`` (or, with
``invert``, ``scale``) change. See :mod:`mitsuba_pbrt_tex.sampling`. ``sample_spectrum`` returns
the value and no wavelengths (RGB and mono variants, as ``bitmap``), which ``ptracer`` and the
emitters' ``sample_ray`` need; ``pdf_spectrum`` returns empty wavelengths. ``to_uv`` written
through ``params`` rebuilds the mapping. A bare ``mi.SurfaceInteraction3f()`` with only ``uv``
set is evaluated with zero differentials.

Gradients: ``data`` and ``scale`` are differentiable through every filter; the pyramid is rebuilt
inside the AD graph by ``parameters_changed`` (``params.update()``) — also when it is built lazily
during a render — so gradients reach base texels through coarse levels. ``eval_1_grad`` (for
``bumpmap``) is the exact gradient of point, bilinear and trilinear lookups and, where the hit has
differentials, pbrt-v4's ``BumpMap`` difference of ``ewa`` and ``box`` values (see
:meth:`Plugin.eval_1_grad`).
"""

import difflib
import math
import os
import threading

import drjit as dr
import mitsuba as mi

from mitsuba_pbrt_tex import gauss, pixel
from mitsuba_pbrt_tex.box import BOX_WRAPS, build_box_tables
from mitsuba_pbrt_tex.differentials import TextureEvalContext
from mitsuba_pbrt_tex.ewa import build_ewa_buffers
from mitsuba_pbrt_tex.filters import TextureFilter
from mitsuba_pbrt_tex.image import (ENCODING_CHOICES, TEXEL_LIMIT, PyramidSlot, decode_bitmap,
                                    load_image, parse_encoding, release_build_temporaries,
                                    warn_clamped)
from mitsuba_pbrt_tex.mapping import mapping_2d
from mitsuba_pbrt_tex.mipmap import (FILTERS, WIDTH_CONVENTIONS, MIPMap, Pyramid, build_pyramid,
                                     sanitized)
from mitsuba_pbrt_tex.params import PluginError
from mitsuba_pbrt_tex.render_scope import in_silhouette_paths
from mitsuba_pbrt_tex.sampling import (PositionSampler, TextureSpaceSampler, texel_weights,
                                       uv_axes)
from mitsuba_pbrt_tex.texture import PbrtTexture, finite_gradient
from mitsuba_pbrt_tex.wrap import WRAP_MODES

FORMATS = ('auto', 'variant', 'float16', 'fp16', 'uint8')


def integer_data_message(value) -> str:
    shape = tuple(getattr(value, 'shape', ()))
    return (f'got an integer tensor ({type(value).__name__} of shape {shape}); accepted: a '
            f'TensorXf of linear float32 values, shape (H, W, 1) or (H, W, 3). Mitsuba\'s bitmap '
            f'stores 8-bit images as uint8 sRGB codes, pbrt_imagemap as linear floats: decode '
            f'codes c with c/255 (raw) or the sRGB curve, e.g. '
            f'mi.TensorXf(mi.Bitmap(...).convert(component_format=mi.Struct.Type.Float32, '
            f'srgb_gamma=False))')


#: :func:`_luminance_mean` reduces this many texels at a time.
MEAN_CHUNK = 1 << 20


def _luminance_mean(texels, channels: int, scale, invert: bool):
    """Mean over the texels (flat, as the pyramid holds them: NaN → 0, ±1e38) of the luminance
    (or channel) of ``scale``·texel, or with ``invert`` of max(0, 1 - scale·texel) channel by
    channel, as lookups invert. Evaluated.

    Reduced :data:`MEAN_CHUNK` texels at a time, each read from the texels as they are and
    sanitized as read: a reduction evaluates its input, so one over the whole image held a
    sanitized copy of it (gathered from) and a value per texel — 1.33× the image on top of the
    pyramid at construction, the peak of a large texture's load (4.14× the image for ``ewa``
    where the pyramid holds 2.81×; found in a user trial)."""
    n = dr.width(texels) // channels
    total = mi.Float(0)
    for start in range(0, n, MEAN_CHUNK):
        index = dr.arange(mi.UInt32, start, min(n, start + MEAN_CHUNK))
        values = sanitized(dr.gather(mi.Color3f if channels == 3 else mi.Float, texels,
                                     index)) * scale
        if invert:
            values = dr.maximum(0, 1 - values)
        if channels == 3:
            values = mi.luminance(values)
        # summed scaled by 2^-40 (exact, a power of two): texels near float32's maximum
        # (3.4e38) must not overflow the sum of up to 2^40 texels
        total = total + dr.sum(values * 2.0**-40)
        dr.eval(total)
    mean = total * (2.0**40 / max(n, 1))
    dr.eval(mean)
    return mean


class Plugin(PbrtTexture):
    NAME = 'pbrt_imagemap'

    # ------------------------------------------------------------------ parameters
    def configure(self, p):
        self.filter_name = p.enum('filter', 'bilinear', FILTERS, alias='filter_type',
                                  alias_choices={'nearest': 'point', 'bilinear': 'bilinear'},
                                  spellings={'EWA': 'ewa'})      # pbrt-v4 reads both
        self.max_anisotropy = p.float('maxanisotropy', 8.0, lo=1.0)
        self.sort_lookups = p.bool('sortlookups', True)
        self.wrap = p.enum('wrap', 'repeat', WRAP_MODES, alias='wrap_mode',
                           alias_choices={'repeat': 'repeat', 'mirror': 'mirror', 'clamp': 'clamp'})
        if self.filter_name == 'box' and self.wrap == 'octahedralsphere':
            raise p.error('filter', 'value "box" does not support wrap "octahedralsphere" (its '
                                    'wrap couples the axes); accepted wraps with "box": '
                                    + ', '.join(BOX_WRAPS))
        self._scale_value = p.float('scale', 1.0)
        self.scale = self.jit_value('scale', self._scale_value)
        self.invert = p.bool('invert', False)
        self.width_convention = p.enum('trilinearwidth', 'v3', WIDTH_CONVENTIONS)
        p.enum('format', 'auto', FORMATS)
        p.bool('accel', True)
        self.mapping = mapping_2d(p)
        # params['…to_uv'], as bitmap's (the uv mapping only)
        self._to_uv = self.mapping.to_uv_3x3() if self.mapping.name == 'uv' else None
        self._sampler, self._sampler_lock = None, threading.Lock()    # built when an emitter asks
        self._footprints = False            # prepared for differentials (prepare_differentials)
        encoding = self._encoding(p)
        self._load(p, encoding)
        self.describe('source', self.source)
        self.describe('resolution', f'{self.pyramid.width}x{self.pyramid.height}x'
                                    f'{self.channels}')
        for name in ('filter_name', 'wrap', 'max_anisotropy', 'sort_lookups', 'invert',
                     'width_convention'):
            self.describe(name.replace('_name', ''), getattr(self, name))
        self.describe('mapping', self.mapping.describe())
        self._make_filter()

    def _encoding(self, p):
        text = p.string('encoding', None)
        raw = p.has('raw')
        if text is not None and raw:
            raise p.error('encoding', 'given together with its alias "raw"; give only one of them')
        if raw:
            return parse_encoding('linear') if p.bool('raw', False) else None
        if text is None:
            return None
        enc = parse_encoding(text)
        if enc is None:
            raise p.error('encoding', f'unknown value "{text}"; accepted values: '
                                      f'{", ".join(ENCODING_CHOICES)}')
        return enc

    def _load(self, p, encoding):
        sources = ('filename', 'bitmap', 'data')
        given = [k for k in sources if p.has(k)]
        if not given:
            # a misspelt source is named here: the unknown-parameter check comes later
            for k in p.props.keys():
                near = difflib.get_close_matches(k, sources, 1, 0.7)
                if near and k not in sources:
                    raise PluginError(f'{self.NAME}: parameter "{k}": unknown; did you mean '
                                      f'"{near[0]}"? (give exactly one of the parameters '
                                      f'"filename", "bitmap", "data")')
        if len(given) != 1:
            raise PluginError(f'{self.NAME}: give exactly one of the parameters "filename", '
                              f'"bitmap", "data" (got {", ".join(given) if given else "none"})')
        source = given[0]
        self._shared = None          # the cached file this texture's texels still are, if any
        if source == 'data':
            if encoding is not None and encoding.kind != 'linear':
                raise p.error('encoding', 'applies to 8/16-bit image files only; "data" tensors '
                                          'are linear')
            # our own tensor object over the caller's texels: gradients enabled on ours (through
            # mi.traverse) must not reach another texture built from the same tensor
            self.data = mi.TensorXf(self._checked_tensor(p.raw('data'), p))
            self.source = 'data tensor'
        elif source == 'filename':
            name = p.string('filename', None)
            if not name.strip():
                raise p.error('filename', 'value "" is empty; expected the path of an image file')
            path = str(mi.file_resolver().resolve(name))
            if os.path.isdir(path):
                raise p.error('filename', f'"{path}" is a directory; expected the path of an '
                                          f'image file')
            self._shared = self._call(lambda: load_image(path, encoding), 'filename')
            # our own tensor object over the shared texels, so in-place updates stay ours
            self.data, self.source = mi.TensorXf(self._shared.tensor), name
            self._warn_nonfinite(self._shared.nonfinite)
        else:
            bmp = p.raw('bitmap')
            if not isinstance(bmp, mi.Bitmap):
                raise p.error('bitmap', f'expected an mi.Bitmap, got {type(bmp).__name__}')
            img = self._call(lambda: decode_bitmap(bmp, encoding, 'the bitmap'), 'bitmap')
            self.data, self.source = mi.TensorXf(img.texels), 'bitmap object'
            self._warn_nonfinite(img.nonfinite)
        self._tables = None
        self._rebuild(levels=self.filter_name in ('trilinear', 'ewa', 'box'))
        self._update_mean()

    def _call(self, fn, param):
        try:
            return fn()
        except ValueError as e:
            raise PluginError(f'{self.NAME}: parameter "{param}": {e}') from None

    def _checked_tensor(self, value, p):
        if dr.is_tensor_v(value) and dr.is_integral_v(value):
            raise p.error('data', integer_data_message(value))
        if not isinstance(value, mi.TensorXf) or len(value.shape) != 3 or value.shape[2] not in (1, 3) \
                or min(value.shape[:2]) < 1:
            shape = getattr(value, 'shape', None)
            raise p.error('data', f'expected a TensorXf of shape (H, W, 1) or (H, W, 3), got '
                                  f'{type(value).__name__}' + (f' of shape {tuple(shape)}'
                                                               if shape is not None else ''))
        dr.eval(value)      # a lazy tensor from another thread must not be extended on this one
        return self._finite_texels(value)

    def _finite_texels(self, value):
        """``value`` with non-finite texels replaced by 0 and others clamped to ±TEXEL_LIMIT
        (with warnings giving their counts), as for image files."""
        x = value.array
        if not int(dr.count(~(dr.abs(x) <= TEXEL_LIMIT))[0]):       # NaN compares false
            return value
        bad = int(dr.count(~dr.isfinite(x))[0])
        big = int(dr.count(dr.isfinite(x) & (dr.abs(x) > TEXEL_LIMIT))[0])
        x = dr.select(dr.isfinite(x), dr.clip(x, -TEXEL_LIMIT, TEXEL_LIMIT), 0)
        self._warn_nonfinite(bad)
        warn_clamped(big)
        return mi.TensorXf(x, value.shape)

    def _warn_nonfinite(self, count):
        if count:
            mi.Log(mi.LogLevel.Warn, f'{self.NAME}: {count} non-finite texel value(s) '
                                     f'replaced by 0')

    @property
    def pyramid(self) -> Pyramid:
        """The pyramid lookups read: while the texels are still a file's, the best one the file's
        cache has built (a complete pyramid serves level-0 lookups too, so once another texture
        of the file has built it no second copy of level 0 stays alive); else the texture's
        own (a :class:`~mitsuba_pbrt_tex.image.PyramidSlot`, filled in :meth:`_rebuild`)."""
        return self.pyramid_slot.pyramid

    def _rebuild(self, levels: bool) -> None:
        """The one place the internals follow the texels: the pyramid of ``self.data`` (every
        level, or level 0 alone) — the file's shared one while the texels are still the file's,
        else built from the tensor, inside the AD graph even during a render's primal pass
        (which suspends gradients), so gradients enabled on the tensor reach every level; large
        builds give their temporaries back — and, for ``box`` and ``ewa``, the AD aliases of
        its buffer that the filter's loops read (pure, in the AD graph like the pyramid)."""
        self._levels = levels
        if self._shared is not None:
            self._shared.pyramid(levels)            # built once per file
            self.pyramid_slot = self._shared.slot          # the file's textures read one slot
        else:
            with dr.resume_grad():
                pyramid = build_pyramid(self.data, levels)
            release_build_temporaries(pyramid)
            self.pyramid_slot = PyramidSlot(pyramid)
        if self.filter_name in ('box', 'ewa'):          # what the filter's loops read
            with dr.resume_grad():
                self._tables = (build_box_tables(self.pyramid, self.wrap)
                                if self.filter_name == 'box' else build_ewa_buffers(self.pyramid))

    def _state(self):
        """(pyramid, what the filter's loops read) for a lookup — read only. Stale state is an
        error naming the fix: gradients enabled on ``data`` after the pyramid was built, without
        ``params.update()``, would not reach the texels (the pyramid is a copy; Mitsuba's
        ``bitmap`` gives no gradient at all then). ``point`` and ``bilinear`` pick a level from
        the footprint only once this texture was prepared for differentials
        (:meth:`prepare_differentials`), whatever levels its pyramid holds — another texture of
        the file, or gradients on the texels, build them too: before, they read level 0."""
        pyr = self.pyramid
        if self.filter_name in ('point', 'bilinear') and not self._footprints:
            pyr = pyr.level0()
        if dr.grad_enabled(self.data) and not dr.grad_enabled(pyr.buffer):
            raise PluginError(
                f'{self.NAME}: parameter "data": gradients were enabled on it after the '
                f'texture was built, so they cannot reach its MIP levels; call '
                f'params.update() after dr.enable_grad(params[...]) (Mitsuba\'s optimizers '
                f'do this in params.update(opt))')
        return pyr, self._tables

    def _make_filter(self):
        self.filter = TextureFilter(self.filter_name, self.wrap, self.max_anisotropy,
                                    WIDTH_CONVENTIONS[self.width_convention], self.sort_lookups)
        # silhouette paths: N per edge pixel, each of which would walk the pixel's box again
        self.silhouette_filter = TextureFilter(
            'ewa', self.wrap, self.max_anisotropy, WIDTH_CONVENTIONS[self.width_convention],
            self.sort_lookups) if self.filter_name == 'box' else None

    def filters_film_kernel(self):
        """``box`` filters a Gaussian film's kernel around the pixel centre (camera hits of
        ``pbrt_path`` ``footprint="pixel"``)."""
        return self.filter_name == 'box'

    # ------------------------------------------------------------------ evaluation
    def context(self, si):
        """``box`` opts in to pixel footprints (``pbrt_path`` ``footprint="pixel"``: camera hits
        filter their pixel's footprint, see :mod:`mitsuba_pbrt_tex.pixel`); the other filters
        stay sample-centred."""
        if self.filter_name == 'box':
            return pixel.context(si)
        return TextureEvalContext.from_si(si)

    def _value(self, si, active, around_sample: bool = False):
        pixels = pixel.published_pixels() if self.filter_name == 'box' else None
        pyr, tables = self._state()
        if around_sample:
            v = self.filter(pyr, self.mapping.map(TextureEvalContext.from_si(si)), active,
                            tables) * self.scale
        elif self.silhouette_filter is not None and in_silhouette_paths():
            # the extra paths through a pixel that crosses a silhouette estimate its coverage:
            # EWA over the footprint the box would average (the same for all of a pixel's)
            v = self.silhouette_filter(pyr, self.mapping.map(pixel.context(si)), active) \
                * self.scale
        elif pixels is not None:
            v = self._film_filtered(si, active, pixels, pyr, tables) * self.scale
        elif self.filter_name == 'box':         # the pixel's average, strip by strip
            v = pixel.pixel_average(
                si, lambda ctx, act: self.filter(pyr, self.mapping.map(ctx), act, tables),
                mi.Color3f if self.channels == 3 else mi.Float, active) * self.scale
        else:
            v = self.filter(pyr, self.mapping.map(self.context(si)), active, tables) * self.scale
        if self.invert:
            v = dr.maximum(0, 1 - v)
        return v

    def _film_filtered(self, si, active, pixels, pyr, tables):
        """``pbrt_path`` ``footprint="pixel"`` with a Gaussian film: the film filter's kernel
        around the pixel centre (:func:`mitsuba_pbrt_tex.gauss.pixel_filter`) for camera hits,
        the sample-centred box elsewhere."""
        active = mi.Bool(active)
        centre, g, h, ok = pixel.filter_context(si, pixels)
        tc = self.mapping.map(centre)
        kernel = gauss.pixel_filter(MIPMap(pyr, self.wrap), tc.st,
                                    mi.Vector2f(tc.dsdx, tc.dtdx), mi.Vector2f(tc.dsdy, tc.dtdy),
                                    g, h, pixels, active & ok)
        tc_sample = self.mapping.map(TextureEvalContext.from_si(si))
        sample = self.filter(pyr, tc_sample, active & ~ok, tables)
        return dr.select(ok, kernel, sample)

    def evaluate(self, si, kind, active):
        v = self._value(si, active)
        return kind.from_rgb(v) if self.channels == 3 else kind.from_float(v)

    def eval_1_grad(self, si, active=True):
        """``d eval_1 / d(u, v)`` for ``bumpmap``: the exact gradient of point, bilinear and
        trilinear lookups (:meth:`TextureFilter.gradient`). ``ewa`` and ``box`` values are not
        smooth on the texel scale — EWA's table weights make it a step function there, and the
        slope of the box's area average changes wherever its outline crosses a texel — so where
        the hit has differentials their gradient is pbrt-v4's ``BumpMap`` difference of the
        filtered value over half the footprint (:meth:`PbrtTexture.eval_1_grad`, as for the
        procedural textures and as pbrt renders bump maps of them); without differentials both
        are the bilinear lookup of level 0, whose exact gradient (``bitmap``'s) they keep. The
        difference is of sample-centred lookups also where ``box`` filters the pixel's
        footprint (camera hits of ``pbrt_path`` ``footprint="pixel"``): the hit moved by half
        a footprint is no longer the camera's, so a pixel average there would have been
        differenced against a sample-centred value (found by a review)."""
        active = mi.Bool(active)
        if self.filter_name not in ('ewa', 'box'):
            return self._exact_gradient(si, active)
        ctx = TextureEvalContext.from_si(si)
        footprint = (ctx.dudx != 0) | (ctx.dudy != 0) | (ctx.dvdx != 0) | (ctx.dvdy != 0)
        exact = self._exact_gradient(si, active & ~footprint)
        difference = self.bump_difference(si, active & footprint, self._eval_1_around_sample)
        return dr.select(footprint, difference, exact)

    def _eval_1_around_sample(self, si, active):
        """``eval_1`` of the lookup around the sample (never the pixel's footprint)."""
        v = self._value(si, active, around_sample=True)
        return mi.luminance(v) if self.channels == 3 else v

    def _exact_gradient(self, si, active):
        tc = self.mapping.map(self.context(si))
        # inverted RGB: eval_1 is the luminance of max(0, 1 - scale·rgb) channel by channel, so
        # each channel's slope counts where that channel is not clipped
        per_channel = self.invert and self.channels == 3
        f, dfds, dfdt = self.filter.gradient(self._state()[0], tc, active, per_channel)
        jac = self.mapping.map(TextureEvalContext.uv_jacobian(si))
        dfdu = (dfds * jac.dsdx + dfdt * jac.dtdx) * self.scale
        dfdv = (dfds * jac.dsdy + dfdt * jac.dtdy) * self.scale
        if self.invert:
            live = 1 - f * self.scale > 0
            dfdu, dfdv = dr.select(live, -dfdu, 0), dr.select(live, -dfdv, 0)
        if per_channel:
            dfdu, dfdv = mi.luminance(dfdu), mi.luminance(dfdv)
        return finite_gradient(mi.Vector2f(dfdu, dfdv))

    # ------------------------------------------------------------------ Mitsuba interface
    @property
    def channels(self) -> int:
        return int(self.data.shape[2])

    def mean(self):
        """The texels' mean, computed where they (or the scale) change: a reduction over the
        image cannot run where Mitsuba or a user asks for it inside a symbolic call or loop (a
        user's BSDF, dr.dispatch: it aborted the process, found in a user trial). A copy: the
        caller may change it in place. (With gradients on the texels or the scale it is in the
        AD graph, as the pyramid is.)"""
        return mi.Float(self._mean)

    def _update_mean(self):
        """:meth:`mean` for the current texels and scale. Without ``invert`` it is linear in the
        scale: the texels' own mean, found once per file's texels (textures of one file share
        it) or per ``data``, times the scale; with ``invert``, a mean of each texel's inverted
        value. A reduction's temporaries go back, as a large build's do."""
        if self.invert:
            self._mean = _luminance_mean(self.data.array, self.channels, self.scale, True)
            release_build_temporaries(self.pyramid)
            return
        cache = self._shared if self._shared is not None else self
        if getattr(cache, 'texel_mean', None) is None:
            cache.texel_mean = _luminance_mean(self.data.array, self.channels, 1.0, False)
            release_build_temporaries(self.pyramid)
        self._mean = cache.texel_mean * self.scale

    def resolution(self):
        return mi.ScalarVector2i(int(self.data.shape[1]), int(self.data.shape[0]))

    def carry_forward_gradient(self) -> list:
        """Forward mode started after the render, in Mitsuba's tutorial order (``dr.forward(
        params[key])`` after ``mi.render``): Dr.Jit then hands the render the texels' derivative
        but not the pyramid's, whose edges from the texels lie outside the render's AD scope, so
        the gradient image was silently zero. Called by ``pbrt_path.render_forward``: where the
        texels carry a derivative that has not reached the pyramid, the pyramid of that
        derivative (the pyramid is linear in the texels) is set as the gradient of the buffer and
        of the aliases the filter's loops read. Returns the variables given a gradient (cleared
        after the render). Forward mode propagated before the render leaves nothing to do; a
        frozen function is left as it is (the checks read values back, which recording
        forbids)."""
        if not dr.grad_enabled(self.data) or dr.flag(dr.JitFlag.FreezingScope):
            return []
        buffer = self.pyramid.buffer
        tangent = dr.detach(dr.grad(self.data))
        if not dr.grad_enabled(buffer) or not bool(dr.any(tangent.array != 0)) or \
                bool(dr.any(dr.grad(buffer) != 0)):
            return []
        pyramid_tangent = build_pyramid(mi.TensorXf(tangent), self._levels).buffer
        targets = [buffer]
        if self._tables is not None:
            targets += [getattr(self._tables, k) for k in type(self._tables).DRJIT_STRUCT]
        targets = [v for v in targets if dr.grad_enabled(v)]
        for v in targets:
            dr.set_grad(v, pyramid_tangent)
        return targets

    def prepare_differentials(self):
        self._footprints = True             # point and bilinear pick levels from now on
        if not self._levels:
            self._rebuild(levels=True)
        return True

    def traverse(self, cb):
        cb.put('data', self.data, mi.ParamFlags.Differentiable)
        cb.put('scale', self.scale, mi.ParamFlags.Differentiable)
        if self._to_uv is not None:
            cb.put('to_uv', self._to_uv, mi.ParamFlags.NonDifferentiable)

    def on_parameters_changed(self, keys):
        if (not keys or 'to_uv' in keys) and self._to_uv is not None:
            self._set_to_uv(self._to_uv)
        if self.invert and (not keys or 'scale' in keys) and \
                not dr.flag(dr.JitFlag.FreezingScope):
            # only invert makes the sampling density depend on the scale (read now, outside
            # any kernel being traced; not while dr.freeze records, which cannot read values
            # back: an emitter's density then keeps the scale read last — its pdf is still the
            # density it samples, only less well matched)
            self._scale_value = float(dr.detach(self.scale)[0])
        if not keys or {'data', 'scale', 'to_uv'} & set(keys):
            self._sampler = None            # rebuilt when an emitter next asks
        if keys and 'data' not in keys:
            if 'scale' in keys:
                self._update_mean()
            return
        t = self.data
        if len(t.shape) != 3 or t.shape[2] not in (1, 3) or min(t.shape[:2]) < 1:
            raise PluginError(f'{self.NAME}: parameter "data": expected shape (H, W, 1) or '
                              f'(H, W, 3), got {tuple(t.shape)}')
        self._check_new_texels()
        self._shared = None
        self.texel_mean = None              # (the texels' own mean, see _update_mean)
        # Texels being differentiated get every level now: forward mode propagates the input's
        # derivative through the pyramid before the render (Mitsuba's recipe), so levels built
        # lazily during the render (under pbrt_path) would miss it.
        self._rebuild(self._levels or dr.grad_enabled(self.data))
        self._update_mean()
        self.describe('resolution', f'{t.shape[1]}x{t.shape[0]}x{t.shape[2]}')

    def _check_new_texels(self):
        """Warnings about texels written through ``params`` (the pyramid replaces non-finite
        texels by 0 and clamps the others to ±TEXEL_LIMIT in any case, as at construction):
        their counts, and a warning when they look like ``bitmap``'s 8-bit codes.

        Mitsuba's ``SceneParameters`` converts whatever is written into ``params['...data']``
        (a TensorXu8 of codes, a numpy uint8 array) to the parameter's type, TensorXf, before the
        plugin is told, so an integer tensor cannot be refused here as it is at construction.
        Texels that are all integers in [0, 255] with some above 1 are what such a write
        leaves; linear radiance can be like that too, so this warns rather than refuses. Skipped
        for tensors with gradients (an optimiser's step), where reading them back would cost a
        synchronisation per step, and while ``dr.freeze`` records, which cannot read them back
        (a frozen step that wrote texels failed to record; found by a review).
        """
        if dr.grad_enabled(self.data) or dr.flag(dr.JitFlag.FreezingScope):
            return
        v = self.data.array                 # reductions on the device: no copy to the host
        finite = dr.isfinite(v)
        counts = [dr.count(~finite), dr.count(finite & (dr.abs(v) > TEXEL_LIMIT))]
        hi, lo = dr.max(v), dr.min(v)
        dr.eval(counts, hi, lo)
        self._warn_nonfinite(int(counts[0][0]))
        warn_clamped(int(counts[1][0]))
        hi, lo = float(hi[0]), float(lo[0])
        if 1 < hi <= 255 and lo >= 0 and bool(dr.all(dr.round(v) == v)):
            mi.Log(mi.LogLevel.Warn,
                   f'{self.NAME}: parameter "data": the new texels are all integers in [0, 255] '
                   f'(max {hi:g}). If they are 8-bit codes as Mitsuba\'s bitmap stores them: '
                   f'{integer_data_message(self.data).split("; accepted: ")[1]}')

    # ------------------------------------------------------------------ emitters, light tracing
    def _set_to_uv(self, to_uv):
        """Rebuild the uv mapping after ``params['...to_uv']`` changed (as ``bitmap``)."""
        if not isinstance(to_uv, mi.ScalarAffineTransform3f):
            raise PluginError(f'{self.NAME}: parameter "to_uv": expected a '
                              f'mi.ScalarAffineTransform3f (as bitmap), got {type(to_uv).__name__}')
        m = to_uv.matrix
        values = [float(m[i][j]) for i in range(3) for j in range(3)]
        if not all(math.isfinite(x) for x in values) or values[6:] != [0.0, 0.0, 1.0]:
            raise PluginError(f'{self.NAME}: parameter "to_uv": expected a finite affine 2D '
                              f'transform (last row 0, 0, 1), got the matrix {values}')
        self.mapping = self.mapping.with_to_uv(to_uv)
        self.describe('mapping', self.mapping.describe())

    def _position_sampler(self) -> PositionSampler:
        sampler = self._sampler
        if sampler is None:
            with self._sampler_lock:
                if self._sampler is None:
                    self._sampler = self._build_position_sampler()
                sampler = self._sampler
        return sampler

    def _build_position_sampler(self) -> PositionSampler:
        axes, why = uv_axes(self.mapping, self.wrap)
        if axes is None:
            mi.Log(mi.LogLevel.Warn,
                   f'{self.NAME}: parameters "mapping"/"to_uv"/"uscale"/"vscale"/"udelta"/'
                   f'"vdelta": position sampling (an area emitter\'s or projector\'s radiance) '
                   f'is not proportional to the texture with {why}; positions are sampled '
                   f'uniformly in uv instead (unbiased, noisier)')
            return PositionSampler(None, None)
        # the texels as the user's tensor holds them (evaluated: reading them is allowed while
        # Mitsuba traces a kernel, which is when an emitter first asks)
        texels = dr.detach(self.data).numpy()
        weights = texel_weights(texels, self._scale_value if self.invert else 1.0, self.invert)
        return PositionSampler(TextureSpaceSampler(weights, self.filter_name == 'point',
                                                   self.wrap), axes)

    def sample_position(self, sample, active=True):
        """A uv position with density ∝ the texture's (zero-footprint) value, and that density
        per unit uv area (see :mod:`mitsuba_pbrt_tex.sampling`)."""
        return self._position_sampler().sample(mi.Point2f(sample), mi.Bool(active))

    def pdf_position(self, p, active=True):
        return self._position_sampler().pdf(mi.Point2f(p), mi.Bool(active))
