"""Each node's YAML under <pkg>/config/ is what `scripts/run_graph.sh` passes with --params-file: it must
name every parameter the node declares, only those, at the node's defaults (the files say so), and mark as
"live" exactly the parameters the node applies at run time (every other one is declared read-only)."""

from __future__ import annotations

import importlib
import re
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
    "cmd_vel_script": ("tal_control", "tal_control.cmd_vel_script_node", "CmdVelScriptNode"),
    "bag_player": ("tal_sim_bridge", "tal_sim_bridge.bag_player_node", "BagPlayerNode"),
    "bag_recorder": ("tal_sim_bridge", "tal_sim_bridge.bag_recorder_node", "BagRecorderNode"),
}


def required_overrides(exe: str, tmp_path: Path) -> list[Parameter]:
    """What a node cannot start without (a bag to play) or should not default to in a test (a bag folder in
    the working directory)."""
    if exe == "bag_player":
        from std_msgs.msg import String

        from tal_core.ros.bag_io import BagWriter

        with BagWriter(tmp_path / "bag") as writer:
            writer.write("/level", String(data="x"), 0)
        return [Parameter("bag", value=str(tmp_path / "bag"))]
    if exe == "bag_recorder":
        return [Parameter("output", value=str(tmp_path / "recorded"))]
    return []


def live_in_file(text: str) -> set[str]:
    """Parameter names whose YAML comment says "live" (the last name component for nested ones)."""
    return {m.group(1) for m in re.finditer(r"^\s*([A-Za-z_][\w]*):[^#\n]*#[^\n]*\blive\b", text, re.M)}


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
def test_config_names_every_declared_parameter_at_its_default(exe: str, context, tmp_path: Path) -> None:
    package, module, class_name = NODES[exe]
    text = (ROOT / package / "config" / f"{exe}.yaml").read_text()
    data = yaml.safe_load(text)
    assert list(data) == [exe], f"{exe}.yaml must be keyed by the node name"
    in_file = flatten(data[exe]["ros__parameters"])
    overrides = required_overrides(exe, tmp_path)
    node = getattr(importlib.import_module(module), class_name)(context=context, parameter_overrides=overrides)
    try:
        declared = {name: node.get_parameter(name) for name in node._parameters if name not in RCLPY_PARAMETERS}
        assert set(in_file) == set(declared), (
            f"{exe}.yaml: not declared {sorted(set(in_file) - set(declared))}, "
            f"missing {sorted(set(declared) - set(in_file))}")
        live = {name.split(".")[-1] for name in declared if not node.describe_parameter(name).read_only}
        assert live_in_file(text) == live, (
            f"{exe}.yaml marks live {sorted(live_in_file(text))}, the node applies at run time {sorted(live)}")
        for name, value in in_file.items():
            if name in {p.name for p in overrides}:
                continue
            default = declared[name]
            expected = list(default.value) if default.type_ in (Parameter.Type.DOUBLE_ARRAY,
                                                                  Parameter.Type.INTEGER_ARRAY,
                                                                  Parameter.Type.STRING_ARRAY) else default.value
            assert value == expected, f"{exe}.yaml: {name} is {value!r}, the node's default {expected!r}"
            assert type(value) is type(expected) or (isinstance(expected, list) and isinstance(value, list)), (
                f"{exe}.yaml: {name} has type {type(value).__name__}, the node declares {type(expected).__name__}")
    finally:
        node.destroy_node()
