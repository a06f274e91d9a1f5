#!/usr/bin/env python3
"""Does ``CnnFootholdSelector`` select what a reference commit selected? (``select_legs`` / ``select`` / ``predict``.)

Run after ``source scripts/env.sh``:

    python bench/check_vfa_cnn_selections.py --save bench/out/vfa_cnn_selections_ref.npz   # at the reference
    python bench/check_vfa_cnn_selections.py --against bench/out/vfa_cnn_selections_ref.npz  # at the change

To record the reference of another commit without checking it out here, run this file with that commit's
``tal_perception`` first on the path (``git worktree add <worktree> <commit>``, then
``PYTHONPATH=<worktree>/tal_perception:$PYTHONPATH python bench/check_vfa_cnn_selections.py --save ...``).

What is compared, bit for bit (selected point [m], status, offset [cells], any_safe), with the default
backend and the weights' stored decode:

* ``test_*``: the protocol's test tuples (``--data``, 17,604 by default) through ``select_legs`` in calls of 4,
  2 and 1 legs, without verification: each call's map is its tuples' patches side by side (33 x 33k cells,
  yaw 0, so the aligned extraction returns each tuple's own patch), each request's nominal at its patch's
  centre; ``test_select``: the same one-leg calls through ``select`` (its own one-leg path); and ``predict``
  in batches of 256 (what ``eval_vfa`` does);
* ``test_verified``: the first ``--verified`` tuples in calls of 4 legs with the verification on (the exact
  check, and the exact search when the CNN's choice is unsafe); ``cases_verified*``: the first 50 bench
  cases (below) verified, 4 legs per ``select_legs`` call and one leg per ``select`` call;
* ``cases_*``: ``bench_vfa.make_cases`` (200 seeded terrains) for the 4 legs in one call, 2 legs and one leg
  per call (``cases_select``: one leg per ``select`` call), at the map's heading and rotated by 0.37 rad (the
  interpolating extraction), the nominal also moved 0.25 m off the map's centre (a patch partly off the map:
  unknown cells).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from bench_vfa import make_cases

try:
    import torch
    from tal_lab.vital.eval_vfa import predict_all
    from tal_lab.vital.vfa_dataset import VfaDataset

    from tal_core.heightmap import HeightMapGrid
    from tal_core.legs import LEGS
    from tal_core.robot_model import RobotModel
    from tal_perception.fec import FootholdEvaluator
    from tal_perception.vfa import VfaStatus
    from tal_perception.vfa_cnn import CnnFootholdSelector, FootholdRequest
except ImportError as _exc:  # environment problem, not a result
    raise SystemExit(f"check_vfa_cnn_selections: {_exc}; run it after `source scripts/env.sh`") from None

STATUSES = list(VfaStatus)
RESOLUTION_M = 0.02


def encode_results(results: list) -> np.ndarray:
    """(k, 7) float64 per result: selected x, y, z [m], status index, offset row, col [cells] (-99: none), any_safe."""
    rows = []
    for r in results:
        offset = r.offset_cells if r.offset_cells is not None else (-99, -99)
        rows.append([*np.asarray(r.selected, float), STATUSES.index(r.status), *offset, float(r.any_safe)])
    return np.array(rows, dtype=np.float64).reshape(-1, 7)


def test_set_calls(
    selector: CnnFootholdSelector, data: VfaDataset, legs_per_call: int, count: int, single: bool = False
) -> np.ndarray:
    """The first ``count`` test tuples through ``select_legs``, ``legs_per_call`` per call (see the docstring);
    ``single``: one leg per ``select`` call instead."""
    n = data.cells
    out = []
    for start in range(0, count, legs_per_call):
        index = range(start, min(start + legs_per_call, count))
        heights = np.concatenate([data.heights[i] for i in index], axis=1)
        grid = HeightMapGrid(center_xy=(0.0, 0.0), yaw=0.0, resolution_m=RESOLUTION_M, heights=heights)
        requests = []
        for k, i in enumerate(index):
            y = (k * n + n // 2 - 0.5 * (heights.shape[1] - 1)) * RESOLUTION_M
            requests.append(FootholdRequest(
                LEGS[int(data.leg[i])], np.array([0.0, y, 0.0]), float(data.hip_height_m[i]),
                np.asarray(data.twist[i], float), data.gait_timing(i),
            ))  # fmt: skip
        out.append(encode_results(_select(selector, requests, grid, 0.0, single)))
    return np.concatenate(out)


def _select(
    selector: CnnFootholdSelector, requests: list[FootholdRequest], grid: HeightMapGrid, yaw: float, single: bool
) -> list:
    """``select_legs(requests)``, or with ``single`` one ``select`` call per request."""
    if not single:
        return selector.select_legs(requests, grid, yaw=yaw)
    return [selector.select(r.leg, r.nominal_world, grid, hip_height_m=r.hip_height_m, twist=r.twist, gait=r.gait,
                            yaw=yaw) for r in requests]  # fmt: skip


def case_calls(
    selector: CnnFootholdSelector, cases: list[dict], legs_per_call: int, single: bool = False
) -> np.ndarray:
    """The bench cases at the map's heading, rotated, and with the nominal off the map's centre."""
    out = []
    for case in cases:
        for yaw_offset, shift in ((0.0, 0.0), (0.37, 0.0), (0.0, 0.25), (0.37, 0.25)):
            nominal = case["nominal"] + np.array([shift, -0.5 * shift, 0.0])
            requests = [FootholdRequest(leg, nominal, case["hip"], case["twist"], case["gait"]) for leg in LEGS]
            yaw = case["grid"].yaw + yaw_offset
            for start in range(0, len(LEGS), legs_per_call):
                batch = requests[start : start + legs_per_call]
                out.append(encode_results(_select(selector, batch, case["grid"], yaw, single)))
    return np.concatenate(out)


def collect(data_path: Path, verified: int) -> dict[str, np.ndarray]:
    torch.set_num_threads(1)
    model = RobotModel.from_name("hyq")
    selector = CnnFootholdSelector(FootholdEvaluator(model), verify=False)
    data = VfaDataset.load(data_path)
    arrays: dict[str, np.ndarray] = {}
    for legs in (4, 2, 1):
        print(f"test set, {legs} legs per call", file=sys.stderr, flush=True)
        arrays[f"test_{legs}"] = test_set_calls(selector, data, legs, len(data))
    print("test set, one leg per select call", file=sys.stderr, flush=True)
    arrays["test_select"] = test_set_calls(selector, data, 1, len(data), single=True)
    arrays["test_predict"] = predict_all(selector, data).astype(np.int64)
    cases = make_cases(model, 200, 20240601)
    for legs in (4, 2, 1):
        arrays[f"cases_{legs}"] = case_calls(selector, cases, legs)
    arrays["cases_select"] = case_calls(selector, cases, 1, single=True)
    selector.verify = True
    print(f"test set, verified, first {verified}", file=sys.stderr, flush=True)
    arrays["test_verified"] = test_set_calls(selector, data, 4, min(verified, len(data)))
    arrays["cases_verified"] = case_calls(selector, cases[:50], 4)
    arrays["cases_verified_select"] = case_calls(selector, cases[:50], 1, single=True)
    arrays["rejected"] = np.array([selector.counters.rejected])
    return arrays


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=Path("data/vfa/test_seed2_n4401.npz"))
    parser.add_argument("--verified", type=int, default=2000, help="test tuples checked with verification")
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--save", type=Path, help="write the selections here (the reference)")
    group.add_argument("--against", type=Path, help="compare with the selections stored here")
    args = parser.parse_args()
    arrays = collect(args.data, args.verified)
    if args.save:
        args.save.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(args.save, **arrays)
        print(f"wrote {args.save}: " + ", ".join(f"{k} {v.shape[0]}" for k, v in arrays.items()))
        return 0
    reference = np.load(args.against)
    differ = 0
    for key, value in arrays.items():
        ref = reference[key]
        same_shape = ref.shape == value.shape
        rows = int((ref != value).reshape(len(ref), -1).any(axis=1).sum()) if same_shape else len(value)
        differ += rows
        note = "" if same_shape else f" (shape {value.shape} vs {ref.shape})"
        print(f"{key}: {rows} of {len(value)} differ{note}")
    print(f"total: {differ} differ")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
