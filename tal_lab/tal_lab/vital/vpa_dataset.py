"""Seeded VPA dataset: random leg maps and twists labelled by the exact pose evaluation (NSF over heights).

Maps come from ``terrain_samples`` (flat, bars, gaps, stairs, rocks as tal_core courses at a random
heading); a fraction gets an unknown (NaN) region, as an occluded or unmapped part of the robot's map
would (a strip from one border), so the CNN learns that unknown cells are unsafe. Twists: vx, vy [m/s]
and yaw rate [rad/s] in the horizontal frame, uniform in the ranges below; the gait is the VPA's
(trot by default). Labels: ``PoseEvaluator.evaluate`` (exact FEC at every sampled hip height).

    python -m tal_lab.vital.vpa_dataset --seed 1 --count 2000 --out data/vpa_train.npz
"""

from __future__ import annotations

import argparse
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from tal_core.legs import LEGS
from tal_core.robot_model import RobotModel
from tal_lab.vital.terrain_samples import terrain_samples
from tal_perception.fec import FootholdEvaluator
from tal_perception.fec_settings import GaitTiming
from tal_perception.vpa_evaluation import PoseEvaluator
from tal_perception.vpa_settings import VpaSettings

LOG = logging.getLogger("tal_lab.vital.vpa_dataset")
TROT_GAIT = GaitTiming(step_frequency_hz=1.5, duty_factor=0.6, swing_time_left_s=0.0, step_height_m=0.10)
TWIST_LOW = np.array([-0.1, -0.15, -0.4])  # [m/s, m/s, rad/s] vx, vy, yaw rate
TWIST_HIGH = np.array([0.5, 0.15, 0.4])
UNKNOWN_FRACTION = 0.15  # [-] share of maps with an unknown strip


@dataclass(frozen=True, eq=False)
class VpaDataset:
    """heights (n, 33, 33) float32 [m] world z (NaN unknown); twists (n, 6) [m/s, rad/s]; legs (n,);
    nsf (n, N) int16 exact NSF at the sampled hip heights; kinds (n,) terrain kind names."""

    heights: NDArray[np.float32]
    twists: NDArray[np.float64]
    legs: NDArray[np.int64]
    nsf: NDArray[np.int16]
    kinds: NDArray[np.str_]
    hip_heights: NDArray[np.float64]

    def save(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, heights=self.heights, twists=self.twists, legs=self.legs, nsf=self.nsf,
                            kinds=self.kinds, hip_heights=self.hip_heights)  # fmt: skip

    @classmethod
    def load(cls, path: Path) -> VpaDataset:
        with np.load(path) as data:
            return cls(*(data[k] for k in ("heights", "twists", "legs", "nsf", "kinds", "hip_heights")))

    def __len__(self) -> int:
        return int(self.legs.size)


def random_twist(rng: np.random.Generator) -> NDArray[np.float64]:
    """(6,) twist [m/s, rad/s]: vx, vy, yaw rate uniform in the dataset ranges, the rest zero."""
    vx, vy, wz = rng.uniform(TWIST_LOW, TWIST_HIGH)
    return np.array([vx, vy, 0.0, 0.0, 0.0, wz])


def add_unknown_strip(heights: NDArray, rng: np.random.Generator) -> NDArray:
    """Copy of ``heights`` with a random-width strip along one border set unknown (NaN)."""
    out = heights.copy()
    width = int(rng.integers(3, heights.shape[0] // 2))
    side = int(rng.integers(4))
    rotated = np.rot90(out, side)  # a view: writing into it writes into ``out``
    rotated[:width, :] = np.nan
    return out


def generate(seed: int, count: int, evaluator: PoseEvaluator, gait: GaitTiming = TROT_GAIT,
             progress: bool = True) -> VpaDataset:  # fmt: skip
    """``count`` labelled samples reproducible from ``seed`` (legs cycle LF, RF, LH, RH)."""
    rng = np.random.default_rng(seed + 7919)  # twists and occlusions; terrains use ``seed`` itself
    n = evaluator.hip_heights.size
    heights, twists, legs, nsf, kinds = [], [], [], [], []
    samples = terrain_samples(seed, count, cells=evaluator.evaluator.settings.patch_cells)
    for i, sample in enumerate(tqdm(samples, total=count, desc=f"VPA labels (seed {seed})", disable=not progress)):
        h = sample.heights.astype(float)
        if rng.uniform() < UNKNOWN_FRACTION:
            h = add_unknown_strip(h, rng)
        leg = LEGS[i % 4]
        twist = random_twist(rng)
        heights.append(h.astype(np.float32))
        twists.append(twist)
        legs.append(int(leg))
        nsf.append(evaluator.evaluate(leg, h, twist, gait).nsf)
        kinds.append(sample.kind)
    return VpaDataset(
        np.array(heights), np.array(twists), np.array(legs, dtype=np.int64),
        np.array(nsf, dtype=np.int16).reshape(-1, n), np.array(kinds), evaluator.hip_heights.copy(),
    )  # fmt: skip


def build_evaluator(settings: VpaSettings | None = None, robot: str = "hyq") -> PoseEvaluator:
    settings = settings if settings is not None else VpaSettings()
    return PoseEvaluator(FootholdEvaluator(RobotModel.from_name(robot)), settings.hip_heights)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=1, help="terrain / twist seed")
    parser.add_argument("--count", type=int, default=2000, help="number of labelled leg maps")
    parser.add_argument("--out", type=Path, required=True, help="output .npz")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    started = time.perf_counter()
    dataset = generate(args.seed, args.count, build_evaluator())
    dataset.save(args.out)
    LOG.info("%d samples in %.1f s -> %s", len(dataset), time.perf_counter() - started, args.out)


if __name__ == "__main__":
    main()
