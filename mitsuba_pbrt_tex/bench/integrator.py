"""``python -m mitsuba_pbrt_tex bench integrator``: the cost of ``pbrt_path`` against ``path``.

The same scenes and textures rendered by Mitsuba's ``path``, by ``pbrt_path`` with texture
differentials, and by ``pbrt_path`` with ``texture_differentials=false``, in one process,
interleaved, median of ``--repeats`` renders after a warm-up (compilation excluded). Prints the
time ratios to ``path``. Targets: ≤ 1.2× with differentials, ≈ 1.0× without. Mitsuba's own
``prb`` (the path-replay integrator whose stages ``pbrt_path`` follows) is timed too: its ratio
to ``path`` is the cost of that Python structure (``pbrt_path`` records its loop once where
``prb`` records it twice, so without differentials it costs a little less).

The first cases isolate the integrator: Mitsuba's ``bitmap`` wrapped in a one-sample
``pbrt_supersample`` does the same lookups whatever the footprint, but asks for differentials.
In the other cases the textures are filtered, so with differentials they also read coarser MIP
levels or run EWA — the cost of filtering is then part of what is measured.
"""

from __future__ import annotations

import os

CASES = (
    # the integrator's own overhead: identical texture lookups, differentials computed or not
    ('grazing, bitmap asking for differentials', 'grazing.xml',
     {'texture': 'tex/image_bitmap_footprint.xml', 'tiles': '125'}),
    ('specular, bitmap asking for differentials', 'specular.xml',
     {'texture': 'tex/image_bitmap_footprint.xml'}),
    # with filtering: the textures' own cost changes with the footprint too
    ('grazing, image (bilinear)', 'grazing.xml',
     {'texture': 'tex/image_pbrt.xml', 'filter': 'bilinear', 'tiles': '125'}),
    ('grazing, image (trilinear)', 'grazing.xml',
     {'texture': 'tex/image_pbrt.xml', 'filter': 'trilinear', 'tiles': '125'}),
    ('grazing, procedural checkerboard', 'grazing.xml',
     {'texture': 'tex/checker_pbrt.xml', 'cells': '2000'}),
    ('specular, image (trilinear)', 'specular.xml',
     {'texture': 'tex/image_pbrt.xml', 'filter': 'trilinear'}),
    ('mappings (ewa)', 'mappings.xml', {'filter': 'ewa'}),
    ('noise (clamp)', 'noise.xml', {}),
)


def run(spp=16, res=(320, 180), repeats=5, variant='llvm_ad_rgb', out=print):
    import mitsuba as mi

    import mitsuba_pbrt_tex as mpt
    from .render import scenes_dir
    from .timing import measure

    mi.set_variant(variant)
    mpt.register()
    integrators = {'path': mi.load_dict({'type': 'path', 'max_depth': 5}),
                   'pbrt_path': mi.load_dict({'type': 'pbrt_path', 'max_depth': 5}),
                   'pbrt_path, differentials off': mi.load_dict(
                       {'type': 'pbrt_path', 'max_depth': 5, 'texture_differentials': False}),
                   'prb': mi.load_dict({'type': 'prb', 'max_depth': 5})}
    out(f'integrators: {res[0]}x{res[1]}, {spp} spp, max_depth 5, median of {repeats}, {variant}')
    out('| scene | path (ms) | pbrt_path (ms) | ratio (target ≤ 1.2) | differentials off (ms) '
        '| ratio (target ≈ 1.0) | Mitsuba\'s prb: ratio |')
    out('|---|---|---|---|---|---|---|')
    rows = []
    for name, xml, params in CASES:
        scene = mi.load_file(os.path.join(scenes_dir(), xml), width=str(res[0]),
                             height=str(res[1]), **params)
        fns = {k: (lambda i=i: mi.render(scene, integrator=i, spp=spp, seed=1))
               for k, i in integrators.items()}
        times, _ = measure(fns, repeats)
        base = times['path']
        on, off = times['pbrt_path'], times['pbrt_path, differentials off']
        out(f'| {name} | {base * 1e3:.1f} | {on * 1e3:.1f} | {on / base:.2f}× | '
            f'{off * 1e3:.1f} | {off / base:.2f}× | {times["prb"] / base:.2f}× |')
        rows.append(dict(scene=name, path=base, on=on, off=off, prb=times['prb']))
    return rows


def main(argv=None) -> int:
    from ..cli import command_parser, positive_int, variant_name
    ap = command_parser('bench integrator', __doc__)
    ap.add_argument('--spp', type=positive_int, default=16,
                    help='samples per pixel of each render')
    ap.add_argument('--repeats', type=positive_int, default=5,
                    help='timed renders per configuration after a warm-up (medians reported)')
    ap.add_argument('--variant', type=variant_name, default='llvm_ad_rgb',
                    help='Mitsuba variant')
    ap.add_argument('--res', default='320x180', help='image size WxH (default 320x180)')
    args = ap.parse_args(argv)
    try:
        res = tuple(int(v) for v in args.res.lower().split('x'))
        if len(res) != 2 or min(res) < 1:
            raise ValueError
    except ValueError:
        ap.error(f'--res: expected WxH with positive integers, got {args.res!r}')
    run(args.spp, res=res, repeats=args.repeats, variant=args.variant)
    return 0
