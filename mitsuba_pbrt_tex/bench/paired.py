"""Paired timing: two configurations of one scene rendered in turn, each in a process of its own.

Where two methods render the same image — Mitsuba's ``bitmap`` and ``pbrt_imagemap`` with
``filter="bilinear"`` under Mitsuba's ``path`` (the drop-in) — they are at equal error at every
spp, and the equal-error speed-up is their time ratio. Timed one method after the other (as
``bench render`` times its curves), that ratio carries the machine's drift between the two
(±20% on a shared 2-core machine). Here each render of one is followed by a render of the other
and the ratio is taken per pair, so a drift slower than two renders cancels; the order within a
pair alternates.

Each configuration lives in its own process: Dr.Jit traces a symbolic call over every registered
instance of its domain, so a second scene loaded in the same process would be traced into
the first one's kernels and change what is timed. The processes take turns (never render at the
same time) and are started with ``spawn`` (Dr.Jit's thread pool does not survive ``fork``), so a
script that calls ``bench render``'s ``run`` needs Python's ``if __name__ == '__main__':`` guard
(the command line and pytest have it).
"""

from __future__ import annotations

import multiprocessing
from dataclasses import dataclass

import numpy as np


@dataclass
class PairedRatio:
    """Per-pair time ratios (``a`` over ``b``) at one spp: their median and quartiles, and the
    largest difference between the two images at the same seed."""
    spp: int
    median: float
    q1: float
    q3: float
    max_image_diff: float

    def text(self) -> str:
        return f'{self.median:.2f}× ({self.q1:.2f}–{self.q3:.2f})'


def _worker(conn, variant, load, load_args):
    """One configuration: load it, then render on request, ``(spp, seed)`` → (seconds, image)."""
    import mitsuba_pbrt_tex                  # finds libLLVM before Dr.Jit starts
    import mitsuba as mi
    mi.set_variant(variant)
    mitsuba_pbrt_tex.register()
    scene = load(*load_args)
    from .render import _render
    from .timing import timed
    while True:
        msg = conn.recv()
        if msg is None:
            break
        spp, seed = msg
        image, seconds = timed(lambda: _render(scene, spp, seed))
        conn.send((seconds, image))
    conn.close()


class _Renderer:
    """A configuration in a spawned process."""

    def __init__(self, ctx, variant, load, load_args):
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_worker, args=(child, variant, load, load_args),
                                daemon=True)
        self.proc.start()
        child.close()

    def render(self, spp, seed):
        self.conn.send((spp, seed))
        return self.conn.recv()

    def close(self):
        try:
            self.conn.send(None)
        except (BrokenPipeError, OSError):
            pass
        self.proc.join(timeout=60)
        if self.proc.is_alive():
            self.proc.kill()


def paired_ratios(load, args_a, args_b, spp_list, pairs: int, variant: str) -> list:
    """Time ratios ``t_a / t_b`` of configurations ``load(*args_a)`` and ``load(*args_b)`` (each
    a scene; ``load`` picklable) at each spp: two warm-up renders each (compilation), then
    ``pairs`` pairs in alternating order, every pair at its own seed for both."""
    ctx = multiprocessing.get_context('spawn')
    a = _Renderer(ctx, variant, load, args_a)
    b = _Renderer(ctx, variant, load, args_b)
    out = []
    try:
        for spp in spp_list:
            # warm-up: the first render compiles, and the second can too (state a render keeps
            # for the next, e.g. pbrt_path's camera approximation, changes what is traced)
            for seed in (1, 2):
                _, img_a = a.render(spp, seed)
                _, img_b = b.render(spp, seed)
            diff = float(np.max(np.abs(img_a - img_b)))
            ratios = []
            for k in range(pairs):
                seed = 20 + k
                if k % 2:
                    t_b, _ = b.render(spp, seed)
                    t_a, _ = a.render(spp, seed)
                else:
                    t_a, _ = a.render(spp, seed)
                    t_b, _ = b.render(spp, seed)
                ratios.append(t_a / t_b)
            q1, med, q3 = (float(q) for q in np.percentile(ratios, [25, 50, 75]))
            out.append(PairedRatio(spp, med, q1, q3, diff))
    finally:
        a.close()
        b.close()
    return out
