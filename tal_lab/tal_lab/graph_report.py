"""Report of a whole-graph run (``make run``, scenario ``tour``): summary, rates, stiffness per patch, plots.

Usage: python -m tal_lab.graph_report RUN_DIR [--title TITLE]

RUN_DIR holds what ``scripts/run_scenario.sh`` leaves: the nodes' end-of-run summaries
(``bridge_summary.json``, ``wbc_summary.json``, ``estimator_summary.json``, ``tce_summary.json``,
``vfa_summary.json``, ``vpa_summary.json``), ``resources.json`` (``tal_core.resource_monitor``) and the
recorded bag (``bag/``). The report, ``report.md``, and its plots are written into RUN_DIR; the summary is
printed.

Rates come from the header stamps of the recorded messages (sim time): the rate over the run, and the
missed ticks (a gap of n periods between two stamps misses n - 1). They count what the recorder received,
so a message the recorder lost counts as missed too. The wall-clock rate is the sim-time rate times the
bridge's real-time factor (lockstep runs as fast as the slowest node lets it; realtime holds ~1).

Stiffness per patch: an estimate of a leg counts for a patch when every ground-truth contact sample of that
leg in the preceding ``lookback_s`` (longer than the TCE's window of stance samples) was on that patch.

A run in which the robot fell (the bridge summary's ``fell``) is marked INVALID at the top; the base track,
the estimator's drift and the stiffness estimates are cut at the fall's onset (the distance travelled and the
drift are then those at the fall, from the bag), the wbc's tracking errors and the estimator summary's drift
are left out (``run_report.format_report``). Rates cover the whole recording.
"""

from __future__ import annotations

import argparse
import json
import math
from collections import defaultdict, deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tal_core.course_io import load_course
from tal_core.legs import LEG_NAMES
from tal_core.ros.bag_io import BagReader
from tal_lab.run_report import FallInfo, fall_of, format_estimator, format_report
from tal_lab.section_drift import SectionDrift, format_section_table

SOFT_N_PER_M = 1e5  # [N/m] patches softer than this are shaded in the trajectory plot
LOOKBACK_S = 2.5  # [s] the TCE window is 250 stance samples at 250 Hz: ~1.7 s of trot at duty factor 0.6
ADOPT_CONFIDENCE = 0.1  # [-] the wbc's impedance_min_confidence default: estimates it adopts
SOFT_READING_N_PER_M = 5e4  # [N/m] a confident estimate below this on rigid ground is a false soft reading


@dataclass(frozen=True)
class TopicRate:
    """A topic the report checks: the node publishing it and its target period [s] (None: event driven)."""

    node: str
    topic: str
    period_s: float | None


TOPIC_RATES = (
    TopicRate("sim_bridge", "joint_states", 0.001),
    TopicRate("sim_bridge", "imu", 0.001),
    TopicRate("sim_bridge", "ground_truth/contacts", 0.004),
    TopicRate("state_estimator", "state_estimate", 0.003),
    TopicRate("tce", "terrain_impedance", 0.004),
    TopicRate("wbc", "joint_command", 0.004),
    TopicRate("wbc", "gait_state", 0.004),
    TopicRate("vpa", "body_pose_reference", 0.05),
    TopicRate("vfa", "footholds", None),
)


@dataclass
class RateResult:
    node: str
    topic: str
    target_hz: float | None
    messages: int
    sim_rate_hz: float | None
    wall_rate_hz: float | None
    missed_ticks: int | None


def stamp_ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def topic_rates(stamps: dict[str, list[int]], real_time_factor: float | None) -> list[RateResult]:
    """Rate and missed ticks per checked topic from its header stamps [ns]."""
    results = []
    for spec in TOPIC_RATES:
        # Distinct stamps: the bridge re-sends its initial state until the first command (one tick, not many).
        s = np.unique(np.array(stamps.get(spec.topic, []), dtype=np.int64))
        sim_rate = wall_rate = missed = None
        if s.size >= 2 and s[-1] > s[0]:
            sim_rate = (s.size - 1) / ((s[-1] - s[0]) * 1e-9)
            wall_rate = sim_rate * real_time_factor if real_time_factor else None
            if spec.period_s is not None:
                gaps = np.round(np.diff(s) * 1e-9 / spec.period_s).astype(np.int64)
                missed = int(np.sum(np.clip(gaps - 1, 0, None)))
        results.append(RateResult(spec.node, spec.topic, None if spec.period_s is None else 1.0 / spec.period_s,
                                  int(s.size), sim_rate, wall_rate, missed))
    return results


@dataclass
class BagSeries:
    """What the report takes from the bag: base track, stamps per topic, stiffness samples per patch."""

    t_s: np.ndarray            # ground truth stamps [s]
    position: np.ndarray       # (n, 3) ground-truth base position [m], world
    estimate_t_s: np.ndarray
    estimate_position: np.ndarray
    stamps: dict[str, list[int]]
    stiffness: dict[str, list[tuple[float, str, float, float, float]]]   # patch -> (t [s], leg, x [m], k [N/m],
    #                                                                    confidence [-])

    def until(self, t_s: float) -> BagSeries:
        """The base tracks and stiffness samples up to sim time ``t_s`` [s] (a fall's onset); stamps stay whole."""
        truth, estimate = self.t_s <= t_s, self.estimate_t_s <= t_s
        stiffness = {patch: kept for patch, samples in self.stiffness.items()
                     if (kept := [sample for sample in samples if sample[0] <= t_s])}
        return BagSeries(self.t_s[truth], self.position[truth], self.estimate_t_s[estimate],
                         self.estimate_position[estimate], self.stamps, stiffness)

    def distance_m(self) -> float | None:
        """Horizontal ground-truth distance [m] from the first to the last sample."""
        if not self.position.size:
            return None
        return float(np.linalg.norm(self.position[-1, :2] - self.position[0, :2]))

    def final_drift_m(self) -> np.ndarray | None:
        """Estimate - ground truth [m] (x, y, z) at the last estimate (truth interpolated at its stamp)."""
        if not self.estimate_position.size or self.t_s.size < 2:
            return None
        t = self.estimate_t_s[-1]
        truth = np.array([np.interp(t, self.t_s, self.position[:, j]) for j in range(3)])
        return self.estimate_position[-1] - truth


def read_bag(bag: Path, course_name: str, lookback_s: float = LOOKBACK_S) -> BagSeries:
    """One pass over the bag (time order is the file's order, close to stamp order)."""
    course = load_course(course_name)
    checked = {spec.topic for spec in TOPIC_RATES}
    stamps: dict[str, list[int]] = defaultdict(list)
    gt_t, gt_p, est_t, est_p = [], [], [], []
    recent: list[deque] = [deque() for _ in LEG_NAMES]   # per leg: (t [s], patch) of contact samples
    foot_x = [math.nan] * len(LEG_NAMES)
    stiffness: dict[str, list] = defaultdict(list)
    topics = checked | {"ground_truth/odom", "state_estimate", "ground_truth/contacts", "terrain_impedance"}
    # rosbag2 stores the fully qualified names the recorder subscribed to ("/joint_states").
    for record in BagReader(bag).messages(topics | {f"/{name}" for name in topics}):
        msg, topic = record.message, record.topic.lstrip("/")
        ns = stamp_ns(msg)
        if topic in checked:
            stamps[topic].append(ns)
        t = ns * 1e-9
        if topic in ("ground_truth/odom", "state_estimate"):
            p = msg.pose.pose.position
            (gt_t if topic == "ground_truth/odom" else est_t).append(t)
            (gt_p if topic == "ground_truth/odom" else est_p).append((p.x, p.y, p.z))
        elif topic == "ground_truth/contacts":
            for i in range(len(LEG_NAMES)):
                foot = msg.foot_position[i]
                foot_x[i] = foot.x
                if msg.in_contact[i]:
                    recent[i].append((t, str(course.patch_at(foot.x, foot.y))))
                while recent[i] and recent[i][0][0] < t - lookback_s:
                    recent[i].popleft()
        elif topic == "terrain_impedance":
            for i, leg in enumerate(LEG_NAMES):
                k = msg.stiffness_normal[i]
                patches = {patch for _, patch in recent[i]}
                if msg.valid[i] and math.isfinite(k) and len(patches) == 1:
                    stiffness[patches.pop()].append((t, leg, foot_x[i], k, msg.confidence[i]))
    as_array = lambda rows: np.array(rows, dtype=float).reshape(-1, 3)  # noqa: E731
    return BagSeries(np.array(gt_t), as_array(gt_p), np.array(est_t), as_array(est_p), dict(stamps),
                     dict(stiffness))


def stiffness_table(series: BagSeries, course_name: str) -> list[dict]:
    """Per patch: the true stiffness, the estimates' median / spread and the error of the median [%]."""
    course = load_course(course_name)
    rows = []
    for patch, samples in sorted(series.stiffness.items(), key=lambda kv: kv[1][0][0]):
        k = np.array([s[3] for s in samples])
        xs = np.array([s[2] for s in samples])
        true_k = float(np.median(course.properties_array(xs, np.zeros_like(xs)).stiffness_n_per_m))
        median = float(np.median(k))
        confident = k[np.array([s[4] for s in samples]) >= ADOPT_CONFIDENCE]
        rows.append({"patch": patch, "true_n_per_m": true_k, "median_n_per_m": median,
                     "confident_share": confident.size / k.size,
                     "confident_below_5e4": int(np.count_nonzero(confident < SOFT_READING_N_PER_M)),
                     "confident_samples": int(confident.size),
                     "confident_median_n_per_m": float(np.median(confident)) if confident.size else math.nan,
                     "p10_n_per_m": float(np.percentile(k, 10)), "p90_n_per_m": float(np.percentile(k, 90)),
                     "samples": int(k.size), "error_pct": 100.0 * (median - true_k) / true_k})
    return rows


def format_graph_sections(rates: list[RateResult], stiffness: list[dict], resources: dict | None,
                          vfa: dict | None, vpa: dict | None) -> str:
    lines = ["", "## Rates (header stamps of the recorded messages)", "",
             "| node | topic | target [Hz] | messages | sim-time rate [Hz] | wall-clock rate [Hz] | missed ticks |",
             "|---|---|---|---|---|---|---|"]
    f = lambda v, d=1: "n/a" if v is None else f"{v:.{d}f}"  # noqa: E731
    for r in rates:
        lines.append(f"| {r.node} | {r.topic} | {f(r.target_hz)} | {r.messages} | {f(r.sim_rate_hz)} | "
                     f"{f(r.wall_rate_hz)} | {'n/a' if r.missed_ticks is None else r.missed_ticks} |")
    lines += ["", "## Terrain stiffness: TCE estimates vs truth per patch", "",
              f"Estimates of a leg whose contacts in the preceding {LOOKBACK_S} s all lay on the patch. The "
              f"c3WBC adopts an estimate from confidence {ADOPT_CONFIDENCE} on (``ImpedanceGate``); on rigid "
              "ground the TCE reports a lower bound (std F / std p >= 5e4 N/m).", "",
              "| patch | true [N/m] | median estimate [N/m] | 10-90 % [N/m] | error of the median [%] | samples "
              "| confident (adopted) share | median of the confident [N/m] "
              f"| confident below {SOFT_READING_N_PER_M:g} N/m |",
              "|---|---|---|---|---|---|---|---|---|"]
    for row in stiffness:
        lines.append(f"| {row['patch']} | {row['true_n_per_m']:.4g} | {row['median_n_per_m']:.4g} | "
                     f"{row['p10_n_per_m']:.4g} - {row['p90_n_per_m']:.4g} | {row['error_pct']:+.2f} | "
                     f"{row['samples']} | {row['confident_share']:.2f} | {row['confident_median_n_per_m']:.4g} | "
                     f"{row['confident_below_5e4']} of {row['confident_samples']} |")
    if vfa is not None or vpa is not None:
        lines += ["", "## ViTAL", ""]
        if vfa is not None:
            lines.append("vfa: " + ", ".join(f"{k} {v}" for k, v in vfa.items() if not isinstance(v, (dict, list))))
        if vpa is not None:
            lines.append("\nvpa: " + ", ".join(f"{k} {v}" for k, v in vpa.items()
                                               if not isinstance(v, (dict, list))))
    if resources is not None:
        lines += ["", "## Resources (every process of each node, sampled each second)", "",
                  f"Peak resident memory of the whole graph: **{resources['peak_total_rss_mb']:.0f} MB** "
                  f"over {resources['wall_s']:.0f} s of wall time.", "",
                  "| node | peak RSS [MB] | CPU [s] | CPU share of one core |", "|---|---|---|---|"]
        for name, n in sorted(resources["nodes"].items(), key=lambda kv: -kv[1]["cpu_s"]):
            lines.append(f"| {name} | {n['peak_rss_mb']:.0f} | {n['cpu_s']:.1f} | {f(n['cpu_fraction'], 3)} |")
    return "\n".join(lines) + "\n"


def plot_run(series: BagSeries, course_name: str, rates: list[RateResult],
             resources: dict | None, out_dir: Path, fall: FallInfo | None = None) -> list[Path]:
    """trajectory.png (side view over the terrain, estimator drift), stiffness.png, rates_resources.png. With a
    fall, ``series`` ends at its onset and the trajectory marks it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    course = load_course(course_name)
    paths = []
    fig, (ax_side, ax_drift) = plt.subplots(2, 1, figsize=(10, 7))
    if series.position.size:
        x = np.linspace(min(series.position[:, 0].min(), 0.0) - 0.5, series.position[:, 0].max() + 1.0, 800)
        ax_side.fill_between(x, -0.2, course.height(x, np.zeros_like(x)), color="0.8", label="terrain (y = 0)")
        soft = [patch for patch in course.patches if patch.stiffness_n_per_m < SOFT_N_PER_M]
        for i, patch in enumerate(soft):
            ax_side.axvspan(patch.region.x_min, patch.region.x_max, alpha=0.15, color=f"C{i + 2}",
                            label=f"{patch.name} ({patch.stiffness_n_per_m:.0f} N/m)")
        ax_side.plot(series.position[:, 0], series.position[:, 2], label="base, ground truth")
        if fall is not None and fall.position_m is not None:
            ax_side.plot(fall.position_m[0], fall.position_m[2], "rx", ms=10,
                         label=f"fall at t = {fall.time_s:.2f} s (series end here)")
    if series.estimate_position.size:
        ax_side.plot(series.estimate_position[:, 0], series.estimate_position[:, 2], "--", label="base, estimate")
        gt_at = np.column_stack([np.interp(series.estimate_t_s, series.t_s, series.position[:, j]) for j in range(3)])
        drift = series.estimate_position - gt_at
        for j, axis in enumerate("xyz"):
            ax_drift.plot(series.estimate_t_s, drift[:, j], label=f"{axis}")
    ax_side.set_xlabel("x [m]")
    ax_side.set_ylabel("z [m]")
    ax_side.legend(fontsize=8, loc="upper left")
    ax_side.set_title("base trajectory over the course")
    ax_drift.set_xlabel("sim time [s]")
    ax_drift.set_ylabel("estimate - truth [m]")
    ax_drift.set_title("state estimator drift")
    ax_drift.legend(fontsize=8)
    fig.tight_layout()
    paths.append(out_dir / "trajectory.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(10, 4))
    for patch, samples in series.stiffness.items():
        arr = np.array([(s[2], s[3]) for s in samples])
        ax.semilogy(arr[:, 0], arr[:, 1], ".", ms=2, label=f"estimates on {patch}")
    all_x = [s[2] for samples in series.stiffness.values() for s in samples]
    if all_x:
        x = np.linspace(min(all_x), max(all_x), 2000)
        ax.semilogy(x, course.properties_array(x, np.zeros_like(x)).stiffness_n_per_m, "k--", label="truth (y = 0)")
    ax.set_xlabel("foot x [m]")
    ax.set_ylabel("normal stiffness [N/m]")
    ax.set_title("TCE estimates (dots) vs the true stiffness of each patch (dashed)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    paths.append(out_dir / "stiffness.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    fig, (ax_rate, ax_mem) = plt.subplots(1, 2, figsize=(12, 4))
    checked = [r for r in rates if r.target_hz and r.wall_rate_hz]
    ax_rate.barh([f"{r.node}\n{r.topic}" for r in checked], [r.wall_rate_hz / r.target_hz for r in checked])
    ax_rate.axvline(1.0, color="k", ls="--")
    ax_rate.set_xlabel("wall-clock rate / target")
    ax_rate.tick_params(axis="y", labelsize=7)
    if resources is not None and resources["total_rss_mb"]:
        series_mb = np.array(resources["total_rss_mb"])
        ax_mem.plot(series_mb[:, 0], series_mb[:, 1])
    ax_mem.set_xlabel("wall time [s]")
    ax_mem.set_ylabel("graph resident memory [MB]")
    fig.tight_layout()
    paths.append(out_dir / "rates_resources.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)
    return paths


PRIMARY_TOPIC = {"sim_bridge": "joint_states", "state_estimator": "state_estimate", "tce": "terrain_impedance",
                 "wbc": "joint_command", "vpa": "body_pose_reference"}


BRIDGE_FALLBACK = ("ground_truth/contacts", 4)
"""The bridge's physics rate when joint_states was not recorded: its contacts' rate times the physics steps
between two (the same loop publishes both; 1 kHz physics, 250 Hz contacts)."""


def bench_rates(summary: dict) -> dict:
    """The rate each node held (its main output) and its missed ticks, in the schema bench/report.py reads."""
    rates = {r["topic"]: r for r in summary["rates"]}
    nodes = {}
    counted = {r["node"]: r for r in summary.get("node_rates") or []}
    for node, topic in PRIMARY_TOPIC.items():
        if node in counted:  # the node's own counter: the recorder may not keep up on two busy cores
            c = counted[node]
            nodes[node] = {"topic": f"{c['counter']} (node counter)", "target_hz": c["target_hz"],
                           "achieved_hz": c["wall_rate_hz"], "deadline_misses": c["missed_ticks"], "ticks": c["ticks"]}
            continue
        scale = 1
        if node == "sim_bridge" and not rates[topic]["messages"]:
            topic, scale = BRIDGE_FALLBACK  # a real-time run records no 1 kHz topic (two cores)
        r = rates[topic]
        nodes[node] = {"topic": topic if scale == 1 else f"{topic} x {scale}",
                       "target_hz": None if r["target_hz"] is None else r["target_hz"] * scale,
                       "achieved_hz": None if r["wall_rate_hz"] is None else r["wall_rate_hz"] * scale,
                       "deadline_misses": r["missed_ticks"], "ticks": r["messages"]}
    return {"mode": summary["mode"], "real_time_factor": summary["real_time_factor"], "nodes": nodes,
            "peak_rss_mb": summary["peak_total_rss_mb"]}


def load_json(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


NODE_COUNTERS = (("sim_bridge", "bridge_summary.json", None, 1000.0), ("state_estimator", "estimator_summary.json",
                 ("ticks",), 1000.0 / 3.0), ("tce", "tce_summary.json", ("ticks",), 250.0),
                 ("wbc", "wbc_summary.json", ("ticks", "safe_mode_ticks"), 250.0), ("vpa", "vpa_summary.json",
                                                                                  ("published",), 20.0))
"""Each node's own count of what it computed (the bridge: its physics steps, sim time x 1 kHz) and its target."""


def node_rates(run_dir: Path, bridge: dict) -> list[dict]:
    """Rate [Hz] each node held on the wall clock from its own counter over the run's sim time / real-time factor,
    and its missed ticks (expected over the sim time minus counted). Unlike the recorded stamps it does not
    depend on the recorder keeping up."""
    sim_s, rtf = bridge.get("sim_time_s"), bridge.get("real_time_factor")
    if not sim_s or not rtf:
        return []
    out = []
    for node, file, keys, target_hz in NODE_COUNTERS:
        doc = bridge if keys is None else load_json(run_dir / file)
        if doc is None:
            continue
        ticks = round(sim_s * target_hz) if keys is None else sum(int(doc.get(k) or 0) for k in keys)
        out.append({"node": node, "counter": "physics steps" if keys is None else " + ".join(keys),
                    "target_hz": target_hz, "ticks": ticks, "wall_rate_hz": ticks / (sim_s / rtf),
                    "missed_ticks": max(0, round(sim_s * target_hz) - ticks)})
    return out


def fallbacks_by_section(times_s: list[float], series: BagSeries, course_name: str) -> str:
    """'default 3 (x 5.21-5.48 m), stairs_up 12 (x ...)' from the wbc's QP fallback times and the base track:
    where a run struggled (empty without fallbacks or a track)."""
    if not times_s or not series.t_s.size:
        return ""
    course = load_course(course_name)
    index = np.clip(np.searchsorted(series.t_s, np.asarray(times_s, dtype=float)), 0, series.t_s.size - 1)
    where: dict[str, list[float]] = {}
    for i in index:
        x, y = series.position[i, 0], series.position[i, 1]
        where.setdefault(str(course.patch_at(x, y)), []).append(float(x))
    return ", ".join(f"{name} {len(xs)} (x {min(xs):.2f}-{max(xs):.2f} m)" for name, xs in where.items())


SECTION_SAMPLE_S = 0.02  # [s] estimate samples fed to the per-section drift (50 Hz: sections last seconds)


def estimator_sections(series: BagSeries, course_name: str) -> list[dict[str, object]]:
    """The estimator's drift per course section (``SectionDrift``: rigid, T1, T2, stairs, landing, in the order
    crossed) from the bag's estimate and ground truth (interpolated at the estimate's stamps); empty without
    both tracks."""
    if not series.estimate_position.size or series.t_s.size < 2:
        return []
    t = series.estimate_t_s
    keep = (t >= series.t_s[0]) & (t <= series.t_s[-1])
    step = max(1, int(round(SECTION_SAMPLE_S / max(float(np.median(np.diff(t))), 1e-6)))) if t.size > 1 else 1
    t, estimate = t[keep][::step], series.estimate_position[keep][::step]
    truth = np.column_stack([np.interp(t, series.t_s, series.position[:, j]) for j in range(3)])
    course = load_course(course_name)
    drift = SectionDrift(course.patch_at)
    for t_s, p, e in zip(t, truth, estimate - truth):
        drift.add(float(t_s), p, e)
    return drift.summary()


def build_report(run_dir: Path, title: str) -> str:
    bridge = load_json(run_dir / "bridge_summary.json")
    wbc = load_json(run_dir / "wbc_summary.json")
    if bridge is None or wbc is None:
        raise FileNotFoundError(f"{run_dir}: no bridge_summary.json / wbc_summary.json (did the graph finish?)")
    fall = fall_of(bridge)
    series = read_bag(run_dir / "bag", bridge["course"])
    fall_time_s = None if fall is None else fall.time_s
    cut = fall_time_s is not None
    if fall_time_s is not None:
        series = series.until(fall_time_s)
    distance = series.distance_m() if cut else None
    report = format_report(bridge, wbc, title, distance_to_fall_m=distance)
    if series.position.size and (cut or fall is None):  # after a fall of unknown time: meaningless
        report += (f"| {'base position at the fall' if cut else 'final base position'} (ground truth) | "
                   f"x {series.position[-1, 0]:.2f} m, z {series.position[-1, 2]:.2f} m |\n")
    fallbacks = fallbacks_by_section(wbc.get("qp_fallback_times_s") or [], series, bridge["course"])
    if fallbacks:
        report += f"| QP fallbacks by course section (base position) | {fallbacks} |\n"
    estimator = load_json(run_dir / "estimator_summary.json")
    if estimator is not None:
        report += format_estimator(estimator, fell=fall is not None, drift_at_fall_m=series.final_drift_m() if cut
                                   else None)
    sections = estimator_sections(series, bridge["course"])
    if sections:
        report += ("\nDrift per course section (the estimate - ground truth accumulated over each stretch; the "
                   "sections add up to the final drift):\n\n" + "\n".join(format_section_table(sections)) + "\n")
    rates = topic_rates(series.stamps, bridge.get("real_time_factor"))
    stiffness = stiffness_table(series, bridge["course"])
    resources = load_json(run_dir / "resources.json")
    report += format_graph_sections(rates, stiffness, resources, load_json(run_dir / "vfa_summary.json"),
                                    load_json(run_dir / "vpa_summary.json"))
    if cut:
        report += (f"\nThe base track, the estimator drift and the stiffness estimates end at the fall's onset "
                   f"(t = {fall_time_s:.2f} s); the rates cover the whole recording.\n")
    plots = plot_run(series, bridge["course"], rates, resources, run_dir, fall)
    report += "\nPlots: " + ", ".join(f"[{p.name}]({p.name})" for p in plots) + "\n"
    counted = node_rates(run_dir, bridge)
    if counted:
        report += ("\n## Rates held (each node's own counter over the run's wall time)\n\n"
                   "| node | counter | target [Hz] | counted | wall-clock rate [Hz] | missed ticks |\n"
                   "|---|---|---|---|---|---|\n")
        report += "".join(f"| {r['node']} | {r['counter']} | {r['target_hz']:.4g} | {r['ticks']} | "
                          f"{r['wall_rate_hz']:.1f} | {r['missed_ticks']} |\n" for r in counted)
    summary = {"rates": [r.__dict__ for r in rates], "node_rates": counted, "stiffness": stiffness,
               "peak_total_rss_mb": None if resources is None else resources["peak_total_rss_mb"],
               "real_time_factor": bridge.get("real_time_factor"), "mode": bridge.get("mode"),
               "fell": fall is not None, "fall_time_s": fall_time_s,
               "fall_position_m": None if fall is None else fall.position_m,
               "fall_links": [] if fall is None else list(fall.links),
               "links_touching_terrain": bridge["body_ground_contact"],
               "distance_m": distance if cut else (wbc.get("distance_m") if fall is None else None),
               "command_latency_ms": bridge.get("command_latency_ms"), "estimator_sections": sections}
    (run_dir / "graph_summary.json").write_text(json.dumps(summary, indent=1))
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--title", default="Whole-graph run")
    parser.add_argument("--bench-json", type=Path, help="also write the nodes' rates for bench/report.py here "
                        "(bench/out/graph_rates.json)")
    args = parser.parse_args(argv)
    try:
        report = build_report(args.run_dir, args.title)
    except FileNotFoundError as exc:
        parser.error(str(exc))
    (args.run_dir / "report.md").write_text(report)
    print(report)
    if args.bench_json is not None:
        summary = json.loads((args.run_dir / "graph_summary.json").read_text())
        args.bench_json.parent.mkdir(parents=True, exist_ok=True)
        args.bench_json.write_text(json.dumps({**bench_rates(summary), "run": str(args.run_dir)}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
