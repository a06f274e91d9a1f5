"""Command line of the sim-vs-measured gap workflow (``python -m tal_sim2real`` or ``tal_sim2real``).

tal_sim2real identify BAG [--model SIM_BRIDGE.yaml | --course NAME] --out DIR [--no-closed-loop] [--jobs 2]
    find, name and fit the missing effect(s), write the updated model and report.md with plots
tal_sim2real generate --out DIR [--count 30] [--seed 0] [--variants N] [--out-of-library N] [--only NAME ...]
    hidden-effect test bags (labels sealed in DIR/sealed/); --only: just the benchmark's datasets so named
    (e.g. outlib_00 variant_02), the same bags the benchmark with these arguments generates
tal_sim2real benchmark --out results/sim2real [--count 30] [--jobs 2]
    generate, identify every bag, score against the sealed labels, write the summary
tal_sim2real mujoco --out results/sim2real/mujoco [--data data/sim2real/mujoco]
    record a HyQ trot in MuJoCo (a second physics engine) as the measured data and identify it
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from .errors import Sim2RealError
from .model import SimModel

if TYPE_CHECKING:
    from .outcomes import Identification

LOG = logging.getLogger("tal.sim2real")


def run_identify(
    bag: Path, model: SimModel, out: Path, closed_loop: bool = True, gait: str | None = None, jobs: int = 1
) -> Path:
    """The whole workflow on one bag; returns the report path."""
    return identify_and_report(bag, model, out, closed_loop, gait, jobs)[1]


def available_cpus() -> int:
    """CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def default_jobs() -> int:
    """identify's default ``--jobs``: 2 when a CPU is to spare (the 1-minute load average below the CPUs less
    half of one), else 1. Each prediction waits for its slowest share: on this 2-CPU machine a helper took
    identify from 33-35 s to 26-28 s at a load average of 1.1, and made the workflow 5 s slower at 2.1-2.7."""
    cpus = available_cpus()
    try:
        load = os.getloadavg()[0]
    except OSError:
        return 1
    return 2 if cpus >= 2 and load < cpus - 0.5 else 1


def identify_and_report(
    bag: Path, model: SimModel, out: Path, closed_loop: bool = True, gait: str | None = None, jobs: int = 1
) -> tuple[Identification, Path]:
    """The whole workflow on one bag; returns the identification and the report path. ``jobs``: processes
    that share the open-loop segments (``Settings.segment_workers``; the results do not depend on it)."""
    from tal_core.robot_description import load_robot_description

    from .identify import Settings, identify
    from .measured import load_measured
    from .replay import closed_loop_rerun, holdout_overlay, start_nominal_rerun
    from .report import write_report

    data = load_measured(bag, load_robot_description(model.robot))  # read once for all three steps
    # the nominal closed-loop re-run needs nothing identified: it runs in its own process meanwhile
    nominal_run = start_nominal_rerun(model, data, gait) if closed_loop else None
    try:
        result = identify(bag, model, Settings(segment_workers=max(1, jobs)), data=data)
        model_path = result.updated.write_yaml(out / "model_updated.yaml")
        overlay = holdout_overlay(result, data)
        closed = closed_loop_rerun(result, data, gait, nominal_run) if closed_loop else None
    finally:
        if nominal_run is not None:
            nominal_run.close()
    path = write_report(result, out, overlay, closed, model_path)
    for f in result.named:
        LOG.info("named %s: %s", f.candidate, {k: round(v, 6) for k, v in f.values.items()})
    if not result.named:
        LOG.info("no missing effect named")
    LOG.info("verdict: %s", result.verdict)
    return result, path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="tal_sim2real",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__,
    )
    sub = parser.add_subparsers(dest="command", required=True)
    p_id = sub.add_parser("identify", help="identify the missing effects in a measured bag")
    p_id.add_argument("bag", type=Path)
    group = p_id.add_mutually_exclusive_group()
    group.add_argument("--model", type=Path, help="nominal model: a sim_bridge parameter YAML")
    group.add_argument("--course", default="flat_rigid", help="nominal course when no --model (default flat_rigid)")
    p_id.add_argument("--out", type=Path, required=True, help="report folder")
    p_id.add_argument("--no-closed-loop", action="store_true", help="skip the closed-loop re-runs in the report")
    p_id.add_argument(
        "--gait", choices=("stand", "crawl", "trot"), help="gait of the closed-loop re-run (default: the recording's)"
    )
    p_id.add_argument(
        "--jobs",
        type=int,
        default=default_jobs(),
        help="processes that share the open-loop re-simulations (default: 2 when the load average leaves a CPU "
        "idle, else 1; the same results either way)",
    )
    p_gen = sub.add_parser("generate", help="hidden-effect test bags")
    p_gen.add_argument("--out", type=Path, required=True)
    p_gen.add_argument("--count", type=int, default=30)
    p_gen.add_argument("--seed", type=int, default=0)
    p_gen.add_argument(
        "--variants", type=int, help="variant_NN datasets as in benchmark (default 0; with --only: 3, the benchmark's)"
    )
    p_gen.add_argument(
        "--out-of-library", type=int, help="outlib_NN datasets as in benchmark (default 0; with --only: 3)"
    )
    p_gen.add_argument(
        "--only", nargs="+", metavar="NAME", help="generate only these datasets of the benchmark's list (hidden_13 ...)"
    )
    p_b = sub.add_parser("benchmark", help="generate, identify and score hidden-effect datasets")
    p_b.add_argument("--out", type=Path, default=Path("results/sim2real"))
    p_b.add_argument("--data", type=Path, default=Path("data/sim2real"), help="where the bags go (git-ignored)")
    p_b.add_argument("--count", type=int, default=30)
    p_b.add_argument("--seed", type=int, default=0)
    p_b.add_argument("--jobs", type=int, default=2)
    p_b.add_argument(
        "--out-of-library", type=int, default=3, help="datasets with a per-joint effect the library lacks (default 3)"
    )
    p_b.add_argument(
        "--variants", type=int, default=3, help="datasets with a per-leg / per-joint effect of a library variant"
    )
    p_mj = sub.add_parser("mujoco", help="a HyQ trot recorded in MuJoCo as the measured side (issue 34)")
    p_mj.add_argument("--out", type=Path, default=Path("results/sim2real/mujoco"), help="results page and plots")
    p_mj.add_argument("--data", type=Path, default=Path("data/sim2real/mujoco"), help="where the bags go")
    p_mj.add_argument("--duration-s", type=float, default=8.0)
    p_mj.add_argument("--seed", type=int, default=0, help="seed of the sensor noise")
    p_mj.add_argument("--no-control", action="store_true", help="skip identifying the PyBullet twin (control)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        if args.command == "identify":
            model = SimModel.from_yaml(args.model) if args.model else SimModel.nominal(args.course)
            report = run_identify(args.bag, model, args.out, not args.no_closed_loop, args.gait, args.jobs)
            print(f"report: {report}")
        elif args.command == "generate":
            from .benchmark import generate_cases

            default_local = 3 if args.only else 0
            try:
                generate_cases(
                    args.out,
                    args.only,
                    args.count,
                    args.seed,
                    default_local if args.out_of_library is None else args.out_of_library,
                    default_local if args.variants is None else args.variants,
                )
            except ValueError as exc:
                parser.error(str(exc))
        elif args.command == "mujoco":
            from .mujoco_experiment import run_mujoco_experiment

            readme = run_mujoco_experiment(args.out, args.data, args.duration_s, args.seed, not args.no_control)
            print(f"results: {readme}")
        else:
            from .benchmark import run_benchmark

            summary = run_benchmark(
                args.out, args.data, args.count, args.seed, args.jobs, args.out_of_library, args.variants
            )
            print(f"summary: {summary}")
    except Sim2RealError as exc:
        LOG.error("%s", exc)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
