"""Benchmarks as smoke tests: they run end to end and produce their outputs (not timed tests)."""

import csv

import numpy as np
import pytest


def test_render_benchmark_quick(tmp_path):
    from mitsuba_pbrt_tex.bench import render
    lines = []
    rows, summary = render.run(['grazing-checker', 'grazing-zoneplate'], quick=True,
                               out_dir=str(tmp_path), log=lines.append)
    assert (tmp_path / 'results.csv').exists() and (tmp_path / 'results.md').exists()
    with open(tmp_path / 'results.csv') as f:
        table = list(csv.DictReader(f))
    assert len(table) == len(rows) > 10
    assert all(np.isfinite(float(r['rmse'])) and float(r['time_s']) > 0 for r in table)
    assert any('equal-error speed-up' in s for s in summary)
    assert any(r['method'].startswith('Mitsuba') for r in table)
    # the reference is cached: a second run does not render it again
    lines.clear()
    render.run(['grazing-checker'], quick=True, out_dir=str(tmp_path), log=lines.append)
    assert not any('reference:' in line for line in lines)
    pytest.importorskip('matplotlib')
    assert (tmp_path / 'charts.png').exists()


def test_lookup_benchmark_runs():
    from mitsuba_pbrt_tex.bench import lookups
    out = []
    rows = lookups.run(size=64, count=4096, repeats=1, out=out.append)
    names = {r['method'] for r in rows}
    assert {'bitmap (bilinear)', 'ewa', 'trilinear'} <= names
    assert all(r['ratio'] > 0 for r in rows)


def test_pyramid_benchmark_runs():
    from mitsuba_pbrt_tex.bench import pyramid
    rows = pyramid.run(lookups=20, out=lambda s: None)
    ours = [r for r in rows if r['pyramid'].startswith('area-box')]
    pbrt = [r for r in rows if r['pyramid'].startswith('lanczos')]
    assert all(r['memory'] <= 1.34 for r in ours)
    assert all(r['rmse_level0'] == 0 for r in ours)
    assert all(p['memory'] > o['memory'] for o, p in zip(ours, pbrt))


def test_inverse_demo_quick(tmp_path):
    from mitsuba_pbrt_tex.demo import inverse
    history, summary = inverse.run(str(tmp_path), iterations=2, res=16, spp=2, target_spp=8,
                                   log=lambda s: None)
    assert set(history) == {m[0] for m in inverse.METHODS}
    for rows in history.values():
        assert all(np.isfinite(r['loss']) and np.isfinite(r['texture_rmse']) for r in rows)
        assert rows[-1]['texture_rmse'] < rows[0]['texture_rmse'] + 1e-3
    assert (tmp_path / 'inverse.csv').exists() and (tmp_path / 'summary.md').exists()


def test_integrator_benchmark_runs():
    from mitsuba_pbrt_tex.bench import integrator
    rows = integrator.run(spp=1, res=(16, 9), repeats=1, out=lambda s: None)
    assert len(rows) == len(integrator.CASES)
    assert all(r['path'] > 0 and r['on'] > 0 and r['off'] > 0 for r in rows)
