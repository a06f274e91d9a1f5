"""Accuracy protocol of the VFA CNN (thesis, ViTAL chapter, "Estimation Accuracy"): g_hat versus g.

    python -m tal_lab.vital.eval_vfa --out results/vital [--weights ...] [--seed 2] [--samples-per-leg 4401]

Fresh random tuples (``vfa_dataset``, a seed other than the training seed; 4401 per leg as in the
thesis) are labelled by the exact evaluation (full FEC + argmin) and given to the committed CNN through
``CnnFootholdSelector.predict`` without verification (with the decode stored with the weights).
Measures, per leg and overall, on the samples that have a safe candidate (those without one are
counted apart: the CNN cannot say "none"):

* perfect match: g_hat = g (same cell);
* safe: g_hat is in the exact eroded safe set (includes the perfect matches; the thesis' 93.7 % is
  above its 74.0 % perfect match, so it counts them too) = how often the optional verification accepts;
* mean distance: |g_hat - g| [m] horizontal, in the patch.

Writes ``<out>/vfa_cnn_accuracy.md`` (table versus the thesis and the goal), ``vfa_cnn_accuracy.json``
and ``vfa_cnn_accuracy.png`` (distance histogram and example patches).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from tal_core.legs import LEGS
from tal_core.robot_model import RobotModel
from tal_lab.vital.terrain_samples import TERRAIN_KINDS
from tal_lab.vital.vfa_dataset import (
    HIP_RANGES,
    VfaDataset,
    cache_path,
    load_or_generate,
    mix_description,
    set_prefix,
)
from tal_perception.fec import FootholdEvaluator
from tal_perception.vfa_cnn import DEFAULT_WEIGHTS, CnnFootholdSelector, load_model

LOG = logging.getLogger("tal_lab.vital.eval_vfa")
THESIS = {"perfect_match": 0.740, "safe": 0.937, "mean_distance_m": 0.02}
# [m] bins of the hip's height above the median known patch height: below, within and above the standard range
HIP_BINS_M = (0.40, *HIP_RANGES["standard"], 0.80)
GOAL = {"perfect_match": 0.85, "safe": 0.98, "mean_distance_m": 0.01}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m tal_lab.vital.eval_vfa", description=__doc__.split("\n\n")[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )  # fmt: skip
    parser.add_argument("--out", type=Path, required=True, help="folder of the report (md, json, png)")
    parser.add_argument("--weights", type=Path, default=DEFAULT_WEIGHTS)
    parser.add_argument("--data", type=Path, default=Path("data/vfa"), help="dataset cache folder")
    parser.add_argument("--robot", default="hyq")
    parser.add_argument("--seed", type=int, default=2, help="seed of the test tuples (training used 1)")
    parser.add_argument("--samples-per-leg", type=int, default=4401)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--hip-range", choices=sorted(HIP_RANGES), default="standard",
                        help="sampling of the test tuples' hip heights (standard: the thesis' protocol as before)")
    args = parser.parse_args(argv)
    if args.samples_per_leg < 1:
        parser.error("--samples-per-leg must be >= 1")
    return args


def predict_all(selector: CnnFootholdSelector, data: VfaDataset, batch_size: int = 256) -> np.ndarray:
    """The CNN's choice (flat index) for every sample, in batches."""
    choices = np.empty(len(data), np.intp)
    for start in tqdm(range(0, len(data), batch_size), desc="CNN", unit="batch"):
        index = range(start, min(start + batch_size, len(data)))
        choices[index.start : index.stop] = selector.predict([data.fec_input(i) for i in index])
    return choices


def score(data: VfaDataset, choices: np.ndarray, resolution_m: float) -> dict[str, object]:
    """The three measures on the samples with a safe candidate, plus counts and distance percentiles."""
    n = data.cells
    has_safe = data.label >= 0
    centre = (n // 2) * n + n // 2
    label, choice = data.label[has_safe].astype(np.intp), choices[has_safe]
    rows = np.flatnonzero(has_safe)
    distance = np.hypot(choice // n - label // n, choice % n - label % n) * resolution_m
    safe = data.safe.reshape(len(data), -1)[rows, choice]
    adapted = label != centre
    scored = int(has_safe.sum())

    def rate(mask: np.ndarray) -> float | None:
        return float(mask.mean()) if mask.size else None

    return {
        "samples": len(data),
        "scored": scored,
        "no_safe_candidate": int((~has_safe).sum()),
        "adapted": int(adapted.sum()),
        "perfect_match": rate(choice == label),
        "safe": rate(safe),
        "mean_distance_m": float(distance.mean()) if scored else None,
        "distance_p90_m": float(np.percentile(distance, 90)) if scored else None,
        "perfect_match_adapted": rate((choice == label)[adapted]),
        "safe_adapted": rate(safe[adapted]),
        "perfect_match_nominal_optimal": rate((choice == label)[~adapted]),
        "cnn_kept_nominal_when_adapted": rate((choice == centre)[adapted]),
    }


def hip_above_median_m(data: VfaDataset) -> np.ndarray:
    """[m] each sample's hip height above its patch's median known height (what the sampling draws)."""
    return data.hip_height_m - np.nanmedian(data.heights.reshape(len(data), -1), axis=1)


def per_hip_bin(data: VfaDataset, choices: np.ndarray, resolution_m: float) -> dict[str, object]:
    """``score`` per bin of ``HIP_BINS_M`` (the bins that hold samples), keyed "low-high" [m]."""
    above = hip_above_median_m(data)
    bins = {}
    for low, high in zip(HIP_BINS_M[:-1], HIP_BINS_M[1:]):
        mask = (above >= low - 1e-4) & (above < high - 1e-4)
        if mask.any():
            bins[f"{low:.2f}-{high:.2f}"] = score(data.subset(mask), choices[mask], resolution_m)
    return bins


def markdown(summary: dict[str, object]) -> str:
    per_leg, overall = summary["per_leg"], summary["overall"]

    def pct(x: float | None) -> str:
        return "-" if x is None else f"{100 * x:.1f} %"

    seeds = ", ".join(str(x) for x in [summary["training_seed"], *summary.get("extra_training_seeds", [])])
    lines = [
        "# VFA CNN accuracy (g_hat versus the exact g)",
        "",
        f"Command: `{summary['command']}`  ",
        f"Weights: `{summary['weights']}` ({summary['weights_kb']:.0f} kB); test seed {summary['seed']} "
        f"(training seeds {seeds}); "
        f"{summary['samples_per_leg']} fresh tuples per leg, "
        "labelled by the full exact FEC + argmin (cached under the --data folder).",
        f"Sampling: {summary['sampling']}.",
        f"Network: `{summary['architecture']}`; decode (stored with the weights): `{summary['decode']}`.",
        "",
        'Scored on the samples with at least one safe candidate; "safe" = the CNN\'s cell is in the exact '
        "eroded safe set (perfect matches included); distance = |g_hat - g| horizontally.",
        "",
        "| leg | scored | no safe (excluded) | need adaptation | perfect match | safe | mean distance [m] | "
        "p90 distance [m] | perfect match, adapted | safe, adapted |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for name, m in [*per_leg.items(), ("all", overall)]:
        lines.append(
            f"| {name} | {m['scored']} | {m['no_safe_candidate']} | {m['adapted']} | {pct(m['perfect_match'])} | "
            f"{pct(m['safe'])} | {m['mean_distance_m']:.4f} | {m['distance_p90_m']:.3f} | "
            f"{pct(m['perfect_match_adapted'])} | {pct(m['safe_adapted'])} |"
        )
    lines += [
        "",
        "| measure (all legs) | measured | thesis | goal |",
        "| --- | --- | --- | --- |",
        f"| perfect match | {pct(overall['perfect_match'])} | {pct(THESIS['perfect_match'])} | "
        f">= {pct(GOAL['perfect_match'])} |",
        f"| safe | {pct(overall['safe'])} | {pct(THESIS['safe'])} | >= {pct(GOAL['safe'])} |",
        f"| mean distance | {overall['mean_distance_m']:.4f} m | {THESIS['mean_distance_m']} m | "
        f"<= {GOAL['mean_distance_m']} m |",
        "",
        "Per terrain kind (all legs): "
        + "; ".join(
            f"{kind} {pct(m['perfect_match'])} match / {pct(m['safe'])} safe (n = {m['scored']})"
            for kind, m in summary["per_kind"].items()
        )
        + ".",
        "",
        "By the hip's height above the median patch height [m] (the standard sampling draws 0.52-0.66): "
        + "; ".join(
            f"{name}: {pct(m['perfect_match'])} match / {pct(m['safe'])} safe / {m['mean_distance_m']:.4f} m "
            f"(n = {m['scored']})"
            for name, m in summary.get("per_hip_bin", {}).items() if m["scored"]
        )
        + ".",
        "",
        f"With the verification on (the `vfa` node's `cnn` selector), the exact lazy search replaces the CNN's "
        f"choice on {pct(1 - overall['safe'])} of these samples and on every sample without a safe candidate.",
        "",
        "![distances and examples](vfa_cnn_accuracy.png)",
        "",
    ]
    return "\n".join(lines)


def plot(data: VfaDataset, choices: np.ndarray, resolution_m: float, path: Path) -> None:
    """Histogram of |g_hat - g| and six example patches (heights, exact safe set, g and g_hat)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = data.cells
    has_safe = np.flatnonzero(data.label >= 0)
    centre = (n // 2) * n + n // 2
    label, choice = data.label[has_safe].astype(np.intp), choices[has_safe]
    distance = np.hypot(choice // n - label // n, choice % n - label % n) * resolution_m
    fig = plt.figure(figsize=(13, 7.5), constrained_layout=True)
    grid = fig.add_gridspec(2, 4)
    ax = fig.add_subplot(grid[:, 0])
    ax.hist(distance, bins=np.arange(0.0, max(distance.max(), 0.1) + 0.02, 0.02) - 0.01, color="tab:blue")
    ax.set_yscale("log")
    ax.set_xlabel("|g_hat - g| [m]")
    ax.set_ylabel("samples")
    ax.set_title(f"{has_safe.size} samples, {np.mean(distance == 0):.1%} exact")
    colours = plt.get_cmap("viridis").copy()
    colours.set_bad("white")  # unknown cells
    adapted = has_safe[label != centre]
    wrong = has_safe[choice != label]
    examples = [*adapted[:4], *wrong[:2]]
    extent = np.array([-0.5, n - 0.5]) - n // 2
    for k, i in enumerate(examples):
        ax = fig.add_subplot(grid[k // 3, 1 + k % 3])
        image = ax.imshow(data.heights[i], cmap=colours, origin="lower", extent=(*extent, *extent))
        fig.colorbar(image, ax=ax, shrink=0.8, label="height [m] (white: unknown)")
        ax.contour(np.arange(n) - n // 2, np.arange(n) - n // 2, data.safe[i].astype(float), levels=[0.5],
                   colors="orange", linewidths=1.2)  # fmt: skip
        marks = ((data.label[i], "o", "white", "g (exact)"), (choices[i], "x", "red", "g_hat (CNN)"))
        for index, marker, colour, name in marks:
            ax.plot(index % n - n // 2, index // n - n // 2, marker, color=colour, ms=9, mew=2, mfc="none", label=name)
        ax.plot(0, 0, "+", color="k", ms=8, label="nominal")
        ax.set_title(f"{LEGS[data.leg[i]].name}, {TERRAIN_KINDS[data.kind[i]]}", fontsize=9)
        ax.set_xlabel("column (y, left) [cells]", fontsize=8)
        ax.set_ylabel("row (x, forward) [cells]", fontsize=8)
        if k == 0:
            ax.legend(fontsize=7, loc="lower left")
    fig.suptitle("VFA CNN versus exact g: orange contour = exact safe set (eroded)")
    fig.savefig(path, dpi=80)
    plt.close(fig)


def run(args: argparse.Namespace) -> dict[str, object]:
    torch.set_num_threads(args.threads)
    evaluator = FootholdEvaluator(RobotModel.from_name(args.robot))
    net = load_model(args.weights)
    selector = CnnFootholdSelector(evaluator, net, verify=False)
    started = time.perf_counter()
    path = cache_path(args.data, set_prefix("test", args.hip_range), args.seed, args.samples_per_leg)
    data = load_or_generate(evaluator, path, args.seed, args.samples_per_leg, "labelling test set (exact FEC)",
                            hip_range=args.hip_range)  # fmt: skip
    labelling_s = time.perf_counter() - started
    started = time.perf_counter()
    choices = predict_all(selector, data)
    inference_s = time.perf_counter() - started
    res = evaluator.settings.resolution_m
    metadata = torch.load(args.weights, map_location="cpu", weights_only=True).get("metadata", {})
    training_seed = metadata.get("seed", "?")
    extra_seeds = list(metadata.get("extra_seeds", []))  # fine-tuning data of other seeds (train_vfa --extra-seeds)
    if args.seed == training_seed or args.seed in extra_seeds:
        LOG.warning("the test seed is a training seed: the test tuples are training tuples")
    summary = {
        "command": "python -m tal_lab.vital.eval_vfa " + " ".join(sys.argv[1:]),
        "weights": str(args.weights.name),
        "weights_kb": args.weights.stat().st_size / 1e3,
        "architecture": net.config.architecture,
        "decode": selector.decode.to_dict(),
        "seed": args.seed,
        "training_seed": training_seed,
        "extra_training_seeds": extra_seeds,
        "samples_per_leg": args.samples_per_leg,
        "sampling": mix_description(args.hip_range),
        "hip_range": args.hip_range,
        "labelling_or_cache_s": labelling_s,
        "inference_s": inference_s,
        "thesis": THESIS,
        "goal": GOAL,
        "overall": score(data, choices, res),
        "per_leg": {
            leg.name: score(data.subset(data.leg == i), choices[data.leg == i], res) for i, leg in enumerate(LEGS)
        },
        "per_kind": {
            kind: score(data.subset(data.kind == i), choices[data.kind == i], res)
            for i, kind in enumerate(TERRAIN_KINDS)
            if (data.kind == i).any()
        },
        "per_hip_bin": per_hip_bin(data, choices, res),
        "dataset": data.statistics(),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "vfa_cnn_accuracy.json").write_text(json.dumps(summary, indent=1))
    (args.out / "vfa_cnn_accuracy.md").write_text(markdown(summary))
    plot(data, choices, res, args.out / "vfa_cnn_accuracy.png")
    overall = summary["overall"]
    LOG.info("perfect match %.1f %%, safe %.1f %%, mean distance %.4f m on %d samples; wrote %s",
             100 * overall["perfect_match"], 100 * overall["safe"], overall["mean_distance_m"], overall["scored"],
             args.out / "vfa_cnn_accuracy.md")  # fmt: skip
    return summary


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="[eval_vfa] %(message)s")
    run(parse_args(argv))
    return 0


if __name__ == "__main__":
    sys.exit(main())
