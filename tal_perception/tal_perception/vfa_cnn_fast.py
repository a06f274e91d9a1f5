"""Inference-only form of ``vfa_cnn.VfaUNet``: the same weights and the same function, rearranged for speed.

``FastVfaUNet(net)`` computes what ``net(image, scalars)`` computes (up to float32 rounding: sums are
taken in another order, ~1e-6 relative on the logits), with these exact rewrites:

* the CoordConv channels 2 and 3 of the image are the same for every sample: their contribution to
  the first encoder convolution (plus its bias) and to the last decoder convolution is a constant map
  computed once, so those two convolutions only read channels 0 and 1 (height, unknown mask);
* everything that depends only on the scalars (their part of the context layer, the per-sample decoder
  biases, plus the decoders' own biases) is one small matrix product;
* the context layer reads the pooled 5 x 5 features in channels-last order (its weight columns and the
  second layer's rows permuted accordingly), so no concatenation and no layout copy is needed;
* the 1 x 1 output convolution is one matrix product;
* weights are float32 copies made once (the file stores float16), convolutions run channels-last.

``compile_fast_unet(net)`` traces and freezes it with TorchScript (no Python per layer at call time).
Measured with ``python bench/bench_vfa_cnn.py`` (one torch thread): see ``docs/models/VFA_CARD.md``.
Plain torch, no ROS.
"""

from __future__ import annotations

from typing import Protocol

import torch
from torch import nn
from torch.nn import functional as fn

COORD_CHANNELS = 2  # image channels 2, 3: row and column offset of the cell (constant per configuration)


class UNetLike(Protocol):
    """What ``FastVfaUNet`` reads of a ``vfa_cnn.VfaUNet`` (kept structural: no import cycle)."""

    encoders: nn.ModuleList
    decoders: nn.ModuleList
    context: nn.Sequential
    scalar_bias: nn.Linear
    head: nn.ModuleList
    output: nn.Conv2d
    act: nn.LeakyReLU
    sizes: list[int]

    def state_dict(self) -> dict[str, torch.Tensor]: ...


def coordinate_channels(cells: int) -> torch.Tensor:
    """The image's channels 2 and 3 (1, 2, n, n): row and column offset from the centre in [-1, 1]
    (as ``vfa_cnn.encode``; float32, computed the same way so the values are bit-identical)."""
    offsets = (torch.arange(cells, dtype=torch.float32) - cells // 2) / (cells // 2)
    rows, cols = torch.meshgrid(offsets, offsets, indexing="ij")
    return torch.stack([rows, cols])[None]


def _channels_last(t: torch.Tensor) -> torch.Tensor:
    return t.contiguous(memory_format=torch.channels_last)


class FastVfaUNet(nn.Module):
    """``VfaUNet.forward`` rearranged for inference (see the module docstring); no training.

    forward(image (B, 4, n, n), scalars (B, S)) -> (optimum logits (B, n*n), safe-mask logits (B, n*n)):
    the inputs of ``encode`` and the outputs of ``VfaUNet``; the network must have the safe-mask head (the
    committed weights do). Only image channels 0 and 1 are read: channels 2 and 3 are the coordinate
    channels of ``encode`` by construction. The weights are copied at construction (later changes of
    ``net`` are not seen).
    """

    def __init__(self, net: UNetLike, cells: int) -> None:
        super().__init__()
        if net.output.out_channels != 2:
            raise ValueError("FastVfaUNet needs a VfaUNet with the safe-mask head (2 output channels)")
        sd = {k: v.detach().to(torch.float32).clone() for k, v in net.state_dict().items()}
        self.slope = float(net.act.negative_slope)
        self.sizes = [int(s) for s in net.sizes]  # 33, 17, 9, 5
        coords = coordinate_channels(cells)
        image_channels = net.encoders[0].in_channels
        keep = image_channels - COORD_CHANNELS  # height, unknown mask

        w, b = sd["encoders.0.weight"], sd["encoders.0.bias"]
        pad0 = net.encoders[0].padding[0]
        self.enc0_weight = _channels_last(w[:, :keep])
        self.enc0_const = _channels_last(fn.conv2d(coords, w[:, keep:], b, padding=pad0))  # (1, c1, n, n)
        self.enc1_weight, self.enc1_bias = _channels_last(sd["encoders.1.weight"]), sd["encoders.1.bias"]
        self.enc2_weight, self.enc2_bias = _channels_last(sd["encoders.2.weight"]), sd["encoders.2.bias"]
        self.enc_padding = [int(c.padding[0]) for c in net.encoders]

        c3, s3 = int(sd["encoders.2.weight"].shape[0]), self.sizes[3]
        bottleneck = c3 * s3 * s3
        w1, b1 = sd["context.0.weight"], sd["context.0.bias"]
        self.hidden = int(w1.shape[0])
        # columns of the pooled features in (h, w, c) order instead of (c, h, w)
        self.ctx0_weight_t = w1[:, :bottleneck].reshape(-1, c3, s3, s3).permute(0, 2, 3, 1).reshape(-1, bottleneck)
        self.ctx0_weight_t = self.ctx0_weight_t.t().contiguous()  # (bottleneck, hidden)
        w2, b2 = sd["context.2.weight"], sd["context.2.bias"]
        self.ctx1_weight_t = w2.reshape(c3, s3, s3, -1).permute(1, 2, 0, 3).reshape(bottleneck, -1).t().contiguous()
        self.ctx1_bias = b2.reshape(c3, s3, s3).permute(1, 2, 0).reshape(-1).contiguous()
        self.c3, self.s3 = c3, s3

        # everything the scalars feed: the context layer's scalar columns and the decoders' biases
        self.dec_channels = [int(d.out_channels) for d in net.decoders]
        decoder_bias = torch.cat([sd[f"decoders.{i}.bias"] for i in range(len(net.decoders))])
        self.scalar_weight_t = torch.cat([w1[:, bottleneck:], sd["scalar_bias.weight"]]).t().contiguous()
        self.scalar_bias = torch.cat([b1, sd["scalar_bias.bias"] + decoder_bias])

        self.dec0_weight = _channels_last(sd["decoders.0.weight"])
        self.dec1_weight = _channels_last(sd["decoders.1.weight"])
        w = sd["decoders.2.weight"]  # inputs: upsampled features, skip, image (coordinate channels last)
        self.dec2_weight = _channels_last(w[:, : w.shape[1] - COORD_CHANNELS])
        self.dec2_const = _channels_last(fn.conv2d(coords, w[:, w.shape[1] - COORD_CHANNELS :], padding=1))
        self.head_weights = [_channels_last(sd[f"head.{i}.weight"]) for i in range(len(net.head))]
        self.head_biases = [sd[f"head.{i}.bias"] for i in range(len(net.head))]
        self.out_weight = sd["output.weight"].reshape(sd["output.weight"].shape[0], -1).contiguous()  # (2, d1)
        self.out_bias = sd["output.bias"][:, None].contiguous()  # (2, 1)
        self.keep = keep

    @staticmethod
    def _up(x: torch.Tensor, size: int) -> torch.Tensor:
        """Nearest 2x upsampling cropped to ``size`` (as ``VfaUNet._up``)."""
        return fn.interpolate(x, scale_factor=2.0, mode="nearest")[:, :, :size, :size]

    def forward(self, image: torch.Tensor, scalars: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(optimum logits (B, n*n), safe-mask logits (B, n*n)), row-major candidates (image in any layout)."""
        b = image.shape[0]
        slope = self.slope
        from_scalars = torch.addmm(self.scalar_bias, scalars, self.scalar_weight_t)
        hidden_bias = from_scalars[:, : self.hidden]
        bias0, bias1, bias2 = torch.split(from_scalars[:, self.hidden :], self.dec_channels, dim=1)
        pixels = image[:, : self.keep].contiguous(memory_format=torch.channels_last)
        skip0 = fn.conv2d(pixels, self.enc0_weight, None, padding=self.enc_padding[0])
        skip0 = fn.leaky_relu(skip0 + self.enc0_const, slope)
        x = fn.max_pool2d(skip0, 2, ceil_mode=True)
        skip1 = fn.leaky_relu(fn.conv2d(x, self.enc1_weight, self.enc1_bias, padding=self.enc_padding[1]), slope)
        x = fn.max_pool2d(skip1, 2, ceil_mode=True)
        skip2 = fn.leaky_relu(fn.conv2d(x, self.enc2_weight, self.enc2_bias, padding=self.enc_padding[2]), slope)
        x = fn.max_pool2d(skip2, 2, ceil_mode=True)  # (B, c3, 5, 5), channels-last
        hidden = torch.addmm(hidden_bias, x.permute(0, 2, 3, 1).reshape(b, -1), self.ctx0_weight_t)
        hidden = fn.leaky_relu(hidden, slope)
        context = fn.leaky_relu(torch.addmm(self.ctx1_bias, hidden, self.ctx1_weight_t), slope)
        context = context.reshape(b, self.s3, self.s3, self.c3).permute(0, 3, 1, 2)
        x = self._up(torch.cat([x, context], dim=1), self.sizes[2])
        x = fn.conv2d(torch.cat([x, skip2], 1), self.dec0_weight, None, padding=1)
        x = self._up(fn.leaky_relu(x + bias0[:, :, None, None], slope), self.sizes[1])
        x = fn.conv2d(torch.cat([x, skip1], 1), self.dec1_weight, None, padding=1)
        x = fn.leaky_relu(x + bias1[:, :, None, None], slope)
        x = self._up(x, self.sizes[0])
        x = fn.conv2d(torch.cat([x, skip0, pixels], 1), self.dec2_weight, None, padding=1)
        x = fn.leaky_relu(x + (self.dec2_const + bias2[:, :, None, None]), slope)  # (B, d1, n, n)
        for weight, bias in zip(self.head_weights, self.head_biases):
            x = x + fn.leaky_relu(fn.conv2d(x, weight, bias), slope)
        out = torch.mm(self.out_weight, x.permute(0, 2, 3, 1).reshape(-1, x.shape[1]).t()) + self.out_bias
        out = out.reshape(out.shape[0], b, -1)  # (2, B, n*n)
        return out[0], out[1]


def compile_fast_unet(net: UNetLike, cells: int, example_batch: int = 4) -> torch.jit.ScriptModule:
    """``FastVfaUNet(net)`` traced with an example batch and frozen (TorchScript); any batch size works
    (the trace keeps the batch dimension symbolic). Call under ``torch.inference_mode()``."""
    fast = FastVfaUNet(net, cells).eval()
    image = torch.zeros(example_batch, net.encoders[0].in_channels, cells, cells)
    scalars = torch.zeros(example_batch, net.scalar_bias.in_features)
    with torch.inference_mode():
        traced = torch.jit.trace(fast, (image, scalars), check_trace=False)
        return torch.jit.freeze(traced)


__all__ = ["FastVfaUNet", "compile_fast_unet", "coordinate_channels"]
