"""Raibert nominal footholds and the terrain look-ups they use."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tal_control.motion.footholds import (
    hip_at_touchdown,
    nominal_foothold,
    raibert_footholds_xy,
    terrain_height,
    terrain_normal,
    terrain_normals,
)
from tal_core.errors import InputError
from tal_core.heightmap import HeightMapGrid

HIP = np.array([0.3735, 0.207])  # HyQ's LF hip at the nominal pose, base at the origin
T_STANCE = 1.6  # [s] crawl stance
T_LEFT = 0.25  # [s] remaining swing time


def flat(height: float):
    return lambda x, y: height


def test_zero_velocity_lands_under_the_hip():
    foothold = nominal_foothold(HIP, [0.0, 0.0], [0.0, 0.0], 0.0, T_STANCE, T_LEFT, height_fn=flat(0.05))
    np.testing.assert_allclose(foothold, [HIP[0], HIP[1], 0.05])


def test_forward_command_adds_hip_travel_and_half_the_stance_travel():
    v = np.array([0.2, -0.05])
    foothold = nominal_foothold(HIP, v, v, 0.0, T_STANCE, T_LEFT)
    expected = HIP + v * T_LEFT + v * T_STANCE / 2.0
    np.testing.assert_allclose(foothold[:2], expected, atol=1e-12)
    assert foothold[2] == 0.0  # no terrain callback: default_z


def test_velocity_feedback():
    v_cmd, v = np.array([0.3, 0.0]), np.array([0.4, 0.1])
    k = 0.08
    foothold = nominal_foothold(HIP, v, v_cmd, 0.0, 0.4, 0.0, k)
    np.testing.assert_allclose(foothold[:2], HIP + v_cmd * 0.2 + k * (v - v_cmd), atol=1e-12)


def test_yaw_rate_turns_the_hip_about_the_trunk():
    centre = np.array([0.0, 0.0])
    yaw_rate = 0.5
    hip_td = hip_at_touchdown(HIP, [0.0, 0.0], yaw_rate, T_LEFT, centre)
    angle = yaw_rate * T_LEFT
    rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    np.testing.assert_allclose(hip_td, rotation @ HIP, atol=1e-12)
    assert np.linalg.norm(hip_td) == pytest.approx(np.linalg.norm(HIP))
    foothold = nominal_foothold(HIP, [0.0, 0.0], [0.0, 0.0], yaw_rate, T_STANCE, T_LEFT,
                                rotation_centre_xy_world=centre)
    tangential = yaw_rate * np.array([-hip_td[1], hip_td[0]])  # hip velocity from the turn
    np.testing.assert_allclose(foothold[:2], hip_td + tangential * T_STANCE / 2.0, atol=1e-12)
    # without a rotation centre the yaw rate has no effect
    np.testing.assert_allclose(hip_at_touchdown(HIP, [0.0, 0.0], yaw_rate, T_LEFT), HIP)


def test_offset_limit_keeps_the_foot_within_reach():
    v = np.array([1.0, 0.0])
    foothold = nominal_foothold(HIP, v, v, 0.0, T_STANCE, T_LEFT, max_offset_m=0.2)
    hip_td = HIP + v * T_LEFT
    assert np.linalg.norm(foothold[:2] - hip_td) == pytest.approx(0.2)


def test_vectorised_form_matches_the_single_leg_form():
    hips = np.array([[0.37, 0.21], [0.37, -0.21], [-0.37, 0.21], [-0.37, -0.21]])
    t_left = np.array([0.1, 0.0, 0.3, 1.2])
    args = ([0.12, 0.02], [0.1, 0.0], 0.3, 0.4)
    all_legs = raibert_footholds_xy(hips, *args, t_left, 0.05, rotation_centre_xy_world=[0.01, 0.0],
                                    max_offset_m=0.25)
    for hip, t, xy in zip(hips, t_left, all_legs, strict=True):
        single = nominal_foothold(hip, *args, t, 0.05, rotation_centre_xy_world=[0.01, 0.0],
                                  max_offset_m=0.25)
        np.testing.assert_allclose(xy, single[:2], atol=1e-12)


def test_heights_from_a_heightmap_and_off_map_fallback():
    heights = np.fromfunction(lambda r, c: 0.01 * r, (21, 21))  # rises 1 cm per 2 cm cell forward
    grid = HeightMapGrid(center_xy=(0.4, 0.2), yaw=0.0, resolution_m=0.02, heights=heights)
    foothold = nominal_foothold(HIP, [0.0, 0.0], [0.0, 0.0], 0.0, T_STANCE, T_LEFT, height_fn=grid.height_at)
    assert foothold[2] == pytest.approx(float(grid.height_at(HIP[0], HIP[1])))
    assert foothold[2] == pytest.approx(0.10 + 0.5 * (HIP[0] - 0.4), abs=1e-6)
    # outside the map the callback gives NaN: the default height is used
    assert terrain_height(grid.height_at, 5.0, 5.0, default_z=-0.3) == -0.3
    assert terrain_height(None, 0.0, 0.0, default_z=0.2) == 0.2


def test_terrain_normal_fallbacks():
    np.testing.assert_allclose(terrain_normal(None, 0.0, 0.0), [0.0, 0.0, 1.0])
    np.testing.assert_allclose(terrain_normal(lambda x, y: [0.0, 0.0, 0.0], 0.0, 0.0), [0.0, 0.0, 1.0])
    tilted = terrain_normal(lambda x, y: [0.0, -1.0, 1.0], 0.0, 0.0)
    np.testing.assert_allclose(tilted, [0.0, -math.sqrt(0.5), math.sqrt(0.5)])


def test_terrain_normals_ask_a_batched_callback_once_and_fall_back_per_row():
    class Normals:
        calls = 0

        def __call__(self, x, y):
            raise AssertionError("the batched form is used")

        def many(self, x, y):
            Normals.calls += 1
            return np.array([[0.0, -1.0, 1.0], [0.0, 0.0, 0.0], [np.nan, 0.0, 1.0]])

    xy = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    out = terrain_normals(Normals(), xy)
    assert Normals.calls == 1
    np.testing.assert_allclose(out, [[0.0, -math.sqrt(0.5), math.sqrt(0.5)], [0, 0, 1], [0, 0, 1]])
    # a plain callback: one call per point, as terrain_normal
    np.testing.assert_allclose(terrain_normals(lambda x, y: [0.0, -1.0, 1.0], xy[:1]), out[:1])
    np.testing.assert_allclose(terrain_normals(None, xy), np.tile([0.0, 0.0, 1.0], (3, 1)))

    class Wrong(Normals):
        def many(self, x, y):
            return np.zeros((2, 3))

    with pytest.raises(InputError, match="shape"):
        terrain_normals(Wrong(), xy)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"hip_xy_world": [0.0, math.nan]}, "hip_xy_world must be 2 finite values"),
        ({"base_lin_vel_world_xy": [0.0, 0.0, 0.0]}, "base_lin_vel_world_xy must be 2 finite values"),
        ({"stance_duration_s": -1.0}, "stance_duration_s must be a finite number >= 0"),
        ({"swing_time_left_s": math.inf}, "swing_time_left_s must be a finite number >= 0"),
        ({"k_feedback": -0.1}, "k_feedback must be a finite number >= 0"),
        ({"yaw_rate": math.nan}, "yaw_rate must be finite"),
    ],
)
def test_invalid_inputs(kwargs, match):
    args = {"hip_xy_world": HIP, "base_lin_vel_world_xy": [0.0, 0.0], "commanded_vel_world_xy": [0.0, 0.0],
            "yaw_rate": 0.0, "stance_duration_s": T_STANCE, "swing_time_left_s": T_LEFT, "k_feedback": 0.05}
    args.update(kwargs)
    with pytest.raises(InputError, match=match):
        nominal_foothold(**args)
