"""Trunk references and the motion generator, checked by kinematic replay (the measured state is the
previous tick's targets: feet where the generator puts them, trunk where it asks) on HyQ."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tal_control.errors import MotionConfigError
from tal_control.motion import (
    CRAWL,
    STAND,
    TROT,
    FeetMotion,
    GaitScheduler,
    MeasuredState,
    MotionGenerator,
    MotionParameters,
    MotionTargets,
    TrunkParameters,
    TrunkReference,
)
from tal_core.errors import InputError
from tal_core.legs import Leg
from tal_core.robot_model import RobotModel

DT = 0.004  # [s] 250 Hz


@pytest.fixture(scope="module")
def hyq() -> RobotModel:
    return RobotModel.from_name("hyq")


def standing_state(model: RobotModel) -> MeasuredState:
    model.update(model.neutral_q(), np.zeros(model.nv))
    return MeasuredState(model.neutral_q()[:3], [0.0, 0.0, 0.0, 1.0], np.zeros(3), np.zeros(3),
                         model.foot_positions().copy(), np.zeros((4, 3)), model.com().copy())


def replayed(targets: MotionTargets) -> MeasuredState:
    """The state a perfect tracker would have after this tick."""
    trunk = targets.trunk
    return MeasuredState(trunk.base_position, Rotation.from_matrix(trunk.world_R_base).as_quat(),
                         trunk.com_velocity, trunk.angular_velocity, targets.foot_position,
                         targets.foot_velocity, trunk.com_position)


def replay(generator: MotionGenerator, state: MeasuredState, t_end: float, cmd_vel=(0.0, 0.0, 0.0),
           height_fn=None, on_tick=None) -> list[MotionTargets]:
    out = []
    for k in range(int(round(t_end / DT))):
        targets = generator.update(k * DT, state, cmd_vel, height_fn)
        if on_tick is not None:
            on_tick(generator, targets)
        out.append(targets)
        state = replayed(targets)
    return out


def triangle_margin(point: np.ndarray, triangle: np.ndarray) -> float:
    """Signed distance [m] from ``point`` to the nearest edge of ``triangle`` (3, 2); > 0 inside."""
    margins = []
    for i in range(3):
        a, b, c = triangle[i], triangle[(i + 1) % 3], triangle[(i + 2) % 3]
        normal = np.array([a[1] - b[1], b[0] - a[0]]) / np.linalg.norm(b - a)
        normal = normal if normal @ (c - a) > 0.0 else -normal
        margins.append(float(normal @ (point - a)))
    return min(margins)


def point_in_triangle(point: np.ndarray, triangle: np.ndarray) -> bool:
    """Same-side test with 2-D cross products."""
    signs = [np.cross(triangle[(i + 1) % 3] - triangle[i], point - triangle[i]) for i in range(3)]
    return all(s > 0 for s in signs) or all(s < 0 for s in signs)


def swing_margins(history: list[MotionTargets]) -> list[tuple[float, int, float, bool]]:
    """(time, swinging leg, CoM margin in the support triangle, point-in-triangle) for one-leg swings."""
    out = []
    for targets in history:
        if targets.gait.swing.sum() == 1:
            leg = int(np.argmax(targets.gait.swing))
            triangle = np.delete(targets.touchdown_positions[:, :2], leg, axis=0)
            com = targets.trunk.com_position[:2]
            out.append((targets.t_s, leg, triangle_margin(com, triangle), point_in_triangle(com, triangle)))
    return out


# --- trunk reference ---------------------------------------------------------------------------------------
def test_step_command_is_rate_limited_and_integrates_to_the_right_displacement():
    params = TrunkParameters(nominal_height_m=0.6, max_acceleration_m_s2=0.5)
    trunk = TrunkReference(params, [0.0, 0.0, 0.6], [0.0, 0.0, 0.0])
    scheduler = GaitScheduler(TROT)  # trunk commands count once the gait steps (after 1 preparation cycle)
    feet = FeetMotion(np.array([[0.37, 0.2, 0.0], [0.37, -0.2, 0.0], [-0.37, 0.2, 0.0], [-0.37, -0.2, 0.0]]),
                      np.zeros((4, 3)), np.zeros((4, 3)))
    ground = feet.positions.copy()
    t_start = 1.0
    v_cmd = 0.3
    velocities, accelerations = [], []
    for k in range(int(round(3.0 / DT)) + 1):
        t = k * DT
        command = [v_cmd if t >= t_start else 0.0, 0.0, 0.0]
        target = trunk.update(t, command, scheduler.update(t), feet, ground)
        velocities.append(target.command_velocity_world[0])
        accelerations.append(target.com_acceleration[0])
    velocities = np.array(velocities)
    assert np.max(np.diff(velocities)) <= 0.5 * DT + 1e-12  # never faster than the acceleration limit
    times = np.arange(len(velocities)) * DT
    ramp_s = times[np.argmax(velocities >= v_cmd - 1e-12)] - times[velocities == 0.0][-1]
    assert ramp_s == pytest.approx(v_cmd / 0.5, abs=1e-9)  # 0.6 s ramp
    assert max(accelerations) == pytest.approx(0.5)
    assert velocities[-1] == pytest.approx(v_cmd)
    # x(t) = v (t - t_start - v / (2 a)) once the ramp is over (the ramp starts one tick before t_start)
    expected = v_cmd * (3.0 - (t_start - DT) - v_cmd / (2 * 0.5))
    assert target.com_position[0] == pytest.approx(expected, abs=1e-9)
    assert target.com_shift[0] == 0.0  # no CoM shift in a trot


def test_yaw_command_and_height_following():
    params = TrunkParameters(nominal_height_m=0.55)
    trunk = TrunkReference(params, [0.0, 0.0, 0.55], [0.0, 0.0, 0.0])
    scheduler = GaitScheduler(TROT)
    feet = FeetMotion(np.zeros((4, 3)), np.zeros((4, 3)), np.zeros((4, 3)))
    ground = np.array([[0.37, 0.2, 0.12], [0.37, -0.2, 0.12], [-0.37, 0.2, 0.08], [-0.37, -0.2, 0.08]])
    heights = []
    for k in range(int(round(4.0 / DT))):
        t = k * DT
        target = trunk.update(t, [0.0, 0.0, 0.4], scheduler.update(t), feet, ground)
        heights.append(target.base_position[2])
    assert target.base_position[2] == pytest.approx(0.55 + 0.10, abs=1e-3)  # mean stance ground + nominal
    assert np.max(np.abs(np.diff(heights))) <= params.max_height_rate_m_s * DT + 1e-12
    assert target.command_yaw_rate == pytest.approx(0.4)
    np.testing.assert_allclose(target.angular_velocity, [0.0, 0.0, 0.4], atol=1e-12)
    expected_yaw = 0.4 * (4.0 - DT - TROT.cycle_duration_s) - 0.4**2 / 2.0  # ramp at 1 rad/s^2
    assert target.rpy[2] == pytest.approx(expected_yaw, abs=0.4 * DT + 1e-6)
    np.testing.assert_allclose(target.world_R_base, Rotation.from_euler("z", target.rpy[2]).as_matrix(),
                               atol=1e-12)


def test_override_and_terrain_pitch():
    params = TrunkParameters(nominal_height_m=0.55, align_pitch_to_terrain=True)
    trunk = TrunkReference(params, [0.0, 0.0, 0.55], [0.0, 0.0, 0.0])
    scheduler = GaitScheduler(STAND)
    feet = FeetMotion(np.zeros((4, 3)), np.zeros((4, 3)), np.zeros((4, 3)))
    ground = np.array([[0.37, 0.2, 0.1], [0.37, -0.2, 0.1], [-0.37, 0.2, 0.0], [-0.37, -0.2, 0.0]])
    for k in range(int(round(3.0 / DT))):
        target = trunk.update(k * DT, [0.0, 0.0, 0.0], scheduler.update(k * DT), feet, ground)
    assert target.rpy[1] == pytest.approx(-math.atan2(0.1, 0.74), abs=1e-4)  # nose up on the slope
    trunk.override(base_height_m=0.5, roll=0.05)
    for k in range(int(round(3.0 / DT)), int(round(6.0 / DT))):
        target = trunk.update(k * DT, [0.0, 0.0, 0.0], scheduler.update(k * DT), feet, ground)
    assert target.base_position[2] == pytest.approx(0.5, abs=1e-4)
    assert target.rpy[0] == pytest.approx(0.05, abs=1e-4)
    with pytest.raises(InputError, match="base_height_m must be finite"):
        trunk.override(base_height_m=math.nan)
    with pytest.raises(MotionConfigError, match="max_acceleration_m_s2 must be finite and > 0"):
        TrunkParameters(nominal_height_m=0.5, max_acceleration_m_s2=0.0)


# --- generator ---------------------------------------------------------------------------------------------
def test_crawl_com_shift_keeps_the_com_inside_the_support_triangle(hyq):
    generator = MotionGenerator(hyq, CRAWL)
    history = replay(generator, standing_state(hyq), 6.5)  # preparation cycle + 2 cycles of steps
    margins = swing_margins(history)
    assert {leg for _, leg, _, _ in margins} == {0, 1, 2, 3}
    assert all(inside for *_, inside in margins)
    assert min(m for _, _, m, _ in margins) > 0.01  # [m] even at lift-off and touchdown
    mid_swing = [m for t, leg, m, _ in margins
                 if abs(history[int(round(t / DT))].gait.swing_progress[leg] - 0.5) < 0.01]
    assert min(mid_swing) > 0.04
    # the shift is smooth: the CoM reference moves less than 0.5 m/s and its acceleration stays < 1.5 m/s^2
    com = np.array([h.trunk.com_position for h in history])
    assert np.max(np.linalg.norm(np.diff(com[:, :2], axis=0), axis=1)) < 0.5 * DT
    assert max(np.linalg.norm(h.trunk.com_acceleration[:2]) for h in history) < 1.5
    # the feet step in place: every touchdown lands under the hip
    final = history[-1]
    neutral_hips = final.hip_positions[:, :2] - final.trunk.com_shift[:2]
    np.testing.assert_allclose(final.touchdown_positions[:, :2], neutral_hips, atol=2e-3)


def test_crawl_walking_keeps_static_margin_after_the_first_cycle(hyq):
    generator = MotionGenerator(hyq, CRAWL)
    t_end = 8.0
    history = replay(generator, standing_state(hyq), t_end, cmd_vel=(0.1, 0.0, 0.0))
    steady = [m for t, _, m, _ in swing_margins(history) if t >= 2.0 + CRAWL.cycle_duration_s]
    assert len({round(t) for t, *_ in swing_margins(history) if t >= 4.0}) >= 3 and min(steady) > 0.01
    # walked at the commanded speed after the preparation cycle and the 0.2 s acceleration ramp
    assert history[-1].trunk.com_position[0] == pytest.approx(0.1 * (t_end - 2.0 - 0.1) + 0.0394, abs=0.06)


def test_trot_replay_steps_from_liftoff_to_the_target_foothold(hyq):
    generator = MotionGenerator(hyq, TROT)
    radius = generator.foot_radius_m
    history = replay(generator, standing_state(hyq), 4.0, cmd_vel=(0.2, 0.0, 0.0))
    prep = TROT.cycle_duration_s
    expected_steps = [sum(prep + (k + off) * prep < 4.0 - DT for k in range(6)) for off in TROT.phase_offsets]
    np.testing.assert_array_equal(history[-1].gait.step_count, expected_steps)  # 5 each
    for i, targets in enumerate(history[1:], start=1):
        previous = history[i - 1]
        for leg in Leg:
            if targets.gait.liftoff_event[leg]:  # lift-off sampled from the measured foot, swing starts there
                np.testing.assert_allclose(targets.liftoff_positions[leg], previous.foot_position[leg])
                np.testing.assert_allclose(targets.foot_position[leg], previous.foot_position[leg], atol=1e-4)
            if targets.gait.touchdown_event[leg]:  # the foot arrives at the target foothold at rest
                np.testing.assert_allclose(previous.foot_position[leg],
                                           previous.target_footholds[leg] + [0.0, 0.0, radius], atol=1e-3)
                np.testing.assert_allclose(targets.touchdown_positions[leg], previous.foot_position[leg])
                np.testing.assert_allclose(previous.foot_velocity[leg], 0.0, atol=0.05)
            if targets.stance[leg]:
                np.testing.assert_allclose(targets.foot_position[leg], targets.touchdown_positions[leg])
                np.testing.assert_allclose(targets.foot_velocity[leg], 0.0)
        assert np.max(np.abs(targets.foot_position - previous.foot_position)) < 2.0 * DT  # < 2 m/s
    final = history[-1]
    assert final.trunk.com_position[0] == pytest.approx(0.2 * (4.0 - prep - 0.2) + 0.0394, abs=0.01)
    # the nominal footholds are Raibert's: hip at the next touchdown plus v T_stance / 2, on the ground
    gait = final.gait
    for leg in Leg:
        t_left = gait.time_to_touchdown_s[leg] if gait.swing[leg] else (gait.time_to_liftoff_s[leg]
                                                                        + gait.swing_duration_s[leg])
        expected_x = final.hip_positions[leg, 0] + 0.2 * t_left + 0.2 * TROT.stance_duration_s / 2.0
        assert final.nominal_footholds[leg, 0] == pytest.approx(expected_x, abs=1e-9)
        assert final.nominal_footholds[leg, 2] == pytest.approx(0.0, abs=1e-3)


def test_external_foothold_replaces_the_target_of_the_current_step(hyq):
    generator = MotionGenerator(hyq, TROT)
    radius = generator.foot_radius_m
    requests: list[tuple[float, int, np.ndarray, bool]] = []

    def vfa(gen: MotionGenerator, targets: MotionTargets) -> None:
        if targets.gait.liftoff_event[Leg.LF]:
            step = int(targets.gait.step_count[Leg.LF])
            selected = targets.nominal_footholds[Leg.LF] + [0.05, 0.03, 0.0]
            assert not gen.set_foothold(Leg.LF, step + 1, selected)  # not the current step
            assert not gen.set_foothold(Leg.RF, int(targets.gait.step_count[Leg.RF]), selected)  # stands
            requests.append((targets.t_s, step, selected, gen.set_foothold(Leg.LF, step, selected)))

    history = replay(generator, standing_state(hyq), 2.5, on_tick=vfa)
    assert requests and all(accepted for *_, accepted in requests)
    for t_request, step, selected, _ in requests:
        during = [h for h in history if h.t_s > t_request and h.gait.swing[Leg.LF]
                  and h.gait.step_count[Leg.LF] == step]
        assert all(h.external_foothold[Leg.LF] for h in during)
        np.testing.assert_allclose(during[-1].target_footholds[Leg.LF], selected)
        np.testing.assert_allclose(during[-1].foot_position[Leg.LF], selected + [0.0, 0.0, radius], atol=1e-3)
    feet = np.array([h.foot_position for h in history])
    assert np.max(np.abs(np.diff(feet, axis=0))) < 2.0 * DT


def test_touchdown_depth_ends_the_swing_below_the_foothold_and_anchor_moves_the_stance_foot(hyq):
    depth = 0.02
    generator = MotionGenerator(hyq, TROT, params=MotionParameters(touchdown_depth_m=depth))
    radius = generator.foot_radius_m
    history = replay(generator, standing_state(hyq), 2.0, cmd_vel=(0.2, 0.0, 0.0))
    touchdowns = [(i, leg) for i, h in enumerate(history) for leg in Leg if i and h.gait.touchdown_event[leg]]
    assert touchdowns
    for i, leg in touchdowns:
        before = history[i - 1]
        np.testing.assert_allclose(before.foot_position[leg],
                                   before.target_footholds[leg] + [0.0, 0.0, radius - depth], atol=1e-3)
    generator.anchor_stance_foot(Leg.LH, [1.0, 2.0, 0.3])
    state = replayed(history[-1])
    after = generator.update(2.0, state, (0.2, 0.0, 0.0))
    np.testing.assert_allclose(after.touchdown_positions[Leg.LH], [1.0, 2.0, 0.3])
    with pytest.raises(InputError):
        generator.anchor_stance_foot(Leg.LH, [np.nan, 0.0, 0.0])
    with pytest.raises(InputError):
        generator.anchor_stance_foot(7, [0.0, 0.0, 0.0])
    with pytest.raises(MotionConfigError):
        MotionParameters(touchdown_depth_m=-0.01)


def test_stand_to_trot_and_terrain_heights(hyq):
    generator = MotionGenerator(hyq, STAND)
    state = standing_state(hyq)
    height = 0.04

    def height_fn(x: float, y: float) -> float:
        return height

    def switch(gen: MotionGenerator, targets: MotionTargets) -> None:
        if targets.t_s == pytest.approx(0.5):
            gen.set_gait(TROT)

    history = replay(generator, state, 3.0, height_fn=height_fn, on_tick=switch)
    first_liftoff = next(h.t_s for h in history if h.gait.liftoff_event.any())
    assert first_liftoff == pytest.approx(1.0 + TROT.cycle_duration_s, abs=DT)
    assert not any(h.gait.swing.any() for h in history if h.t_s < first_liftoff)
    swing_targets = [h.target_footholds[leg] for h in history for leg in Leg if h.gait.swing[leg]]
    np.testing.assert_allclose(np.array(swing_targets)[:, 2], height)  # footholds on the terrain
    assert history[-1].trunk.stance_ground_height_m == pytest.approx(height)
    assert history[-1].trunk.base_position[2] == pytest.approx(generator.nominal_height_m + height, abs=2e-3)


def test_invalid_measured_state_and_parameters(hyq):
    good = standing_state(hyq)
    with pytest.raises(InputError, match=r"foot_positions must be finite with shape \(4, 3\)"):
        MeasuredState(good.base_position, good.base_quat_xyzw, good.base_lin_vel, good.base_ang_vel,
                      np.zeros((3, 3)), good.foot_velocities, good.com)
    with pytest.raises(InputError, match="base_quat_xyzw norm"):
        MeasuredState(good.base_position, [0.0, 0.0, 0.0, 2.0], good.base_lin_vel, good.base_ang_vel,
                      good.foot_positions, good.foot_velocities, good.com)
    with pytest.raises(MotionConfigError, match="retarget_until_progress"):
        MotionParameters(retarget_until_progress=1.5)
    generator = MotionGenerator(hyq.description, TROT)
    generator.update(0.0, good, (0.0, 0.0, 0.0))
    with pytest.raises(InputError, match="cmd_vel must be 3 finite values"):
        generator.update(DT, good, (0.0, math.nan, 0.0))
    generator.update(DT, good, (0.0, 0.0, 0.0))  # a rejected tick changes nothing: the same time works
    with pytest.raises(InputError, match="not after the previous"):
        generator.update(0.0, good, (0.0, 0.0, 0.0))
    with pytest.raises(InputError, match="xyz must be 3 finite values"):
        generator.set_foothold(Leg.LF, 1, [0.0, 0.0])


def test_com_centred_footholds_move_by_the_com_offset_under_the_trunk_attitude(hyq):
    """foothold_centre="com": every nominal foothold moves by the horizontal part of R @ (CoM - hips' centre)
    in the base frame (HyQ: 3.9 cm forward, 1.5 cm left), here with the trunk pitched 0.2 rad nose down."""
    standing = standing_state(hyq)
    quat = Rotation.from_euler("xyz", [0.0, 0.2, 0.0]).as_quat()
    state = MeasuredState(standing.base_position, quat, standing.base_lin_vel, standing.base_ang_vel,
                          standing.foot_positions, standing.foot_velocities, standing.com)
    by_hips = MotionGenerator(hyq, TROT).update(0.0, state, (0.2, 0.0, 0.0))
    centred = MotionGenerator(hyq, TROT, params=MotionParameters(foothold_centre="com"))
    by_com = centred.update(0.0, state, (0.2, 0.0, 0.0))
    offset_base = np.asarray(centred.trunk_params.com_offset_base_m)
    assert offset_base[0] == pytest.approx(0.0394, abs=1e-3) and offset_base[1] == pytest.approx(0.0151, abs=1e-3)
    offset = Rotation.from_quat(quat).as_matrix() @ offset_base
    np.testing.assert_allclose(by_com.nominal_footholds[:, :2] - by_hips.nominal_footholds[:, :2],
                               np.tile(offset[:2], (4, 1)), atol=1e-9)
    with pytest.raises(MotionConfigError, match="foothold_centre"):
        MotionParameters(foothold_centre="feet")


def test_pose_filter_settings_set_how_fast_the_height_reference_follows_the_body_pose(hyq):
    """A body pose 0.15 m above the standing height: the default filter (0.1 m/s) follows it at most 0.1 m/s;
    with max_height_rate_m_s 0.3 and bandwidth 8 rad/s it rises faster, never faster than 0.3 m/s."""
    state = standing_state(hyq)

    def heights(params: MotionParameters) -> np.ndarray:
        generator = MotionGenerator(hyq, TROT, params=params)
        start = generator.update(0.0, state, (0.0, 0.0, 0.0)).trunk.base_position[2]
        generator.set_body_pose_reference(start + 0.15, 0.0, 0.0)
        return np.array([generator.update(k * DT, state, (0.0, 0.0, 0.0)).trunk.base_position[2]
                         for k in range(1, 126)]) - start  # 0.5 s

    slow = heights(MotionParameters())
    fast = heights(MotionParameters(pose_bandwidth_rad_s=8.0, max_height_rate_m_s=0.3))
    assert np.max(np.diff(slow)) / DT <= 0.1 + 1e-9 and np.max(np.diff(fast)) / DT <= 0.3 + 1e-9
    assert slow[-1] < 0.05 < 0.12 < fast[-1] <= 0.15 + 1e-6
    generator = MotionGenerator(hyq, TROT, params=MotionParameters(max_attitude_rate_rad_s=0.6))
    assert generator.trunk_params.max_attitude_rate_rad_s == 0.6 and generator.trunk_params.max_height_rate_m_s == 0.1
    with pytest.raises(MotionConfigError, match="max_height_rate_m_s must be > 0"):
        MotionParameters(max_height_rate_m_s=0.0)
    with pytest.raises(MotionConfigError, match="not both"):
        MotionParameters(trunk=generator.trunk_params, pose_bandwidth_rad_s=8.0)


def test_hip_velocities_are_the_trunk_references_rigid_body_velocity_at_the_hips(hyq) -> None:
    """A lowered and pitched pose reference: the hips move with v_com + w x (hip - com), so the front
    hips (ahead of the CoM) sink faster than the hind ones while the trunk pitches nose down."""
    state = standing_state(hyq)
    generator = MotionGenerator(hyq, TROT)
    start = generator.update(0.0, state, (0.0, 0.0, 0.0)).trunk.base_position[2]
    generator.set_body_pose_reference(start - 0.1, 0.0, 0.2)
    for k in range(1, 26):
        targets = generator.update(k * DT, state, (0.0, 0.0, 0.0))
    trunk = targets.trunk
    expected = trunk.com_velocity + np.cross(trunk.angular_velocity, targets.hip_positions - trunk.com_position)
    np.testing.assert_allclose(targets.hip_velocities(), expected, atol=1e-12)
    assert trunk.com_velocity[2] < -0.01 and trunk.angular_velocity[1] > 0.01  # sinking, pitching nose down
    front, hind = targets.hip_velocities()[[Leg.LF, Leg.RF], 2], targets.hip_velocities()[[Leg.LH, Leg.RH], 2]
    assert np.all(front < trunk.com_velocity[2] - 0.01) and np.all(hind > trunk.com_velocity[2] + 0.01)


def test_run_time_motion_parameters_change_and_the_others_are_refused_by_name(hyq):
    generator = MotionGenerator(hyq, TROT)
    generator.update_params(touchdown_depth_m=0.03, k_feedback=0.12)
    assert generator.params.touchdown_depth_m == 0.03 and generator.params.k_feedback == 0.12
    history = replay(generator, standing_state(hyq), 1.6, cmd_vel=(0.2, 0.0, 0.0))
    touchdowns = [(i, leg) for i, h in enumerate(history) for leg in Leg if i and h.gait.touchdown_event[leg]]
    assert touchdowns
    for i, leg in touchdowns:  # the swing ends the new depth below the foothold
        before = history[i - 1]
        np.testing.assert_allclose(before.foot_position[leg][2],
                                   before.target_footholds[leg][2] + generator.foot_radius_m - 0.03, atol=1e-3)
    with pytest.raises(MotionConfigError, match="foothold_centre"):
        generator.update_params(foothold_centre="com")
    with pytest.raises(MotionConfigError, match="touchdown_depth_m"):
        generator.update_params(touchdown_depth_m=0.5)
    assert generator.params.touchdown_depth_m == 0.03
