"""A simulated robot log in the form a real quadruped writes it (default: Unitree Go1 trotting), for the
estimator on real robots' sensors (issue 32 item 3).

    python -m tal_lab.go1_dataset --out DIR [--duration 20] [--seed 0] [--config tal_lab/config/go1_dataset.yaml]

The in-process closed loop (sWBC on ground truth, 1 kHz PyBullet) trots the robot over the config's floor
(friction below what the WBC plans with, so stance feet slip; a soft gym mat across the path). Every number of
the robot, the gait, the command and the sensor model comes from the config YAML; this module has none.
At the log rate (500 Hz) it writes what the robot's low-level state stream gives, with the sensors' flaws:

* IMU at the URDF's IMU link (the lever arm's angular and centripetal terms included): white noise and a
  constant bias per axis (drawn from the seed);
* joint encoders: a per-joint zero-calibration offset, white noise, quantisation to the encoder resolution;
* foot force sensors: raw counts = offset + normal force / scale, lagged (first order), noisy, rounded,
  saturated at the sensor's maximum, per-leg scale and offset;
* host stamps: sample time + latency + clipped white jitter; a few rows dropped by the logger;
* no joint torques and no joint velocities.

Files in DIR:

* ``log.csv``: the log. ``stamp`` [s] host time, ``tick`` [ms] robot clock, ``q_0``..``q_11`` [rad] in the
  robot's motor order (config ``log.motor_joints``), ``gyro_x/y/z`` [rad/s] and ``acc_x/y/z`` [m/s^2] in the
  IMU frame, ``foot_force_0``..``foot_force_3`` [counts] in the robot's foot order (config ``log.foot_legs``).
* ``column_map.yaml``: the csv_import column map of ``log.csv``.
* ``estimator.yaml``: the state_estimator node's parameters for it (contact_source force_sensor with the
  user's per-leg calibration, derived joint velocities, tick period and stamp tolerance).
* ``ground_truth.csv``: for evaluation only. ``t_s`` sim time, ``stamp`` the log's stamp of that sample (also
  for dropped rows), base position [m] and quaternion xyzw (world), world velocity [m/s], true contacts and
  normal forces [N] per leg LF, RF, LH, RH.
* ``manifest.yaml``: config, seed, the drawn sensor errors, the true calibration, foot slip, distance.
"""

from __future__ import annotations

import argparse
import copy
import csv
import logging
import math
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from tal_control.motion.gait import GaitParameters
from tal_control.wbc import WbcGains
from tal_core.legs import LEGS, NUM_LEGS
from tal_core.robot_description import RobotDescription, load_robot_description
from tal_core.rotations import rotation_from_quat_xyzw
from tal_core.terrain import load_course
from tal_lab.closed_loop import ClosedLoopConfig, run_closed_loop, stance_slip
from tal_sim_bridge.bridge_core import BridgeCore
from tal_sim_bridge.physics import RobotState

LOG = logging.getLogger("tal_lab.go1_dataset")
CONFIG_DIR = Path(__file__).resolve().parent / "config"
DEFAULT_CONFIG = CONFIG_DIR / "go1_dataset.yaml"
GRAVITY_M_S2 = 9.81
LEG_NAMES = tuple(leg.name for leg in LEGS)  # LF, RF, LH, RH


class DatasetConfigError(ValueError):
    """The dataset config is incomplete or inconsistent (the message names the entry)."""


def load_config(path: str | Path = DEFAULT_CONFIG) -> dict:
    """The dataset config (YAML) with the course resolved relative to the file; DatasetConfigError names a
    missing section."""
    path = Path(path)
    config = yaml.safe_load(path.read_text())
    for key in ("robot", "course", "duration_s", "seed", "gait", "commands", "log", "imu", "encoders",
                "foot_force", "estimator"):
        if key not in config:
            raise DatasetConfigError(f"{path}: missing '{key}'")
    course = Path(str(config["course"]))
    if course.suffix in (".yaml", ".yml") and not course.is_absolute():
        config["course"] = str(path.parent / course)
    config["source"] = str(path)
    return config


def _portable(path: object) -> object:
    """A path inside the repository as relative to its root (a manifest is committed; an absolute path names
    one machine's checkout); anything else as it is."""
    if not isinstance(path, str):
        return path
    root = Path(__file__).resolve().parents[2]
    try:
        return str(Path(path).resolve().relative_to(root))
    except ValueError:
        return path


def _per_leg(config: dict, section: str, key: str) -> np.ndarray:
    values = config[section][key]
    if set(values) != set(LEG_NAMES):
        raise DatasetConfigError(f"{section}.{key} needs the legs {LEG_NAMES}, got {sorted(values)}")
    return np.array([float(values[leg]) for leg in LEG_NAMES])


def gait_from_config(config: dict) -> GaitParameters:
    gait = dict(config["gait"])
    gait["phase_offsets"] = tuple(gait.get("phase_offsets", (0.0,) * NUM_LEGS))
    return GaitParameters(**gait)


@dataclass
class SensorErrors:
    """The constant sensor errors drawn from the seed, and the calibration the user gives the estimator."""

    gyro_bias_rad_s: np.ndarray
    accel_bias_m_s2: np.ndarray
    joint_offset_rad: np.ndarray           # canonical joint order
    force_scale_n_per_count: np.ndarray    # LF, RF, LH, RH (true)
    force_offset_counts: np.ndarray
    calibration_scale: np.ndarray          # the user's calibration
    calibration_offset: np.ndarray

    @classmethod
    def draw(cls, config: dict, n_joints: int, rng: np.random.Generator) -> SensorErrors:
        imu, enc, ff = config["imu"], config["encoders"], config["foot_force"]
        scale = _per_leg(config, "foot_force", "scale_n_per_count")
        offset = _per_leg(config, "foot_force", "offset_counts")
        return cls(
            gyro_bias_rad_s=rng.normal(0.0, float(imu["gyro_bias_std_rad_s"]), 3),
            accel_bias_m_s2=rng.normal(0.0, float(imu["accel_bias_std_m_s2"]), 3),
            joint_offset_rad=rng.normal(0.0, float(enc["offset_std_rad"]), n_joints),
            force_scale_n_per_count=scale,
            force_offset_counts=offset,
            calibration_scale=scale * (1.0 + rng.normal(0.0, float(ff["calibration_scale_error"]), NUM_LEGS)),
            calibration_offset=offset + rng.normal(0.0, float(ff["calibration_offset_error_counts"]), NUM_LEGS),
        )


class SensorLog:
    """Step hook of the closed loop: models the sensors every physics step and keeps a row at the log rate."""

    def __init__(self, config: dict, description: RobotDescription, physics_dt_s: float,
                 rng: np.random.Generator) -> None:
        self.config = config
        self.description = description
        self.dt = physics_dt_s
        self.rng = rng
        self.errors = SensorErrors.draw(config, len(description.joint_names), rng)
        log = config["log"]
        every = 1.0 / (float(log["rate_hz"]) * physics_dt_s)
        if abs(every - round(every)) > 1e-6 or round(every) < 1:
            raise DatasetConfigError(f"log.rate_hz {log['rate_hz']} must divide the physics rate {1 / physics_dt_s} Hz")
        self.every = round(every)
        names = list(description.joint_names)
        motor = [str(j) for j in log["motor_joints"]]
        if sorted(motor) != sorted(names):
            raise DatasetConfigError(f"log.motor_joints must list the robot's joints {names}, got {motor}")
        self.motor_index = [names.index(j) for j in motor]            # column q_i <- canonical joint
        feet = [str(leg) for leg in log["foot_legs"]]
        if sorted(feet) != sorted(LEG_NAMES):
            raise DatasetConfigError(f"log.foot_legs must list {LEG_NAMES} in the robot's foot order, got {feet}")
        self.foot_index = [LEG_NAMES.index(leg) for leg in feet]       # column foot_force_i <- tal leg
        self.base_R_imu = rotation_from_quat_xyzw(np.asarray(description.base_quat_imu_xyzw, float))
        self.imu_position = np.asarray(description.imu_position_base_m, float)
        self.force_lagged = np.zeros(NUM_LEGS)
        self.force_alpha = 1.0 - math.exp(-physics_dt_s / float(config["foot_force"]["time_constant_s"]))
        self.previous_omega: np.ndarray | None = None
        self.steps = 0
        self.rows: list[list[float]] = []
        self.truth: list[list[float]] = []

    def header(self) -> list[str]:
        return (["stamp", "tick"] + [f"q_{i}" for i in range(len(self.motor_index))]
                + [f"gyro_{a}" for a in "xyz"] + [f"acc_{a}" for a in "xyz"]
                + [f"foot_force_{i}" for i in range(NUM_LEGS)])

    @staticmethod
    def truth_header() -> list[str]:
        return (["t_s", "stamp", "x", "y", "z", "qx", "qy", "qz", "qw", "vx", "vy", "vz"]
                + [f"contact_{leg}" for leg in LEG_NAMES] + [f"normal_force_{leg}_n" for leg in LEG_NAMES])

    def on_step(self, t_s: float, state: RobotState, core: BridgeCore) -> None:
        contacts = core.sim.foot_contacts()
        normal = np.array([max(0.0, float(c.force_n @ c.normal)) if c.in_contact else 0.0 for c in contacts])
        if self.steps == 0:
            self.force_lagged = normal.copy()  # the sensor has settled before the log starts
        self.force_lagged += self.force_alpha * (normal - self.force_lagged)
        omega = np.asarray(state.base_ang_vel_rad_s, float)
        alpha = np.zeros(3) if self.previous_omega is None else (omega - self.previous_omega) / self.dt
        self.previous_omega = omega
        self.steps += 1
        if self.steps % self.every:
            return
        log, enc, ff, imu = self.config["log"], self.config["encoders"], self.config["foot_force"], self.config["imu"]
        jitter = float(np.clip(self.rng.normal(0.0, float(log["stamp_jitter_std_s"])),
                               -float(log["stamp_jitter_max_s"]), float(log["stamp_jitter_max_s"])))
        stamp = t_s + float(log["stamp_latency_s"]) + jitter
        self.truth.append([t_s, stamp, *state.base_position_m, *state.base_quat_xyzw, *state.base_lin_vel_m_s,
                           *[float(c.in_contact) for c in contacts], *normal])
        f_imu, w_imu = self._imu(state, omega, alpha, imu)
        q = state.joint_position_rad + self.errors.joint_offset_rad
        q = q + self.rng.normal(0.0, float(enc["noise_std_rad"]), len(q))
        resolution = float(enc["resolution_rad"])
        q = np.round(q / resolution) * resolution
        counts = (self.errors.force_offset_counts + self.force_lagged / self.errors.force_scale_n_per_count
                  + self.rng.normal(0.0, float(ff["noise_std_counts"]), NUM_LEGS))
        counts = np.clip(np.round(counts), 0, int(ff["max_counts"]))
        if self.rng.random() < float(log["drop_probability"]):
            return  # the logger lost this row (the truth keeps it)
        self.rows.append([round(stamp, 6), int(round(t_s * 1000.0)), *q[self.motor_index], *w_imu, *f_imu,
                          *counts[self.foot_index]])

    def _imu(self, state: RobotState, omega_world: np.ndarray, alpha_world: np.ndarray,
             imu: dict) -> tuple[np.ndarray, np.ndarray]:
        """Specific force [m/s^2] and angular rate [rad/s] at the IMU link, IMU frame, with bias and noise."""
        base_R_world = rotation_from_quat_xyzw(state.base_quat_xyzw).T
        w = base_R_world @ omega_world
        dw = base_R_world @ alpha_world
        r = self.imu_position
        f = base_R_world @ (state.base_lin_acc_m_s2 - np.array([0.0, 0.0, -GRAVITY_M_S2]))
        f = f + np.cross(dw, r) + np.cross(w, np.cross(w, r))
        imu_R_base = self.base_R_imu.T
        f_imu = imu_R_base @ f + self.errors.accel_bias_m_s2 + self.rng.normal(
            0.0, float(imu["accel_noise_std_m_s2"]), 3)
        w_imu = imu_R_base @ w + self.errors.gyro_bias_rad_s + self.rng.normal(
            0.0, float(imu["gyro_noise_std_rad_s"]), 3)
        return f_imu, w_imu


def column_map(config: dict, description: RobotDescription, sensor: SensorLog) -> str:
    """The csv_import column map of the log (YAML text, commented)."""
    names = list(description.joint_names)
    motor_of = {names[canonical]: i for i, canonical in enumerate(sensor.motor_index)}
    foot_of = {LEG_NAMES[leg]: i for i, leg in enumerate(sensor.foot_index)}
    doc = {
        "time": {"column": "stamp", "unit": "s"},
        "joint_states": {"joints": names, "position": {"columns": [f"q_{motor_of[j]}" for j in names], "unit": "rad"}},
        "imu": {"angular_velocity": {a: {"column": f"gyro_{a}", "unit": "rad/s"} for a in "xyz"},
                "linear_acceleration": {a: {"column": f"acc_{a}", "unit": "m/s^2"} for a in "xyz"}},
        "foot_contacts": {"force": {"columns": [f"foot_force_{foot_of[leg]}" for leg in LEG_NAMES],
                                    "unit": "count"}},
    }
    head = (f"# csv_import column map of a {config['robot']} log (python -m tal_core.ros.csv_import log.csv --map "
            "column_map.yaml --out BAG).\n# Joint positions are listed in the robot description's joint order, "
            "feet in tal's leg order LF, RF, LH, RH;\n# the log has no joint velocities and no torques (the "
            "estimator derives the velocities; contact comes from the foot force counts).\n")
    return head + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=110)


def estimator_parameters(config: dict, sensor: SensorLog) -> str:
    """The state_estimator node's parameters for the log (YAML text)."""
    est = config["estimator"]
    params = {"robot": config["robot"], "period_s": float(est["period_s"]),
              "tick_tolerance_s": float(est["tick_tolerance_s"]), "leg_odometry": str(est["leg_odometry"]),
              "contact_source": "force_sensor", "joint_velocities_optional": True,
              "foot_force_scale": [round(float(v), 4) for v in sensor.errors.calibration_scale],
              "foot_force_offset": [round(float(v), 1) for v in sensor.errors.calibration_offset]}
    head = ("# state_estimator parameters for the log (foot_force_* per leg LF, RF, LH, RH: force [N] = scale x "
            "(counts - offset),\n# the user's calibration, a few % off the sensor's true one).\n")
    return head + yaml.safe_dump({"state_estimator": {"ros__parameters": params}}, sort_keys=False,
                                 default_flow_style=None)


def generate(out: str | Path, config: dict | None = None, *, duration_s: float | None = None,
             seed: int | None = None, progress: bool = True) -> dict:
    """Run the closed loop and write the dataset folder ``out`` (replaced). Returns the manifest."""
    config = copy.deepcopy(config if config is not None else load_config())
    if duration_s is not None:
        config["duration_s"] = float(duration_s)
    if seed is not None:
        config["seed"] = int(seed)
    out = Path(out)
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    description = load_robot_description(config["robot"])
    course = load_course(config["course"])
    loop = ClosedLoopConfig(name=f"{config['robot']}_dataset", robot=config["robot"], course=course,
                            gait=gait_from_config(config), gains=WbcGains(**config.get("wbc_gains", {})),
                            commands=tuple(tuple(c) for c in config["commands"]),
                            duration_s=float(config["duration_s"]), progress=progress)
    sensor = SensorLog(config, description, loop.physics_dt_s, np.random.default_rng(int(config["seed"])))
    result = run_closed_loop(loop, step_hook=sensor.on_step)
    if result.fell:
        raise RuntimeError(f"the robot fell at t = {result.meta['fall_time_s']} s ({result.meta['fall_reason']})")
    for name, header, rows in (("log.csv", sensor.header(), sensor.rows),
                               ("ground_truth.csv", sensor.truth_header(), sensor.truth)):
        with (out / name).open("w", newline="") as stream:
            writer = csv.writer(stream)
            writer.writerow(header)
            writer.writerows([[_cell(v) for v in row] for row in rows])
    (out / "column_map.yaml").write_text(column_map(config, description, sensor))
    (out / "estimator.yaml").write_text(estimator_parameters(config, sensor))
    truth = np.array(sensor.truth)
    xy = truth[:, 2:4]
    slip = stance_slip(result)
    errors = sensor.errors
    manifest = {
        "robot": config["robot"], "config": _portable(config.get("source")),
        "seed": int(config["seed"]), "duration_s": float(config["duration_s"]), "course": course.name,
        "rows": len(sensor.rows), "samples": len(sensor.truth), "dropped_rows": len(sensor.truth) - len(sensor.rows),
        "distance_m": round(float(np.sum(np.linalg.norm(np.diff(xy[::50], axis=0), axis=1))), 3),
        "foot_slip_m": {leg: round(float(v), 4) for leg, v in zip(LEG_NAMES, slip["contact_point"], strict=True)},
        "sensor_errors": {
            "gyro_bias_rad_s": np.round(errors.gyro_bias_rad_s, 5).tolist(),
            "accel_bias_m_s2": np.round(errors.accel_bias_m_s2, 4).tolist(),
            "joint_offset_rad": np.round(errors.joint_offset_rad, 5).tolist(),
            "foot_force_scale_true": errors.force_scale_n_per_count.tolist(),
            "foot_force_offset_true": errors.force_offset_counts.tolist(),
            "foot_force_saturated_fraction": round(float(np.mean(
                np.array(sensor.rows)[:, -NUM_LEGS:] >= int(config["foot_force"]["max_counts"]))), 4),
        },
        "config_used": {k: _portable(v) if k == "course" else v for k, v in config.items() if k != "source"},
    }
    (out / "manifest.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False, default_flow_style=None, width=110))
    return manifest


def _cell(value: float) -> str:
    if isinstance(value, int) or (isinstance(value, float) and value.is_integer() and abs(value) < 1e6):
        return str(int(value))
    return f"{value:.7g}" if abs(value) < 1e3 else f"{value:.6f}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="dataset folder to create (replaced)")
    parser.add_argument("--config", type=Path, default=DEFAULT_CONFIG, help="dataset config YAML")
    parser.add_argument("--duration", type=float, default=None, help="sim time [s] (default: the config's)")
    parser.add_argument("--seed", type=int, default=None, help="sensor noise seed (default: the config's)")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        manifest = generate(args.out, load_config(args.config), duration_s=args.duration, seed=args.seed,
                            progress=not args.quiet)
    except (DatasetConfigError, RuntimeError) as exc:
        LOG.error("%s", exc)
        return 1
    sys.stdout.write(f"{args.out}: {manifest['rows']} rows ({manifest['dropped_rows']} dropped), "
                     f"{manifest['distance_m']} m, foot slip {manifest['foot_slip_m']}\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
