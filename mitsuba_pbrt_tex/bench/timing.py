"""Timing helpers shared by the benchmarks: Dr.Jit launches kernels asynchronously, so a time is
only meaningful after ``dr.sync_thread()``; the first call of a kernel includes its compilation,
which is measured and reported separately."""

from __future__ import annotations

import statistics
import time

import drjit as dr


def timed(fn):
    """(result, seconds) of ``fn()`` including all kernels it launched."""
    dr.sync_thread()
    t0 = time.perf_counter()
    out = fn()
    dr.eval(out)
    dr.sync_thread()
    return out, time.perf_counter() - t0


def measure(fns: dict, repeats: int) -> tuple[dict, dict]:
    """Warm each function up once (compile time), then time ``repeats`` rounds, interleaving the
    functions within each round so slow drifts of the machine affect all of them alike.

    Returns ({name: median seconds}, {name: first-call seconds})."""
    first = {name: timed(fn)[1] for name, fn in fns.items()}
    samples = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            samples[name].append(timed(fn)[1])
    return {name: statistics.median(v) for name, v in samples.items()}, first
