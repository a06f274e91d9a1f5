"""ViTAL's closed-loop experiments: HyQ trots over stairs, gapped stairs and rough terrain in PyBullet.

    python -m tal_lab.vital.vital_experiments --out results/vital [--only speeds,tbr,...] [--jobs 2]

Every run is ``tal_control``'s lockstep closed loop (sWBC on the ground-truth base state, 250 Hz; physics
1 kHz) with ``VitalLoop`` as its tick hook (VFA + VPA or TBR, the nodes' planners, a perfect 121 x 121
heightmap at 20 Hz; VFA and VPA both exact, the VPA at 20 Hz). The controller gets the simulator's foot
contacts (a planned stance foot that does not touch searches for the ground instead of being loaded,
``TouchdownSearch``), ends each swing ``touchdown_depth_m`` below the foothold and places its nominal
footholds with the Raibert velocity feedback ``k_feedback_s`` = 0.12 s (the generator's default 0.05 s
let the trot's roll and lateral sway grow into falls on the stairs), centred under the CoM
(``foothold_centre`` "com": HyQ's CoM is 3.9 cm ahead of its hips' centre), and the VFA compensates a
leg's adaptation with its diagonal partner (``PlannerSettings.pair_compensation_m`` 0.08 m), so that the
trot's support lines pass under the CoM. The body-pose reference (the VPA's, or the default) goes through a
faster filter than the controller's default (6 rad/s, 0.25 m/s, 0.5 rad/s; ``POSE_BANDWIDTH_RAD_S``), which
would let the trunk fall 10-20 cm behind the VPA's height on the way up at 0.4 m/s. Experiments (thesis, ViTAL results):

* ``speeds``: the stairs (rise 0.1 m, go 0.25 m, up and down; course ``vital_stairs``) at 0.2, 0.3, 0.4
  and 0.5 m/s with VFA + VPA, 3 runs each (starts x = -0.1, 0, +0.1 m): success, leg and foot
  collisions, mean absolute pitch and height tracking errors (thesis table: 0.7-2.3 deg, 0.3-3.8 cm);
* ``cnn``: the same stairs at 0.2, 0.3 and 0.4 m/s (3 starts each) with the VPA's CNN (committed weights)
  instead of the exact pose evaluation;
* ``tbr``: VPA vs TBR on the same stairs at 0.2 m/s, 3 runs each (the same starts; the VPA runs are the
  speeds runs): success and the safe footholds at the actual pose (exact evaluation at the actual hips);
* ``gaps``: gapped stairs (``vital_gap_stairs``) at 0.4 m/s with VPA and with TBR;
* ``rough``: cobblestones (``vital_rough``) at 0.2 m/s with ViTAL and blind (nominal footholds, default
  pose): collisions;
* ``horizon``: stairs at 0.4 m/s with N_h = 1 and N_h = 2 (9 starts each): success, pose variation per
  metre dz/dx, dpitch/dx;
* ``cost``: stairs at 0.4 m/s with C_sum and C_int (9 starts each): success, envelope thickness
  |F(u*+m) - F(u*-m)|, m = 0.025 m;
* ``pose_filter`` (ours): the stairs at 0.4 m/s from 9 starts with the controller's default body-pose
  filter (4 rad/s, 0.1 m/s, 0.3 rad/s) against these runs' filter;
* ``step_frequency`` (ours): the stairs at 0.5 m/s from 9 starts at 1.8 Hz (these runs) and at 1.5 Hz;
* ``centre`` (ours): the stairs with the previous footholds (about the hips, no pair compensation) at 0.2
  and 0.3 m/s from the 3 starts (at 0.4 m/s, with the previous body-pose filter, 3 vs 4 of 9 starts
  succeeded: no measurable difference there);
* ``starts`` (ours): the speeds runs' configuration at all four speeds from the 9 starts, with the Wilson
  95 % interval of each success rate (the 0.4 and 0.5 m/s runs are those of ``pose_filter`` and
  ``step_frequency``; 12 runs of its own).
* ``swing_model`` (ours): the starts runs against the same 36 with the VPA's terrain swing model
  (``VpaSettings.swing_hip_model`` "terrain": the hip starts the evaluated swing as high above the lift-off
  terrain as it ends above the map reference) and its legs weighted by their curves' peaks
  (``leg_weighting`` "peak", the thesis' Q).
* ``learned``: both CNNs in the loop, as the thesis' ViTAL ran: the VFA's CNN (committed weights) with the
  verification of the ``vfa`` node's ``cnn`` selector (the exact criteria on the chosen candidate, exact search when it
  fails) and the VPA's CNN, on the stairs at 0.2, 0.3, 0.4 and 0.5 m/s from the 9 starts (as ``starts``);
  and at 0.2 m/s the VFA's CNN alone (``cnn_unverified``, the thesis' g_hat: its unsafe choices reach the
  robot), 9 starts.
* ``moment_weight`` (ours, stop 28): the starts runs against the same 36 with the QP's weights on the trunk's
  moment error 10 times those on its force error (``WbcSettings.wrench_weights`` (1, 1, 1, 10, 10, 10); the
  thesis' Q weighs both 1 per N and per N m). In a trot's two-leg stance the QP buys the moment about the
  support line with force; a lower weight on it made the falls more frequent (probe), so this tries a higher
  one.

The comparisons at 0.4 and 0.5 m/s run from 9 starts (``STARTS_M`` + ``EXTRA_STARTS_M``): single runs there
could succeed or fall by chance.

A run succeeds when the robot reaches the course's goal x without falling (trunk too low or a trunk,
hip or thigh touching the ground) before the run ends: the forward command stops when its path is
``past_goal_m`` (0.6 m) past the goal, and the robot trots in place for ``hold_s`` (3 s). Tracking
errors are taken over the samples after the start (1.5 s).
Writes ``closed_loop.md``, ``closed_loop.json`` and plots into ``--out``; progress on stderr. ``--jobs N``
runs N closed loops at once (separate processes; each run is deterministic, so the results do not depend
on it).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import math
import multiprocessing
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from tal_lab.vital.vital_loop import VitalLoopSettings, collision_events
from tal_perception.vpa_settings import CostKind

START_S = 1.0  # [s] standing before the command starts
SETTLE_S = 1.5  # [s] samples before this are left out of the tracking errors
# The body-pose filter of the ViTAL runs. Climbing the stairs at 0.4-0.5 m/s raises the trunk 0.16-0.2 m/s
# (rise / go = 0.4), more than the controller's default rate limit (0.1 m/s), and a critically damped filter
# lags a ramp by 2 rate / bandwidth: with the defaults the height reference fell 9-10 cm (up to 20 cm) behind
# the VPA's on the way up at 0.4 m/s, the front legs started their swings compressed and their HFE reached its
# limit. 6 rad/s, 0.25 m/s, 0.5 rad/s: 3.5 cm on average (probe sweeps at 0.4 m/s from 9 starts: 9 of 9
# succeeded, against 6 of 9 with 4 rad/s and 5 of 9 with 8 rad/s, 0.3 m/s, 0.6 rad/s).
POSE_BANDWIDTH_RAD_S = 6.0  # [rad/s]
MAX_HEIGHT_RATE_M_S = 0.25  # [m/s]
MAX_ATTITUDE_RATE_RAD_S = 0.5  # [rad/s]
EXPERIMENTS = ("speeds", "cnn", "tbr", "gaps", "rough", "horizon", "cost", "centre", "pose_filter", "step_frequency",
               "starts", "swing_model", "learned", "moment_weight")
MOMENT_WEIGHT_TAG = "moment10"  # run-name tag of the moment_weight experiment (moment weights 10)
MOMENT_WEIGHT = 10.0  # [-] the moment_weight experiment's weight of the moment error relative to the force error
SWING_MODEL_TAG = "terrain_swing"  # run-name tag of the swing_model experiment's VPA (terrain swing, peak weighting)
LEARNED_TAG = "cnns"  # run-name tag of the learned experiment (VFA CNN verified + VPA CNN)
UNVERIFIED_TAG = "cnns_unverified"  # the same with the VFA CNN's choices unverified
# At 0.5 m/s the trot steps at 1.8 Hz instead of its preset 1.5 Hz: the preset's stride (0.33 m) is longer than
# the stairs' go (0.25 m) and made the feet skip treads; at 1.8 Hz it is 0.28 m (probe sweeps from 9 starts: 5 of
# 9 succeeded at 1.8 Hz, 1 of 9 at 1.5 Hz; experiment step_frequency).
FAST_TROT_SPEED_MPS = 0.45  # [m/s] from this commanded speed on
FAST_TROT_STEP_FREQUENCY_HZ = 1.8


@dataclass(frozen=True)
class VitalRun:
    """One closed-loop run. loop None: blind (no VFA, default pose); goal_x_m [m]: success line."""

    name: str
    course: str
    speed_mps: float
    loop: VitalLoopSettings | None
    goal_x_m: float
    initial_x_m: float = 0.0
    past_goal_m: float = 0.6  # [m] the command stops when its path is this far past the goal
    hold_s: float = 3.0  # [s] trotting in place after the command stopped (a fall then still counts)
    contact_feedback: bool = True  # the controller gets the simulator's foot contacts (TouchdownSearch)
    touchdown_depth_m: float = 0.02  # [m] swings end this far below the foothold (MotionParameters)
    k_feedback_s: float = 0.12  # [s] Raibert velocity feedback of the nominal footholds (MotionParameters)
    foothold_centre: str = "com"  # nominal footholds about the CoM, not the hips (MotionParameters)
    # Body-pose reference filter (MotionParameters; None: the controller's 4 rad/s, 0.1 m/s, 0.3 rad/s).
    pose_bandwidth_rad_s: float | None = POSE_BANDWIDTH_RAD_S
    max_height_rate_m_s: float | None = MAX_HEIGHT_RATE_M_S
    max_attitude_rate_rad_s: float | None = MAX_ATTITUDE_RATE_RAD_S
    step_frequency_hz: float | None = None  # [Hz] None: the trot preset's (1.5 Hz)
    # [-] the QP's weights on the trunk's moment error (Tx, Ty, Tz) relative to those on its force error (the
    # thesis' Q: 1, i.e. 1 per N m as per N); WbcSettings.wrench_weights (1, 1, 1, w, w, w)
    moment_weight: float = 1.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.moment_weight) and self.moment_weight > 0.0):
            raise ValueError(f"VitalRun {self.name!r}: moment_weight must be finite and > 0, "
                             f"got {self.moment_weight!r}")

    @property
    def stop_s(self) -> float:
        """[s] when the forward command returns to zero: the commanded path is then ``past_goal_m`` past
        the goal, so a robot lagging its reference by less than that still reaches the goal, and no run
        walks off the end of its course (the stairs course ends 3.2 m past the goal)."""
        return START_S + (self.goal_x_m + self.past_goal_m - self.initial_x_m) / self.speed_mps

    @property
    def duration_s(self) -> float:
        return self.stop_s + self.hold_s


@dataclass
class VitalRunResult:
    """What a run measured (see the module docstring); arrays per leg LF, RF, LH, RH."""

    name: str
    course: str
    speed_mps: float
    success: bool
    fell: bool
    fall_reason: str
    x_end_m: float
    leg_collisions: list[int]
    foot_collisions: list[int]
    pitch_mae_deg: float
    height_mae_cm: float
    height_variation_per_m: float
    pitch_variation_deg_per_m: float
    actual_safe_footholds_mean: float
    actual_safe_footholds_min: float
    envelope_thickness_mean: float
    decisions: int
    adapted: int
    no_safe: int
    vpa_compute_median_ms: float
    wall_s: float
    first_wrench_miss: str = ""  # the first tick where the QP missed the trunk's wrench, and why (fall_analysis)
    # The episodes of QP wrench misses the trot recovered from (fall_analysis.wrench_miss_episodes), each
    # [start s, end s, peak force error N, base x at the start m]; a fall's own episode is not one of them.
    recovered_wrench_misses: list[list[float]] = field(default_factory=list)
    series: dict[str, np.ndarray] = field(default_factory=dict, repr=False)


STARTS_M = (-0.1, 0.0, 0.1)  # [m] start positions of the repeated stairs runs
EXTRA_STARTS_M = (-0.2, -0.15, -0.05, 0.05, 0.15, 0.2)  # [m] more starts for the 0.4 m/s comparison


def step_frequency_for(speed_mps: float) -> float | None:
    """[Hz] the trot's step frequency of a run at ``speed_mps`` (None: the preset's)."""
    return FAST_TROT_STEP_FREQUENCY_HZ if speed_mps >= FAST_TROT_SPEED_MPS else None


def _stairs(name: str, speed: float, loop: VitalLoopSettings | None, x0: float = 0.0) -> VitalRun:
    return VitalRun(name, "vital_stairs", speed, loop, goal_x_m=4.8, initial_x_m=x0,
                    step_frequency_hz=step_frequency_for(speed))


def stairs_name(speed: float, x0: float, source: str = "") -> str:
    """Run name of the stairs at ``speed`` [m/s] from ``x0`` [m] (``source``: "tbr", "cnn" or "" for the exact VPA)."""
    start = f"{x0:+.1f}" if abs(round(x0, 1) - x0) < 1e-9 else f"{x0:+.2f}"
    return f"stairs_{speed:.1f}{'_' + source if source else ''}_x{start}"


def experiment_runs(only: tuple[str, ...] = EXPERIMENTS) -> dict[str, list[VitalRun]]:
    """The runs of each experiment; runs with equal settings are shared (run once)."""
    vital = VitalLoopSettings(monitor_period_s=0.2, vpa_use_cnn=False)
    tbr = replace(vital, pose_source="tbr")
    runs: dict[str, list[VitalRun]] = {}
    if "speeds" in only:
        runs["speeds"] = [_stairs(stairs_name(v, x0), v, vital, x0) for v in (0.2, 0.3, 0.4, 0.5) for x0 in STARTS_M]
    if "cnn" in only:
        cnn = replace(vital, vpa_use_cnn=True)
        runs["cnn"] = [_stairs(stairs_name(v, x0, "cnn"), v, cnn, x0) for v in (0.2, 0.3, 0.4) for x0 in STARTS_M]
    if "tbr" in only:
        runs["tbr"] = [_stairs(stairs_name(0.2, x0, "" if source == "vpa" else "tbr"), 0.2, settings, x0)
                       for source, settings in (("vpa", vital), ("tbr", tbr)) for x0 in STARTS_M]
    if "gaps" in only:
        runs["gaps"] = [VitalRun(f"gap_stairs_0.4_{source}", "vital_gap_stairs", 0.4, settings, goal_x_m=3.2)
                        for source, settings in (("vpa", vital), ("tbr", tbr))]
    if "rough" in only:
        runs["rough"] = [VitalRun("rough_0.2_vital", "vital_rough", 0.2, vital, goal_x_m=4.5),
                         VitalRun("rough_0.2_blind", "vital_rough", 0.2, None, goal_x_m=4.5)]
    # At 0.4 m/s single runs succeed or fall by chance: the comparisons there run from 9 starts each.
    starts_04 = STARTS_M + EXTRA_STARTS_M
    if "horizon" in only:
        single = replace(vital, vpa=replace(vital.vpa, horizon=1))
        runs["horizon"] = ([_stairs(stairs_name(0.4, x0), 0.4, vital, x0) for x0 in starts_04]
                           + [_stairs(stairs_name(0.4, x0, "single_horizon"), 0.4, single, x0) for x0 in starts_04])
    if "cost" in only:
        c_sum = replace(vital, vpa=replace(vital.vpa, cost=CostKind.SUM))
        runs["cost"] = ([_stairs(stairs_name(0.4, x0), 0.4, vital, x0) for x0 in starts_04]
                        + [_stairs(stairs_name(0.4, x0, "c_sum"), 0.4, c_sum, x0) for x0 in starts_04])
    if "centre" in only:
        hips = replace(vital, vfa_planner=replace(vital.vfa_planner, pair_compensation_m=0.0))
        speeds = ((0.2, STARTS_M), (0.3, STARTS_M))
        previous = [replace(_stairs(stairs_name(v, x0, "hips"), v, hips, x0), foothold_centre="hips")
                    for v, starts in speeds for x0 in starts]
        runs["centre"] = [_stairs(stairs_name(v, x0), v, vital, x0) for v, starts in speeds for x0 in starts] + previous
    if "pose_filter" in only:
        default = [replace(_stairs(stairs_name(0.4, x0, "default_filter"), 0.4, vital, x0),
                           pose_bandwidth_rad_s=None, max_height_rate_m_s=None, max_attitude_rate_rad_s=None)
                   for x0 in starts_04]
        runs["pose_filter"] = [_stairs(stairs_name(0.4, x0), 0.4, vital, x0) for x0 in starts_04] + default
    if "step_frequency" in only:
        preset = [replace(_stairs(stairs_name(0.5, x0, "1.5hz"), 0.5, vital, x0), step_frequency_hz=None)
                  for x0 in starts_04]
        runs["step_frequency"] = [_stairs(stairs_name(0.5, x0), 0.5, vital, x0) for x0 in starts_04] + preset
    four_speeds = (0.2, 0.3, 0.4, 0.5)
    # the speeds runs from all 9 starts (shared with the speeds, pose_filter, step_frequency runs); the baseline
    # of the swing_model and moment_weight comparisons
    starts = [_stairs(stairs_name(v, x0), v, vital, x0) for v in four_speeds for x0 in starts_04]
    if "starts" in only:
        runs["starts"] = starts
    if "swing_model" in only:  # the starts runs against the same with the VPA's terrain swing and peak weighting
        terrain = replace(vital, vpa=replace(vital.vpa, swing_hip_model="terrain", leg_weighting="peak"))
        runs["swing_model"] = starts + [_stairs(stairs_name(v, x0, SWING_MODEL_TAG), v, terrain, x0)
                                        for v in four_speeds for x0 in starts_04]
    if "moment_weight" in only:  # the starts runs against the same with the moment error weighted 10
        runs["moment_weight"] = starts + [replace(_stairs(stairs_name(v, x0, MOMENT_WEIGHT_TAG), v, vital, x0),
                                                  moment_weight=MOMENT_WEIGHT) for v in four_speeds for x0 in starts_04]
    if "learned" in only:
        verified = replace(vital, vpa_use_cnn=True, vfa_selector="cnn")
        unverified = replace(vital, vpa_use_cnn=True, vfa_selector="cnn_unverified")
        runs["learned"] = ([_stairs(stairs_name(v, x0, LEARNED_TAG), v, verified, x0)
                            for v in four_speeds for x0 in starts_04]
                           + [_stairs(stairs_name(0.2, x0, UNVERIFIED_TAG), 0.2, unverified, x0) for x0 in starts_04])
    return runs


def run_vital(run: VitalRun, progress: bool = True, max_sim_s: float | None = None) -> VitalRunResult:
    """Run one closed loop and measure it (``max_sim_s`` [s]: cut the run short, for smoke tests)."""
    import torch

    from tal_control.motion.gait import TROT
    from tal_control.motion.generator import MotionParameters
    from tal_control.wbc import WbcSettings
    from tal_core.robot_description import load_robot_description
    from tal_core.robot_model import RobotModel
    from tal_core.terrain import load_course
    from tal_lab.closed_loop import ClosedLoopConfig, run_closed_loop
    from tal_lab.fall_analysis import first_wrench_miss_of_log, wrench_miss_episodes
    from tal_lab.vital.vital_loop import VitalLoop

    torch.set_num_threads(1)  # the CNNs are small; a second thread only contends with the physics
    course = load_course(run.course)
    description = load_robot_description("hyq")
    loop = VitalLoop(course, RobotModel(description),
                     run.loop if run.loop is not None else VitalLoopSettings(vfa=False, pose_source="none"))
    gait = TROT if run.step_frequency_hz is None else replace(TROT, step_frequency_hz=run.step_frequency_hz)
    config = ClosedLoopConfig(name=run.name, course=course, gait=gait,
                              commands=((0.0, 0.0, 0.0, 0.0), (START_S, run.speed_mps, 0.0, 0.0),
                                        (run.stop_s, 0.0, 0.0, 0.0)),
                              duration_s=run.duration_s if max_sim_s is None else min(run.duration_s, max_sim_s),
                              initial_xy=(run.initial_x_m, 0.0), progress=progress,
                              contact_feedback=run.contact_feedback,
                              settings=None if run.moment_weight == 1.0 else WbcSettings(
                                  wrench_weights=(1.0, 1.0, 1.0) + (run.moment_weight,) * 3),
                              motion=MotionParameters(touchdown_depth_m=run.touchdown_depth_m,
                                                      k_feedback=run.k_feedback_s,
                                                      foothold_centre=run.foothold_centre,
                                                      pose_bandwidth_rad_s=run.pose_bandwidth_rad_s,
                                                      max_height_rate_m_s=run.max_height_rate_m_s,
                                                      max_attitude_rate_rad_s=run.max_attitude_rate_rad_s))
    started = time.perf_counter()
    log = run_closed_loop(config, hook=loop)
    wall = time.perf_counter() - started
    trace = loop.trace.arrays()
    n = min(len(log.t), len(trace["t"]))
    mask = log.t[:n] >= SETTLE_S
    pitch_error = np.degrees(np.abs(log.rpy_des[:n, 1] - log.base_rpy[:n, 1]))[mask]
    height_error = 100.0 * np.abs(log.base_position_des[:n, 2] - log.base_position[:n, 2])[mask]
    x = log.base_position[:n, 0]
    reached = bool(np.any(x >= run.goal_x_m))
    # For a fall, the onset of the episode of misses that ended in it (not a transient at the gait start).
    miss = first_wrench_miss_of_log(log, description, WbcSettings().joint_limit_horizon_s, after_s=SETTLE_S,
                                    last_episode=bool(log.fell))
    episodes = wrench_miss_episodes(log.t[:n], log.wrench_des[:n], log.wrench_wbc[:n], after_s=SETTLE_S)
    recovered_misses = [[e.start_s, e.end_s, e.peak_force_error_n, float(np.interp(e.start_s, log.t[:n], x))]
                        for e in episodes if e.recovered]
    pose = trace["pose_reference"][:n]
    dz, dpitch = _variation_per_metre(x, pose[:, 0], np.degrees(pose[:, 2]))
    safe = trace["actual_safe_footholds"][:n]
    thickness = trace["envelope_thickness"][:n]
    return VitalRunResult(
        name=run.name, course=run.course, speed_mps=run.speed_mps, success=reached and not log.fell,
        fell=log.fell, fall_reason=str(log.meta.get("fall_reason", "")), x_end_m=float(x[-1]),
        leg_collisions=collision_events(trace["leg_collision"]).tolist(),
        foot_collisions=collision_events(trace["foot_collision"]).tolist(),
        pitch_mae_deg=_mean(pitch_error), height_mae_cm=_mean(height_error),
        height_variation_per_m=dz, pitch_variation_deg_per_m=dpitch,
        actual_safe_footholds_mean=_mean(safe[np.isfinite(safe)]),
        actual_safe_footholds_min=float(np.nanmin(safe)) if np.isfinite(safe).any() else math.nan,
        envelope_thickness_mean=_mean(thickness[np.isfinite(thickness)]),
        decisions=loop.decisions, adapted=loop.adapted, no_safe=loop.no_safe,
        vpa_compute_median_ms=1e3 * float(np.median(loop.pose_compute_s)) if loop.pose_compute_s else math.nan,
        wall_s=wall, first_wrench_miss="" if miss is None else miss.describe(),
        recovered_wrench_misses=recovered_misses,
        series={"t": log.t[:n], "x": x, "z": log.base_position[:n, 2], "z_des": log.base_position_des[:n, 2],
                "pitch_deg": np.degrees(log.base_rpy[:n, 1]), "pitch_des_deg": np.degrees(log.rpy_des[:n, 1]),
                "pose_reference": pose, "safe": safe, "thickness": thickness,
                "leg_collision": trace["leg_collision"][:n], "foot_collision": trace["foot_collision"][:n],
                "foot_x": log.foot_position[:n, :, 0], "foot_z": log.foot_position[:n, :, 2]})


def _mean(values: np.ndarray) -> float:
    return float(np.mean(values)) if np.size(values) else math.nan


def _variation_per_metre(x: np.ndarray, z_ref: np.ndarray, pitch_ref_deg: np.ndarray) -> tuple[float, float]:
    """Total variation of the pose reference over the distance walked: sum|dz| / sum|dx| [m/m] and
    sum|dpitch| / sum|dx| [deg/m] (thesis: numerical differences of the optimal pose along x)."""
    ok = np.isfinite(z_ref) & np.isfinite(pitch_ref_deg)
    if ok.sum() < 2:
        return math.nan, math.nan
    distance = float(np.sum(np.abs(np.diff(x[ok]))))
    if distance <= 0.0:
        return math.nan, math.nan
    return (float(np.sum(np.abs(np.diff(z_ref[ok])))) / distance,
            float(np.sum(np.abs(np.diff(pitch_ref_deg[ok])))) / distance)


# -- report ---------------------------------------------------------------------------------------------
def _row(r: VitalRunResult) -> str:
    return (f"| {r.name} | {r.speed_mps:.1f} | {'yes' if r.success else 'NO'} | {r.x_end_m:.2f} | "
            f"{sum(r.leg_collisions)} {r.leg_collisions} | {sum(r.foot_collisions)} {r.foot_collisions} | "
            f"{r.pitch_mae_deg:.2f} | {r.height_mae_cm:.2f} | {r.actual_safe_footholds_mean:.0f} | "
            f"{r.adapted}/{r.decisions} | {len(r.recovered_wrench_misses)} | {r.wall_s:.0f} s |")


HEADER = ("| run | speed [m/s] | success | x end [m] | leg collisions (LF, RF, LH, RH) | foot collisions | "
          "pitch MAE [deg] | height MAE [cm] | safe footholds at the actual pose (mean) | adapted/decisions | "
          "recovered QP wrench misses | wall |\n|---|---|---|---|---|---|---|---|---|---|---|---|")


def write_report(out: Path, runs: dict[str, list[VitalRun]], results: dict[str, VitalRunResult]) -> None:
    lines = ["# ViTAL in the closed loop", "",
             "`python -m tal_lab.vital.vital_experiments --out results/vital` (part of `make experiments`). "
             "HyQ, trot, sWBC on the ground-truth base with the simulator's foot contacts (late touchdowns search "
             "for the ground), swings ending 2 cm below the foothold, Raibert velocity feedback 0.12 s on the nominal "
             "footholds, which are centred under the CoM (`foothold_centre` com); VFA with diagonal-pair compensation "
             "(0.08 m); lockstep PyBullet; VFA exact, VPA exact at "
             "20 Hz, N_h = 2, C_int unless the run says otherwise. Collisions are events (a collision starting): leg = "
             "shin/knee cylinder in the terrain by more than 5 mm; foot = swing foot hitting the terrain. Recovered QP "
             "wrench misses: episodes in which the QP's forces missed the trunk's desired wrench by more than 300 N "
             "(misses less than 0.5 s apart are one episode) and the trot went on (a fall's own episode is not "
             "counted; start and base x of each in closed_loop.json). They are routine on these stairs, in "
             "successful runs too, so a miss with a joint at its torque limit (the onsets in the last table) is "
             "how a fall begins, not what decides it.", ""]
    titles = {"speeds": "Stairs (rise 0.1 m, go 0.25 m) at four speeds, VFA + VPA",
              "cnn": "Stairs with the VPA's CNN instead of the exact VPA, VFA + VPA (CNN)",
              "tbr": "VPA vs TBR on the stairs at 0.2 m/s (3 runs each)",
              "gaps": "Gapped stairs at 0.4 m/s", "rough": "Rough terrain at 0.2 m/s, with and without ViTAL",
              "horizon": "Single vs receding horizon (stairs, 0.4 m/s)", "cost": "C_sum vs C_int (stairs, 0.4 m/s)",
              "centre": "Footholds under the CoM with diagonal-pair compensation vs about the hips (previous)",
              "pose_filter": "The body-pose filter of these runs vs the controller's default (stairs, 0.4 m/s)",
              "step_frequency": "Trot at 1.8 Hz vs the preset's 1.5 Hz (stairs, 0.5 m/s)",
              "starts": "Stairs at four speeds from 9 starts each, VFA + VPA (the speeds runs' configuration)",
              "learned": ("Both CNNs in the loop: the VFA's CNN (verified, as the vfa node's cnn selector runs it; "
                          "and alone) and the VPA's CNN"),
              "moment_weight": "The QP's moment error weighted 10 times its force error vs the thesis' equal "
                               "weights (stairs, four speeds, 9 starts)",
              "swing_model": "The VPA's hip following the terrain during the swing and legs weighted by their peaks "
                             "vs the thesis' level hip and equal weights (stairs, four speeds, 9 starts)"}
    for key, group in runs.items():
        lines += [f"## {titles[key]}", "", HEADER] + [_row(results[r.name]) for r in group] + [""]
        if key in SUMMARIES:
            lines += SUMMARIES[key](group, results)
        if key == "centre":
            for label, members in (("under the CoM, pair compensation (these experiments)",
                                    [r for r in group if r.foothold_centre == "com"]),
                                   ("about the hips, no pair compensation (before)",
                                    [r for r in group if r.foothold_centre == "hips"])):
                lines += [f"Footholds {label}:", ""] + speed_summary(members, results)
        lines += NOTES.get(key, [])
        common = _common_path_m([results[r.name] for r in group])
        if key in ("horizon", "cost"):
            lines += config_summary(group, results) + [""]
        if key == "horizon":
            lines += [f"| run | height variation [m/m] | pitch variation [deg/m] | same, over x <= {common:.2f} m "
                      "(the path both runs walked) |", "|---|---|---|---|"]
            for r in group:
                res = results[r.name]
                dz, dp = _variation_over(res, common)
                lines.append(f"| {res.name} | {res.height_variation_per_m:.3f} | {res.pitch_variation_deg_per_m:.1f} | "
                             f"{dz:.3f} m/m, {dp:.1f} deg/m |")
            lines += ["", "Thesis: the receding horizon varies the pose less.", ""]
        if key == "cost":
            lines += [f"| run | envelope thickness (mean over legs and updates) [footholds] | same, over x <= "
                      f"{common:.2f} m |", "|---|---|---|"]
            lines += [f"| {results[r.name].name} | {results[r.name].envelope_thickness_mean:.1f} | "
                      f"{_thickness_over(results[r.name], common):.1f} |" for r in group]
            lines += ["", "Thesis: C_int gives the thinner envelope (more robust to pose tracking errors).", "",
                      "![envelope](vital_cost_envelope.png)", ""]
    failed = [r for r in results.values() if not r.success]
    if failed:
        lines += ["## Why the failed runs fell: where the QP stopped delivering the trunk's wrench", "",
                  "`tal_lab.fall_analysis`: the first control tick of the episode of misses that ended "
                  "in the fall (misses less than 0.5 s apart) where the force part of "
                  "the WBC's centroidal wrench left the desired one by more than 300 N, the planned stance legs, the "
                  "joints at their torque limits and those whose joint-limit acceleration bound had closed (< 50 "
                  "rad/s^2 of room), and the swing leg with the largest swing-task slack.", "",
                  "| run | x end [m] | first wrench miss |", "|---|---|---|"]
        lines += [f"| {r.name} | {r.x_end_m:.2f} | {r.first_wrench_miss or 'none before the fall'} |"
                  for r in sorted(failed, key=lambda r: r.name)]
        lines.append("")
    (out / "closed_loop.md").write_text("\n".join(lines) + "\n")
    payload = {name: {k: v for k, v in vars(r).items() if k != "series"} for name, r in results.items()}
    (out / "closed_loop.json").write_text(json.dumps(payload, indent=1, default=float) + "\n")


def _common_path_m(group: list[VitalRunResult]) -> float:
    """[m] the largest base x every run of ``group`` reached (the path they can be compared on)."""
    return min(float(np.max(r.series["x"])) if "x" in r.series and len(r.series["x"]) else math.nan for r in group)


def _variation_over(r: VitalRunResult, x_max: float) -> tuple[float, float]:
    """``_variation_per_metre`` of ``r``'s pose reference over the samples with base x <= ``x_max`` [m]."""
    s = r.series
    if "x" not in s or not np.isfinite(x_max):
        return math.nan, math.nan
    keep = s["x"] <= x_max
    pose = s["pose_reference"][keep]
    return _variation_per_metre(s["x"][keep], pose[:, 0], np.degrees(pose[:, 2]))


def _thickness_over(r: VitalRunResult, x_max: float) -> float:
    """Mean envelope thickness of ``r`` over the samples with base x <= ``x_max`` [m]."""
    s = r.series
    if "x" not in s or not np.isfinite(x_max):
        return math.nan
    values = s["thickness"][s["x"] <= x_max]
    return _mean(values[np.isfinite(values)])


def _by_config(group: list[VitalRun]) -> dict[str, list[VitalRun]]:
    """The runs of a comparison by configuration (the run names without their start)."""
    configs: dict[str, list[VitalRun]] = {}
    for run in group:
        configs.setdefault(run.name.rsplit("_x", 1)[0], []).append(run)
    return configs


def config_summary(group: list[VitalRun], results: dict[str, VitalRunResult]) -> list[str]:
    """Markdown line: successes per configuration of a comparison."""
    return ["Success: " + "; ".join(f"`{name}` {sum(results[r.name].success for r in runs)} of {len(runs)}"
                                    for name, runs in _by_config(group).items())]


def per_config_summary(group: list[VitalRun], results: dict[str, VitalRunResult]) -> list[str]:
    """Markdown lines: the speed summary of each configuration of a comparison."""
    lines: list[str] = []
    for name, runs in _by_config(group).items():
        lines += [f"`{name}`:", "", *speed_summary(runs, results)]
    return lines


def tagged_summary(tag: str, untagged: str, tagged: str) -> Callable[[list[VitalRun], dict[str, VitalRunResult]],
                                                                     list[str]]:
    """A summary of a two-configuration experiment: the speed summary of the runs whose name lacks ``tag``
    under the heading ``untagged``, then of those with it under ``tagged``."""

    def summary(group: list[VitalRun], results: dict[str, VitalRunResult]) -> list[str]:
        plain = [r for r in group if tag not in r.name]
        marked = [r for r in group if tag in r.name]
        return [f"{untagged}:", "", *speed_summary(plain, results), f"{tagged}:", "", *speed_summary(marked, results)]

    return summary


def speed_summary(group: list[VitalRun], results: dict[str, VitalRunResult]) -> list[str]:
    """Markdown lines: per speed, successes of the repeated runs, collisions summed over them and the
    tracking errors averaged over the successful ones."""
    lines = ["| speed [m/s] | success | success rate, 95 % interval | leg collisions (all runs) | foot collisions "
             "(all runs) | pitch MAE [deg] (successful runs) | height MAE [cm] (successful runs) | recovered "
             "QP wrench misses (all runs) |",
             "|---|---|---|---|---|---|---|---|"]
    for speed in sorted({run.speed_mps for run in group}):
        rs = [results[run.name] for run in group if run.speed_mps == speed]
        ok = [r for r in rs if r.success]
        pitch = f"{np.mean([r.pitch_mae_deg for r in ok]):.2f}" if ok else "-"
        height = f"{np.mean([r.height_mae_cm for r in ok]):.2f}" if ok else "-"
        low, high = wilson_interval(len(ok), len(rs))
        lines.append(f"| {speed:.1f} | {len(ok)} of {len(rs)} | {100 * low:.0f}-{100 * high:.0f} % | "
                     f"{sum(sum(r.leg_collisions) for r in rs)} | {sum(sum(r.foot_collisions) for r in rs)} | "
                     f"{pitch} | {height} | {sum(len(r.recovered_wrench_misses) for r in rs)} |")
    return [*lines, ""]


def wilson_interval(successes: int, trials: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval [-] of a success rate (z = 1.96: 95 %); (0, 1) without trials. Unlike the
    normal approximation it stays inside [0, 1] and is not zero-width at 0 or n successes of few trials."""
    if trials <= 0:
        return 0.0, 1.0
    if not 0 <= successes <= trials:
        raise ValueError(f"successes must be in [0, {trials}], got {successes}")
    rate = successes / trials
    denominator = 1.0 + z * z / trials
    centre = (rate + z * z / (2 * trials)) / denominator
    half = z * math.sqrt(rate * (1.0 - rate) / trials + z * z / (4 * trials * trials)) / denominator
    return max(0.0, centre - half), min(1.0, centre + half)


# The summary table(s) under an experiment's run table, and the note after them.
SUMMARIES: dict[str, Callable[[list[VitalRun], dict[str, VitalRunResult]], list[str]]] = {
    "cnn": speed_summary,
    "speeds": speed_summary,
    "starts": speed_summary,
    "pose_filter": per_config_summary,
    "step_frequency": per_config_summary,
    "swing_model": tagged_summary(SWING_MODEL_TAG, "Thesis' model (`swing_hip_model` level, `leg_weighting` none; "
                                  "the starts runs)", "Terrain swing model and peak weighting (`swing_hip_model` "
                                  "terrain, `leg_weighting` peak)"),
    "moment_weight": tagged_summary(MOMENT_WEIGHT_TAG, "The thesis' wrench weights (the starts runs)",
                                    f"Moment error weighted {MOMENT_WEIGHT:g} (`WbcSettings.wrench_weights` "
                                    f"(1, 1, 1, {MOMENT_WEIGHT:g}, {MOMENT_WEIGHT:g}, {MOMENT_WEIGHT:g}))"),
    "learned": tagged_summary(UNVERIFIED_TAG, "VFA CNN verified (`vfa` node `selector` cnn) + VPA CNN",
                              "VFA CNN alone (`selector` cnn_unverified, the thesis' g_hat) + VPA CNN"),
}
NOTES: dict[str, list[str]] = {
    "centre": ["The runs under the CoM are the speeds runs above.", ""],
    "pose_filter": ["The default filter's rate limit (0.1 m/s) is below the 0.16-0.2 m/s at which the trunk rises on "
                    "these stairs at 0.4-0.5 m/s, and it lags a ramp by 2 rate / bandwidth.", ""],
    "step_frequency": ["At 1.5 Hz and 0.5 m/s the stride (0.33 m) is longer than the stairs' go (0.25 m).", ""],
    "swing_model": ["Why: going down, the front legs lift off the upper tread behind their hips; the thesis' "
                    "evaluation holds the hip at the touchdown height for the whole swing, so those legs were folded "
                    "past their joint limits at lift-off unless the hip stayed high enough that the lower tread was "
                    "barely in reach, and with few safe footholds they weighed little against the hind legs' many.",
                    "", "![swing model](vital_swing_model.png)", ""],
    "starts": ["The start x shifts where the gait's phase meets the first riser. The interval is the Wilson score "
               "interval (95 %) of the success rate over the 9 starts.", ""],
    "speeds": ["Thesis (HyQ, same stairs): pitch MAE 0.7-2.3 deg and height MAE 0.3-3.8 cm from 0.2 to 0.5 m/s, all "
               "successful.", "", "![stairs](vital_stairs_speeds.png)", ""],
    "tbr": ["Thesis: TBR fails, VPA succeeds; TBR has fewer safe footholds.", "", "![VPA vs TBR](vital_vpa_vs_tbr.png)",
            ""],
}


def plot(out: Path, runs: dict[str, list[VitalRun]], results: dict[str, VitalRunResult]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if "speeds" in runs:
        fig, axes = plt.subplots(4, 1, figsize=(9, 10), sharex=True)
        centred = [run for run in runs["speeds"] if run.initial_x_m == 0.0]  # one run per speed
        for run in centred:
            s = results[run.name].series
            axes[0].plot(s["x"], s["z"], label=f"{run.speed_mps:.1f} m/s")
            axes[0].plot(s["x"], s["z_des"], "k:", lw=0.6)
            axes[1].plot(s["x"], s["pitch_deg"])
            axes[1].plot(s["x"], s["pitch_des_deg"], "k:", lw=0.6)
            axes[2].plot(s["x"], 100 * np.abs(s["z_des"] - s["z"]))
            axes[3].plot(s["x"], np.abs(s["pitch_des_deg"] - s["pitch_deg"]))
        first = results[centred[0].name].series
        axes[0].plot(first["x"], first["foot_z"][:, 0], color="grey", lw=0.5, label="LF foot z (0.2 m/s)")
        for ax, label in zip(axes, ("base z [m] (dotted: VPA)", "pitch [deg] (dotted: VPA)", "|height error| [cm]",
                                    "|pitch error| [deg]")):
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
        axes[0].legend(fontsize=7)
        axes[-1].set_xlabel("base x [m]")
        fig.tight_layout()
        fig.savefig(out / "vital_stairs_speeds.png", dpi=110)
        plt.close(fig)
    if "tbr" in runs:
        fig, ax = plt.subplots(figsize=(9, 4))
        for run in runs["tbr"]:
            r = results[run.name]
            s = r.series
            style = "-" if run.loop is not None and run.loop.pose_source == "vpa" else "--"
            ax.plot(s["x"], np.nansum(s["safe"], axis=1), style, lw=0.9,
                    label=f"{run.name} ({'success' if r.success else 'failed'})")
        _finish(plt, fig, ax, "safe footholds at the actual pose (4 legs)", out / "vital_vpa_vs_tbr.png")
    if "cost" in runs:
        fig, ax = plt.subplots(figsize=(9, 4))
        for run in [run for run in runs["cost"] if run.initial_x_m == 0.0]:  # one start per cost
            s = results[run.name].series
            ax.plot(s["x"], np.nanmean(s["thickness"], axis=1), lw=0.9, label=run.name)
        _finish(plt, fig, ax, "|F(u*+m) - F(u*-m)| mean over legs", out / "vital_cost_envelope.png")
    if "swing_model" in runs:
        plot_swing_model(plt, out / "vital_swing_model.png", runs["swing_model"], results)


def plot_swing_model(plt, path: Path, group: list[VitalRun], results: dict[str, VitalRunResult]) -> None:
    """The swing_model experiment: base height and the front legs' safe footholds along the stairs at 0.5 m/s
    from x = 0 under both models (series of those two runs), and per speed the successes and collisions over
    the 9 starts of each model."""
    fig, axes = plt.subplots(3, 1, figsize=(9, 10))
    for run in group:
        s = results[run.name].series
        if run.speed_mps != 0.5 or run.initial_x_m != 0.0 or "x" not in s:
            continue
        terrain = SWING_MODEL_TAG in run.name
        label = "terrain swing, peak weights" if terrain else "thesis (level hip)"
        line = axes[0].plot(s["x"], s["z"], label=f"{label}: base z")[0]
        axes[0].plot(s["x"], s["z_des"], ":", color=line.get_color(), lw=0.8, label=f"{label}: reference")
        axes[1].plot(s["x"], np.nanmean(s["safe"][:, :2], axis=1), color=line.get_color(), lw=0.9, label=label)
    axes[0].set_ylabel("base z [m], 0.5 m/s from x = 0")
    axes[1].set_ylabel("front legs' safe footholds\nat the actual pose (mean)")
    for ax in axes[:2]:
        ax.set_xlabel("base x [m]")
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    speeds = sorted({run.speed_mps for run in group})
    width = 0.2
    for k, terrain in enumerate((False, True)):
        members = [run for run in group if (SWING_MODEL_TAG in run.name) == terrain]
        rs = [[results[run.name] for run in members if run.speed_mps == v] for v in speeds]
        x = np.arange(len(speeds)) + (k - 0.5) * 2 * width
        tag = "terrain" if terrain else "thesis"
        successes = [sum(r.success for r in at_speed) for at_speed in rs]
        collisions = [sum(sum(r.leg_collisions) + sum(r.foot_collisions) for r in at_speed) for at_speed in rs]
        axes[2].bar(x - width / 2, successes, width, label=f"{tag}: successes of 9", alpha=0.8)
        axes[2].bar(x + width / 2, collisions, width, label=f"{tag}: leg + foot collisions", alpha=0.5, hatch="//")
    axes[2].set_xticks(np.arange(len(speeds)), [f"{v:.1f} m/s" for v in speeds])
    axes[2].legend(fontsize=7, ncol=2)
    axes[2].grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _finish(plt, fig, ax, ylabel: str, path: Path) -> None:
    """Label a plot over base x, save it as PNG and close it."""
    ax.set_xlabel("base x [m]")
    ax.set_ylabel(ylabel)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("results/vital"))
    parser.add_argument("--only", default=",".join(EXPERIMENTS), help=f"comma-separated subset of {EXPERIMENTS}")
    parser.add_argument("--jobs", type=int, default=1, help="closed loops run at once (processes)")
    args = parser.parse_args(argv)
    only = tuple(name.strip() for name in args.only.split(",") if name.strip())
    unknown = sorted(set(only) - set(EXPERIMENTS))
    if unknown:
        parser.error(f"unknown experiment(s) {unknown}; known: {', '.join(EXPERIMENTS)}")
    if args.jobs < 1:
        parser.error(f"--jobs must be >= 1, got {args.jobs}")
    args.out.mkdir(parents=True, exist_ok=True)
    runs = experiment_runs(only)
    unique = {run.name: run for group in runs.values() for run in group}
    results: dict[str, VitalRunResult] = {}
    for i, r in enumerate(_run_all(list(unique.values()), args.jobs), start=1):
        results[r.name] = r
        sys.stderr.write(f"[vital] {i}/{len(unique)} {r.name}: {'success' if r.success else 'FAILED'}, x_end "
                         f"{r.x_end_m:.2f} m, leg collisions {sum(r.leg_collisions)}, foot collisions "
                         f"{sum(r.foot_collisions)}, {r.wall_s:.0f} s\n")
    write_report(args.out, runs, results)
    plot(args.out, runs, results)
    print((args.out / "closed_loop.md").read_text())
    return 0


def _run_quietly(run: VitalRun) -> VitalRunResult:
    return run_vital(run, progress=False)


def _run_all(runs: list[VitalRun], jobs: int):
    """Results of ``runs`` as they finish: in this process (jobs 1, with progress bars) or in ``jobs``
    spawned processes (PyBullet and torch state are per process)."""
    if jobs == 1:
        for run in runs:
            sys.stderr.write(f"[vital] {run.name} ({run.duration_s:.0f} s of sim time)\n")
            yield run_vital(run)
        return
    sys.stderr.write(f"[vital] {len(runs)} runs, {jobs} at a time\n")
    context = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(max_workers=jobs, mp_context=context) as pool:
        futures = [pool.submit(_run_quietly, run) for run in runs]
        for future in concurrent.futures.as_completed(futures):
            yield future.result()


if __name__ == "__main__":
    raise SystemExit(main())
