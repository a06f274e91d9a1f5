"""Accuracy protocol of the VPA CNN and agreement of the pose optimiser's solvers.

    python -m tal_lab.vital.eval_vpa --out results/vital

1. Curve accuracy (thesis, "estimation accuracy"): on a fresh labelled test set (seed 2, never trained
   on), F_bar = the exact NSF at the 31 hip heights and F_hat = the NSF rebuilt from the CNN's RBF
   weights at the same heights; the thesis' measure is mean(F_hat) / mean(F_bar) (96.5 % there). A
   ratio of means hides errors of opposite sign, so 1 - mean|F_hat - F_bar| / mean(F_bar) is reported too.
2. Optimum accuracy: on whole-robot scenes (``vpa_scenes``), the VPA runs once with the exact evaluation
   and once with the CNN; both poses are scored with the *exact* NSF curves (RBF of the exact samples) of
   the current stage: sum over legs of F_exact(pose_CNN) / F_exact(pose_exact).
3. Solver agreement: on the exact problems of those scenes, for each cost (C_sum, C_prod, C_int),
   trust-constr (reference) and L-BFGS-B start from the same guess; they agree when the poses differ by
   <= 1e-3 (m, rad) or the objectives by <= 1e-6 relative.
Writes vpa_accuracy.md, vpa_accuracy.json and vpa_curves.png into --out.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from tal_core.legs import LEGS
from tal_core.robot_model import RobotModel
from tal_lab.vital.vpa_dataset import TROT_GAIT, VpaDataset, build_evaluator, generate
from tal_lab.vital.vpa_scenes import vpa_scenes
from tal_perception.fec_settings import GaitTiming
from tal_perception.vpa import PoseAdapter
from tal_perception.vpa_cnn import DEFAULT_WEIGHTS, CnnNsfModel
from tal_perception.vpa_optimizer import PoseOptimizer, PoseProblem, Solver
from tal_perception.vpa_settings import CostKind, VpaSettings

LOG = logging.getLogger("tal_lab.vital.eval_vpa")
AGREE_POSE = 1e-3  # [m, rad]
AGREE_OBJECTIVE = 1e-6  # [-] relative


def curve_accuracy(model: CnnNsfModel, test: VpaDataset, adapter: PoseAdapter) -> dict[str, object]:
    """Thesis ratio mean(F_hat) / mean(F_bar) overall and per terrain kind, plus the absolute error."""
    weights, _ = model.predict([LEGS[i] for i in test.legs], test.heights.astype(float), test.twists)
    f_hat = adapter.basis.values(adapter.settings.hip_heights) @ weights.T * adapter.cells  # (N, n)
    f_hat = f_hat.T
    f_bar = test.nsf.astype(float)
    f_fit = adapter.basis.fit(f_bar) @ adapter.basis.design.T  # exact samples through the RBF
    result: dict[str, object] = {
        "samples": len(test),
        "mean_f_bar": float(f_bar.mean()),
        "mean_f_hat": float(f_hat.mean()),
        "ratio": float(f_hat.mean() / f_bar.mean()),
        "one_minus_nmae": float(1.0 - np.abs(f_hat - f_bar).mean() / f_bar.mean()),
        "mae_footholds": float(np.abs(f_hat - f_bar).mean()),
        "rbf_fit_mae_footholds": float(np.abs(f_fit - f_bar).mean()),
        "per_kind": {},
    }
    for kind in sorted(set(test.kinds.tolist())):
        mask = test.kinds == kind
        result["per_kind"][kind] = {
            "samples": int(mask.sum()),
            "ratio": float(f_hat[mask].mean() / max(f_bar[mask].mean(), 1e-9)),
            "mae_footholds": float(np.abs(f_hat[mask] - f_bar[mask]).mean()),
        }
    result["_curves"] = (f_bar, f_hat)
    return result


def scene_study(robot: RobotModel, model: CnnNsfModel, settings: VpaSettings, seed: int, count: int,
                gait: GaitTiming) -> dict[str, object]:  # fmt: skip
    """Optimum accuracy (CNN vs exact pose, scored exactly) and solver agreement on ``count`` scenes."""
    exact = PoseAdapter(robot, settings)
    cnn = PoseAdapter(robot, settings, evaluator=exact.evaluator, nsf_model=model)
    rows, agreement = [], {kind.value: [] for kind in CostKind}
    for scene in tqdm(list(vpa_scenes(seed, count, robot.nominal_base_height_m)), desc="VPA scenes"):
        exact.reset()
        cnn.reset()
        args = (scene.grid, scene.base_position, 0.0, scene.twist, gait)
        r_exact, r_cnn = exact.update(*args), cnn.update(*args)
        d = r_exact.diagnostics
        if d.weights is None:
            continue
        reference = d.body_reference_m
        offsets = reference - np.nan_to_num(d.map_references[0], nan=reference)

        def exact_score(pose: np.ndarray, weights=d.weights[0], offsets=offsets, reference=reference) -> float:
            z = exact.hips.heights(pose - np.array([reference, 0.0, 0.0])) + offsets
            return float(np.clip(exact.basis.evaluate(weights, z), 0.0, None).sum() * exact.cells)

        previous = exact.default_relative
        problem = PoseProblem(d.weights, reference - np.nan_to_num(d.map_references, nan=reference), previous)
        # The objective the VPA maximises (both stages, C_int, smoothness) with the exact curves, at the
        # stage poses found with the exact curves and with the CNN's (same references: same maps).
        objective_exact = exact.optimizer.objective(problem, d.stage_poses.reshape(-1))[0]
        objective_cnn = exact.optimizer.objective(problem, r_cnn.diagnostics.stage_poses.reshape(-1))[0]
        rows.append({"kind": scene.kind, "nsf_exact_pose": exact_score(r_exact.pose),
                     "nsf_cnn_pose": exact_score(r_cnn.pose), "objective_exact_pose": objective_exact,
                     "objective_cnn_pose": objective_cnn, "pose_exact": r_exact.pose.tolist(),
                     "pose_cnn": r_cnn.pose.tolist()})  # fmt: skip
        for kind in CostKind:
            optimizer = PoseOptimizer(dataclasses.replace(settings, cost=kind), exact.basis, exact.hips)
            x0 = optimizer.initial_guess(problem)
            timings, solutions = {}, {}
            for solver in (Solver.TRUST_CONSTR, Solver.LBFGSB):
                started = time.perf_counter()
                solutions[solver] = optimizer.solve(problem, solver, x0=x0)
                timings[solver] = time.perf_counter() - started
            a, b = solutions[Solver.TRUST_CONSTR], solutions[Solver.LBFGSB]
            pose_diff = float(np.abs(a.poses - b.poses).max())
            obj_diff = abs(a.objective - b.objective) / max(abs(a.objective), 1e-12)
            agreement[kind.value].append({
                "pose_diff": pose_diff, "objective_rel_diff": obj_diff,
                "agree": pose_diff <= AGREE_POSE or obj_diff <= AGREE_OBJECTIVE,
                "lbfgsb_better_or_equal": b.objective >= a.objective - 1e-9 * max(abs(a.objective), 1.0),
                "lbfgsb_relative_gain": (b.objective - a.objective) / max(abs(a.objective), 1e-12),
                "trust_constr_ms": timings[Solver.TRUST_CONSTR] * 1e3, "lbfgsb_ms": timings[Solver.LBFGSB] * 1e3,
            })  # fmt: skip
    exact_total = sum(r["nsf_exact_pose"] for r in rows)
    cnn_total = sum(r["nsf_cnn_pose"] for r in rows)
    summary = {
        "scenes": len(rows),
        "optimum_ratio": cnn_total / max(exact_total, 1e-9),
        "objective_ratio": sum(r["objective_cnn_pose"] for r in rows) / sum(r["objective_exact_pose"] for r in rows),
        "objective_ratio_min": float(min(r["objective_cnn_pose"] / r["objective_exact_pose"] for r in rows)),
        "per_scene_ratio_median": float(np.median([r["nsf_cnn_pose"] / max(r["nsf_exact_pose"], 1e-9) for r in rows])),
        "rows": rows,
        "solver_agreement": {
            kind: {
                "cases": len(cases), "agree": int(sum(c["agree"] for c in cases)),
                "lbfgsb_better_or_equal": int(sum(c["lbfgsb_better_or_equal"] for c in cases)),
                "max_pose_diff": float(max(c["pose_diff"] for c in cases)) if cases else 0.0,
                "worst_lbfgsb_relative_gain": float(min(c["lbfgsb_relative_gain"] for c in cases)) if cases else 0.0,
                "trust_constr_median_ms": float(np.median([c["trust_constr_ms"] for c in cases])) if cases else 0.0,
                "lbfgsb_median_ms": float(np.median([c["lbfgsb_ms"] for c in cases])) if cases else 0.0,
            }
            for kind, cases in agreement.items()
        },
    }
    return summary


def plot_curves(path: Path, test: VpaDataset, f_bar: np.ndarray, f_hat: np.ndarray, heights: np.ndarray) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kinds = list(dict.fromkeys(test.kinds.tolist()))
    fig, axes = plt.subplots(2, 3, figsize=(12, 6.5), sharex=True)
    picks = [int(np.flatnonzero((test.kinds == k) & (test.nsf.max(axis=1) > 50))[0]) for k in kinds]
    unknown = np.flatnonzero(np.isnan(test.heights).any(axis=(1, 2)) & (test.nsf.max(axis=1) > 50))
    if unknown.size:
        picks.append(int(unknown[0]))
    for ax, index in zip(axes.ravel(), picks):
        ax.plot(heights, f_bar[index], "o-", ms=3, label="exact NSF (F_bar)")
        ax.plot(heights, f_hat[index], "-", lw=2, label="CNN RBF (F_hat)")
        title = test.kinds[index] + (" + unknown strip" if np.isnan(test.heights[index]).any() else "")
        ax.set_title(f"{title}, leg {LEGS[test.legs[index]].name}, vx {test.twists[index, 0]:.2f} m/s")
        ax.set_xlabel("hip height above the map reference [m]")
        ax.set_ylabel("safe footholds")
        ax.grid(alpha=0.3)
    axes.ravel()[0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_markdown(path: Path, curves: dict, scenes: dict, weights: Path, test_path: Path) -> None:
    lines = [
        "# VPA CNN accuracy and pose-optimiser solver agreement",
        "",
        f"Command: `python -m tal_lab.vital.eval_vpa --out {path.parent}` (weights `{weights.name}`, test set "
        f"`{test_path}`, seed 2, {curves['samples']} leg maps never trained on).",
        "",
        "## Curve accuracy (thesis measure)",
        "",
        "| measure | value |",
        "| --- | --- |",
        f"| mean(F_bar) exact NSF [footholds] | {curves['mean_f_bar']:.1f} |",
        f"| mean(F_hat) CNN NSF [footholds] | {curves['mean_f_hat']:.1f} |",
        f"| **mean(F_hat) / mean(F_bar)** (thesis 96.5 %) | **{100 * curves['ratio']:.1f} %** |",
        f"| 1 - mean abs error / mean(F_bar) | {100 * curves['one_minus_nmae']:.1f} % |",
        f"| mean abs error [footholds] (of 1089 cells) | {curves['mae_footholds']:.1f} |",
        f"| RBF fit of the exact samples, mean abs error [footholds] | {curves['rbf_fit_mae_footholds']:.1f} |",
        "",
        "| terrain | maps | mean(F_hat)/mean(F_bar) | mean abs error [footholds] |",
        "| --- | --- | --- | --- |",
    ]
    for kind, row in curves["per_kind"].items():
        lines.append(f"| {kind} | {row['samples']} | {100 * row['ratio']:.1f} % | {row['mae_footholds']:.1f} |")
    lines += [
        "",
        "## Optimum accuracy (whole robot, 4 legs, N_h = 2)",
        "",
        f"{scenes['scenes']} scenes (`vpa_scenes`, seed 3). Both poses scored with the exact NSF curves of the "
        "current stage (sum over the legs):",
        "",
        f"- the VPA's objective (2 stages, C_int, smoothness; exact curves) at the CNN's stage poses / at the "
        f"exact stage poses: **{100 * scenes['objective_ratio']:.1f} %** (worst scene "
        f"{100 * scenes['objective_ratio_min']:.1f} %)",
        f"- sum of the current stage's exact NSF at the CNN pose / at the exact pose: "
        f"{100 * scenes['optimum_ratio']:.1f} % (median per scene {100 * scenes['per_scene_ratio_median']:.1f} %). "
        "This can exceed 100 %: the exact pose maximises the objective above (future stage, margin, "
        "smoothness), not the current stage's NSF alone.",
        "",
        "## Solver agreement (trust-constr reference vs L-BFGS-B, same start)",
        "",
        "| cost | cases | agree (pose <= 1e-3 or objective <= 1e-6 rel.) | L-BFGS-B objective >= trust-constr "
        "| worst L-BFGS-B objective vs trust-constr | max pose diff | trust-constr median [ms] "
        "| L-BFGS-B median [ms] |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for kind, row in scenes["solver_agreement"].items():
        lines.append(
            f"| C_{kind} | {row['cases']} | {row['agree']} | {row['lbfgsb_better_or_equal']} | "
            f"{100 * row['worst_lbfgsb_relative_gain']:+.2f} % | {row['max_pose_diff']:.2e} | "
            f"{row['trust_constr_median_ms']:.1f} | {row['lbfgsb_median_ms']:.1f} |"
        )
    lines += [
        "",
        "Where the two disagree they stopped in different local optima of a multimodal objective (same start);",
        "the column 'worst' is the largest relative objective deficit of L-BFGS-B against trust-constr.",
        "",
        "![exact vs CNN NSF curves](vpa_curves.png)",
        "",
    ]
    path.write_text("\n".join(lines), encoding="utf-8")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("results/vital"))
    parser.add_argument("--weights", type=Path, default=DEFAULT_WEIGHTS)
    parser.add_argument("--test", type=Path, default=Path("data/vpa/test.npz"), help="generated if missing")
    parser.add_argument("--test-count", type=int, default=1500)
    parser.add_argument("--scenes", type=int, default=30)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.set_num_threads(1)
    settings = VpaSettings()
    if not args.test.is_file():
        generate(2, args.test_count, build_evaluator(settings)).save(args.test)
    test = VpaDataset.load(args.test)
    robot = RobotModel.from_name("hyq")
    model = CnnNsfModel.load(args.weights)
    adapter = PoseAdapter(robot, settings, nsf_model=model)
    curves = curve_accuracy(model, test, adapter)
    f_bar, f_hat = curves.pop("_curves")
    # Wider change bounds than the running VPA so the scored optimum reflects the NSF landscape.
    scene_settings = dataclasses.replace(settings, max_change=(0.3, 0.35, 0.35))
    scenes = scene_study(robot, model, scene_settings, 3, args.scenes, TROT_GAIT)
    args.out.mkdir(parents=True, exist_ok=True)
    plot_curves(args.out / "vpa_curves.png", test, f_bar, f_hat, settings.hip_heights)
    (args.out / "vpa_accuracy.json").write_text(json.dumps({"curves": curves, "scenes": scenes}, indent=1))
    write_markdown(args.out / "vpa_accuracy.md", curves, scenes, args.weights, args.test)
    LOG.info("mean(F_hat)/mean(F_bar) = %.3f, optimum ratio = %.3f -> %s", curves["ratio"],
             scenes["optimum_ratio"], args.out)  # fmt: skip


if __name__ == "__main__":
    main()
