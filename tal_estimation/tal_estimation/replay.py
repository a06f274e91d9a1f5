"""Offline replay: run the state estimator (and the TCE) on a recorded bag, in-process, deterministic and
faster than real time, and write a report.

    python -m tal_estimation.replay BAG [--out DIR] [--leg-odometry rigid|terrain_aware] [--robot hyq]

Reads ``/joint_states`` and ``/imu`` (paired by header stamp), ``/ground_truth/odom`` (initial pose and
the errors, when the bag has it) and ``/state_estimate`` (the estimate the live graph published, to
compare with). The estimator ticks exactly as the ``state_estimator`` node does (tal_estimation.offline).
The TCE runs on the replayed estimate (causal: its impedance reaches the terrain-aware leg odometry at the
next tick). Everything is streamed: memory does not grow with the bag's length (plots use 20 Hz series).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
from pathlib import Path

import numpy as np

from tal_core.bag_io import BagReader
from tal_core.legs import LEGS, NUM_LEGS
from tal_core.robot_model import RobotModel
from tal_core.rotations import rotation_from_quat_xyzw

from .drift_statistics import DriftStatistics
from .leg_odometry import LegOdometrySettings
from .offline import StreamingEstimator
from .state_estimator import StateEstimate, StateEstimatorSettings, legs_from_impedance_arrays
from .tce import FiniteDifferenceAcceleration, TerrainComplianceEstimator

LOG = logging.getLogger("tal_estimation.replay")
PAIRING_WINDOW_NS = 20_000_000   # [ns] a joint or IMU sample unpaired for this long is dropped (counted)
PLOT_PERIOD_NS = 50_000_000      # [ns] plot series decimation (20 Hz)


def _odometry_state(msg) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(position, world_R_base, world velocity) of a nav_msgs/Odometry (twist in the base frame)."""
    p, o, v = msg.pose.pose.position, msg.pose.pose.orientation, msg.twist.twist.linear
    rotation = rotation_from_quat_xyzw(np.array([o.x, o.y, o.z, o.w]))
    return np.array([p.x, p.y, p.z]), rotation, rotation @ np.array([v.x, v.y, v.z])


def _stamp(msg) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


class BagReplay:
    """Streams a bag through the estimator (and TCE); see the module docstring."""

    def __init__(self, model: RobotModel, leg_odometry: str = "rigid", run_tce: bool = True) -> None:
        self.model = model
        self.joint_index = {name: i for i, name in enumerate(model.description.joint_names)}
        self.settings = StateEstimatorSettings(leg_odometry=LegOdometrySettings(mode=leg_odometry))
        self.stream: StreamingEstimator | None = None
        self.tce = TerrainComplianceEstimator(model) if run_tce else None
        self._tce_fd = FiniteDifferenceAcceleration(max_gap_s=1.5 * self.settings.period_s)
        self.impedance = None
        self._joints: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._imu: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._last_sample_ns: int | None = None
        self._initial_pose: tuple[np.ndarray, np.ndarray] | None = None
        self._truth: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._live: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._estimates: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.vs_truth = DriftStatistics(align_start=True)
        self.vs_live = DriftStatistics(align_start=False)
        self.counts = {"samples": 0, "ticks": 0, "unpaired": 0, "duplicates": 0, "rejected": 0}
        self.series: dict[str, list] = {k: [] for k in ("t", "position", "velocity", "truth_position",
                                                        "truth_velocity", "stiffness")}
        self._next_plot_ns = 0

    # -- input ------------------------------------------------------------------------------------------------
    def add(self, topic: str, msg) -> None:
        if topic == "/joint_states":
            self._add_joints(msg)
        elif topic == "/imu":
            stamp = _stamp(msg)
            a, w = msg.linear_acceleration, msg.angular_velocity
            self._imu[stamp] = (np.array([a.x, a.y, a.z]), np.array([w.x, w.y, w.z]))
            self._pair(stamp)
        elif topic == "/ground_truth/odom":
            stamp = _stamp(msg)
            position, rotation, velocity = _odometry_state(msg)
            if self._initial_pose is None:
                self._initial_pose = (position, rotation)
            self._truth[stamp] = (position, velocity)
            self._match(stamp)
        elif topic == "/state_estimate":
            position, _, velocity = _odometry_state(msg)
            self._live[_stamp(msg)] = (position, velocity)
            self._match(_stamp(msg))

    def _add_joints(self, msg) -> None:
        n = len(self.joint_index)
        q, qd, tau = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
        if not (len(msg.position) == len(msg.velocity) == len(msg.effort) == len(msg.name)):
            self.counts["rejected"] += 1
            return
        for name, p, v, e in zip(msg.name, msg.position, msg.velocity, msg.effort):
            k = self.joint_index.get(name)
            if k is None:
                self.counts["rejected"] += 1
                return
            q[k], qd[k], tau[k] = p, v, e
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(qd)) and np.all(np.isfinite(tau))):
            self.counts["rejected"] += 1
            return
        stamp = _stamp(msg)
        self._joints[stamp] = (q, qd, tau)
        self._pair(stamp)

    def _pair(self, stamp: int) -> None:
        """Feed the samples whose joint state and IMU are both in, in stamp order."""
        if stamp in self._joints and stamp in self._imu:
            ready = sorted(s for s in self._joints if s in self._imu)
            for s in ready:
                if self._last_sample_ns is not None and s <= self._last_sample_ns:
                    self.counts["duplicates"] += 1  # the driver's repeated first state
                else:
                    self._sample(s, *self._joints[s], *self._imu[s])
                del self._joints[s], self._imu[s]
        horizon = max(self._joints.keys() | self._imu.keys(), default=stamp) - PAIRING_WINDOW_NS
        for buffer in (self._joints, self._imu):
            for s in [s for s in buffer if s < horizon]:
                del buffer[s]
                self.counts["unpaired"] += 1

    def _sample(self, stamp: int, q, qd, tau, f, w) -> None:
        self._last_sample_ns = stamp
        self.counts["samples"] += 1
        if self.stream is None:
            position, rotation = self._initial_pose if self._initial_pose is not None else (None, None)
            self.stream = StreamingEstimator(self.model, self.settings, initial_position=position,
                                             initial_world_R_base=rotation)
        estimate = self.stream.add(stamp, f, w, q, qd, tau, impedance=self.impedance)
        if estimate is not None:
            self._tick(stamp, estimate, q, qd, tau)

    def _tick(self, stamp: int, e: StateEstimate, q, qd, tau) -> None:
        self.counts["ticks"] += 1
        if self.tce is not None:
            qq = self.model.make_q(e.position, e.quat_xyzw, q)
            v = self.model.make_v(e.linear_velocity, e.world_R_base @ e.angular_velocity_base, qd, e.quat_xyzw)
            samples = self.tce.contact_states(qq, v, tau, lambda x, y: 0.0, vdot=self._tce_fd.update(stamp * 1e-9, v))
            estimates = self.tce.update(samples)
            k = np.array([x.stiffness_n_per_m for x in estimates])
            d = np.array([x.damping_ns_per_m for x in estimates])
            self.impedance = legs_from_impedance_arrays(k, d, np.array([x.valid for x in estimates]))
        if stamp >= self._next_plot_ns:
            self._next_plot_ns = stamp + PLOT_PERIOD_NS
            truth = self._truth.get(stamp)
            self.series["t"].append(stamp * 1e-9)
            self.series["position"].append(e.position)
            self.series["velocity"].append(e.linear_velocity)
            self.series["truth_position"].append(truth[0] if truth else np.full(3, np.nan))
            self.series["truth_velocity"].append(truth[1] if truth else np.full(3, np.nan))
            stiffness = (self.impedance.stiffness_n_per_m if self.impedance is not None else np.full(NUM_LEGS, np.nan))
            self.series["stiffness"].append(np.where(self.impedance.valid, stiffness, np.nan)
                                            if self.impedance is not None else stiffness)
        self._estimates[stamp] = (e.position, e.linear_velocity)
        self._match(stamp)

    def _match(self, stamp: int) -> None:
        """Compare the replayed estimate with ground truth and the live estimate of the same stamp."""
        estimate = self._estimates.get(stamp)
        if estimate is None:
            return
        truth = self._truth.pop(stamp, None) if stamp in self._truth else None
        if truth is not None:
            self.vs_truth.add(stamp * 1e-9, estimate[0] - truth[0], estimate[1] - truth[1])
        live = self._live.pop(stamp, None)
        if live is not None:
            self.vs_live.add(stamp * 1e-9, estimate[0] - live[0], estimate[1] - live[1])
        # Keep the buffers bounded: anything older than the pairing window is not coming any more.
        horizon = stamp - PAIRING_WINDOW_NS
        for buffer in (self._estimates, self._truth, self._live):
            for s in [s for s in buffer if s < horizon]:
                del buffer[s]

    # -- output -----------------------------------------------------------------------------------------------
    def summary(self) -> dict[str, object]:
        estimates = self.tce.estimates if self.tce is not None else []
        return {
            "counts": self.counts, "leg_odometry": self.settings.leg_odometry.mode,
            "vs_ground_truth": self.vs_truth.summary(), "vs_live_estimate": self.vs_live.summary(),
            "tce_final_stiffness_n_per_m": {leg.name: (round(e.stiffness_n_per_m, 1) if math.isfinite(
                e.stiffness_n_per_m) else None) for leg, e in zip(LEGS, estimates)},
        }


def replay_bag(bag: str | Path, model: RobotModel, *, leg_odometry: str = "rigid", run_tce: bool = True,
               progress: bool = False) -> tuple[BagReplay, dict[str, object]]:
    """Replay ``bag`` and return the replay (with its plot series) and its summary."""
    reader = BagReader(bag)
    replay = BagReplay(model, leg_odometry, run_tce)
    topics = ("/joint_states", "/imu", "/ground_truth/odom", "/state_estimate")
    wall = time.perf_counter()
    last_report = wall
    for message in reader.messages(topics):
        replay.add(message.topic, message.message)
        if progress and time.perf_counter() - last_report > 2.0:
            last_report = time.perf_counter()
            sys.stderr.write(f"[replay] t = {message.log_time_ns * 1e-9:.1f} s, {replay.counts['ticks']} ticks\n")
    wall = time.perf_counter() - wall
    summary = replay.summary()
    span = (replay.series["t"][-1] - replay.series["t"][0]) if len(replay.series["t"]) > 1 else 0.0
    summary.update(bag=str(bag), read_complete=reader.report.complete, read_error=reader.report.error,
                   wall_time_s=round(wall, 3), bag_time_s=round(span, 3),
                   real_time_factor=round(span / wall, 2) if wall > 0 else None)
    return replay, summary


def write_report(replay: BagReplay, summary: dict[str, object], out: Path) -> None:
    """summary.json, report.md and the plots (position, velocity, stiffness)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    lines = [f"# Offline replay of {summary['bag']}", "",
             f"Leg odometry {summary['leg_odometry']}; {summary['counts']['ticks']} estimator ticks from "
             f"{summary['counts']['samples']} samples in {summary['wall_time_s']} s "
             f"({summary['real_time_factor']}x real time).", ""]
    for key, title in (("vs_ground_truth", "against ground truth (start aligned)"),
                       ("vs_live_estimate", "against the live state_estimate in the bag")):
        errors = summary[key]
        if errors:
            lines += [f"## Estimate {title}", "", "| | x | y | z |", "|---|---|---|---|"]
            for name, label in (("final_drift_m", "final [m]"), ("rms_drift_m", "RMS [m]"),
                                ("velocity_rmse_m_s", "velocity RMSE [m/s]")):
                lines.append(f"| {label} | " + " | ".join(f"{v:+.3g}" for v in errors[name]) + " |")
            lines.append(f"\nMax abs difference: position {errors['max_abs_position_m']:.3g} m, velocity "
                         f"{errors['max_abs_velocity_m_s']:.3g} m/s over {errors['samples']} ticks.\n")
    stiffness = summary["tce_final_stiffness_n_per_m"]
    if stiffness:
        lines += ["## TCE (on the replayed estimate)", "", "| leg | stiffness [N/m] |", "|---|---|"]
        lines += [f"| {leg} | {k if k is not None else 'n/a'} |" for leg, k in stiffness.items()]
    if not summary["read_complete"]:
        lines += ["", f"The bag ended early: {summary['read_error']}"]
    (out / "report.md").write_text("\n".join(lines) + "\n")
    _plot(replay, out)


def _plot(replay: BagReplay, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = {k: np.array(v) for k, v in replay.series.items()}
    if s["t"].size == 0:
        return
    fig, axes = plt.subplots(2, 3, figsize=(14, 6), sharex=True)
    for i, axis in enumerate("xyz"):
        for row, (key, unit) in enumerate((("position", "m"), ("velocity", "m/s"))):
            ax = axes[row, i]
            ax.plot(s["t"], s[f"truth_{key}"][:, i], "k", lw=1, label="ground truth")
            ax.plot(s["t"], s[key][:, i], "C0", lw=1, label="replayed estimate")
            ax.set_title(f"{key} {axis}")
            ax.set_ylabel(f"[{unit}]")
            ax.set_xlabel("t [s]")
    axes[0, 0].legend()
    fig.suptitle("Offline replay: estimate vs ground truth (world frame)")
    fig.tight_layout()
    fig.savefig(out / "replay_state.png", dpi=100)
    plt.close(fig)
    if np.any(np.isfinite(s["stiffness"])):
        fig, ax = plt.subplots(figsize=(10, 3.5))
        for leg in range(NUM_LEGS):
            ax.semilogy(s["t"], s["stiffness"][:, leg], label=LEGS[leg].name)
        ax.set_xlabel("t [s]")
        ax.set_ylabel("TCE stiffness [N/m]")
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / "replay_stiffness.png", dpi=100)
        plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bag", type=Path, help="bag folder or .mcap file")
    parser.add_argument("--out", type=Path, help="report folder (default: <bag>/replay)")
    parser.add_argument("--leg-odometry", choices=("rigid", "terrain_aware"), default="rigid")
    parser.add_argument("--robot", default="hyq")
    parser.add_argument("--no-tce", action="store_true", help="skip the TCE")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    replay, summary = replay_bag(args.bag, RobotModel.from_name(args.robot), leg_odometry=args.leg_odometry,
                                 run_tce=not args.no_tce, progress=True)
    out = args.out or (args.bag / "replay" if args.bag.is_dir() else args.bag.with_suffix(".replay"))
    write_report(replay, summary, out)
    sys.stdout.write((out / "report.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
