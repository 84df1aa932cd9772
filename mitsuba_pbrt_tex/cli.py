"""Command line: ``python -m mitsuba_pbrt_tex {render,info,bench,demo} ...``."""

from __future__ import annotations

import argparse
import math
import os
import sys

#: Set this environment variable to see the Python traceback of an unexpected error.
DEBUG_ENV = 'MITSUBA_PBRT_TEX_DEBUG'


def _whole_number(text: str, lowest: int) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected a whole number, got "{text}"') from None
    if value < lowest:
        raise argparse.ArgumentTypeError(f'must be >= {lowest}, got {value}')
    return value


def positive_int(text: str) -> int:
    """An argparse type: a whole number >= 1 (else argparse's one-line error, exit 2)."""
    return _whole_number(text, 1)


def non_negative_int(text: str) -> int:
    """An argparse type: a whole number >= 0."""
    return _whole_number(text, 0)


def positive_float(text: str) -> float:
    """An argparse type: a finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected a number, got "{text}"') from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f'must be a finite number > 0, got {text}')
    return value


def positive_floats(text: str) -> tuple:
    """An argparse type: comma-separated finite numbers > 0 (empty: none)."""
    return tuple(positive_float(part) for part in text.split(',') if part.strip())


def definition(text: str) -> tuple:
    """An argparse type: ``NAME=VALUE`` (a scene parameter, as Mitsuba's ``-D``: any name
    without ``$`` or white space)."""
    name, eq, value = text.partition('=')
    if not eq or not name or '$' in name or any(c.isspace() for c in name):
        raise argparse.ArgumentTypeError(f'expected NAME=VALUE (a scene parameter, as in '
                                         f'"-D spp=16"), got "{text}"')
    return name, value


def variant_name(text: str) -> str:
    """An argparse type: a Mitsuba variant the plugins take and this machine runs."""
    from .variants import variant_problem
    problem = variant_problem(text)
    if problem:
        raise argparse.ArgumentTypeError(problem)
    return text


def output_folder(text: str) -> str:
    """An argparse type: a folder to write into (made if missing): not empty, not a file, a
    dangling link or below one — as the system resolves the path (``a_file/../x`` is below a
    file)."""
    if not text:
        raise argparse.ArgumentTypeError('the folder name is empty')
    path = text.rstrip(os.sep) or os.sep
    while True:
        if os.path.lexists(path):
            if os.path.isdir(path):
                return text
            kind = 'a dangling symbolic link' if not os.path.exists(path) else 'a file'
            where = 'is' if path == (text.rstrip(os.sep) or os.sep) else f'is below "{path}",'
            raise argparse.ArgumentTypeError(f'"{text}" {where} {kind}, not a folder')
        parent = os.path.dirname(path)
        if parent in ('', path):        # the working directory (relative) or the root
            return text
        path = parent


def output_file(text: str) -> str:
    """An argparse type: a file to write, in a folder that exists."""
    if not text or text.endswith(os.sep):
        raise argparse.ArgumentTypeError(f'"{text}" is not a file name')
    if os.path.isdir(text):
        raise argparse.ArgumentTypeError(f'"{text}" is a folder, not a file')
    if os.path.islink(text) and not os.path.exists(text):
        raise argparse.ArgumentTypeError(f'"{text}" is a dangling symbolic link')
    folder = os.path.dirname(text) or '.'
    if not os.path.isdir(folder):
        raise argparse.ArgumentTypeError(f'"{text}": its folder "{folder}" does not exist (or '
                                         f'is a file)')
    return text


def _render(args) -> int:
    from .outputs import terminate_on_sigterm
    from .render import RenderError, render_file
    terminate_on_sigterm()
    try:
        info = render_file(args.scene, args.output, spp=args.spp, variant=args.variant,
                           progress=not args.quiet, params=dict(args.define))
    except RenderError as e:
        print(f'error: {e}', file=sys.stderr)
        return 2
    print(f'wrote {info["exr"]} and {info["png"]} ({info["shape"][1]}x{info["shape"][0]}, '
          f'{info["spp"]} spp, {info["variant"]})')
    print(f'time: {info["render_s"]:.2f} s rendering ({info["first_pass_s"]:.2f} s for the first '
          f'pass, including kernel compilation), {info["load_s"]:.2f} s loading')
    if info['nonfinite']:
        print(f'warning: {info["nonfinite"]} non-finite pixel values', file=sys.stderr)
        return 1
    return 0


def _info(args) -> int:
    from . import docs
    from .registry import PLUGINS
    names = args.plugins or list(PLUGINS)
    unknown = [n for n in names if n not in PLUGINS]
    if unknown:
        print(f'error: unknown plugin(s) {", ".join(unknown)}; plugins: {", ".join(PLUGINS)}',
              file=sys.stderr)
        return 2
    if args.bench_results and not args.update_readme:
        print('error: --bench-results is read by --update-readme only; give both (nothing was '
              'changed)', file=sys.stderr)
        return 2
    if args.update_readme:
        try:
            changed = docs.update_readme(args.update_readme, args.bench_results)
        except (OSError, ValueError) as e:
            print(f'error: {e}', file=sys.stderr)
            return 2
        print(f'updated {args.update_readme}' if changed else
              f'{args.update_readme} is up to date')
        return 0
    print(docs.markdown(names) if args.markdown else docs.text(names), end='')
    return 0


def _bench(args) -> int:
    if args.what == 'lookups':
        from .bench.lookups import main as run
    elif args.what == 'render':
        from .bench.render import main as run
    elif args.what == 'pyramid':
        from .bench.pyramid import main as run
    elif args.what == 'integrator':
        from .bench.integrator import main as run
    elif args.what == 'memory':
        from .bench.memory import main as run
    else:  # pragma: no cover - argparse restricts the choices
        raise ValueError(args.what)
    return run(args.rest)


def _demo(args) -> int:
    if args.what == 'inverse':
        from .demo.inverse import main as run
    elif args.what == 'horizon':
        from .demo.horizon import main as run
    else:  # pragma: no cover
        raise ValueError(args.what)
    return run(args.rest)


class _Parser(argparse.ArgumentParser):
    """argparse, with usage errors as one line (instead of the usage block and the error)."""

    def error(self, message):
        self.exit(2, f'error: {message} (see: {self.prog} --help)\n')


def program() -> str:
    """How the user started us, for usage lines: the console script's own name when started
    as it (``mitsuba-pbrt-tex``, ``.exe`` on Windows), else the module form."""
    script = os.path.splitext(os.path.basename(sys.argv[0]))[0] if sys.argv and sys.argv[0] \
        else ''
    return script if script == 'mitsuba-pbrt-tex' else 'python -m mitsuba_pbrt_tex'


def command_parser(command: str, doc: str) -> argparse.ArgumentParser:
    """The parser of ``<program> <command>`` (a benchmark's or a demo's options): its usage line
    as the user started us, its description the first paragraph of ``doc``."""
    return argparse.ArgumentParser(prog=f'{program()} {command}',
                                   description=doc.split('\n\n')[0])


def parser() -> argparse.ArgumentParser:
    ap = _Parser(prog=program(), description="PBRT's texture system as Mitsuba 3 plugins.")
    sub = ap.add_subparsers(dest='command', required=True)

    r = sub.add_parser('render', help='render a scene to EXR (+ tone-mapped PNG)')
    r.add_argument('scene', help='scene XML file')
    r.add_argument('-o', '--output', required=True, help='output .exr (a .png is written beside it)')
    r.add_argument('--spp', type=positive_int, default=None,
                   help='samples per pixel, >= 1 (default: the scene\'s)')
    r.add_argument('--variant', default='llvm_ad_rgb', help='Mitsuba variant (default llvm_ad_rgb)')
    r.add_argument('-D', dest='define', metavar='NAME=VALUE', type=definition, action='append',
                   default=[], help='set the scene parameter $NAME (over its <default>), as '
                                    "Mitsuba's -D; repeatable")
    r.add_argument('-q', '--quiet', action='store_true', help='no progress display')
    r.set_defaults(func=_render)

    i = sub.add_parser('info', help='list the plugins and their parameters')
    i.add_argument('plugins', nargs='*', help='plugin names (default: all)')
    i.add_argument('--markdown', action='store_true', help='Markdown tables (as in the README)')
    i.add_argument('--update-readme', metavar='README', default=None,
                   help="rewrite the README's generated sections (plugin reference, benchmark "
                        'summary) in place')
    i.add_argument('--bench-results', metavar='RESULTS_MD', default=None,
                   help='results.md of a full `bench render` run, for --update-readme')
    i.set_defaults(func=_info)

    b = sub.add_parser('bench', help='benchmarks: lookups, render (speed vs error), pyramid, '
                                     'integrator, memory')
    b.add_argument('what', choices=['lookups', 'render', 'pyramid', 'integrator', 'memory'])
    b.add_argument('rest', nargs=argparse.REMAINDER, help='options of that benchmark (--help)')
    b.set_defaults(func=_bench)

    d = sub.add_parser('demo', help='demos: inverse (texture recovery with Adam), horizon '
                                    '(filters on a plane to the horizon)')
    d.add_argument('what', choices=['inverse', 'horizon'])
    d.add_argument('rest', nargs=argparse.REMAINDER, help='options of that demo (--help)')
    d.set_defaults(func=_demo)
    return ap


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    from .outputs import Terminated
    try:
        return args.func(args)
    except KeyboardInterrupt:
        print('interrupted', file=sys.stderr)
        return 130
    except Terminated:
        print('terminated (SIGTERM); no partial output left behind', file=sys.stderr)
        return 143
    except Exception as e:          # a bug, not a user error: one line, traceback on request
        if os.environ.get(DEBUG_ENV):
            raise
        print(f'error: unexpected {type(e).__name__}: {" ".join(str(e).split())[:500]} (set '
              f'{DEBUG_ENV}=1 for the traceback)', file=sys.stderr)
        return 3
