"""Offline replay: run the state estimator (and the TCE) on a recorded bag, in-process, deterministic and
faster than real time, and write a report.

    python -m tal_lab.estimation_replay BAG [--out DIR] [--leg-odometry rigid|terrain_aware] [--robot hyq]
        [--course NAME|PATH|flat] [--tce-base estimate|ground_truth]

Reads ``/joint_states`` and ``/imu``, ``/ground_truth/odom`` (initial pose and the errors, when the bag has
it) and ``/state_estimate`` (the estimate the live graph published, to compare with). The messages go in
bag order through the nodes' own timing (tal_estimation.streaming and tal_estimation.tce_driver), so the
estimator ticks, pairs samples by stamp and rejects input exactly as the ``state_estimator`` node does. The
estimator starts at the bag's first ground truth if it comes before the first tick, else standing at the
origin. The TCE runs on the replayed estimate (``--tce-base estimate``) or, as the live graph's ``tce`` node
by default (the thesis' motion capture), on the bag's ground truth (``--tce-base ground_truth``), over the
course's undeformed surface (``--course``; by default the course in the run's bridge_summary.json next to the
bag, else flat ground at z = 0) (causal: its impedance reaches the terrain-aware leg odometry at the next
tick). With a course and ground truth the report has the drift per course section (``section_drift``).
Everything is streamed: memory does not grow with the bag's length (plots use 20 Hz series).
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
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu, JointState

from tal_core.errors import InputError
from tal_core.legs import LEGS, NUM_LEGS
from tal_core.robot_model import RobotModel
from tal_core.ros.bag_io import BagReader
from tal_core.ros.cdr import CdrReader
from tal_core.ros.conversions import JointStateReader, base_state_from_odometry_view
from tal_core.rotations import rotation_from_quat_xyzw
from tal_core.terrain import Course, load_course
from tal_estimation.drift_statistics import DriftStatistics
from tal_estimation.leg_odometry import LegOdometrySettings
from tal_estimation.state_estimator import StateEstimatorSettings, legs_from_impedance_arrays
from tal_estimation.streaming import EstimatorOutput, StreamingEstimator
from tal_estimation.tce import PENETRATION_REFERENCES, TceSettings
from tal_estimation.tce_driver import TceDriver

from .section_drift import SectionDrift, format_section_table

LOG = logging.getLogger("tal_lab.estimation_replay")
TCE_BASES = ("estimate", "ground_truth")
# The topics read, and their types (read in place, as the nodes read them).
REPLAY_TOPICS = {"/joint_states": JointState, "/imu": Imu, "/ground_truth/odom": Odometry, "/state_estimate": Odometry}
MATCH_WINDOW_NS = 20_000_000     # [ns] an estimate, truth or live sample unmatched for this long is dropped
PLOT_PERIOD_NS = 50_000_000      # [ns] plot series decimation (20 Hz)


class BagReplay:
    """Streams a bag through the estimator (and TCE); see the module docstring."""

    def __init__(self, model: RobotModel, leg_odometry: str = "rigid", run_tce: bool = True,
                 tce_base: str = "estimate", course: Course | None = None, vertical_crossover_rad_s: float = 0.0,
                 penetration_reference: str = "surface",
                 leg_velocity_gate_m_s: float = StateEstimatorSettings.leg_velocity_gate_m_s,
                 base_drift_fit: bool = False) -> None:
        if tce_base not in TCE_BASES:
            raise ValueError(f"tce_base must be one of {TCE_BASES}, got {tce_base!r}")
        self.model = model
        self.tce_base = tce_base
        self.course = course
        self.joint_index = {name: i for i, name in enumerate(model.description.joint_names)}
        self.settings = StateEstimatorSettings(leg_odometry=LegOdometrySettings(mode=leg_odometry),
                                               vertical_crossover_rad_s=vertical_crossover_rad_s,
                                               leg_velocity_gate_m_s=leg_velocity_gate_m_s)
        self.stream = StreamingEstimator(model, self.settings)
        self.tce: TceDriver | None = None
        if run_tce:
            self.tce = TceDriver(model, TceSettings(penetration_reference=penetration_reference,
                                                    base_drift_fit=base_drift_fit),
                                 period_s=self.settings.period_s)
            if course is None:
                self.tce.set_terrain(lambda x, y: 0.0)
            else:
                self.tce.set_terrain(course.height, course.normal)
        self.sections = SectionDrift(course.patch_at) if course is not None else None
        self._section_offset: np.ndarray | None = None
        self._truth: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._live: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._estimates: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.vs_truth = DriftStatistics(align_start=True)
        self.vs_live = DriftStatistics(align_start=False)
        self.joint_samples = 0
        self.imu_samples = 0
        self.unreadable: dict[str, int] = {}   # topic -> records that could not be read
        self.read_joints = JointStateReader(self.joint_index, efforts=True)
        self._readers = {topic: CdrReader(msg_type) for topic, msg_type in REPLAY_TOPICS.items()}
        self.series: dict[str, list] = {k: [] for k in ("t", "position", "velocity", "truth_position",
                                                        "truth_velocity", "stiffness")}
        self._next_plot_ns = 0

    @property
    def counts(self) -> dict[str, object]:
        """Samples read, and the estimator's (and TCE's) ticks and counters."""
        stream = self.stream
        counts: dict[str, object] = {
            "joint_samples": self.joint_samples, "imu_samples": self.imu_samples, "ticks": stream.ticks,
            "duplicates": stream.duplicates, "gated_legs": stream.estimator.gated_legs, "restarts": stream.restarts,
            "held_imu_ticks": stream.held_imu_ticks,
            "rejected": sum(stream.rejections.values()), "rejected_by_reason": dict(stream.rejections),
            "unreadable": dict(self.unreadable)}
        if self.tce is not None:
            counts.update(tce_ticks=self.tce.ticks, tce_rejected=self.tce.rejected)
        return counts

    # -- input ------------------------------------------------------------------------------------------------
    def add(self, topic: str, data: bytes) -> None:
        """One serialised message of ``topic`` (REPLAY_TOPICS), read in place as the nodes read it
        (tal_core.ros.cdr.CdrReader: no Python message is built); an unreadable one is counted."""
        try:
            view = self._readers[topic].read(data)
        except Exception as exc:  # noqa: BLE001 - a corrupt record is counted, the replay goes on
            self.unreadable[topic] = self.unreadable.get(topic, 0) + 1
            LOG.warning("unreadable %s message (%d so far): %s", topic, self.unreadable[topic], exc)
            return
        stamp = view.stamp_ns
        if topic == "/joint_states":
            self.joint_samples += 1
            self._outputs(self.stream.add_joints(stamp, lambda: self.read_joints(view)))
        elif topic == "/imu":
            self.imu_samples += 1
            self._outputs(self.stream.add_imu(stamp, view.vector("linear_acceleration").copy(),
                                              view.vector("angular_velocity").copy()))
        elif topic == "/ground_truth/odom":
            try:
                base = base_state_from_odometry_view(view)
            except InputError as exc:
                self.unreadable[topic] = self.unreadable.get(topic, 0) + 1
                LOG.warning("ground truth rejected: %s", exc)
                return
            if self.tce is not None and self.tce_base == "ground_truth":
                self.tce.set_base(stamp, base)
            if not self.stream.has_initial_pose:   # only the first ground truth is the start pose
                self._outputs(self.stream.set_initial_pose(base.position, rotation_from_quat_xyzw(base.quat_xyzw)))
            self._truth[stamp] = (base.position, base.linear_velocity)
            self._match(stamp)
        elif topic == "/state_estimate":
            self._live[stamp] = (view.vector("pose.pose.position").copy(),
                                 rotation_from_quat_xyzw(view.quaternion("pose.pose.orientation"))
                                 @ view.vector("twist.twist.linear"))
            self._match(stamp)

    def _outputs(self, outputs: list[EstimatorOutput]) -> None:
        for out in outputs:
            if out.kind == "estimate":
                self._tick(out)

    def _tick(self, out: EstimatorOutput) -> None:
        stamp, e = out.stamp_ns, out.estimate
        assert e is not None and out.joints is not None
        if self.tce is not None:
            if self.tce_base == "estimate":
                self.tce.set_base(stamp, e.base_state)
            tick = self.tce.add_joints(stamp, lambda: out.joints)
            if tick is not None:
                self.stream.impedance = legs_from_impedance_arrays(
                    tick.stiffness_n_per_m, tick.damping_ns_per_m, tick.valid, confidence=tick.confidence,
                    rigid=np.array([e.rigid for e in tick.estimates]))
        if stamp >= self._next_plot_ns:
            self._next_plot_ns = stamp + PLOT_PERIOD_NS
            truth = self._truth.get(stamp)
            impedance = self.stream.impedance
            self.series["t"].append(stamp * 1e-9)
            self.series["position"].append(e.position)
            self.series["velocity"].append(e.linear_velocity)
            self.series["truth_position"].append(truth[0] if truth else np.full(3, np.nan))
            self.series["truth_velocity"].append(truth[1] if truth else np.full(3, np.nan))
            self.series["stiffness"].append(np.full(NUM_LEGS, np.nan) if impedance is None else
                                            np.where(impedance.valid, impedance.stiffness_n_per_m, np.nan))
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
            if self.sections is not None:
                error = estimate[0] - truth[0]
                if self._section_offset is None:
                    self._section_offset = error  # start aligned, as vs_truth
                self.sections.add(stamp * 1e-9, truth[0], error - self._section_offset)
        live = self._live.pop(stamp, None)
        if live is not None:
            self.vs_live.add(stamp * 1e-9, estimate[0] - live[0], estimate[1] - live[1])
        # Keep the buffers bounded: anything older than the match window is not coming any more.
        horizon = stamp - MATCH_WINDOW_NS
        for buffer in (self._estimates, self._truth, self._live):
            for s in [s for s in buffer if s < horizon]:
                del buffer[s]

    # -- output -----------------------------------------------------------------------------------------------
    def summary(self) -> dict[str, object]:
        estimates = self.tce.tce.estimates if self.tce is not None else []
        return {
            "counts": self.counts, "leg_odometry": self.settings.leg_odometry.mode,
            "tce_base": self.tce_base if self.tce is not None else None,
            "vertical_crossover_rad_s": self.settings.vertical_crossover_rad_s,
            "leg_velocity_gate_m_s": self.settings.leg_velocity_gate_m_s,
            "penetration_reference": self.tce.settings.penetration_reference if self.tce is not None else None,
            "base_drift_fit": self.tce.settings.base_drift_fit if self.tce is not None else None,
            "course": self.course.name if self.course is not None else None,
            "sections": self.sections.summary() if self.sections is not None else [],
            "vs_ground_truth": self.vs_truth.summary(), "vs_live_estimate": self.vs_live.summary(),
            "tce_final_stiffness_n_per_m": {leg.name: (round(e.stiffness_n_per_m, 1) if math.isfinite(
                e.stiffness_n_per_m) else None) for leg, e in zip(LEGS, estimates)},
        }


def replay_bag(bag: str | Path, model: RobotModel, *, leg_odometry: str = "rigid", run_tce: bool = True,
               progress: bool = False, tce_base: str = "estimate",
               course: Course | None = None, vertical_crossover_rad_s: float = 0.0,
               penetration_reference: str = "surface",
               leg_velocity_gate_m_s: float = StateEstimatorSettings.leg_velocity_gate_m_s,
               base_drift_fit: bool = False) -> tuple[BagReplay, dict[str, object]]:
    """Replay ``bag`` and return the replay (with its plot series) and its summary."""
    reader = BagReader(bag)
    replay = BagReplay(model, leg_odometry, run_tce, tce_base, course, vertical_crossover_rad_s,
                       penetration_reference, leg_velocity_gate_m_s, base_drift_fit)
    wall = time.perf_counter()
    last_report = wall
    for message in reader.messages(REPLAY_TOPICS, decode=False):
        replay.add(message.topic, message.data)
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
             f"{summary['counts']['joint_samples']} joint samples in {summary['wall_time_s']} s "
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
    if summary.get("sections"):
        lines += ["## Drift per course section (against ground truth)", "",
                  f"Course {summary['course']}: sections by the ground-truth base position; each section's drift is "
                  "the change of the start-aligned error over it (they add up to the final drift).", ""]
        lines += format_section_table(summary["sections"]) + [""]
    stiffness = summary["tce_final_stiffness_n_per_m"]
    if stiffness:
        lines += ["## TCE", "", f"Base state: {summary.get('tce_base')}; terrain: "
                  f"{summary.get('course') or 'flat (z = 0)'}.", "", "| leg | stiffness [N/m] |", "|---|---|"]
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


def course_of_run(bag: Path) -> str | None:
    """The course of the run a bag was recorded in (``course`` of bridge_summary.json in the bag folder's
    parent), or None."""
    folder = bag if bag.is_dir() else bag.parent
    summary = folder.parent / "bridge_summary.json"
    try:
        course = json.loads(summary.read_text()).get("course")
    except (OSError, ValueError, AttributeError):
        return None
    return course if isinstance(course, str) and course else None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bag", type=Path, help="bag folder or .mcap file")
    parser.add_argument("--out", type=Path, help="report folder (default: <bag>/replay)")
    parser.add_argument("--leg-odometry", choices=("rigid", "terrain_aware"), default="rigid")
    parser.add_argument("--robot", default="hyq")
    parser.add_argument("--no-tce", action="store_true", help="skip the TCE")
    parser.add_argument("--tce-base", choices=TCE_BASES, default="estimate",
                        help="base state of the TCE: the replayed estimate or the bag's ground truth (live default)")
    parser.add_argument("--course", help="course name or YAML (terrain of the TCE, sections of the report); 'flat' for "
                                         "z = 0; default: the course in the run's bridge_summary.json, else flat")
    parser.add_argument("--vertical-crossover", type=float, default=0.0, metavar="RAD_S",
                        help="the estimator's vertical channel crossover (state_estimator.vertical_crossover_rad_s)")
    parser.add_argument("--penetration-reference", choices=PENETRATION_REFERENCES, default="surface",
                        help="the TCE's penetration reference (tce.penetration_reference)")
    parser.add_argument("--leg-velocity-gate", type=float, default=StateEstimatorSettings.leg_velocity_gate_m_s,
                        metavar="M_S", help="the estimator's leg velocity gate (state_estimator.leg_velocity_gate_m_s; "
                        "0: off)")
    parser.add_argument("--base-drift-fit", action="store_true",
                        help="the TCE also fits the base estimate's vertical drift (tce.base_drift_fit; with "
                        "--penetration-reference touchdown)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    course_name = args.course if args.course is not None else course_of_run(args.bag)
    course = load_course(course_name) if course_name not in (None, "flat") else None
    replay, summary = replay_bag(args.bag, RobotModel.from_name(args.robot), leg_odometry=args.leg_odometry,
                                 run_tce=not args.no_tce, progress=True, tce_base=args.tce_base, course=course,
                                 vertical_crossover_rad_s=args.vertical_crossover,
                                 penetration_reference=args.penetration_reference,
                                 leg_velocity_gate_m_s=args.leg_velocity_gate, base_drift_fit=args.base_drift_fit)
    out = args.out or (args.bag / "replay" if args.bag.is_dir() else args.bag.with_suffix(".replay"))
    write_report(replay, summary, out)
    sys.stdout.write((out / "report.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
