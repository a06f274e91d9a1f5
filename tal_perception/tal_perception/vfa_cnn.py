"""CNN approximation g_hat of the VFA's foothold evaluation (thesis, ViTAL chapter, appendix "CNN
approximation in the VFA and the VPA").

Architecture (thesis): the 33 x 33 heightmap passes through three convolutional layers (5 x 5 kernels,
padding 2, Leaky ReLU, 2 x 2 max-pooling); the flattened features are concatenated with the other
entries of the tuple (hip height, twist, gait parameters; the nominal foothold is the patch centre by
construction) and pass through two fully connected layers (Leaky ReLU, then softmax over the 33 x 33
candidates), trained with cross-entropy against the exact optimum g. Ours adds, optionally, a second
output block of the last layer that predicts the exact safe mask (sigmoid per candidate): a denser
training signal than one class per sample, which the masked decodes of ``vfa_decode`` also use to select.
``VfaUNet`` (``NetConfig.architecture = "unet"``) keeps the thesis' trunk and adds a full-resolution
decoder that outputs both maps per cell. The file of the weights records the architecture and the decode.

Input encoding (``encode``), chosen so that it is exactly invariant where the FEC is: the FEC depends
on heights and hip height only through their difference, so

* channel 0: (h - (z_hip - d_nom)) / 0.1 m, clipped to +-0.5 m first, where d_nom is the robot's nominal
  hip height above flat ground (HyQ: 0.587 m); 0 = ground on which the robot would stand nominally,
  positive = higher (an obstacle), negative = lower (a gap or a step down). Unknown (NaN) cells are 0;
* channel 1: 1 on unknown (NaN) cells, else 0 (the exact FEC never selects them);
* channels 2, 3: the cell's row and column offset from the centre (the nominal), in [-1, 1];
* scalars: hip height above the median known patch height minus d_nom [0.05 m]; vx [0.5 m/s], vy
  [0.15 m/s], yaw rate [0.4 rad/s] (horizontal frame; the other twist entries do not enter the FEC);
  step frequency, duty factor, time left until touchdown (as a fraction of the swing and in [0.1 s]),
  step height, each centred on the trot's values; the leg as a one-hot vector (LF, RF, LH, RH).

Patch frame as in ``fec_settings`` (x forward, y left, origin at the nominal foothold, world z).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
from numpy.typing import ArrayLike, NDArray
from torch import nn

from tal_core.heightmap import HeightMapGrid
from tal_core.legs import LEGS, MIRROR_LEG_INDEX, RIGHT_LEGS, Leg
from tal_perception import vfa_cnn_ort
from tal_perception.errors import FecConfigError, PerceptionInputError
from tal_perception.fec import FootholdEvaluator
from tal_perception.fec_grid import disc_offsets
from tal_perception.fec_settings import FecInput, GaitTiming, check_motion_inputs
from tal_perception.vfa import (
    FootholdRequest,
    FootholdSelector,
    VfaResult,
    VfaStatus,
    check_map_age,
    extract_patches,
    map_status,
    patch_heading,
)
from tal_perception.vfa_cnn_fast import compile_fast_unet
from tal_perception.vfa_decode import VfaDecode, decode, decode_unchecked

FloatArray = NDArray[np.float64]
MODEL_DIR = Path(__file__).resolve().parent / "models"
DEFAULT_WEIGHTS = MODEL_DIR / "vfa_cnn.pt"
LEAKY_SLOPE = 0.01  # negative slope of the Leaky ReLUs (PyTorch's default)
IMAGE_CHANNELS = 4  # relative height, unknown mask, row offset, column offset
# NetConfig.roughness_features: RMS, std and mean of the slopes over the FEC's roughness disc, unknown nearby.
# Four, so that the last decoder layer reads 16 + 8 + 4 + 4 = 32 channels: ONNX Runtime's blocked (NCHWc)
# convolution needs a multiple of 4 (with 30 it fell back to a plain convolution, 0.73 instead of 0.38 ms).
ROUGHNESS_CHANNELS = 4


def mirror_tuples(
    heights: NDArray[np.floating], twist: NDArray[np.floating], legs: NDArray[np.integer]
) -> tuple[NDArray[np.floating], NDArray[np.floating], NDArray[np.integer]]:
    """The y-mirror of B tuples (new arrays, same dtypes): patch columns flipped (heights (B, n, n) [m]), vy and
    yaw rate negated (twist (B, 6) [m/s, rad/s], horizontal frame), each leg index (B,) replaced by its mirror's."""
    twist = np.array(twist, copy=True)
    twist[:, 1] *= -1.0
    twist[:, 5] *= -1.0
    return np.ascontiguousarray(heights[:, :, ::-1]), twist, np.asarray(MIRROR_LEG_INDEX, legs.dtype)[legs]



@dataclass(frozen=True)
class EncodingConfig:
    """Constants of the input encoding (stored with the weights so that training and inference agree)."""

    cells: int = 33  # [-] patch edge (thesis: 33)
    resolution_m: float = 0.02  # [m] cell edge (thesis: 0.02)
    nominal_hip_height_m: float = 0.587  # [m] the robot's HAA height above flat ground when standing
    height_scale_m: float = 0.1  # [m] one unit of channel 0
    height_clip_m: float = 0.5  # [m] relative heights are clipped to +- this (beyond: unreachable anyway)
    hip_scale_m: float = 0.05  # [m]
    twist_scale: tuple[float, float, float] = (0.5, 0.15, 0.4)  # [m/s, m/s, rad/s] vx, vy, yaw rate
    gait_centre: tuple[float, float, float, float] = (1.5, 0.6, 0.13, 0.11)  # [Hz, -, s, m]
    gait_scale: tuple[float, float, float, float] = (0.3, 0.1, 0.1, 0.03)  # [Hz, -, s, m]

    @property
    def scalar_count(self) -> int:
        return 1 + 3 + 5 + len(LEGS)


ARCHITECTURES = ("thesis", "unet")
BACKENDS = ("auto", "onnxruntime", "torch")  # CnnFootholdSelector's network runtimes (auto: onnxruntime if present)


@dataclass(frozen=True)
class NetConfig:
    """Architecture and layer sizes: ``thesis`` = ``VfaNet``, ``unet`` = ``VfaUNet`` (decoder_channels used)."""

    channels: tuple[int, int, int] = (8, 16, 32)
    hidden: int = 256
    safe_head: bool = True  # the network also predicts the safe mask (a training signal; some decodes use it)
    encoding: EncodingConfig = field(default_factory=EncodingConfig)
    architecture: str = "thesis"
    decoder_channels: tuple[int, int, int] = (32, 16, 8)  # unet: at 9 x 9, 17 x 17, 33 x 33
    # unet only: a fixed (not learned) layer adds the FEC's roughness statistics of every cell
    # (``RoughnessFeatures``) to the image that the full-resolution decoder layer reads. Off in the files
    # before it (they load with False).
    roughness_features: bool = False
    # unet only: residual 1 x 1 blocks at full resolution after the last decoder layer, x + LeakyReLU(W x + b)
    # per candidate (per-cell depth for the criteria's sharp boundaries at ~5 % more multiply-adds each).
    # 0 in the files before it (they load with 0).
    head_blocks: int = 0
    # Trained on left legs only (LF, LH): a right leg's tuple is y-mirrored in (``canonical_inputs``) and the
    # choice mirrored back, so the network learns half the function (HyQ is symmetric about its x-z plane).
    # False in the files before it.
    canonical_legs: bool = False

    def __post_init__(self) -> None:
        if self.architecture not in ARCHITECTURES:
            raise FecConfigError(f"NetConfig.architecture must be one of {ARCHITECTURES}, got {self.architecture!r}")
        if self.roughness_features and self.architecture != "unet":
            raise FecConfigError("NetConfig.roughness_features needs the unet architecture")
        if self.head_blocks < 0 or (self.head_blocks and self.architecture != "unet"):
            raise FecConfigError(f"NetConfig.head_blocks must be >= 0 and needs the unet architecture, "
                                 f"got {self.head_blocks} with {self.architecture!r}")  # fmt: skip

    @property
    def image_channels(self) -> int:
        """Image channels the full-resolution decoder layer reads: ``encode``'s 4 (+ 2 roughness features)."""
        return IMAGE_CHANNELS + (ROUGHNESS_CHANNELS if self.roughness_features else 0)


def encode(
    cfg: EncodingConfig,
    heights: NDArray[np.floating],
    hip_height_m: ArrayLike,
    twist: ArrayLike,
    gait: ArrayLike,
    leg: ArrayLike,
    out: tuple[NDArray[np.float32], NDArray[np.float32]] | None = None,
    unknown: NDArray[np.bool_] | None = None,
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Network inputs of B tuples (see the module docstring): image (B, 4, n, n), scalars (B, S).

    heights (B, n, n) [m] world z, NaN unknown; hip_height_m (B,) [m] world z of the HAA joint; twist
    (B, 6) [m/s, rad/s] horizontal frame; gait (B, 4): step frequency [Hz], duty factor [-], time left
    until touchdown [s], step height [m]; leg (B,) index 0-3 into LEGS, not checked here (the selector passes
    ``Leg`` values, the datasets are written by ``vfa_dataset``; another index gives an all-zero one-hot).
    Arrays or nested lists, rounded to float32 as given. out: preallocated (image, scalars) of those shapes,
    float32, C-contiguous, written and returned (the selector's per-call buffers). unknown:
    ``np.isnan(heights)`` (B, n, n) when the caller has it (the selector's decode needs it too).
    """
    heights = np.asarray(heights, dtype=np.float32)
    hip = np.asarray(hip_height_m, dtype=np.float32)
    b = heights.shape[0]
    coordinates, centre, scale = _constants(cfg)
    if unknown is None:
        unknown = np.isnan(heights)
    if out is None:
        image = np.empty((b, IMAGE_CHANNELS, cfg.cells, cfg.cells), np.float32)
        scalars = np.empty((b, cfg.scalar_count), np.float32)
    else:
        image, scalars = out
    relative = image[:, 0]
    np.subtract(heights, (hip - cfg.nominal_hip_height_m)[:, None, None], out=relative)
    np.minimum(np.maximum(relative, -cfg.height_clip_m, out=relative), cfg.height_clip_m, out=relative)
    relative /= cfg.height_scale_m
    relative[unknown] = 0.0  # NaN -> 0 last: 0 is inside the clip and 0 / scale = 0
    image[:, 1] = unknown
    image[:, 2:] = coordinates
    median, has_known = _row_medians(heights.reshape(b, -1), unknown.reshape(b, -1))
    # scalars 0-8 = (raw - centre) / scale in float32, raw = (hip - median, vx, vy, yaw rate, gait (4), fraction
    # of the swing still to go); in place and in two operations for all nine (a centre of 0 and a scale of 1
    # change nothing: x - 0 and x / 1 are exact)
    raw = scalars[:, :9]
    np.subtract(hip, median, out=raw[:, 0])
    twist = np.asarray(twist)
    raw[:, 1:3] = twist[:, :2]  # vx, vy, rounded to float32 here
    raw[:, 3] = twist[:, 5]  # yaw rate
    raw[:, 4:8] = gait  # rounded to float32 here
    swing = 1.0 - raw[:, 5]
    swing /= raw[:, 4]  # [s] swing duration = (1 - duty factor) / step frequency
    np.divide(raw[:, 6], swing, out=raw[:, 8])
    np.subtract(raw, centre, out=raw)
    np.divide(raw, scale, out=raw)
    if not all(has_known.tolist()):  # 0 when nothing is known (tolist: ~1 us less than .all() for a few rows)
        raw[~has_known, 0] = 0.0
    np.equal(np.asarray(leg, dtype=np.intp)[:, None], _LEG_INDICES, out=scalars[:, 9:])  # one-hot leg
    return image, scalars


_LEG_INDICES = np.arange(len(LEGS))


def canonical_inputs(
    heights: NDArray[np.floating], twist: ArrayLike, legs: ArrayLike
) -> tuple[NDArray[np.floating], NDArray[np.float64], NDArray[np.int64], NDArray[np.bool_]]:
    """The inputs of a ``NetConfig.canonical_legs`` network: every right-leg tuple replaced by its y-mirror
    (``mirror_tuples``: patch columns flipped, vy and yaw rate negated, the left leg of the same
    end). heights (B, n, n) [m], twist (B, 6) [m/s, rad/s], legs (B,) indices into LEGS.
    Returns (heights, twist, legs, right) with right (B,) True where a tuple was mirrored; the inputs are not
    modified (copies are made only when a right leg is present)."""
    leg_index = np.array(legs, dtype=np.int64)
    right = np.isin(leg_index, RIGHT_LEGS)
    twist_array = np.array(twist, dtype=np.float64)
    if not right.any():
        return heights, twist_array, leg_index, right
    heights = np.array(heights, copy=True)
    heights[right], twist_array[right], leg_index[right] = mirror_tuples(heights[right], twist_array[right],
                                                                         leg_index[right])  # fmt: skip
    return heights, twist_array, leg_index, right


def mirror_cell_maps(maps: NDArray[np.floating], flip: NDArray[np.bool_], cells: int) -> NDArray[np.floating]:
    """Per-candidate maps (B, n*n) of a canonical network mapped back to the tuples' own frame: the rows of
    ``flip`` mirrored in y (columns reversed), in place; returns ``maps``."""
    if flip.any():
        grid = maps.reshape(len(maps), cells, cells)
        grid[flip] = grid[flip][:, :, ::-1]
    return maps


def mirror_cell_index(index: NDArray[np.intp], flip: NDArray[np.bool_], cells: int) -> NDArray[np.intp]:
    """Flat (row-major) candidate indices of a canonical network mapped back to the tuples' own frame: the
    column of the entries of ``flip`` mirrored (c -> n - 1 - c)."""
    column = index % cells
    return np.where(flip, index - column + (cells - 1 - column), index)


@lru_cache(maxsize=4)
def _constants(cfg: EncodingConfig) -> tuple[NDArray[np.float32], ...]:
    """Per-configuration constants of ``encode``: the coordinate channels (2, n, n) and the centres and scales
    (9,) of scalars 0-8.

    Channels 2 and 3 are the cell's row and column offset from the centre in [-1, 1] ("CoordConv"): the
    optimum is defined by its distance from the centre, which convolutions alone do not see."""
    offsets = (np.arange(cfg.cells, dtype=np.float32) - cfg.cells // 2) / (cfg.cells // 2)
    rows, cols = np.meshgrid(offsets, offsets, indexing="ij")
    coordinates = np.stack([rows, cols]).astype(np.float32)
    centre = np.array([cfg.nominal_hip_height_m, 0.0, 0.0, 0.0, *cfg.gait_centre, 0.0], np.float32)
    scale = np.array([cfg.hip_scale_m, *cfg.twist_scale, *cfg.gait_scale, 1.0], np.float32)
    return coordinates, centre, scale


def _row_medians(
    values: NDArray[np.float32], unknown: NDArray[np.bool_]
) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """Median of the known (not ``unknown``) entries of each row of ``values`` (B, m) [same unit], and
    whether the row has any; one partition of all rows (unknown entries as +inf, so they come last) at
    the middle positions of every row. Each median is ``np.median``'s in float32: the middle value, or
    0.5 * (sum of the two middle values) for an even count (~25 us for 4 rows of 1089, 4 x ~10 us before)."""
    rows, m = values.shape
    if not _any(unknown):  # the common case: every row's middle is at the same positions (no index arrays)
        ordered = np.partition(values, ((m - 1) // 2, m // 2), axis=1)
        high, low = ordered[:, m // 2], ordered[:, (m - 1) // 2]
        median = high if m % 2 == 1 else np.float32(0.5) * (low + high)
        return median.astype(np.float32, copy=False), np.ones(rows, dtype=bool)
    count = m - unknown.sum(axis=1)
    has_known = count > 0
    upper = np.minimum(count // 2, m - 1)
    lower = np.maximum(count - 1, 0) // 2
    if unknown.any():
        values = np.where(unknown, np.float32(np.inf), values)
    # two or more positions (repeated if equal): numpy's partition is ~2x faster than with a single one
    ordered = np.partition(values, np.sort(np.concatenate([lower, upper])), axis=1)
    index = np.arange(rows)
    high, low = ordered[index, upper], ordered[index, lower]
    median = np.where(count % 2 == 1, high, np.float32(0.5) * (low + high))
    return median.astype(np.float32, copy=False), has_known


class VfaNet(nn.Module):
    """The thesis' VFA CNN: 3 x (conv 5x5 pad 2, Leaky ReLU, max-pool 2x2) -> concat scalars -> FC, Leaky
    ReLU -> FC -> logits over the n x n candidates (softmax in the loss / at selection), plus optionally
    logits of the safe mask (the "thesis" architecture)."""

    def __init__(self, config: NetConfig) -> None:
        super().__init__()
        self.config = config
        enc = config.encoding
        layers: list[nn.Module] = []
        in_channels, size = IMAGE_CHANNELS, enc.cells
        for out_channels in config.channels:
            layers += [
                nn.Conv2d(in_channels, out_channels, kernel_size=5, padding=2),
                nn.LeakyReLU(LEAKY_SLOPE),
                nn.MaxPool2d(2, ceil_mode=True),  # 33 -> 17 -> 9 -> 5: the border cells keep their own pool
            ]
            in_channels, size = out_channels, math.ceil(size / 2)
        self.features = nn.Sequential(*layers, nn.Flatten())
        self.candidates = enc.cells * enc.cells
        outputs = self.candidates * (2 if config.safe_head else 1)
        self.head = nn.Sequential(
            nn.Linear(in_channels * size * size + enc.scalar_count, config.hidden),
            nn.LeakyReLU(LEAKY_SLOPE),
            nn.Linear(config.hidden, outputs),
        )

    def forward(self, image: torch.Tensor, scalars: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(optimum logits (B, n*n), safe-mask logits (B, n*n) or None); row-major candidate order."""
        out = self.head(torch.cat([self.features(image), scalars], dim=1))
        if self.config.safe_head:
            return out[:, : self.candidates], out[:, self.candidates :]
        return out, None

    def optimum_logits(self, image: torch.Tensor, scalars: torch.Tensor) -> torch.Tensor:
        """Only the optimum logits, computing only their rows of the last layer (inference)."""
        hidden = self.head[1](self.head[0](torch.cat([self.features(image), scalars], dim=1)))
        last = self.head[2]
        return nn.functional.linear(hidden, last.weight[: self.candidates], last.bias[: self.candidates])


class RoughnessFeatures(nn.Module):
    """Fixed preprocessing inside the network (no learned weights): from ``encode``'s image (channel 0 the
    relative height [0.1 m], channel 1 the unknown mask), per cell two statistics of the slopes that the
    FEC's roughness criterion (``fec_grid.terrain_roughness``) uses, s_j = (h_j - h_c) / d_j [-] to the
    neighbours j within ``radius_m``: (B, 4, n, n) = the root mean square of s_j / scale[0] and the standard
    deviation of s_j / scale[1] (the FEC's own second statistic), each clipped to [0, clip] (with the
    default scales, the FEC's ``max_mean_slope`` 0.3 and ``max_slope_std`` 0.35, 1 is at the FEC's limit);
    the mean of s_j / scale[0] clipped to [-clip, clip] (positive in a hollow, negative on a crest); 1 where
    the cell is unknown or has an unknown neighbour (the FEC calls it rough; there the first two are
    ``clip`` and the third 0). Neighbours outside the patch are ignored, as the FEC does.

    The FEC's first statistic is the mean |s_j|; its root mean square (>= the mean |s_j|) is used instead
    because it is a sum of squares: everything is then one fixed 3 -> 4 channel convolution of (h, h^2,
    unknown) (sums of w_j h_j^q and the unknown neighbours over the disc, w_j = 1 / d_j) and a few per-cell
    operations; the per-position neighbour counts and weight sums of a fully known patch are constants.
    Computing the 12 |s_j| per cell took ~0.5 ms per 4-leg call on ONNX Runtime, over the time budget.
    The heights are ``encode``'s clipped ones (+-0.5 m around the nominal ground): slopes differ from the
    FEC's only next to such cells, unreachable anyway. Height differences only, so the network stays
    invariant where ``encode`` is.

    Why: the FEC's roughness statistics (and the erosion after them) are fine geometry that the thin
    full-resolution decoder layer only approximates; on rocks half of the unsafe choices are cells eroded
    by a rough neighbour (``bench/analyse_vfa_cnn_errors.py``)."""

    def __init__(
        self, cells: int, resolution_m: float, height_scale_m: float, radius_m: float = 0.04,
        scale: tuple[float, float] = (0.3, 0.35), clip: float = 5.0,
    ) -> None:  # fmt: skip
        super().__init__()
        offsets = disc_offsets(radius_m, resolution_m)
        k = max(max(abs(di), abs(dj)) for di, dj in offsets)
        # inputs (h, h^2, unknown), h in channel-0 units; outputs: sums over the disc of w_j h_j,
        # w_j^2 h_j, w_j^2 h_j^2 and the unknown neighbours, w_j = height_scale_m / d_j [1/unit] (slope [-])
        weight = torch.zeros(4, 3, 2 * k + 1, 2 * k + 1, dtype=torch.float64)
        inside = torch.zeros(3, 1, 2 * k + 1, 2 * k + 1, dtype=torch.float64)  # count, sum w_j, sum w_j^2
        for di, dj in offsets:  # output cell (r, c) reads (r + di, c + dj) (cross-correlation)
            w = height_scale_m / (resolution_m * math.hypot(di, dj))
            weight[0, 0, k + di, k + dj], weight[1, 0, k + di, k + dj], weight[2, 1, k + di, k + dj] = w, w * w, w * w
            weight[3, 2, k + di, k + dj] = 1.0
            inside[:, 0, k + di, k + dj] = torch.tensor([1.0, w, w * w], dtype=torch.float64)
        # per-position sums over the neighbours inside the patch (constants: unknown cells are handled apart)
        sums = nn.functional.conv2d(torch.ones(1, 1, cells, cells, dtype=torch.float64), inside, padding=k)[0]
        count, w_sum, w2_sum = sums
        self.padding = k
        self.register_buffer("weight", weight.to(torch.float32), persistent=False)
        self.register_buffer("inv_count", (1.0 / count).to(torch.float32)[None, None], persistent=False)
        self.register_buffer("w_sum", w_sum.to(torch.float32)[None, None], persistent=False)
        self.register_buffer("w2_sum", w2_sum.to(torch.float32)[None, None], persistent=False)
        self.inv_scale = (1.0 / scale[0], 1.0 / scale[1])
        self.clip = float(clip)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        """(B, 4, n, n) roughness statistics of ``encode``'s image (B, >= 2, n, n)."""
        height, unknown = image[:, 0:1], image[:, 1:2]  # encode sets unknown heights to 0
        sums = nn.functional.conv2d(torch.cat([height, height * height, unknown], dim=1), self.weight,
                                    padding=self.padding)  # (B, 4, n, n); cells outside the patch read 0
        wh, w2h, w2h2, unknown_near = torch.split(sums, 1, dim=1)
        mean = (wh - height * self.w_sum) * self.inv_count  # mean of s_j
        mean_square = (w2h2 - height * (2.0 * w2h - height * self.w2_sum)) * self.inv_count  # mean of s_j^2
        rms = torch.sqrt(torch.clamp(mean_square, min=0.0))
        std = torch.sqrt(torch.clamp(mean_square - mean * mean, min=0.0))
        stats = torch.cat([rms * self.inv_scale[0], std * self.inv_scale[1]], dim=1)
        rough = (unknown_near + unknown) > 0.5  # an unknown cell or neighbour: rough for the FEC
        stats = torch.where(rough, torch.full_like(stats, self.clip), torch.clamp(stats, 0.0, self.clip))
        signed = torch.clamp(mean * self.inv_scale[0], -self.clip, self.clip) * (~rough)  # + = in a hollow
        return torch.cat([stats, signed, rough.to(stats.dtype)], dim=1)


class VfaUNet(nn.Module):
    """A localising variant: the thesis' convolutional trunk (3 x conv 5x5 + Leaky ReLU + max-pool 2x2,
    33 -> 17 -> 9 -> 5) and its fully connected layer (flattened features + scalars -> ``hidden``), whose
    output is projected back onto the 5 x 5 grid as global context; a decoder then upsamples (nearest,
    the inverse of the ceil-mode pooling) to 9, 17 and 33 cells, each level a 3 x 3 convolution over the
    upsampled features, the trunk's features of that resolution (skip) and, at 33, the input image, plus a
    per-sample bias computed from the scalars (= the scalars broadcast as channels); ``head_blocks``
    residual 1 x 1 blocks per candidate (none in the files before them); a 1 x 1 convolution gives per
    candidate the optimum logit and (``safe_head``) the safe-mask logit. Receptive field: the whole patch
    (through the context)."""

    def __init__(self, config: NetConfig) -> None:
        super().__init__()
        self.config = config
        enc = config.encoding
        c1, c2, c3 = config.channels
        d3, d2, d1 = config.decoder_channels
        image_channels = IMAGE_CHANNELS
        full_resolution = config.image_channels  # the last decoder layer also reads the roughness features
        self.roughness = (
            RoughnessFeatures(enc.cells, enc.resolution_m, enc.height_scale_m) if config.roughness_features else None
        )  # fmt: skip
        self.encoders = nn.ModuleList(
            nn.Conv2d(i, o, kernel_size=5, padding=2) for i, o in ((image_channels, c1), (c1, c2), (c2, c3))
        )
        self.pool = nn.MaxPool2d(2, ceil_mode=True)
        self.sizes = [enc.cells]
        for _ in range(3):
            self.sizes.append(math.ceil(self.sizes[-1] / 2))  # 33, 17, 9, 5
        bottleneck = c3 * self.sizes[3] ** 2
        self.context = nn.Sequential(
            nn.Linear(bottleneck + enc.scalar_count, config.hidden), nn.LeakyReLU(LEAKY_SLOPE),
            nn.Linear(config.hidden, bottleneck), nn.LeakyReLU(LEAKY_SLOPE),
        )  # fmt: skip
        self.decoders = nn.ModuleList([
            nn.Conv2d(2 * c3 + c3, d3, kernel_size=3, padding=1),
            nn.Conv2d(d3 + c2, d2, kernel_size=3, padding=1),
            nn.Conv2d(d2 + c1 + full_resolution, d1, kernel_size=3, padding=1),
        ])  # fmt: skip
        self.scalar_bias = nn.Linear(enc.scalar_count, d3 + d2 + d1)
        self.head = nn.ModuleList(nn.Conv2d(d1, d1, kernel_size=1) for _ in range(config.head_blocks))
        self.output = nn.Conv2d(d1, 2 if config.safe_head else 1, kernel_size=1)
        self.act = nn.LeakyReLU(LEAKY_SLOPE)

    @staticmethod
    def _up(x: torch.Tensor, size: int) -> torch.Tensor:
        """Nearest 2x upsampling cropped to ``size``: cell j takes the pooled cell j // 2."""
        return nn.functional.interpolate(x, scale_factor=2.0, mode="nearest")[:, :, :size, :size]

    def forward(self, image: torch.Tensor, scalars: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(optimum logits (B, n*n), safe-mask logits (B, n*n) or None); row-major candidate order."""
        skips, x = [], image
        for conv in self.encoders:
            x = self.act(conv(x))
            skips.append(x)
            x = self.pool(x)
        b = x.shape[0]
        context = self.context(torch.cat([x.flatten(1), scalars], dim=1)).view_as(x)
        x = torch.cat([x, context], dim=1)
        biases = torch.split(self.scalar_bias(scalars), [d.out_channels for d in self.decoders], dim=1)
        # full resolution: the image with the roughness features before its coordinate channels (those
        # stay last, as vfa_cnn_fast expects of the image)
        full = image if self.roughness is None else torch.cat([image[:, :2], self.roughness(image), image[:, 2:]], 1)
        inputs = [[skips[2]], [skips[1]], [skips[0], full]]
        for level, (conv, bias, extra) in enumerate(zip(self.decoders, biases, inputs)):
            x = self._up(x, self.sizes[2 - level])
            x = self.act(conv(torch.cat([x, *extra], dim=1)) + bias[:, :, None, None])
        for block in self.head:
            x = x + self.act(block(x))
        out = self.output(x).reshape(b, self.output.out_channels, -1)
        return out[:, 0], (out[:, 1] if self.config.safe_head else None)

    def optimum_logits(self, image: torch.Tensor, scalars: torch.Tensor) -> torch.Tensor:
        """Only the optimum logits (B, n*n)."""
        return self.forward(image, scalars)[0]


def build_net(config: NetConfig) -> VfaNet | VfaUNet:
    """The network of ``config.architecture`` (untrained)."""
    return VfaUNet(config) if config.architecture == "unet" else VfaNet(config)


def save_model(net: VfaNet | VfaUNet, path: Path, metadata: dict[str, object] | None = None) -> None:
    """Weights in float16 (half the size; the loaded model computes in float32) with the config; the
    metadata may hold the decode (``"decode"``: ``VfaDecode.to_dict()``) the selector uses by default."""
    cfg = net.config
    document = {
        "format": "tal_perception.vfa_cnn/1",
        "net": {
            "channels": list(cfg.channels),
            "hidden": cfg.hidden,
            "safe_head": cfg.safe_head,
            "architecture": cfg.architecture,
            "decoder_channels": list(cfg.decoder_channels),
            "roughness_features": cfg.roughness_features,
            "head_blocks": cfg.head_blocks,
            "canonical_legs": cfg.canonical_legs,
        },  # fmt: skip
        "encoding": {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(cfg.encoding).items()},
        "state_dict": {k: v.detach().to(torch.float16).contiguous() for k, v in net.state_dict().items()},
        "metadata": metadata or {},
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(document, path)


def load_model(path: Path = DEFAULT_WEIGHTS) -> VfaNet | VfaUNet:
    """The network saved by ``save_model`` (float32, eval mode); ``net.decode`` is the stored decode
    (``VfaDecode``; the thesis' argmax when the file has none)."""
    if not path.exists():
        raise FecConfigError(f"VFA CNN weights not found: {path} (train them with python -m tal_lab.vital.train_vfa)")
    document = torch.load(path, map_location="cpu", weights_only=True)
    if document.get("format") != "tal_perception.vfa_cnn/1":
        raise FecConfigError(f"{path} is not a tal_perception VFA CNN file (format {document.get('format')!r})")
    enc = {k: tuple(v) if isinstance(v, list) else v for k, v in document["encoding"].items()}
    net_cfg = document["net"]
    config = NetConfig(tuple(net_cfg["channels"]), int(net_cfg["hidden"]), bool(net_cfg["safe_head"]),
                       EncodingConfig(**enc), str(net_cfg.get("architecture", "thesis")),
                       tuple(net_cfg.get("decoder_channels", NetConfig.decoder_channels)),
                       bool(net_cfg.get("roughness_features", False)), int(net_cfg.get("head_blocks", 0)),
                       bool(net_cfg.get("canonical_legs", False)))  # fmt: skip
    net = build_net(config)
    net.load_state_dict({k: v.to(torch.float32) for k, v in document["state_dict"].items()})
    net.eval()
    net.decode = stored_decode(document.get("metadata", {}), path)
    return net


def stored_decode(metadata: dict[str, object], path: Path) -> VfaDecode:
    """The decode recorded in a model file's metadata (the thesis' argmax if none)."""
    values = metadata.get("decode")
    if values is None:
        return VfaDecode()
    if not isinstance(values, dict):
        raise FecConfigError(f"{path}: metadata 'decode' must be a mapping, got {values!r}")
    return VfaDecode.from_dict(values)


def store_decode(path: Path, settings: VfaDecode) -> None:
    """Record ``settings`` as the decode of the model file ``path`` (the weights are left as they are)."""
    document = torch.load(path, map_location="cpu", weights_only=True)
    if document.get("format") != "tal_perception.vfa_cnn/1":
        raise FecConfigError(f"{path} is not a tal_perception VFA CNN file (format {document.get('format')!r})")
    if settings.needs_safe_head and not document["net"]["safe_head"]:
        raise FecConfigError(f"{path}: the decode {settings.mode!r} needs a safe head, the network has none")
    document["metadata"] = {**document.get("metadata", {}), "decode": settings.to_dict()}
    torch.save(document, path)


@dataclass
class CnnVfaCounters:
    """What the CNN selector did since construction (selections with a map)."""

    selections: int = 0
    verified: int = 0  # CNN choices checked with the exact FEC
    rejected: int = 0  # ... of which were unsafe: the exact lazy search ran instead


class CnnFootholdSelector:
    """g_hat: the VFA's foothold evaluation by the CNN, with the interface and results of
    ``FootholdSelector`` (same patch extraction, same NO_MAP / STALE_MAP pass-through).

    verify: check the CNN's choice with the exact FEC on that one candidate (and its uncertainty-margin
    neighbours); if it is unsafe, run the exact lazy search instead (``counters`` say how often). Off,
    the CNN's choice is returned as is (``any_safe`` then means "predicted safe"); a choice on an
    unknown cell is never returned (NO_SAFE_CANDIDATE, nominal passed through).
    The CNN was trained with the default lift-off and hip-at-touchdown; given values reach only the
    exact verification and fallback.

    decode: how the network's outputs become a candidate (``vfa_decode.VfaDecode``); None = the decode
    stored with the weights (``net.decode``; the thesis' argmax for a network without one).

    backend: which runtime computes the network. ``"onnxruntime"``: the module's forward exported to ONNX
    and run by ONNX Runtime on one thread (``vfa_cnn_ort``; the faster one, see ``docs/models/VFA_CARD.md``);
    ``"torch"``: PyTorch (see ``fast``); ``"auto"`` (default): onnxruntime when ``onnxruntime`` and
    ``onnx`` import, else torch. An explicit ``"onnxruntime"`` that cannot be imported falls back to torch
    with a ``RuntimeWarning``. ``self.backend`` says which one runs. Both compute the same function (float32
    summation order aside; same selections); the weights are copied once here, so later changes of
    ``net`` are not seen.

    fast (torch backend only): run a ``VfaUNet`` (with its safe head) through
    ``vfa_cnn_fast.compile_fast_unet``, the same function rearranged for inference (same selections);
    False, or another network: the module's own forward.
    """

    def __init__(
        self, evaluator: FootholdEvaluator, net: VfaNet | VfaUNet | None = None, max_map_age_s: float = 0.5,
        verify: bool = True, decode: VfaDecode | None = None, fast: bool = True, backend: str = "auto",
    ) -> None:  # fmt: skip
        self.exact = FootholdSelector(evaluator, max_map_age_s)  # validates max_map_age_s
        self.evaluator = evaluator
        self.net = net if net is not None else load_model()
        self.net.eval()
        self.net.to(memory_format=torch.channels_last)  # ~30 % faster convolutions on CPU (4-leg batch)
        if decode is not None and not isinstance(decode, VfaDecode):
            raise FecConfigError(f"CnnFootholdSelector: decode must be a VfaDecode or None, got {decode!r}")
        self.decode = decode if decode is not None else getattr(self.net, "decode", VfaDecode())
        if self.decode.needs_safe_head and not self.net.config.safe_head:
            raise FecConfigError(f"the decode {self.decode.mode!r} needs the safe-mask head; the network has none")
        self.verify = bool(verify)
        self.counters = CnnVfaCounters()
        s, enc = evaluator.settings, self.net.config.encoding
        if (s.patch_cells, s.resolution_m) != (enc.cells, enc.resolution_m):
            raise FecConfigError(
                f"the VFA CNN was trained on {enc.cells} x {enc.cells} patches of {enc.resolution_m} m, the FEC "
                f"settings have {s.patch_cells} x {s.patch_cells} of {s.resolution_m} m"
            )
        self._margin = np.array(disc_offsets(s.uncertainty_margin_m, s.resolution_m, include_centre=True))
        if backend not in BACKENDS:
            raise FecConfigError(f"CnnFootholdSelector: backend must be one of {BACKENDS}, got {backend!r}")
        self._ort_net: vfa_cnn_ort.OrtVfaNet | None = None
        self._workspaces: dict[int, _Workspace] = {}  # by batch size (select_legs' buffers)
        if backend != "torch":
            if vfa_cnn_ort.available():
                self._ort_net = vfa_cnn_ort.OrtVfaNet(self.net)
            elif backend == "onnxruntime":
                warnings.warn("CnnFootholdSelector: onnxruntime / onnx not importable, the VFA CNN runs on torch",
                              RuntimeWarning, stacklevel=2)  # fmt: skip
        use_fast = (self._ort_net is None and fast and isinstance(self.net, VfaUNet) and self.net.config.safe_head
                    and not self.net.config.roughness_features)  # the rearranged network has no roughness layer
        self._fast_net = compile_fast_unet(self.net, enc.cells) if use_fast else None

    @property
    def backend(self) -> str:
        """The runtime that computes the network: ``"onnxruntime"`` or ``"torch"``."""
        return "onnxruntime" if self._ort_net is not None else "torch"

    @property
    def fast(self) -> bool:
        """True when ``predict`` runs the rearranged torch network (``vfa_cnn_fast``)."""
        return self._fast_net is not None

    @property
    def max_map_age_s(self) -> float:
        return self.exact.max_map_age_s

    # -- the CNN on FEC tuples ------------------------------------------------------------------------
    def predict(self, inputs: Sequence[FecInput]) -> NDArray[np.intp]:
        """Flat (row-major) index of the CNN's choice for each tuple (one batched forward pass, then ``decode``)."""
        n = self.net.config.encoding.cells
        for inp in inputs:
            if inp.heights.shape != (n, n):
                raise PerceptionInputError(
                    f"VFA CNN: heights must have the model's patch shape ({n}, {n}), got {inp.heights.shape}"
                )
        if not inputs:
            return np.zeros(0, np.intp)
        gait = np.array([_gait_row(i.gait) for i in inputs])
        return self._choose(
            np.stack([i.heights for i in inputs]), np.array([i.hip_height_m for i in inputs]),
            np.stack([i.twist for i in inputs]), gait, np.array([int(i.leg) for i in inputs]),
        )  # fmt: skip

    def _choose(
        self, heights: NDArray[np.floating], hip_height_m: ArrayLike, twist: ArrayLike, gait: ArrayLike,
        legs: ArrayLike, workspace: _Workspace | None = None,
    ) -> NDArray[np.intp]:  # fmt: skip
        """The CNN's choices (B,) for the arrays of ``encode``: encoding, network, decode; into ``workspace``'s
        buffers when given (a call of 1-4 legs), else into new arrays. A ``canonical_legs`` network sees a
        right leg's tuple as its left mirror; its choice is mirrored back."""
        flip = None
        if self.net.config.canonical_legs:  # right legs go through the network as their left mirror
            heights, twist, legs, flip = canonical_inputs(heights, twist, legs)
        choices = self._decide(heights, hip_height_m, twist, gait, legs, workspace)
        return choices if flip is None else mirror_cell_index(choices, flip, self.net.config.encoding.cells)

    def _decide(
        self, heights: NDArray[np.floating], hip_height_m: ArrayLike, twist: ArrayLike, gait: ArrayLike,
        legs: ArrayLike, workspace: _Workspace | None,
    ) -> NDArray[np.intp]:  # fmt: skip
        """``_choose`` on the network's own frame: encoding, network, decode."""
        out = (workspace.image, workspace.scalars) if workspace is not None else None
        unknown = np.isnan(heights)
        image, scalars = encode(self.net.config.encoding, heights, hip_height_m, twist, gait, legs, out, unknown)
        logits, safe_logits = self._network_outputs(image, scalars, workspace)
        if safe_logits is None:  # the decode needs the optimum head alone
            return logits.argmax(axis=1).astype(np.intp)
        unknown = unknown.reshape(logits.shape)
        if workspace is not None and workspace.safe_logits_tensor is not None:  # the bound ORT output
            torch.sigmoid(workspace.safe_logits_tensor, out=workspace.probability_tensor)
            # our own arrays, of known shapes and types: the decode's checks are skipped
            return decode_unchecked(self.decode, logits, workspace.probability, unknown, self.net.config.encoding.cells)
        with torch.inference_mode():
            probability = torch.sigmoid(torch.from_numpy(safe_logits)).numpy()
        return decode(self.decode, logits, probability, unknown)

    def _network_outputs(
        self, image: NDArray[np.float32], scalars: NDArray[np.float32], workspace: _Workspace | None = None
    ) -> tuple[NDArray[np.float32], NDArray[np.float32] | None]:
        """(optimum logits (B, n*n), safe-mask logits (B, n*n) or None when the decode does not use them) from
        the backend in use: ONNX Runtime (bound to ``workspace``'s buffers when given), the torch fast path or
        the module's forward."""
        needs_safe = self.decode.needs_safe_head
        if self._ort_net is not None:
            if workspace is not None and workspace.binding is not None:
                logits, safe_logits = workspace.binding.run()
            else:
                logits, safe_logits = self._ort_net(image, scalars)
            return logits, safe_logits if needs_safe else None
        with torch.inference_mode():
            if self._fast_net is not None:
                out, safe = self._fast_net(torch.from_numpy(image), torch.from_numpy(scalars))
            else:
                pixels = torch.from_numpy(image).contiguous(memory_format=torch.channels_last)
                if needs_safe:
                    out, safe = self.net(pixels, torch.from_numpy(scalars))
                else:  # the optimum head alone is enough
                    out, safe = self.net.optimum_logits(pixels, torch.from_numpy(scalars)), None
            return out.numpy(), (safe.numpy() if needs_safe and safe is not None else None)

    def _workspace(self, batch: int) -> _Workspace | None:
        """The preallocated buffers of a call of ``batch`` legs (1 to 4; None for other sizes), made once."""
        if not 1 <= batch <= len(LEGS):
            return None
        workspace = self._workspaces.get(batch)
        if workspace is None:
            workspace = _Workspace(batch, self.net.config.encoding, self._ort_net)
            self._workspaces[batch] = workspace
        return workspace

    def is_safe(self, inp: FecInput, index: int) -> bool:
        """Exact FEC on one candidate: the candidate and every cell within the uncertainty margin are safe."""
        n = inp.heights.shape[0]
        rows, cols = index // n + self._margin[:, 0], index % n + self._margin[:, 1]
        inside = (rows >= 0) & (rows < n) & (cols >= 0) & (cols < n)  # cells off the patch are ignored
        cells = (rows * n + cols)[inside]
        return bool(self.evaluator.raw_safety(self.evaluator.prepare(inp), cells).all())

    # -- the VFA interface ----------------------------------------------------------------------------
    def select(
        self,
        leg: Leg,
        nominal_world: ArrayLike,
        grid: HeightMapGrid | None,
        *,
        hip_height_m: float,
        twist: ArrayLike,
        gait: GaitTiming,
        yaw: float | None = None,
        map_age_s: float = 0.0,
        liftoff_world: ArrayLike | None = None,
        hip_touchdown_world: ArrayLike | None = None,
    ) -> VfaResult:
        """As ``FootholdSelector.select`` (same arguments, frames and units), with g_hat: the result, checks and
        errors of ``select_legs`` for this one request, in the same order.

        Why a path of its own: ``select_legs``' lists, per-request loops and stacking cost ~10 us of a ~0.5 ms
        one-leg call (the ``vfa`` node decides a lone swinging leg this way)."""
        nominal = _vector(nominal_world, 3, "nominal_world")
        check_map_age(map_age_s, "VFA")
        leg = Leg(leg)
        status = map_status(grid, map_age_s, self.max_map_age_s)
        if status is not None:
            return VfaResult(leg, nominal, nominal.copy(), False, status, None, None)
        heading = patch_heading(grid, yaw)
        twist_array = check_motion_inputs(hip_height_m, twist, gait)
        s = self.evaluator.settings
        workspace = self._workspace(1)
        patches = extract_patches(grid, nominal[:2], heading, s.patch_cells, s.resolution_m, out=workspace.patches)
        _check_finite_or_unknown(patches)
        # one-row lists: encode converts them to float32 as it converts arrays (~2 us less than 3 np.array calls)
        choices = self._choose(patches, [hip_height_m], twist_array[None], [_gait_row(gait)], [int(leg)], workspace)
        self.counters.selections += 1
        request = (FootholdRequest(leg, nominal_world, hip_height_m, twist, gait, liftoff_world, hip_touchdown_world)
                   if self.verify else None)  # only the verification reads it  # fmt: skip
        return self._result(request, leg, patches[0], nominal, int(choices[0]), grid, heading, map_age_s)

    def select_legs(
        self, requests: Sequence[FootholdRequest], grid: HeightMapGrid | None, *, yaw: float | None = None,
        map_age_s: float = 0.0,
    ) -> list[VfaResult]:  # fmt: skip
        """g_hat for several legs on one map: one batched CNN pass (the VFA node's call, 4 legs).

        The patches, the network's inputs and outputs of a call of 1-4 legs live in buffers kept between
        calls (``_Workspace``): one call at a time per selector (not re-entrant)."""
        nominals = [_vector(r.nominal_world, 3, "nominal_world") for r in requests]
        check_map_age(map_age_s, "VFA")
        legs = [Leg(r.leg) for r in requests]
        status = map_status(grid, map_age_s, self.max_map_age_s)
        if status is not None:
            return [VfaResult(leg, nom, nom.copy(), False, status, None, None) for leg, nom in zip(legs, nominals)]
        heading = patch_heading(grid, yaw)
        if not requests:
            return []
        twist = np.stack([check_motion_inputs(r.hip_height_m, r.twist, r.gait) for r in requests])
        s = self.evaluator.settings
        workspace = self._workspace(len(requests))
        patches = extract_patches(
            grid, [nom[:2] for nom in nominals], heading, s.patch_cells, s.resolution_m,
            out=workspace.patches if workspace is not None else None,
        )  # fmt: skip
        _check_finite_or_unknown(patches)
        gait = np.array([_gait_row(r.gait) for r in requests])
        hip = np.array([r.hip_height_m for r in requests], dtype=float)
        choices = self._choose(patches, hip, twist, gait, np.array([int(leg) for leg in legs]), workspace)
        results = []
        for request, leg, patch, nominal, index in zip(requests, legs, patches, nominals, choices.tolist()):
            self.counters.selections += 1
            results.append(self._result(request, leg, patch, nominal, index, grid, heading, map_age_s))
        return results

    def _result(
        self, request: FootholdRequest | None, leg: Leg, patch: NDArray[np.floating], nominal: FloatArray, index: int,
        grid: HeightMapGrid, heading: float, map_age_s: float,
    ) -> VfaResult:  # fmt: skip
        """The VfaResult of the CNN's choice ``index`` on ``patch`` (n, n) [m], verified (and replaced by the
        exact g) if asked (``request``: the leg's inputs, needed only then)."""
        if self.verify:
            assert request is not None
            self.counters.verified += 1
            exact_inp = FecInput(leg, patch.astype(np.float64), request.hip_height_m, request.twist, request.gait)
            if request.liftoff_world is not None or request.hip_touchdown_world is not None:
                exact_inp = self._with_exact_extras(exact_inp, request, nominal, heading)
            if not self.is_safe(exact_inp, index):
                self.counters.rejected += 1
                return self.exact.select(
                    leg, nominal, grid, hip_height_m=request.hip_height_m, twist=request.twist, gait=request.gait,
                    yaw=heading, map_age_s=map_age_s, liftoff_world=request.liftoff_world,
                    hip_touchdown_world=request.hip_touchdown_world,
                )  # fmt: skip
        n = patch.shape[0]
        z = patch.item(index)  # float32 -> float: exact (the float64 patch held the same value)
        if not math.isfinite(z):  # an unknown cell is never a foothold
            return VfaResult(leg, nominal, nominal.copy(), False, VfaStatus.NO_SAFE_CANDIDATE, None, None)
        d_row, d_col = index // n - n // 2, index % n - n // 2
        resolution = self.evaluator.settings.resolution_m
        forward, left = d_row * resolution, d_col * resolution
        c, s = math.cos(heading), math.sin(heading)
        selected = np.array([nominal[0] + c * forward - s * left, nominal[1] + s * forward + c * left, z])
        return VfaResult(leg, nominal, selected, True, VfaStatus.SELECTED, None, (int(d_row), int(d_col)))

    @staticmethod
    def _with_exact_extras(inp: FecInput, request: FootholdRequest, nominal: FloatArray, heading: float) -> FecInput:
        """``inp`` with the given lift-off / hip-at-touchdown, rotated into the patch frame."""
        c, s = math.cos(heading), math.sin(heading)
        liftoff = hip_td = None
        if request.liftoff_world is not None:
            lo = _vector(request.liftoff_world, 3, "liftoff_world")
            dx, dy = lo[0] - nominal[0], lo[1] - nominal[1]
            liftoff = np.array([c * dx + s * dy, -s * dx + c * dy, lo[2]])
        if request.hip_touchdown_world is not None:
            hip = _vector(request.hip_touchdown_world, 2, "hip_touchdown_world")
            dx, dy = hip[0] - nominal[0], hip[1] - nominal[1]
            hip_td = np.array([c * dx + s * dy, -s * dx + c * dy])
        return FecInput(inp.leg, inp.heights, inp.hip_height_m, inp.twist, inp.gait, hip_td, liftoff)


def _vector(value: object, size: int, name: str) -> FloatArray:
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as error:
        raise PerceptionInputError(f"VFA: {name}: cannot convert to a float array ({error})") from None
    # math.isfinite on the few Python floats: ~1 us less than np.isfinite(array).all() (same test)
    if array.shape != (size,) or not all(map(math.isfinite, array.tolist())):
        raise PerceptionInputError(f"VFA: {name} must be {size} finite values, got {value!r}")
    return array


def _check_finite_or_unknown(patches: NDArray[np.floating]) -> None:
    """FecInput's check of the heights [m]: finite or NaN (unknown); a map may hold +-inf (the planner rejects
    it earlier)."""
    if _any(np.isinf(patches)):
        raise PerceptionInputError("FecInput.heights must be finite or NaN (unknown), got +-inf")


def _any(mask: NDArray[np.bool_]) -> bool:
    """``mask.any()`` without the Python layer of ndarray.any: ~1-3 us less per call in a one-leg call, where
    it runs on caches that the network's forward pass has just evicted."""
    return bool(np.logical_or.reduce(mask, axis=None))


def _gait_row(gait: GaitTiming) -> tuple[float, float, float, float]:
    """The ``gait`` row of ``encode``: step frequency [Hz], duty factor [-], time left [s], step height [m]."""
    return (gait.step_frequency_hz, gait.duty_factor, gait.swing_time_left_s, gait.step_height_m)


class _Workspace:
    """The buffers of ``select_legs`` calls of one batch size, made once per selector and reused: the patches,
    the network's inputs (``encode`` writes them), its outputs (ONNX Runtime writes them through an I/O
    binding) and the safe probabilities. Why: a call of 1-4 legs otherwise spends a good part of its
    Python time allocating and filling fresh arrays and ORT feeds."""

    def __init__(self, batch: int, cfg: EncodingConfig, ort_net: vfa_cnn_ort.OrtVfaNet | None) -> None:
        n = cfg.cells
        self.patches = np.empty((batch, n, n), np.float32)  # [m] world z, NaN unknown (the grid's float32)
        self.image = np.empty((batch, IMAGE_CHANNELS, n, n), np.float32)
        self.scalars = np.empty((batch, cfg.scalar_count), np.float32)
        self.probability = np.empty((batch, n * n), np.float32)
        self.probability_tensor = torch.from_numpy(self.probability)  # shares the memory
        self.binding = ort_net.bind(self.image, self.scalars) if ort_net is not None else None
        # a torch view of the bound safe-logit output: the sigmoid reads it and writes the probabilities in place
        safe_logits = self.binding.safe_logits if self.binding is not None else None
        self.safe_logits_tensor = torch.from_numpy(safe_logits) if safe_logits is not None else None


__all__ = [
    "ARCHITECTURES", "BACKENDS", "DEFAULT_WEIGHTS", "CnnFootholdSelector", "CnnVfaCounters", "EncodingConfig",
    "FootholdRequest", "NetConfig", "RoughnessFeatures", "VfaNet", "VfaUNet", "build_net", "encode", "load_model",
    "save_model", "store_decode", "stored_decode",
]  # fmt: skip
