"""Parameters at run time, as `ros2 param set` sends them: a live one is validated and takes effect, a
read-only one is refused with a reason, an invalid live value is refused and changes nothing."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from rclpy.parameter import Parameter
from std_msgs.msg import String

from tal_core.ros.bag_io import BagWriter
from tal_sim_bridge.bag_player_node import BagPlayerNode
from tal_sim_bridge.sim_bridge_node import SimBridgeNode

pytestmark = pytest.mark.ros


def test_sim_bridge_live_and_read_only_parameters(context) -> None:
    bridge = SimBridgeNode(context=context, parameter_overrides=[Parameter("duration_s", value=1.0)])
    try:
        assert bridge.duration_steps == 1000
        result = bridge.set_parameters([Parameter("duration_s", value=2.5)])[0]
        assert result.successful, result.reason
        assert bridge.duration_steps == 2500 and bridge.get_parameter("duration_s").value == 2.5

        result = bridge.set_parameters([Parameter("lockstep_timeout_s", value=0.5)])[0]
        assert result.successful and bridge.gate.timeout_s == 0.5

        refused = bridge.set_parameters([Parameter("mode", value="realtime")])[0]
        assert not refused.successful and "read-only" in refused.reason
        assert bridge.mode == "lockstep" and bridge.get_parameter("mode").value == "lockstep"

        out_of_range = bridge.set_parameters([Parameter("max_catch_up_steps", value=0)])[0]
        assert not out_of_range.successful and bridge.pacer.max_catch_up_steps == 20
    finally:
        bridge.destroy_node()


def test_bag_player_rate_is_live_but_not_to_as_fast_as_possible(context, tmp_path: Path) -> None:
    with BagWriter(tmp_path / "bag") as writer:
        for k in range(10):
            writer.write("/level", String(data=str(k)), k * 100_000_000)
    player = BagPlayerNode(context=context, parameter_overrides=[Parameter("bag", value=str(tmp_path / "bag"))])
    try:
        player._wall_start = time.monotonic() - 0.2  # 0.2 s into the bag at 1x
        result = player.set_parameters([Parameter("rate", value=2.0)])[0]
        assert result.successful, result.reason
        assert player.rate == 2.0
        # The position in the bag is kept: 0.2 s of bag time is now 0.1 s of wall time behind us.
        assert (time.monotonic() - player._wall_start) * player.rate == pytest.approx(0.2, abs=0.02)

        refused = player.set_parameters([Parameter("rate", value=0.0)])[0]
        assert not refused.successful and "QoS" in refused.reason and player.rate == 2.0
        assert player.get_parameter("rate").value == 2.0
    finally:
        player.destroy_node()
