"""The streaming estimator with a real robot's sensors (no ROS): contact from torques, foot force sensors or
binary flags; joint states without velocities (derived) or without torques; 500 Hz stamps with jitter."""

from __future__ import annotations

import dataclasses
import math
from functools import cache

import numpy as np
import pytest

from tal_core.robot_model import RobotModel
from tal_estimation.leg_odometry import LegOdometrySettings
from tal_estimation.state_estimator import StateEstimatorSettings
from tal_estimation.streaming import EstimatorOutput, StreamingEstimator

MS = 1_000_000  # [ns]
G = 9.81
F_STILL = np.array([0.0, 0.0, G])
W_STILL = np.zeros(3)


@cache
def model() -> RobotModel:
    return RobotModel.from_name("hyq")


@cache
def standing() -> tuple[np.ndarray, np.ndarray]:
    """Nominal joint positions and the torques holding the weight on four feet."""
    m = model()
    q = np.asarray(m.description.nominal_joint_positions_rad, float).copy()
    m.update(m.make_q(np.array([0.0, 0.0, m.nominal_base_height_m]), np.array([0.0, 0.0, 0.0, 1.0]), q),
             np.zeros(m.nv))
    h = m.nonlinear_effects()
    grf = np.array([0.0, 0.0, m.total_mass_kg * G / 4.0])
    tau = np.concatenate([h[m.leg_joint_v_indices(leg)] + m.leg_torques_for_foot_force(leg, grf) for leg in range(4)])
    return q, tau


def settings(source: str = "torque", **changes) -> StateEstimatorSettings:
    legs = LegOdometrySettings(contact_source=source, foot_force_scale=(0.5,) * 4, foot_force_offset=(40.0,) * 4)
    return dataclasses.replace(StateEstimatorSettings(leg_odometry=legs), **changes)


def sensor_values(source: str) -> np.ndarray | None:
    weight_share = model().total_mass_kg * G / 4.0
    return {"torque": None, "force_sensor": np.full(4, weight_share / 0.5 + 40.0),  # raw counts
            "contact_flags": np.ones(4)}[source]


def estimates(outputs: list[EstimatorOutput]) -> list:
    return [o.estimate for o in outputs if o.kind == "estimate"]


# -- contact source: one estimator test each ------------------------------------------------------------------
@pytest.mark.parametrize("source", ["torque", "force_sensor", "contact_flags"])
def test_standing_still_holds_with_each_contact_source(source: str) -> None:
    """Standing, noisy IMU: every source supports the legs (velocity updates), no torques with a sensor."""
    q, tau = standing()
    stream = StreamingEstimator(model(), settings(source))
    rng = np.random.default_rng(1)
    out: list[EstimatorOutput] = []
    for k in range(600):
        out += stream.add_sample(k * MS, F_STILL + rng.normal(0, 0.05, 3), W_STILL + rng.normal(0, 1e-3, 3),
                                 q, np.zeros(12), tau if source == "torque" else None,
                                 foot_contact=sensor_values(source))
    rows = estimates(out)
    assert not stream.rejections and len(rows) == 199
    last = rows[-1]
    assert np.all(last.legs.in_contact) and last.legs.weight_sum == 4.0
    assert np.linalg.norm(last.position - rows[0].position) < 2e-3
    assert np.linalg.norm(last.linear_velocity) < 0.01


def test_contacts_are_paired_by_stamp_in_any_order() -> None:
    """add_contacts as a topic of its own: a tick waits for the contact sample of its stamp, whichever of
    IMU, joints and contacts comes last; the estimates equal those of contacts given with the joints."""
    q, _ = standing()
    contact = sensor_values("force_sensor")
    together = StreamingEstimator(model(), settings("force_sensor"))
    apart = StreamingEstimator(model(), settings("force_sensor"))
    a: list[EstimatorOutput] = []
    b: list[EstimatorOutput] = []
    for k in range(60):
        load = contact * (1.0 + 0.1 * math.sin(0.3 * k))
        f = F_STILL + [0.0, 0.01 * math.sin(k), 0.0]
        a += together.add_sample(k * MS, f, W_STILL, q, np.zeros(12), None, foot_contact=load)
        order = k % 3
        if order == 0:
            b += apart.add_contacts(k * MS, load) + apart.add_imu(k * MS, f, W_STILL)
            b += apart.add_joints(k * MS, lambda: (q, np.zeros(12), None))
        elif order == 1:
            b += apart.add_joints(k * MS, lambda: (q, np.zeros(12), None)) + apart.add_imu(k * MS, f, W_STILL)
            assert not [o for o in b if o.stamp_ns == k * MS and k % 3 == 0 and o.kind == "estimate"]
            b += apart.add_contacts(k * MS, load)
        else:
            b += apart.add_imu(k * MS, f, W_STILL) + apart.add_contacts(k * MS, load)
            b += apart.add_joints(k * MS, lambda: (q, np.zeros(12), None))
    ea, eb = estimates(a), estimates(b)
    assert len(ea) == len(eb) == 19 and not apart.rejections
    for x, y in zip(ea, eb):
        assert x.t_s == y.t_s
        np.testing.assert_array_equal(x.position, y.position)
        np.testing.assert_array_equal(x.legs.probability, y.legs.probability)


def test_a_tick_without_any_contact_sample_is_rejected_and_bad_contacts_are_counted() -> None:
    q, _ = standing()
    stream = StreamingEstimator(model(), settings("contact_flags"))
    for k in range(10):
        stream.add_sample(k * MS, F_STILL, W_STILL, q, np.zeros(12), None)
    stream.add_contacts(10 * MS, np.array([1.0, 1.0, math.nan, 1.0]))
    assert stream.rejections["no_contacts"] >= 1 and stream.rejections["contacts"] == 1


# -- joint states without velocities --------------------------------------------------------------------------
def test_joint_velocities_are_derived_from_every_sample_when_absent() -> None:
    """qd None: the filter sees every joint sample (not only the ticks') and the tick gets its output."""
    q0, _ = standing()
    amplitude, frequency = 0.05, 1.0
    stamps = 2 * MS * np.arange(1000) + np.random.default_rng(2).integers(-300_000, 300_000, 1000)
    stream = StreamingEstimator(model(), settings("contact_flags"))
    reads = 0
    errors = []
    for stamp in stamps:
        t = stamp * 1e-9
        q = q0 + amplitude * math.sin(2 * math.pi * frequency * t)

        def read(q=q):
            nonlocal reads
            reads += 1
            return q, None, None

        stream.add_imu(int(stamp), F_STILL, W_STILL)
        for out in stream.add_joints(int(stamp), read, foot_contact=np.ones(4)):
            if out.kind == "estimate" and t > 0.5:
                true = amplitude * 2 * math.pi * frequency * math.cos(2 * math.pi * frequency * t)
                errors.append(np.max(np.abs(out.joints[1] - true)))
    assert stream.deriving_velocities and reads == len(stamps) and stream.wants_joints(0)
    assert not stream.rejections and len(errors) > 200
    assert max(errors) < 0.02  # of an amplitude of 0.31 rad/s


def test_torques_are_still_required_with_contact_from_torques() -> None:
    q, _ = standing()
    stream = StreamingEstimator(model())
    for k in range(10):
        stream.add_sample(k * MS, F_STILL, W_STILL, q, np.zeros(12), None)
    assert stream.rejections["joints"] == 3 and stream.ticks == 0


# -- stamps with jitter ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("period_s, tolerance_s", [(0.003, 1e-4), (0.002, 4e-4)])
@pytest.mark.parametrize("separate_imu_stamps", [False, True])
def test_jittered_500_hz_stamps_tick_on_the_data_clock(period_s: float, tolerance_s: float,
                                                       separate_imu_stamps: bool) -> None:
    """500 Hz +- 0.3 ms: ticks happen at (nearly) every grid point, on the data's stamps, and nothing is
    rejected, held or re-initialised."""
    q, _ = standing()
    rng = np.random.default_rng(5)
    n = 1500  # 3 s
    joint_stamps = 2 * MS * np.arange(n) + 5 * MS + rng.integers(-300_000, 300_001, n)
    imu_stamps = (2 * MS * np.arange(n) + 5 * MS + rng.integers(-300_000, 300_001, n) if separate_imu_stamps
                  else joint_stamps)
    stream = StreamingEstimator(model(), settings("force_sensor", period_s=period_s, tick_tolerance_s=tolerance_s))
    out: list[EstimatorOutput] = []
    events = sorted([(int(s), 0) for s in imu_stamps] + [(int(s), 1) for s in joint_stamps])
    for stamp, kind in events:
        if kind == 0:
            out += stream.add_imu(stamp, F_STILL, W_STILL)
        else:
            out += stream.add_joints(stamp, lambda: (q, np.zeros(12), None), foot_contact=sensor_values("force_sensor"))
    rows = estimates(out)
    grid_points = (joint_stamps[-1] - joint_stamps[0]) / (period_s * 1e9)
    assert not stream.rejections and stream.held_imu_ticks == 0 and stream.estimator.reinitialisations == 0
    assert len(rows) >= 0.95 * grid_points
    stamps = np.array([o.stamp_ns for o in out if o.kind == "estimate"])
    assert set(stamps) <= set(int(s) for s in joint_stamps)  # ticks at the data's own stamps
    assert np.max(np.diff(stamps)) <= 2 * period_s * 1e9
    assert np.linalg.norm(rows[-1].position - rows[0].position) < 1e-3


# -- the IMU's pose from the URDF -----------------------------------------------------------------------------
def test_an_imu_mounted_as_the_urdf_says_is_read_in_the_base_frame(tmp_path) -> None:
    """HyQ's trunk_imu is upside down, 0.29 m ahead of the base: with ``imu: {link: trunk_imu}`` its raw
    samples of a robot standing still give a level, still estimate; read as if at the base origin they
    would not."""
    import yaml

    from tal_core.robot_description import load_robot_description
    from tal_core.rotations import rotation_from_quat_xyzw

    document = yaml.safe_load(open(model().description.source, encoding="utf-8")) | {"imu": {"link": "trunk_imu"}}
    path = tmp_path / "hyq_imu.yaml"
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    mounted = RobotModel(load_robot_description(path))
    base_R_imu = rotation_from_quat_xyzw(mounted.description.base_quat_imu_xyzw)
    f_imu = base_R_imu.T @ F_STILL  # (0, 0, -g): upside down
    q, tau = standing()
    results = {}
    for name, robot in (("urdf", mounted), ("origin", model())):
        stream = StreamingEstimator(robot)
        rows = estimates([o for k in range(300) for o in stream.add_sample(k * MS, f_imu, W_STILL, q,
                                                                            np.zeros(12), tau)])
        results[name] = rows[-1]
    level = results["urdf"].world_R_base
    np.testing.assert_allclose(level, np.eye(3), atol=1e-6)
    assert np.linalg.norm(results["urdf"].linear_velocity) < 1e-6
    # at the base origin: the specific force reads as -g, the filter sees the robot falling at 2 g
    assert results["origin"].linear_velocity[2] < -0.1
