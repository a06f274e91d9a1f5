"""Self-supervised dataset for the CNN approximation of the VFA's foothold evaluation (thesis, ViTAL).

Each sample is one VFA tuple T = (H, z_hip, twist, gait) for one leg, labelled by the EXACT evaluation
g: the full FEC (``FootholdEvaluator.evaluate``, all 33 x 33 candidates, eroded) and the safe candidate
closest to the nominal foothold (ties in row-major order, exactly as ``FootholdSelector``). The whole
safe mask is kept (bit-packed) so that "safe" accuracy can be scored and mirrored samples relabelled.

Sampling (every value drawn from ``np.random.default_rng([seed, index])``, so sample ``index`` is the
same whatever the chunking or the count):

* terrain: ``terrain_samples.random_terrain`` (a 33 x 33 patch of 0.02 m at a random heading, centred on
  the nominal foothold) of a kind drawn with ``TERRAIN_MIX`` (flat is rare: its nominal is always safe);
* unknown cells: with probability ``UNKNOWN_PROBABILITY`` a random rectangle of NaN (occlusion);
* hip height [m] world z of the HAA joint: the median known height of the patch plus
  U(``HIP_ABOVE_TERRAIN_M``), the robot's body following the terrain as it does with the VPA;
* twist (6,) horizontal frame: vx, vy [m/s], yaw rate [rad/s] uniform in ``TWIST_RANGES`` (HyQ trot);
  vz, roll and pitch rates are zero (the FEC takes the base level and never reads them);
* gait: trot-like step frequency, duty factor and step height uniform in ``GAIT_RANGES``, time left until
  touchdown uniform in [0, swing duration].

Samples whose leg has no safe candidate have label -1; training excludes them (the CNN cannot output
"none"; the VFA passes the nominal through there), the accuracy protocol counts them separately.

Mirror symmetry: LF <-> RF and LH <-> RH are exact mirror images in y on HyQ (checked: identical safe
masks on 150 random tuples). ``mirrored`` flips a set (columns, vy, yaw rate, leg) and relabels from the
flipped safe mask (the row-major tie-break is not mirror symmetric, so labels are recomputed).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from tal_core.legs import LEGS, RIGHT_LEGS, Leg
from tal_lab.vital.terrain_samples import TERRAIN_KINDS, random_terrain
from tal_perception.errors import FecConfigError
from tal_perception.fec import FootholdEvaluator
from tal_perception.fec_settings import FecInput, GaitTiming
from tal_perception.vfa_cnn import mirror_tuples

LOG = logging.getLogger(__name__)

# Terrain kinds and their probabilities: flat ground is rare because its nominal is always safe (the
# label would be trivially "the centre"); obstacles that cross the patch dominate.
TERRAIN_MIX: dict[str, float] = {"flat": 0.05, "bars": 0.25, "gaps": 0.25, "stairs": 0.2, "rocks": 0.25}
HIP_ABOVE_TERRAIN_M = (0.52, 0.66)  # [m] HAA joint above the median patch height (HyQ stands at 0.587)
# The hip ranges a set can be sampled with ("standard": the accuracy protocol's and the first sets'). In the
# closed loop on the stairs (0.4 m/s, VPA) the hips were 0.49-0.53 m above a front foot's patch on the way up
# and above 0.7 m on the way down; under 0.52 m the committed weights chose footholds 0.2-0.5 m from the
# exact ones (outside their training inputs), so sets sampled over "wide" teach the network those heights.
HIP_RANGES: dict[str, tuple[float, float]] = {"standard": HIP_ABOVE_TERRAIN_M, "wide": (0.40, 0.80)}
TWIST_RANGES = {"vx_mps": (-0.1, 0.5), "vy_mps": (-0.15, 0.15), "yaw_rate_radps": (-0.4, 0.4)}
GAIT_RANGES = {"step_frequency_hz": (1.2, 1.8), "duty_factor": (0.55, 0.7), "step_height_m": (0.08, 0.14)}
UNKNOWN_PROBABILITY = 0.15  # fraction of patches with a rectangle of unknown (NaN) cells
UNKNOWN_EDGE_CELLS = (3, 12)  # [cells] edge lengths of that rectangle


@dataclass(frozen=True, eq=False)
class VfaDataset:
    """N labelled VFA tuples (arrays of length N; patch frame of ``fec_settings``).

    heights (N, n, n) float32 [m] world z, NaN unknown; hip_height_m (N,) [m] world z of the HAA joint;
    twist (N, 6) [m/s, rad/s] horizontal frame; gait (N, 4): step frequency [Hz], duty factor [-], time
    left until touchdown [s], step height [m]; leg (N,) int8 index into ``LEGS``; kind (N,) int8 index
    into ``TERRAIN_KINDS``; safe (N, n, n) bool the eroded exact safe mask; label (N,) int16 flat index of
    the exact optimum g (row-major), -1 when no candidate is safe.
    """

    heights: NDArray[np.float32]
    hip_height_m: NDArray[np.float32]
    twist: NDArray[np.float32]
    gait: NDArray[np.float32]
    leg: NDArray[np.int8]
    kind: NDArray[np.int8]
    safe: NDArray[np.bool_]
    label: NDArray[np.int16]
    seed: int

    def __len__(self) -> int:
        return int(self.label.size)

    @property
    def cells(self) -> int:
        return int(self.heights.shape[1])

    def subset(self, mask: NDArray[np.bool_] | NDArray[np.intp]) -> VfaDataset:
        """The samples selected by a boolean mask or index array."""
        return VfaDataset(
            self.heights[mask], self.hip_height_m[mask], self.twist[mask], self.gait[mask], self.leg[mask],
            self.kind[mask], self.safe[mask], self.label[mask], self.seed,
        )  # fmt: skip

    def gait_timing(self, i: int) -> GaitTiming:
        return gait_from_row(self.gait[i])

    def fec_input(self, i: int) -> FecInput:
        """Sample ``i`` as the FEC tuple it was labelled from."""
        return _fec_input(self.leg[i], self.heights[i], self.hip_height_m[i], self.twist[i], self.gait[i])

    def statistics(self) -> dict[str, object]:
        """Label statistics: counts, fraction adapted (optimum != nominal), no-safe count, per kind/leg."""
        n = len(self)
        centre = (self.cells // 2) * self.cells + self.cells // 2
        has_safe = self.label >= 0
        adapted = has_safe & (self.label != centre)

        def split(index: NDArray[np.int8], names: tuple[str, ...]) -> dict[str, dict[str, int]]:
            return {
                name: {"samples": int((index == i).sum()), "adapted": int(adapted[index == i].sum()),
                       "no_safe": int((~has_safe[index == i]).sum())}
                for i, name in enumerate(names)
            }  # fmt: skip

        return {
            "samples": n,
            "adapted": int(adapted.sum()),
            "adapted_fraction": float(adapted.mean()) if n else 0.0,
            "nominal_optimal": int((self.label == centre).sum()),
            "no_safe": int((~has_safe).sum()),
            "with_unknown_cells": int(np.isnan(self.heights).any(axis=(1, 2)).sum()),
            "mean_safe_fraction": float(self.safe.mean()) if n else 0.0,
            "per_kind": split(self.kind, TERRAIN_KINDS),
            "per_leg": split(self.leg, tuple(leg.name for leg in LEGS)),
        }

    def save(self, path: Path) -> None:
        """Compressed ``.npz`` (safe masks bit-packed)."""
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(
            path, heights=self.heights, hip_height_m=self.hip_height_m, twist=self.twist, gait=self.gait,
            leg=self.leg, kind=self.kind, safe_bits=np.packbits(self.safe.reshape(len(self), -1), axis=1),
            label=self.label, seed=np.int64(self.seed),
        )  # fmt: skip

    @classmethod
    def load(cls, path: Path) -> VfaDataset:
        with np.load(path) as data:
            heights = data["heights"]
            n, cells = heights.shape[0], heights.shape[1]
            safe = np.unpackbits(data["safe_bits"], axis=1, count=cells * cells).astype(bool).reshape(n, cells, cells)
            return cls(
                heights, data["hip_height_m"], data["twist"], data["gait"], data["leg"], data["kind"], safe,
                data["label"], int(data["seed"]),
            )  # fmt: skip

    @classmethod
    def concatenate(cls, parts: list[VfaDataset]) -> VfaDataset:
        names = ("heights", "hip_height_m", "twist", "gait", "leg", "kind", "safe", "label")
        arrays = {name: np.concatenate([getattr(p, name) for p in parts]) for name in names}
        return cls(**arrays, seed=parts[0].seed)


def gait_from_row(row: NDArray[np.float32]) -> GaitTiming:
    """GaitTiming of a stored gait row (step frequency [Hz], duty factor, time left [s], step height [m])."""
    f, duty, left, step_height = (float(v) for v in row)
    swing = (1.0 - duty) / f
    return GaitTiming(f, duty, min(left, swing), step_height)  # float32 rounding may pass the swing's end


def _fec_input(
    leg: int, heights: NDArray[np.float32], hip: float, twist: NDArray[np.float32], gait: NDArray[np.float32]
) -> FecInput:
    """The FEC tuple of one stored sample (float32 values widened exactly to float64)."""
    hip_m = float(hip)
    return FecInput(LEGS[int(leg)], heights.astype(np.float64), hip_m, twist.astype(np.float64), gait_from_row(gait))


def search_order(cells: int) -> NDArray[np.intp]:
    """Flat candidate indices by distance from the centre, ties in row-major order (``FootholdSelector``)."""
    centre = cells // 2
    r, c = np.meshgrid(np.arange(cells), np.arange(cells), indexing="ij")
    return np.argsort(((r - centre) ** 2 + (c - centre) ** 2).reshape(-1), kind="stable")


def closest_safe_index(safe: NDArray[np.bool_], order: NDArray[np.intp] | None = None) -> int:
    """g on an eroded safe mask (cells, cells): flat index of the safe cell closest to the centre, -1 if none."""
    order = search_order(safe.shape[0]) if order is None else order
    ranked = safe.reshape(-1)[order]
    return int(order[np.argmax(ranked)]) if ranked.any() else -1


def random_tuple(
    rng: np.random.Generator, cells: int, resolution_m: float, hip_range: str = "standard"
) -> tuple[str, NDArray[np.float32], float, NDArray[np.float64], GaitTiming]:
    """One random VFA tuple (kind, heights float32 [m], hip height [m], twist (6,), gait); see the module doc.
    ``hip_range``: a key of ``HIP_RANGES`` (the hip's height above the median patch height)."""
    kinds = tuple(TERRAIN_MIX)
    probabilities = np.array([TERRAIN_MIX[k] for k in kinds])
    kind = kinds[int(rng.choice(len(kinds), p=probabilities / probabilities.sum()))]
    heights = np.array(random_terrain(rng, kind, cells, resolution_m).heights, dtype=np.float32)
    if rng.uniform() < UNKNOWN_PROBABILITY:
        edge_r, edge_c = rng.integers(UNKNOWN_EDGE_CELLS[0], UNKNOWN_EDGE_CELLS[1] + 1, size=2)
        r0, c0 = rng.integers(0, cells - edge_r + 1), rng.integers(0, cells - edge_c + 1)
        heights[r0 : r0 + edge_r, c0 : c0 + edge_c] = np.nan
    hip = float(np.nanmedian(heights)) + float(rng.uniform(*HIP_RANGES[hip_range]))
    twist = np.zeros(6)
    twist[0], twist[1], twist[5] = (rng.uniform(*TWIST_RANGES[k]) for k in TWIST_RANGES)
    f, duty, step_height = (float(rng.uniform(*GAIT_RANGES[k])) for k in GAIT_RANGES)
    swing = (1.0 - duty) / f
    gait = GaitTiming(f, duty, float(rng.uniform(0.0, swing)), step_height)
    return kind, heights, hip, twist, gait


def generate(
    evaluator: FootholdEvaluator,
    seed: int,
    count: int,
    legs: tuple[Leg, ...] = LEGS,
    progress: bool = True,
    description: str = "labelling",
    start: int = 0,
    hip_range: str = "standard",
) -> VfaDataset:
    """``count`` samples per leg in ``legs``, each its own random tuple labelled by the full exact FEC
    (samples ``start`` .. ``count - 1`` of each leg: a set of ``count`` is the set of ``start``
    concatenated with this one).

    Sample k of leg j uses ``default_rng([seed, j, k])`` (j = the leg's index in LEGS), so a sample does
    not depend on the count or on which other legs are generated. About 4-9 ms per sample on this machine.
    ``hip_range``: a key of ``HIP_RANGES``.
    """
    check_hip_range(hip_range)
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise FecConfigError(f"count must be an integer >= 1, got {count!r}")
    if isinstance(start, bool) or not isinstance(start, int) or not 0 <= start < count:
        raise FecConfigError(f"start must be an integer in [0, count), got {start!r}")
    s = evaluator.settings
    n = s.patch_cells
    order = search_order(n)
    jobs = [(leg, k) for k in range(start, count) for leg in legs]
    total = len(jobs)
    heights = np.empty((total, n, n), np.float32)
    hip = np.empty(total, np.float32)
    twist = np.empty((total, 6), np.float32)
    gait = np.empty((total, 4), np.float32)
    leg_index = np.empty(total, np.int8)
    kind_index = np.empty(total, np.int8)
    safe = np.empty((total, n, n), bool)
    label = np.empty(total, np.int16)
    for i, (leg, k) in enumerate(tqdm(jobs, desc=description, unit="sample", disable=not progress)):
        rng = np.random.default_rng([seed, LEGS.index(leg), k])
        kind, h, z_hip, tw, timing = random_tuple(rng, n, s.resolution_m, hip_range)
        # Round the stored inputs to float32 first, so that the label is exactly that of the stored sample.
        heights[i], hip[i], twist[i] = h, z_hip, tw
        gait[i] = (timing.step_frequency_hz, timing.duty_factor, timing.swing_time_left_s, timing.step_height_m)
        leg_index[i], kind_index[i] = LEGS.index(leg), TERRAIN_KINDS.index(kind)
        safe[i] = evaluator.evaluate(_fec_input(leg_index[i], heights[i], hip[i], twist[i], gait[i])).safe
        label[i] = closest_safe_index(safe[i], order)
    return VfaDataset(heights, hip, twist, gait, leg_index, kind_index, safe, label, seed)


def mirrored(data: VfaDataset) -> VfaDataset:
    """The y-mirror of every sample (``mirror_tuples``), labels recomputed from the flipped safe masks (exact on
    robots symmetric about the base's x-z plane)."""
    heights, twist, leg = mirror_tuples(data.heights, data.twist, data.leg)
    safe = np.ascontiguousarray(data.safe[:, :, ::-1])
    order = search_order(data.cells)
    label = np.array([closest_safe_index(m, order) for m in safe], np.int16)
    return VfaDataset(heights, data.hip_height_m, twist, data.gait, leg, data.kind, safe, label, data.seed)


def canonical_legs(data: VfaDataset) -> VfaDataset:
    """Every sample in the frame of a left leg: the left legs' samples as they are, then the y-mirrors
    (``mirrored``) of the right legs' samples; the training set of a ``NetConfig.canonical_legs`` network.
    Holds the same tuples as ``data`` (each once), so it carries what ``data`` plus its mirror does."""
    right = np.isin(data.leg, RIGHT_LEGS)
    return VfaDataset.concatenate([data.subset(~right), mirrored(data.subset(right))])


def check_hip_range(hip_range: str) -> None:
    """A precise error for a name that is not a key of ``HIP_RANGES``."""
    if hip_range not in HIP_RANGES:
        raise FecConfigError(f"hip_range must be one of {sorted(HIP_RANGES)}, got {hip_range!r}")


def set_prefix(prefix: str, hip_range: str) -> str:
    """The cache prefix of a set sampled with ``hip_range``: ``prefix`` for "standard" (the caches made before
    the option), ``<prefix>_<hip_range>`` otherwise (e.g. ``train_wide``)."""
    check_hip_range(hip_range)
    return prefix if hip_range == "standard" else f"{prefix}_{hip_range}"


def cache_path(folder: Path, prefix: str, seed: int, count: int) -> Path:
    """``<folder>/<prefix>_seed<seed>_n<count>.npz``, or an existing cache of that seed with more samples."""
    sizes = []
    for path in folder.glob(f"{prefix}_seed{seed}_n*.npz"):
        size = path.stem.rsplit("_n", 1)[1]
        if size.isdigit() and int(size) >= count:
            sizes.append((int(size), path))
    return min(sizes)[1] if sizes else folder / f"{prefix}_seed{seed}_n{count}.npz"


def load_or_generate(
    evaluator: FootholdEvaluator, path: Path, seed: int, count: int, description: str = "labelling",
    hip_range: str = "standard",
) -> VfaDataset:
    """The cached set at ``path`` if it was made with ``seed`` and at least ``count`` samples per leg (its
    first ``count`` per leg are exactly the set of that size, see ``generate``), else a new one (saved); a
    smaller cache of the same seed in the same folder is extended rather than relabelled. ``hip_range``
    (``HIP_RANGES``) is how a new set is sampled; the cache's name tells it (``set_prefix``)."""
    if path.exists():
        data = VfaDataset.load(path)
        if data.seed == seed and len(data) >= count * len(LEGS):
            used = count * len(LEGS)
            LOG.info("using the cached dataset %s (%d of its %d samples, seed %d)", path, used, len(data), seed)
            return data if len(data) == count * len(LEGS) else data.subset(np.arange(count * len(LEGS)))
        LOG.info("cached %s has another seed or size; regenerating", path)
    smaller = _smaller_cache(path, seed, count)
    if smaller is not None:
        part = VfaDataset.load(smaller)
        start = len(part) // len(LEGS)
        LOG.info("extending the cached dataset %s (%d per leg) to %d per leg", smaller, start, count)
        data = VfaDataset.concatenate([part, generate(evaluator, seed, count, description=description, start=start,
                                                      hip_range=hip_range)])
    else:
        data = generate(evaluator, seed, count, description=description, hip_range=hip_range)
    data.save(path)
    LOG.info("saved %s (%d samples, %.1f MB)", path, len(data), path.stat().st_size / 1e6)
    return data


def _smaller_cache(path: Path, seed: int, count: int) -> Path | None:
    """The largest ``<prefix>_seed<seed>_n<m>.npz`` beside ``path`` with m < count, if any (``path`` is named so)."""
    prefix, sep, _ = path.stem.rpartition(f"_seed{seed}_n")
    if not sep:
        return None
    sizes = []
    for other in path.parent.glob(f"{prefix}_seed{seed}_n*.npz"):
        size = other.stem.rsplit("_n", 1)[1]
        if size.isdigit() and 0 < int(size) < count:
            sizes.append((int(size), other))
    return max(sizes)[1] if sizes else None


def mix_description(hip_range: str = "standard") -> str:
    """One line describing the sampling ranges (for model cards and reports)."""
    check_hip_range(hip_range)
    hip = HIP_RANGES[hip_range]
    mix = ", ".join(f"{k} {v:.0%}" for k, v in TERRAIN_MIX.items())
    twist = ", ".join(f"{k} {lo:+g}..{hi:+g}" for k, (lo, hi) in TWIST_RANGES.items())
    gait = ", ".join(f"{k} {lo:g}..{hi:g}" for k, (lo, hi) in GAIT_RANGES.items())
    return (
        f"terrain {mix}; unknown-cell rectangle ({UNKNOWN_EDGE_CELLS[0]}-{UNKNOWN_EDGE_CELLS[1]} cells) in "
        f"{UNKNOWN_PROBABILITY:.0%} of patches; hip {hip[0]:g}..{hip[1]:g} m above "
        f"the median patch height; {twist}; {gait}; time left uniform in [0, swing duration]"
    )


__all__ = [
    "HIP_RANGES", "TERRAIN_MIX", "VfaDataset", "cache_path", "check_hip_range", "closest_safe_index", "generate",
    "load_or_generate", "mirrored", "mix_description", "random_tuple", "search_order", "set_prefix",
]  # fmt: skip
