"""Tests of tal_core.robot_description: shipped YAMLs, URDF defaults, overrides, torque tables, errors."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from tal_core.errors import InputError, RobotConfigError
from tal_core.legs import Leg
from tal_core.robot_description import (
    EXAMPLE_ROBOT_DATA_ENV,
    RobotDescription,
    find_example_robot_data_dir,
    load_robot_description,
    read_urdf_summary,
    shipped_robot_names,
)

HYQ_YAML = Path(__file__).resolve().parents[1] / "tal_core" / "config" / "robots" / "hyq.yaml"


def hyq_document() -> dict[str, Any]:
    return yaml.safe_load(HYQ_YAML.read_text(encoding="utf-8"))


def write_yaml(tmp_path: Path, document: dict[str, Any], name: str = "robot.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    return path


# ----------------------------------------------------------------------------------------------------
# Shipped robots
# ----------------------------------------------------------------------------------------------------
def test_shipped_robots_are_listed() -> None:
    assert {"hyq", "solo12"} <= set(shipped_robot_names())


def test_hyq_names_follow_the_canonical_order() -> None:
    hyq = load_robot_description("hyq")
    assert hyq.name == "hyq"
    assert hyq.joint_names[:3] == ("lf_haa_joint", "lf_hfe_joint", "lf_kfe_joint")
    assert hyq.joint_names[RobotDescription.joint_index(Leg.LH, "KFE")] == "lh_kfe_joint"
    assert hyq.leg_joint_names(Leg.RH) == ("rh_haa_joint", "rh_hfe_joint", "rh_kfe_joint")
    assert tuple(hyq.foot_frames) == ("lf_foot", "rf_foot", "lh_foot", "rh_foot")
    assert hyq.hip_frames[Leg.RF] == "rf_haa_joint"
    assert hyq.foot_radius_m == pytest.approx(0.02175)
    assert hyq.urdf_path.name == "hyq_no_sensors.urdf" and hyq.urdf_path.is_file()


def test_hyq_limits_default_to_the_urdf() -> None:
    hyq = load_robot_description("hyq")
    np.testing.assert_allclose(hyq.velocity_limit_rad_s, 12.0)
    tau_min, tau_max = hyq.torque_limits(hyq.nominal_joint_positions_rad)
    np.testing.assert_allclose(tau_max, 150.0)
    np.testing.assert_allclose(tau_min, -150.0)
    lf_kfe = RobotDescription.joint_index(Leg.LF, "KFE")
    lh_kfe = RobotDescription.joint_index(Leg.LH, "KFE")
    assert hyq.position_lower_rad[lf_kfe] == pytest.approx(-2.44346095279)
    assert hyq.position_upper_rad[lf_kfe] == pytest.approx(-0.349065850399)
    assert hyq.position_lower_rad[lh_kfe] == pytest.approx(0.349065850399)


def test_hyq_nominal_pose_is_inside_the_limits_and_mirrored_front_to_hind() -> None:
    hyq = load_robot_description("hyq")
    nominal = hyq.nominal_joint_positions_rad
    assert np.all(nominal >= hyq.position_lower_rad) and np.all(nominal <= hyq.position_upper_rad)
    front, hind = (
        nominal[RobotDescription.leg_joint_slice(Leg.LF)],
        nominal[RobotDescription.leg_joint_slice(Leg.LH)],
    )
    np.testing.assert_allclose(front, -hind)


def test_arrays_are_read_only() -> None:
    hyq = load_robot_description("hyq")
    with pytest.raises(ValueError):
        hyq.nominal_joint_positions_rad[0] = 1.0


def test_imu_defaults_to_the_base_origin() -> None:
    hyq = load_robot_description("hyq")
    np.testing.assert_array_equal(hyq.imu_position_base_m, [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(hyq.base_quat_imu_xyzw, [0.0, 0.0, 0.0, 1.0])


def test_solo12_uses_its_own_names_and_yaml_torque_limits() -> None:
    solo = load_robot_description("solo12")
    assert solo.joint_names[RobotDescription.joint_index(Leg.LH, "HAA")] == "HL_HAA"
    assert tuple(solo.hip_frames) == ("FL_HAA", "FR_HAA", "HL_HAA", "HR_HAA")  # defaulted from the HAA joints
    np.testing.assert_allclose(solo.torque_limits(np.zeros(12))[1], 2.7)


def test_go1_is_configuration_only_with_its_urdf_names_limits_and_imu() -> None:
    """Unitree Go1 from example-robot-data: Unitree's joint names (rear legs RL/RR mapped to LH/RH), the URDF's
    own torque limits (hip and thigh 23.7, calf 35.55 N m), every knee pointing backwards, and the IMU pose
    read from the URDF's imu_link (issue 32: no Go1 number in any algorithm)."""
    go1 = load_robot_description("go1")
    assert "go1" in shipped_robot_names()
    assert go1.joint_names[RobotDescription.joint_index(Leg.LH, "KFE")] == "RL_calf_joint"
    assert tuple(go1.foot_frames) == ("FL_foot", "FR_foot", "RL_foot", "RR_foot")
    np.testing.assert_allclose(go1.torque_limits(np.zeros(12))[1], [23.7, 23.7, 35.55] * 4)
    np.testing.assert_allclose(go1.imu_position_base_m, [-0.01592, -0.06659, -0.00617], atol=1e-12)
    np.testing.assert_allclose(go1.base_quat_imu_xyzw, [0.0, 0.0, 0.0, 1.0], atol=1e-12)


# ----------------------------------------------------------------------------------------------------
# Locating files
# ----------------------------------------------------------------------------------------------------
def test_example_robot_data_dir_honours_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    found = find_example_robot_data_dir()
    assert (found / "robots" / "hyq_description").is_dir()
    monkeypatch.setenv(EXAMPLE_ROBOT_DATA_ENV, str(found))
    assert find_example_robot_data_dir() == found
    monkeypatch.setenv(EXAMPLE_ROBOT_DATA_ENV, "/nonexistent/erd")
    with pytest.raises(RobotConfigError, match=EXAMPLE_ROBOT_DATA_ENV):
        find_example_robot_data_dir()


def test_missing_example_robot_data_is_a_clear_error(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv(EXAMPLE_ROBOT_DATA_ENV, raising=False)
    monkeypatch.setattr("sys.path", [str(tmp_path)])
    with pytest.raises(RobotConfigError, match="example-robot-data not found"):
        find_example_robot_data_dir()


def test_urdf_path_relative_to_the_yaml(tmp_path: Path) -> None:
    urdf = load_robot_description("hyq").urdf_path
    (tmp_path / "urdf").mkdir()
    (tmp_path / "urdf" / "hyq.urdf").write_text(urdf.read_text(encoding="utf-8"), encoding="utf-8")
    document = hyq_document() | {"urdf": "urdf/hyq.urdf"}
    description = load_robot_description(write_yaml(tmp_path, document))
    assert description.urdf_path == (tmp_path / "urdf" / "hyq.urdf").resolve()


def test_urdf_summary_skips_transmission_joints() -> None:
    summary = read_urdf_summary(load_robot_description("hyq").urdf_path)
    assert summary.joints["lf_kfe_joint"].effort == 150.0
    assert summary.joints["lf_foot_joint"].joint_type == "fixed"
    assert "lf_foot" in summary.frame_names and "trunk" in summary.links


# ----------------------------------------------------------------------------------------------------
# Overrides and torque tables
# ----------------------------------------------------------------------------------------------------
def test_torque_table_interpolates_and_clamps(tmp_path: Path) -> None:
    document = hyq_document()
    document["limits"] = {
        "torque_Nm": {
            "KFE": [[-2.0, 100.0], [-1.0, 200.0], [-0.5, 150.0]],
            "lh_kfe_joint": 120.0,  # a joint name wins over its kind
            "HFE": [[-1.0, 80.0], [1.0, 160.0]],
        }
    }
    description = load_robot_description(write_yaml(tmp_path, document))
    q = np.zeros(12)
    lf_kfe, rf_kfe = RobotDescription.joint_index(Leg.LF, "KFE"), RobotDescription.joint_index(Leg.RF, "KFE")
    lh_kfe, rh_kfe = RobotDescription.joint_index(Leg.LH, "KFE"), RobotDescription.joint_index(Leg.RH, "KFE")
    lf_hfe = RobotDescription.joint_index(Leg.LF, "HFE")
    q[lf_kfe], q[rf_kfe], q[rh_kfe], q[lf_hfe] = -1.5, -0.75, -3.0, 0.5
    tau_min, tau_max = description.torque_limits(q)
    assert tau_max[lf_kfe] == pytest.approx(150.0)  # halfway between 100 and 200
    assert tau_max[rf_kfe] == pytest.approx(175.0)  # halfway between 200 and 150
    assert tau_max[rh_kfe] == pytest.approx(100.0)  # clamped below the first breakpoint
    assert tau_max[lh_kfe] == pytest.approx(120.0)
    assert tau_max[lf_hfe] == pytest.approx(140.0)  # 80 + 0.75 * 80
    assert tau_max[RobotDescription.joint_index(Leg.LF, "HAA")] == pytest.approx(150.0)  # URDF effort
    np.testing.assert_array_equal(tau_min, -tau_max)


def test_position_and_velocity_overrides(tmp_path: Path) -> None:
    document = hyq_document()
    document["limits"] = {"position_rad": {"HAA": [-0.5, 0.4]}, "velocity_rad_s": {"rf_kfe_joint": 8.0}}
    description = load_robot_description(write_yaml(tmp_path, document))
    np.testing.assert_allclose(description.position_lower_rad[0::3], -0.5)
    assert description.velocity_limit_rad_s[RobotDescription.joint_index(Leg.RF, "KFE")] == 8.0
    assert description.velocity_limit_rad_s[RobotDescription.joint_index(Leg.LF, "KFE")] == 12.0


def test_torque_limits_rejects_a_wrong_size() -> None:
    with pytest.raises(InputError, match="12 joint positions"):
        load_robot_description("hyq").torque_limits(np.zeros(11))
    with pytest.raises(InputError, match=r"non-finite joint position\(s\) at index \[3\]"):
        load_robot_description("hyq").torque_limits(np.r_[np.zeros(3), np.nan, np.zeros(8)])


# ----------------------------------------------------------------------------------------------------
# Errors name the file and the field
# ----------------------------------------------------------------------------------------------------
def _expect_error(tmp_path: Path, document: dict[str, Any], pattern: str) -> None:
    path = write_yaml(tmp_path, document)
    with pytest.raises(RobotConfigError, match=re.escape(str(path)) + ".*" + pattern):
        load_robot_description(path)


def test_unknown_joint_name(tmp_path: Path) -> None:
    document = hyq_document()
    document["joints"]["LH"][1] = "lh_hip_joint"
    _expect_error(tmp_path, document, r"'joints.LH.HFE': joint 'lh_hip_joint' not in URDF")


def test_unknown_and_missing_keys(tmp_path: Path) -> None:
    _expect_error(tmp_path, hyq_document() | {"foot_radius": 0.02}, r"unknown key\(s\) \['foot_radius'\]")
    document = hyq_document()
    del document["foot_frames"]
    _expect_error(tmp_path, document, r"missing key\(s\) \['foot_frames'\]")
    document = hyq_document()
    document["limits"] = {"torque_Nm": {"ANKLE": 3.0}}
    _expect_error(tmp_path, document, r"'limits.torque_Nm': unknown key\(s\) \['ANKLE'\]")


def test_wrong_counts(tmp_path: Path) -> None:
    document = hyq_document()
    document["joints"]["RF"] = ["rf_haa_joint", "rf_hfe_joint"]
    _expect_error(tmp_path, document, r"'joints.RF': expected 3 joint names")
    document = hyq_document()
    del document["foot_frames"]["RH"]
    _expect_error(tmp_path, document, r"'foot_frames': missing key\(s\) \['RH'\]")
    document = hyq_document()
    document["nominal_joint_positions_rad"]["LF"] = [0.0, 0.8]
    _expect_error(tmp_path, document, r"'nominal_joint_positions_rad.LF': expected a list of 3 numbers")


def test_inverted_limits(tmp_path: Path) -> None:
    document = hyq_document()
    document["limits"] = {"position_rad": {"HFE": [1.0, -1.0]}}
    _expect_error(tmp_path, document, r"'limits.position_rad': inverted position limits \[1.0, -1.0\]")


def test_bad_torque_table(tmp_path: Path) -> None:
    document = hyq_document()
    document["limits"] = {"torque_Nm": {"KFE": [[-1.0, 100.0], [-2.0, 120.0]]}}
    _expect_error(
        tmp_path, document, r"'limits.torque_Nm.KFE': breakpoint angles must be strictly increasing"
    )
    document["limits"] = {"torque_Nm": {"KFE": -5.0}}
    _expect_error(tmp_path, document, r"'limits.torque_Nm.KFE': torque limit must be > 0")


def test_nominal_outside_limits(tmp_path: Path) -> None:
    document = hyq_document()
    document["nominal_joint_positions_rad"]["LH"] = [0.0, -0.8, -1.6]  # hind knee bent the front way
    _expect_error(tmp_path, document, r"'nominal_joint_positions_rad': -1.6 rad for joint 'lh_kfe_joint'")


def test_unknown_frame_duplicate_joint_and_bad_imu(tmp_path: Path) -> None:
    document = hyq_document()
    document["foot_frames"]["LF"] = "lf_toe"
    _expect_error(tmp_path, document, r"'foot_frames.LF': frame 'lf_toe' is neither a link nor a joint")
    document = hyq_document()
    document["joints"]["RF"] = list(document["joints"]["LF"])
    _expect_error(tmp_path, document, r"'joints': joint\(s\) .*listed more than once")
    document = hyq_document() | {"imu": {"orientation_xyzw": [0.0, 0.0, 0.0, 2.0]}}
    _expect_error(tmp_path, document, r"'imu.orientation_xyzw': quaternion must have unit norm")


def test_missing_urdf_file(tmp_path: Path) -> None:
    _expect_error(
        tmp_path, hyq_document() | {"urdf": "nowhere/robot.urdf"}, r"'urdf': file .* does not exist"
    )


def test_unknown_robot_name_lists_the_shipped_ones() -> None:
    with pytest.raises(RobotConfigError, match="unknown robot 'anymal'.*hyq"):
        load_robot_description("anymal")


def test_not_a_mapping(tmp_path: Path) -> None:
    path = tmp_path / "robot.yaml"
    path.write_text("- just\n- a list\n", encoding="utf-8")
    with pytest.raises(RobotConfigError, match="must be a mapping"):
        load_robot_description(path)


def test_foot_radius_must_be_a_non_negative_number(tmp_path: Path) -> None:
    _expect_error(tmp_path, hyq_document() | {"foot_radius_m": -0.01}, r"'foot_radius_m': must be >= 0")
    _expect_error(
        tmp_path, hyq_document() | {"foot_radius_m": math.nan}, r"'foot_radius_m': expected a finite"
    )


# ----------------------------------------------------------------------------------------------------
# IMU pose from the URDF
# ----------------------------------------------------------------------------------------------------
def test_imu_pose_is_read_from_the_urdf_link(tmp_path: Path) -> None:
    """HyQ's URDF mounts trunk_imu 0.29 m ahead, 0.1 m above base_link, upside down (rpy 0, -pi, 0): the
    pose equals Pinocchio's placement of that frame in the base frame."""
    import pinocchio as pin

    description = load_robot_description(write_yaml(tmp_path, hyq_document() | {"imu": {"link": "trunk_imu"}}))
    np.testing.assert_allclose(description.imu_position_base_m, [0.29, 0.0, 0.0999214], atol=1e-12)
    model = pin.buildModelFromUrdf(str(description.urdf_path), pin.JointModelFreeFlyer())
    data = model.createData()
    pin.framesForwardKinematics(model, data, pin.neutral(model))
    base_T_imu = data.oMf[model.getFrameId(description.base_frame)].inverse() * data.oMf[model.getFrameId("trunk_imu")]
    from tal_core.rotations import rotation_from_quat_xyzw

    np.testing.assert_allclose(rotation_from_quat_xyzw(description.base_quat_imu_xyzw), base_T_imu.rotation,
                               atol=1e-9)
    np.testing.assert_allclose(description.imu_position_base_m, base_T_imu.translation, atol=1e-12)


@pytest.mark.parametrize("imu, message", [
    ({"link": "trunk_imu", "position_m": [0.0, 0.0, 0.0]}, r"'imu': give either link"),
    ({"link": "no_such_link"}, r"'imu.link': frame 'no_such_link' is neither"),
    ({"link": "lf_foot"}, r"'imu.link': .*'lf_foot' is not rigidly attached to 'base_link'"),
])
def test_imu_link_errors(tmp_path: Path, imu: dict, message: str) -> None:
    with pytest.raises(RobotConfigError, match=message):
        load_robot_description(write_yaml(tmp_path, hyq_document() | {"imu": imu}))
