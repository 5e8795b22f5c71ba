#!/usr/bin/env bash
# The tests that need no ROS (test/core, test/mapio, test/sensing) with Ubuntu 24.04's numpy
# 1.26 and numba 0.58 (LLVM 14), what `colcon build` in a Jazzy workspace runs with: the
# development .venv has numpy 2 and numba 0.68, so a call only numpy 2 has, or an LLVM
# intrinsic only LLVM 19 knows, passes there and fails on a robot. Builds .venv-distro
# (pip, from scripts/distro-requirements.txt) once, then runs pytest with the checkout first
# on the path. About 10 minutes on an idle 2-core machine, most of it numba compiling.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
VENV="$ROOT/.venv-distro"
REQ="$ROOT/scripts/distro-requirements.txt"
STAMP="$VENV/.requirements.sha256"
if [[ ! -x "$VENV/bin/python" ]]; then
    "${PYTHON:-python3}" -m venv "$VENV"
fi
want="$(sha256sum "$REQ" | cut -d' ' -f1)"
if [[ "$(cat "$STAMP" 2>/dev/null)" != "$want" ]]; then
    "$VENV/bin/pip" install --quiet --disable-pip-version-check -r "$REQ"
    echo "$want" >"$STAMP"
fi
export PYTHONPATH="$ROOT" NUMBA_CACHE_DIR="$ROOT/.numba_cache_distro" MPLBACKEND=Agg
"$VENV/bin/python" -c 'import numpy, numba; print(f"numpy {numpy.__version__}, numba {numba.__version__}")'
exec "$VENV/bin/python" -m pytest -q -p no:cacheprovider test/core test/mapio test/sensing "$@"
