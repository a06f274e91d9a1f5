"""The simulated Go1 log (tal_lab.go1_dataset) has a real Go1 log's form, goes through csv_import with its
column map and through the estimator with contact from the foot force counts (tal_lab.log_estimation)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
import yaml
from tal_lab.go1_dataset import generate, load_config
from tal_lab.log_estimation import estimate_log, estimator_settings, load_parameters, sensor_arrays_from_bag

from tal_core.robot_model import RobotModel
from tal_core.ros.csv_import import ColumnMap, CsvImportError, import_csv

DURATION_S = 2.5


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("go1") / "ds"
    generate(out, load_config(), duration_s=DURATION_S, progress=False)
    return out


def read_csv(path: Path) -> tuple[list[str], np.ndarray]:
    with path.open(newline="") as stream:
        rows = list(csv.reader(stream))
    return rows[0], np.array(rows[1:], dtype=float)


def test_the_log_has_a_go1_logs_form(dataset: Path) -> None:
    config = load_config()
    header, data = read_csv(dataset / "log.csv")
    assert header[:2] == ["stamp", "tick"] and not any(h.startswith(("dq", "tau", "effort")) for h in header)
    dt = np.diff(data[:, 0])
    assert np.all(dt > 0.0) and abs(np.median(dt) - 0.002) < 2e-4      # 500 Hz, increasing host stamps
    assert np.std(dt) > 5e-5                                            # with jitter
    assert len(data) < DURATION_S * 500                                  # a few rows dropped
    feet = data[:, [header.index(f"foot_force_{i}") for i in range(4)]]
    assert np.all(feet == np.round(feet)) and feet.min() >= 0 and feet.max() <= config["foot_force"]["max_counts"]
    offsets = np.array(list(config["foot_force"]["offset_counts"].values()))
    assert np.all(feet.max(axis=0) > 3 * offsets.max())                  # each foot carries load at times
    assert np.any(feet < offsets.max() + 20, axis=0).all()                 # and swings (about its offset)
    q = data[:, [header.index(f"q_{i}") for i in range(12)]]
    resolution = config["encoders"]["resolution_rad"]
    assert np.allclose(q / resolution, np.round(q / resolution), atol=1e-2)  # quantised encoders


def test_the_log_imports_and_the_estimator_runs_on_force_counts(dataset: Path, tmp_path: Path) -> None:
    estimate, truth, figures = estimate_log(dataset / "log.csv", dataset / "column_map.yaml",
                                            dataset / "estimator.yaml", dataset / "ground_truth.csv", tmp_path)
    params = load_parameters(dataset / "estimator.yaml")
    settings = estimator_settings(params)
    assert settings.leg_odometry.contact_source == "force_sensor" and params["robot"] == "go1"
    sensors = sensor_arrays_from_bag(tmp_path / "bag", RobotModel.from_name("go1"),
                                     ColumnMap.load(dataset / "column_map.yaml"), "force_sensor")
    assert sensors.joint_velocity is None and sensors.joint_torque is None and sensors.foot_contact is not None
    assert figures["skipped_rows"] == 0 and figures["imported_rows"] == len(sensors.t)
    assert figures["contact_agreement"] > 0.9                 # contact from the counts matches the truth's
    assert np.any(~estimate.contact) and np.any(estimate.contact)
    assert figures["velocity_rmse_m_s"] < 0.08
    assert abs(figures["final_z_drift_m"]) < 0.03
    assert figures["distance_true_m"] > 0.2 and abs(figures["distance_error_percent"]) < 20.0


def test_wrong_force_calibration_breaks_contact(dataset: Path, tmp_path: Path) -> None:
    """The contact really comes from the counts: an offset above every reading leaves no stance leg."""
    raw = yaml.safe_load((dataset / "estimator.yaml").read_text())
    raw["state_estimator"]["ros__parameters"]["foot_force_offset"] = [5000.0] * 4
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(raw))
    estimate, _, figures = estimate_log(dataset / "log.csv", dataset / "column_map.yaml", tmp_path / "bad.yaml",
                                        dataset / "ground_truth.csv", tmp_path)
    assert not np.any(estimate.contact) and figures["contact_agreement"] < 0.5


def test_a_log_missing_a_mapped_column_is_refused_naming_it(dataset: Path, tmp_path: Path) -> None:
    header, data = read_csv(dataset / "log.csv")
    keep = [i for i, h in enumerate(header) if h != "foot_force_2"]
    with (tmp_path / "log.csv").open("w", newline="") as stream:
        writer = csv.writer(stream)
        writer.writerow([header[i] for i in keep])
        writer.writerows(data[:20, keep].tolist())
    with pytest.raises(CsvImportError, match=r"log.csv line 1: column 'foot_force_2' \(foot_contacts.force of "
                                             r"(LF|RF|LH|RH), map .*column_map.yaml\) is not in the header"):
        import_csv(tmp_path / "log.csv", dataset / "column_map.yaml", tmp_path / "bag")
