"""ONNX Runtime inference path of the VFA CNN (``vfa_cnn.VfaUNet`` / ``VfaNet``): the same weights and
the same function, run by ONNX Runtime's CPU kernels instead of PyTorch's.

Why: the network is tiny (channels 8/16/32), so with PyTorch a forward pass is dominated by per-operator
overhead; ONNX Runtime (graph optimisation level "all") fuses each convolution with its Leaky ReLU and
runs the convolutions in its blocked channel layout (NCHWc), with less overhead per operator.

``export_onnx(net)`` exports the module's own forward (``VfaUNet.forward`` / ``VfaNet.forward``, in
float32) with PyTorch's TorchScript-based exporter (``dynamo=False``; needs the ``onnx`` package) into
memory, with a symbolic batch dimension; nothing is written to disk and nothing is downloaded.
``OrtVfaNet(net)`` is an ONNX Runtime session on it (one intra-op thread, sequential execution, all graph
optimisations) that takes and returns numpy arrays: ``(image (B, 4, n, n), scalars (B, S)) -> (optimum
logits (B, n*n), safe-mask logits (B, n*n) or None)``, like the network. Only float32 summation order
differs from the torch forward (~1e-6 relative on the logits).

``available()`` says whether both ``onnxruntime`` and ``onnx`` import; ``CnnFootholdSelector`` falls back
to its torch path when they do not. The rearranged ``vfa_cnn_fast.FastVfaUNet`` is not what is exported:
under ONNX Runtime it measured slower than the plain graph (its constant-folded coordinate maps and
channels-last matrix products break the fusions). Plain numpy + torch (export) + onnxruntime, no ROS.
"""

from __future__ import annotations

import importlib.util
import io
import warnings
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray
from torch import nn

ONNX_OPSET = 17


def available() -> bool:
    """True when ``onnxruntime`` (to run) and ``onnx`` (torch's exporter needs it) can be imported."""
    return all(importlib.util.find_spec(name) is not None for name in ("onnxruntime", "onnx"))


class _Outputs(nn.Module):
    """The network's forward with a fixed number of outputs (ONNX has no None): both heads, or the
    optimum head alone for a network without the safe head."""

    def __init__(self, net: nn.Module, safe_head: bool) -> None:
        super().__init__()
        self.net = net
        self.safe_head = safe_head

    def forward(self, image: torch.Tensor, scalars: torch.Tensor) -> tuple[torch.Tensor, ...]:
        logits, safe_logits = self.net(image, scalars)
        return (logits, safe_logits) if self.safe_head else (logits,)


def export_onnx(net: nn.Module, example_batch: int = 4) -> bytes:
    """The ONNX model (serialised bytes) of ``net``'s forward in float32, batch dimension symbolic.

    ``net`` is a ``VfaUNet`` or ``VfaNet`` (anything with ``config.encoding`` and ``config.safe_head``);
    it is not changed (a float32 copy of the weights is exported)."""
    config = net.config  # type: ignore[attr-defined]
    cells, scalar_count = config.encoding.cells, config.encoding.scalar_count
    image_channels = 4
    module = _Outputs(net, bool(config.safe_head))
    image = torch.zeros(example_batch, image_channels, cells, cells)
    scalars = torch.zeros(example_batch, scalar_count)
    outputs = ["logits", "safe_logits"] if config.safe_head else ["logits"]
    axes = {name: {0: "batch"} for name in ("image", "scalars", *outputs)}
    buffer = io.BytesIO()
    state = module.training
    module.eval()
    try:
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation notice
            torch.onnx.export(
                module, (image, scalars), buffer, dynamo=False, input_names=["image", "scalars"],
                output_names=outputs, dynamic_axes=axes, opset_version=ONNX_OPSET, do_constant_folding=True,
            )  # fmt: skip
    finally:
        module.train(state)
    return buffer.getvalue()


def session_options() -> Any:
    """One intra-op thread (the node's budget is one core), sequential execution, all graph optimisations,
    no spinning worker threads."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    options.log_severity_level = 3  # errors only
    return options


class OrtVfaNet:
    """An ONNX Runtime session computing ``net``'s forward (see the module docstring); the weights are
    exported once here, so later changes of ``net`` are not seen."""

    def __init__(self, net: nn.Module) -> None:
        import onnxruntime as ort

        self.safe_head = bool(net.config.safe_head)  # type: ignore[attr-defined]
        self.model_bytes = export_onnx(net)
        self.session = ort.InferenceSession(self.model_bytes, session_options(), providers=["CPUExecutionProvider"])

    def __call__(
        self, image: NDArray[np.float32], scalars: NDArray[np.float32]
    ) -> tuple[NDArray[np.float32], NDArray[np.float32] | None]:
        """(optimum logits (B, n*n), safe-mask logits (B, n*n) or None) for float32 inputs of ``encode``."""
        feed = {"image": np.ascontiguousarray(image, np.float32), "scalars": np.ascontiguousarray(scalars, np.float32)}
        outputs = self.session.run(None, feed)
        return outputs[0], (outputs[1] if self.safe_head else None)


__all__ = ["ONNX_OPSET", "OrtVfaNet", "available", "export_onnx", "session_options"]
