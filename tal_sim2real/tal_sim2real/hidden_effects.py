"""Hidden-effect test data: measured bags produced by the simulator with a sealed model effect.

Each dataset is a closed-loop sWBC trot (forward, turning, sideways) on flat ground, recorded like the
graph records a real robot (joint states with encoder/torque-sensor noise, IMU with noise, motion-capture
ground truth, the torque commands sent, cmd_vel). The simulated robot carries zero, one or two effects of
random type and size; the truth goes to ``<out>/sealed/<name>.yaml``, a file the identification code never
opens (``tal_sim2real.identify`` takes a bag path only). Scoring (``score``) reads it afterwards.

The label also says whether the data can show the effect (``detectable``) from the simulator's own record:
a torque limit that no command reached, or a friction coefficient that no stance foot came near, leaves no
trace in the data, and ground stiffer than 1e5 N/m sinks a foot by < 3 mm (not identifiable).
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from tal_lab.datasets import DatasetError, DatasetScenario, generate

from tal_core.robot_description import load_robot_description

from .measured import load_measured
from .model import SimModel
from .outcomes import STIFF_GROUND_N_PER_M
from .torque_path import torque_limits

LOG = logging.getLogger("tal.sim2real.hidden")

DURATION_S = 8.0
COMMANDS = (
    (0.0, 0.0, 0.0, 0.0),
    (0.8, 0.3, 0.0, 0.0),
    (3.0, 0.2, 0.0, 0.35),
    (5.0, -0.1, 0.15, 0.0),
    (6.5, 0.25, 0.0, -0.3),
)
JOINT_NOISE = (2e-4, 0.02, 0.3)  # [rad], [rad/s], [N m] encoder, velocity and torque-sensor noise (std)
EFFECT_TYPES = (
    "ground",
    "ground_nonlinear",
    "foot_friction",
    "joint_viscous_friction",
    "joint_coulomb_friction",
    "actuator_delay",
    "actuator_lag",
    "torque_gain",
    "torque_limit",
    "payload",
    "imu_bias",
)
VARIANT_TYPES = ("encoder_offset", "leg_torque_sensor_gain", "leg_link_mass")
"""Per-joint / per-leg effects the library names as variants (``library.VARIANTS``, issue 34 item 3); the label
carries the joint and the leg, the scorer checks the variant is named there (``benchmark.VARIANT_SCORING``):

* ``encoder_offset``: a constant offset of one knee's encoder [rad] (``joint``: its index), applied to the
  recorded joint states (the robot and its controller never see it);
* ``leg_torque_sensor_gain``: a gain of one leg's three torque sensors [-] (``leg``: 0-3 as LF, RF, LH, RH),
  applied to the recording;
* ``leg_link_mass``: extra mass [kg] at the centre of mass of one leg's lower link (a sensor box or a repair
  clamp on the shin), applied to the simulated robot (``links.LowerLinkMasses``); the controller keeps the
  nominal masses."""
OUT_OF_LIBRARY_TYPES = ("joint_spring", "valve_dead_band", "torque_sensor_offset")
"""Per-joint effects the library lacks (issue 34 item 6), each on one joint (``joint``: its index), so the
benchmark can check that the report says the library does not explain them and where:

* ``joint_spring``: a hose or cable bundle across one joint acting as a torsional spring,
  tau = -k (q - q_rest) [N m/rad, rad], applied by the simulated robot every physics step between the links
  (after the torque sensor, like friction: the measured torque does not contain it);
* ``valve_dead_band``: the overlap of one joint's servo valve: a torque command within +-b [N m] delivers
  nothing and a larger one b less (the delivered torque, and so the torque sensor, show it);
* ``torque_sensor_offset``: a zero drift of one joint's torque sensor [N m], added to the recorded efforts
  (the robot and its controller never see it)."""
SENSOR_TYPES = ("encoder_offset", "leg_torque_sensor_gain", "torque_sensor_offset")
"""Effects applied to the recording after the run (``apply_sensor_effects``)."""
PHYSICS_TYPES = ("leg_link_mass", "joint_spring", "valve_dead_band")
"""Effects applied to the simulated robot beyond the bridge's global ``ModelEffects`` (``physics_setup``)."""
LOCAL_TYPES = VARIANT_TYPES + OUT_OF_LIBRARY_TYPES
"""Effects of one joint or one leg (not sim_bridge parameters)."""


@dataclass(frozen=True)
class HiddenEffect:
    """One sealed effect: its type and the true parameter values (model parameter names, SI units)."""

    kind: str
    values: dict[str, float]


def draw_effect(kind: str, rng: np.random.Generator) -> HiddenEffect:
    """A random size of effect ``kind`` over a realistic range."""

    def log_uniform(low: float, high: float) -> float:
        return float(math.exp(rng.uniform(math.log(low), math.log(high))))

    if kind == "ground":
        stiff = rng.random() < 0.25
        k = log_uniform(2e5, 1e6) if stiff else log_uniform(1.2e4, 8e4)
        return HiddenEffect(
            kind, {"ground_stiffness_n_per_m": k, "ground_damping_ns_per_m": log_uniform(300.0, 1500.0)}
        )
    if kind == "ground_nonlinear":
        return HiddenEffect(
            kind,
            {
                "ground_stiffness_n_per_m": log_uniform(1.5e4, 6e4),
                "ground_damping_ns_per_m": log_uniform(300.0, 1500.0),
                "ground_contact_exponent": float(rng.uniform(1.3, 2.0)),
            },
        )
    if kind == "foot_friction":
        return HiddenEffect(kind, {"foot_friction": float(rng.uniform(0.3, 0.6))})
    if kind == "joint_viscous_friction":
        return HiddenEffect(kind, {"joint_viscous_friction_nms_per_rad": float(rng.uniform(0.5, 4.0))})
    if kind == "joint_coulomb_friction":
        return HiddenEffect(kind, {"joint_coulomb_friction_nm": float(rng.uniform(1.0, 6.0))})
    if kind == "actuator_delay":
        return HiddenEffect(kind, {"actuator_delay_s": float(rng.uniform(0.003, 0.012))})
    if kind == "actuator_lag":
        return HiddenEffect(kind, {"actuator_lag_s": float(rng.uniform(0.003, 0.015))})
    if kind == "torque_gain":
        gain = float(rng.uniform(0.8, 0.93)) if rng.random() < 0.5 else float(rng.uniform(1.07, 1.2))
        return HiddenEffect(kind, {"torque_gain": gain})
    if kind == "torque_limit":
        return HiddenEffect(kind, {"torque_limit_scale": float(rng.uniform(0.25, 0.6))})
    if kind == "payload":
        return HiddenEffect(
            kind,
            {
                "payload_mass_kg": float(rng.uniform(4.0, 15.0)),
                "payload_offset_x_m": float(rng.uniform(-0.1, 0.1)),
                "payload_offset_y_m": float(rng.uniform(-0.05, 0.05)),
            },
        )
    if kind == "imu_bias":
        signs = rng.choice([-1.0, 1.0], 6)
        gyro = signs[:3] * rng.uniform(0.005, 0.03, 3)
        accel = signs[3:] * rng.uniform(0.05, 0.3, 3)
        return HiddenEffect(
            kind,
            {
                **{f"imu_gyro_bias_{a}_rad_s": float(v) for a, v in zip("xyz", gyro)},
                **{f"imu_accel_bias_{a}_m_s2": float(v) for a, v in zip("xyz", accel)},
            },
        )
    if kind == "leg_link_mass":
        return HiddenEffect(kind, {"leg_link_mass_kg": float(rng.uniform(1.0, 3.0)), "leg": float(rng.integers(0, 4))})
    if kind == "joint_spring":
        joint = int(3 * rng.integers(0, 4) + rng.integers(1, 3))  # a hip flexion or a knee
        nominal_q = load_robot_description("hyq").nominal_joint_positions_rad[joint]
        return HiddenEffect(
            kind,
            {
                "joint_spring_nm_per_rad": float(rng.uniform(30.0, 80.0)),
                "joint_spring_rest_rad": float(nominal_q + rng.choice([-1.0, 1.0]) * rng.uniform(0.1, 0.25)),
                "joint": float(joint),
            },
        )
    if kind == "valve_dead_band":
        joint = int(3 * rng.integers(0, 4) + rng.integers(1, 3))
        return HiddenEffect(kind, {"valve_dead_band_nm": float(rng.uniform(4.0, 10.0)), "joint": float(joint)})
    if kind == "torque_sensor_offset":
        joint = int(rng.integers(0, 12))
        offset = float(rng.choice([-1.0, 1.0]) * rng.uniform(2.0, 5.0))
        return HiddenEffect(kind, {"torque_sensor_offset_nm": offset, "joint": float(joint)})
    if kind == "encoder_offset":
        joint = int(rng.choice([2, 5, 8, 11]))  # a knee
        offset = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.03, 0.08))
        return HiddenEffect(kind, {"encoder_offset_rad": offset, "joint": float(joint)})
    if kind == "leg_torque_sensor_gain":
        leg = int(rng.integers(0, 4))
        gain = float(rng.uniform(0.8, 0.9)) if rng.random() < 0.5 else float(rng.uniform(1.1, 1.2))
        return HiddenEffect(kind, {"leg_torque_sensor_gain": gain, "leg": float(leg)})
    raise ValueError(f"unknown effect type '{kind}'; known: {EFFECT_TYPES + LOCAL_TYPES}")


def _scaled(effect: HiddenEffect, factor: float) -> HiddenEffect:
    """The same effect, ``factor`` of the way from nominal (used after a fall)."""
    if effect.kind in SENSOR_TYPES:  # applied to the recording: cannot make HyQ fall
        return effect
    if effect.kind in PHYSICS_TYPES:  # shrink the size, keep the place (and a spring's rest angle)
        key = {"leg_link_mass": "leg_link_mass_kg", "joint_spring": "joint_spring_nm_per_rad",
               "valve_dead_band": "valve_dead_band_nm"}[effect.kind]
        return HiddenEffect(effect.kind, {**effect.values, key: factor * effect.values[key]})
    nominal = SimModel.nominal().values()
    values = {}
    for name, value in effect.values.items():
        if name == "ground_stiffness_n_per_m":
            values[name] = value / factor  # stiffer ground is closer to nominal
        else:
            values[name] = nominal[name] + factor * (value - nominal[name])
    return HiddenEffect(effect.kind, values)


def generate_hidden(
    out_root: Path,
    name: str,
    effects: list[HiddenEffect],
    seed: int,
    duration_s: float = DURATION_S,
    progress: bool = False,
) -> tuple[Path, Path]:
    """Generate one measured bag ``<out_root>/bags/<name>`` with ``effects`` sealed in
    ``<out_root>/sealed/<name>.yaml``. Effects that make HyQ fall are shrunk towards nominal (x0.6, at most
    4 times; the label records it). Returns (bag path, label path)."""
    out_root = Path(out_root)
    bag = out_root / "bags" / name
    label_path = out_root / "sealed" / f"{name}.yaml"
    label_path.parent.mkdir(parents=True, exist_ok=True)
    planned = [{"kind": e.kind, "values": dict(e.values)} for e in effects]
    shrinks = 0
    while True:
        model = SimModel.nominal("flat_rigid")
        for effect in effects:
            if effect.kind not in LOCAL_TYPES:
                model = model.with_values(effect.values)
        scenario = DatasetScenario(
            name,
            "hidden-effect dataset (tal_sim2real)",
            model.course,
            commands=COMMANDS,
            effects=model.effects,
            joint_position_noise_std_rad=JOINT_NOISE[0],
            joint_velocity_noise_std_rad_s=JOINT_NOISE[1],
            joint_effort_noise_std_nm=JOINT_NOISE[2],
        )
        try:
            generate(scenario, bag, duration_s, seed=seed, progress=progress, sim_setup=physics_setup(effects))
            break
        except DatasetError as exc:
            if shrinks >= 4:
                raise
            LOG.info("%s: %s; shrinking the effect(s)", name, exc)
            effects = [_scaled(e, 0.6) for e in effects]
            shrinks += 1
    sensor = [e for e in effects if e.kind in SENSOR_TYPES]
    if sensor:
        apply_sensor_effects(bag, sensor)
    label = {
        "name": name,
        "seed": seed,
        "duration_s": duration_s,
        "shrunk_after_falls": shrinks,
        "planned": planned,  # the effects asked for (before shrinking), so a stale dataset is recognised
        "effects": [{"kind": e.kind, "values": e.values, **_detectability(e, bag)} for e in effects],
    }
    label_path.write_text(yaml.safe_dump(label, sort_keys=False))
    return bag, label_path


class SealedJointEffects:
    """The simulated robot's actuators with per-joint effects the bridge lacks (it replaces the
    ``Simulation``'s ``actuators``, which ``Simulation.step`` calls every physics step): a servo valve's dead
    band on the torque command of some joints (``dead_band_nm``, 12 values) and torsional springs across some
    joints (``spring_nm_per_rad`` and ``spring_rest_rad``, 12 values each) acting, like friction, between the
    links after the torque sensor."""

    def __init__(self, sim, dead_band_nm: np.ndarray, spring_nm_per_rad: np.ndarray,
                 spring_rest_rad: np.ndarray) -> None:
        n = len(sim.joint_ids)
        arrays = [np.asarray(a, dtype=float) for a in (dead_band_nm, spring_nm_per_rad, spring_rest_rad)]
        if any(a.shape != (n,) or not np.all(np.isfinite(a)) for a in arrays):
            shapes = [a.shape for a in arrays]
            raise ValueError(f"sealed joint effects need {n} finite values each, got shapes {shapes}")
        if np.any(arrays[0] < 0.0) or np.any(arrays[1] < 0.0):
            raise ValueError("a dead band and a spring stiffness must be >= 0")
        self.sim = sim
        self.inner = sim.actuators
        self.dead_band_nm, self.spring_nm_per_rad, self.spring_rest_rad = arrays
        self._spring_joints = [int(j) for j in np.flatnonzero(self.spring_nm_per_rad)]

    def __getattr__(self, name: str):  # delay_steps, effects, tau limits: the bridge's actuator model's
        return getattr(self.inner, name)

    def reset(self) -> None:
        self.inner.reset()

    def delivered_torque(self, commanded: np.ndarray, tau_min=None, tau_max=None) -> np.ndarray:
        u = np.asarray(commanded, dtype=float)
        u = np.sign(u) * np.maximum(np.abs(u) - self.dead_band_nm, 0.0)
        return self.inner.delivered_torque(u, tau_min, tau_max)

    def friction_torque(self, joint_velocity: np.ndarray) -> np.ndarray:
        tau = self.inner.friction_torque(joint_velocity)
        for j in self._spring_joints:
            q = self.sim.client.getJointState(self.sim.robot, self.sim.joint_ids[j])[0]
            tau[j] -= self.spring_nm_per_rad[j] * (q - self.spring_rest_rad[j])
        return tau


def physics_setup(effects: list[HiddenEffect]):
    """The ``sim_setup`` of ``tal_lab.datasets.generate`` for the effects applied to the simulated robot
    (``PHYSICS_TYPES``), or None when there are none."""
    physical = [e for e in effects if e.kind in PHYSICS_TYPES]
    if not physical:
        return None

    def setup(sim) -> None:
        from .links import LowerLinkMasses

        n = len(sim.joint_ids)
        extra, band, k, rest = np.zeros(4), np.zeros(n), np.zeros(n), np.zeros(n)
        for e in physical:
            if e.kind == "leg_link_mass":
                extra[int(e.values["leg"])] += e.values["leg_link_mass_kg"]
            elif e.kind == "valve_dead_band":
                band[int(e.values["joint"])] = e.values["valve_dead_band_nm"]
            else:
                j = int(e.values["joint"])
                k[j], rest[j] = e.values["joint_spring_nm_per_rad"], e.values["joint_spring_rest_rad"]
        if extra.any():
            LowerLinkMasses(sim).apply(extra)
        if band.any() or k.any():
            sim.actuators = SealedJointEffects(sim, band, k, rest)

    return setup


def apply_sensor_effects(bag: Path, effects: list[HiddenEffect]) -> None:
    """Rewrite ``bag`` in place with the sensor effects applied to /joint_states (encoder offset of one joint,
    gain of one leg's torque sensors, offset of one joint's torque sensor); every other message is copied
    unchanged."""
    from tal_core.ros.bag_io import BagReader, BagWriter

    bag = Path(bag)
    tmp = bag.with_name(bag.name + ".sensor_tmp")
    if tmp.exists():
        import shutil

        shutil.rmtree(tmp)
    reader = BagReader(bag)
    with BagWriter(tmp) as writer:
        for topic, type_name in reader.topics().items():
            writer.add_topic(topic, type_name)
        for record in reader.messages():
            message = record.message
            if record.topic == "/joint_states":
                position = list(message.position)
                effort = list(message.effort)
                for e in effects:
                    if e.kind == "encoder_offset":
                        position[int(e.values["joint"])] += e.values["encoder_offset_rad"]
                    elif e.kind == "torque_sensor_offset" and effort:
                        effort[int(e.values["joint"])] += e.values["torque_sensor_offset_nm"]
                    elif e.kind == "leg_torque_sensor_gain" and effort:
                        leg = int(e.values["leg"])
                        for j in range(3 * leg, 3 * leg + 3):
                            effort[j] *= e.values["leg_torque_sensor_gain"]
                message.position = position
                message.effort = effort
            writer.write(record.topic, message, record.log_time_ns)
    import shutil

    shutil.rmtree(bag)
    tmp.rename(bag)


def _detectability(effect: HiddenEffect, bag: Path) -> dict[str, object]:
    """Whether the recorded motion excites the effect, from the simulator's record (scorer's oracle)."""
    if effect.kind == "encoder_offset":
        joint = load_robot_description("hyq").joint_names[int(effect.values["joint"])]
        return {"detectable": True, "why": "", "out_of_library": False, "joint": joint, "leg": joint[:2].upper()}
    if effect.kind in ("leg_torque_sensor_gain", "leg_link_mass"):
        leg = ("LF", "RF", "LH", "RH")[int(effect.values["leg"])]
        return {"detectable": True, "why": "", "out_of_library": False, "joint": "", "leg": leg}
    if effect.kind in OUT_OF_LIBRARY_TYPES:
        joint = load_robot_description("hyq").joint_names[int(effect.values["joint"])]
        return {"detectable": True, "why": "", "out_of_library": True, "joint": joint, "leg": joint[:2].upper()}
    if effect.kind in ("ground", "ground_nonlinear"):
        k = effect.values["ground_stiffness_n_per_m"]
        ok = k < STIFF_GROUND_N_PER_M
        return {"detectable": ok, "why": "" if ok else f"stiffer than {STIFF_GROUND_N_PER_M:.0e} N/m"}
    if effect.kind not in ("torque_limit", "foot_friction"):
        return {"detectable": True, "why": ""}
    description = load_robot_description("hyq")
    data = load_measured(bag, description)
    if effect.kind == "torque_limit":
        scale = effect.values["torque_limit_scale"]
        command = data.command_in_force()
        low, high = torque_limits(description, data.q_rad[::10])
        cmd = command[::10]
        clipped = int(((cmd > scale * high) | (cmd < scale * low)).sum())
        return {
            "detectable": clipped >= 20,
            "why": f"{clipped} commanded joint torques beyond the limit (every 10th sample)",
        }
    mu = effect.values["foot_friction"]
    force = data.contact_force_n
    normal = force[..., 2]
    tangential = np.linalg.norm(force[..., :2], axis=-1)
    stance = normal > 20.0
    # sliding: at the cone's edge; a foot that stays inside it moves as it would with the nominal friction
    near = int((tangential[stance] > 0.99 * mu * normal[stance]).sum())
    return {"detectable": near >= 25, "why": f"{near} stance samples sliding (>= 99% of the friction cone)"}


def plan(count: int, seed: int) -> list[tuple[str, list[str]]]:
    """Names and effect types of ``count`` datasets: 20% effect-free, 20% two effects, the rest single
    effects cycling over all types (so every type appears)."""
    rng = np.random.default_rng(seed)
    n_free = max(1, round(0.2 * count))
    n_two = max(1, round(0.2 * count))
    kinds: list[list[str]] = [[] for _ in range(n_free)]
    singles = count - n_free - n_two
    kinds += [[EFFECT_TYPES[i % len(EFFECT_TYPES)]] for i in range(singles)]
    for _ in range(n_two):
        # two ground models would set the same parameters; foot friction is rarely excited by these trots
        pair = rng.choice([k for k in EFFECT_TYPES if k not in ("foot_friction", "ground_nonlinear")], 2, replace=False)
        kinds.append([str(k) for k in pair])
    order = rng.permutation(len(kinds))
    return [(f"hidden_{i:02d}", kinds[j]) for i, j in enumerate(order)]


def generate_set(out_root: Path, count: int, seed: int = 0, progress: bool = True) -> list[tuple[Path, Path]]:
    """``count`` hidden-effect datasets under ``out_root`` (see ``plan``)."""
    rng = np.random.default_rng(seed + 1)
    out = []
    for i, (name, kinds) in enumerate(plan(count, seed)):
        effects = [draw_effect(k, rng) for k in kinds]
        if progress:
            sys.stderr.write(f"[hidden] {i + 1}/{count} {name}\n")
        out.append(generate_hidden(out_root, name, effects, seed=seed * 1000 + i))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Generate measured bags with sealed (hidden) model effects.")
    parser.add_argument("--out", type=Path, required=True, help="output folder (bags/ and sealed/)")
    parser.add_argument("--count", type=int, default=30, help="number of datasets (default 30)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    generate_set(args.out, args.count, args.seed)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
