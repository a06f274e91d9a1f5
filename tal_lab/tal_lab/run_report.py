"""Summary of a locomotion run of the graph (``make run``): the bridge's and the wbc's end-of-run JSON.

Usage: python -m tal_lab.run_report --bridge bridge.json --wbc wbc.json [--tce tce.json]
    [--estimator estimator.json] [--output report.md]
With ``--tce`` the report lists the TCE's final per-leg stiffness estimates and plots their history
(``tce_estimates.png`` next to the report).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

TRUNK_LINKS = {"trunk", "base"}  # the names the simulator gives the floating base in its contact report


def format_report(bridge: dict, wbc: dict, title: str) -> str:
    touched = bridge["body_ground_contact"]
    # The trunk on the ground is a fall; upper legs (the shins are filtered) also touch step edges on stairs.
    fell = "yes (" + ", ".join(touched) + ")" if TRUNK_LINKS & set(touched) else (
        "no" + (f" (but {', '.join(touched)} touched the terrain)" if touched else ""))

    def fmt(value, unit: str, scale: float = 1.0, digits: int = 3) -> str:
        return "n/a" if value is None else f"{value * scale:.{digits}f} {unit}"

    rows = [
        ("gait", wbc.get("gait", "?")),
        ("course", bridge["course"]),
        ("sim time", f"{bridge['sim_time_s']:.1f} s ({bridge['mode']}, "
                     f"real-time factor {bridge['real_time_factor']:.2f})"),
        ("fell", fell),
        ("distance travelled", fmt(wbc.get("distance_m"), "m")),
        ("body height error (mean abs, after 2 s)", fmt(wbc.get("height_error_mean_abs_m"), "mm", 1e3, 1)),
        ("velocity error (mean abs, after 2 s)", fmt(wbc.get("velocity_error_mean_abs_m_s"), "m/s")),
        ("yaw-rate error (mean abs, after 2 s)", fmt(wbc.get("yaw_rate_error_mean_abs_rad_s"), "rad/s")),
        ("control ticks / QP fallbacks / safe-mode ticks",
         f"{wbc.get('ticks')} / {wbc.get('qp_fallbacks')} / {wbc.get('safe_mode_ticks')}"),
        ("rejected inputs (wbc) / rejected commands (bridge)",
         f"{wbc.get('rejected_inputs')} / {sum(bridge['commands_rejected'].values())}"),
        ("lockstep timeouts", str(bridge["lockstep_timeouts"])),
    ]
    lines = [f"# {title}", "", "| | |", "|---|---|"] + [f"| {k} | {v} |" for k, v in rows]
    return "\n".join(lines) + "\n"


def format_tce(tce: dict) -> str:
    """Final per-leg estimates of the tce node's summary as a markdown table."""
    lines = ["", "## TCE (final estimates)", "", "| leg | stiffness [N/m] | damping [N s/m] | confidence | samples |",
             "|---|---|---|---|---|"]
    for leg, e in tce["final"].items():
        k, d = e["stiffness_n_per_m"], e["damping_ns_per_m"]
        lines.append(f"| {leg} | {'n/a' if k is None else f'{k:.0f}'} | {'n/a' if d is None else f'{d:.0f}'} | "
                     f"{e['confidence']:.2f} | {e['samples']} |")
    lines.append(f"\nTCE ticks {tce['ticks']}, rejected inputs {tce['rejected_inputs']}, "
                 f"samples outside the heightmap {tce['samples_outside_map']}.")
    return "\n".join(lines) + "\n"


def format_estimator(estimator: dict) -> str:
    """The state_estimator node's summary: drift and velocity error against ground truth, counters."""
    lines = ["", f"## State estimator ({estimator.get('leg_odometry', '?')} leg odometry)", ""]
    if "final_drift_m" in estimator:
        lines += ["| | x | y | z |", "|---|---|---|---|"]
        for key, label in (("final_drift_m", "final drift [m]"), ("rms_drift_m", "RMS drift [m]"),
                           ("velocity_rmse_m_s", "velocity RMSE [m/s]")):
            lines.append(f"| {label} | " + " | ".join(f"{v:+.4f}" for v in estimator[key]) + " |")
        lines.append(f"\nCompared with ground truth over {estimator['compared_s']:.1f} s.")
    lines.append(f"Ticks {estimator['ticks']}, rejected inputs {estimator['rejected'] or 'none'}, restarts "
                 f"{estimator['restarts']}, velocity re-initialisations {estimator['reinitialisations']}.")
    return "\n".join(lines) + "\n"


def plot_tce(tce: dict, path: Path) -> None:
    """Estimated stiffness per leg over sim time (log scale)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    rows = np.array([[np.nan if v is None else v for v in row] for row in tce["history"]], dtype=float)
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
    report = format_report(json.loads(args.bridge.read_text()), json.loads(args.wbc.read_text()), args.title)
    if args.tce is not None:
        if not args.tce.is_file():
            parser.error(f"{args.tce}: no summary (did the tce node finish cleanly?)")
        tce = json.loads(args.tce.read_text())
        report += format_tce(tce)
        if args.output:
            plot_tce(tce, args.output.parent / "tce_estimates.png")
    if args.estimator is not None:
        if not args.estimator.is_file():
            parser.error(f"{args.estimator}: no summary (did the state_estimator node finish cleanly?)")
        report += format_estimator(json.loads(args.estimator.read_text()))
    print(report)
    if args.output:
        args.output.write_text(report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
