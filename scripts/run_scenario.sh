#!/usr/bin/env bash
# `make run SCENARIO=...`: run one scenario of the full node graph and print its summary.
# Scenarios:
#   stand           (default) HyQ stands 10 s of sim time in lockstep, first on rigid ground, then on T1 soft
#   stand_realtime  the same, following the wall clock
# Results: runs/<timestamp>/<part>/ (one log per node, summary.json) and runs/<timestamp>/report.md.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
SCENARIO="${1:-stand}"
DURATION_S="${DURATION_S:-10.0}"
RUN_ROOT="$ROOT/runs/$(date +%Y%m%d-%H%M%S)-$SCENARIO"
# A private DDS domain per run, so concurrent runs and tests do not see each other.
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(( (RANDOM % 100) + 1 ))}"

stand() {
    local mode="$1"
    local parts=()
    for course in flat_rigid flat_t1; do
        local dir="$RUN_ROOT/$course"
        echo "[run] $SCENARIO: HyQ stands on '$course' for $DURATION_S s of sim time ($mode)"
        bash "$ROOT/scripts/run_graph.sh" -d "$dir" -w sim_bridge \
            -s "sim_bridge.course:=$course" -s "sim_bridge.mode:=$mode" \
            -s "sim_bridge.duration_s:=$DURATION_S" -s "sim_bridge.summary_path:=$dir/summary.json" \
            tal_sim_bridge/sim_bridge tal_control/stand_controller \
            || { echo "[run] the graph failed; logs in $dir" >&2; tail -n 20 "$dir"/*.log >&2; exit 1; }
        parts+=("$dir/summary.json")
    done
    python -m tal_sim_bridge.stand_report --output "$RUN_ROOT/report.md" "${parts[@]}"
}

case "$SCENARIO" in
    stand) stand lockstep ;;
    stand_realtime) stand realtime ;;
    *) echo "unknown SCENARIO '$SCENARIO'; known: stand, stand_realtime" >&2; exit 2 ;;
esac
echo "[run] report: $RUN_ROOT/report.md"
