"""``python -m mitsuba_pbrt_tex render``: render a scene with progress and write EXR + PNG.

The samples are split into passes (different seeds, images averaged) so that progress can be shown
for a JIT variant, where a render is otherwise one opaque kernel launch. ``pbrt_path`` is told the
*total* sample count, so its texture footprints (scaled by ``max(1/8, 1/√spp)``) are those of one
render with all the samples. The first pass includes Dr.Jit's kernel compilation; its time is
reported separately.
"""

from __future__ import annotations

import os
import sys
import time
import xml.etree.ElementTree as ET

import numpy as np


class RenderError(RuntimeError):
    pass


def scene_inputs(scene_path: str) -> list[str]:
    """Real paths of files a scene XML refers to (``filename`` strings, includes)."""
    folder = os.path.dirname(os.path.abspath(scene_path))
    out = []
    try:
        root = ET.parse(scene_path).getroot()
    except (ET.ParseError, OSError):
        return out
    for el in root.iter():
        if el.tag == 'string' and el.get('name') == 'filename' and el.get('value'):
            out.append(el.get('value'))
        elif el.tag == 'include' and el.get('filename'):
            out.append(el.get('filename'))
    return [os.path.realpath(v if os.path.isabs(v) else os.path.join(folder, v)) for v in out]


def check_output(scene_path: str, out_path: str) -> tuple[str, str]:
    """Validate the output path; returns (exr path, png path)."""
    if not out_path.lower().endswith('.exr'):
        raise RenderError(f'output "{out_path}" must end in .exr (a tone-mapped .png is written '
                          f'beside it)')
    png_path = out_path[:-4] + '.png'
    protected = {os.path.realpath(scene_path)} | set(scene_inputs(scene_path))
    for p in (out_path, png_path):
        if os.path.realpath(p) in protected:
            raise RenderError(f'refusing to overwrite "{p}": it is the scene or one of its inputs')
    return out_path, png_path


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
                variant: str = 'llvm_ad_rgb', progress: bool = True, stream=None) -> dict:
    """Render ``scene_path`` to ``out_path`` (EXR) and a PNG beside it; returns timing info."""
    import mitsuba as mi

    import mitsuba_pbrt_tex as mpt

    stream = stream or sys.stderr
    if not os.path.isfile(scene_path):
        raise RenderError(f'scene "{scene_path}" does not exist')
    exr_path, png_path = check_output(scene_path, out_path)
    mi.set_variant(variant)
    mpt.register()
    t0 = time.perf_counter()
    scene = mi.load_file(scene_path)
    t_load = time.perf_counter() - t0
    sensor = scene.sensors()[0]
    integrator = scene.integrator()
    total = int(spp) if spp else int(sensor.sampler().sample_count())
    if total < 1:
        raise RenderError(f'--spp must be >= 1, got {total}')
    passes, per_pass = _passes(total)
    if hasattr(integrator, 'set_total_spp'):
        integrator.set_total_spp(total)
    acc = None
    t_start = time.perf_counter()
    t_first = None
    for i in range(passes):
        img = np.array(mi.render(scene, spp=per_pass, seed=i), dtype=np.float64)
        if t_first is None:
            t_first = time.perf_counter() - t_start
        acc = img if acc is None else acc + img
        if progress:
            stream.write(_bar(i + 1, passes, time.perf_counter() - t_start))
            stream.flush()
    if progress:
        stream.write('\n')
    image = (acc / passes).astype(np.float32)
    t_render = time.perf_counter() - t_start
    bad = int((~np.isfinite(image)).sum())
    if hasattr(integrator, 'set_total_spp'):
        integrator.set_total_spp(None)

    from .outputs import write_exr, write_png
    names = None
    if image.ndim == 3 and image.shape[2] > 3:       # RGB [+ alpha] + the integrator's AOVs
        aovs = list(integrator.aov_names()) if hasattr(integrator, 'aov_names') else []
        alpha = ['A'] if image.shape[2] - 3 - len(aovs) == 1 else []
        names = ['R', 'G', 'B'] + alpha + aovs
    write_exr(exr_path, image, names)
    write_png(png_path, image[..., :3] if image.ndim == 3 else image)
    info = dict(scene=scene_path, exr=exr_path, png=png_path, spp=total, passes=passes,
                load_s=t_load, first_pass_s=t_first, render_s=t_render, nonfinite=bad,
                shape=tuple(image.shape), variant=variant)
    return info
