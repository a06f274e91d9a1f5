"""Net2Net-style widening of a trained ``VfaUNet``: a network with more channels in some or all of its
convolutions (encoder widths ``channels``, decoder widths ``decoder_channels``, each a multiple of the old
width; the fully connected layer's width unchanged) that computes the same function, as the starting
weights of a fine-tuning run (``train_vfa --init-weights``).

    python -m tal_lab.vital.widen_vfa --weights tal_perception/tal_perception/models/vfa_cnn.pt \
        --decoder-channels 32 16 16 --out data/vfa_wide/vfa_cnn_widened.pt [--noise 0.01] [--seed 1]

Each channel of a layer widened k times is copied k times (new channel j is old channel j mod C); the
layers that read a copied channel divide its weights by k, so their sums are unchanged. Leaky ReLU,
max-pooling and nearest upsampling act per channel, so the widened network's outputs equal the original's
(float32 rounding aside). Copies would receive equal gradients and stay equal; ``--noise`` s adds Gaussian
noise of s x the layer's weight standard deviation to the incoming weights of every copy but the first
(the function then changes by about that relative amount), which lets the copies diverge in training.

``--roughness-features`` (``add_roughness_features``): the same network with ``NetConfig.roughness_features``
on, i.e. the last decoder layer also reads the fixed roughness statistics (``vfa_cnn.RoughnessFeatures``);
their incoming weights start at 0, so the function is unchanged until fine-tuning moves them.

``--head-blocks`` n (``deepen_head``): n more residual 1 x 1 blocks at full resolution
(``NetConfig.head_blocks``, x + LeakyReLU(W x + b) per candidate) with W = 0 and b = 0, so each block adds 0
and the function is unchanged; the gradient through LeakyReLU at 0 (its slope 0.01) moves them in training.
Plain torch, no ROS.
"""

from __future__ import annotations

import argparse
import logging
import sys
from dataclasses import replace
from pathlib import Path

import torch

from tal_perception.vfa_cnn import (
    IMAGE_CHANNELS,
    ROUGHNESS_CHANNELS,
    VfaUNet,
    build_net,
    load_model,
    save_model,
)

LOG = logging.getLogger("tal_lab.vital.widen_vfa")


def _tile(n: int, factor: int) -> torch.Tensor:
    """Old channel of each new channel: j mod n for j < factor * n."""
    return torch.arange(factor * n) % n


def _inputs(segments: list[tuple[int, int]]) -> tuple[torch.Tensor, torch.Tensor]:
    """For a layer reading a concatenation of segments (old width, widening factor): the old input index of
    each new input and the factor its weight is divided by (the segment's factor)."""
    index, divide, start = [], [], 0
    for width, factor in segments:
        index.append(start + _tile(width, factor))
        divide.append(torch.full((factor * width,), float(factor)))
        start += width
    return torch.cat(index), torch.cat(divide)


def _factors(old: tuple[int, ...], new: tuple[int, ...], name: str) -> list[int]:
    if len(new) != len(old) or any(n < o or n % o for o, n in zip(old, new)):
        raise ValueError(f"widen_unet: {name} {new} must be multiples of {old}, one per layer")
    return [n // o for o, n in zip(old, new)]


def widen_unet(
    net: VfaUNet, channels: tuple[int, int, int], decoder_channels: tuple[int, int, int], noise: float = 0.0,
    seed: int = 1,
) -> VfaUNet:  # fmt: skip
    """A ``VfaUNet`` with the given widths computing ``net``'s function (see the module docstring); ``noise``
    > 0 perturbs the copies' incoming weights. ``net`` is not changed."""
    if not isinstance(net, VfaUNet):
        raise ValueError("widen_unet needs a VfaUNet")
    cfg = net.config
    c1, c2, c3 = cfg.channels
    d3, d2, d1 = cfg.decoder_channels
    f1, f2, f3 = _factors(cfg.channels, tuple(channels), "channels")
    g3, g2, g1 = _factors(cfg.decoder_channels, tuple(decoder_channels), "decoder_channels")
    if cfg.head_blocks and g1 != 1:
        raise ValueError("widen_unet: the last decoder layer of a network with head blocks cannot be widened")
    # every other setting (hidden width, heads, feature options, head blocks) carries over
    wide = build_net(replace(cfg, channels=tuple(channels), decoder_channels=tuple(decoder_channels)))
    assert isinstance(wide, VfaUNet)
    old = {k: v.detach().to(torch.float32) for k, v in net.state_dict().items()}
    new: dict[str, torch.Tensor] = {}
    generator = torch.Generator().manual_seed(seed)

    def conv(name: str, out: int, factor: int, segments: list[tuple[int, int]]) -> None:
        w, b = old[f"{name}.weight"], old[f"{name}.bias"]
        out_index = _tile(out, factor)
        in_index, divide = _inputs(segments)
        weight = w[out_index][:, in_index] / divide.view(1, -1, *([1] * (w.dim() - 2)))
        if noise > 0.0 and factor > 1:
            copies = torch.arange(weight.shape[0]) >= out  # every copy but the first
            perturbation = torch.randn(weight.shape, generator=generator) * (noise * float(w.std()))
            weight = weight + perturbation * copies.view(-1, *([1] * (w.dim() - 1)))
        new[f"{name}.weight"], new[f"{name}.bias"] = weight.contiguous(), b[out_index].clone()

    conv("encoders.0", c1, f1, [(IMAGE_CHANNELS, 1)])
    conv("encoders.1", c2, f2, [(c1, f1)])
    conv("encoders.2", c3, f3, [(c2, f2)])
    cells = wide.sizes[3] ** 2
    # context.0 reads the flattened (c3, 5, 5) features (channel-major) and the scalars; context.2 writes them
    w, b = old["context.0.weight"], old["context.0.bias"]
    scalars = w.shape[1] - c3 * cells
    feature_index = (_tile(c3, f3)[:, None] * cells + torch.arange(cells)[None, :]).reshape(-1)
    in_index = torch.cat([feature_index, c3 * cells + torch.arange(scalars)])
    divide = torch.cat([torch.full((f3 * c3 * cells,), float(f3)), torch.ones(scalars)])
    new["context.0.weight"], new["context.0.bias"] = (w[:, in_index] / divide).contiguous(), b.clone()
    w, b = old["context.2.weight"], old["context.2.bias"]
    new["context.2.weight"], new["context.2.bias"] = w[feature_index].contiguous(), b[feature_index].clone()
    conv("decoders.0", d3, g3, [(c3, f3), (c3, f3), (c3, f3)])
    conv("decoders.1", d2, g2, [(d3, g3), (c2, f2)])
    conv("decoders.2", d1, g1, [(d2, g2), (c1, f1), (cfg.image_channels, 1)])
    rows = torch.cat([_tile(d3, g3), d3 + _tile(d2, g2), d3 + d2 + _tile(d1, g1)])
    new["scalar_bias.weight"] = old["scalar_bias.weight"][rows].contiguous()
    new["scalar_bias.bias"] = old["scalar_bias.bias"][rows].clone()
    for i in range(cfg.head_blocks):  # the last decoder layer keeps its width: copied unchanged
        new[f"head.{i}.weight"], new[f"head.{i}.bias"] = old[f"head.{i}.weight"], old[f"head.{i}.bias"]
    conv("output", old["output.weight"].shape[0], 1, [(d1, g1)])
    wide.load_state_dict(new)
    wide.eval()
    return wide


def add_roughness_features(net: VfaUNet) -> VfaUNet:
    """``net`` with ``roughness_features`` on and the same function: every weight copied, the last decoder
    layer's weights from the new roughness channels zero (they sit between the image's unknown mask and its
    coordinate channels, see ``VfaUNet.forward``)."""
    if not isinstance(net, VfaUNet) or net.config.roughness_features:
        raise ValueError("add_roughness_features needs a VfaUNet without the roughness features")
    new_net = build_net(replace(net.config, roughness_features=True))
    assert isinstance(new_net, VfaUNet)
    state = {k: v.detach().to(torch.float32).clone() for k, v in net.state_dict().items()}
    w = state["decoders.2.weight"]  # inputs: upsampled, skip, image (height, unknown, row, column)
    split = w.shape[1] - (IMAGE_CHANNELS - 2)  # before the coordinate channels
    zeros = torch.zeros(w.shape[0], ROUGHNESS_CHANNELS, *w.shape[2:])
    state["decoders.2.weight"] = torch.cat([w[:, :split], zeros, w[:, split:]], dim=1).contiguous()
    new_net.load_state_dict(state)
    new_net.eval()
    return new_net


def deepen_head(net: VfaUNet, blocks: int) -> VfaUNet:
    """``net`` with ``blocks`` more residual 1 x 1 head blocks, zero-initialised (the same function)."""
    if not isinstance(net, VfaUNet) or blocks < 1:
        raise ValueError(f"deepen_head needs a VfaUNet and blocks >= 1, got {type(net).__name__} and {blocks}")
    old_blocks = net.config.head_blocks
    deep = build_net(replace(net.config, head_blocks=old_blocks + blocks))
    assert isinstance(deep, VfaUNet)
    state = {k: v.detach().to(torch.float32).clone() for k, v in net.state_dict().items()}
    for i in range(old_blocks, old_blocks + blocks):
        state[f"head.{i}.weight"] = torch.zeros_like(deep.head[i].weight)
        state[f"head.{i}.bias"] = torch.zeros_like(deep.head[i].bias)
    deep.load_state_dict(state)
    deep.eval()
    return deep


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="[widen_vfa] %(message)s")
    parser = argparse.ArgumentParser(prog="python -m tal_lab.vital.widen_vfa", description=__doc__.split("\n\n")[0])
    parser.add_argument("--weights", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--channels", type=int, nargs=3, default=None, help="encoder widths (default: unchanged)")
    parser.add_argument("--decoder-channels", type=int, nargs=3, default=None,
                        help="decoder widths at 9, 17 and 33 cells (default: unchanged)")  # fmt: skip
    parser.add_argument("--noise", type=float, default=0.01, help="relative noise on the copies' incoming weights")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--roughness-features", action="store_true",
                        help="also turn on the roughness features (zero weights: the same function)")  # fmt: skip
    parser.add_argument("--head-blocks", type=int, default=0,
                        help="add this many residual 1 x 1 head blocks (zero weights: the same function)")  # fmt: skip
    args = parser.parse_args(argv)
    net = load_model(args.weights)
    if not isinstance(net, VfaUNet):
        raise SystemExit(f"{args.weights}: not a VfaUNet")
    channels = tuple(args.channels or net.config.channels)
    decoder_channels = tuple(args.decoder_channels or net.config.decoder_channels)
    wide = widen_unet(net, channels, decoder_channels, args.noise, args.seed)  # type: ignore[arg-type]
    if args.roughness_features:
        wide = add_roughness_features(wide)
    if args.head_blocks:
        wide = deepen_head(wide, args.head_blocks)
    save_model(wide, args.out, {"widened_from": str(args.weights), "noise": args.noise, "seed": args.seed,
                                "roughness_features_added": bool(args.roughness_features),
                                "head_blocks_added": args.head_blocks, "decode": net.decode.to_dict()})  # fmt: skip
    before, after = net.config, wide.config
    LOG.info("%s: channels %s, decoder %s, head blocks %d -> %s, %s, %d (%d parameters)", args.out,
             before.channels, before.decoder_channels, before.head_blocks, after.channels, after.decoder_channels,
             after.head_blocks, sum(p.numel() for p in wide.parameters()))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
