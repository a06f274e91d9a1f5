#!/usr/bin/env python3
"""Score several VFA CNN weight files on one labelled set (A/B comparisons of training runs).

    python bench/score_vfa_cnn_ab.py --weights data/ab_base/vfa_cnn.pt data/ab_rough/vfa_cnn.pt \
        [--data data/vfa/tune_seed3_n2000.npz] [--safe-weight 2] [--json out.json]

For each file: perfect match, safe rate and mean distance [m] (as ``eval_vfa``) on the samples with a safe
candidate, with the argmax decode and with the ``combined`` decode (lambda = ``--safe-weight``, mu = 0,
the shipped decode's family), overall and per terrain kind; plus the per-cell precision / recall of the
predicted safe mask at p >= 0.5. The network runs on torch (module forward), one thread. The default set is
the decode tuning set (seed 3), never trained on; the protocol's test set (seed 2) is left for the final
model. A benchmark script, not a test.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from tal_lab.vital.eval_vfa import score
from tal_lab.vital.terrain_samples import TERRAIN_KINDS
from tal_lab.vital.tune_vfa_decode import network_outputs, safe_head_quality
from tal_lab.vital.vfa_dataset import VfaDataset

from tal_perception.vfa_cnn import load_model
from tal_perception.vfa_decode import VfaDecode, decode


def rates(data: VfaDataset, choices: np.ndarray, mask: np.ndarray, resolution_m: float = 0.02) -> dict[str, float]:
    """Perfect match, safe, mean distance [m] (``eval_vfa.score``) over the samples of ``mask`` that have a
    safe candidate."""
    scored = score(data.subset(mask), choices[mask], resolution_m)
    return {"count": scored["scored"], **{k: scored[k] for k in ("perfect_match", "safe", "mean_distance_m")}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--weights", type=Path, nargs="+", required=True)
    parser.add_argument("--data", type=Path, default=Path("data/vfa/tune_seed3_n2000.npz"))
    parser.add_argument("--safe-weight", type=float, default=2.0, help="lambda of the combined decode")
    parser.add_argument(
        "--sweep", type=float, nargs="*", default=[0.5, 1.0, 2.0, 3.0, 4.0],
        help="lambdas of the combined decode for the sweep line (the best perfect match + safe over them)",
    )  # fmt: skip
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    data = VfaDataset.load(args.data)
    has_safe = data.label >= 0
    everything = np.ones(len(data), dtype=bool)
    report: dict[str, object] = {"data": str(args.data), "scored": int(has_safe.sum()), "runs": {}}
    print(f"{args.data}: {int(has_safe.sum())} scored samples")
    print("| weights | decode | perfect match | safe | mean distance [m] | " +
          " | ".join(f"{k} match / safe" for k in TERRAIN_KINDS) + " |")  # fmt: skip
    print("| --- " * (4 + len(TERRAIN_KINDS)) + "| --- |")
    for weights in args.weights:
        logits, prob, unknown = network_outputs(load_model(weights), data)
        run: dict[str, object] = {}
        quality = safe_head_quality(data, prob, [0.5])[0]
        run["safe_mask_precision"], run["safe_mask_recall"] = quality["precision"], quality["recall"]
        for name, settings in (
            ("argmax", VfaDecode("argmax")),
            (f"combined {args.safe_weight:g}", VfaDecode("combined", safe_weight=args.safe_weight)),
        ):
            choices = decode(settings, logits, prob, unknown)
            overall = rates(data, choices, everything)
            kinds = {k: rates(data, choices, data.kind == i) for i, k in enumerate(TERRAIN_KINDS)}
            run[name] = {"overall": overall, "per_kind": kinds}
            print(f"| {weights} | {name} | {100 * overall['perfect_match']:.1f} % | {100 * overall['safe']:.1f} % | "
                  f"{overall['mean_distance_m']:.4f} | " +
                  " | ".join(f"{100 * v['perfect_match']:.1f} / {100 * v['safe']:.1f}" for v in kinds.values())
                  + " |")  # fmt: skip
        sweep = {}
        for value in args.sweep:
            choices = decode(VfaDecode("combined", safe_weight=value), logits, prob, unknown)
            sweep[value] = rates(data, choices, everything)
        best = max(sweep, key=lambda v: sweep[v]["perfect_match"] + sweep[v]["safe"])
        run["combined_sweep"] = {str(k): v for k, v in sweep.items()}
        best_sum = 100 * (sweep[best]["perfect_match"] + sweep[best]["safe"])
        print("  combined sweep (lambda: perfect match / safe): " + ", ".join(
            f"{k:g}: {100 * v['perfect_match']:.1f} / {100 * v['safe']:.1f}" for k, v in sweep.items())
            + f"; best sum at lambda {best:g}: {best_sum:.1f}")  # fmt: skip
        print(f"  safe mask at p >= 0.5: precision {100 * run['safe_mask_precision']:.1f} %, recall "
              f"{100 * run['safe_mask_recall']:.1f} %")  # fmt: skip
        report["runs"][str(weights)] = run  # type: ignore[index]
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
