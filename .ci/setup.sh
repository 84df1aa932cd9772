#!/usr/bin/env bash
# One-step set-up on a fresh machine (what the README's two commands start with):
#   1. a libLLVM >= 17 for Dr.Jit's LLVM backend (Debian/Ubuntu: installs libllvm19 if missing),
#   2. a virtual environment in .venv,
#   3. this package, editable, with the extras named on the command line (test, bench).
# Usage: bash .ci/setup.sh [test] [bench]
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON="${PYTHON:-python3}"

# ---- 1. libLLVM (the package's own finder decides what counts as usable) -----------------------
has_llvm() {
    "$PYTHON" - <<'PY'
import importlib.util, os, sys
if os.environ.get('DRJIT_LIBLLVM_PATH'):
    sys.exit(0)
spec = importlib.util.spec_from_file_location('_llvm', 'mitsuba_pbrt_tex/_llvm.py')
mod = importlib.util.module_from_spec(spec)
spec.loader.exec_module(mod)
sys.exit(0 if mod.find_libllvm() else 1)
PY
}

if ! has_llvm; then
    echo "[setup] no libLLVM >= 17 found: installing Debian's libllvm19" >&2
    SUDO=""
    if [ "$(id -u)" != 0 ]; then SUDO="sudo"; fi
    if command -v apt-get >/dev/null 2>&1; then
        $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -q libllvm19 >/dev/null 2>&1 || {
            $SUDO apt-get update -q >/dev/null
            $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -q libllvm19 >/dev/null
        }
    else
        echo "[setup] apt-get is not available: install LLVM >= 17 yourself and set" \
             "DRJIT_LIBLLVM_PATH to its libLLVM shared library" >&2
        exit 1
    fi
    has_llvm || { echo "[setup] libllvm19 was installed but no libLLVM >= 17 is visible" >&2; exit 1; }
fi

# ---- 2. virtual environment ---------------------------------------------------------------------
if [ ! -x .venv/bin/python ]; then
    "$PYTHON" -m venv .venv
fi

# ---- 3. the package ------------------------------------------------------------------------------
extras=$(IFS=,; echo "$*")
spec="."
if [ -n "$extras" ]; then spec=".[${extras}]"; fi
.venv/bin/python -m pip install -q --disable-pip-version-check -e "$spec"
.venv/bin/python -c "import mitsuba_pbrt_tex"
