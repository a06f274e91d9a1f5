#!/usr/bin/env python3
"""Mirror test-time augmentation of the VFA CNN: does averaging a tuple with its y-mirror help?

    python bench/score_vfa_cnn_mirror.py [--weights path/vfa_cnn.pt] [--data data/vfa/tune_seed3_n2000.npz] \
        [--safe-weights 1 1.5 2 3] [--json out.json]

HyQ is symmetric about its x-z plane, so a tuple and its mirror (columns flipped, vy and yaw rate negated, left
and right legs swapped: ``vfa_dataset.mirrored``) have mirrored optima. The network sees both; the mirror's
outputs are flipped back and averaged with the plain ones (optimum head: mean log-softmax; safe head: mean
probability), then decoded with the ``combined`` decode (lambda = each ``--safe-weights``, mu = 0). Printed and
written: perfect match, safe rate and mean distance [m] (``eval_vfa.score``) of the plain and the averaged
outputs. It costs a second forward pass per leg, which this script does not time. The default set is the
decode tuning set (seed 3), never trained on. A benchmark script, not a test.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from scipy.special import log_softmax
from tal_lab.vital.eval_vfa import score
from tal_lab.vital.tune_vfa_decode import network_outputs
from tal_lab.vital.vfa_dataset import VfaDataset, mirrored

from tal_perception.vfa_cnn import load_model, mirror_cell_maps
from tal_perception.vfa_decode import VfaDecode, decode


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", type=Path, default=None, help="weights file (default: the shipped vfa_cnn.pt)")
    parser.add_argument("--data", type=Path, default=Path("data/vfa/tune_seed3_n2000.npz"))
    parser.add_argument("--safe-weights", type=float, nargs="+", default=[1.0, 1.5, 2.0, 3.0])
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    if not args.data.exists():
        parser.error(f"{args.data}: no such labelled set (make it with python -m tal_lab.vital.eval_vfa)")
    if any(not np.isfinite(w) or w < 0.0 for w in args.safe_weights):
        parser.error(f"--safe-weights must be finite and >= 0, got {args.safe_weights}")
    torch.set_num_threads(1)
    net = load_model(args.weights) if args.weights is not None else load_model()
    if not net.config.safe_head:
        parser.error("the combined decode needs a network with a safe-mask head")
    data = VfaDataset.load(args.data)
    cells, resolution = data.cells, net.config.encoding.resolution_m
    logits, probability, unknown = network_outputs(net, data)
    mirror_logits, mirror_probability, _ = network_outputs(net, mirrored(data))
    every = np.ones(len(data), dtype=bool)  # each mirrored tuple's outputs flipped back to the original columns
    averaged_logits = 0.5 * (log_softmax(logits, axis=1) + mirror_cell_maps(log_softmax(mirror_logits, axis=1),
                                                                            every, cells))  # fmt: skip
    averaged_probability = 0.5 * (probability + mirror_cell_maps(mirror_probability, every, cells))
    rows = []
    for weight in args.safe_weights:
        settings = VfaDecode(mode="combined", safe_weight=weight)
        row: dict[str, object] = {"safe_weight": weight}
        for name, (lg, pr) in {"plain": (logits, probability), "mirror_averaged": (averaged_logits,
                                                                                   averaged_probability)}.items():
            scored = score(data, decode(settings, lg, pr, unknown), resolution)
            row[name] = {k: scored[k] for k in ("perfect_match", "safe", "mean_distance_m")}
        rows.append(row)
        plain, both = row["plain"], row["mirror_averaged"]
        sys.stdout.write(
            f"lambda {weight:g}: plain {100 * plain['perfect_match']:.1f} / {100 * plain['safe']:.1f} % / "
            f"{plain['mean_distance_m']:.4f} m; mirror-averaged {100 * both['perfect_match']:.1f} / "
            f"{100 * both['safe']:.1f} % / {both['mean_distance_m']:.4f} m\n"
        )
    if args.json is not None:
        args.json.write_text(json.dumps({"data": str(args.data), "scored": int((data.label >= 0).sum()),
                                         "rows": rows}, indent=1) + "\n")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
