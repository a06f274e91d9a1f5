"""Summary of a locomotion run of the graph (``make run``): the bridge's and the wbc's end-of-run JSON.

Usage: python -m tal_lab.run_report --bridge bridge.json --wbc wbc.json [--tce tce.json]
    [--estimator estimator.json] [--output report.md]
With ``--tce`` the report lists the TCE's final per-leg stiffness estimates and plots their history
(``tce_estimates.png`` next to the report).

A run in which the robot fell (the bridge's ``fell``, ``fall_time_s``, ``fall_position_m``, ``fall_links``;
for summaries from before the bridge detected falls: the trunk on the ground) is marked INVALID at the top,
and the figures the fall makes meaningless are left out, saying so: the wbc's height, velocity and yaw-rate
errors and the estimator's drift (means and end values over a run that includes the fall), and the distance
travelled unless the bridge stopped at the fall (then it is the distance to the fall).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path

TRUNK_LINKS = {"trunk", "base"}  # the names the simulator gives the floating base in its contact report
ROBOT_LABELS = {"hyq": "HyQ"}
LEFT_OUT_WBC = "the body height, velocity and yaw-rate errors (their means run over the fall)"


@dataclass(frozen=True)
class FallInfo:
    """The bridge's fall. ``time_s``/``position_m`` are None for a summary from before fall detection."""

    robot: str
    time_s: float | None
    position_m: tuple[float, float, float] | None
    links: tuple[str, ...]
    reason: str
    stopped: bool        # the bridge ended the run at the fall: the nodes' figures end there too

    def banner(self) -> str:
        """The report's first line on an invalid run."""
        where = ("" if self.time_s is None or self.position_m is None else
                 f" at t = {self.time_s:.2f} s, x = {self.position_m[0]:.2f} m")
        what = f"links {', '.join(self.links)}" if self.links else self.reason
        return f"**INVALID RUN: {self.robot} fell{where} ({what}).**"

    def describe(self) -> str:
        if self.time_s is None or self.position_m is None:
            return f"yes ({', '.join(self.links)}; time unknown: a bridge summary without fall detection)"
        x, y, z = self.position_m
        return (f"yes, at t = {self.time_s:.3f} s (onset), base at x {x:.3f}, y {y:.3f}, z {z:.3f} m: "
                f"{self.reason}" + (f" ({', '.join(self.links)})" if self.links else "")
                + ("; the run stopped there" if self.stopped else "; the run went on (stop_on_fall false)"))


def fall_of(bridge: dict) -> FallInfo | None:
    """The fall in a bridge summary (None: the robot stayed up)."""
    robot = ROBOT_LABELS.get(bridge.get("robot", ""), bridge.get("robot") or "the robot")
    touched = bridge["body_ground_contact"]
    if "fell" not in bridge:  # a summary from before the bridge detected falls: the trunk on the ground
        if not TRUNK_LINKS & set(touched):
            return None
        return FallInfo(robot, None, None, tuple(touched), "body-ground contact", False)
    if not bridge["fell"]:
        return None
    position = bridge.get("fall_position_m")
    return FallInfo(robot, bridge.get("fall_time_s"), None if position is None else tuple(position),
                    tuple(bridge.get("fall_links") or ()), bridge.get("fall_reason") or "fell",
                    bool(bridge.get("stopped_on_fall")))


def format_latency(bridge: dict) -> str | None:
    """The bridge's joint state -> command latency (None: a summary without it)."""
    latency = bridge.get("command_latency_ms")
    if not latency:
        return None
    if not latency.get("count"):
        return "n/a (no command timed)"
    return (f"{latency['median_ms']:.2f} / {latency['p99_ms']:.2f} / {latency['max_ms']:.2f} ms "
            f"({latency['count']} commands)")


def format_report(bridge: dict, wbc: dict, title: str, distance_to_fall_m: float | None = None) -> str:
    """The run's table. On a fall: the INVALID banner first, the figures the fall voids left out (said below
    the table); ``distance_to_fall_m`` (ground truth, from the bag) is then the distance travelled."""
    fall = fall_of(bridge)
    touched = bridge["body_ground_contact"]

    def fmt(value, unit: str, scale: float = 1.0, digits: int = 3) -> str:
        return "n/a" if value is None else f"{value * scale:.{digits}f} {unit}"

    rows = [
        ("gait", wbc.get("gait", "?")),
        ("course", bridge["course"]),
        ("sim time", f"{bridge['sim_time_s']:.1f} s ({bridge['mode']}, "
                     f"real-time factor {bridge['real_time_factor']:.2f})"),
    ]
    left_out = []
    if fall is None:
        # Upper legs (the shins are filtered) may touch step edges on stairs for less than fall_confirm_s.
        rows += [("fell", "no" + (f" (but {', '.join(touched)} touched the terrain)" if touched else "")),
                 ("distance travelled", fmt(wbc.get("distance_m"), "m")),
                 ("body height error (mean abs, after 2 s)", fmt(wbc.get("height_error_mean_abs_m"), "mm", 1e3, 1)),
                 ("velocity error (mean abs, after 2 s)", fmt(wbc.get("velocity_error_mean_abs_m_s"), "m/s")),
                 ("yaw-rate error (mean abs, after 2 s)", fmt(wbc.get("yaw_rate_error_mean_abs_rad_s"), "rad/s"))]
    else:
        rows.append(("fell", fall.describe()))
        if distance_to_fall_m is not None:
            rows.append(("distance travelled to the fall (ground truth)", fmt(distance_to_fall_m, "m")))
        elif fall.stopped:
            rows.append(("distance travelled to the fall (wbc, base estimate)", fmt(wbc.get("distance_m"), "m")))
        else:
            left_out.append("the distance travelled (it runs past the fall)")
        left_out.append(LEFT_OUT_WBC)
    rows += [
        ("control ticks / QP fallbacks / safe-mode ticks",
         f"{wbc.get('ticks')} / {wbc.get('qp_fallbacks')} / {wbc.get('safe_mode_ticks')}"),
        ("rejected inputs (wbc) / rejected commands (bridge)",
         f"{wbc.get('rejected_inputs')} / {sum(bridge['commands_rejected'].values())}"),
        ("lockstep timeouts", str(bridge["lockstep_timeouts"])),
    ]
    latency = format_latency(bridge)
    if latency is not None:
        rows.append(("joint state -> command latency, wall time (median / p99 / max)", latency))
    lines = [f"# {title}", ""]
    if fall is not None:
        lines += [fall.banner(), "",
                  "Figures the fall makes meaningless are left out: " + "; ".join(left_out) + ".", ""]
    lines += ["| | |", "|---|---|"] + [f"| {k} | {v} |" for k, v in rows]
    return "\n".join(lines) + "\n"


def format_tce(tce: dict, fall: FallInfo | None = None) -> str:
    """Final per-leg estimates of the tce node's summary as a markdown table (left out when the robot fell and
    the run went on: they are estimates of the fallen robot's contacts)."""
    if fall is not None and not fall.stopped:
        return ("\n## TCE\n\nThe final estimates are left out: the run went on after the fall.\n"
                f"TCE ticks {tce['ticks']}, rejected inputs {tce['rejected_inputs']}.\n")
    title = "TCE (final estimates)" if fall is None else "TCE (estimates at the end of the run: the fall)"
    lines = ["", f"## {title}", "", "| leg | stiffness [N/m] | damping [N s/m] | confidence | samples |",
             "|---|---|---|---|---|"]
    for leg, e in tce["final"].items():
        k, d = e["stiffness_n_per_m"], e["damping_ns_per_m"]
        lines.append(f"| {leg} | {'n/a' if k is None else f'{k:.0f}'} | {'n/a' if d is None else f'{d:.0f}'} | "
                     f"{e['confidence']:.2f} | {e['samples']} |")
    lines.append(f"\nTCE ticks {tce['ticks']}, rejected inputs {tce['rejected_inputs']}, "
                 f"samples outside the heightmap {tce['samples_outside_map']}.")
    return "\n".join(lines) + "\n"


def format_estimator(estimator: dict, fell: bool = False, drift_at_fall_m=None) -> str:
    """The state_estimator node's summary: drift and velocity error against ground truth, counters. On a run
    that fell the summary's drift and velocity error (which include the fall) are left out; ``drift_at_fall_m``
    (x, y, z [m], estimate - truth at the fall's onset, from the bag) is shown instead when given."""
    lines = ["", f"## State estimator ({estimator.get('leg_odometry', '?')} leg odometry)", ""]
    if fell:
        if drift_at_fall_m is not None:
            lines += ["| | x | y | z |", "|---|---|---|---|",
                      "| drift at the fall's onset [m] | " + " | ".join(f"{v:+.4f}" for v in drift_at_fall_m) + " |",
                      ""]
        lines.append("The run fell: the estimator's final and RMS drift and its velocity RMSE (over the whole run, "
                     "fall included) are left out.")
    elif "final_drift_m" in estimator:
        lines += ["| | x | y | z |", "|---|---|---|---|"]
        for key, label in (("final_drift_m", "final drift [m]"), ("rms_drift_m", "RMS drift [m]"),
                           ("velocity_rmse_m_s", "velocity RMSE [m/s]")):
            lines.append(f"| {label} | " + " | ".join(f"{v:+.4f}" for v in estimator[key]) + " |")
        lines.append(f"\nCompared with ground truth over {estimator['compared_s']:.1f} s.")
    lines.append(f"Ticks {estimator['ticks']}, rejected inputs {estimator['rejected'] or 'none'}, restarts "
                 f"{estimator['restarts']}, velocity re-initialisations {estimator['reinitialisations']}.")
    return "\n".join(lines) + "\n"


def plot_tce(tce: dict, path: Path, until_s: float | None = None) -> None:
    """Estimated stiffness per leg over sim time (log scale), up to ``until_s`` [s] (the fall) when given."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    rows = np.array([[np.nan if v is None else v for v in row] for row in tce["history"]], dtype=float)
    if until_s is not None and rows.size:
        rows = rows[rows[:, 0] <= until_s]
    if rows.size == 0:
        return
    fig, ax = plt.subplots(figsize=(10, 4))
    for i, leg in enumerate(tce["final"]):
        ax.semilogy(rows[:, 0], rows[:, 1 + i], label=leg)
    ax.set_xlabel("sim time [s]")
    ax.set_ylabel("estimated stiffness [N/m]")
    ax.set_title("TCE estimates")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bridge", type=Path, required=True, help="summary.json of sim_bridge")
    parser.add_argument("--wbc", type=Path, required=True, help="summary.json of wbc")
    parser.add_argument("--tce", type=Path, help="summary.json of tce (optional)")
    parser.add_argument("--estimator", type=Path, help="summary.json of state_estimator (optional)")
    parser.add_argument("--title", default="Locomotion run")
    parser.add_argument("--output", type=Path)
    args = parser.parse_args(argv)
    for path in (args.bridge, args.wbc):
        if not path.is_file():
            parser.error(f"{path}: no summary (did the node finish cleanly?)")
    bridge = json.loads(args.bridge.read_text())
    fall = fall_of(bridge)
    report = format_report(bridge, json.loads(args.wbc.read_text()), args.title)
    if args.tce is not None:
        if not args.tce.is_file():
            parser.error(f"{args.tce}: no summary (did the tce node finish cleanly?)")
        tce = json.loads(args.tce.read_text())
        report += format_tce(tce, fall)
        if args.output:
            plot_tce(tce, args.output.parent / "tce_estimates.png", None if fall is None else fall.time_s)
    if args.estimator is not None:
        if not args.estimator.is_file():
            parser.error(f"{args.estimator}: no summary (did the state_estimator node finish cleanly?)")
        report += format_estimator(json.loads(args.estimator.read_text()), fell=fall is not None)
    print(report)
    if args.output:
        args.output.write_text(report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
