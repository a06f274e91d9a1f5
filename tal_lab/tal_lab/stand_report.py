"""Summary table of standing runs (``make run``): base height and per-foot penetration vs expectation.

Usage: python -m tal_lab.stand_report [--output report.md] summary.json [summary.json ...]
Each summary.json is the end-of-run summary the sim_bridge node writes (parameter ``summary_path``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from tal_core.legs import LEG_NAMES


def format_report(summaries: list[dict]) -> str:
    """Markdown report: one section per run with its per-foot table."""
    lines = ["# Standing runs", ""]
    lines.append("| course | mode | sim time [s] | real-time factor | base height [m] | fell | commands | "
                 "rejected | lockstep timeouts |")
    lines.append("|---|---|---|---|---|---|---|---|---|")
    for s in summaries:
        fell = "yes (" + ", ".join(s["body_ground_contact"]) + ")" if s["body_ground_contact"] else "no"
        lines.append(f"| {s['course']} | {s['mode']} | {s['sim_time_s']:.1f} | {s['real_time_factor']:.2f} | "
                     f"{s.get('base_height_m', float('nan')):.4f} | {fell} | {s['commands_accepted']} | "
                     f"{sum(s['commands_rejected'].values())} | {s['lockstep_timeouts']} |")
    for s in summaries:
        lines += ["", f"## {s['course']}: foot penetration (mean over the last second)", "",
                  "| foot | K [N/m] | normal force [N] | penetration [mm] | F/K [mm] | error vs F/K | "
                  "m g/(n K) [mm] |", "|---|---|---|---|---|---|---|"]
        for leg in LEG_NAMES:
            f = s.get("feet", {}).get(leg)
            if f is None:
                continue
            error = f["error_vs_force_pct"]
            lines.append(f"| {leg} | {f['stiffness_n_per_m']:.0f} | {f['normal_force_n']:.1f} | "
                         f"{1e3 * f['penetration_m']:.3f} | {1e3 * f['expected_from_force_m']:.3f} | "
                         f"{'n/a' if error is None else f'{error:+.2f} %'} | "
                         f"{1e3 * f['expected_static_mg_over_nk_m']:.3f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("summaries", nargs="+", type=Path, help="summary.json files written by sim_bridge")
    parser.add_argument("--output", type=Path, help="also write the report to this markdown file")
    args = parser.parse_args(argv)
    summaries = []
    for path in args.summaries:
        if not path.is_file():
            parser.error(f"{path}: no summary (did the sim_bridge run finish?)")
        summaries.append(json.loads(path.read_text()))
    report = format_report(summaries)
    print(report)
    if args.output:
        args.output.write_text(report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
