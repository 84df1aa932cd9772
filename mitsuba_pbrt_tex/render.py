"""``python -m mitsuba_pbrt_tex render``: render a scene with progress and write EXR + PNG.

The samples are split into passes (different seeds, images averaged) so that progress can be shown
for a JIT variant, where a render is otherwise one opaque kernel launch. ``pbrt_path`` is told the
*total* sample count, so its texture footprints (scaled by ``max(1/8, 1/√spp)``) are those of one
render with all the samples. The first pass includes Dr.Jit's kernel compilation; its time is
reported separately.
"""

from __future__ import annotations

import os
import re
import sys
import tempfile
import time
import xml.etree.ElementTree as ET

import numpy as np


class RenderError(RuntimeError):
    pass


# ------------------------------------------------------------------------------ scene inputs
_VAR_RE = re.compile(r'\$([A-Za-z_][A-Za-z0-9_]*)')
_NUMBERS_RE = re.compile(r'^[-+0-9.eE,\s]*$')          # "0.5", "0, 1, 0": not file names
_NOT_PATHS = ('type', 'version', 'name', 'id')        # identifiers, never read as files


def _resolver_dirs() -> list[str]:
    """The folders of Mitsuba's file resolver (when a variant is set), in search order."""
    try:
        import mitsuba as mi
        return [str(p) for p in mi.file_resolver()] if mi.variant() else []
    except Exception:          # pragma: no cover - no variant/resolver: the other folders remain
        return []


def _candidates(value: str, folders: list[str]) -> list[str]:
    if os.path.isabs(value):
        return [value]
    return [os.path.join(f, value) for f in folders] + [os.path.abspath(value)]


def scene_inputs(scene_path: str, params: dict | None = None) -> set[str]:
    """Real paths of every existing file the scene XML may read, as Mitsuba's loader finds them:
    ``params`` (the command line's ``-D``) or else ``<default>`` values substituted for
    ``$name`` in every attribute, ``<include>``d files followed (recursively), and every
    attribute value looked up like the file resolver does (``<path>`` folders, the scene's
    folder, the resolver's folders, the working directory). Any attribute that names an existing
    file counts, whatever the parameter: protecting too much only refuses an output name,
    protecting too little loses a user's file."""
    scene_path = os.path.abspath(scene_path)
    found: set[str] = {os.path.realpath(scene_path)}
    defaults: dict[str, str] = dict(params or {})
    extra_dirs: list[str] = []
    seen_docs: set[str] = set()
    roots = []

    def read(path):
        real = os.path.realpath(path)
        if real in seen_docs:
            return
        seen_docs.add(real)
        try:
            root = ET.parse(path).getroot()
        except (ET.ParseError, OSError):
            return                      # Mitsuba reports this file when it loads the scene
        roots.append((path, root))
        for el in root.iter('default'):     # (its value substituted as Mitsuba parses it)
            if el.get('name') is not None and el.get('value') is not None:
                defaults.setdefault(el.get('name'), _replaced(el.get('value'), defaults))
        for el in root.iter('path'):            # <path value="..."/> extends the resolver
            for value in substituted(el.get('value') or ''):
                if value:
                    extra_dirs.extend(_candidates(value, [os.path.dirname(scene_path)]))
        for el in root.iter('include'):
            for value in substituted(el.get('filename') or ''):
                for c in _candidates(value, folders(path)) if value else ():
                    if os.path.isfile(c):
                        read(c)

    def substituted(value: str) -> set[str]:
        """``value`` with the parameters substituted, every way Mitsuba might: its loader
        replaces the text ``$name`` for each parameter in turn (so ``$wx`` reads ``$w``'s
        value when only ``w`` is given, and any name works, also ``1img`` or ``my-mode``);
        a whole-word substitution too. Protecting too much only refuses an output name."""
        return {_VAR_RE.sub(lambda m: defaults.get(m.group(1), m.group(0)), value),
                _replaced(value, defaults, list(defaults)), _replaced(value, defaults)}

    def folders(doc_path):
        base = [os.path.dirname(scene_path), os.path.dirname(os.path.abspath(doc_path))]
        return extra_dirs + base + _resolver_dirs()

    read(scene_path)
    for doc, root in roots:
        for el in root.iter():
            for attr, value in el.attrib.items():
                if attr in _NOT_PATHS:
                    continue
                for value in substituted(value):
                    value = value.strip()
                    if not value or len(value) > 4096 or _NUMBERS_RE.match(value):
                        continue
                    for c in _candidates(value, folders(doc)):
                        if os.path.isfile(c):
                            found.add(os.path.realpath(c))
    return found


def _replaced(value: str, params: dict, order=None) -> str:
    """``value`` with the text ``$name`` replaced by each parameter's value in turn (``order``,
    by default the longest names first), as Mitsuba's loader substitutes."""
    for name in order if order is not None else sorted(params, key=len, reverse=True):
        value = value.replace('$' + name, params[name])
    return value


# ------------------------------------------------------------------------------ outputs
def output_paths(out_path: str) -> tuple[str, str]:
    """(exr path, png path) for ``-o``."""
    if not out_path.lower().endswith('.exr'):
        raise RenderError(f'output "{out_path}" must end in .exr (a tone-mapped .png is written '
                          f'beside it)')
    return out_path, out_path[:-4] + '.png'


def check_writable(path: str) -> list[str]:
    """Can ``path`` be written (atomically: a file created in its folder, renamed over it)?
    Missing folders are created here, before rendering; a probe file is created and removed.
    Returns the folders it created (innermost first: :func:`remove_empty`)."""
    if os.path.isdir(path):
        raise RenderError(f'cannot write "{path}": it is a directory')
    folder = os.path.dirname(os.path.abspath(path))
    created, up = [], folder
    while not os.path.lexists(up) and os.path.dirname(up) != up:
        created.append(up)
        up = os.path.dirname(up)
    probe = None
    try:
        os.makedirs(folder, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix='.tmp-', suffix='.probe', dir=folder)
        os.close(fd)
    except OSError as e:
        reason = e.strerror or str(e)
        if isinstance(e, (FileExistsError, NotADirectoryError)):
            reason = 'a part of the folder path is a file, not a folder'
        raise RenderError(f'cannot write "{path}": cannot create a file in "{folder}": '
                          f'{reason}') from None
    finally:
        if probe is not None:
            os.unlink(probe)
    if os.path.exists(path) and not os.access(path, os.W_OK):
        raise RenderError(f'cannot write "{path}": the file exists and is read-only')
    return created


def remove_empty(folders) -> None:
    """Remove those of ``folders`` (innermost first) that are still empty: what
    :func:`check_writable` created for a render that then failed."""
    for folder in folders:
        try:
            os.rmdir(folder)
        except OSError:             # not empty, or gone: keep going outwards
            pass


def check_not_inputs(paths, inputs: set[str]) -> None:
    """None of ``paths`` is one of ``inputs`` — by path, or as the same file under another
    name (a hard link)."""
    for p in paths:
        same = os.path.realpath(p) in inputs or (
            os.path.exists(p) and any(os.path.exists(i) and os.path.samefile(p, i)
                                      for i in inputs))
        if same:
            raise RenderError(f'refusing to overwrite "{p}": it is the scene or one of its inputs')


def check_png_twin(png_path: str) -> None:
    """The ``.png`` written beside the ``.exr`` named by ``-o`` may replace only an earlier
    render's (marked by :func:`~mitsuba_pbrt_tex.outputs.write_png`), never a file of yours
    that happens to have that name."""
    from .outputs import written_by_us
    if os.path.isfile(png_path) and not written_by_us(png_path):
        raise RenderError(f'refusing to overwrite "{png_path}" (the .png written beside the .exr): '
                          f'it exists and is not an earlier render of this command; choose '
                          f'another -o or move the file')


def check_output(scene_path: str, out_path: str) -> tuple[str, str]:
    """Validate the output path against the scene's XML inputs; returns (exr path, png path)."""
    exr_path, png_path = output_paths(out_path)
    check_not_inputs((exr_path, png_path), scene_inputs(scene_path))
    return exr_path, png_path


# ------------------------------------------------------------------------------ errors
_AT_RE = re.compile(r'At (.*? \(line \d+, col \d+\))')
_OURS_RE = re.compile(r'^(?:\w+\.)*(?:PluginError|ImageError|UnsupportedVariantError): (.*)$',
                      re.M)


def _chain(e: BaseException) -> list:
    """``e`` and the exceptions it was raised from (Dr.Jit's wrappers — a loop's, a custom
    operation's — carry the real error as their cause and say only "see above")."""
    out = []
    while e is not None and e not in out:
        out.append(e)
        e = e.__cause__ or (None if e.__suppress_context__ else e.__context__)
    return out


def error_line(e: BaseException) -> str:
    """One line for an exception Mitsuba raised while loading/rendering: our plugin's message
    (with the scene position) when a plugin of ours refused a parameter — also where it is the
    cause of a wrapper's error — Mitsuba's own message otherwise (the innermost one where the
    outer only points at it), without the C++ source position and without the Python
    traceback."""
    chain = _chain(e)
    at = _AT_RE.search(str(e))
    for link in chain:
        ours = _OURS_RE.findall(f'{type(link).__name__}: {link}') or _OURS_RE.findall(str(link))
        if ours:
            msg = ours[-1].strip()
            return f'{at.group(1)}: {msg}' if at else msg
    text = str(chain[-1] if '(see above)' in str(e) else e)
    text = text.split('Traceback (most recent call last)')[0]
    text = re.sub(r'\[[\w.]+:\d+\]\s*', '', text)
    text = ' '.join(text.split()).rstrip(':')
    return text or type(e).__name__


def _set_variant(variant: str) -> None:
    import mitsuba as mi

    from .variants import variant_problem
    problem = variant_problem(variant)
    if problem:
        raise RenderError(f'--variant {variant}: {problem}')
    try:
        mi.set_variant(variant)
    except Exception as e:
        raise RenderError(f'--variant {variant} cannot be used here: {error_line(e)}') from None


#: samples per pixel at most (Mitsuba's samplers count them in 32 bits)
MAX_SPP = 2**32 - 1


def _passes(spp: int) -> tuple[int, int]:
    for n in (8, 4, 2):
        if spp % n == 0 and spp >= n:
            return n, spp // n
    return 1, spp


def _bar(done: int, total: int, elapsed: float, width: int = 30) -> str:
    filled = int(round(width * done / total))
    return f'\rrendering [{"#" * filled}{"." * (width - filled)}] {done}/{total} passes, ' \
           f'{elapsed:6.1f} s'


def render_file(scene_path: str, out_path: str, spp: int | None = None,
                variant: str = 'llvm_ad_rgb', progress: bool = True, stream=None,
                params: dict | None = None) -> dict:
    """Render ``scene_path`` to ``out_path`` (EXR) and a PNG beside it; returns timing info.
    ``params``: values for the scene's ``$name`` parameters (over its ``<default>`` values), as
    Mitsuba's ``-D name=value``."""
    stream = stream or sys.stderr
    if spp is not None and int(spp) < 1:
        raise RenderError(f'--spp must be >= 1, got {spp}')
    if spp is not None and int(spp) > MAX_SPP:
        raise RenderError(f'--spp must be <= {MAX_SPP} (the sampler counts samples in 32 bits), '
                          f'got {spp}')
    if os.path.isdir(scene_path):
        raise RenderError(f'scene "{scene_path}" is a directory; give the scene\'s XML file')
    if not os.path.isfile(scene_path):
        raise RenderError(f'scene "{scene_path}" does not exist')
    exr_path, png_path = output_paths(out_path)
    created = []
    for p in (exr_path, png_path):          # before anything slow: a render must not be lost
        created += check_writable(p)
    try:
        return _load_and_render(scene_path, exr_path, png_path, spp, variant, progress, stream,
                                params)
    except BaseException:
        remove_empty(created)               # a failed render leaves no folder behind
        raise


def _load_and_render(scene_path, exr_path, png_path, spp, variant, progress, stream,
                     params) -> dict:
    """:func:`render_file` once the outputs are known to be writable."""
    import mitsuba as mi

    import mitsuba_pbrt_tex as mpt

    _set_variant(variant)
    mpt.register()
    params = dict(params or {})
    inputs = scene_inputs(scene_path, params)   # with this variant's file resolver
    check_not_inputs((exr_path, png_path), inputs)
    check_png_twin(png_path)
    from .image import files_read
    t0 = time.perf_counter()
    try:
        with files_read() as read:
            scene = mi.load_file(scene_path, **params)
    except Exception as e:
        raise RenderError(error_line(e)) from None
    t_load = time.perf_counter() - t0
    check_not_inputs((exr_path, png_path), inputs | read)    # what our plugins actually read
    if not scene.sensors():
        raise RenderError(f'scene "{scene_path}" has no sensor: add a <sensor> (a camera)')
    total, passes, per_pass = _sample_plan(scene.sensors()[0], spp)
    image, names, t_first, t_render = _render_passes(scene, total, passes, per_pass, progress,
                                                     stream)
    _write_outputs(exr_path, png_path, image, names)
    return dict(scene=scene_path, exr=exr_path, png=png_path, spp=total, passes=passes,
                load_s=t_load, first_pass_s=t_first, render_s=t_render,
                nonfinite=int((~np.isfinite(image)).sum()), shape=tuple(image.shape),
                variant=variant)


def _sample_plan(sensor, spp):
    """(total spp, passes, spp per pass): ``--spp`` or the scene's sampler, in passes that
    Dr.Jit can render at once."""
    total = int(spp) if spp is not None else int(sensor.sampler().sample_count())
    if total < 1:
        raise RenderError(f"the scene's sampler has sample_count {total}; give --spp >= 1")
    passes, per_pass = _passes(total)
    size = sensor.film().crop_size()
    pixels = int(size[0]) * int(size[1])
    if pixels < 1:              # (Mitsuba's film takes a width or height of 0)
        raise RenderError(f"the film's size is {size[0]}x{size[1]}: give it a width and a "
                          f"height >= 1")
    if per_pass * pixels >= 2**32:
        where = '--spp' if spp is not None else "the scene's sample_count"
        raise RenderError(f'{where} {total} is too many for one image of {size[0]}x{size[1]}: a '
                          f'pass of {per_pass} samples per pixel needs {per_pass * pixels} '
                          f'samples at once, and Dr.Jit renders at most 2^32 - 1')
    return total, passes, per_pass


def _render_passes(scene, total, passes, per_pass, progress, stream):
    """(the mean image of the passes, its channel names, time of the first pass, total time);
    the integrator's footprint follows the total spp (``set_total_spp``) while it renders."""
    import mitsuba as mi
    integrator = scene.integrator()
    if hasattr(integrator, 'set_total_spp'):
        integrator.set_total_spp(total)
    acc = None
    t_start = time.perf_counter()
    t_first = None
    try:
        for i in range(passes):
            mi.render(scene, spp=per_pass, seed=i)
            img, names = film_image(scene.sensors()[0].film())
            if t_first is None:
                t_first = time.perf_counter() - t_start
            acc = img if acc is None else acc + img
            if progress:
                stream.write(_bar(i + 1, passes, time.perf_counter() - t_start))
                stream.flush()
    except Exception as e:
        raise RenderError(f'rendering failed: {error_line(e)}') from None
    finally:
        if hasattr(integrator, 'set_total_spp'):
            integrator.set_total_spp(None)
    if progress:
        stream.write('\n')
    return (acc / passes).astype(np.float32), names, t_first, time.perf_counter() - t_start


def film_image(film) -> tuple[np.ndarray, list[str]]:
    """The film's developed image (H, W, C) and its channels' names, as Mitsuba's own command
    line writes them (``film.bitmap()``): the pixel format's — R, G, B [, A], Y [, A], X, Y, Z
    [, A] — then the AOVs'. (The tensor ``mi.render`` returns holds the channels of Mitsuba's
    ``aov`` integrator in another order than the film names them.)"""
    bmp = film.bitmap()
    image = np.array(bmp, dtype=np.float64)
    return image.reshape(image.shape[:2] + (-1,)), [c.name for c in bmp.struct_()]


def display_rgb(image: np.ndarray, names: list[str]) -> np.ndarray:
    """Linear sRGB for the PNG from the film's base channels: RGB as they are, XYZ converted
    (Mitsuba's ``xyz_to_srgb``), luminance Y as grey."""
    import mitsuba as mi
    if names[:3] == ['R', 'G', 'B']:
        return image[..., :3]
    if names[:3] == ['X', 'Y', 'Z']:
        xyz = image[..., :3].reshape(-1, 3).astype(np.float32)
        rgb = mi.xyz_to_srgb(mi.Color3f(*(mi.Float(xyz[:, i]) for i in range(3))))
        return np.stack([np.array(rgb[i]) for i in range(3)], -1).reshape(image.shape[:2] + (3,))
    return np.repeat(image[..., :1], 3, axis=2)


def _write_outputs(exr_path, png_path, image, names):
    """The EXR (every channel, named as the film names it) and the tone-mapped PNG."""
    from .outputs import write_exr, write_png
    try:
        write_exr(exr_path, image, names)
        write_png(png_path, display_rgb(image, names))
    except Exception as e:
        raise RenderError(f'writing the image failed: {error_line(e)}') from None
