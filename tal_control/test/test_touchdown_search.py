"""Late and lost touchdowns: TouchdownSearch and the LocomotionController's contact feedback."""

from __future__ import annotations

import numpy as np
import pytest

from tal_control.errors import MotionConfigError
from tal_control.locomotion import LocomotionController
from tal_control.motion import TROT
from tal_control.motion.touchdown import TouchdownSearch
from tal_core.errors import InputError
from tal_core.robot_model import RobotModel
from tal_core.state import BaseState

FEET = np.array([[0.37, 0.33, 0.02], [0.37, -0.33, 0.02], [-0.37, 0.33, 0.02], [-0.37, -0.33, 0.02]])
ZEROS = np.zeros((4, 3))


def _update(search: TouchdownSearch, t: float, stance, contact, measured=FEET):
    return search.update(t, np.array(stance), np.array(contact), FEET.copy(), ZEROS, ZEROS, measured)


def test_touching_stance_feet_are_supports_and_keep_their_references() -> None:
    out = _update(TouchdownSearch(), 0.0, [True, False, False, True], [True, False, True, True])
    assert out.supported.tolist() == [True, False, False, True]
    assert not out.searching.any() and not out.anchored.any()
    np.testing.assert_array_equal(out.foot_position, FEET)


def test_a_hovering_stance_foot_descends_until_it_touches_then_is_anchored() -> None:
    search = TouchdownSearch(search_speed_mps=0.2, max_depth_m=0.05)
    stance = [True, True, True, True]
    hovering = FEET + [0.0, 0.0, 0.01]
    first = _update(search, 1.0, stance, [True, False, True, True], hovering)
    assert first.supported.tolist() == [True, False, True, True]
    assert first.searching.tolist() == [False, True, False, False]
    np.testing.assert_allclose(first.foot_position[1], hovering[1])
    np.testing.assert_allclose(first.foot_velocity[1], [0.0, 0.0, -0.2])
    later = _update(search, 1.1, stance, [True, False, True, True], hovering)
    np.testing.assert_allclose(later.foot_position[1], hovering[1] - [0.0, 0.0, 0.02])
    deepest = _update(search, 2.0, stance, [True, False, True, True], hovering)
    np.testing.assert_allclose(deepest.foot_position[1], hovering[1] - [0.0, 0.0, 0.05])
    np.testing.assert_allclose(deepest.foot_velocity[1], 0.0)
    touched = _update(search, 2.1, stance, [True, True, True, True])
    assert touched.supported.all() and touched.anchored.tolist() == [False, True, False, False]
    again = _update(search, 2.2, stance, [True, True, True, True])
    assert not again.anchored.any()
    assert search.searches.tolist() == [0, 1, 0, 0]


def test_swing_legs_never_search() -> None:
    out = _update(TouchdownSearch(), 0.0, [False, False, False, False], [False, True, False, True])
    assert not out.supported.any() and not out.searching.any()


def test_bad_input_is_rejected() -> None:
    with pytest.raises(MotionConfigError):
        TouchdownSearch(search_speed_mps=0.0)
    with pytest.raises(MotionConfigError):
        TouchdownSearch(max_depth_m=float("nan"))
    search = TouchdownSearch()
    with pytest.raises(InputError):
        search.update(0.0, np.ones(3, bool), np.ones(4, bool), FEET, ZEROS, ZEROS, FEET)
    with pytest.raises(InputError):
        search.update(0.0, np.ones(4, bool), np.ones(4, bool), FEET, ZEROS, ZEROS, FEET * np.nan)


def test_controller_plans_no_force_on_a_stance_foot_that_does_not_touch() -> None:
    """Standing HyQ, all four feet planned in stance, one reported without contact: the WBC carries the
    robot on the other three and the untouched foot is driven downwards."""
    model = RobotModel.from_name("hyq")
    q = model.neutral_q()
    base = BaseState(q[:3].copy(), q[3:7].copy(), np.zeros(3), np.zeros(3))
    joints, rates = q[7:].copy(), np.zeros(model.nv - 6)
    plain = LocomotionController(RobotModel.from_name("hyq"), TROT)
    fed = LocomotionController(RobotModel.from_name("hyq"), TROT)
    touching = np.array([True, True, False, True])
    out_plain = plain.tick(0.0, base, joints, rates, (0.0, 0.0, 0.0))
    out_fed = fed.tick(0.0, base, joints, rates, (0.0, 0.0, 0.0), foot_contact=touching)
    assert out_plain.targets.stance.all()
    assert out_plain.solution.forces[2, 2] > 50.0  # the plan alone loads the foot in the air
    assert np.allclose(out_fed.solution.forces[2], 0.0, atol=0.5)  # OSQP tolerance, against > 50 N
    assert out_fed.support is not None and out_fed.support.searching.tolist() == [False, False, True, False]
    assert out_fed.solution.forces[touching, 2].sum() > 0.9 * model.total_mass_kg * 9.81  # still carried
    assert out_fed.support.foot_velocity[2, 2] < 0.0


def test_a_swing_foot_landing_late_in_its_swing_is_held_as_a_support() -> None:
    search = TouchdownSearch(early_touchdown_progress=0.7)
    swing = [False, True, True, False]
    touching = np.array([True, True, True, True])
    out = search.update(0.0, ~np.array(swing), touching, FEET.copy(), ZEROS, ZEROS, FEET,
                        swing_progress=np.array([0.0, 0.8, 0.3, 0.0]))
    # RF (80 % through its swing) landed early; LH (30 %: lift-off or a trip) did not.
    assert out.early.tolist() == [False, True, False, False]
    assert out.supported.tolist() == [True, True, False, True]
    moved = FEET + [0.05, 0.0, -0.01]
    later = search.update(0.01, ~np.array(swing), touching, moved, ZEROS, ZEROS, moved,
                          swing_progress=np.array([0.0, 0.85, 0.35, 0.0]))
    np.testing.assert_allclose(later.foot_position[1], FEET[1])  # held where it landed
    np.testing.assert_allclose(later.foot_velocity[1], 0.0)
    lifted = search.update(0.02, ~np.array(swing), np.array([True, False, True, True]), FEET.copy(), ZEROS, ZEROS,
                           FEET, swing_progress=np.array([0.0, 0.9, 0.4, 0.0]))
    assert not lifted.early[1] and not lifted.supported[1]  # lost the ground: a swing foot again
    assert search.early_touchdowns.tolist() == [0, 1, 0, 0]
    with pytest.raises(MotionConfigError):
        TouchdownSearch(early_touchdown_progress=0.0)


def test_with_a_contact_grace_a_late_sensor_flag_does_not_start_a_search() -> None:
    """contact_grace_s 12 ms (a foot sensor's sample of delay plus a tick): a leg whose stance began is a support
    as planned until its flag comes; one whose flag has not come after the grace searches for the ground."""
    search = TouchdownSearch(contact_grace_s=0.012)
    _update(search, 0.0, [False, True, True, False], [False, True, True, False])
    stance = [True, False, False, True]                  # the other diagonal touches down at 4 ms
    out = _update(search, 0.004, stance, [False, True, False, False])
    assert out.supported.tolist() == [True, False, False, True] and not out.searching.any()
    out = _update(search, 0.008, stance, [True, False, False, False])   # LF's flag came, RH's not yet
    assert out.supported.tolist() == [True, False, False, True] and not out.searching.any()
    out = _update(search, 0.016, stance, [True, False, False, False])   # 12 ms without RH's flag
    assert out.searching.tolist() == [False, False, False, True] and search.searches.tolist() == [0, 0, 0, 1]
    with pytest.raises(MotionConfigError, match="contact_grace_s"):
        TouchdownSearch(contact_grace_s=-0.001)


def test_a_latched_contact_holds_until_lift_off_and_a_foot_that_never_reported_searches() -> None:
    """latch_contact: LF reported its touchdown, then its flag dropped (a lightly loaded stance foot under a load
    sensor's threshold): it stays a support; RH never reported one and searches once the grace is over; the next
    stance starts unlatched."""
    search = TouchdownSearch(contact_grace_s=0.008, latch_contact=True)
    _update(search, 0.0, [False, True, True, False], [False, True, True, False])
    stance = [True, False, False, True]
    _update(search, 0.004, stance, [True, False, False, False])
    out = _update(search, 0.016, stance, [False, False, False, False])
    assert out.supported.tolist() == [True, False, False, False]
    assert out.searching.tolist() == [False, False, False, True]
    _update(search, 0.2, [False, True, True, False], [False, True, True, False])      # lift-off
    _update(search, 0.4, stance, [False, False, False, False])                      # a new stance ...
    out = _update(search, 0.412, stance, [False, False, False, False])              # ... with no report
    assert out.searching.tolist() == [True, False, False, True]
