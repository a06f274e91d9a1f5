"""The state estimator on a robot's own CSV log: import it through its column map (``csv_import``), run the
estimator with the state_estimator node's parameters file, and compare with a ground-truth CSV.

    python -m tal_lab.log_estimation --dataset DIR [--out DIR] [--plot PATH]
    python -m tal_lab.log_estimation --csv LOG.csv --map MAP.yaml --params PARAMS.yaml --truth TRUTH.csv --out DIR

``--dataset DIR`` reads ``log.csv``, ``column_map.yaml``, ``estimator.yaml`` and ``ground_truth.csv`` from DIR
(the layout ``tal_lab.go1_dataset`` writes). Nothing here knows the robot: the robot comes from the parameters
(``robot``), the columns from the map, the contact source and its calibration from the parameters.

The ground truth CSV has ``stamp`` [s] (the log's time of the sample), ``x, y, z`` [m], ``qx, qy, qz, qw`` and
``vx, vy, vz`` [m/s] (world); optional ``contact_<LEG>`` (0/1, LF, RF, LH, RH). The estimator starts at the
truth's first pose (as the node's ``initial_pose_source:=ground_truth``, a motion-capture start). Figures
(``drift_figures``): distance travelled (horizontal path length at 10 Hz) of estimate and truth, horizontal
path error RMS as % of the true distance, world velocity RMSE (3D and horizontal), final z drift, final
horizontal drift, and the contact agreement with the truth when it has contacts.
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import sys
from pathlib import Path

import numpy as np
import yaml

from tal_core.errors import InputError
from tal_core.legs import LEGS
from tal_core.robot_model import RobotModel
from tal_core.ros.bag_io import BagReader
from tal_core.ros.csv_import import ColumnMap, import_csv
from tal_core.rotations import rotation_from_quat_xyzw
from tal_estimation.attitude import AttitudeSettings
from tal_estimation.leg_odometry import LegOdometrySettings
from tal_estimation.messages import foot_contact_values, joint_state_arrays
from tal_estimation.state_estimator import StateEstimatorSettings
from tal_lab.offline_estimation import EstimateArrays, SensorArrays, run_estimator

LOG = logging.getLogger("tal_lab.log_estimation")
LEG_NAMES = tuple(leg.name for leg in LEGS)
PATH_SAMPLE_S = 0.1  # [s] the path length is measured on 10 Hz samples (the trot's sway is not distance)

# state_estimator parameters -> StateEstimatorSettings fields (the node's names)
_TOP = ("period_s", "accel_noise_m_s2", "leg_velocity_noise_m_s", "vertical_crossover_rad_s", "leg_velocity_gate_m_s",
        "max_gap_periods",
        "accel_range_m_s2", "gyro_range_rad_s", "joint_velocity_cutoff_hz", "tick_tolerance_s")
_LEG = {"leg_odometry": "mode", "contact_source": "contact_source",
        "contact_threshold_weight_fraction": "contact_threshold_weight_fraction",
        "contact_hysteresis_fraction": "contact_hysteresis_fraction", "foot_force_scale": "foot_force_scale",
        "foot_force_offset": "foot_force_offset"}
_ATTITUDE = {"attitude_k_p": "k_p", "attitude_k_i": "k_i"}
_NOT_OFFLINE = ("robot", "joint_velocities_optional", "initial_pose_source", "initial_xy_m", "use_magnetometer",
                "magnetic_field_world", "summary_path", "use_sim_time")


def load_parameters(path: str | Path) -> dict:
    """The ``ros__parameters`` of the state_estimator in a node parameters file (or a flat mapping)."""
    raw = yaml.safe_load(Path(path).read_text()) or {}
    params = raw.get("state_estimator", {}).get("ros__parameters", raw) if isinstance(raw, dict) else None
    if not isinstance(params, dict):
        raise InputError(f"{path}: expected state_estimator: ros__parameters: {{...}}")
    return params


def estimator_settings(params: dict, source: str = "<parameters>") -> StateEstimatorSettings:
    """StateEstimatorSettings from the node's parameter names; InputError names an unknown parameter."""
    unknown = sorted(set(params) - set(_TOP) - set(_LEG) - set(_ATTITUDE) - set(_NOT_OFFLINE))
    if unknown:
        raise InputError(f"{source}: unknown state_estimator parameter(s) {unknown}")
    leg = {field: (tuple(params[key]) if key.startswith("foot_force") else params[key])
           for key, field in _LEG.items() if key in params}
    attitude = {field: float(params[key]) for key, field in _ATTITUDE.items() if key in params}
    top = {key: params[key] for key in _TOP if key in params}
    return StateEstimatorSettings(**top, attitude=AttitudeSettings(**attitude), leg_odometry=LegOdometrySettings(**leg))


def sensor_arrays_from_bag(bag: str | Path, model: RobotModel, cmap: ColumnMap, contact_source: str) -> SensorArrays:
    """One row per stamp at which the bag (as csv_import writes it) has joint states and IMU (and the feet's
    sensor values for a sensor contact source). Joint velocities and torques are None when the log has none."""
    topics = [cmap.topics["joint_states"], cmap.topics["imu"]]
    sensed = contact_source != "torque"
    if sensed:
        topics.append(cmap.topics["foot_contacts"])
    index = {name: i for i, name in enumerate(model.description.joint_names)}
    rows: dict[str, list] = {k: [] for k in ("t", "f", "w", "q", "qd", "tau", "feet")}
    slot: dict[str, object] = {}
    stamp = None

    def flush() -> None:
        if len(slot) < len(topics):
            return
        js, imu = slot[topics[0]], slot[topics[1]]
        q, qd, tau = joint_state_arrays(js, index, velocities_optional=True, efforts_optional=sensed)
        a, g = imu.linear_acceleration, imu.angular_velocity
        rows["t"].append(stamp * 1e-9)
        rows["f"].append([a.x, a.y, a.z])
        rows["w"].append([g.x, g.y, g.z])
        rows["q"].append(q)
        rows["qd"].append(qd)
        rows["tau"].append(tau)
        rows["feet"].append(foot_contact_values(slot[topics[2]], contact_source) if sensed else None)

    for message in BagReader(bag).messages(topics):
        if message.log_time_ns != stamp:
            if stamp is not None:
                flush()
            slot, stamp = {}, message.log_time_ns
        slot[message.topic] = message.message
    if stamp is not None:
        flush()
    if not rows["t"]:
        raise InputError(f"{bag}: no stamp with all of {topics}")

    def stacked(key: str) -> np.ndarray | None:
        return None if rows[key][0] is None else np.array(rows[key], float)

    return SensorArrays(t=np.array(rows["t"]), specific_force=np.array(rows["f"]), angular_rate=np.array(rows["w"]),
                        joint_position=np.array(rows["q"]), joint_velocity=stacked("qd"), joint_torque=stacked("tau"),
                        foot_contact=stacked("feet"))


def load_truth(path: str | Path) -> dict[str, np.ndarray]:
    """Ground-truth columns as arrays (stamp, position (N, 3), quat_xyzw (N, 4), velocity (N, 3), contact)."""
    with Path(path).open(newline="") as stream:
        reader = csv.reader(stream)
        header = next(reader)
        data = np.array([[float(v) for v in row] for row in reader if row])
    col = {name: i for i, name in enumerate(header)}
    missing = [c for c in ("stamp", "x", "y", "z", "qx", "qy", "qz", "qw", "vx", "vy", "vz") if c not in col]
    if missing:
        raise InputError(f"{path}: ground truth lacks column(s) {missing}")
    out = {"stamp": data[:, col["stamp"]], "position": data[:, [col[c] for c in "xyz"]],
           "quat_xyzw": data[:, [col[c] for c in ("qx", "qy", "qz", "qw")]],
           "velocity": data[:, [col[c] for c in ("vx", "vy", "vz")]]}
    if all(f"contact_{leg}" in col for leg in LEG_NAMES):
        out["contact"] = data[:, [col[f"contact_{leg}"] for leg in LEG_NAMES]] > 0.5
    return out


def _interpolate(t: np.ndarray, tt: np.ndarray, values: np.ndarray) -> np.ndarray:
    return np.stack([np.interp(t, tt, values[:, k]) for k in range(values.shape[1])], axis=1)


def path_length(t: np.ndarray, xy: np.ndarray, sample_s: float = PATH_SAMPLE_S) -> float:
    """Horizontal path length [m] of ``xy`` resampled every ``sample_s`` [s]."""
    grid = np.arange(t[0], t[-1] + 1e-9, sample_s)
    points = _interpolate(grid, t, xy)
    return float(np.sum(np.linalg.norm(np.diff(points, axis=0), axis=1)))


def drift_figures(estimate: EstimateArrays, truth: dict[str, np.ndarray]) -> dict[str, float]:
    """The drift figures of the estimate against the truth over the estimate's time span (module docstring)."""
    t = estimate.t
    inside = (t >= truth["stamp"][0]) & (t <= truth["stamp"][-1])
    t = t[inside]
    p_true = _interpolate(t, truth["stamp"], truth["position"])
    v_true = _interpolate(t, truth["stamp"], truth["velocity"])
    p_est, v_est = estimate.position[inside], estimate.linear_velocity[inside]
    distance_true = path_length(t, p_true[:, :2])
    distance_est = path_length(t, p_est[:, :2])
    horizontal = np.linalg.norm(p_est[:, :2] - p_true[:, :2], axis=1)
    figures = {
        "duration_s": float(t[-1] - t[0]),
        "ticks": int(len(t)),
        "distance_true_m": distance_true,
        "distance_estimate_m": distance_est,
        "distance_error_percent": 100.0 * (distance_est - distance_true) / distance_true,
        "path_error_rms_m": float(np.sqrt(np.mean(horizontal ** 2))),
        "path_error_rms_percent_of_distance": 100.0 * float(np.sqrt(np.mean(horizontal ** 2))) / distance_true,
        "final_horizontal_drift_m": float(horizontal[-1]),
        "final_horizontal_drift_percent": 100.0 * float(horizontal[-1]) / distance_true,
        "final_z_drift_m": float(p_est[-1, 2] - p_true[-1, 2]),
        "z_rms_m": float(np.sqrt(np.mean((p_est[:, 2] - p_true[:, 2]) ** 2))),
        "velocity_rmse_m_s": float(np.sqrt(np.mean(np.sum((v_est - v_true) ** 2, axis=1)))),
        "velocity_rmse_horizontal_m_s": float(np.sqrt(np.mean(np.sum((v_est[:, :2] - v_true[:, :2]) ** 2, axis=1)))),
    }
    if "contact" in truth:
        nearest = np.clip(np.searchsorted(truth["stamp"], t), 0, len(truth["stamp"]) - 1)
        figures["contact_agreement"] = float(np.mean(estimate.contact[inside] == truth["contact"][nearest]))
    return figures


def estimate_log(csv_path: str | Path, map_path: str | Path, params_path: str | Path, truth_path: str | Path,
                 work: str | Path, overrides: dict | None = None,
                 ) -> tuple[EstimateArrays, dict[str, np.ndarray], dict[str, float]]:
    """Import ``csv_path`` into ``work/bag``, run the estimator (parameters from ``params_path``, then
    ``overrides``) and compare with the truth."""
    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    bag = work / "bag"
    if bag.exists():
        import shutil

        shutil.rmtree(bag)
    cmap = ColumnMap.load(map_path)
    report = import_csv(csv_path, cmap, bag)
    params = {**load_parameters(params_path), **(overrides or {})}
    settings = estimator_settings(params, str(params_path))
    model = RobotModel.from_name(str(params.get("robot", "hyq")))
    sensors = sensor_arrays_from_bag(bag, model, ColumnMap.load(map_path), settings.leg_odometry.contact_source)
    truth = load_truth(truth_path)
    start = int(np.argmin(np.abs(truth["stamp"] - sensors.t[0])))
    estimate = run_estimator(model, sensors, settings, initial_position=truth["position"][start],
                             initial_world_R_base=rotation_from_quat_xyzw(truth["quat_xyzw"][start]))
    figures = drift_figures(estimate, truth)
    figures["imported_rows"] = report.rows
    figures["skipped_rows"] = int(sum(report.skipped_rows.values()))
    return estimate, truth, figures


def plot(estimate: EstimateArrays, truth: dict[str, np.ndarray], figures: dict[str, float], path: str | Path,
         title: str = "") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = estimate.t
    p_true = _interpolate(t, truth["stamp"], truth["position"])
    v_true = _interpolate(t, truth["stamp"], truth["velocity"])
    fig, axes = plt.subplots(2, 2, figsize=(11, 8))
    ax = axes[0, 0]
    ax.plot(truth["position"][:, 0], truth["position"][:, 1], "k", label="truth")
    ax.plot(estimate.position[:, 0], estimate.position[:, 1], "C1", label="estimate")
    ax.set(xlabel="x [m]", ylabel="y [m]", title="horizontal path", aspect="equal")
    ax.legend()
    ax = axes[0, 1]
    ax.plot(t - t[0], np.linalg.norm(estimate.position[:, :2] - p_true[:, :2], axis=1), label="horizontal")
    ax.plot(t - t[0], estimate.position[:, 2] - p_true[:, 2], label="z")
    ax.set(xlabel="t [s]", ylabel="error [m]", title="position error (estimate - truth)")
    ax.legend()
    for k, ax in zip((0, 1), axes[1], strict=True):
        ax.plot(t - t[0], v_true[:, k], "k", lw=0.8, label="truth")
        ax.plot(t - t[0], estimate.linear_velocity[:, k], "C1", lw=0.6, label="estimate")
        ax.set(xlabel="t [s]", ylabel=f"v{'xy'[k]} [m/s] world", title=f"velocity {'xy'[k]}")
        ax.legend()
    f = figures
    fig.suptitle(f"{title} distance {f['distance_true_m']:.2f} m (estimate {f['distance_error_percent']:+.1f} %), "
                 f"path RMS {f['path_error_rms_percent_of_distance']:.2f} %, v RMSE {f['velocity_rmse_m_s']:.3f} "
                 f"m/s, final z {f['final_z_drift_m']:+.3f} m")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", type=Path, help="folder with log.csv, column_map.yaml, estimator.yaml, "
                        "ground_truth.csv")
    parser.add_argument("--csv", type=Path)
    parser.add_argument("--map", type=Path)
    parser.add_argument("--params", type=Path, help="state_estimator parameters YAML")
    parser.add_argument("--truth", type=Path)
    parser.add_argument("--out", type=Path, help="where figures.json and the plot go (default: the "
                        "dataset folder)")
    parser.add_argument("--plot", type=Path, help="PNG path (default OUT/estimate.png)")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="override a state_estimator parameter (YAML value), e.g. leg_odometry=rigid")
    parser.add_argument("--work", type=Path, help="folder for the imported bag (default: the dataset folder, "
                        "else OUT)")
    parser.add_argument("--name", default="", help="name of this run in figures.json and the plot title")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    if args.dataset is not None:
        args.csv = args.csv or args.dataset / "log.csv"
        args.map = args.map or args.dataset / "column_map.yaml"
        args.params = args.params or args.dataset / "estimator.yaml"
        args.truth = args.truth or args.dataset / "ground_truth.csv"
        args.out = args.out or args.dataset
    if None in (args.csv, args.map, args.params, args.truth, args.out):
        parser.error("give --dataset, or --csv, --map, --params, --truth and --out")
    overrides = {}
    for item in args.set:
        name, sep, value = item.partition("=")
        if not sep:
            parser.error(f"--set needs NAME=VALUE, got {item!r}")
        overrides[name.strip()] = yaml.safe_load(value)
    try:
        estimate, truth, figures = estimate_log(args.csv, args.map, args.params, args.truth,
                                                args.work or args.dataset or args.out, overrides)
    except InputError as exc:
        LOG.error("%s", exc)
        return 2
    figures = {"name": args.name or args.csv.name, "overrides": overrides, **figures}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "figures.json").write_text(json.dumps(figures, indent=2) + "\n")
    plot(estimate, truth, figures, args.plot or args.out / "estimate.png", title=args.name or args.csv.name)
    for key, value in figures.items():
        sys.stdout.write(f"{key:38s} {value:.4g}\n" if isinstance(value, float) else f"{key:38s} {value}\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
