"""``python -m mitsuba_pbrt_tex demo inverse``: recover a texture from grazing-angle renders.

A 64×64 texture, tiled 8×8 on a large plane, is seen by three cameras at grazing angles (3°, 8°
and 20° above the plane). Target images are rendered from the true texture point-sampled (no
footprint: Mitsuba's ``bitmap``-like lookup under ``path``) with many samples, i.e. correct
pixel averages, as a photograph would be. Starting from grey, Mitsuba's Adam then fits the texels
to the targets by gradient descent on the squared image error, with three lookup models:

* ``bitmap + prb`` — what Mitsuba users do today: bilinear lookups, no footprint;
* ``trilinear + pbrt_path`` and ``ewa + pbrt_path`` — our filtered lookups, whose MIP pyramid is
  rebuilt inside the AD graph after every step, so far-away pixels send their gradient to every
  texel of their footprint.

With ``--freeze`` each method is also run with its per-view step (render, loss,
``dr.backward``) frozen by ``dr.freeze`` — parameter updates and ``opt.step()`` outside, as in
Mitsuba's own frozen-optimisation tests — and the summary gives its time per step beside the
unfrozen one.

Written to ``--out``: ``inverse.png`` (loss and texture RMSE per iteration), ``textures.png``
(true, initial and recovered textures, and a target view), ``inverse.csv`` and a summary with
time per iteration and peak memory.
"""

from __future__ import annotations

import csv
import gc
import os
import resource
import sys
import time
from dataclasses import dataclass

import numpy as np

from ..cli import output_folder, positive_float, positive_int
from ..outputs import save_figure

VIEWS = ((0.12, 3.0), (0.35, 8.0), (0.9, 20.0))      # (camera height, look-down angle in degrees)


def true_texture(size=64) -> np.ndarray:
    """Colour blocks with thin lines: low and high frequencies (deterministic)."""
    y, x = (np.mgrid[0:size, 0:size] + 0.5) / size
    img = np.stack([0.2 + 0.6 * (np.floor(x * 4) % 2), 0.2 + 0.6 * (np.floor(y * 4) % 2),
                    0.3 + 0.5 * np.sin(np.pi * x) * np.sin(np.pi * y)], -1)
    lines = ((np.arange(size) % 8) == 0)
    img[lines, :, :] = 0.05
    img[:, lines, :] = 0.05
    return img.astype(np.float32)


def scene_dict(texture: dict, integrator: str, view, res: int):
    import math

    import mitsuba as mi
    T = mi.ScalarTransform4f
    height, angle = view
    target = [0, height - 10 * math.tan(math.radians(angle)), -10]
    return {
        'type': 'scene',
        'integrator': {'type': integrator, 'max_depth': 2},
        'sensor': {'type': 'perspective', 'fov': 50,
                   'to_world': T().look_at([0, height, 4], target, [0, 1, 0]),
                   'film': {'type': 'hdrfilm', 'width': res, 'height': res,
                            'rfilter': {'type': 'box'}},
                   'sampler': {'type': 'independent'}},
        'sun': {'type': 'directional', 'direction': [0.2, -1, -0.4], 'irradiance': 3.0},
        'plane': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(16),
                  'bsdf': {'type': 'diffuse', 'reflectance': texture}},
    }


def texture_dict(kind: str, data):
    import mitsuba as mi
    tiles = mi.ScalarTransform4f().scale([8, 8, 1])
    if kind == 'bitmap':
        return {'type': 'bitmap', 'data': mi.TensorXf(data), 'raw': True, 'to_uv': tiles}
    return {'type': 'pbrt_imagemap', 'data': mi.TensorXf(data), 'filter': kind, 'to_uv': tiles}


METHODS = (('bitmap + prb', 'bitmap', 'prb'), ('trilinear + pbrt_path', 'trilinear', 'pbrt_path'),
           ('ewa + pbrt_path', 'ewa', 'pbrt_path'))


@dataclass(frozen=True)
class Settings:
    """What ``demo inverse`` runs: Adam steps and their rate, the views' resolution, spp per
    view and step, and the targets' spp."""
    iterations: int = 60
    res: int = 64
    spp: int = 4
    target_spp: int = 256
    lr: float = 0.03


KEY = 'plane.bsdf.reflectance.data'


def run(out_dir='demo-out', iterations=60, res=64, spp=4, target_spp=256, lr=0.03,
        variant='llvm_ad_rgb', log=print, freeze=False):
    import mitsuba as mi

    import mitsuba_pbrt_tex as mpt

    mi.set_variant(variant)
    mpt.register()
    os.makedirs(out_dir, exist_ok=True)
    cfg = Settings(iterations, res, spp, target_spp, lr)
    truth = true_texture()
    # ---- targets: the true texture, point-sampled, many samples (correct pixel averages)
    targets = []
    for view in VIEWS:
        scene = mi.load_dict(scene_dict(texture_dict('bilinear', truth), 'path', view, res))
        targets.append(mi.TensorXf(mi.render(scene, spp=target_spp, seed=99)))
    history, finals, frozen_rows = {}, {}, {}
    for label, kind, integrator in METHODS:
        history[label], finals[label] = _fit(cfg, label, kind, integrator, truth, targets,
                                             False, log)
        if freeze:
            frozen_rows[label], _ = _fit(cfg, label + ' (frozen)', kind, integrator, truth,
                                         targets, True, log)
    summary = _report(cfg, history, frozen_rows, out_dir)
    plots(history, truth, finals, np.array(targets[0]), out_dir)
    for line in summary:
        log(line)
    # matplotlib's and Mitsuba's reference cycles can keep the last scenes (and their AD graph)
    # alive until the next collection; release them now for whatever the caller does next
    del targets
    gc.collect()
    return history, summary, frozen_rows


def _step(scene, target, seed, spp):
    """One view's share of an Adam step: render, loss, back-propagation (what dr.freeze
    records with --freeze; parameter updates and opt.step() stay outside, as in Mitsuba's
    frozen-optimisation tests)."""
    import drjit as dr
    import mitsuba as mi
    params = mi.traverse(scene)
    params.keep(KEY)
    img = mi.render(scene, params, spp=spp, seed=seed)
    loss = dr.mean(dr.square(img - target), axis=None)
    dr.backward(loss)
    return loss


def _fit(cfg: Settings, label, kind, integrator, truth, targets, frozen, log):
    """Recover the texture with one method: the history rows and the final texture."""
    import drjit as dr
    import mitsuba as mi
    init = np.full_like(truth, 0.5)
    scenes = [mi.load_dict(scene_dict(texture_dict(kind, init), integrator, v, cfg.res))
              for v in VIEWS]
    params = [mi.traverse(s) for s in scenes]
    opt = mi.ad.Adam(lr=cfg.lr)
    opt[KEY] = params[0][KEY]
    for p in params:
        p.update(opt)
    fn = dr.freeze(_step) if frozen else _step
    rows = []
    t_start = time.perf_counter()
    for it in range(cfg.iterations):
        loss_total = 0.0
        for k, (scene, target) in enumerate(zip(scenes, targets)):
            loss = fn(scene, target, mi.UInt32(it * len(VIEWS) + k), cfg.spp)
            loss_total += float(np.array(loss).ravel()[0])
        opt.step()
        opt[KEY] = dr.clip(opt[KEY], 0.0, 1.0)
        for p in params:
            p.update(opt)
        tex = np.array(params[0][KEY])
        tex_rmse = float(np.sqrt(np.mean((tex - truth) ** 2)))
        rows.append(dict(method=label, iteration=it, loss=loss_total / len(VIEWS),
                         texture_rmse=tex_rmse, seconds=time.perf_counter() - t_start))
        if it % 10 == 0 or it == cfg.iterations - 1:
            log(f'{label:24s} it {it:3d}  image loss {rows[-1]["loss"]:.5f}  '
                f'texture RMSE {tex_rmse:.4f}  {rows[-1]["seconds"]:6.1f} s')
    return rows, np.array(params[0][KEY])


def _report(cfg: Settings, history, frozen_rows, out_dir) -> list:
    """Write inverse.csv and summary.md; the summary's lines."""
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    with open(os.path.join(out_dir, 'inverse.csv'), 'w', newline='') as f:
        w = csv.DictWriter(f, fieldnames=list(history[METHODS[0][0]][0].keys()))
        w.writeheader()
        for rows in history.values():
            w.writerows(rows)
    summary = [f'demo inverse: {cfg.iterations} Adam steps (lr {cfg.lr}), {len(VIEWS)} views at '
               f'{cfg.res}×{cfg.res}, {cfg.spp} spp per view and step, targets '
               f'{cfg.target_spp} spp; peak resident memory {peak_mib:.0f} MiB']
    for label, rows in history.items():
        per_it = rows[-1]['seconds'] / len(rows)
        line = (f'- {label}: final texture RMSE {rows[-1]["texture_rmse"]:.4f}, image loss '
                f'{rows[-1]["loss"]:.5f}, {per_it * 1e3:.0f} ms per step')
        if label in frozen_rows:
            fr = frozen_rows[label]
            # the first steps record the frozen function; the rest replay it
            settled = [b['seconds'] - a['seconds'] for a, b in zip(fr[2:], fr[3:])]
            replayed = (f'{1e3 * sum(settled) / len(settled):.0f} ms per replayed step'
                        if settled else 'too few steps to time a replay: give --iterations 4 or '
                                        'more')
            line += (f'; frozen (dr.freeze): {fr[-1]["seconds"] / len(fr) * 1e3:.0f} ms per step '
                     f'including recording, {replayed}, final texture RMSE '
                     f'{fr[-1]["texture_rmse"]:.4f}')
        summary.append(line)
    with open(os.path.join(out_dir, 'summary.md'), 'w') as f:
        f.write('\n'.join(summary) + '\n')
    return summary


def plots(history, truth, finals, target_view, out_dir):
    try:
        import matplotlib
        matplotlib.use('Agg')
        import matplotlib.pyplot as plt
    except ImportError:
        print('matplotlib is not installed: no plots', file=sys.stderr)
        return
    from ..outputs import tonemap
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for label, rows in history.items():
        its = [r['iteration'] for r in rows]
        axes[0].semilogy(its, [r['loss'] for r in rows], label=label)
        axes[1].plot(its, [r['texture_rmse'] for r in rows], label=label)
    axes[0].set_title('image loss (MSE vs targets)')
    axes[1].set_title('texture RMSE vs the true texture')
    for ax in axes:
        ax.set_xlabel('Adam step')
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    save_figure(fig, os.path.join(out_dir, 'inverse.png'), 100)
    panels = [('true texture', truth), ('initial', np.full_like(truth, 0.5))]
    panels += [(f'recovered: {k}', v) for k, v in finals.items()]
    fig, axes = plt.subplots(1, len(panels) + 1, figsize=(3 * (len(panels) + 1), 3.2))
    for ax, (title, img) in zip(axes, panels):
        ax.imshow(np.clip(img, 0, 1), interpolation='nearest')
        ax.set_title(title, fontsize=8)
        ax.axis('off')
    axes[-1].imshow(tonemap(target_view))
    axes[-1].set_title('target view (3°)', fontsize=8)
    axes[-1].axis('off')
    save_figure(fig, os.path.join(out_dir, 'textures.png'), 100)


def main(argv=None) -> int:
    from ..cli import command_parser
    ap = command_parser('demo inverse', __doc__)
    ap.add_argument('--out', type=output_folder, default='demo-out',
                    help='output folder (default demo-out)')
    ap.add_argument('--iterations', type=positive_int, default=None,
                    help='optimisation steps (default 60; 3 with --quick)')
    ap.add_argument('--res', type=positive_int, default=None,
                    help='film and texture resolution (default 64; 16 with --quick)')
    ap.add_argument('--spp', type=positive_int, default=None,
                    help='samples per pixel of the optimised renders (default 4; 2 with --quick)')
    ap.add_argument('--lr', type=positive_float, default=0.03, help='Adam\'s learning rate')
    ap.add_argument('--freeze', action='store_true',
                    help='also run every method with its render + backward frozen by dr.freeze, '
                         'and report its time per step beside the unfrozen one')
    ap.add_argument('--quick', action='store_true',
                    help='3 iterations at 16×16, 2 spp (smoke test; options given win)')
    args = ap.parse_args(argv)
    q = args.quick                      # options given win (they are >= 1, never falsy)
    run(args.out, args.iterations or (3 if q else 60), args.res or (16 if q else 64),
        args.spp or (2 if q else 4), lr=args.lr, freeze=args.freeze,
        **({'target_spp': 16} if q else {}))
    return 0
