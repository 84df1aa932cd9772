"""``python -m mitsuba_pbrt_tex bench lookups``: texture lookups per second, ours vs ``bitmap``.

One random RGB float32 texture (1024² by default), one batch of random uv with anisotropic
footprints (``--anisotropy`` : 1, minor axis ``--minor`` texels, random orientation), evaluated
by Mitsuba's ``bitmap`` (bilinear, the same texels) and by ``pbrt_imagemap`` with each filter,
in the same process, interleaved, median of ``--repeats`` runs after a warm-up that compiles the
kernels. Prints millions of lookups per second and the ratio to ``bitmap``.

``box`` (the exact footprint average) is timed in the order given (it never sorts).

Point and bilinear are timed twice: as under Mitsuba's integrators (no pyramid: level 0, like
``bitmap``) and as under ``pbrt_path`` (the level the footprint selects). EWA is timed twice as
well: as this call gets it (the batch is evaluated, so ``ewa`` filters it sorted by texture tile,
see :mod:`mitsuba_pbrt_tex.lookup_order`) and in the order given (``sortlookups`` false), which is
what it costs inside a render's kernel, where lookups cannot be reordered.

At random uv the filters are bound by memory latency, so the run also counts, for a sample of
the same lookups, the distinct 64-byte cache lines (4 RGBA texels of a row) each lookup reads:
EWA's count over ``bitmap``'s bounds the ratio EWA in the given order could reach if both paid
the same per line. It then times EWA again for larger minor axes (``--sweep``): the same
ellipses in texels of coarser levels — the same number of texels and cache lines per lookup, on
levels a quarter the size per step — which separates what the filter costs from what the memory
holding its level costs.
"""

from __future__ import annotations

import functools
import math

import numpy as np

#: EWA without sorting the batch by texture tile: as inside a render's kernel.
GIVEN_ORDER = 'ewa (given order, as in a render kernel)'
TARGETS = {'point (level 0)': 1.0, 'bilinear (level 0)': 1.0, 'trilinear': 0.5, 'ewa': 0.05}


class _Batch:
    """``count`` lookups at random (or raster-order, ``coherent``) uv with footprints of
    ``anisotropy``:1 at random orientations; :meth:`set_minor` sets their minor axis."""

    def __init__(self, rng, size, count, anisotropy, coherent):
        import drjit as dr
        import mitsuba as mi
        self.size, self.count, self.anisotropy = size, count, anisotropy
        self.si = dr.zeros(mi.SurfaceInteraction3f, count)
        if coherent:
            # neighbouring lookups at neighbouring texels, as neighbouring pixels of a render: a
            # raster of the texture, one lookup per cell, jittered within the cell
            side = int(math.ceil(math.sqrt(count)))
            k = np.arange(count)
            self.u = (k % side + rng.random(count)) / side
            self.v = (k // side + rng.random(count)) / side
        else:
            self.u, self.v = rng.random(count), rng.random(count)
        self.si.uv = mi.Point2f(self.u.astype(np.float32), self.v.astype(np.float32))
        self.ang = rng.uniform(0, math.pi, count)

    def footprints(self, minor):
        """The derivative vectors of the footprints with this minor axis (texels)."""
        major_len, minor_len = self.anisotropy * minor / self.size, minor / self.size
        return (np.stack([major_len * np.cos(self.ang), major_len * np.sin(self.ang)], 1),
                np.stack([-minor_len * np.sin(self.ang), minor_len * np.cos(self.ang)], 1))

    def set_minor(self, minor):
        import drjit as dr
        import mitsuba as mi
        d0, d1 = self.footprints(minor)
        self.si.duv_dx = mi.Vector2f(d0[:, 0].astype(np.float32), d0[:, 1].astype(np.float32))
        self.si.duv_dy = mi.Vector2f(d1[:, 0].astype(np.float32), d1[:, 1].astype(np.float32))
        dr.eval(self.si)


def _textures(texels, max_anisotropy):
    """Mitsuba's bitmap and every filter of ours on the same texels (name → texture)."""
    import mitsuba as mi
    textures = {'bitmap (bilinear)': mi.load_dict(
        {'type': 'bitmap', 'data': mi.TensorXf(texels), 'raw': True, 'filter_type': 'bilinear'})}
    for name, filt, prepare in (('point (level 0)', 'point', False),
                                ('point (MIP level)', 'point', True),
                                ('bilinear (level 0)', 'bilinear', False),
                                ('bilinear (MIP level)', 'bilinear', True),
                                ('trilinear', 'trilinear', True), ('ewa', 'ewa', True),
                                (GIVEN_ORDER, 'ewa', True), ('box', 'box', True)):
        tex = mi.load_dict({'type': 'pbrt_imagemap', 'data': mi.TensorXf(texels), 'filter': filt,
                            'maxanisotropy': max_anisotropy,
                            'sortlookups': name != GIVEN_ORDER})
        if prepare:
            tex.prepare_differentials()
        textures[name] = tex
    return textures


def run(size=1024, count=1 << 20, anisotropy=8.0, minor=1.5, repeats=7, variant='llvm_ad_rgb',
        max_anisotropy=8.0, seed=1, coherent=False, out=print, sweep=(3.0, 6.0, 12.0)):
    import mitsuba as mi

    import mitsuba_pbrt_tex as mpt
    from .timing import measure

    mi.set_variant(variant)
    mpt.register()
    rng = np.random.default_rng(seed)
    texels = rng.random((size, size, 3), dtype=np.float32)
    batch = _Batch(rng, size, count, anisotropy, coherent)
    batch.set_minor(minor)
    fns = {name: (lambda t=tex: t.eval(batch.si))
           for name, tex in _textures(texels, max_anisotropy).items()}
    times, first = measure(fns, repeats)
    base = times['bitmap (bilinear)']
    order = 'coherent (raster order)' if coherent else 'random'
    out(f'lookups: {count} per batch at {order} uv, {size}x{size} RGB float32, footprints '
        f'{anisotropy:g}:1 (minor axis {minor:g} texels, random orientation), maxanisotropy '
        f'{max_anisotropy:g}, variant {variant}, median of {repeats}')
    out('| method | ms / batch | M lookups/s | vs bitmap | target | first call (compile) ms |')
    out('|---|---|---|---|---|---|')
    rows = []
    for name, t in times.items():
        ratio = base / t
        target = TARGETS.get(name)
        mark = '' if target is None else f'≥ {target:g}× ' + ('(met)' if ratio >= target else '(MISSED)')
        out(f'| {name} | {t * 1e3:.2f} | {count / t / 1e6:.1f} | {ratio:.3f}× | {mark} | '
            f'{first[name] * 1e3:.0f} |')
        rows.append(dict(method=name, ms=t * 1e3, mlookups=count / t / 1e6, ratio=ratio,
                         target=target, first_ms=first[name] * 1e3))
    if not coherent:
        rows += _ewa_by_level(batch, fns, minor, sweep, max_anisotropy, repeats, out)
    return rows


def _ewa_by_level(batch, fns, minor, sweep, max_anisotropy, repeats, out):
    """EWA's cache lines per lookup against bilinear's, and (``sweep``) EWA's time on the same
    ellipses at coarser levels: the rows for those runs."""
    from .timing import measure
    size, count, anisotropy = batch.size, batch.count, batch.anisotropy
    sample = slice(0, min(count, 2000))
    u, v = batch.u[sample], batch.v[sample]

    @functools.cache
    def ewa_lines(m):
        d0, d1 = batch.footprints(m)
        return cache_lines_ewa(size, u, v, d0[sample], d1[sample], max_anisotropy).mean()

    bilinear_lines = cache_lines_bilinear(size, u, v).mean()
    lines = ewa_lines(minor)
    out(f'cache lines read per lookup (mean of {len(u)}): bilinear '
        f'{bilinear_lines:.1f}, EWA {lines:.1f} → at an equal cost per line '
        f'EWA could reach {bilinear_lines / lines:.3f}× bitmap')
    rows = []
    if not sweep:
        return rows
    out('EWA by the levels its footprints select (same ellipses in texels, smaller levels):')
    out('| minor axis (level-0 texels) | levels blended | their size MB | cache lines / lookup '
        '| bitmap ms | ewa, given order: ms | vs bitmap | ewa (sorted) ms | vs bitmap |')
    out('|---|---|---|---|---|---|---|---|---|')
    trio = {k: fns[k] for k in ('bitmap (bilinear)', GIVEN_ORDER, 'ewa')}
    for m in (minor, *sweep):
        batch.set_minor(m)
        t, _ = measure(trio, repeats)
        # pbrt's level: log2 of the minor axis in level-0 texels, after the anisotropy clamp
        level = max(0, int(math.floor(math.log2(m * max(1.0, anisotropy / max_anisotropy)))))
        mb = sum(16 * max(1, size >> lv) ** 2 for lv in (level, level + 1)) / 2 ** 20
        tb, tg, ts = t['bitmap (bilinear)'], t[GIVEN_ORDER], t['ewa']
        out(f'| {m:g} | {level}, {level + 1} | {mb:.2f} | {ewa_lines(m):.1f} | {tb * 1e3:.2f} '
            f'| {tg * 1e3:.1f} | {tb / tg:.3f}× | {ts * 1e3:.1f} | {tb / ts:.3f}× |')
        for name, tm in (('ewa, given order', tg), ('ewa', ts)):
            rows.append(dict(method=f'{name}, minor {m:g}', ms=tm * 1e3,
                             mlookups=count / tm / 1e6, ratio=tb / tm, target=None,
                             first_ms=float('nan')))
    return rows


#: --anisotropy and --maxanisotropy at most this (EWA's cost grows with the clamped ratio).
MAX_ANISOTROPY = 256.0
TEXELS_PER_LINE = 4        # 64-byte lines of RGBA float32 texels, rows stored one after another


def _lines(x, y, size):
    """Distinct cache lines of the texels (x, y) (wrapped with repeat) of a size² level."""
    return len(set(zip((y % size).tolist(), ((x % size) // TEXELS_PER_LINE).tolist())))


def cache_lines_bilinear(size, u, v):
    out = np.empty(len(u))
    for k in range(len(u)):
        x0, y0 = math.floor(u[k] * size - 0.5), math.floor(v[k] * size - 0.5)
        xs, ys = np.array([x0, x0 + 1, x0, x0 + 1]), np.array([y0, y0, y0 + 1, y0 + 1])
        out[k] = _lines(xs, ys, size)
    return out


def cache_lines_ewa(size, u, v, d0, d1, max_anisotropy):
    """pbrt's EWA footprint (anisotropy clamp, level from the minor axis, the two levels it
    blends, the +1 texel² ellipse) → distinct cache lines of the texels inside, per lookup."""
    out = np.zeros(len(u))
    for k in range(len(u)):
        a, b = np.array(d0[k], float), np.array(d1[k], float)
        if a @ a < b @ b:
            a, b = b, a
        major, minor = np.linalg.norm(a), np.linalg.norm(b)
        if minor * max_anisotropy < major:
            b *= major / (minor * max_anisotropy)
            minor = major / max_anisotropy
        lod = max(0.0, math.log2(minor * size))
        levels = [int(lod)] + ([int(lod) + 1] if lod > int(lod) else [])
        for lvl in levels:
            n = max(1, size >> lvl)
            (ds0, dt0), (ds1, dt1) = a * n, b * n
            A, B, C = dt0 ** 2 + dt1 ** 2 + 1, -2 * (ds0 * dt0 + ds1 * dt1), ds0 ** 2 + ds1 ** 2 + 1
            f = A * C - B * B / 4
            s, t = u[k] * n - 0.5, v[k] * n - 0.5
            r = int(math.ceil(math.sqrt(max(A, C)))) + 1        # the extents are √C and √A
            if r > n:                   # wider than the level: every line of it is read
                out[k] += n * -(-n // TEXELS_PER_LINE)
                continue
            xs, ys = np.meshgrid(np.arange(math.floor(s) - r, math.ceil(s) + r + 1),
                                 np.arange(math.floor(t) - r, math.ceil(t) + r + 1))
            ss, tt = xs - s, ys - t
            inside = (A * ss * ss + B * ss * tt + C * tt * tt) / f < 1
            out[k] += _lines(xs[inside], ys[inside], n)
    return out


def main(argv=None) -> int:
    from ..cli import (command_parser, positive_float, positive_floats, positive_int,
                       variant_name)
    ap = command_parser('bench lookups', __doc__)
    ap.add_argument('--size', type=positive_int, default=1024,
                    help='texture resolution (square)')
    ap.add_argument('--count', type=positive_int, default=1 << 20, help='lookups per batch')
    ap.add_argument('--anisotropy', type=positive_float, default=8.0,
                    help='major/minor axis ratio (1 to 256)')
    ap.add_argument('--minor', type=positive_float, default=1.5,
                    help='minor axis length in texels')
    ap.add_argument('--maxanisotropy', type=positive_float, default=8.0,
                    help='EWA anisotropy clamp (1 to 256)')
    ap.add_argument('--repeats', type=positive_int, default=7,
                    help='timed batches per filter after a warm-up (their median is reported)')
    ap.add_argument('--variant', type=variant_name, default='llvm_ad_rgb',
                    help='Mitsuba variant')
    ap.add_argument('--sweep', type=positive_floats, default=(3.0, 6.0, 12.0),
                    help='comma-separated larger minor axes (texels) at which EWA is timed again '
                         '(random uv; empty: none)')
    ap.add_argument('--coherent', action='store_true',
                    help='lookups in raster order over the texture (as from a render) instead of '
                         'at random uv')
    args = ap.parse_args(argv)
    for name in ('anisotropy', 'maxanisotropy'):
        if not 1 <= getattr(args, name) <= MAX_ANISOTROPY:
            ap.error(f'argument --{name}: must be in [1, {MAX_ANISOTROPY:g}] (an EWA lookup '
                     f'reads about that many texels per minor axis), got {getattr(args, name)}')
    for name, values in (('minor', (args.minor,)), ('sweep', args.sweep)):
        if max(values, default=0) > args.size:
            ap.error(f'argument --{name}: a minor axis must be at most --size ({args.size}) '
                     f'texels, got {max(values):g}')
    run(args.size, args.count, args.anisotropy, args.minor, args.repeats, args.variant,
        args.maxanisotropy, coherent=args.coherent, sweep=args.sweep)
    return 0
