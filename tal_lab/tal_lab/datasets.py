"""Deterministic simulated trot datasets as rosbag2 MCAP bags (``make datasets``).

In the spirit of the thesis' state-estimation dataset (HyQ trotting in place on rigid ground and on a
2400 N/m foam, lines 3530-3913): each scenario is a closed-loop run (sWBC on ground truth, 1 kHz PyBullet)
recorded with exactly the messages the live graph carries:

| topic | type | rate |
|---|---|---|
| /joint_states, /imu (white noise, seeded), /ground_truth/odom | sensor_msgs, nav_msgs | 1 kHz |
| /ground_truth/contacts | tal_msgs/ContactState | 250 Hz |
| /joint_command (the torques sent), /cmd_vel (the velocity command) | tal_msgs, geometry_msgs | 250 Hz, 10 Hz |
| /terrain/heightmap (33 x 33 cells of 0.02 m around the base) | tal_msgs/HeightMap | 20 Hz |

Log times are the sim stamps, so ``bag_player`` replays them on the recorded clock. The same scenario and
seed give the same messages (physics and noise are deterministic; the manifest's ``content_sha256`` is
a digest of the decoded content, since FastCDR leaves padding bytes uninitialised). A manifest (``manifest.yaml``) lists
scenario, seed, parameters, duration and message counts of every bag.

Usage: ``python -m tal_lab.datasets --out data [--duration-s 60] [--only NAME ...]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import shutil
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from tal_core.heightmap import extract_heightmap
from tal_core.robot_description import load_robot_description
from tal_core.ros.bag_io import BagWriter, content_digest
from tal_core.ros.node_utils import stamp_from_ns
from tal_core.rotations import yaw_from_quat_xyzw
from tal_core.terrain import Course, load_course
from tal_lab.closed_loop import ClosedLoopConfig, Command, TickContext, run_closed_loop
from tal_sim_bridge.bridge_core import BridgeCore, ImuModel
from tal_sim_bridge.effects import ModelEffects
from tal_sim_bridge.physics import RobotState, Simulation
from tal_sim_bridge.sensor_messages import (
    contact_state_message,
    heightmap_message,
    imu_message,
    joint_command_message,
    joint_state_message,
    odometry_message,
    twist_message,
)
from tal_sim_bridge.stepping import OutputSchedule

LOG = logging.getLogger("tal.datasets")

GYRO_NOISE_RAD_S = 0.002
ACCEL_NOISE_M_S2 = 0.05
# The bridge's own schedule at its default rates (1 kHz sensors, 250 Hz contacts, 20 Hz heightmap).
SCHEDULE = OutputSchedule.from_rates(1000.0, 1000.0, 250.0, 20.0)
CMD_VEL_EVERY_STEPS = 100  # 10 Hz, a joystick's rate
HEIGHTMAP_CELLS = 33
HEIGHTMAP_RESOLUTION_M = 0.02


class DatasetError(RuntimeError):
    """A dataset could not be generated (the robot fell, bad scenario)."""


@dataclass(frozen=True)
class DatasetScenario:
    """One dataset: course (shipped name, YAML path or a Course), gait, piecewise-constant command
    (t_start [s], vx [m/s], vy [m/s], yaw rate [rad/s]), start pose, sensor noise (white, std per 1 kHz
    sample; joint_* noise is added to the recorded joint states only, the controller sees the true ones)
    and optional model effects."""

    name: str
    description: str
    course: str | Course
    gait: str = "trot"
    commands: tuple[Command, ...] = ((0.0, 0.0, 0.0, 0.0),)
    initial_xy: tuple[float, float] = (0.0, 0.0)
    initial_yaw_rad: float = 0.0
    gyro_noise_std_rad_s: float = GYRO_NOISE_RAD_S
    accel_noise_std_m_s2: float = ACCEL_NOISE_M_S2
    effects: ModelEffects = field(default_factory=ModelEffects)
    joint_position_noise_std_rad: float = 0.0
    joint_velocity_noise_std_rad_s: float = 0.0
    joint_effort_noise_std_nm: float = 0.0


SCENARIOS: dict[str, DatasetScenario] = {s.name: s for s in (
    DatasetScenario("trot_in_place_rigid", "HyQ trotting in place on rigid ground (thesis dataset, rigid)",
                    "flat_rigid"),
    DatasetScenario("trot_in_place_soft", "HyQ trotting in place on a 2400 N/m, 400 N s/m foam (thesis "
                    "dataset, soft)", "flat_foam"),
    DatasetScenario("trot_loop_mixed", "HyQ trotting a 2 m circle (0.3 m/s, 0.15 rad/s) over rigid ground, "
                    "T1, foam and T2", "trot_loop",
                    commands=((0.0, 0.0, 0.0, 0.0), (2.0, 0.3, 0.0, 0.15)), initial_xy=(0.0, -2.0)),
)}


class DatasetRecorder:
    """Writes the bridge's and the controller's messages of a closed-loop run into a bag: ``on_step`` after
    every physics step (sensors, ground truth; it reads ``core.sim.foot_contacts()``), ``on_tick`` after
    every control tick (commands, gait). The closed-loop datasets and the MuJoCo recording
    (``tal_lab.mujoco_hyq``) share it, so their bags have the same topics, rates and sensor noise."""

    def __init__(self, writer: BagWriter, scenario: DatasetScenario, config: ClosedLoopConfig,
                 joint_names: Sequence[str], seed: int, course: Course) -> None:
        self.writer = writer
        self.scenario = scenario
        self.config = config
        self.joint_names = list(joint_names)
        self.course = course
        self.imu = ImuModel(scenario.effects, scenario.gyro_noise_std_rad_s, scenario.accel_noise_std_m_s2, seed)
        self.joint_noise = np.array([scenario.joint_position_noise_std_rad, scenario.joint_velocity_noise_std_rad_s,
                                     scenario.joint_effort_noise_std_nm])
        self.joint_rng = np.random.default_rng([seed, 1])  # separate stream: the IMU noise stays as it was
        self.steps = 0

    def _put(self, topic: str, message, t_ns: int) -> None:
        self.writer.write(topic, message, t_ns)

    def on_step(self, t_s: float, state: RobotState, core: BridgeCore) -> None:
        """After every physics step (and once at t = 0): sensors, contacts, heightmap, cmd_vel."""
        t_ns = round(t_s * 1e9)
        stamp = stamp_from_ns(t_ns)
        due = SCHEDULE.due(self.steps)
        if due.sensors:
            self._put("/joint_states", joint_state_message(stamp, self.joint_names, self._noisy(state)), t_ns)
            f, w = self.imu.measure(state)
            self._put("/imu", imu_message(stamp, f, w, self.scenario.gyro_noise_std_rad_s,
                                         self.scenario.accel_noise_std_m_s2), t_ns)
            self._put("/ground_truth/odom", odometry_message(stamp, state), t_ns)
        if due.contacts:
            self._put("/ground_truth/contacts", contact_state_message(stamp, core.sim.foot_contacts()), t_ns)
        if due.heightmap:
            grid = extract_heightmap(self.course, tuple(state.base_position_m[:2]),
                                     yaw_from_quat_xyzw(state.base_quat_xyzw), rows=HEIGHTMAP_CELLS,
                                     cols=HEIGHTMAP_CELLS, resolution_m=HEIGHTMAP_RESOLUTION_M)
            self._put("/terrain/heightmap", heightmap_message(stamp, grid), t_ns)
        if self.steps % CMD_VEL_EVERY_STEPS == 0:
            self._put("/cmd_vel", twist_message(*self.config.command_at(t_s)), t_ns)
        self.steps += 1

    def _noisy(self, state: RobotState) -> RobotState:
        """The joint states as measured: true values plus white noise (when the scenario sets any)."""
        if not self.joint_noise.any():
            return state
        n = len(state.joint_position_rad)
        noise = self.joint_rng.normal(0.0, 1.0, (3, n)) * self.joint_noise[:, None]
        return dataclasses.replace(state, joint_position_rad=state.joint_position_rad + noise[0],
                                   joint_velocity_rad_s=state.joint_velocity_rad_s + noise[1],
                                   joint_torque_nm=state.joint_torque_nm + noise[2])

    def on_tick(self, context: TickContext) -> None:
        """Every control tick: the torque command sent to the robot."""
        t_ns = round(context.t_s * 1e9)
        self._put("/joint_command", joint_command_message(stamp_from_ns(t_ns), self.joint_names,
                                                         context.output.tau), t_ns)


TOPIC_TYPES = {
    "/joint_states": "sensor_msgs/msg/JointState",
    "/imu": "sensor_msgs/msg/Imu",
    "/ground_truth/odom": "nav_msgs/msg/Odometry",
    "/ground_truth/contacts": "tal_msgs/msg/ContactState",
    "/terrain/heightmap": "tal_msgs/msg/HeightMap",
    "/cmd_vel": "geometry_msgs/msg/Twist",
    "/joint_command": "tal_msgs/msg/JointCommand",
}


def generate(scenario: DatasetScenario, out_dir: Path, duration_s: float, seed: int = 0,
             progress: bool = True, sim_setup: Callable[[Simulation], None] | None = None) -> dict[str, object]:
    """Run ``scenario`` for ``duration_s`` [s] of sim time and write the bag ``out_dir`` (replaced if it
    exists). Returns its manifest entry. Raises DatasetError when the robot falls.

    ``sim_setup`` is called once with the simulated robot before its first physics step: physics the bridge's
    global ``ModelEffects`` cannot express (tal_sim2real's sealed per-link and per-joint effects). The
    controller never sees it; the manifest does not describe it."""
    out_dir = Path(out_dir)
    if out_dir.exists():
        shutil.rmtree(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    course = scenario.course if isinstance(scenario.course, Course) else load_course(scenario.course)
    config = ClosedLoopConfig(name=scenario.name, course=course, gait=scenario.gait, commands=scenario.commands,
                              duration_s=duration_s, effects=scenario.effects, initial_xy=scenario.initial_xy,
                              initial_yaw_rad=scenario.initial_yaw_rad, progress=progress)
    joint_names = load_robot_description(config.robot).joint_names
    with BagWriter(out_dir) as writer:
        for topic, type_name in TOPIC_TYPES.items():
            writer.add_topic(topic, type_name)
        recorder = DatasetRecorder(writer, scenario, config, joint_names, seed, course)

        def tick_hook(context: TickContext) -> None:
            if context.tick == 0:  # the state at t = 0, as the bridge publishes it before the first step
                if sim_setup is not None:
                    sim_setup(context.core.sim)
                recorder.on_step(0.0, context.state, context.core)
            recorder.on_tick(context)

        log = run_closed_loop(config, hook=tick_hook, step_hook=recorder.on_step)
        counts = writer.message_counts
    if log.fell:
        raise DatasetError(f"{scenario.name}: HyQ fell at t = {log.meta['fall_time_s']} s "
                           f"({log.meta['fall_reason']}); the dataset is not valid")
    entry = {
        "name": scenario.name,
        "description": scenario.description,
        "bag": out_dir.name,
        "seed": seed,
        "duration_s": duration_s,
        "course": course.name,
        "gait": scenario.gait,
        "commands": [list(c) for c in scenario.commands],
        "initial_xy_m": list(scenario.initial_xy),
        "initial_yaw_rad": scenario.initial_yaw_rad,
        "imu_noise": {"gyro_std_rad_s": scenario.gyro_noise_std_rad_s,
                      "accel_std_m_s2": scenario.accel_noise_std_m_s2},
        "effects": _effects_dict(scenario.effects),
        "joint_noise": {"position_std_rad": scenario.joint_position_noise_std_rad,
                        "velocity_std_rad_s": scenario.joint_velocity_noise_std_rad_s,
                        "effort_std_nm": scenario.joint_effort_noise_std_nm},
        "controller": "sWBC (rigid contact model) on ground truth, 250 Hz; physics 1 kHz",
        "net_displacement_m": round(float(np.linalg.norm(log.base_position[-1, :2] - log.base_position[0, :2])), 3),
        "content_sha256": content_digest(out_dir),
    }
    entry["message_counts"] = counts
    return entry


def _effects_dict(effects: ModelEffects) -> dict[str, object]:
    out = {}
    for f in dataclasses.fields(effects):
        value = getattr(effects, f.name)
        out[f.name] = list(value) if isinstance(value, tuple | list | np.ndarray) else value
    return out


def generate_all(out: Path, duration_s: float = 60.0, names: Sequence[str] | None = None, seed: int = 0,
                 progress: bool = True) -> Path:
    """Generate the named scenarios (default: all) under ``out`` and write ``out/manifest.yaml``."""
    names = list(SCENARIOS) if not names else list(names)
    unknown = [n for n in names if n not in SCENARIOS]
    if unknown:
        raise DatasetError(f"unknown dataset(s) {unknown}; known: {sorted(SCENARIOS)}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    manifest_path = out / "manifest.yaml"
    manifest = yaml.safe_load(manifest_path.read_text()) if manifest_path.exists() else None
    entries = {e["name"]: e for e in (manifest or {}).get("datasets", [])}
    for i, name in enumerate(names, 1):
        if progress:
            sys.stderr.write(f"[datasets] {i}/{len(names)} {name}: {duration_s:.0f} s of sim time\n")
        entries[name] = generate(SCENARIOS[name], out / name, duration_s, seed=seed, progress=progress)
        manifest_path.write_text(yaml.safe_dump({"format": "rosbag2 MCAP (tal bag_io)", "datasets": [
            entries[n] for n in sorted(entries)]}, sort_keys=False))
    return manifest_path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("data"), help="output folder (default: data)")
    parser.add_argument("--duration-s", type=float, default=60.0, help="sim time per dataset [s] (default 60)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the IMU noise (default 0)")
    parser.add_argument("--only", nargs="+", metavar="NAME", help=f"subset of {sorted(SCENARIOS)}")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        path = generate_all(args.out, args.duration_s, args.only, args.seed, progress=not args.quiet)
    except DatasetError as exc:
        LOG.error("%s", exc)
        return 1
    print(f"manifest: {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
