"""Choose the VFA CNN's decode (``vfa_decode``) on a tuning set, then score it once on the protocol's test set.

    python -m tal_lab.vital.tune_vfa_decode --out results/vital [--weights ...] [--seed 3] [--samples-per-leg 2000]

The tuning tuples (seed 3 by default: neither the training seeds 1 and 4 nor the protocol's seed 2) are
labelled like the protocol's (``vfa_dataset``, cached under ``--data``). Every decode of the grid
(``argmax``; ``masked_argmax`` and ``closest_safe`` over ``--taus``; ``closest_safe`` also over ``--bands``;
``combined`` over ``--safe-weights`` x ``--distance-weights``) is scored on them; the best of each mode by
the selection rule ``--rule`` is then scored once on the test set (seed 2, 4401 per leg), and the best of
all modes by the same rule on the tuning set is the chosen decode. Rules (``RULES``): ``match`` = highest
perfect match, then safe rate; ``match_plus_safe`` = highest perfect match + safe rate (= 1 + perfect match
- unsafe rate: one point of perfect match is worth one point of safe rate), then perfect match. Same
measures as ``eval_vfa`` (samples with a safe candidate only). Writes ``<out>/vfa_cnn_decode.json`` and
``<out>/vfa_cnn_decode.md``; with ``--store`` the chosen decode is recorded in the weights file
(``vfa_cnn.store_decode``; the weights unchanged), where ``CnnFootholdSelector`` and ``eval_vfa`` take it
from. The test set never enters a choice.
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

from tal_core.robot_model import RobotModel
from tal_lab.vital.eval_vfa import score
from tal_lab.vital.vfa_dataset import VfaDataset, cache_path, load_or_generate
from tal_perception.fec import FootholdEvaluator
from tal_perception.vfa_cnn import DEFAULT_WEIGHTS, canonical_inputs, encode, load_model, mirror_cell_maps, store_decode
from tal_perception.vfa_decode import VfaDecode, decode

LOG = logging.getLogger("tal_lab.vital.tune_vfa_decode")
MEASURES = ("perfect_match", "safe", "mean_distance_m", "verified_equals_g")
DEFAULT_TAUS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)
DEFAULT_BANDS = (-1.0, 0.0, 1.0, 2.0, 4.0, 8.0)  # -1: the exact tie rule (row-major)
DEFAULT_SAFE_WEIGHTS = (0.25, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0)  # combined: lambda [-]
DEFAULT_DISTANCE_WEIGHTS = (0.0, 0.01, 0.03, 0.1)  # combined: mu [1/cells^2]
MODES = ("argmax", "masked_argmax", "closest_safe", "combined")
RULES = {
    "match": "highest perfect match, then safe rate",
    "match_plus_safe": "highest perfect match + safe rate, then perfect match",
}


def rule_key(rule: str, row: dict[str, object]) -> tuple[float, float]:
    """Sort key of a tuning row under the selection rule (see ``RULES``; larger is better)."""
    match, safe = float(row["perfect_match"]), float(row["safe"])
    if rule == "match":
        return (match, safe)
    if rule == "match_plus_safe":
        return (match + safe, match)
    raise ValueError(f"unknown selection rule {rule!r}; one of {sorted(RULES)}")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m tal_lab.vital.tune_vfa_decode", description=__doc__.split("\n\n")[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )  # fmt: skip
    parser.add_argument("--out", type=Path, required=True, help="folder of vfa_cnn_decode.{json,md}")
    parser.add_argument("--weights", type=Path, default=DEFAULT_WEIGHTS)
    parser.add_argument("--data", type=Path, default=Path("data/vfa"), help="dataset cache folder")
    parser.add_argument("--robot", default="hyq")
    parser.add_argument("--seed", type=int, default=3, help="seed of the tuning tuples")
    parser.add_argument("--samples-per-leg", type=int, default=2000, help="tuning tuples per leg")
    parser.add_argument("--test-seed", type=int, default=2, help="seed of the protocol's test tuples")
    parser.add_argument("--test-samples-per-leg", type=int, default=4401)
    parser.add_argument("--taus", type=float, nargs="+", default=list(DEFAULT_TAUS), help="safe-probability thresholds")
    parser.add_argument(
        "--bands", type=float, nargs="+", default=list(DEFAULT_BANDS),
        help="closest_safe tie bands [cells^2]; a negative value = the exact tie rule",
    )  # fmt: skip
    parser.add_argument(
        "--safe-weights", type=float, nargs="+", default=list(DEFAULT_SAFE_WEIGHTS),
        help="combined: lambda [-], the weight of log(p_safe)",
    )  # fmt: skip
    parser.add_argument(
        "--distance-weights", type=float, nargs="+", default=list(DEFAULT_DISTANCE_WEIGHTS),
        help="combined: mu [1/cells^2], the weight of the squared distance from the nominal",
    )  # fmt: skip
    parser.add_argument("--rule", choices=sorted(RULES), default="match_plus_safe",
                        help="selection rule on the tuning set (per mode and overall)")  # fmt: skip
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--no-test", action="store_true", help="tune only (pilots): do not score the test set")
    parser.add_argument(
        "--store", action="store_true",
        help="record the best decode on the tuning set (all modes) in the weights' metadata (the selector's default)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    if args.seed == args.test_seed:
        parser.error("the tuning seed must differ from the test seed")
    if args.samples_per_leg < 1 or args.test_samples_per_leg < 1:
        parser.error("--samples-per-leg and --test-samples-per-leg must be >= 1")
    return args


def network_outputs(
    net: torch.nn.Module, data: VfaDataset, batch_size: int = 512
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Optimum logits (N, n*n), safe probabilities (N, n*n) or None, unknown cells (N, n*n) of every sample."""
    cfg = net.config.encoding
    logits, safe = [], []
    with torch.inference_mode():
        for start in range(0, len(data), batch_size):
            index = np.arange(start, min(start + batch_size, len(data)))
            heights, twist, legs = data.heights[index], data.twist[index], data.leg[index]
            flip = np.zeros(len(index), dtype=bool)
            if net.config.canonical_legs:  # right legs through their left mirror, the maps mirrored back
                heights, twist, legs, flip = canonical_inputs(heights, twist, legs)
            image, scalars = encode(cfg, heights, data.hip_height_m[index], twist, data.gait[index], legs)
            optimum, safe_logits = net(torch.from_numpy(image), torch.from_numpy(scalars))
            logits.append(mirror_cell_maps(optimum.numpy(), flip, cfg.cells))
            if safe_logits is not None:
                safe.append(mirror_cell_maps(torch.sigmoid(safe_logits).numpy(), flip, cfg.cells))
    unknown = np.isnan(data.heights.reshape(len(data), -1))
    return np.concatenate(logits), (np.concatenate(safe) if safe else None), unknown


def measures(data: VfaDataset, choices: np.ndarray, resolution_m: float) -> dict[str, float]:
    """The protocol's perfect match, safe rate and mean distance [m] (``eval_vfa.score``), plus the share of
    samples where the verified selector returns exactly g (an unsafe choice is replaced by the exact g)."""
    scored = score(data, choices, resolution_m)
    match, safe = scored["perfect_match"], scored["safe"]
    return {"perfect_match": match, "safe": safe, "mean_distance_m": scored["mean_distance_m"],
            "verified_equals_g": match + 1.0 - safe}  # fmt: skip


def fallback_rate(
    data: VfaDataset, settings: VfaDecode, logits: np.ndarray, probability: np.ndarray | None, unknown: np.ndarray
) -> float | None:
    """Fraction of the scored samples where no known cell reaches tau (the masked decodes fall back to the argmax);
    None for the decodes without a threshold (argmax, combined)."""
    if settings.mode not in ("masked_argmax", "closest_safe") or probability is None:
        return None
    rows = data.label >= 0
    return float(np.mean(~((probability[rows] >= settings.tau) & ~unknown[rows]).any(axis=1)))


def safe_head_quality(data: VfaDataset, probability: np.ndarray, taus: list[float]) -> list[dict[str, float]]:
    """Per-cell quality of the predicted safe mask on the scored samples, per tau: precision (passing cells
    that are safe), recall (safe cells that pass) and the fraction of cells classified right."""
    rows = data.label >= 0
    truth = data.safe.reshape(len(data), -1)[rows]
    out = []
    for tau in taus:
        passing = probability[rows] >= tau
        out.append({
            "tau": tau,
            "precision": float((passing & truth).sum() / max(passing.sum(), 1)),
            "recall": float((passing & truth).sum() / max(truth.sum(), 1)),
            "accuracy": float(np.mean(passing == truth)),
        })  # fmt: skip
    return out


def grid_of_decodes(
    taus: list[float], bands: list[float], safe_weights: list[float] = (), distance_weights: list[float] = ()
) -> list[VfaDecode]:
    """argmax; masked_argmax per tau; closest_safe per tau x band (band < 0: exact ties); combined per
    lambda x mu."""
    decodes = [VfaDecode("argmax")]
    decodes += [VfaDecode("masked_argmax", tau) for tau in taus]
    decodes += [VfaDecode("closest_safe", tau, None if band < 0 else band) for tau in taus for band in bands]
    decodes += [VfaDecode("combined", safe_weight=lam, distance_weight=mu) for lam in safe_weights
                for mu in distance_weights]  # fmt: skip
    return decodes


def run(args: argparse.Namespace) -> dict[str, object]:
    torch.set_num_threads(args.threads)
    evaluator = FootholdEvaluator(RobotModel.from_name(args.robot))
    res = evaluator.settings.resolution_m
    net = load_model(args.weights)
    tune = load_or_generate(evaluator, cache_path(args.data, "tune", args.seed, args.samples_per_leg), args.seed,
                            args.samples_per_leg, "labelling tuning set (exact FEC)")  # fmt: skip
    started = time.perf_counter()
    outputs = network_outputs(net, tune)
    decodes = grid_of_decodes(args.taus, args.bands, args.safe_weights, args.distance_weights)
    if outputs[1] is None:
        decodes = decodes[:1]
    tuning = [
        {
            "decode": d.to_dict(),
            **measures(tune, decode(d, *outputs), res),
            "fallback": fallback_rate(tune, d, *outputs),
        }
        for d in decodes
    ]
    best = {}
    for mode in MODES:
        rows = [r for r in tuning if r["decode"]["mode"] == mode]
        if rows:
            best[mode] = max(rows, key=lambda r: rule_key(args.rule, r))
    chosen = max(best.values(), key=lambda r: rule_key(args.rule, r))["decode"]
    if args.no_test:
        summary = {"weights": args.weights.name, "rule": args.rule, "grid": tuning, "best": best, "chosen": chosen}
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "vfa_cnn_decode_tuning.json").write_text(json.dumps(summary, indent=1))
        for mode, row in best.items():
            LOG.info("%s %s: tuning perfect match %.1f %%, safe %.1f %%, mean distance %.4f m", mode, row["decode"],
                     100 * row["perfect_match"], 100 * row["safe"], row["mean_distance_m"])  # fmt: skip
        return summary
    test = load_or_generate(evaluator, cache_path(args.data, "test", args.test_seed, args.test_samples_per_leg),
                            args.test_seed, args.test_samples_per_leg, "labelling test set (exact FEC)")  # fmt: skip
    test_outputs = network_outputs(net, test)
    scored = {
        mode: {"decode": row["decode"], "tuning": {k: row[k] for k in MEASURES},
               "test": measures(test, decode(VfaDecode.from_dict(row["decode"]), *test_outputs), res)}
        for mode, row in best.items()
    }  # fmt: skip
    summary = {
        "command": "python -m tal_lab.vital.tune_vfa_decode " + " ".join(sys.argv[1:]),
        "weights": args.weights.name,
        "rule": args.rule,
        "tuning_set": {"seed": args.seed, "samples_per_leg": args.samples_per_leg,
                       "scored": int((tune.label >= 0).sum())},
        "test_set": {"seed": args.test_seed, "samples_per_leg": args.test_samples_per_leg,
                     "scored": int((test.label >= 0).sum())},
        "best": scored,
        "grid": tuning,
        "safe_head": None if outputs[1] is None else safe_head_quality(tune, outputs[1], args.taus),
        "seconds": time.perf_counter() - started,
    }  # fmt: skip
    summary["chosen"] = chosen
    if args.store:
        store_decode(args.weights, VfaDecode.from_dict(chosen))
        LOG.info("stored the decode %s in %s", chosen, args.weights)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "vfa_cnn_decode.json").write_text(json.dumps(summary, indent=1))
    (args.out / "vfa_cnn_decode.md").write_text(markdown(summary))
    for mode, row in scored.items():
        t = row["test"]
        LOG.info("%s %s: test perfect match %.1f %%, safe %.1f %%, mean distance %.4f m", mode, row["decode"],
                 100 * t["perfect_match"], 100 * t["safe"], t["mean_distance_m"])  # fmt: skip
    return summary


def markdown(summary: dict[str, object]) -> str:
    tuning, test = summary["tuning_set"], summary["test_set"]
    lines = [
        "# VFA CNN decodes (chosen on a tuning set, scored once on the test set)",
        "",
        f"Command: `{summary['command']}`  ",
        f"Weights: `{summary['weights']}`; tuning set seed {tuning['seed']} ({tuning['samples_per_leg']} per leg, "
        f"{tuning['scored']} scored); test set seed {test['seed']} ({test['samples_per_leg']} per leg, "
        f"{test['scored']} scored).",
        "",
        '"verified = g": with the selector\'s verification an unsafe choice is replaced by the exact g, so the '
        "returned foothold is g in perfect match + (1 - safe) of the calls.",
        "",
        f"Selection rule (`--rule {summary.get('rule', 'match')}`, on the tuning set only, per mode and overall): "
        f"{RULES[summary.get('rule', 'match')]}. Each mode's best is scored once on the test set.",
        "",
        "| decode | tau | tie band [cells^2] | lambda / mu [1/cells^2] | tuning: perfect match / safe / mean distance "
        "/ verified = g | test: the same |",
        "| --- | --- | --- | --- | --- | --- |",
    ]

    def triple(m: dict[str, float]) -> str:
        return (f"{100 * m['perfect_match']:.1f} % / {100 * m['safe']:.1f} % / {m['mean_distance_m']:.4f} m "
                f"/ {100 * m['verified_equals_g']:.1f} %")  # fmt: skip

    for mode, row in summary["best"].items():
        d = row["decode"]
        mode = f"**{mode}** (chosen)" if d == summary["chosen"] else mode
        lines.append(f"| {mode} | {_settings_cells(d, 'exact (row-major)')} | {triple(row['tuning'])} | "
                     f"{triple(row['test'])} |")  # fmt: skip
    if summary.get("safe_head"):
        lines += ["", "Predicted safe mask per cell on the tuning set (scored samples):", ""]
        lines += ["| tau | precision | recall | cells right |", "| --- | --- | --- | --- |"]
        for q in summary["safe_head"]:
            lines.append(f"| {q['tau']:g} | {100 * q['precision']:.1f} % | {100 * q['recall']:.1f} % | "
                         f"{100 * q['accuracy']:.1f} % |")  # fmt: skip
    lines += [
        "",
        "Tuning grid (perfect match / safe / mean distance / verified = g on the tuning set; fallback = no cell "
        "passes):",
        "",
    ]
    lines += ["| decode | tau | tie band | lambda / mu | tuning | fallback |", "| --- | --- | --- | --- | --- | --- |"]
    for row in summary["grid"]:
        d = row["decode"]
        fallback = "-" if row["fallback"] is None else f"{100 * row['fallback']:.1f} %"
        lines.append(f"| {d['mode']} | {_settings_cells(d, 'exact')} | {triple(row)} | {fallback} |")
    return "\n".join(lines) + "\n"


def _settings_cells(d: dict[str, object], exact_band: str) -> str:
    """The tau, tie band and lambda / mu cells of a decode's table row ("-" where the mode has none)."""
    tau = "-" if d["mode"] in ("argmax", "combined") else f"{d['tau']:g}"
    band = "-" if d["mode"] != "closest_safe" else (exact_band if d["tie_band_cells2"] is None
                                                    else f"{d['tie_band_cells2']:g}")  # fmt: skip
    weights = "-" if d["mode"] != "combined" else f"{d['safe_weight']:g} / {d['distance_weight']:g}"
    return f"{tau} | {band} | {weights}"


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="[tune_vfa_decode] %(message)s")
    run(parse_args(argv))
    return 0


if __name__ == "__main__":
    sys.exit(main())
