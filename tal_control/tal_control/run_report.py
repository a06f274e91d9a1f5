"""Summary of a locomotion run of the graph (``make run``): the bridge's and the wbc's end-of-run JSON.

Usage: python -m tal_control.run_report --bridge bridge.json --wbc wbc.json [--output report.md]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def format_report(bridge: dict, wbc: dict, title: str) -> str:
    fell = "yes (" + ", ".join(bridge["body_ground_contact"]) + ")" if bridge["body_ground_contact"] else "no"

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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bridge", type=Path, required=True, help="summary.json of sim_bridge")
    parser.add_argument("--wbc", type=Path, required=True, help="summary.json of wbc")
    parser.add_argument("--title", default="Locomotion run")
    parser.add_argument("--output", type=Path)
    args = parser.parse_args(argv)
    for path in (args.bridge, args.wbc):
        if not path.is_file():
            parser.error(f"{path}: no summary (did the node finish cleanly?)")
    report = format_report(json.loads(args.bridge.read_text()), json.loads(args.wbc.read_text()), args.title)
    print(report)
    if args.output:
        args.output.write_text(report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
