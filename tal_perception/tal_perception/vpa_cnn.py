"""CNN of the VPA: the RBF weights of a leg's NSF curve from its heightmap and the body twist.

Thesis (implementation details): the 33 x 33 heightmap passes through three 5 x 5 convolutions
(padding 2, Leaky ReLU, 2 x 2 max-pooling); the body velocities pass through a fully connected layer
with Leaky ReLU; both are concatenated and two fully connected layers (Leaky ReLU, then linear) give the
E RBF weights; the loss is the mean squared error between the NSF rebuilt from the predicted weights
and the exact one. Our additions, because the thesis leaves them open: a second input channel marks
unknown cells (NaN cannot enter a convolution, and unknown cells must count as unsafe), the heights are
relative to the map's reference height (median of the known cells, as in the exact evaluation), and the
leg (one-hot) joins the twist, so one network serves the four legs. The NSF is normalised by the number
of cells of the patch (F in [0, 1]).

Units: heights [m]; twist inputs vx, vy [m/s] and yaw rate [rad/s] in the horizontal frame.
"""

from __future__ import annotations

import json
import pickle
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from numpy.typing import NDArray
from torch import nn

from tal_core.legs import Leg
from tal_perception.errors import VpaModelError
from tal_perception.vpa_evaluation import map_reference_height

FloatArray = NDArray[np.float64]
MODELS_DIR = Path(__file__).resolve().parent / "models"
DEFAULT_WEIGHTS = MODELS_DIR / "vpa_cnn.pt"
UNKNOWN_FILL_M = 0.0  # [m] relative height written into unknown cells (the mask channel says they are unknown)


@dataclass(frozen=True)
class VpaNetConfig:
    """Layer sizes of ``VpaNet`` (stored with the weights so a file always rebuilds its own network)."""

    cells: int = 33
    channels: tuple[int, int, int] = (8, 16, 32)
    twist_features: int = 32
    hidden: int = 128
    rbf_count: int = 30


class VpaNet(nn.Module):
    """Heightmap (+ unknown mask) and (twist, leg) -> E RBF weights (thesis architecture, see module)."""

    def __init__(self, config: VpaNetConfig) -> None:
        super().__init__()
        self.config = config
        layers: list[nn.Module] = []
        size, previous = config.cells, 2
        for channels in config.channels:
            layers += [nn.Conv2d(previous, channels, 5, padding=2), nn.LeakyReLU(), nn.MaxPool2d(2)]
            previous, size = channels, size // 2
        self.features = nn.Sequential(*layers, nn.Flatten())
        self.twist = nn.Sequential(nn.Linear(3 + 4, config.twist_features), nn.LeakyReLU())
        self.head = nn.Sequential(
            nn.Linear(previous * size * size + config.twist_features, config.hidden),
            nn.LeakyReLU(),
            nn.Linear(config.hidden, config.rbf_count),
        )

    def forward(self, maps: torch.Tensor, twist_leg: torch.Tensor) -> torch.Tensor:
        """maps (B, 2, cells, cells), twist_leg (B, 7) -> weights (B, E)."""
        return self.head(torch.cat([self.features(maps), self.twist(twist_leg)], dim=1))


def encode_maps(heights: FloatArray) -> tuple[NDArray[np.float32], FloatArray]:
    """Network input (B, 2, n, n) float32 and the references (B,) [m] of maps (B, n, n) [m] world z."""
    heights = np.asarray(heights, dtype=float)
    references = np.array([map_reference_height(h) for h in heights])
    unknown = np.isnan(heights)
    relative = np.where(unknown, UNKNOWN_FILL_M, heights - np.nan_to_num(references)[:, None, None])
    return np.stack([relative, unknown], axis=1).astype(np.float32), references


def encode_twist_leg(twists: FloatArray, legs: NDArray[np.int64]) -> NDArray[np.float32]:
    """(B, 7) float32: vx, vy [m/s], yaw rate [rad/s] (horizontal frame) and the leg one-hot."""
    twists = np.asarray(twists, dtype=float)
    one_hot = np.eye(4)[np.asarray(legs, dtype=np.int64)]
    return np.concatenate([twists[:, [0, 1, 5]], one_hot], axis=1).astype(np.float32)


class CnnNsfModel:
    """Loaded VPA CNN: predicts the normalised-NSF RBF weights of a batch of leg maps (CPU, 1 thread)."""

    def __init__(self, net: VpaNet, metadata: dict[str, object]) -> None:
        self.net = net.eval()
        self.metadata = metadata

    @classmethod
    def load(cls, path: str | Path = DEFAULT_WEIGHTS) -> CnnNsfModel:
        """Load a weights file written by ``save`` (``VpaModelError`` if missing or corrupt)."""
        path = Path(path)
        if not path.is_file():
            raise VpaModelError(f"VPA CNN weights not found: {path}")
        try:
            blob = torch.load(path, map_location="cpu", weights_only=True)
            config = VpaNetConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in blob["config"].items()})
            net = VpaNet(config)
            net.load_state_dict({k: v.float() for k, v in blob["state"].items()})
            metadata = json.loads(blob["metadata"])
        except (KeyError, TypeError, RuntimeError, ValueError, EOFError, pickle.UnpicklingError) as error:
            raise VpaModelError(f"VPA CNN weights {path} are corrupt or of another network: {error}") from None
        return cls(net, metadata)

    def save(self, path: str | Path) -> None:
        """Write config, float16 weights (halves the file; the error is far below the fit error) and
        metadata (settings the network was trained with)."""
        state = {k: v.detach().to(torch.float16) for k, v in self.net.state_dict().items()}
        blob = {"config": asdict(self.net.config), "state": state, "metadata": json.dumps(self.metadata)}
        torch.save(blob, Path(path))

    def check(self, rbf_count: int, cells: int) -> None:
        """``VpaModelError`` unless the network outputs ``rbf_count`` weights for ``cells`` maps."""
        config = self.net.config
        if config.rbf_count != rbf_count or config.cells != cells:
            raise VpaModelError(
                f"VPA CNN was built for E = {config.rbf_count}, {config.cells} x {config.cells} maps; the "
                f"settings need E = {rbf_count}, {cells} x {cells}"
            )

    def predict(self, legs: list[Leg], heights: FloatArray, twists: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Weights (B, E) of the normalised NSF and map references (B,) [m] for maps (B, n, n) [m]."""
        maps, references = encode_maps(heights)
        extra = encode_twist_leg(np.asarray(twists, dtype=float), np.array([int(leg) for leg in legs]))
        with torch.inference_mode():
            weights = self.net(torch.from_numpy(maps), torch.from_numpy(extra)).numpy().astype(float)
        weights[np.isnan(references)] = 0.0  # nothing known: no safe foothold
        return weights, references
