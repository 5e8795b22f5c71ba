#!/usr/bin/env bash
# Build mfp_mapper with colcon in a throw-away workspace and check what it installs, the way
# a ROS 2 user gets it: `colcon build`, `source install/setup.bash`, `ros2 run mfp_mapper ...`.
#
#   scripts/colcon_check.sh            (PYTHON=/path/to/python, default .venv/bin/python)
#
# Exit codes: 0 ok, 1 a check failed, 3 colcon is not installed for that Python (skip).
# MFP_KEEP_WS=1 keeps the temporary workspace and prints its path.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PY="${PYTHON:-$ROOT/.venv/bin/python}"
PKG=mfp_mapper

fail() {
    printf 'colcon check: FAIL: %s\n' "$*" >&2
    exit 1
}

if ! "$PY" -c 'import colcon_core, colcon_ros' >/dev/null 2>&1; then
    printf 'colcon check: SKIP: colcon (colcon-common-extensions) not installed for %s\n' "$PY" >&2
    exit 3
fi

WS="$(mktemp -d "${TMPDIR:-/tmp}/mfp_colcon.XXXXXX")"
if [[ "${MFP_KEEP_WS:-0}" == 1 ]]; then
    printf 'colcon check: workspace kept at %s\n' "$WS" >&2
else
    trap 'rm -rf "$WS"' EXIT
fi

# Copy (not symlink) the package so the build cannot write into the repository.
mkdir -p "$WS/src/$PKG"
tar -C "$ROOT" \
    --exclude=./.git --exclude=./.venv --exclude=./.numba_cache --exclude='__pycache__' \
    --exclude=./build --exclude=./install --exclude=./log --exclude='*.egg-info' \
    --exclude=./.pytest_cache --exclude=./.mypy_cache --exclude=./.ruff_cache \
    --exclude=./.hypothesis --exclude=./out --exclude=./example_output \
    -cf - . | tar -C "$WS/src/$PKG" -xf -

# The ROS wheels keep their ament index in the venv prefix (<prefix>/share/ament_index);
# a sourced /opt/ros/jazzy keeps its own AMENT_PREFIX_PATH. colcon does not need either
# to build an ament_python package, but the installed node needs them at run time.
VENV_PREFIX="$("$PY" -c 'import sys; print(sys.prefix)')"
export AMENT_PREFIX_PATH="${AMENT_PREFIX_PATH:+$AMENT_PREFIX_PATH:}$VENV_PREFIX"
export COLCON_HOME="$WS/.colcon" # no user-level colcon defaults/mixins
# The installed node is started (--help); keep anything it does off the network.
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(($$ % 101 + 1))}"
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"

cd "$WS"
if ! "$PY" -m colcon build --packages-select "$PKG" >"$WS/build.out" 2>&1; then
    cat "$WS/build.out" >&2
    find "$WS/log/latest_build/$PKG" -name 'stdout_stderr.log' -exec tail -n 40 {} + >&2 2>/dev/null || true
    fail "colcon build --packages-select $PKG"
fi
grep -E '^Summary:' "$WS/build.out" >&2 || true

INSTALL="$WS/install/$PKG"
SHARE="$INSTALL/share/$PKG"
[[ -f "$SHARE/package.xml" ]] || fail "share/$PKG/package.xml not installed"
[[ -f "$INSTALL/share/ament_index/resource_index/packages/$PKG" ]] ||
    fail "ament index marker share/ament_index/resource_index/packages/$PKG not installed"
shopt -s nullglob
for f in "$ROOT"/config/*.yaml "$ROOT"/config/*.xml "$ROOT"/config/*.rviz; do
    [[ -f "$SHARE/config/$(basename "$f")" ]] || fail "config/$(basename "$f") not installed"
done
for f in "$ROOT"/launch/*.launch.py; do
    [[ -f "$SHARE/launch/$(basename "$f")" ]] || fail "launch/$(basename "$f") not installed"
done
shopt -u nullglob

# The environment a user gets from `source install/setup.bash` (the setup scripts are not
# written for `set -u`).
set +u
# shellcheck disable=SC1091
source "$WS/install/setup.bash"
set -u

# Where `ros2 run mfp_mapper <exe>` looks: <package prefix>/lib/mfp_mapper/<exe>.
PREFIX="$("$PY" -c "from ament_index_python.packages import get_package_prefix as g; print(g('$PKG'))")" ||
    fail "ament_index_python cannot find $PKG after sourcing install/setup.bash"
[[ "$PREFIX" == "$INSTALL" ]] || fail "package prefix is $PREFIX, expected $INSTALL"
"$PY" -c "import $PKG" || fail "import $PKG from the install space"

checked=()
problems=()
check_exe() { # check_exe NAME MODULE: installed where `ros2 run` looks; `--help` works
    local exe="$PREFIX/lib/$PKG/$1" module="$2"
    if [[ ! -x "$exe" ]]; then
        problems+=("lib/$PKG/$1 not installed (setup.cfg script_dir / console_scripts)")
        return 0
    fi
    if [[ ! -f "$ROOT/${module//.//}.py" && ! -f "$ROOT/${module//.//}/__init__.py" ]]; then
        problems+=("$module (console script $1) does not exist")
        return 0
    fi
    local out rc=0
    out="$(timeout -k 5s 30s "$exe" --help 2>&1 </dev/null)" || rc=$?
    if ((rc == 0)); then
        checked+=("$1 --help")
    elif ((rc == 124)); then
        printf '%s\n' "$out" | tail -n 5 >&2
        problems+=("'lib/$PKG/$1 --help' did not return within 30 s (main() should handle -h/--help before spinning)")
    else
        printf '%s\n' "$out" | tail -n 20 >&2
        problems+=("'lib/$PKG/$1 --help' exited $rc")
    fi
}
check_exe mfp_mapper mfp_mapper.ros.node
check_exe mfp-mapper mfp_mapper.cli

if ((${#problems[@]})); then
    fail "$(printf '\n  %s' "${problems[@]}")"
fi
printf 'colcon check: ok (package.xml, ament index, config, launch; %s)\n' \
    "$(IFS=';'; echo "${checked[*]}")" >&2
