"""State estimation on soft terrain (thesis' state-estimation chapter), reproduced in simulation.

HyQ trots in place for ``--duration`` seconds (default 70) on rigid ground and on a 2400 N/m foam (the
thesis' dataset), driven by the sWBC on the ground-truth base state (the estimator is not in the loop,
as in the thesis, which processed a recorded dataset). The 1 kHz IMU (with white noise) and joint
samples are recorded and the estimator is run offline on them, ticking at 333 Hz:

* ``rigid``: the thesis' estimator (binary force-threshold contact, feet assumed static);
* ``terrain_aware (TCE)``: the continuous contact weighting and Kelvin-Voigt foot motion, with the
  stiffness and damping the TCE estimates online (on the ground-truth base, as the thesis' motion
  capture);
* ``terrain_aware (true K, D)``: the same with the true ground parameters (an upper bound).

Then the estimator goes into the loop: STANCE crawls over the transition course on the estimate, once
with the rigid and once with the terrain-aware leg odometry.

Writes ``results/estimation/``: ``summary.md`` and ``summary.json`` (drift, velocity RMSE, attitude
RMSE, chatter per run and estimator) and the thesis-like plots. Usage::

    python -m tal_lab.estimation_experiments [--duration 70] [--out results/estimation]
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tal_core.legs import LEGS, NUM_LEGS
from tal_core.robot_model import RobotModel
from tal_core.rotations import rotation_from_quat_xyzw, so3_log
from tal_core.state import BaseState
from tal_core.terrain import load_course
from tal_estimation.leg_odometry import LegImpedance, LegOdometrySettings
from tal_estimation.state_estimator import StateEstimatorSettings, legs_from_impedance_arrays
from tal_estimation.tce_driver import TceDriver
from tal_lab.closed_loop import ClosedLoopConfig, ClosedLoopLog, run_closed_loop
from tal_lab.offline_estimation import EstimateArrays, SensorArrays, run_estimator
from tal_sim_bridge.bridge_core import BridgeCore, ImuModel
from tal_sim_bridge.effects import ModelEffects
from tal_sim_bridge.physics import RobotState

GYRO_NOISE_RAD_S = 0.002   # [rad/s] per 1 kHz sample
ACCEL_NOISE_M_S2 = 0.05    # [m/s^2] per 1 kHz sample
CHATTER_MAX_S = 0.03       # [s] a contact-flag segment shorter than this is chatter (phases last >= 0.27 s)
SETTLE_S = 2.0             # [s] the robot settles before the estimator starts
ZOOM_S = (30.0, 32.0)      # [s] the thesis' zoom window
SURFACES = {"rigid": "flat_rigid", "soft": "flat_foam"}


@dataclass
class Recording:
    """A closed-loop trot with its 1 kHz sensors and ground truth."""

    surface: str
    log: ClosedLoopLog
    sensors: SensorArrays
    true_position: np.ndarray      # (N, 3) [m] world
    true_quat: np.ndarray          # (N, 4) xyzw
    true_velocity: np.ndarray      # (N, 3) [m/s] world


def record_trot(surface: str, duration_s: float, seed: int = 0, progress: bool = True) -> Recording:
    """Trot in place on ``surface`` (rigid | soft) and record the sensors at 1 kHz."""
    imu = ImuModel(ModelEffects(), gyro_noise_std_rad_s=GYRO_NOISE_RAD_S, accel_noise_std_m_s2=ACCEL_NOISE_M_S2,
                   seed=seed)
    rows: dict[str, list] = {k: [] for k in ("t", "f", "w", "q", "qd", "tau", "p", "quat", "v")}

    def on_step(t: float, state: RobotState, core: BridgeCore) -> None:
        if t < SETTLE_S - 1e-9:
            return
        f, w = imu.measure(state)
        for key, value in (("t", t), ("f", f), ("w", w), ("q", state.joint_position_rad),
                           ("qd", state.joint_velocity_rad_s), ("tau", state.joint_torque_nm),
                           ("p", state.base_position_m), ("quat", state.base_quat_xyzw),
                           ("v", state.base_lin_vel_m_s)):
            rows[key].append(value)

    config = ClosedLoopConfig(name=f"trot-in-place-{surface}", course=SURFACES[surface], gait="trot",
                              duration_s=duration_s + SETTLE_S, progress=progress)
    log = run_closed_loop(config, step_hook=on_step)
    if log.fell:
        raise RuntimeError(f"trot in place on {surface} fell: {log.meta['fall_reason']}")
    a = {k: np.array(v) for k, v in rows.items()}
    sensors = SensorArrays(a["t"], a["f"], a["w"], a["q"], a["qd"], a["tau"])
    return Recording(surface, log, sensors, a["p"], a["quat"], a["v"])


def tce_impedance(recording: Recording, model: RobotModel, period_s: float = 0.003):
    """The TCE's per-leg estimates along the recording (ground-truth base, flat ground at z = 0), ticking on
    every ``period_s`` worth of samples from the first, as a function of time for the terrain-aware leg
    odometry."""
    driver = TceDriver(model, period_s=period_s)
    driver.set_terrain(lambda x, y: 0.0)
    sensors = recording.sensors
    decimation = max(1, round(period_s / float(np.median(np.diff(sensors.t)))))
    times, stiffness, damping, valid, confidence, rigid = [], [], [], [], [], []
    for i in range(0, len(sensors.t), decimation):
        world_R_base = rotation_from_quat_xyzw(recording.true_quat[i])
        base = BaseState(recording.true_position[i], recording.true_quat[i], recording.true_velocity[i],
                         world_R_base @ sensors.angular_rate[i])
        tick = driver.step(float(sensors.t[i]), base, sensors.joint_position[i], sensors.joint_velocity[i],
                           sensors.joint_torque[i])
        times.append(float(sensors.t[i]))
        stiffness.append(tick.stiffness_n_per_m)
        damping.append(tick.damping_ns_per_m)
        valid.append(tick.valid)
        confidence.append(tick.confidence)
        rigid.append([e.rigid for e in tick.estimates])
    times_a, k_a, d_a, valid_a = np.array(times), np.array(stiffness), np.array(damping), np.array(valid)
    confidence_a, rigid_a = np.array(confidence), np.array(rigid, dtype=bool)

    def at(t: float) -> LegImpedance:
        j = max(0, int(np.searchsorted(times_a, t + 1e-9)) - 1)
        return legs_from_impedance_arrays(k_a[j], d_a[j], valid_a[j], confidence=confidence_a[j], rigid=rigid_a[j])

    return at, (times_a, k_a)


def true_impedance(surface: str):
    """The true ground K, D under the feet (uniform courses) for every leg."""
    props = load_course(SURFACES[surface]).properties(0.0, 0.0)
    constant = legs_from_impedance_arrays(np.full(NUM_LEGS, props.stiffness_n_per_m),
                                          np.full(NUM_LEGS, props.damping_ns_per_m), np.ones(NUM_LEGS, bool))
    return lambda t: constant


def metrics(recording: Recording, est: EstimateArrays) -> dict[str, object]:
    """Drift, velocity and attitude errors against ground truth, and contact chatter."""
    t = recording.sensors.t
    index = np.searchsorted(np.round(t * 1e9), np.round(est.t * 1e9))
    p_true, v_true, q_true = recording.true_position[index], recording.true_velocity[index], recording.true_quat[index]
    p_err = (est.position - est.position[0]) - (p_true - p_true[0])
    v_err = est.linear_velocity - v_true
    att = np.array([so3_log(rotation_from_quat_xyzw(a).T @ rotation_from_quat_xyzw(b))
                    for a, b in zip(q_true, est.quat_xyzw)])
    tilt = np.array([np.arccos(np.clip(rotation_from_quat_xyzw(a)[2] @ rotation_from_quat_xyzw(b)[2], -1, 1))
                     for a, b in zip(q_true, est.quat_xyzw)])
    duration = float(est.t[-1] - est.t[0])
    return {
        "duration_s": round(duration, 2),
        "final_drift_m": np.round(p_err[-1], 4).tolist(),
        "rms_drift_m": np.round(np.sqrt(np.mean(p_err**2, axis=0)), 4).tolist(),
        "velocity_rmse_m_s": np.round(np.sqrt(np.mean(v_err**2, axis=0)), 4).tolist(),
        "attitude_rmse_deg": round(float(np.degrees(np.sqrt(np.mean(np.sum(att**2, axis=1))))), 3),
        "tilt_rmse_deg": round(float(np.degrees(np.sqrt(np.mean(tilt**2)))), 3),
        "chatter_per_s": round(chatter_events(est.t, est.contact) / duration, 3),
        "flag_changes_per_s": round(int(np.sum(np.abs(np.diff(est.contact.astype(int), axis=0)))) / duration, 2),
    }


def chatter_events(t: np.ndarray, contact: np.ndarray, max_s: float = CHATTER_MAX_S) -> int:
    """Contact-flag segments (on or off) shorter than ``max_s`` [s], summed over the legs."""
    events = 0
    for leg in range(contact.shape[1]):
        flags = contact[:, leg].astype(int)
        changes = np.flatnonzero(np.diff(flags)) + 1
        starts = np.r_[0, changes]
        ends = np.r_[changes, len(flags)]
        for start, end in zip(starts[1:-1], ends[1:-1]):  # interior segments only
            if t[end - 1] - t[start] < max_s:
                events += 1
    return events


def estimator_settings(mode: str) -> StateEstimatorSettings:
    return StateEstimatorSettings(leg_odometry=LegOdometrySettings(mode=mode))


def estimator_in_the_loop(duration_s: float, progress: bool = True) -> dict[str, dict[str, object]]:
    """STANCE (c3WBC + TCE) crawling at 0.1 m/s over the transition course (rigid, T1, T2, T3, rigid) with
    the controller on the state estimate instead of ground truth: rigid vs terrain-aware leg odometry."""
    from tal_control.wbc import WbcSettings

    results = {}
    for mode in ("rigid", "terrain_aware"):
        config = ClosedLoopConfig(
            name=f"stance-course-estimate-{mode}", course="stance_course", gait="crawl", duration_s=duration_s,
            commands=((0.0, 0.0, 0.0, 0.0), (1.0, 0.1, 0.0, 0.0)), settings=WbcSettings(contact_model="compliant"),
            impedance_source="tce", initial_xy=(0.5, 0.0), state_estimator=estimator_settings(mode),
            imu_noise=(GYRO_NOISE_RAD_S, ACCEL_NOISE_M_S2), progress=progress)
        log = run_closed_loop(config)
        results[mode] = {"fell": log.fell, "fall_time_s": log.meta["fall_time_s"],
                         "fall_reason": log.meta["fall_reason"],
                         "distance_m": round(float(log.base_position[-1, 0] - log.base_position[0, 0]), 3),
                         "final_trunk_height_m": round(float(log.trunk_height[-1]), 3),
                         "sim_time_s": round(float(log.t[-1]), 2)}
    return results


def run(duration_s: float, out: Path, progress: bool = True, loop_duration_s: float = 60.0) -> dict[str, object]:
    out.mkdir(parents=True, exist_ok=True)
    model = RobotModel.from_name("hyq")
    summary: dict[str, object] = {"duration_s": duration_s, "gyro_noise_rad_s": GYRO_NOISE_RAD_S,
                                  "accel_noise_m_s2": ACCEL_NOISE_M_S2, "runs": {}}
    recordings, estimates = {}, {}
    for surface in SURFACES:
        rec = record_trot(surface, duration_s, progress=progress)
        recordings[surface] = rec
        tce_fn, tce_history = tce_impedance(rec, model)
        variants = {"rigid": ("rigid", None), "terrain_aware_tce": ("terrain_aware", tce_fn),
                    "terrain_aware_true": ("terrain_aware", true_impedance(surface))}
        runs = {}
        for name, (mode, impedance) in variants.items():
            if progress:
                sys.stderr.write(f"[estimation] {surface}: estimator {name}\n")
            est = run_estimator(model, rec.sensors, estimator_settings(mode), initial_position=rec.true_position[0],
                                initial_world_R_base=rotation_from_quat_xyzw(rec.true_quat[0]), impedance=impedance)
            estimates[(surface, name)] = est
            runs[name] = metrics(rec, est)
        final_k = tce_history[1][-1]
        runs["tce_final_stiffness_n_per_m"] = {leg.name: round(float(k), 1) for leg, k in zip(LEGS, final_k)}
        summary["runs"][surface] = runs
    summary["improvement_soft"] = _improvement(summary["runs"]["soft"], "terrain_aware_tce")
    summary["change_rigid"] = _improvement(summary["runs"]["rigid"], "terrain_aware_tce")
    if loop_duration_s > 0.0:
        summary["estimator_in_the_loop"] = estimator_in_the_loop(loop_duration_s, progress)
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    (out / "summary.md").write_text(_markdown(summary))
    from tal_lab.estimation_plots import plot_all  # matplotlib only when writing results
    plot_all(recordings, estimates, out)
    return summary


def _improvement(runs: dict, variant: str) -> dict[str, float]:
    """Relative change [%] of the terrain-aware estimator against the rigid one (negative = lower)."""
    base, new = runs["rigid"], runs[variant]
    z_base, z_new = abs(base["final_drift_m"][2]), abs(new["final_drift_m"][2])
    zr_base, zr_new = base["rms_drift_m"][2], new["rms_drift_m"][2]
    v_base = float(np.linalg.norm(base["velocity_rmse_m_s"]))
    v_new = float(np.linalg.norm(new["velocity_rmse_m_s"]))
    return {"final_z_drift_pct": round(100.0 * (z_new - z_base) / max(z_base, 1e-9), 1),
            "rms_z_drift_pct": round(100.0 * (zr_new - zr_base) / max(zr_base, 1e-9), 1),
            "velocity_rmse_norm_pct": round(100.0 * (v_new - v_base) / max(v_base, 1e-9), 1)}


def _markdown(summary: dict) -> str:
    lines = [f"# State estimation: HyQ trotting in place, {summary['duration_s']:.0f} s per surface", "",
             "Command: `python -m tal_lab.estimation_experiments` (part of `make experiments`).",
             f"IMU white noise {summary['gyro_noise_rad_s']} rad/s, {summary['accel_noise_m_s2']} m/s^2 per 1 kHz "
             "sample; estimator at 333 Hz; control on ground truth (estimator offline, as the thesis' dataset).", "",
             "| surface | estimator | final drift x, y, z [m] | RMS drift x, y, z [m] | velocity RMSE x, y, z [m/s] "
             "| attitude RMSE [deg] | tilt RMSE [deg] | chatter [1/s] | flag changes [1/s] |",
             "|---|---|---|---|---|---|---|---|---|"]
    for surface, runs in summary["runs"].items():
        for name, m in runs.items():
            if not isinstance(m, dict) or "final_drift_m" not in m:
                continue
            lines.append(f"| {surface} | {name} | {_fmt(m['final_drift_m'])} | {_fmt(m['rms_drift_m'])} | "
                         f"{_fmt(m['velocity_rmse_m_s'])} | {m['attitude_rmse_deg']} | {m['tilt_rmse_deg']} | "
                         f"{m['chatter_per_s']} | {m['flag_changes_per_s']} |")
    lines += ["", "TCE final stiffness on the soft run [N/m] (truth 2400): "
              + ", ".join(f"{k} {v}" for k, v in summary["runs"]["soft"]["tce_final_stiffness_n_per_m"].items()),
              "", "Terrain-aware (TCE) vs rigid, relative change [%] (goal on soft: z drift <= -50, velocity RMSE "
              "<= -30; on rigid: no worse than +5):", "",
              "| surface | final z drift | RMS z drift | velocity RMSE (norm) |", "|---|---|---|---|"]
    for surface, key in (("soft", "improvement_soft"), ("rigid", "change_rigid")):
        c = summary[key]
        lines.append(f"| {surface} | {c['final_z_drift_pct']:+.1f} | {c['rms_z_drift_pct']:+.1f} | "
                     f"{c['velocity_rmse_norm_pct']:+.1f} |")
    loop = summary.get("estimator_in_the_loop")
    if loop:
        lines += ["", "Estimator in the loop: STANCE (c3WBC + TCE) crawling at 0.1 m/s over rigid -> T1 -> T2 -> T3 "
                  "-> rigid, the controller on the estimate:", "",
                  "| leg odometry | fell | fall time [s] | distance [m] | final trunk height [m] |",
                  "|---|---|---|---|---|"]
        for mode, r in loop.items():
            lines.append(f"| {mode} | {'yes' if r['fell'] else 'no'} | {r['fall_time_s'] or '-'} | {r['distance_m']} | "
                         f"{r['final_trunk_height_m']} |")
    return "\n".join(lines) + "\n"


def _fmt(values: list[float]) -> str:
    return ", ".join(f"{v:+.3f}" for v in values)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=70.0, help="[s] trot per surface (after 2 s settling)")
    parser.add_argument("--loop-duration", type=float, default=60.0,
                        help="[s] estimator-in-the-loop runs on the STANCE course (0: skip)")
    parser.add_argument("--out", type=Path, default=Path("results/estimation"))
    args = parser.parse_args(argv)
    summary = run(args.duration, args.out, loop_duration_s=args.loop_duration)
    sys.stdout.write((args.out / "summary.md").read_text())
    return 0 if summary else 1


if __name__ == "__main__":
    raise SystemExit(main())
