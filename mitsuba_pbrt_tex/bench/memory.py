"""``python -m mitsuba_pbrt_tex bench memory``: peak and resident memory of image textures, against
Mitsuba's ``bitmap`` in the same run, and the image cache over reloads.

Each configuration runs in a fresh Python process (peak RSS is per process): it sets the variant,
loads the image once and drops it (compiling the kernels for its size: LLVM's memory while it
compiles is not the texture's), resets the high-water mark, records its resident memory, loads
one RGB float32 OpenEXR image as a texture, evaluates a batch of lookups, and reports

* *peak* — the process's maximum resident set size (``VmHWM``: its own, whatever process
  started it) minus the resident memory before the load, i.e. everything the load, the pyramid
  build and the lookups needed at their worst moment;
* *held* — resident memory after the lookups (Python objects collected) minus the same
  baseline: what the process keeps, Dr.Jit's allocation cache included;
* *kept* — the same after flushing that cache: what the texture itself holds (*held − kept*
  is left in the cache: temporaries of the build that were not given back, for instance);

all as multiples of the image's size (H·W·3·4 bytes). Configurations: ``bitmap``,
``pbrt_imagemap`` with ``bilinear`` (no pyramid until a footprint needs it), with ``ewa`` and
with ``box`` (the pyramid and nothing else: the exact footprint average reads its texels). The
reload check loads the image as an ``ewa`` texture, drops it and edits the file, several times, and
reports the resident memory after each (the cache must not keep textures nobody uses).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile

CHILD = r'''
import gc, json, os, resource, sys
import numpy as np
import drjit as dr, mitsuba as mi
import mitsuba_pbrt_tex as mpt

def rss():
    with open('/proc/self/statm') as f:
        return int(f.read().split()[1]) * os.sysconf('SC_PAGE_SIZE')

def peak_rss():
    # this process's own high-water mark: getrusage's ru_maxrss also holds the parent's peak
    # where Python started this process by vfork (Linux keeps the pre-exec image's maximum)
    with open('/proc/self/status') as f:
        for line in f:
            if line.startswith('VmHWM:'):
                return int(line.split()[1]) * 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024

kind, path, reloads = sys.argv[1], sys.argv[2], int(sys.argv[3])
mi.set_variant('llvm_ad_rgb'); mpt.register()
si = dr.zeros(mi.SurfaceInteraction3f, 4096)
rng = np.random.default_rng(1)
si.uv = mi.Point2f(rng.random(4096), rng.random(4096))
si.duv_dx = mi.Vector2f(1e-3, 0); si.duv_dy = mi.Vector2f(0, 4e-3)
dr.eval(si)
# a first load compiles this size's kernels (their sizes are literals): LLVM's memory while it
# compiles is not the texture's (a first run at 512² made bilinear's peak 9.4× the image, 4.1×
# once compiled); then the high-water mark is reset (Linux: clear_refs 5)
spec = ({'type': 'bitmap', 'filename': path} if kind == 'bitmap' else
        {'type': 'pbrt_imagemap', 'filename': path,
         'filter': 'ewa' if kind == 'reload' else kind})
warm = mi.load_dict(spec)
dr.eval(warm.eval(si))
dr.sync_thread()
del warm
gc.collect(); dr.flush_malloc_cache()
try:
    with open('/proc/self/clear_refs', 'w') as f:
        f.write('5')
except OSError:
    pass
base = rss()
out = {}
if kind == 'reload':
    from mitsuba_pbrt_tex.image import image_cache
    after = []
    for i in range(reloads):
        tex = mi.load_dict(spec)
        dr.eval(tex.eval(si))
        dr.sync_thread()
        del tex
        gc.collect()
        after.append(rss() - base)
        st = os.stat(path)                  # "edit" the file: a new modification time and key
        os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    out = dict(after=after, entries=len(image_cache))
else:
    tex = mi.load_dict(spec)
    dr.eval(tex.eval(si))
    dr.sync_thread()
    peak = peak_rss() - base
    gc.collect()
    held = rss() - base
    dr.flush_malloc_cache()
    kept = rss() - base
    out = dict(peak=peak, held=held, kept=kept)
print('RESULT ' + json.dumps(out))
'''


def _child(kind: str, path: str, reloads: int = 0) -> dict:
    r = subprocess.run([sys.executable, '-c', CHILD, kind, path, str(reloads)],
                       capture_output=True, text=True)
    for line in r.stdout.splitlines():
        if line.startswith('RESULT '):
            return json.loads(line[7:])
    raise RuntimeError(f'bench memory: {kind} failed:\n{r.stderr[-2000:]}')


def write_image(path: str, size: int) -> int:
    """A size×size RGB float32 EXR of noise (written in bands, to keep this process small)."""
    import numpy as np

    from ..outputs import write_exr
    rng = np.random.default_rng(0)
    img = np.empty((size, size, 3), np.float32)
    for y in range(0, size, 512):
        img[y:y + 512] = rng.random((min(512, size - y), size, 3), dtype=np.float32)
    write_exr(path, img)
    return img.nbytes


#: What the command line measures (``run``'s default leaves ``box`` out: a smaller run).
KINDS = ('bitmap', 'bilinear', 'ewa', 'box')


def run(size: int = 2048, reloads: int = 5, kinds=('bitmap', 'bilinear', 'ewa'), out=print):
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, f'noise_{size}.exr')
        nbytes = write_image(path, size)
        mib = nbytes / 2**20
        out(f'image: {size}x{size} RGB float32 EXR, {mib:.0f} MiB; memory as multiples of it '
            f"(peak: during load, build and lookups; held: afterwards, Dr.Jit's allocation cache "
            f'included; kept: without it)')
        out('')
        out('| texture | peak | held | kept | peak vs bitmap |')
        out('|---|---|---|---|---|')
        rows = []
        for kind in kinds:
            r = _child(kind, path)
            r = {k: v / nbytes for k, v in r.items()}
            r['kind'] = kind
            rows.append(r)
        ref = next((r['peak'] for r in rows if r['kind'] == 'bitmap'), None)
        for r in rows:
            name = 'bitmap' if r['kind'] == 'bitmap' else f'pbrt_imagemap {r["kind"]}'
            vs = f'{r["peak"] / ref:.2f}x' if ref else '—'
            out(f'| {name} | {r["peak"]:.2f}x | {r["held"]:.2f}x | {r["kept"]:.2f}x | {vs} |')
        reload = None
        if reloads:
            reload = _child('reload', path, reloads)
            after = ', '.join(f'{a / 2**20:.0f}' for a in reload['after'])
            out('')
            out(f'reloads: {reloads} loads of an edited file, each texture dropped: resident MiB '
                f'above the start after each: {after}; cache entries left: {reload["entries"]}')
        return rows, reload


def main(argv=None) -> int:
    from ..cli import command_parser, non_negative_int, output_file, positive_int
    ap = command_parser('bench memory', __doc__)
    ap.add_argument('--size', type=positive_int, default=2048,
                    help='image side in pixels (default 2048; 8192 is a 768 MiB image, with '
                         'peaks near 3 GiB)')
    ap.add_argument('--reloads', type=non_negative_int, default=5,
                    help='times an edited image is reloaded in the cache measurement')
    ap.add_argument('--out', type=output_file, default=None,
                    help='also write the report to this Markdown file')
    args = ap.parse_args(argv)
    lines = []

    def out(line):
        print(line, flush=True)
        lines.append(line)

    run(args.size, args.reloads, kinds=KINDS, out=out)
    if args.out:
        import platform
        with open(args.out, 'w', encoding='utf-8') as f:
            f.write(f'# bench memory\n\n`python -m mitsuba_pbrt_tex bench memory --size {args.size}`'
                    f' ({platform.machine()}, {os.cpu_count()} CPU threads, llvm_ad_rgb)\n\n'
                    + '\n'.join(lines) + '\n')
    return 0
