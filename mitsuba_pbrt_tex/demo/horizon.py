"""``python -m mitsuba_pbrt_tex demo horizon``: ``scenes/demo.xml`` side by side with what Mitsuba
does today, at equal time.

Left: mode ``mitsuba`` — Mitsuba's ``path`` with ``bitmap`` for the ground and the procedurals
point-sampled — at as many samples per pixel as fit in the time of the right image. Right: mode
``pbrt`` — ``pbrt_path`` at 1 spp with pixel footprints (``footprint="pixel"``, the ground
box-filtered over each pixel) and silhouette samples, the procedurals antialiased as pbrt does.
Times are medians of ``--repeats`` renders after a warm-up render (kernel compilation is not
counted); the spp of the left image is the largest whose measured time does not exceed the right
image's. Writes ``<out>/horizon.png`` and ``<out>/horizon.md`` (the times).
"""

from __future__ import annotations

import os
import textwrap
import time

import numpy as np

from ..cli import output_folder, positive_int


def _scene_path() -> str:
    from .. import scenes
    return os.path.join(os.path.dirname(scenes.__file__), 'demo.xml')


def _timed(scene, spp, repeats):
    import drjit as dr
    import mitsuba as mi
    img = mi.render(scene, spp=spp, seed=0)          # warm-up: compiles the kernels
    times = []
    for r in range(repeats):
        dr.sync_thread()
        t0 = time.perf_counter()
        img = mi.render(scene, spp=spp, seed=1 + r)
        dr.sync_thread()
        times.append(time.perf_counter() - t0)
    return np.array(img)[..., :3], float(np.median(times))


def run(out_dir='renders', width=480, height=270, repeats=3, log=print):
    import mitsuba as mi

    import mitsuba_pbrt_tex as mpt
    mi.set_variant('llvm_ad_rgb')
    mpt.register()
    size = {'width': str(width), 'height': str(height)}
    ours_scene = mi.load_file(_scene_path(), mode='pbrt', **size)
    ours, t_ours = _timed(ours_scene, 1, repeats)
    log(f'pbrt_path, footprint pixel, 1 spp: {t_ours * 1e3:.0f} ms')
    theirs_scene = mi.load_file(_scene_path(), mode='mitsuba', **size)
    spp, best = 1, None
    while True:
        img, t = _timed(theirs_scene, spp, repeats)
        log(f'Mitsuba path + bitmap, {spp} spp: {t * 1e3:.0f} ms')
        if t > t_ours and best is not None:
            break
        best = (spp, img, t)
        if t > t_ours:
            break
        spp *= 2
    spp, theirs, t_theirs = best
    os.makedirs(out_dir, exist_ok=True)
    png = os.path.join(out_dir, 'horizon.png')
    _compose(png, theirs, ours, f'Mitsuba: path + bitmap, {spp} spp, {t_theirs * 1e3:.0f} ms',
             f'mitsuba-pbrt-tex: pbrt_path pixel footprints, 1 spp, {t_ours * 1e3:.0f} ms')
    with open(os.path.join(out_dir, 'horizon.md'), 'w') as f:
        f.write(f'{width}×{height}: Mitsuba path + bitmap {spp} spp {t_theirs * 1e3:.0f} ms; '
                f'pbrt_path footprint pixel 1 spp {t_ours * 1e3:.0f} ms (medians of {repeats} '
                f'renders after a warm-up, {os.cpu_count()} CPU threads).\n')
    log(f'wrote {png}')
    return png


def _compose(path, left, right, left_title, right_title):
    from ..outputs import write_png
    try:
        import matplotlib
        matplotlib.use('Agg')
        import matplotlib.pyplot as plt
    except ImportError:
        write_png(path, np.concatenate([left, np.zeros_like(left[:, :4]), right], 1))
        return

    def srgb(x):
        x = np.clip(x, 0, 1)
        return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)

    h, w = left.shape[:2]
    # titles wrapped to their panel (8 pt at 100 dpi: ~6 pixels a character, 0.14 inch a line),
    # so that narrow renders do not overlap them
    titles = [textwrap.fill(t, max(12, w // 6)) for t in (left_title, right_title)]
    head = 0.08 + 0.14 * max(t.count('\n') + 1 for t in titles)
    fig, axes = plt.subplots(1, 2, figsize=(2 * w / 100, h / 100 + head), dpi=100)
    for ax, img, title in zip(axes, (left, right), titles):
        ax.imshow(srgb(img), interpolation='nearest')
        ax.set_title(title, fontsize=8)
        ax.axis('off')
    fig.subplots_adjust(left=0, right=1, bottom=0, top=(h / 100) / (h / 100 + head), wspace=0.01)
    fig.savefig(path)
    plt.close(fig)


def main(argv=None) -> int:
    from ..cli import command_parser
    ap = command_parser('demo horizon', __doc__)
    ap.add_argument('--out', type=output_folder, default='renders',
                    help='output folder (default renders)')
    ap.add_argument('--width', type=positive_int, default=480, help='image width (pixels)')
    ap.add_argument('--height', type=positive_int, default=270, help='image height (pixels)')
    ap.add_argument('--repeats', type=positive_int, default=3,
                    help='timed renders per method (the median counts)')
    args = ap.parse_args(argv)
    run(args.out, args.width, args.height, args.repeats)
    return 0
