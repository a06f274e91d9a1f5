"""The VPA's cost and horizon options compared open loop, on the same path and the same maps.

    python -m tal_lab.vital.vpa_open_loop --out results/vital

The closed-loop comparisons (``vital_experiments``: ``horizon`` and ``cost``) mix the optimiser's choice with
how the trot then walks: a run that falls early is compared with one that climbed, over different maps. Here
the robot's base moves along the stairs (course ``vital_stairs``, heading +x, y = 0) at the commanded speed
and ideally follows the VPA: each update (every ``period_s``, the VPA node's 20 Hz) starts from the previous
pose reference, sees a perfect 121 x 121 heightmap centred on the base and the trot timing. Every variant
gets the same base x sequence, so only the optimiser's settings differ:

* horizon: N_h = 1 vs N_h = 2 (C_int): the pose variation per metre, sum |dz| / sum |dx| [m/m] and
  sum |dpitch| / sum |dx| [deg/m] (thesis: the receding horizon varies less), and where along the path the
  height reference first rises 2 cm above its start (the receding horizon should anticipate the stairs);
* cost: C_sum vs C_int (N_h = 2): the envelope thickness |F(u* + m) - F(u* - m)| per leg (m = 0.025 m, the
  thesis' "error", smaller is more robust) and the safe footholds at u* and at the worse of u* +- m;
* the receding C_int with ``VpaSettings.switch_margin`` 0.05 (an optimum away from the previous pose must be
  5 % better to be taken): how much of the pose variation comes from jumps between near-equal optima.

Writes vpa_open_loop.md, vpa_open_loop.json and vpa_open_loop.png into --out; progress on stderr.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from tal_core.heightmap import extract_heightmap
from tal_core.robot_model import RobotModel
from tal_core.terrain import Course, load_course
from tal_lab.vital.vpa_dataset import TROT_GAIT
from tal_perception.errors import VpaConfigError
from tal_perception.vpa import PoseAdapter, VpaResult, VpaStatus
from tal_perception.vpa_settings import CostKind, VpaSettings

LOG = logging.getLogger("tal_lab.vital.vpa_open_loop")
FloatArray = NDArray[np.float64]
MAP_CELLS = 121  # [-] edge of the robot-centric heightmap (as the ViTAL closed loop)
MAP_RESOLUTION_M = 0.02  # [m]
RISE_THRESHOLD_M = 0.02  # [m] the height reference has "started to climb" this far above its start


@dataclass(frozen=True)
class PathSettings:
    """The base path: from ``start_x_m`` to ``end_x_m`` [m] at ``speed_mps`` [m/s], one VPA update every
    ``period_s`` [s]; ``course`` by name."""

    course: str = "vital_stairs"
    start_x_m: float = 0.0
    end_x_m: float = 4.8
    speed_mps: float = 0.4
    period_s: float = 0.05

    def __post_init__(self) -> None:
        for name in ("speed_mps", "period_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise VpaConfigError(f"PathSettings.{name} must be a finite value > 0, got {value!r}")
        if not (math.isfinite(self.start_x_m) and math.isfinite(self.end_x_m) and self.end_x_m > self.start_x_m):
            raise VpaConfigError(
                f"PathSettings: end_x_m ({self.end_x_m!r}) must be finite and after start_x_m ({self.start_x_m!r})"
            )

    @property
    def xs(self) -> FloatArray:
        """(K,) [m] base x of the updates."""
        step = self.speed_mps * self.period_s
        return self.start_x_m + step * np.arange(int(math.floor((self.end_x_m - self.start_x_m) / step)) + 1)


@dataclass
class PathTrace:
    """One variant along the path: per update the pose reference (height [m] world, roll, pitch [rad]),
    per leg the safe footholds at u*, at u* - m and u* + m (RBF curves, NaN where the update held a pose
    without curves)."""

    name: str
    x: FloatArray
    pose: FloatArray  # (K, 3)
    nsf_at_optimum: FloatArray  # (K, 4)
    nsf_minus: FloatArray  # (K, 4)
    nsf_plus: FloatArray  # (K, 4)
    statuses: list[str] = field(default_factory=list)

    @property
    def thickness(self) -> FloatArray:
        """(K, 4) |F(u* + m) - F(u* - m)| [footholds]."""
        return np.abs(self.nsf_plus - self.nsf_minus)

    def summary(self) -> dict[str, float]:
        dz, dpitch = variation_per_metre(self.x, self.pose[:, 0], np.degrees(self.pose[:, 2]))
        worse = np.minimum(self.nsf_minus, self.nsf_plus)
        return {
            "height_variation_m_per_m": dz,
            "pitch_variation_deg_per_m": dpitch,
            "rise_x_m": rise_x(self.x, self.pose[:, 0]),
            "thickness_mean": _nanmean(self.thickness),
            "nsf_at_optimum_mean": _nanmean(self.nsf_at_optimum),
            "nsf_worse_of_margins_mean": _nanmean(worse),
            "updates": float(len(self.x)),
            "updates_without_curves": float(sum(s != VpaStatus.OK.value for s in self.statuses)),
        }


def variation_per_metre(x: FloatArray, z: FloatArray, pitch_deg: FloatArray) -> tuple[float, float]:
    """sum |dz| / sum |dx| [m/m] and sum |dpitch| / sum |dx| [deg/m] (the thesis' numerical differences)."""
    distance = float(np.sum(np.abs(np.diff(x))))
    if distance <= 0.0:
        return math.nan, math.nan
    return float(np.sum(np.abs(np.diff(z)))) / distance, float(np.sum(np.abs(np.diff(pitch_deg)))) / distance


def rise_x(x: FloatArray, z: FloatArray) -> float:
    """[m] the first base x where the height reference is ``RISE_THRESHOLD_M`` above its first value (NaN: never)."""
    above = np.flatnonzero(z - z[0] > RISE_THRESHOLD_M)
    return float(x[above[0]]) if above.size else math.nan


def _nanmean(values: FloatArray) -> float:
    finite = values[np.isfinite(values)]
    return float(finite.mean()) if finite.size else math.nan


def run_path(name: str, adapter: PoseAdapter, course: Course, path: PathSettings, progress: bool = True) -> PathTrace:
    """Walk ``path`` with ``adapter`` (a fresh one per variant: it keeps its previous pose)."""
    xs = path.xs
    twist = np.array([path.speed_mps, 0.0, 0.0, 0.0, 0.0, 0.0])
    margin = adapter.settings.cost_margin_m
    pose = np.full((len(xs), 3), np.nan)
    nsf = np.full((3, len(xs), 4), np.nan)  # at u*, u* - m, u* + m
    statuses: list[str] = []
    base_z = float(course.height(np.array([xs[0]]), np.array([0.0]))[0]) + adapter.default_relative[0]
    for k, x in enumerate(tqdm(xs, desc=name, unit="update", disable=not progress, file=sys.stderr)):
        grid = extract_heightmap(
            course, (float(x), 0.0), 0.0, rows=MAP_CELLS, cols=MAP_CELLS, resolution_m=MAP_RESOLUTION_M
        )
        result = adapter.update(grid, np.array([x, 0.0, base_z]), 0.0, twist, TROT_GAIT)
        statuses.append(result.status.value)
        pose[k] = (result.base_height_m, result.roll_rad, result.pitch_rad)
        base_z = result.base_height_m  # the base follows the reference (ideal tracking)
        curves = _curves_around_optimum(adapter, result, margin)
        if curves is not None:
            nsf[:, k] = curves
    return PathTrace(name, xs, pose, nsf[0], nsf[1], nsf[2], statuses)


def _curves_around_optimum(adapter: PoseAdapter, result: VpaResult, margin: float) -> FloatArray | None:
    """(3, 4) the current stage's RBF curves per leg at the optimum's hip heights, - m and + m [footholds]."""
    diagnostics = result.diagnostics
    if result.status is not VpaStatus.OK or diagnostics is None or diagnostics.weights is None:
        return None
    references = np.nan_to_num(diagnostics.map_references[0], nan=diagnostics.body_reference_m)
    z = np.asarray(result.hip_heights_m, dtype=float) - references
    weights = diagnostics.weights[0]
    return np.array([adapter.basis.evaluate(weights, z + dz) for dz in (0.0, -margin, margin)]) * adapter.cells


VARIANTS: dict[str, dict[str, object]] = {
    "receding_c_int": {"horizon": 2, "cost": CostKind.INT},
    "single_c_int": {"horizon": 1, "cost": CostKind.INT},
    "receding_c_sum": {"horizon": 2, "cost": CostKind.SUM},
    "receding_c_int_switch_5pct": {"horizon": 2, "cost": CostKind.INT, "switch_margin": 0.05},
}


def run(
    path: PathSettings,
    model: RobotModel | None = None,
    variants: tuple[str, ...] = tuple(VARIANTS),
    progress: bool = True,
) -> dict[str, PathTrace]:
    """Every variant along the same path (exact pose evaluation)."""
    unknown = sorted(set(variants) - set(VARIANTS))
    if unknown:
        raise VpaConfigError(f"unknown variant(s) {unknown}; known: {list(VARIANTS)}")
    model = model if model is not None else RobotModel.from_name("hyq")
    course = load_course(path.course)
    traces = {}
    for name in variants:
        settings = replace(VpaSettings(), **VARIANTS[name])
        traces[name] = run_path(name, PoseAdapter(model, settings), course, path, progress)
    return traces


def markdown(path: PathSettings, traces: dict[str, PathTrace]) -> str:
    s = {name: trace.summary() for name, trace in traces.items()}
    lines = [
        "# The VPA's horizon and cost compared open loop",
        "",
        f"`python -m tal_lab.vital.vpa_open_loop --out results/vital`: the base moves along `{path.course}` from "
        f"x = {path.start_x_m:g} to {path.end_x_m:g} m at {path.speed_mps:g} m/s and follows the pose reference "
        f"exactly; one exact VPA update every {path.period_s:g} s ({len(path.xs)} updates, the same x for every "
        "variant), perfect 121 x 121 map, trot timing. Closed loop, see closed_loop.md.",
        "",
        "| variant | height variation [m/m] | pitch variation [deg/m] | height starts to rise at x [m] | "
        "envelope thickness [footholds] | NSF at u* | NSF, worse of u* +- m |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, v in s.items():
        lines.append(
            f"| {name} | {v['height_variation_m_per_m']:.3f} | {v['pitch_variation_deg_per_m']:.1f} | "
            f"{v['rise_x_m']:.2f} | {v['thickness_mean']:.1f} | {v['nsf_at_optimum_mean']:.1f} | "
            f"{v['nsf_worse_of_margins_mean']:.1f} |"
        )
    lines += [
        "",
        "Envelope thickness |F(u* + m) - F(u* - m)| and the NSF are per leg, averaged over legs and updates "
        "(m = 0.025 m). The first stair riser is at x = 1.0 m; the base is 0.37 m behind the front hips.",
        "",
        "Thesis: the receding horizon varies the pose less than the single one; C_int's envelope is "
        "thinner than C_sum's.",
        "",
        "![open loop](vpa_open_loop.png)",
        "",
    ]
    return "\n".join(lines)


def plot(traces: dict[str, PathTrace], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    for name, trace in traces.items():
        axes[0].plot(trace.x, trace.pose[:, 0], label=name)
        axes[1].plot(trace.x, np.degrees(trace.pose[:, 2]), label=name)
        axes[2].plot(trace.x, np.nanmean(trace.thickness, axis=1), lw=0.8, label=name)
    for ax, label in zip(
        axes, ("base height reference [m]", "pitch reference [deg]", "|F(u*+m) - F(u*-m)| mean over legs")
    ):
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    axes[-1].set_xlabel("base x [m]")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("results/vital"))
    parser.add_argument("--speed", type=float, default=PathSettings.speed_mps, help="[m/s] base speed")
    parser.add_argument("--course", default=PathSettings.course)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        path = PathSettings(course=args.course, speed_mps=args.speed)
    except VpaConfigError as error:
        parser.error(str(error))
    args.out.mkdir(parents=True, exist_ok=True)
    traces = run(path)
    report = markdown(path, traces)
    (args.out / "vpa_open_loop.md").write_text(report)
    payload = {"path": vars(path), "variants": {name: t.summary() for name, t in traces.items()}}
    (args.out / "vpa_open_loop.json").write_text(json.dumps(payload, indent=1) + "\n")
    plot(traces, args.out / "vpa_open_loop.png")
    print(report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
