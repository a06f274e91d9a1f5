"""Error analysis of the VFA CNN on the accuracy protocol's test set: why g_hat misses g.

    python bench/analyse_vfa_cnn_errors.py [--weights ...] [--data data/vfa] [--seed 2] [--samples-per-leg 4401]
        [--json out.json]

For every scored test tuple (one with a safe candidate) the CNN's choice (stored decode, and the argmax)
is classified:

* match: g_hat = g;
* safe, not optimal: g_hat in the exact eroded safe set, but not g; split by the squared distance from the
  nominal compared with g's (equal = a tie that the row-major rule breaks the other way; larger = a safe
  cell farther out than needed; smaller is impossible, g being the closest safe cell) and by |g_hat - g|;
* unsafe: g_hat not in the eroded safe set; split into an unknown cell, a cell that fails a criterion
  itself (raw unsafe; which of TR / LC / KF / FC fail there, as ``FecResult`` reports them: a criterion
  evaluated on every known cell, so several may fail at once) and a cell that passes all four but is
  removed by the erosion (an uncertainty-margin neighbour fails; which criteria fail at those neighbours).
  Also how far g_hat is from the nearest exactly safe cell (1 cell = a boundary error).

The safe head's probability at g_hat tells a head error (p_safe high at an unsafe cell) from a decode
trade (p_safe low but the optimum logit won). Also: how many test patches have heights clipped by the
encoding (``EncodingConfig.height_clip_m``), the only part of the FEC's input the network does not see
(cells outside the patch never enter the FEC: ``fec_grid`` ignores them).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage
from tal_lab.vital.terrain_samples import TERRAIN_KINDS
from tal_lab.vital.tune_vfa_decode import network_outputs
from tal_lab.vital.vfa_dataset import VfaDataset, cache_path, load_or_generate

from tal_core.robot_model import RobotModel
from tal_perception.fec import FootholdEvaluator
from tal_perception.fec_grid import disc_offsets
from tal_perception.vfa_cnn import DEFAULT_WEIGHTS, CnnFootholdSelector, load_model
from tal_perception.vfa_decode import VfaDecode, decode

CRITERIA = ("terrain_roughness", "leg_collision", "kinematic_feasibility", "foot_trajectory_collision")
SHORT = {"terrain_roughness": "TR", "leg_collision": "LC", "kinematic_feasibility": "KF",
         "foot_trajectory_collision": "FC"}  # fmt: skip


def classify(
    evaluator: FootholdEvaluator, data: VfaDataset, choices: np.ndarray, p_safe: np.ndarray
) -> dict[str, object]:
    """Counts of the categories in the module docstring, overall and per terrain kind."""
    n = data.cells
    centre = n // 2
    offsets = disc_offsets(evaluator.settings.uncertainty_margin_m, evaluator.settings.resolution_m)
    rows = np.flatnonzero(data.label >= 0)
    counts: dict[str, Counter] = {"all": Counter(), **{k: Counter() for k in TERRAIN_KINDS}}
    p_at_unsafe, p_at_safe_miss = [], []
    for i in rows:
        kind = TERRAIN_KINDS[int(data.kind[i])]
        c, g = int(choices[i]), int(data.label[i])
        tags = ["scored"]
        if c == g:
            tags.append("match")
        elif data.safe[i].reshape(-1)[c]:
            d2c = (c // n - centre) ** 2 + (c % n - centre) ** 2
            d2g = (g // n - centre) ** 2 + (g % n - centre) ** 2
            tags.append("safe_not_optimal")
            tags.append("safe_tie" if d2c == d2g else "safe_farther")
            dist = np.hypot(c // n - g // n, c % n - g % n)
            tags.append(
                "safe_dist<=1" if dist <= 1.0 + 1e-9 else ("safe_dist<=2" if dist <= 2.0 + 1e-9 else "safe_dist>2")
            )
            p_at_safe_miss.append(p_safe[i, c])
        else:
            tags.append("unsafe")
            p_at_unsafe.append(p_safe[i, c])
            heights = data.heights[i]
            r, col = divmod(c, n)
            dist_to_safe = ndimage.distance_transform_edt(~data.safe[i])[r, col]
            if dist_to_safe <= 1.0 + 1e-9:
                tags.append("unsafe_boundary(1 cell)")
            else:
                tags.append("unsafe_near(<=2 cells)" if dist_to_safe <= 2.0 + 1e-9 else "unsafe_far(>2 cells)")
            if np.isnan(heights[r, col]):
                tags.append("unsafe_unknown_cell")
            else:
                fec = evaluator.evaluate(data.fec_input(i))
                if not fec.raw[r, col]:
                    tags.append("unsafe_raw")
                    failed = [SHORT[k] for k in CRITERIA if not getattr(fec, k)[r, col]]
                    tags += [f"raw_fails_{f}" for f in failed]
                    tags.append("raw_only_" + "+".join(failed))
                else:
                    tags.append("unsafe_eroded")
                    failed = set()
                    unknown_nb = False
                    for di, dj in offsets:
                        rr, cc = r + di, col + dj
                        if 0 <= rr < n and 0 <= cc < n and not fec.raw[rr, cc]:
                            if np.isnan(heights[rr, cc]):
                                unknown_nb = True
                            failed |= {SHORT[k] for k in CRITERIA if not getattr(fec, k)[rr, cc]}
                    if unknown_nb:
                        tags.append("eroded_by_unknown_neighbour")
                    tags += [f"eroded_nb_fails_{f}" for f in sorted(failed)]
        for t in tags:
            counts["all"][t] += 1
            counts[kind][t] += 1
    return {
        "counts": {k: dict(v) for k, v in counts.items()},
        "p_safe_at_unsafe_choice": np.percentile(p_at_unsafe, [10, 25, 50, 75, 90]).tolist() if p_at_unsafe else None,
        "p_safe_at_unsafe_choice_ge_0.5": float(np.mean(np.array(p_at_unsafe) >= 0.5)) if p_at_unsafe else None,
        "p_safe_at_safe_miss": np.percentile(p_at_safe_miss, [10, 50, 90]).tolist() if p_at_safe_miss else None,
    }


def clipping(data: VfaDataset, selector: CnnFootholdSelector) -> dict[str, float]:
    """How many patches have a known height beyond the encoding's clip (information the network loses)."""
    enc = selector.net.config.encoding
    rel = data.heights - (data.hip_height_m - enc.nominal_hip_height_m)[:, None, None]
    clipped = np.nan_to_num(np.abs(rel), nan=0.0) > enc.height_clip_m
    return {"patches_with_clipped_cells": float(clipped.any(axis=(1, 2)).mean()),
            "clipped_cell_fraction": float(clipped.mean())}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--weights", type=Path, default=DEFAULT_WEIGHTS)
    parser.add_argument("--data", type=Path, default=Path("data/vfa"))
    parser.add_argument("--seed", type=int, default=2)
    parser.add_argument("--samples-per-leg", type=int, default=4401)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    started = time.perf_counter()
    evaluator = FootholdEvaluator(RobotModel.from_name("hyq"))
    data = load_or_generate(evaluator, cache_path(args.data, "test", args.seed, args.samples_per_leg), args.seed,
                            args.samples_per_leg)  # fmt: skip
    net = load_model(args.weights)
    selector = CnnFootholdSelector(evaluator, net, verify=False, backend="torch")
    logits, p_safe, unknown = network_outputs(net, data)
    known = ~unknown

    report: dict[str, object] = {"weights": str(args.weights), "clipping": clipping(data, selector)}
    for name, settings in (("stored", selector.decode), ("argmax", VfaDecode("argmax"))):
        choices = decode(settings, logits, p_safe, ~known)
        report[name] = {"decode": settings.to_dict(), **classify(evaluator, data, choices, p_safe)}
        c = report[name]["counts"]["all"]
        print(f"== {name} decode {settings.to_dict()}")
        for key in sorted(c, key=lambda k: -c[k]):
            print(f"  {key:32s} {c[key]:6d}  {100 * c[key] / c['scored']:5.1f} %")
        for kind in TERRAIN_KINDS:
            ck = report[name]["counts"][kind]
            s = ck.get("scored", 1)
            print(f"  [{kind:6s}] scored {s:5d} match {100 * ck.get('match', 0) / s:5.1f} safe-not-opt "
                  f"{100 * ck.get('safe_not_optimal', 0) / s:5.1f} (tie {100 * ck.get('safe_tie', 0) / s:4.1f}) "
                  f"unsafe {100 * ck.get('unsafe', 0) / s:5.1f}: raw {100 * ck.get('unsafe_raw', 0) / s:4.1f} "
                  f"eroded {100 * ck.get('unsafe_eroded', 0) / s:4.1f} "
                  f"unknown {100 * ck.get('unsafe_unknown_cell', 0) / s:4.1f}"
                  f" boundary {100 * ck.get('unsafe_boundary(1 cell)', 0) / s:4.1f}")  # fmt: skip
        print("  p_safe at unsafe choices (10/25/50/75/90 %):", report[name]["p_safe_at_unsafe_choice"],
              ">= 0.5:", report[name]["p_safe_at_unsafe_choice_ge_0.5"])  # fmt: skip
    print("clipping:", report["clipping"])
    report["elapsed_s"] = time.perf_counter() - started
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
