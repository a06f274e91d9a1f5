"""Each node's YAML under <pkg>/config/ is what `scripts/run_graph.sh` passes with --params-file: it must
name every parameter the node declares, only those, at the node's defaults (the files say so)."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest
import yaml
from rclpy.parameter import Parameter

ROOT = Path(__file__).resolve().parents[1]
# Parameters rclpy declares itself: not the node's to document.
RCLPY_PARAMETERS = {"use_sim_time", "start_type_description_service"}
NODES = {
    "sim_bridge": ("tal_sim_bridge", "tal_sim_bridge.sim_bridge_node", "SimBridgeNode"),
    "state_estimator": ("tal_estimation", "tal_estimation.state_estimator_node", "StateEstimatorNode"),
    "tce": ("tal_estimation", "tal_estimation.tce_node", "TceNode"),
    "wbc": ("tal_control", "tal_control.wbc_node", "WbcNode"),
    "stand_controller": ("tal_control", "tal_control.stand_controller_node", "StandControllerNode"),
    "vfa": ("tal_perception", "tal_perception.vfa_node", "VfaNode"),
    "vpa": ("tal_perception", "tal_perception.vpa_node", "VpaNode"),
}


def flatten(params: dict, prefix: str = "") -> dict[str, object]:
    """Nested YAML parameters as ROS names ("effects.torque_gain")."""
    flat = {}
    for key, value in params.items():
        if isinstance(value, dict):
            flat.update(flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def test_every_node_with_a_config_is_checked() -> None:
    shipped = {p.stem for p in ROOT.glob("tal_*/config/*.yaml")}
    assert shipped == set(NODES), "add the node to NODES (or its YAML is missing)"


@pytest.mark.parametrize("exe", sorted(NODES))
def test_config_names_every_declared_parameter_at_its_default(exe: str, context) -> None:
    package, module, class_name = NODES[exe]
    data = yaml.safe_load((ROOT / package / "config" / f"{exe}.yaml").read_text())
    assert list(data) == [exe], f"{exe}.yaml must be keyed by the node name"
    in_file = flatten(data[exe]["ros__parameters"])
    node = getattr(importlib.import_module(module), class_name)(context=context)
    try:
        declared = {name: node.get_parameter(name) for name in node._parameters if name not in RCLPY_PARAMETERS}
        assert set(in_file) == set(declared), (
            f"{exe}.yaml: not declared {sorted(set(in_file) - set(declared))}, "
            f"missing {sorted(set(declared) - set(in_file))}")
        for name, value in in_file.items():
            default = declared[name]
            expected = list(default.value) if default.type_ in (Parameter.Type.DOUBLE_ARRAY,
                                                                  Parameter.Type.INTEGER_ARRAY,
                                                                  Parameter.Type.STRING_ARRAY) else default.value
            assert value == expected, f"{exe}.yaml: {name} is {value!r}, the node's default {expected!r}"
            assert type(value) is type(expected) or (isinstance(expected, list) and isinstance(value, list)), (
                f"{exe}.yaml: {name} has type {type(value).__name__}, the node declares {type(expected).__name__}")
    finally:
        node.destroy_node()
