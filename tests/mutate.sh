#!/usr/bin/env bash
# Mutation check of one module (mutmut), run by hand while developing — not in CI (too slow on
# 2 cores). Usage, from the repository root:
#     bash tests/mutate.sh mitsuba_pbrt_tex/wrap.py tests/test_wrap.py tests/test_imagemap.py
# MUTANTS="name1 name2" restricts the run to those mutants (e.g. the survivors of a first run,
# re-checked with more test files).
# The working tree (tests included, committed or not) is copied to a scratch folder
# ($MUTATE_DIR, default /tmp/mutate-<module>) so that editing the tree while it runs is safe; one
# worker (MUTATE_CHILDREN=2: two, on an otherwise idle machine), nice 15. Results:
# `cd $MUTATE_DIR && ../path/.venv/bin/mutmut results` (the script prints the summary at the end).
# A plugin (plugins/NAME.py) is imported as mitsuba_pbrt_tex.plugins.NAME (pyproject's
# package-dir), while mutmut names a mutant after its file's path: the scratch copy therefore
# holds the plugins inside the package too, and the mutated file is
# mitsuba_pbrt_tex/plugins/NAME.py (else no mutant would ever be switched on).
# A mutant is stopped as a timeout after (its tests' duration in the stats run +
# MUTATE_TIMEOUT_CONSTANT, default 60) × MUTATE_TIMEOUT_MULTIPLIER (default 4) seconds of wall
# time, counted from the mutant's fork (so the constant must cover importing Mitsuba and
# compiling the mutated kernels).
# Slow numpy references that tests compute through conftest.numpy_reference are kept in
# $DIR/reference-cache (MITSUBA_PBRT_TEX_REFERENCE_CACHE): computed once, in mutmut's first,
# unmutated pass, keyed by the test's inputs and the reference code, never by the package.
# MUTATE_SYNTAX=1 also mutates the module's @dr.syntax functions, which mutmut skips (it skips
# every decorated function): see below.
# Dr.Jit's thread pool does not survive fork(): mutmut forks its workers from a fork server that
# imports nothing (forkserver_warmup = none), so each mutant imports mitsuba afresh.
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
MODULE="$1"; shift
NAME="$(basename "$MODULE" .py)"
DIR="${MUTATE_DIR:-/tmp/mutate-$NAME}"
rm -rf "$DIR"; mkdir -p "$DIR"
cd "$ROOT"
git ls-files -co --exclude-standard | grep -v '^tests/mutate.sh$' | tar -cf - -T - | tar -xf - -C "$DIR"
cd "$DIR"
MUTATE="$MODULE"
case "$MODULE" in
  plugins/*.py)
    cp -r plugins mitsuba_pbrt_tex/plugins
    MUTATE="mitsuba_pbrt_tex/$MODULE" ;;
esac
if [ -n "${MUTATE_SYNTAX:-}" ]; then
  # mutmut 3 skips decorated functions, so the @dr.syntax ones (symbolic loops and
  # conditionals written as Python while/if) would get no mutants. In the scratch copy the
  # decorator is removed before mutmut generates the mutants, and a line appended to the module
  # applies it again, when the module is imported, to the original and every mutant of those
  # functions (mutmut's `mutants_<name>__mutmut` dicts, which the trampoline dispatches through;
  # lazily: a mutant is transformed only if it runs). dr.syntax reads the function's source with
  # inspect, which works on the generated file in mutants/. The mutant names are those of a run
  # without MUTATE_SYNTAX for the other functions (the decorator line is not a statement).
  cat > mitsuba_pbrt_tex/_mutate_syntax.py <<'PY'
"""Written by tests/mutate.sh (MUTATE_SYNTAX=1) into its scratch copy only: @dr.syntax applied
again to functions whose decorator was removed so that mutmut mutates them."""
import functools

import drjit as dr


def _lazy(fn):
    done = []

    @functools.wraps(fn)
    def call(*args, **kwargs):
        if not done:
            done.append(dr.syntax(fn))
        return done[0](*args, **kwargs)
    return call


def redecorate(scope, names):
    for name in names:
        dicts = [v for k, v in scope.items() if k.startswith('mutants_x') and (
            k.endswith('\u01c1' + name + '__mutmut') or k == 'mutants_x_' + name + '__mutmut')]
        for d in dicts:                     # mutated: the original and its mutants
            for key in list(d):
                d[key] = _lazy(d[key])
        if dicts:
            continue
        for owner in [scope] + [v for v in scope.values() if isinstance(v, type)]:
            get = owner.get if isinstance(owner, dict) else owner.__dict__.get
            fn = get(name)
            if getattr(getattr(fn, '__code__', None), 'co_name', None) == name and \
                    fn.__module__ == scope['__name__']:
                if isinstance(owner, dict):
                    owner[name] = dr.syntax(fn)
                else:
                    setattr(owner, name, dr.syntax(fn))
PY
  "$ROOT/.venv/bin/python" - "$MUTATE" <<'PY'
import re, sys
path = sys.argv[1]
src = open(path, encoding='utf-8').read()
pattern = re.compile(r'^[ \t]*@dr\.syntax[ \t]*\n(?=[ \t]*def[ \t]+(\w+))', re.M)
names = tuple(m.group(1) for m in pattern.finditer(src))
src = pattern.sub('', src)
src += ('\n\nfrom mitsuba_pbrt_tex._mutate_syntax import redecorate as _mutate_syntax'
        '  # pragma: no mutate\n'
        f'_mutate_syntax(globals(), {names!r})  # pragma: no mutate\n')
open(path, 'w', encoding='utf-8').write(src)
print('MUTATE_SYNTAX: mutating', ', '.join(names) or 'nothing (no @dr.syntax function)')
PY
fi
{
  echo "[mutmut]"
  echo "source_paths = mitsuba_pbrt_tex"
  echo "only_mutate = $MUTATE"
  echo "process_isolation = forkserver"
  echo "forkserver_warmup = none"
  # not mutated (not scored): error-message text and descriptions, whose tests are the
  # error tests; a statement starting on a matching line is skipped whole
  # (MUTATE_ALL=1 keeps them, so mutant names match a run made without these patterns)
  # MUTATE_SKIP="regex …" adds patterns (e.g. 'def _weight_polynomial\(' for ewa.py: it runs
  # at import, so its mutants fail collection and time out instead of running tests)
  if [ -z "${MUTATE_ALL:-}" ]; then
    printf 'do_not_mutate_patterns =\n    ^\\s*raise\\b\n    def describe\\(\n    def to_string\\(\n'
    for pat in ${MUTATE_SKIP:-}; do echo "    $pat"; done
  fi
  echo "timeout_multiplier = ${MUTATE_TIMEOUT_MULTIPLIER:-4.0}"
  echo "timeout_constant = ${MUTATE_TIMEOUT_CONSTANT:-60.0}"
  printf 'pytest_add_cli_args =\n    -q\n    -p\n    no:cacheprovider\n' 
  echo "pytest_add_cli_args_test_selection ="
  for t in "$@"; do echo "    $t"; done
  echo "also_copy ="
  echo "    plugins"
  echo "    scenes"
} > setup.cfg
rm -f pyproject.toml.bak
export MITSUBA_PBRT_TEX_REFERENCE_CACHE="${MITSUBA_PBRT_TEX_REFERENCE_CACHE:-$DIR/reference-cache}"
nice -n 15 "$ROOT/.venv/bin/mutmut" run --max-children "${MUTATE_CHILDREN:-1}" ${MUTANTS:-} || true
"$ROOT/.venv/bin/mutmut" results --all true 2>/dev/null || "$ROOT/.venv/bin/mutmut" results
