"""ONNX Runtime inference path of the VFA CNN (``vfa_cnn.VfaUNet`` / ``VfaNet``): the same weights and
the same function, run by ONNX Runtime's CPU kernels instead of PyTorch's.

Why: the network is tiny (channels 8/16/32), so with PyTorch a forward pass is dominated by per-operator
overhead; ONNX Runtime (graph optimisation level "all") fuses each convolution with its Leaky ReLU and
runs the convolutions in its blocked channel layout (NCHWc), with less overhead per operator.

``export_onnx(net)`` exports the module's own forward (``VfaUNet.forward`` / ``VfaNet.forward``, in
float32) with PyTorch's TorchScript-based exporter (``dynamo=False``; needs the ``onnx`` package) into
memory, with a symbolic batch dimension; nothing is written to disk and nothing is downloaded. It then
rewrites the graph where ONNX Runtime is slow and the outputs stay bit-identical (``rewrite_graph``: the
exporter's per-axis Slice / Unsqueeze pairs merged, the LeakyRelus not fused into a convolution as
Max(x, alpha * x)). ``OrtVfaNet(net)`` is an ONNX Runtime session on it (one intra-op thread, sequential
execution, all graph optimisations) that takes and returns numpy arrays: ``(image (B, 4, n, n), scalars
(B, S)) -> (optimum logits (B, n*n), safe-mask logits (B, n*n) or None)``, like the network. Only float32
summation order differs from the torch forward (~1e-6 relative on the logits).

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
    return rewrite_graph(buffer.getvalue())


def rewrite_graph(model_bytes: bytes) -> bytes:
    """The ONNX model ``model_bytes`` with two rewrites that keep every output bit for bit and that ONNX Runtime
    runs faster (a one-leg forward pass of the shipped VfaUNet: ~40 us less of ~0.39 ms):
    ``_merge_pairs`` (Slice / Unsqueeze pairs) and ``_leaky_relus_as_max`` (the LeakyRelus not fused into a
    convolution)."""
    import onnx

    model = onnx.load_from_string(model_bytes)
    _merge_pairs(model.graph)
    _leaky_relus_as_max(model.graph)
    onnx.checker.check_model(model)
    return model.SerializeToString()


def _merge_pairs(graph: Any) -> None:
    """Merge each Slice -> Slice and Unsqueeze -> Unsqueeze pair of ``graph`` (an onnx GraphProto, changed in
    place) into one node (the second node the first one's only consumer, both with constant parameters, Slices
    on different axes, non-negative axes). Pure data movement: the outputs are bit-identical.

    Why: the exporter writes ``x[:, :, :s, :s]`` (``VfaUNet._up``) as one Slice per axis and
    ``bias[:, :, None, None]`` as one Unsqueeze per axis; each node is a kernel call for ONNX Runtime and each
    Slice a copy (~15 us of a one-leg forward pass)."""
    import onnx
    from onnx import numpy_helper

    constants = {t.name: numpy_helper.to_array(t) for t in graph.initializer}
    constants |= {n.output[0]: numpy_helper.to_array(n.attribute[0].t) for n in graph.node
                  if n.op_type == "Constant" and n.attribute and n.attribute[0].name == "value"}  # fmt: skip
    nodes = list(graph.node)
    consumers: dict[str, list[int]] = {}
    for index, node in enumerate(nodes):
        for name in node.input:
            consumers.setdefault(name, []).append(index)
    graph_outputs = {o.name for o in graph.output}

    def constant(name: str) -> list[int] | None:
        return constants[name].reshape(-1).tolist() if name in constants else None

    def initializer(values: list[int]) -> str:
        name = f"merged_{len(graph.initializer)}"
        graph.initializer.append(numpy_helper.from_array(np.array(values, np.int64), name))
        return name

    dropped: set[int] = set()  # indices of the second nodes of merged pairs
    for index, node in enumerate(nodes):
        if node.op_type not in ("Slice", "Unsqueeze") or index in dropped or node.output[0] in graph_outputs:
            continue
        users = consumers.get(node.output[0], [])
        if len(users) != 1 or nodes[users[0]].op_type != node.op_type:
            continue
        second = nodes[users[0]]
        first_params = [constant(name) for name in node.input[1:]]
        second_params = [constant(name) for name in second.input[1:]]
        if not first_params or not second_params or any(p is None for p in first_params + second_params):
            continue
        if node.op_type == "Unsqueeze":  # axes index the output: the first one's moves up if the second is before
            (first_axes,), (second_axes,) = first_params, second_params
            if len(first_axes) != 1 or len(second_axes) != 1 or min(first_axes + second_axes) < 0:
                continue
            first_axis = first_axes[0] + (second_axes[0] <= first_axes[0])
            inputs = [node.input[0], initializer([first_axis, second_axes[0]])]
        else:  # Slice (data, starts, ends, axes[, steps]): the two slices on disjoint axes as one
            if len(first_params) < 3 or len(second_params) < 3:
                continue
            for params in (first_params, second_params):
                if len(params) == 3:
                    params.append([1] * len(params[0]))  # steps default to 1
            axes = first_params[2] + second_params[2]
            if len(set(axes)) != len(axes) or min(axes) < 0:
                continue
            inputs = [node.input[0], *(initializer(a + b) for a, b in zip(first_params, second_params))]
        name = f"{node.name}_merged"
        nodes[index] = onnx.helper.make_node(node.op_type, inputs, [second.output[0]], name=name)
        dropped.add(users[0])
    del graph.node[:]
    graph.node.extend(node for index, node in enumerate(nodes) if index not in dropped)


def _leaky_relus_as_max(graph: Any) -> None:
    """Replace each LeakyRelu of ``graph`` (changed in place) with 0 < alpha < 1 whose input is not a Conv's
    output by Max(x, alpha * x): the same values bit for bit (x >= 0: alpha * x <= x; x < 0: alpha * x > x; the
    same float32 product alpha * x that LeakyRelu returns there; -0, +-inf and NaN alike).

    Why: ONNX Runtime fuses a LeakyRelu after a Conv into the convolution, but runs the others (after the
    decoder's bias Add and the context's Gemm) with an element-wise select that is data dependent and not
    vectorised (~19 us for the last decoder level's 8 x 33 x 33 values); Mul and Max are vectorised
    (~25 us less per one-leg forward pass)."""
    from onnx import helper, numpy_helper

    producers = {output: node for node in graph.node for output in node.output}
    nodes = []
    for node in graph.node:
        if node.op_type == "LeakyRelu":
            alpha = next((a.f for a in node.attribute if a.name == "alpha"), 0.01)  # 0.01: the ONNX default
            source = producers.get(node.input[0])
            if (source is None or source.op_type != "Conv") and 0.0 < alpha < 1.0:
                x, alpha_name, scaled = node.input[0], f"{node.output[0]}_alpha", f"{node.output[0]}_scaled"
                graph.initializer.append(numpy_helper.from_array(np.array(alpha, np.float32), alpha_name))
                nodes.append(helper.make_node("Mul", [x, alpha_name], [scaled], name=f"{node.name}_mul"))
                nodes.append(helper.make_node("Max", [x, scaled], [node.output[0]], name=f"{node.name}_max"))
                continue
        nodes.append(node)
    del graph.node[:]
    graph.node.extend(nodes)


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
        self.candidates = int(net.config.encoding.cells) ** 2  # type: ignore[attr-defined]
        self.model_bytes = export_onnx(net)
        self.session = ort.InferenceSession(self.model_bytes, session_options(), providers=["CPUExecutionProvider"])

    def __call__(
        self, image: NDArray[np.float32], scalars: NDArray[np.float32]
    ) -> tuple[NDArray[np.float32], NDArray[np.float32] | None]:
        """(optimum logits (B, n*n), safe-mask logits (B, n*n) or None) for float32 inputs of ``encode``."""
        feed = {"image": np.ascontiguousarray(image, np.float32), "scalars": np.ascontiguousarray(scalars, np.float32)}
        outputs = self.session.run(None, feed)
        return outputs[0], (outputs[1] if self.safe_head else None)

    def bind(self, image: NDArray[np.float32], scalars: NDArray[np.float32]) -> OrtBinding:
        """A run of the network on fixed input buffers into preallocated outputs (``OrtBinding``).

        image (B, 4, n, n) and scalars (B, S): float32, C-contiguous; the caller writes them before each
        run and keeps them alive as long as the binding."""
        for name, array in (("image", image), ("scalars", scalars)):
            if array.dtype != np.float32 or not array.flags.c_contiguous:
                raise ValueError(f"OrtVfaNet.bind: {name} must be a C-contiguous float32 array")
        return OrtBinding(self.session, image, scalars, self.candidates, self.safe_head)


class OrtBinding:
    """ONNX Runtime's I/O binding of one ``OrtVfaNet`` session to fixed buffers: ``run()`` computes the
    network on the current contents of ``image`` and ``scalars`` into ``logits`` (B, n*n) and ``safe_logits``
    (B, n*n, None without the safe head), the same arrays at every run (overwritten by the next one).
    Same outputs as ``OrtVfaNet.__call__``; saves the feed dictionary, the input checks and the output
    allocations of ``InferenceSession.run`` (~10 us of a ~0.37 ms one-leg call)."""

    def __init__(self, session: Any, image: NDArray[np.float32], scalars: NDArray[np.float32], candidates: int,
                 safe_head: bool) -> None:  # fmt: skip
        import onnxruntime as ort

        batch = image.shape[0]
        self.image, self.scalars = image, scalars  # referenced here so that the bound memory stays alive
        self.logits = np.empty((batch, candidates), np.float32)
        self.safe_logits = np.empty((batch, candidates), np.float32) if safe_head else None
        self._binding = session.io_binding()
        for name, array in (("image", image), ("scalars", scalars), ("logits", self.logits),
                            ("safe_logits", self.safe_logits)):  # fmt: skip
            if array is None:
                continue
            bind = self._binding.bind_input if name in ("image", "scalars") else self._binding.bind_output
            bind(name, "cpu", 0, np.float32, list(array.shape), array.ctypes.data)
        self._session = session
        self._options = ort.RunOptions()

    def run(self) -> tuple[NDArray[np.float32], NDArray[np.float32] | None]:
        """(optimum logits, safe-mask logits or None) of the buffers' current inputs."""
        self._session.run_with_iobinding(self._binding, self._options)
        return self.logits, self.safe_logits


__all__ = [
    "ONNX_OPSET", "OrtBinding", "OrtVfaNet", "available", "export_onnx", "rewrite_graph", "session_options",
]  # fmt: skip
