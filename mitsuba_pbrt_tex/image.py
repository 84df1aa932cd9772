"""Reading image files into linear float32 texels, colour decoding, and a thread-safe cache.

Sources:

* OpenEXR files through the ``OpenEXR`` package: channels ``R,G,B``, ``X,Y,Z`` or ``Y`` (plus
  ``A``, which is dropped; names matched case-insensitively, as Mitsuba's reader does; other
  channels ignored), at the top level or, where the top level has none, in the one layer that
  has them (``diffuse.R,G,B``: Mitsuba's ``bitmap`` reads a single-layer file so; several
  colour layers are refused, as ``bitmap`` refuses them). Half and float pixels become float32
  exactly, also mixed in one file. ``X,Y,Z`` (what ``hdrfilm`` writes with
  ``pixel_format="xyz"``) is converted to linear sRGB by Mitsuba's own ``Bitmap.convert``, as
  ``bitmap`` converts it. Files that need Mitsuba's colour handling beyond that — RGB with
  chromaticities other than Rec. 709 (ACES, or the XYZ primaries), luminance/chroma ``Y,RY,BY``
  — are read through ``mi.Bitmap``, which converts them as ``bitmap`` does.
* Every other format Mitsuba reads (PNG, JPEG, HDR, PFM, PPM, TGA, BMP, ...) through ``mi.Bitmap``.

The reader is chosen by the file's first bytes (OpenEXR's magic number), not its extension, as
``mi.Bitmap`` chooses: a PNG named ``.exr`` is read as the PNG it is.

Channels: 1 (``Y``/``YA``) or 3 (``RGB``/``RGBA``/``XYZ``...). Alpha is dropped, as Mitsuba's
``bitmap`` does (a texture here is a colour or a float; use a separate texture for opacity).

Encodings (pbrt-v4's ``encoding`` parameter; applied to 8- and 16-bit integer images only — float
images are linear by definition, as in pbrt-v4 — and to ``mi.Bitmap`` objects flagged sRGB):

* ``sRGB`` — the sRGB transfer curve. 8-bit texels are decoded through a 256-entry table that is
  read back from Mitsuba's own ``bitmap`` (Dr.Jit's C++ ``srgb_to_linear`` is a rational
  approximation, within 4.2e-7 of the exact curve); this makes our texels *identical* to what
  ``bitmap`` filters. 16-bit texels use the exact curve.
* ``linear`` — ``v / 255`` (or ``/ 65535``).
* ``gamma G`` — ``(v / 255)^G``.

Default: ``sRGB`` for 8/16-bit formats, ``linear`` for float formats (pbrt-v4 and Mitsuba agree).
An ``mi.Bitmap`` object says itself: sRGB where its ``srgb_gamma()`` is set (integer or float
pixels), linear where not (``mi.Bitmap`` of a uint16 or float numpy array, or after
``set_srgb_gamma(False)``), as Mitsuba's ``bitmap`` reads it; ``raw`` (= ``linear``) keeps the
stored values of a flagged bitmap, as ``bitmap``'s ``raw`` does (which clears the caller's
flag; ours leaves the caller's bitmap as it is).

Non-finite texels are replaced by 0 with a warning that gives their count, and texels beyond
±1e38 are clamped to ±1e38 (also with a warning): filtering values near float32's maximum
(3.4e38) would overflow.
Decoded files are cached as :class:`SharedImage` objects keyed by (real path, modification
time, size, encoding, variant), weakly: the last texture to let go of a file's texels (deleted,
or given new ``data``) frees them, so nothing accumulates over reloads. Mitsuba constructs
plugins on worker threads and merges identical ones, so several textures may ask for the same
file at once; the cache reads each file once under a per-key lock (the work under it — file
decoding in numpy, one host copy into a Dr.Jit array — launches no kernel, so a waiting worker
cannot starve it), and its pyramids are built once on first request (see
:meth:`SharedImage.pyramid`). The
wrap mode is not part of the key because the pyramid does not depend on it (each coarse texel
averages texels inside the image; see :mod:`mitsuba_pbrt_tex.mipmap`).
"""

from __future__ import annotations

import contextlib
import os
import re
import threading
import weakref
from dataclasses import dataclass

import mitsuba as mi
import numpy as np

from .cache import BuildOnceCache
from .mipmap import TEXEL_LIMIT, Pyramid, build_pyramid, may_wait_for_kernels


class ImageError(ValueError):
    pass


@dataclass(frozen=True)
class Encoding:
    kind: str            # 'sRGB' | 'linear' | 'gamma'
    gamma: float = 1.0

    def __str__(self) -> str:
        return f'gamma {self.gamma:g}' if self.kind == 'gamma' else self.kind


ENCODING_CHOICES = ('sRGB', 'linear', 'gamma G (G > 0)')
_GAMMA_RE = re.compile(r'^gamma\s+([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)$')


def parse_encoding(text: str) -> Encoding | None:
    """``"sRGB"``, ``"linear"`` or ``"gamma 2.2"`` → :class:`Encoding`, None if malformed."""
    if text == 'sRGB':
        return Encoding('sRGB')
    if text == 'linear':
        return Encoding('linear')
    m = _GAMMA_RE.match(text.strip())
    if m and float(m.group(1)) > 0:
        return Encoding('gamma', float(m.group(1)))
    return None


@dataclass
class DecodedImage:
    texels: np.ndarray   # float32, (H, W, C), C in {1, 3}, linear
    encoding: Encoding   # the encoding actually applied ('linear' for float sources)
    bit_depth: str       # 'uint8' | 'uint16' | 'float'
    nonfinite: int       # texels that were replaced by 0


# ---------------------------------------------------------------------------------- decoding
_srgb8_lock = threading.Lock()
_srgb8_tables: dict[str, np.ndarray] = {}


def srgb8_table() -> np.ndarray:
    """The 256 linear values Mitsuba's ``bitmap`` decodes 8-bit sRGB bytes to (per variant).

    :func:`mitsuba_pbrt_tex.register` computes it on the calling thread: building it runs a
    Mitsuba texture lookup, which must not happen inside a plugin constructor on a worker thread
    while other workers wait on the image cache (the pool could deadlock)."""
    variant = mi.variant()
    table = _srgb8_tables.get(variant)
    if table is not None:
        return table
    with _srgb8_lock:
        table = _srgb8_tables.get(variant)
        if table is None:
            ramp = np.repeat(np.arange(256, dtype=np.uint8)[None, :], 2, axis=0)[..., None]
            bmp = mi.Bitmap(ramp, mi.Bitmap.PixelFormat.Y)
            bmp.set_srgb_gamma(True)
            tex = mi.load_dict({'type': 'bitmap', 'bitmap': bmp, 'filter_type': 'nearest',
                                'wrap_mode': 'clamp'})
            si = mi.SurfaceInteraction3f()
            si.uv = mi.Point2f((mi.Float(np.arange(256)) + 0.5) / 256.0, 0.25)
            table = np.array(tex.eval_1(si), dtype=np.float32).reshape(256)
            _srgb8_tables[variant] = table
    return table


def _srgb_exact(v: np.ndarray) -> np.ndarray:
    v = v.astype(np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def decode_integer(raw: np.ndarray, encoding: Encoding) -> np.ndarray:
    """uint8/uint16 texels → linear float32 under ``encoding``."""
    if raw.dtype == np.uint8 and encoding.kind == 'sRGB':
        return srgb8_table()[raw]
    scale = 255.0 if raw.dtype == np.uint8 else 65535.0
    v = raw.astype(np.float64) / scale
    if encoding.kind == 'sRGB':
        v = _srgb_exact(v)
    elif encoding.kind == 'gamma':
        v = v ** encoding.gamma
    return v.astype(np.float32)


# ---------------------------------------------------------------------------------- readers
#: The first 4 bytes of every OpenEXR file.
EXR_MAGIC = b'\x76\x2f\x31\x01'

#: Rec. 709 / sRGB primaries and white (OpenEXR's default chromaticities): RGB files whose
#: ``chromaticities`` differ are read through Mitsuba, which converts them (as ``bitmap`` does).
_REC709 = np.array([0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290])


def _rec709(chroma) -> bool:
    """Whether an OpenEXR ``chromaticities`` attribute (or its absence) means Rec. 709, by
    Mitsuba's test (squared differences summing to under 1e-6)."""
    return chroma is None or float(np.sum((np.asarray(chroma, np.float64) - _REC709) ** 2)) < 1e-6


def is_openexr(path: str) -> bool:
    """Does the file begin with OpenEXR's magic number (whatever its name)?"""
    with open(path, 'rb') as f:
        return f.read(4) == EXR_MAGIC


def _exr_colour_channels(names) -> tuple[str, list[str]] | None:
    """``(kind, channel names)`` that an OpenEXR file's colour is read from: ``RGB``, ``XYZ``,
    ``Y`` or ``YC`` (luminance/chroma) by the channels' suffixes, case-insensitively, as
    Mitsuba's reader classifies them; the top level first, else the one layer that has colour
    channels. None if there are none; :class:`ImageError` if several layers have them."""
    groups: dict[str, dict[str, str]] = {}
    for name in names:
        prefix, _, suffix = name.rpartition('.')
        groups.setdefault(prefix, {})[suffix.lower()] = name

    def colour(g):
        for kind, keys in (('RGB', 'rgb'), ('XYZ', 'xyz'), ('YC', ('y', 'ry', 'by'))):
            if all(k in g for k in keys):
                return kind, [g[k] for k in keys]
        if 'y' in g:
            return ('YC' if 'ry' in g or 'by' in g else 'Y'), [g['y']]
        return None

    if '' in groups and colour(groups['']):
        return colour(groups[''])
    layers = {prefix: colour(g) for prefix, g in groups.items() if prefix and colour(g)}
    if len(layers) > 1:
        raise ImageError(f'has {len(layers)} layers with colour channels '
                         f'({", ".join(sorted(layers))}); expected R,G,B, X,Y,Z or Y at the top '
                         f'level or in one layer (Mitsuba\'s bitmap refuses such files too): '
                         f'write the layer to use into a file of its own')
    return next(iter(layers.values()), None)


def _xyz_to_rgb(xyz: np.ndarray) -> np.ndarray:
    """Linear sRGB of XYZ texels through Mitsuba's own ``Bitmap.convert``, the conversion
    ``bitmap`` applies to an XYZ image (float32 in, float32 out)."""
    bmp = mi.Bitmap(np.ascontiguousarray(xyz, dtype=np.float32), mi.Bitmap.PixelFormat.XYZ)
    return np.array(bmp.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, False),
                    copy=True)


def _read_exr(path: str) -> np.ndarray | None:
    """Texels of an OpenEXR file as float32 (H, W, 1|3); None where Mitsuba's own reader has to
    convert the colours (non-Rec. 709 chromaticities, luminance/chroma). The header decides
    which channels to read, so the pixels are decoded once."""
    import OpenEXR
    try:
        with OpenEXR.File(path, header_only=True) as f:   # (empty once the file is closed)
            names = [c.name for c in f.header().get('channels', [])]
            chroma = f.header().get('chromaticities')
        found = _exr_colour_channels(names)
        if found is None:
            raise ImageError(f'has channels {sorted(names)}; expected R,G,B, X,Y,Z or Y (with '
                             f'or without A; at the top level or in one layer, e.g. diffuse.R, '
                             f'diffuse.G, diffuse.B)')
    except ImageError as e:
        raise ImageError(f'OpenEXR file "{path}" {e}') from None
    except Exception as e:  # the OpenEXR package raises plain exceptions for corrupt files
        raise ImageError(f'cannot read OpenEXR file "{path}": {e}') from None
    kind, wanted = found
    if kind == 'YC' or (kind == 'RGB' and not _rec709(chroma)):
        return None
    try:
        if wanted == ['R', 'G', 'B']:
            # interleaved: RGB(A) comes as one (H, W, 3|4) array, without the copy that
            # stacking separate planes costs (the image's size again, at the peak of a load);
            # channels of one group with different pixel types (float RGB with a half A, say)
            # cannot be interleaved (ValueError): read one by one below
            try:
                with OpenEXR.File(path) as f:
                    channels = {name: ch.pixels for name, ch in f.channels().items()}
                for name in ('RGB', 'RGBA'):
                    if name in channels:
                        return np.asarray(channels.pop(name)[..., :3], dtype=np.float32)
                del channels
            except ValueError:
                pass
        with OpenEXR.File(path, separate_channels=True) as f:
            channels = {name: f.channels()[name].pixels for name in wanted}
    except Exception as e:
        raise ImageError(f'cannot read OpenEXR file "{path}": {e}') from None
    texels = np.stack([np.asarray(channels[n], dtype=np.float32) for n in wanted], axis=-1)
    return _xyz_to_rgb(texels) if kind == 'XYZ' else texels


def _bitmap_pixels(bmp: mi.Bitmap, what: str,
                   encoding: Encoding | None) -> tuple[np.ndarray, bool, Encoding]:
    """(pixels, is_integer, encoding applied) of a ``mi.Bitmap``, alpha dropped: 8/16-bit RGB
    and Y codes as stored (to be decoded under the encoding returned), anything else converted
    by Mitsuba to linear float32 RGB or Y — the conversion ``bitmap`` applies, sRGB decoding
    included where the bitmap is flagged sRGB, unless ``encoding`` says otherwise."""
    pf = mi.Bitmap.PixelFormat
    fmt = bmp.pixel_format()
    comp = bmp.component_format()
    flagged = bmp.srgb_gamma()
    integer = comp in (mi.Struct.Type.UInt8, mi.Struct.Type.UInt16)
    if fmt in (pf.Y, pf.YA):
        target = pf.Y
    elif fmt in (pf.RGB, pf.RGBA):
        target = pf.RGB
    elif fmt in (pf.XYZ, pf.XYZA):
        target, integer = pf.RGB, False
    else:
        raise ImageError(f'{what} has pixel format {fmt}; expected Y, YA, RGB, RGBA, XYZ or XYZA')
    # what the bitmap's values are: sRGB codes where it is flagged so (as Mitsuba's bitmap
    # reads it), else linear, unless the caller's encoding (or raw) says otherwise
    applied = encoding if encoding is not None else Encoding('sRGB' if flagged else 'linear')
    if integer:
        if fmt != target:
            bmp = bmp.convert(target, comp, flagged)       # alpha dropped, codes as stored
    else:
        if not flagged and encoding is not None and encoding.kind != 'linear':
            applied = Encoding('linear')       # float pixels not flagged sRGB are linear
        if flagged and applied.kind != 'sRGB':
            # the stored values, not decoded (bitmap's raw): on a copy, the caller's stays flagged
            bmp = mi.Bitmap(bmp)
            bmp.set_srgb_gamma(False)
        bmp = bmp.convert(target, mi.Struct.Type.Float32, False)
    arr = np.array(bmp, copy=True)
    if arr.ndim == 2:
        arr = arr[..., None]
    if not integer and applied.kind == 'gamma':
        arr = (np.sign(arr) * np.abs(arr) ** applied.gamma).astype(np.float32)
    return arr, integer, applied


def decode_bitmap(bmp: mi.Bitmap, encoding: Encoding | None, what: str) -> DecodedImage:
    """Texels of a ``mi.Bitmap``; ``encoding=None``: as the bitmap is flagged (``srgb_gamma()``:
    sRGB, else linear), as Mitsuba's ``bitmap`` reads it."""
    raw, integer, applied = _bitmap_pixels(bmp, what, encoding)
    if not integer:
        return finish_texels(raw.astype(np.float32), applied, 'float')
    return finish_texels(decode_integer(raw, applied), applied,
                         'uint8' if raw.dtype == np.uint8 else 'uint16')


def read_image(path: str, encoding: Encoding | None) -> DecodedImage:
    """Read and decode ``path``; ``encoding=None`` means the format's default. The reader is
    chosen by the file's content (OpenEXR's magic number), whatever its extension."""
    if not os.path.isfile(path):
        raise ImageError(f'file "{path}" does not exist')
    try:
        exr = is_openexr(path)
    except OSError as e:
        raise ImageError(f'cannot read image file "{path}": {e.strerror}') from None
    if exr:
        texels = _read_exr(path)
        if texels is not None:
            return finish_texels(texels, Encoding('linear'), 'float')
    try:
        bmp = mi.Bitmap(path)
    except Exception as e:
        note = ''
        if not exr and path.lower().endswith('.exr'):
            note = ' (its content is not OpenEXR: it does not begin with OpenEXR\'s magic number)'
        raise ImageError(f'cannot read image file "{path}"{note}: '
                         f'{" ".join(str(e).split())}; expected OpenEXR or a format mi.Bitmap '
                         f'reads (PNG, JPEG, RGBE .hdr, PFM, PPM, TGA, BMP)') from None
    # a file has no sRGB flag of its own: Mitsuba sets one for 8/16-bit formats
    if encoding is None and bmp.component_format() in (mi.Struct.Type.UInt8,
                                                        mi.Struct.Type.UInt16):
        encoding = Encoding('sRGB')
    return decode_bitmap(bmp, encoding, f'image file "{path}"')


def warn_clamped(count: int) -> None:
    if count:
        mi.Log(mi.LogLevel.Warn, f'pbrt_imagemap: {count} texel value(s) beyond ±1e38 clamped to '
                                 f'±1e38 (filtering larger values would overflow float32)')


def finish_texels(texels: np.ndarray, encoding: Encoding, bit_depth: str) -> DecodedImage:
    texels = np.ascontiguousarray(texels, dtype=np.float32)
    if texels.ndim != 3 or texels.shape[2] not in (1, 3) or min(texels.shape[:2]) < 1:
        raise ImageError(f'image has shape {texels.shape}; expected (H, W, 1) or (H, W, 3)')
    bad = ~np.isfinite(texels)
    count = int(bad.sum())
    del bad
    if count:
        texels = np.where(np.isfinite(texels), texels, np.float32(0))
    if texels.size and (texels.max() > TEXEL_LIMIT or texels.min() < -TEXEL_LIMIT):
        clamped = int(np.count_nonzero(texels > TEXEL_LIMIT)
                      + np.count_nonzero(texels < -TEXEL_LIMIT))
        texels = np.clip(texels, -TEXEL_LIMIT, TEXEL_LIMIT)
        warn_clamped(clamped)
    texels.setflags(write=False)
    return DecodedImage(texels, encoding, bit_depth, count)



# ---------------------------------------------------------------------------------- cache
class PyramidSlot:
    """Where the textures of one file read its pyramid: the best one built so far (a Dr.Jit
    struct, so that ``dr.freeze`` sees the pyramid as an input of a frozen function). The file's
    :class:`SharedImage` replaces a level-0 pyramid by the complete one when another texture
    builds it — a change made where a texture is built, never in a lookup — so that no second
    copy of level 0 stays alive."""

    DRJIT_STRUCT = {'pyramid': object}

    def __init__(self, pyramid=None):
        self.pyramid = pyramid


class SharedImage:
    """A decoded file as shared between textures: its texels, how they were decoded, and its
    pyramids (built on first request, once).

    Textures built on different worker threads share it, so a pyramid is built with no lock held
    (Mitsuba constructs plugins on the pool that runs Dr.Jit's kernels: a worker blocked on a
    lock while another waits for a kernel can deadlock it) and evaluated before it is published
    (a lazy expression recorded on one thread must not be extended on another; Dr.Jit's scopes
    are per thread). Two threads may race to build the same pyramid; the first one is kept."""

    def __init__(self, texels: np.ndarray, encoding: Encoding, bit_depth: str, nonfinite: int):
        self.tensor = mi.TensorXf(texels)
        self.encoding, self.bit_depth, self.nonfinite = encoding, bit_depth, nonfinite
        self._complete: Pyramid | None = None     # every level
        self._level0: Pyramid | None = None       # level 0 alone, until a complete one exists
        self._lock = threading.Lock()
        self.slot = PyramidSlot()                 # what textures of this file read
        self.texel_mean = None                    # their mean, found by the first texture

    def built(self, levels: bool) -> Pyramid | None:
        """The pyramid already built that serves a request (a complete one serves both)."""
        with self._lock:
            return self._complete if levels or self._complete is not None else self._level0

    def pyramid(self, levels: bool) -> Pyramid:
        """The file's pyramid: every level, or (``levels`` false) at least level 0."""
        pyr = self.built(levels)
        if pyr is not None:
            return pyr
        pyr = build_pyramid(self.tensor, levels)
        release_build_temporaries(pyr)
        with self._lock:
            if levels:
                self._complete = self._complete or pyr
                self._level0 = None          # the complete one serves level-0 requests now
            else:
                self._level0 = self._level0 or pyr
            self.slot.pyramid = self._complete or self._level0
            return self._complete or self._level0


def _pack(key, shared: SharedImage, forget):
    """Cache entries hold the decoded file weakly: it lives as long as a texture holds it."""
    return weakref.ref(shared, lambda _: forget())


image_cache = BuildOnceCache(_pack, lambda ref: ref())

# ---------------------------------------------------------------------------------- files read
_recorders_lock = threading.Lock()
_recorders: list[set] = []


@contextlib.contextmanager
def files_read():
    """Collect the real paths of the image files textures read (cached or not) inside the
    ``with`` block, from any thread: ``python -m mitsuba_pbrt_tex render`` refuses outputs
    that would overwrite one of them."""
    found: set[str] = set()
    with _recorders_lock:
        _recorders.append(found)
    try:
        yield found
    finally:
        with _recorders_lock:
            _recorders.remove(found)


def _note_read(path: str) -> None:
    with _recorders_lock:
        for found in _recorders:
            found.add(os.path.realpath(path))


#: A pyramid at least this large gives the memory its build used back to the system afterwards.
RELEASE_BYTES = 16 * 2**20


def release_build_temporaries(pyramid: Pyramid) -> None:
    """After building a large pyramid: wait for the build's kernels and flush Dr.Jit's
    allocation cache, which would otherwise keep the build's temporaries (the RGBA copy that the
    levels' buffer replaces, the half-downsampled levels: 1.4× the image for RGB) resident until
    something reuses them. On the main thread only (:func:`~.mipmap.may_wait_for_kernels`)."""
    if pyramid.nbytes() >= RELEASE_BYTES and may_wait_for_kernels():
        import drjit as dr
        dr.sync_thread()
        dr.flush_malloc_cache()


def file_key(path: str) -> tuple:
    """What identifies a file's contents for the cache: its real path, inode, size and times —
    the status-change time too, which every write moves and no tool sets back (``cp -p``,
    ``rsync -t`` and ``tar x`` restore the modification time of an edited file)."""
    real = os.path.realpath(path)
    st = os.stat(real)
    return real, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns


def load_image(path: str, encoding: Encoding | None) -> SharedImage:
    """The texels of ``path`` as a :class:`SharedImage` (read once per file, encoding and
    variant; the key includes the file's times, so edited files are re-read)."""
    if not os.path.isfile(path):
        raise ImageError(f'file "{path}" does not exist')
    _note_read(path)
    key = (file_key(path), None if encoding is None else str(encoding), mi.variant())

    def build():
        img = read_image(path, encoding)
        return SharedImage(img.texels, img.encoding, img.bit_depth, img.nonfinite)

    return image_cache.get(key, build)
