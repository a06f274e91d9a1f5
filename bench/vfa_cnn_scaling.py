#!/usr/bin/env python3
"""Learning curve and capacity of the VFA CNN: how much data would the accuracy goal take?

    python bench/vfa_cnn_scaling.py \
        --run curve 3k data/scale/n3k/vfa_cnn.pt --run curve 12k data/scale/n12k/vfa_cnn.pt ... \
        --run wide "2x wide, 12k" data/scale/wide12k/vfa_cnn.pt \
        --run chain "shipped" tal_perception/tal_perception/models/vfa_cnn.pt \
        --out results/vital/vfa_cnn_scaling

Each ``--run GROUP LABEL WEIGHTS`` is a trained weight file with its ``vfa_cnn_training.json`` beside it (or
``WEIGHTS:TRAINING_JSON``). Groups: ``curve`` (trained from scratch with one recipe, only the data size
differs: the learning curve that is fitted), ``check`` (the same recipe on more data, not fitted: scored
against the fit's prediction), ``wide`` (the same recipe with a wider network) and ``chain``
(the fine-tuned weights that were shipped, plotted for reference, not fitted). Every file is scored on one
labelled set (default: the decode tuning set, seed 3, never trained on; the test seed 2 stays for the final
model) with the thesis' argmax decode and with the ``combined`` decode at the lambda of the best perfect
match + safe over ``--sweep`` (``score_vfa_cnn_ab``'s measures).

The fit: perfect match and safe rate against log2 of the training tuples per leg (least squares over the
``curve`` runs), extrapolated to the goal (85 % perfect match, 98 % safe). The labelling and training time
such a data set would take follow from the measured rates: labels per second of one core (``--labels-per-s``,
measured when the caches were made; see the VFA card) and the training runs' own seconds per sample and
epoch. Writes ``<out>.json``, ``<out>.md`` and ``<out>.png``. A measurement script, not a test.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from score_vfa_cnn_ab import rates  # noqa: E402  (bench/ is on sys.path when this script runs)
from tal_lab.vital.tune_vfa_decode import network_outputs  # noqa: E402
from tal_lab.vital.vfa_dataset import VfaDataset  # noqa: E402

from tal_perception.vfa_cnn import load_model  # noqa: E402
from tal_perception.vfa_decode import VfaDecode, decode  # noqa: E402

GROUPS = ("curve", "check", "wide", "chain")
GOAL_MATCH, GOAL_SAFE = 0.85, 0.98


def training_tuples_per_leg(training: dict) -> int:
    """Labelled tuples per leg behind a weight file: its own set plus the extra and wide sets it was (fine-)tuned
    on, i.e. the data the weights have seen in all (mirroring doubles the samples, not the tuples)."""
    extra = training.get("extra_seeds") or []
    wide = training.get("wide_seeds") or []
    return int(training["samples_per_leg"] * (1 + len(extra)) + (training.get("wide_samples_per_leg") or 0) * len(wide))


def score_weights(weights: Path, data: VfaDataset, sweep: list[float]) -> dict[str, object]:
    """Argmax and best-combined rates of one weight file on ``data`` (samples without a safe candidate skipped)."""
    logits, prob, unknown = network_outputs(load_model(weights), data)
    everything = np.ones(len(data), dtype=bool)
    argmax = rates(data, decode(VfaDecode("argmax"), logits, prob, unknown), everything)
    combined = {
        value: rates(data, decode(VfaDecode("combined", safe_weight=value), logits, prob, unknown), everything)
        for value in sweep
    }
    best = max(combined, key=lambda v: combined[v]["perfect_match"] + combined[v]["safe"])
    return {"argmax": argmax, "combined_best_lambda": best, "combined_best": combined[best]}


def fit_log2(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Least-squares (intercept, slope per doubling) of y = a + b log2(x)."""
    slope, intercept = np.polyfit(np.log2(x), y, 1)
    return float(intercept), float(slope)


def tuples_for(target: float, intercept: float, slope: float) -> float:
    """Tuples per leg at which the fitted line reaches ``target`` (inf if it never rises)."""
    if slope <= 0:
        return math.inf
    return float(2.0 ** ((target - intercept) / slope))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", nargs=3, action="append", metavar=("GROUP", "LABEL", "WEIGHTS"), required=True)
    parser.add_argument("--data", type=Path, default=Path("data/vfa/tune_seed3_n2000.npz"))
    parser.add_argument("--sweep", type=float, nargs="*", default=[0.5, 1.0, 1.5, 2.0, 3.0, 4.0])
    parser.add_argument(
        "--labels-per-s", type=float, default=400.0,
        help="exact labels per second of one core (VFA card: 330-520 measured while making the caches)",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, required=True, help="output prefix (.json, .md, .png are added)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    data = VfaDataset.load(args.data)
    runs = []
    for group, label, spec in args.run:
        if group not in GROUPS:
            parser.error(f"--run {group!r}: the group must be one of {GROUPS}")
        weights_text, _, json_text = spec.partition(":")
        weights = Path(weights_text)
        training_path = Path(json_text) if json_text else weights.with_name("vfa_cnn_training.json")
        training = json.loads(training_path.read_text())
        scored = score_weights(weights, data, args.sweep)
        run = {
            "group": group, "label": label, "weights": str(weights), "training_json": str(training_path),
            "tuples_per_leg": training_tuples_per_leg(training), "train_samples": training["train_samples"],
            "epochs_run": training["optimiser"]["epochs_run"], "training_s": training["training_s"],
            "parameters": training["net"]["parameters"], "channels": training["net"].get("channels"),
            "decoder_channels": training["net"].get("decoder_channels"), "command": training["command"], **scored,
        }  # fmt: skip
        runs.append(run)
        print(f"{group:5s} {label:14s} {run['tuples_per_leg']:7d} tuples/leg  argmax "
              f"{100 * scored['argmax']['perfect_match']:.1f} / {100 * scored['argmax']['safe']:.1f} %  combined "
              f"(lambda {scored['combined_best_lambda']:g}) {100 * scored['combined_best']['perfect_match']:.1f} / "
              f"{100 * scored['combined_best']['safe']:.1f} %", flush=True)  # fmt: skip
    curve = [r for r in runs if r["group"] == "curve"]
    report: dict[str, object] = {"data": str(args.data), "scored": int((data.label >= 0).sum()), "runs": runs}
    if len(curve) >= 2:
        x = np.array([r["tuples_per_leg"] for r in curve], dtype=float)
        fits = {}
        for name, decode_key, measure, goal in (
            ("argmax perfect match", "argmax", "perfect_match", GOAL_MATCH),
            ("argmax safe", "argmax", "safe", GOAL_SAFE),
            ("combined perfect match", "combined_best", "perfect_match", GOAL_MATCH),
            ("combined safe", "combined_best", "safe", GOAL_SAFE),
        ):
            y = np.array([r[decode_key][measure] for r in curve])
            intercept, slope = fit_log2(x, y)
            needed = tuples_for(goal, intercept, slope)
            fits[name] = {
                "intercept": intercept, "per_doubling": slope, "goal": goal, "tuples_per_leg_for_goal": needed,
            }  # fmt: skip
        # Cost of the largest goal's data set, from the measured rates.
        seconds_per_sample_epoch = float(
            np.median([r["training_s"] / (r["train_samples"] * r["epochs_run"]) for r in curve])
        )
        samples_per_tuple = float(np.median([r["train_samples"] / (4 * r["tuples_per_leg"]) for r in curve]))
        for fit in fits.values():
            tuples = fit["tuples_per_leg_for_goal"]
            fit["labelling_core_hours"] = 4 * tuples / args.labels_per_s / 3600 if math.isfinite(tuples) else math.inf
            fit["training_core_hours_per_epoch"] = (
                4 * tuples * samples_per_tuple * seconds_per_sample_epoch / 3600 if math.isfinite(tuples) else math.inf
            )
        report["fits"] = fits
        for run in runs:  # the held-out runs of the same recipe against the fit's prediction
            if run["group"] == "check":
                run["predicted"] = {
                    name: fit["intercept"] + fit["per_doubling"] * math.log2(run["tuples_per_leg"])
                    for name, fit in fits.items()
                }
        report["seconds_per_sample_epoch"] = seconds_per_sample_epoch
        report["labels_per_s"] = args.labels_per_s
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(report, indent=1))
    args.out.with_suffix(".md").write_text(markdown(report, argv if argv is not None else sys.argv[1:]))
    plot(report, args.out.with_suffix(".png"))
    print(f"wrote {args.out}.json / .md / .png")
    return 0


def markdown(report: dict, argv: list[str]) -> str:
    """The runs' table and the fits, as markdown."""
    lines = [
        "# VFA CNN: learning curve and capacity",
        "",
        f"Command: `python bench/vfa_cnn_scaling.py {shlex.join(argv)}`  ",
        f"Scored on `{report['data']}` ({report['scored']} tuples with a safe candidate).",
        "",
        "| group | run | tuples per leg | epochs | parameters | training [s] | argmax: perfect match / safe "
        "| combined (best lambda): perfect match / safe |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]  # fmt: skip
    for r in report["runs"]:
        a, c = r["argmax"], r["combined_best"]
        lines.append(
            f"| {r['group']} | {r['label']} | {r['tuples_per_leg']:,} | {r['epochs_run']} | {r['parameters']:,} | "
            f"{r['training_s']:.0f} | {100 * a['perfect_match']:.1f} / {100 * a['safe']:.1f} % | "
            f"{100 * c['perfect_match']:.1f} / {100 * c['safe']:.1f} % (lambda {r['combined_best_lambda']:g}) |"
        )
    for r in report["runs"]:
        if "predicted" in r:
            p = r["predicted"]
            lines += ["", f"Held-out check `{r['label']}` against the fit's prediction: argmax perfect match "
                      f"{100 * r['argmax']['perfect_match']:.1f} % "
                      f"(predicted {100 * p['argmax perfect match']:.1f} %), "
                      f"safe {100 * r['argmax']['safe']:.1f} % ({100 * p['argmax safe']:.1f} %); combined "
                      f"{100 * r['combined_best']['perfect_match']:.1f} / {100 * r['combined_best']['safe']:.1f} % "
                      f"({100 * p['combined perfect match']:.1f} / {100 * p['combined safe']:.1f} %)."]  # fmt: skip
    lines += ["", "Training commands (from each run's `vfa_cnn_training.json`):", ""]
    lines += [f"- {r['label']}: `{r['command']}`" for r in report["runs"]]
    if "fits" in report:
        lines += [
            "",
            "Fit over the `curve` runs: rate = a + b log2(tuples per leg); extrapolated to the goal. Labelling at "
            f"{report['labels_per_s']:g} labels/s per core; training at "
            f"{1e6 * report['seconds_per_sample_epoch']:.0f} us "
            "per sample and epoch (the curve runs' median, one thread).",
            "",
            "| measure | a | b (per doubling) | goal | tuples per leg for the goal | labelling [core-hours] "
            "| training [core-hours per epoch] |",
            "| --- | --- | --- | --- | --- | --- | --- |",
        ]  # fmt: skip
        for name, f in report["fits"].items():
            tuples = f["tuples_per_leg_for_goal"]
            tuples_text = f"{tuples:,.0f}" if math.isfinite(tuples) else "never (no rise)"
            lines.append(
                f"| {name} | {100 * f['intercept']:.1f} % | {100 * f['per_doubling']:+.2f} points | "
                f"{100 * f['goal']:.0f} % | "
                f"{tuples_text} | {f['labelling_core_hours']:,.0f} | {f['training_core_hours_per_epoch']:,.0f} |"
            )
    return "\n".join(lines) + "\n"


def plot(report: dict, path: Path) -> None:
    """Perfect match and safe rate against tuples per leg (log axis), with the fit and the goal."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    markers = {"curve": ("o", "C0"), "check": ("D", "C1"), "wide": ("s", "C3"), "chain": ("^", "C2")}
    for ax, measure, goal, title in (
        (axes[0], "perfect_match", GOAL_MATCH, "perfect match"),
        (axes[1], "safe", GOAL_SAFE, "safe"),
    ):
        for group, (marker, colour) in markers.items():
            runs = [r for r in report["runs"] if r["group"] == group]
            if not runs:
                continue
            x = [r["tuples_per_leg"] for r in runs]
            ax.plot(x, [100 * r["argmax"][measure] for r in runs], marker, color=colour, label=f"{group}, argmax")
            ax.plot(x, [100 * r["combined_best"][measure] for r in runs], marker, color=colour, mfc="none",
                    label=f"{group}, combined")  # fmt: skip
            for k, r in enumerate(runs):  # the chain's labels below their points, alternating, to stay apart
                offset = (4, -10 - 8 * (k % 2)) if group == "chain" else (3, 3)
                ax.annotate(r["label"], (r["tuples_per_leg"], 100 * r["argmax"][measure]), fontsize=7,
                            xytext=offset, textcoords="offset points")  # fmt: skip
        for decode_key, style in (("argmax", "-"), ("combined", "--")):
            fit = report.get("fits", {}).get(f"{decode_key} {title}")
            if fit:
                x_end = fit["tuples_per_leg_for_goal"] if math.isfinite(fit["tuples_per_leg_for_goal"]) else 1e6
                xs = np.geomspace(2000, max(2e5, min(x_end, 1e8)), 50)
                ax.plot(xs, 100 * (fit["intercept"] + fit["per_doubling"] * np.log2(xs)), style, color="C0", lw=0.8,
                        label=f"fit ({decode_key})")  # fmt: skip
        ax.axhline(100 * goal, color="k", ls=":", lw=0.8, label="goal")
        ax.set_xscale("log")
        ax.set_xlabel("labelled tuples per leg")
        ax.set_ylabel(f"{title} [%] (tuning set)")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle("VFA CNN: accuracy against training data (log scale) and width")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
