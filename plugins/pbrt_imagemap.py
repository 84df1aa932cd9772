"""pbrt_imagemap — MIP-mapped image texture with point, bilinear, trilinear and EWA filtering.

A drop-in upgrade of Mitsuba's ``bitmap`` (its parameter names are accepted as aliases) with
pbrt-v4's filters (pbrt section 10.4).

| parameter | type | default | meaning | differentiable |
|---|---|---|---|---|
| filename | string | — | image file: OpenEXR (via the OpenEXR package) or anything ``mi.Bitmap`` reads (PNG, JPEG, HDR, PFM, ...) | no |
| bitmap | Bitmap | — | an ``mi.Bitmap`` object instead of a file (runtime only) | no |
| data | tensor | — | texels as a ``TensorXf`` of shape (H, W, 1 or 3), linear (runtime only) | yes |
| filter | string | bilinear | `point`, `bilinear`, `trilinear` or `ewa` | no |
| filter_type | string | — | Mitsuba ``bitmap`` alias of filter: `nearest` (= point) or `bilinear` | no |
| maxanisotropy | float | 8 | `ewa`: the longest axis is at most this many times the shortest (≥ 1) | no |
| sortlookups | boolean | true | `ewa`: filter a large batch of scattered lookups sorted by texture tile, results in the caller's order (identical values, less waiting on memory; not inside symbolic loops/calls, where lookups cannot be reordered) | no |
| wrap | string | repeat | `repeat`, `black`, `clamp`, `mirror` or `octahedralsphere` | no |
| wrap_mode | string | — | Mitsuba ``bitmap`` alias of wrap: `repeat`, `mirror` or `clamp` | no |
| scale | float | 1 | factor applied to every texel value | yes |
| invert | boolean | false | return ``max(0, 1 - scale·value)`` | no |
| encoding | string | sRGB (8/16-bit), linear (float) | decoding of integer images: `sRGB`, `linear` or `gamma G` | no |
| raw | boolean | false | Mitsuba ``bitmap`` alias: true = encoding `linear` | no |
| trilinearwidth | string | v3 | footprint width of point/bilinear/trilinear: `v3` = max abs derivative (pbrt-v3), `v4` = twice that (pbrt-v4) | no |
| format | string | auto | Mitsuba ``bitmap`` storage option, accepted for drop-in use; storage is always float32 | no |
| accel | boolean | true | Mitsuba ``bitmap`` option, accepted for drop-in use; no effect | no |
| (2D mapping) | | | mapping parameters (``to_uv`` included), see the mapping table | no |

Exactly one of ``filename``, ``bitmap``, ``data``. A pbrt name and its ``bitmap`` alias together
are an error.

Orientation: as Mitsuba's ``bitmap`` and OpenImageIO — ``v = 0`` is the first row of the file (the
top), texel centres at ``((i + 0.5)/W, (j + 0.5)/H)``, no flip. pbrt-v4 instead evaluates at
``t' = 1 - t`` (its texture space has t up) but forgets to negate ``dt/dx, dt/dy``, which mirrors
anisotropic EWA footprints; we do not flip, so nothing needs negating (Mitsuba's OBJ loader already
flips v, so images appear upright on OBJ meshes).

Channels: 1-channel images give grey colours and their value as float; RGB images give colours,
and their luminance as float (``eval_1``, as ``bitmap``). Alpha is dropped. ``invert`` clamps at 0
like pbrt; otherwise values are not clamped (parity with ``bitmap``, negative EXR texels survive).

Filters and footprints: ``point`` and ``bilinear`` look up the level the footprint selects, as
pbrt-v4 does. Under Mitsuba's own integrators the footprint is always 0 (they compute no texture
differentials), so they behave exactly as ``bitmap`` ``nearest``/``bilinear`` and their MIP pyramid
is never built; ``pbrt_path`` (or calling ``tex.prepare_differentials()``) builds it.
``trilinear`` and ``ewa`` build it at once. With zero differentials every filter is a bilinear
lookup at level 0 (``point``: the nearest texel).

Lookup order (``sortlookups``): an EWA lookup reads ~40 cache lines, so a batch of lookups at
random places of a large texture waits on memory. Where the batch exists as evaluated arrays — a
call such as ``tex.eval(si)`` from Python, or Mitsuba's wavefront mode — ``ewa`` sorts it by the
32×32-texel tile each lookup falls in, filters it in that order and returns the results in the
caller's order: the same values, 2.5–3.5× faster at random uv on a 1024² texture (``bench
lookups``). Batches under 16384 lookups, batches with fewer than a quarter of their lookups on
levels of 8 MB or more, batches already in coherent order, and lookups traced inside a symbolic
loop or call (a render's kernel) run in the order given. See :mod:`mitsuba_pbrt_tex.lookup_order`.

Gradients: ``data`` and ``scale`` are differentiable through every filter; the pyramid is rebuilt
inside the AD graph by ``parameters_changed`` (``params.update()``), so gradients reach base texels
through coarse levels. ``eval_1_grad`` (for ``bumpmap``) is the gradient of the bilinear
reconstruction at the selected level(s).
"""

import drjit as dr
import mitsuba as mi

from mitsuba_pbrt_tex.differentials import TextureEvalContext
from mitsuba_pbrt_tex.filters import TextureFilter
from mitsuba_pbrt_tex.image import (ENCODING_CHOICES, TEXEL_LIMIT, decode_bitmap, load_image,
                                    parse_encoding, release_build_temporaries, warn_clamped)
from mitsuba_pbrt_tex.mapping import mapping_2d
from mitsuba_pbrt_tex.mipmap import FILTERS, WIDTH_CONVENTIONS, MIPMap, Pyramid
from mitsuba_pbrt_tex.params import PluginError
from mitsuba_pbrt_tex.texture import PbrtTexture
from mitsuba_pbrt_tex.wrap import WRAP_MODES

FORMATS = ('auto', 'variant', 'float16', 'fp16', 'uint8')


class Plugin(PbrtTexture):
    NAME = 'pbrt_imagemap'

    # ------------------------------------------------------------------ parameters
    def configure(self, p):
        self.filter_name = p.enum('filter', 'bilinear', FILTERS, alias='filter_type',
                                  alias_choices={'nearest': 'point', 'bilinear': 'bilinear'})
        self.max_anisotropy = p.float('maxanisotropy', 8.0, lo=1.0)
        self.sort_lookups = p.bool('sortlookups', True)
        self.wrap = p.enum('wrap', 'repeat', WRAP_MODES, alias='wrap_mode',
                           alias_choices={'repeat': 'repeat', 'mirror': 'mirror', 'clamp': 'clamp'})
        self.scale = self.jit_value('scale', p.float('scale', 1.0))
        self.invert = p.bool('invert', False)
        self.width_convention = p.enum('trilinearwidth', 'v3', WIDTH_CONVENTIONS)
        p.enum('format', 'auto', FORMATS)
        p.bool('accel', True)
        self.mapping = mapping_2d(p)
        encoding = self._encoding(p)
        self._load(p, encoding)
        self.describe('source', self.source)
        self.describe('resolution', f'{self.pyramid.width}x{self.pyramid.height}x'
                                    f'{self.pyramid.channels}')
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
        given = [k for k in ('filename', 'bitmap', 'data') if p.has(k)]
        if len(given) != 1:
            raise PluginError(f'{self.NAME}: give exactly one of the parameters "filename", '
                              f'"bitmap", "data" (got {", ".join(given) if given else "none"})')
        source = given[0]
        if source == 'data':
            if encoding is not None and encoding.kind != 'linear':
                raise p.error('encoding', 'applies to 8/16-bit image files only; "data" tensors '
                                          'are linear')
            self.data = self._checked_tensor(p.raw('data'), p)
            self.pyramid, self.source = Pyramid(self.data).prepare(), 'data tensor'
        else:
            if source == 'filename':
                name = p.string('filename', None)
                path = str(mi.file_resolver().resolve(name))
                shared = self._call(lambda: load_image(path, encoding), 'filename')
                self.source = name
            else:
                bmp = p.raw('bitmap')
                if not isinstance(bmp, mi.Bitmap):
                    raise p.error('bitmap', f'expected an mi.Bitmap, got {type(bmp).__name__}')
                img = self._call(lambda: decode_bitmap(bmp, encoding, 'the bitmap'), 'bitmap')
                shared = None
                self.data = mi.TensorXf(img.texels)
                self.pyramid, self.source = Pyramid(self.data).prepare(), 'bitmap object'
                self._warn_nonfinite(img.nonfinite)
            if shared is not None:
                # Our own tensor object (so in-place parameter updates stay ours) over the shared
                # texels, and the shared levels once they are built.
                self.data = mi.TensorXf(shared.pyramid.tensor)
                self._shared = shared.pyramid
                self.pyramid = Pyramid(self.data)
                self.pyramid.share_from(self._shared, levels=False)
                self._warn_nonfinite(shared.nonfinite)
        if self.filter_name in ('trilinear', 'ewa'):
            self._build_levels()

    def _call(self, fn, param):
        try:
            return fn()
        except ValueError as e:
            raise PluginError(f'{self.NAME}: parameter "{param}": {e}') from None

    def _checked_tensor(self, value, p):
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

    def _build_levels(self):
        if self._sharing():
            self.pyramid.share_from(self._shared, levels=True)
        else:
            self.pyramid.build()
        release_build_temporaries(self.pyramid)

    def _sharing(self) -> bool:
        """Does this texture still hold the shared (cached) texels of its file?"""
        shared = getattr(self, '_shared', None)
        return shared is not None and shared.tensor.array.index == self.data.array.index

    def _make_filter(self):
        self.mip = MIPMap(self.pyramid, self.wrap)
        self.filter = TextureFilter(self.mip, self.filter_name, self.max_anisotropy,
                                    WIDTH_CONVENTIONS[self.width_convention], self.sort_lookups)

    # ------------------------------------------------------------------ evaluation
    def _value(self, si, active):
        tc = self.mapping.map(self.context(si))
        v = self.filter(tc, active) * self.scale
        if self.invert:
            v = dr.maximum(0, 1 - v)
        return v

    def evaluate(self, si, kind, active):
        v = self._value(si, active)
        return kind.from_rgb(v) if self.pyramid.channels == 3 else kind.from_float(v)

    def eval_1_grad(self, si, active=True):
        active = mi.Bool(active)
        tc = self.mapping.map(self.context(si))
        f, dfds, dfdt = self.filter.gradient(tc, active)
        jac = self.mapping.map(TextureEvalContext.uv_jacobian(si))
        dfdu = (dfds * jac.dsdx + dfdt * jac.dtdx) * self.scale
        dfdv = (dfds * jac.dsdy + dfdt * jac.dtdy) * self.scale
        if self.invert:
            live = 1 - f * self.scale > 0
            dfdu, dfdv = dr.select(live, -dfdu, 0), dr.select(live, -dfdv, 0)
        return mi.Vector2f(dfdu, dfdv)

    # ------------------------------------------------------------------ Mitsuba interface
    def mean(self):
        base = self.pyramid.base
        if self.pyramid.channels == 3:
            texels = dr.gather(mi.Color3f, base, dr.arange(mi.UInt32, dr.width(base) // 3))
            values = mi.luminance(texels) * self.scale
        else:
            values = base * self.scale
        if self.invert:
            values = dr.maximum(0, 1 - values)
        # summed scaled by 2^-40 (exact, a power of two): texels near float32's maximum
        # (3.4e38) must not overflow the sum of up to 2^40 texels
        return dr.mean(values * 2.0**-40) * 2.0**40

    def resolution(self):
        return mi.ScalarVector2i(self.pyramid.width, self.pyramid.height)

    def prepare_differentials(self):
        if not self.pyramid.built:
            self._build_levels()
        return True

    def traverse(self, cb):
        cb.put('data', self.data, mi.ParamFlags.Differentiable)
        cb.put('scale', self.scale, mi.ParamFlags.Differentiable)

    def on_parameters_changed(self, keys):
        if keys and 'data' not in keys:
            return
        t = self.data
        if len(t.shape) != 3 or t.shape[2] not in (1, 3) or min(t.shape[:2]) < 1:
            raise PluginError(f'{self.NAME}: parameter "data": expected shape (H, W, 1) or '
                              f'(H, W, 3), got {tuple(t.shape)}')
        self.data = self._finite_texels(t)       # as at construction: NaN/inf texels → 0
        had_levels = self.pyramid.built
        self._shared = None
        self.pyramid = Pyramid(self.data).prepare()
        if had_levels:
            self.pyramid.build()
        self.describe('resolution', f'{t.shape[1]}x{t.shape[0]}x{t.shape[2]}')
        self._make_filter()
