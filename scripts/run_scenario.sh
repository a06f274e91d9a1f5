#!/usr/bin/env bash
# `make run SCENARIO=...`: run one scenario of the full node graph and print its summary.
# Scenarios:
#   tour            (default) the whole graph, each node its own process: HyQ trots at 0.2 m/s for 60 s of sim
#                   time (lockstep) over rigid ground, T1 and T2 soft patches, 4 stairs up, a gap, 4 down (course graph_tour):
#                   sim_bridge (121x121 heightmap) + state_estimator (terrain-aware leg odometry) + tce + wbc
#                   (STANCE: c3WBC with the TCE's impedance; CONTACT_MODEL=rigid: sWBC; the wbc and tce on the state
#                   estimate and the heightmap in its frame, STATE_SOURCE=ground_truth: on the true base and map;
#                   with the bridge's modelled foot sensors (foot_contacts: noise, 4 ms delay, 15 N threshold) for
#                   late and early touchdowns and swings ending 2 cm below the foothold: CONTACT_SOURCE=ground_truth
#                   takes the simulator's contacts, CONTACT_SOURCE=none and TOUCHDOWN_DEPTH_M=0 turn them off; ViTAL's stairs settings of footholds and pose filter) + vfa + vpa
#                   (VPA CNN, 20 Hz) + bag_recorder + cmd_vel_script; prints the summary of graph_report
#   tour_realtime   the same following the wall clock (rates and deadline misses as the machine holds them)
#   stance           STANCE: HyQ crawls at 0.1 m/s over the transition course (rigid, T1 soft, T2, T3,
#                   rigid; 2 m strips) for 90 s of sim time: sim_bridge (81x81 heightmap) + state_estimator
#                   (terrain-aware leg odometry) + wbc (c3WBC on the estimate) + tce (ground-truth base, as
#                   the thesis' motion capture) + cmd_vel_script; prints the report
#   trot            HyQ trots forward at 0.3 m/s on rigid ground for 20 s of sim time (lockstep):
#                   sim_bridge + state_estimator + wbc (sWBC on the estimate) + cmd_vel_script; prints
#                   tracking errors, estimator drift and whether it fell
#   trot_realtime   the same following the wall clock: sim_bridge, state_estimator, wbc, cmd_vel_script (RECORD=1
#                   adds the bag_recorder, which overloads two cores)
#   crawl           the same with a crawl at 0.1 m/s
#   stairs          ViTAL's VFA: HyQ trots at 0.3 m/s over the stairs course (5 steps up, rise 0.1 m, go 0.3 m,
#                   plateau, 5 steps down) for 30 s of sim time (lockstep): the trot graph on the ground-truth
#                   base state (the vfa has no map z alignment to the estimate yet) with a 121x121 heightmap
#                   and the vfa node adapting the footholds; VFA=0 runs the same without the vfa
#   stand           HyQ stands 10 s in lockstep (joint PD hold), first on rigid ground, then on T1 soft
#   stand_realtime  the same, following the wall clock
# VFA=1 adds the vfa node (and a 121x121 heightmap) to trot and crawl too; its counters go to vfa_summary.json.
# Results (RUNS_DIR=... for another folder than runs/): runs/<timestamp>/<part>/ (one log per node, summary.json), runs/<timestamp>/report.md and, for the
# walking scenarios, runs/<timestamp>/bag (the run recorded by bag_recorder).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
SCENARIO="${1:-tour}"
RUN_ROOT="${RUNS_DIR:-$ROOT/runs}/$(date +%Y%m%d-%H%M%S)-$SCENARIO"
# What make run records into runs/<timestamp>/bag (rosbag2 MCAP; sim time as log time).
RECORDED_TOPICS="['joint_states', 'imu', 'ground_truth/odom', 'ground_truth/contacts', 'joint_command', \
'state_estimate', 'contact_estimate', 'terrain_impedance', 'gait_state', 'wbc/diagnostics', 'cmd_vel', 'cmd_vel_stamped']"
# PARAMS="exe.param:=value ..." adds parameter overrides to every node started (after the scenario's own).
EXTRA=()
for override in ${PARAMS:-}; do EXTRA+=(-s "$override"); done
# ROS parameters are typed: DURATION_S=20 would reach a double parameter as an integer and stop the node.
for var in DURATION_S SPEED_M_S TOUCHDOWN_DEPTH_M; do
    if [[ "${!var:-}" =~ ^-?[0-9]+$ ]]; then printf -v "$var" '%s.0' "${!var}"; fi
done
# Every scenario with the wbc also starts cmd_vel_script: the wbc's first tick waits for it (lockstep), and for
# the first answers of the nodes it waits for (tce, vfa, vpa): eight Python processes starting on two busy
# cores took more than 10 s.
COMMAND_SOURCE_WAIT_S=30.0
# A private DDS domain per run, so concurrent runs and tests do not see each other.
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(( (RANDOM % 100) + 1 ))}"

# On the wall clock the next joint sample comes 1 ms after a tick's, before the estimator's answer to it: the wbc
# waits up to 6 ms of sim time for the base state of its tick (lockstep: 0, the bridge waits for the command).
max_defer() { if [ "$1" = realtime ]; then echo 0.006; else echo 0.0; fi; }
# The tce is not what the bridge waits for: in lockstep a later joint sample (up to the next control tick, the
# wbc waits for the tce's answer before the one after) may come before its tick's base state (another topic).
tce_max_defer() { if [ "$1" = realtime ]; then echo 0.006; else echo 0.004; fi; }
# In lockstep every consumer of the heightmap (wbc, tce, vfa, vpa) waits for the map due at its tick: the bridge
# publishes one every 50 ms of sim time (sim_bridge.heightmap_rate_hz 20), and DDS gives no order between topics
# (a CI machine delivered a map after the next tick's joint state). On the wall clock nobody waits for maps.
map_period() { if [ "$1" = realtime ]; then echo 0.0; else echo 0.05; fi; }
# ... and a lockstep bridge takes its first step once that many map consumers have subscribed (DDS drops the
# first map for a subscription that matches after it; a CI run's vpa planned its 0.052 s update without it).
map_subscribers() { if [ "$1" = realtime ]; then echo 0; else echo "$2"; fi; }
# In lockstep the estimator's tick uses the tce's answer one tce period (4 ms) back and waits for it, so a run
# on the estimate repeats itself bit for bit; on the wall clock it takes the latest impedance as it arrives.
# A later joint sample (up to one tce period on) may come before the answer (another topic): it waits that long.
impedance_period() { if [ "$1" = realtime ]; then echo 0.0; else echo 0.004; fi; }

walk() {
    local gait="$1" speed="$2" course="${3:-flat_rigid}" state_source="${4:-estimate}" duration="${DURATION_S:-20.0}"
    local dir="$RUN_ROOT" topics="$RECORDED_TOPICS" mode="${MODE:-lockstep}"
    local nodes=(tal_sim_bridge/sim_bridge tal_estimation/state_estimator tal_control/wbc tal_control/cmd_vel_script)
    # On the wall clock the recorder's twelve subscriptions (three at 1 kHz) overload two cores: it records only
    # when asked (RECORD=1).
    if [ "$mode" != realtime ] || [ "${RECORD:-0}" = 1 ]; then nodes+=(tal_sim_bridge/bag_recorder); fi
    local vfa=()
    if [ "${VFA:-0}" = 1 ]; then
        # The map must reach the footholds (~0.5 m ahead of the base) plus half a 33-cell FEC patch.
        nodes+=(tal_perception/vfa)
        vfa=(-s "sim_bridge.heightmap_rows:=121" -s "sim_bridge.heightmap_cols:=121"
             -s "vfa.use_sim_time:=true" -s "vfa.summary_path:=$dir/vfa_summary.json"
             -s "vfa.map_period_s:=$(map_period "$mode")")
        topics="${topics%]}, 'footholds']"
    fi
    echo "[run] $SCENARIO: HyQ ${gait}s at $speed m/s on '$course' for $duration s of sim time ($mode)," \
         "base state from $state_source, vfa ${VFA:-0}"
    bash "$ROOT/scripts/run_graph.sh" -d "$dir" -w sim_bridge \
        -s "sim_bridge.course:=$course" -s "sim_bridge.duration_s:=$duration" -s "sim_bridge.mode:=$mode" \
        -s "sim_bridge.summary_path:=$dir/bridge_summary.json" -s "wbc.max_defer_s:=$(max_defer "$mode")" \
        -s "wbc.heightmap_period_s:=$(map_period "$mode")" \
        -s "wbc.gait:=$gait" -s "wbc.summary_path:=$dir/wbc_summary.json" -s "wbc.command_source_wait_s:=$COMMAND_SOURCE_WAIT_S" -s "wbc.state_source:=$state_source" \
        -s "state_estimator.summary_path:=$dir/estimator_summary.json" \
        -s "bag_recorder.output:=$dir/bag" -s "bag_recorder.use_sim_time:=true" \
        -s "bag_recorder.topics:=$topics" \
        -s "bag_recorder.summary_path:=$dir/recorder_summary.json" \
        -s "cmd_vel_script.profile:=[0.0, 0.0, 0.0, 0.0, 1.0, $speed, 0.0, 0.0]" \
        "${vfa[@]+"${vfa[@]}"}" "${EXTRA[@]+"${EXTRA[@]}"}" "${nodes[@]}" \
        || { echo "[run] the graph failed; logs in $dir" >&2; tail -n 20 "$dir"/*.log >&2; exit 1; }
    python -m tal_lab.run_report --bridge "$dir/bridge_summary.json" --wbc "$dir/wbc_summary.json" \
        --estimator "$dir/estimator_summary.json" \
        --title "HyQ $gait at $speed m/s on '$course', control on the $state_source base state" --output "$RUN_ROOT/report.md"
    if [ -f "$dir/vfa_summary.json" ]; then
        { echo; echo "## vfa (footholds)"; echo; echo '```json'; cat "$dir/vfa_summary.json"; echo '```'; } >> "$RUN_ROOT/report.md"
    fi
}

stance() {
    local speed="${SPEED_M_S:-0.1}" duration="${DURATION_S:-90.0}"
    local dir="$RUN_ROOT"
    echo "[run] stance: STANCE (c3WBC + TCE), HyQ crawls at $speed m/s over rigid -> T1 -> T2 -> T3 -> rigid" \
         "for $duration s of sim time (lockstep)"
    bash "$ROOT/scripts/run_graph.sh" -d "$dir" -w sim_bridge \
        -s "sim_bridge.course:=stance_course" -s "sim_bridge.duration_s:=$duration" \
        -s "sim_bridge.initial_x_m:=0.5" \
        -s "sim_bridge.heightmap_rows:=81" -s "sim_bridge.heightmap_cols:=81" \
        -s "sim_bridge.summary_path:=$dir/bridge_summary.json" \
        -s "wbc.gait:=crawl" -s "wbc.contact_model:=compliant" -s "wbc.impedance_source:=tce" \
        -s "wbc.heightmap_period_s:=$(map_period lockstep)" -s "tce.heightmap_period_s:=$(map_period lockstep)" \
        -s "sim_bridge.map_subscribers:=$(map_subscribers lockstep 2)" \
        -s "wbc.summary_path:=$dir/wbc_summary.json" -s "wbc.command_source_wait_s:=$COMMAND_SOURCE_WAIT_S" \
        -s "tce.base_source:=ground_truth" -s "tce.summary_path:=$dir/tce_summary.json" \
        -s "state_estimator.leg_odometry:=terrain_aware" \
        -s "state_estimator.impedance_period_s:=$(impedance_period lockstep)" \
        -s "state_estimator.impedance_max_defer_s:=$(impedance_period lockstep)" \
        -s "state_estimator.summary_path:=$dir/estimator_summary.json" \
        -s "bag_recorder.output:=$dir/bag" -s "bag_recorder.use_sim_time:=true" \
        -s "bag_recorder.topics:=$RECORDED_TOPICS" \
        -s "bag_recorder.summary_path:=$dir/recorder_summary.json" \
        -s "cmd_vel_script.profile:=[0.0, 0.0, 0.0, 0.0, 1.0, $speed, 0.0, 0.0]" \
        "${EXTRA[@]+"${EXTRA[@]}"}" tal_sim_bridge/sim_bridge tal_estimation/state_estimator tal_control/wbc \
        tal_estimation/tce tal_control/cmd_vel_script tal_sim_bridge/bag_recorder \
        || { echo "[run] the graph failed; logs in $dir" >&2; tail -n 20 "$dir"/*.log >&2; exit 1; }
    python -m tal_lab.run_report --bridge "$dir/bridge_summary.json" --wbc "$dir/wbc_summary.json" \
        --tce "$dir/tce_summary.json" --estimator "$dir/estimator_summary.json" --title "STANCE: HyQ crawl at $speed m/s, rigid -> T1 -> T2 -> T3 -> rigid" --output "$RUN_ROOT/report.md"
}

tour() {
    local mode="${MODE:-lockstep}" speed="${SPEED_M_S:-0.2}"
    # Lockstep: 60 s, the whole course (the stairs up, the gap and the stairs down). On the wall clock: 40 s (HyQ falls at
    # 30-35 s there; the bench's measurement window).
    local duration="${DURATION_S:-$([ "$mode" = realtime ] && echo 40.0 || echo 60.0)}"
    local contact_model="${CONTACT_MODEL:-compliant}" odometry="${LEG_ODOMETRY:-terrain_aware}"
    local contact_source="${CONTACT_SOURCE:-sensor}" touchdown_depth="${TOUCHDOWN_DEPTH_M:-0.02}"
    local dir="$RUN_ROOT"
    # A robot has no ground truth: the wbc and the tce run on the state estimate, and the heightmap the wbc, vfa,
    # vpa and tce read is in the estimate's frame, as a robot's own elevation map would be (the bridge places
    # each map with the estimate of its instant). STATE_SOURCE=ground_truth runs them on the true base and map
    # (the thesis' motion capture).
    local state_source="${STATE_SOURCE:-estimate}" map_frame=estimate
    case "$state_source" in
        estimate) ;;
        ground_truth) map_frame=world ;;
        *) echo "STATE_SOURCE must be estimate or ground_truth, got '$state_source'" >&2; exit 2 ;;
    esac
    local topics="${RECORDED_TOPICS%]}, 'footholds', 'body_pose_reference']"
    # Lockstep: the wbc waits for every input's answer to the previous tick (tce, vfa, vpa on its 50 ms grid),
    # so the run repeats itself bit for bit; on the wall clock the wbc waits for nobody's estimates.
    local lockstep=true pose_period=0.05 priorities=()
    # On the wall clock two cores are not enough for all eight: the control chain runs under the real-time FIFO
    # scheduler (bridge 30, wbc 20, estimator 10; as a robot's control loop would; without the permission it
    # runs at normal priority), the tce and perception at normal priority, the script and the recorder niced.
    # RT_PRIORITIES="-r EXE:PRIO -n EXE:NICE ..." replaces these.
    if [ "$mode" = realtime ]; then
        lockstep=false; pose_period=0.0
        # shellcheck disable=SC2206
        priorities=(${RT_PRIORITIES:--r sim_bridge:30 -r wbc:20 -r state_estimator:10 -n cmd_vel_script:10 -n bag_recorder:15})
    fi
    # On the wall clock the recorder keeps only what the report reads (each node's main output, the base track,
    # contacts and stiffness) unless asked (RECORD=1): the two 1 kHz topics alone cost 2,000 deliveries a
    # second on two cores. The bridge's rate is then its contacts'; the wbc skips its diagnostics (no subscriber).
    # The first tick waits for the tce's first answer and the vfa's and vpa's discovery in both modes (lockstep
    # already waits for every answer): on the wall clock a wbc that started walking while they still loaded
    # (10-15 s on two cores) was starved and HyQ fell at 2-3 s.
    # The wbc uses ViTAL's stairs settings over the whole tour (Raibert feedback 0.12 s, footholds about the
    # CoM, pose filter 6 rad/s, rate limits 0.25 m/s and 0.5 rad/s): in lockstep the roll RMS fell from
    # 0.034 to 0.020 rad on rigid ground and from 0.025 to 0.008 on T1/T2, the velocity error from 0.053 to
    # 0.030 m/s, and the largest roll on the stairs up from 0.34 to 0.26 rad.
    local stairs_settings=(-s "wbc.foothold_feedback_s:=0.12" -s "wbc.foothold_centre:=com"
                           -s "wbc.pose_bandwidth_rad_s:=6.0" -s "wbc.pose_max_height_rate_m_s:=0.25"
                           -s "wbc.pose_max_attitude_rate_rad_s:=0.5")
    if [ "$mode" = realtime ] && [ "${RECORD:-0}" != 1 ]; then
        topics="['ground_truth/odom', 'ground_truth/contacts', 'joint_command', 'state_estimate', \
'terrain_impedance', 'footholds', 'body_pose_reference', 'cmd_vel_stamped']"
    fi
    echo "[run] tour: the whole graph ($mode, control and TCE on the $state_source base state). HyQ trots at $speed m/s over rigid -> T1 -> T2 -> rigid -> 4 stairs" \
         "up -> landing with a gap -> stairs down for $duration s of sim time: sim_bridge, state_estimator ($odometry leg odometry), tce," \
         "wbc ($contact_model contact model), vfa, vpa, bag_recorder, cmd_vel_script"
    bash "$ROOT/scripts/run_graph.sh" -d "$dir" -w sim_bridge -m "$dir/resources.json" "${priorities[@]}" \
        -s "sim_bridge.course:=graph_tour" -s "sim_bridge.duration_s:=$duration" -s "sim_bridge.mode:=$mode" \
        -s "wbc.max_defer_s:=$(max_defer "$mode")" -s "tce.max_defer_s:=$(tce_max_defer "$mode")" \
        -s "vfa.answer_every_gait_state:=$lockstep" -s "wbc.wait_for_footholds:=$lockstep" \
        -s "wbc.body_pose_period_s:=$pose_period" -s "wbc.wait_for_impedance:=$lockstep" \
        -s "wbc.startup_inputs:=impedance,footholds,body_pose" "${stairs_settings[@]}" \
        -s "wbc.heightmap_period_s:=$(map_period "$mode")" -s "tce.heightmap_period_s:=$(map_period "$mode")" \
        -s "vfa.map_period_s:=$(map_period "$mode")" -s "vpa.map_period_s:=$(map_period "$mode")" \
        -s "sim_bridge.map_subscribers:=$(map_subscribers "$mode" 4)" \
        -s "sim_bridge.heightmap_rows:=121" -s "sim_bridge.heightmap_cols:=121" \
        -s "sim_bridge.summary_path:=$dir/bridge_summary.json" \
        -s "wbc.gait:=trot" -s "wbc.contact_model:=$contact_model" -s "wbc.impedance_source:=tce" \
        -s "wbc.state_source:=$state_source" -s "wbc.summary_path:=$dir/wbc_summary.json" -s "wbc.command_source_wait_s:=$COMMAND_SOURCE_WAIT_S" \
        -s "wbc.contact_source:=$contact_source" -s "wbc.touchdown_depth_m:=$touchdown_depth" \
        -s "sim_bridge.foot_sensors:=$([ "$contact_source" = sensor ] && echo true || echo false)" \
        -s "wbc.contact_grace_s:=$([ "$contact_source" = sensor ] && echo 0.012 || echo 0.0)" \
        -s "wbc.contact_latch:=$([ "$contact_source" = sensor ] && echo true || echo false)" \
        -s "sim_bridge.heightmap_frame:=$map_frame" -s "wbc.map_alignment_time_constant_s:=0.0" \
        -s "tce.base_source:=$state_source" -s "tce.summary_path:=$dir/tce_summary.json" \
        -s "state_estimator.leg_odometry:=$odometry" \
        -s "state_estimator.impedance_period_s:=$(impedance_period "$mode")" \
        -s "state_estimator.impedance_max_defer_s:=$(impedance_period "$mode")" \
        -s "state_estimator.summary_path:=$dir/estimator_summary.json" \
        -s "vfa.summary_path:=$dir/vfa_summary.json" -s "vpa.summary_path:=$dir/vpa_summary.json" \
        -s "bag_recorder.output:=$dir/bag" -s "bag_recorder.use_sim_time:=true" \
        -s "bag_recorder.topics:=$topics" -s "bag_recorder.summary_path:=$dir/recorder_summary.json" \
        -s "cmd_vel_script.profile:=[0.0, 0.0, 0.0, 0.0, 1.0, $speed, 0.0, 0.0]" \
        "${EXTRA[@]+"${EXTRA[@]}"}" \
        tal_sim_bridge/sim_bridge tal_estimation/state_estimator tal_estimation/tce tal_control/wbc \
        tal_perception/vfa tal_perception/vpa tal_control/cmd_vel_script tal_sim_bridge/bag_recorder \
        || { echo "[run] the graph failed; logs in $dir" >&2; tail -n 20 "$dir"/*.log >&2; exit 1; }
    local bench=()
    # A real-time tour is the graph-rates measurement of `make bench` (bench/report.py reads it).
    [ "$mode" = realtime ] && bench=(--bench-json "$ROOT/bench/out/graph_rates.json")
    python -m tal_lab.graph_report "$dir" --title "tour ($mode): HyQ trots at $speed m/s over rigid, T1, T2 and stairs" \
        "${bench[@]+"${bench[@]}"}"
}

stand() {
    local mode="$1"
    DURATION_S="${DURATION_S:-10.0}"
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
    python -m tal_lab.stand_report --output "$RUN_ROOT/report.md" "${parts[@]}"
}

case "$SCENARIO" in
    tour) tour ;;
    tour_realtime) MODE=realtime tour ;;
    stance) stance ;;
    trot) walk trot 0.3 ;;
    trot_realtime) MODE=realtime walk trot 0.3 ;;
    crawl) walk crawl 0.1 ;;
    stairs) VFA="${VFA:-1}" DURATION_S="${DURATION_S:-30.0}" walk trot 0.3 stairs ground_truth ;;
    stand) stand lockstep ;;
    stand_realtime) stand realtime ;;
    *) echo "unknown SCENARIO '$SCENARIO'; known: tour, tour_realtime, stance, trot, trot_realtime, crawl, stairs, stand, stand_realtime" >&2; exit 2 ;;
esac
echo "[run] report: $RUN_ROOT/report.md"
if [ -d "$RUN_ROOT/bag" ]; then echo "[run] bag (rosbag2 MCAP): $RUN_ROOT/bag"; fi
