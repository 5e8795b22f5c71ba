#!/usr/bin/env bash
# Build an interface package of interfaces/ into a venv with the ROS 2 Jazzy rosidl wheels:
# tf2_msgs (TFMessage, for /tf and /tf_static; not on PyPI; a sourced ROS 2 install brings
# its own) and mfp_mapper_msgs (the node's services ClearBbox and QueryMap). Called by
# `./run setup` when the package does not import (mfp_mapper_msgs: also when its definitions
# changed).
#
#   scripts/build_interface.sh [PKG]     (PKG: tf2_msgs (default) or mfp_mapper_msgs;
#                                         PYTHON=/path/to/venv/bin/python, default .venv)
#
# Needs cmake and a C/C++ compiler. The build wheels are pinned to Jazzy (an unpinned name
# resolves to a later distribution): scripts/tf2_msgs-build-requirements.txt.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PY="${PYTHON:-$ROOT/.venv/bin/python}"
PKG="${1:-tf2_msgs}"
[[ -d "$ROOT/interfaces/$PKG" ]] || { printf 'build_interface: no interfaces/%s\n' "$PKG" >&2; exit 1; }

fail() {
    printf 'build_interface: %s: %s\n' "$PKG" "$*" >&2
    exit 1
}

command -v cmake >/dev/null || fail "cmake not found (apt install cmake)"
command -v c++ >/dev/null || command -v g++ >/dev/null || fail "no C++ compiler (apt install g++)"

PREFIX="$("$PY" -c 'import sys; print(sys.prefix)')"
[[ "$PREFIX" != "$("$PY" -c 'import sys; print(sys.base_prefix)')" ]] ||
    fail "$PY is not a virtual environment: refusing to install into the system Python"

"$PY" -m pip install --quiet -r "$ROOT/scripts/tf2_msgs-build-requirements.txt" ||
    fail "could not install the rosidl build wheels"

INCLUDES="$("$PY" -c 'import sysconfig, numpy
print(sysconfig.get_paths()["include"] + ";" + numpy.get_include())')"

WORK="$(mktemp -d "${TMPDIR:-/tmp}/mfp_$PKG.XXXXXX")"
trap 'rm -rf "$WORK"' EXIT
cp -r "$ROOT/interfaces/$PKG" "$WORK/src"
rm -f "$WORK/src/COLCON_IGNORE"

export AMENT_PREFIX_PATH="$PREFIX"
export CMAKE_PREFIX_PATH="$PREFIX"
export PATH="$PREFIX/bin:$PATH"
if ! {
    cmake -S "$WORK/src" -B "$WORK/build" -DCMAKE_BUILD_TYPE=Release \
        -DCMAKE_INSTALL_PREFIX="$PREFIX" -DBUILD_TESTING=OFF \
        -DPython3_EXECUTABLE="$PY" -DPYTHON_EXECUTABLE="$PY" \
        -DMFP_PYTHON_INCLUDES="$INCLUDES" \
        -DCMAKE_INSTALL_RPATH="$PREFIX/lib" &&
        cmake --build "$WORK/build" -j "$(nproc)" &&
        cmake --install "$WORK/build"
} >"$WORK/build.log" 2>&1; then
    tail -n 40 "$WORK/build.log" >&2
    fail "build failed"
fi
"$PY" -c "import $PKG" || fail "built, but it does not import"
