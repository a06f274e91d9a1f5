#!/usr/bin/env bash
# Start tal nodes, each as its own process, the way users run them: `ros2 run <pkg> <exe> --ros-args
# --params-file <pkg>/config/<exe>.yaml ...` when the ros2 CLI exists, otherwise the installed
# executable ros2_ws/install/<pkg>/lib/<pkg>/<exe> with the same arguments.
#
# Usage: scripts/run_graph.sh [-d RUN_DIR] [-w NODE] [-m FILE] [-s EXE.PARAM:=VALUE ...] PKG/EXE ...
#   -d RUN_DIR   where the per-node logs go (default runs/<timestamp>)
#   -m FILE      sample each node's resident memory and CPU time every second into FILE (JSON,
#                tal_core.resource_monitor)
#   -w NODE      wait for this executable to exit, then stop the others (default: wait for any to exit)
#   -s EXE.PARAM:=VALUE  a parameter override for one node, e.g. -s sim_bridge.duration_s:=10.0
#   -n EXE:NICE  start that node at this nice level (0-19: lower priority), e.g. -n vpa:10: on a machine
#                without spare cores the control chain (bridge, estimator, wbc) gets the CPU first
#   -r EXE:PRIO  run that node under the real-time FIFO scheduler at this priority (1-99; needs
#                CAP_SYS_NICE, e.g. root): it preempts every normal process when its message arrives
# Ctrl-C, SIGTERM or a node failing stops every child (SIGINT, then SIGTERM, then SIGKILL): no orphans.
# Exit code: that of the waited-for node (or of the first node to exit).
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
RUN_DIR=""
WAIT_FOR=""
MONITOR_OUT=""
MONITOR_PID=""
OVERRIDES=()
declare -A NICENESS=()  # exe -> nice level
declare -A FIFO=()      # exe -> SCHED_FIFO priority
while getopts "d:w:m:s:n:r:h" opt; do
    case "$opt" in
        d) RUN_DIR="$OPTARG" ;;
        w) WAIT_FOR="$OPTARG" ;;
        m) MONITOR_OUT="$OPTARG" ;;
        s) OVERRIDES+=("$OPTARG") ;;
        n) [[ "$OPTARG" =~ ^[a-z_]+:[0-9]+$ ]] || { echo "run_graph: -n wants EXE:NICE (0-19), got '$OPTARG'" >&2; exit 2; }
           NICENESS["${OPTARG%%:*}"]="${OPTARG##*:}" ;;
        r) [[ "$OPTARG" =~ ^[a-z_]+:[0-9]+$ ]] || { echo "run_graph: -r wants EXE:PRIO (1-99), got '$OPTARG'" >&2; exit 2; }
           FIFO["${OPTARG%%:*}"]="${OPTARG##*:}" ;;
        h) sed -n '2,18p' "$0"; exit 0 ;;
        *) echo "run_graph: see -h" >&2; exit 2 ;;
    esac
done
shift $((OPTIND - 1))
[ "$#" -gt 0 ] || { echo "run_graph: no nodes given (PKG/EXE ...); see -h" >&2; exit 2; }
RUN_DIR="${RUN_DIR:-$ROOT/runs/$(date +%Y%m%d-%H%M%S)}"
mkdir -p "$RUN_DIR"

if [ -z "${AMENT_PREFIX_PATH:-}" ] || [ ! -d "$ROOT/ros2_ws/install" ]; then
    echo "run_graph: the tal environment is not set up: run 'bash scripts/bootstrap.sh && source scripts/env.sh'" >&2
    exit 2
fi

declare -A PIDS=()      # exe -> pid
declare -A NAMES=()     # pid -> exe
stopping=0

stop_monitor() {
    [ -n "$MONITOR_PID" ] || return 0
    kill -TERM "$MONITOR_PID" 2>/dev/null || true
    wait "$MONITOR_PID" 2>/dev/null || true
    MONITOR_PID=""
}

stop_nodes() {
    local sig pid
    for sig in INT TERM KILL; do
        local alive=0
        for pid in "${!NAMES[@]}"; do
            if kill -0 "$pid" 2>/dev/null; then
                alive=1
                kill "-$sig" -- "-$pid" 2>/dev/null || kill "-$sig" "$pid" 2>/dev/null || true
            fi
        done
        [ "$alive" = 1 ] || return 0
        for _ in $(seq 1 30); do  # up to 3 s per signal
            alive=0
            for pid in "${!NAMES[@]}"; do kill -0 "$pid" 2>/dev/null && alive=1; done
            [ "$alive" = 1 ] || return 0
            sleep 0.1
        done
    done
}
# The monitor stops after the nodes; its file keeps the peaks it saw.
stop_all() {
    stopping=1
    stop_nodes
    stop_monitor
}
trap 'stop_all; exit 130' INT
trap 'stop_all; exit 143' TERM

for spec in "$@"; do
    pkg="${spec%%/*}"
    exe="${spec#*/}"
    [ "$pkg" != "$spec" ] || { echo "run_graph: '$spec' is not PKG/EXE" >&2; stop_all; exit 2; }
    binary="$ROOT/ros2_ws/install/$pkg/lib/$pkg/$exe"
    [ -x "$binary" ] || { echo "run_graph: no executable $exe in package $pkg ($binary)" >&2; stop_all; exit 2; }
    args=(--ros-args)
    params="$ROOT/ros2_ws/install/$pkg/share/$pkg/config/$exe.yaml"
    [ -f "$params" ] && args+=(--params-file "$params")
    for override in "${OVERRIDES[@]+"${OVERRIDES[@]}"}"; do
        case "$override" in "$exe".*) args+=(-p "${override#"$exe".}") ;; esac
    done
    if command -v ros2 >/dev/null 2>&1; then
        cmd=(ros2 run "$pkg" "$exe" "${args[@]}")
    else
        cmd=("$binary" "${args[@]}")
    fi
    # setsid: each node leads its own process group, so stop_all reaches its children too.
    if [ -n "${NICENESS[$exe]:-}" ]; then cmd=(nice -n "${NICENESS[$exe]}" "${cmd[@]}"); fi
    if [ -n "${FIFO[$exe]:-}" ]; then
        if chrt -f "${FIFO[$exe]}" true 2>/dev/null; then cmd=(chrt -f "${FIFO[$exe]}" "${cmd[@]}")
        else echo "run_graph: no permission for SCHED_FIFO: $exe runs at normal priority" >&2; fi
    fi
    setsid "${cmd[@]}" > "$RUN_DIR/$exe.log" 2>&1 < /dev/null &
    PIDS[$exe]=$!
    NAMES[$!]=$exe
    echo "$(date +%T) pid $! ${cmd[*]}" >> "$RUN_DIR/graph.log"
done
if [ -n "$MONITOR_OUT" ]; then
    targets=()
    for exe in "${!PIDS[@]}"; do targets+=("$exe=${PIDS[$exe]}"); done
    python -m tal_core.resource_monitor --out "$MONITOR_OUT" "${targets[@]}" >> "$RUN_DIR/graph.log" 2>&1 &
    MONITOR_PID=$!
fi
echo "run_graph: started ${!PIDS[*]} (logs in $RUN_DIR, ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-0})"

code=0
if [ -n "$WAIT_FOR" ]; then
    [ -n "${PIDS[$WAIT_FOR]:-}" ] || { echo "run_graph: -w $WAIT_FOR is not among the nodes" >&2; stop_all; exit 2; }
    # Poll so that a failing helper node also ends the run instead of hanging the waited-for node.
    while kill -0 "${PIDS[$WAIT_FOR]}" 2>/dev/null; do
        for pid in "${!NAMES[@]}"; do
            if ! kill -0 "$pid" 2>/dev/null && [ "$pid" != "${PIDS[$WAIT_FOR]}" ]; then
                wait "$pid" && rc=0 || rc=$?
                if [ "$rc" != 0 ]; then
                    echo "run_graph: ${NAMES[$pid]} exited with code $rc; stopping the graph" >&2
                    stop_all
                    exit "$rc"
                fi
                unset "NAMES[$pid]"
            fi
        done
        sleep 0.2
    done
    wait "${PIDS[$WAIT_FOR]}" && code=0 || code=$?
else
    wait -n && code=0 || code=$?
fi
stop_all
exit "$code"
