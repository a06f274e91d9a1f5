#!/usr/bin/env bash
# Create the separate venv of the TSID side of the WBC benchmark (bench/bench_wbc.py, bench/tsid_side.py).
#
# TSID does not co-install with tal's pin 4.1 (DESIGN.md section 7): libtsid 1.10 has no wheel and tsid 1.7.1
# needs an older cmeel-boost. So it lives in its own venv, under bench/out/ (already gitignored):
#     bench/out/.venv-tsid   tsid==1.7.1, pin==3.4.0, cmeel-urdfdom<5, cmeel-tinyxml2<11,
#                            numpy, example-robot-data==6.0.0 (the same HyQ URDF as tal's)
# Two defects of the tsid 1.7.1 wheel (cp311 manylinux, measured here) are worked around:
#   * its bindings link libpinocchio_*.so.3.4.0 but the wheel only asks for "pin", which resolves to 3.7.0
#     ("libpinocchio_parsers.so.3.4.0: cannot open shared object file"): pin is pinned to 3.4.0;
#   * the extension sits one directory above its package (site-packages/tsid/tsid_pywrap*.so next to
#     site-packages/tsid/tsid/__init__.py), so `import tsid` gives an empty namespace package (upstream
#     stack-of-tasks/tsid#288, fixed in tsid 1.9): a .pth puts site-packages/tsid on sys.path and the
#     package's __init__ imports the extension from there (its RUNPATH is relative to where it lies, so the
#     file is not moved).
# Binary wheels only. Idempotent: a venv that already imports tsid (with its classes), pinocchio and
# example-robot-data is left as it is (fast no-op). Override the location with TAL_TSID_VENV, the base
# interpreter with TAL_TSID_PYTHON (default: the interpreter of tal's .venv, else python3.11, else python3).
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${TAL_TSID_VENV:-$ROOT/bench/out/.venv-tsid}"
PY="$VENV/bin/python"
STAMP="$VENV/.tal-tsid-ok"
REQUIREMENTS=(
  "tsid==1.7.1"
  "pin==3.4.0"
  "cmeel-urdfdom<5"
  "cmeel-tinyxml2<11"
  "numpy"
  "example-robot-data==6.0.0"
)

fail() {
  echo "setup_tsid_venv: ERROR: $*" >&2
  exit 1
}

check_venv() {
  "$PY" - <<'PYEOF' >/dev/null 2>&1
import importlib.metadata as metadata
import pathlib
import sys

import numpy  # noqa: F401
import pinocchio  # noqa: F401
import tsid

assert metadata.version("tsid") == "1.7.1", metadata.version("tsid")
assert hasattr(tsid, "InverseDynamicsFormulationAccForce") and hasattr(tsid, "SolverHQuadProgFast")
assert any((pathlib.Path(p) / "cmeel.prefix/share/example-robot-data/robots/hyq_description").is_dir()
           for p in sys.path)
PYEOF
}

if [ -x "$PY" ] && [ -f "$STAMP" ] && check_venv; then
  echo "setup_tsid_venv: $VENV is ready" >&2
  exit 0
fi

if [ -n "${TAL_TSID_PYTHON:-}" ]; then
  BASE_PY="$TAL_TSID_PYTHON"
elif [ -x "$ROOT/.venv/bin/python" ]; then
  BASE_PY="$(readlink -f "$ROOT/.venv/bin/python")"
elif command -v python3.11 >/dev/null 2>&1; then
  BASE_PY="$(command -v python3.11)"
else
  BASE_PY="$(command -v python3 || true)"
fi
[ -n "$BASE_PY" ] && [ -x "$BASE_PY" ] || fail "no Python interpreter found (set TAL_TSID_PYTHON)"

if [ -e "$VENV" ]; then
  # Only ever delete a (broken or partial) venv, never some other directory TAL_TSID_VENV points at.
  [ -f "$VENV/pyvenv.cfg" ] || [ -z "$(ls -A "$VENV")" ] || fail "$VENV exists and is not a venv; not touching it"
  rm -rf "$VENV"
fi
mkdir -p "$(dirname "$VENV")"
echo "setup_tsid_venv: creating $VENV with $BASE_PY ($("$BASE_PY" -V 2>&1))" >&2
"$BASE_PY" -m venv "$VENV" || fail "'$BASE_PY -m venv $VENV' failed"

LOG="$VENV/pip-install.log"
echo "setup_tsid_venv: pip install --only-binary=:all: ${REQUIREMENTS[*]} (log: $LOG)" >&2
if ! "$PY" -m pip install --disable-pip-version-check --only-binary=:all: "${REQUIREMENTS[@]}" >"$LOG" 2>&1; then
  tail -n 30 "$LOG" >&2
  fail "pip could not install the TSID side (${REQUIREMENTS[*]}); full log in $LOG"
fi

# Layout fix of the tsid 1.7.1 wheel (see the header).
"$PY" - <<'PYEOF' || fail "cannot apply the tsid 1.7.1 package layout fix in $VENV"
import pathlib
import sysconfig

platlib = pathlib.Path(sysconfig.get_paths()["platlib"])
outer = next(platlib.glob("cmeel.prefix/lib/python3*/site-packages/tsid"))
if not list(outer.glob("tsid_pywrap*.so")) or not (outer / "tsid" / "__init__.py").is_file():
    raise SystemExit(f"unexpected tsid layout in {outer}")
(platlib / "tal_tsid_layout_fix.pth").write_text(f"{outer}\n")
(outer / "tsid" / "__init__.py").write_text(
    "# tal: the tsid 1.7.1 wheel puts its extension one level up (see bench/setup_tsid_venv.sh)\n"
    "import pinocchio  # noqa: F401  (registers the types the bindings use)\n"
    "from tsid_pywrap import *  # noqa: F403\n"
)
PYEOF

if ! check_venv; then
  "$PY" -c "import numpy, pinocchio, tsid; print('pin', pinocchio.__version__, 'tsid names', len(dir(tsid)))" >&2 || true
  fail "installed, but importing tsid / pinocchio / example-robot-data (HyQ) in $VENV fails (see above)"
fi
touch "$STAMP"
echo "setup_tsid_venv: ready: $("$PY" -c 'import importlib.metadata as m, pinocchio; print("tsid", m.version("tsid"), "pinocchio", pinocchio.__version__)')" >&2
