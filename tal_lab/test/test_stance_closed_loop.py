"""STANCE without ROS: trunk oscillation references, closed-loop settings, and a short STANCE crawl on T1
(the online TCE feeding the c3WBC) in the PyBullet simulation."""

from __future__ import annotations

import numpy as np
import pytest
from tal_lab.closed_loop import ClosedLoopConfig, ClosedLoopLog, run_closed_loop
from tal_lab.stance_experiments import contact_losses, controller_config, grf_error, ramp_commands

from tal_control.locomotion import ImpedanceGate
from tal_control.motion.trunk import TrunkOscillation
from tal_control.wbc import WbcSettings
from tal_core.errors import InputError


def test_trunk_oscillation_derivatives_are_consistent() -> None:
    osc = TrunkOscillation(height_amplitude_m=0.05, height_frequency_hz=1.8, roll_amplitude_rad=0.5,
                           roll_frequency_hz=1.5, start_time_s=1.0)
    assert osc.offsets(0.5) == ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    h = 1e-5
    for t in (1.1, 1.37, 2.0):
        (_, dz0, ddz0), (_, dr0, ddr0) = osc.offsets(t)
        (z_plus, dz_plus, _), (r_plus, dr_plus, _) = osc.offsets(t + h)
        (z_minus, dz_minus, _), (r_minus, dr_minus, _) = osc.offsets(t - h)
        assert (z_plus - z_minus) / (2 * h) == pytest.approx(dz0, abs=1e-6)
        assert (dz_plus - dz_minus) / (2 * h) == pytest.approx(ddz0, abs=1e-4)
        assert (r_plus - r_minus) / (2 * h) == pytest.approx(dr0, abs=1e-6)
        assert (dr_plus - dr_minus) / (2 * h) == pytest.approx(ddr0, abs=1e-4)
    assert max(abs(osc.offsets(t)[1][0]) for t in np.linspace(1.0, 3.0, 400)) == pytest.approx(0.5, rel=1e-3)
    with pytest.raises(InputError, match="roll_amplitude_rad"):
        TrunkOscillation(roll_amplitude_rad=float("nan"))


def test_invalid_closed_loop_and_wbc_settings_are_rejected() -> None:
    with pytest.raises(InputError, match="impedance_source"):
        ClosedLoopConfig(impedance_source="magic")
    with pytest.raises(InputError, match="terrain_stiffness_n_per_m"):
        ClosedLoopConfig(terrain_stiffness_n_per_m=-1.0)
    with pytest.raises(InputError, match="penetration_history"):
        WbcSettings(penetration_history="guessed")
    with pytest.raises(InputError, match="max_load_ramp_stance_fraction"):
        WbcSettings(max_load_ramp_stance_fraction=0.0)
    with pytest.raises(InputError, match="min_confidence"):
        ImpedanceGate(2e6, 400.0, min_confidence=1.5)


def test_impedance_gate_adopts_confident_estimates_and_holds_the_rest() -> None:
    gate = ImpedanceGate(2e6, 400.0, min_confidence=0.1)
    valid = np.array([True, True, True, False])
    first = gate.update(np.array([3500.0, 100.0, np.nan, 8000.0]), np.array([380.0, 50.0, 400.0, 400.0]),
                        valid, np.array([0.5, 0.0, 0.9, 0.9]))
    # LF adopted; RF's clamped 100 N/m with R^2 ~ 0 refused; LH NaN refused; RH not valid: the fallback.
    np.testing.assert_array_equal(first.stiffness_normal, [3500.0, 2e6, 2e6, 2e6])
    np.testing.assert_array_equal(first.damping_normal, [380.0, 400.0, 400.0, 400.0])
    # A mixed window (a foot crossing onto rigid ground) has confidence 0: LF keeps 3500 N/m.
    second = gate.update(np.array([9e5, 8000.0, 8000.0, 8000.0]), np.array([np.nan, 400.0, 400.0, -1.0]),
                         np.ones(4, bool), np.array([0.0, 0.2, 0.2, 0.2]))
    np.testing.assert_array_equal(second.stiffness_normal, [3500.0, 8000.0, 8000.0, 8000.0])
    np.testing.assert_array_equal(second.damping_normal, [380.0, 400.0, 400.0, 400.0])  # -1 refused: held
    np.testing.assert_array_equal(gate.adopted, [1, 1, 1, 1])
    np.testing.assert_array_equal(gate.held, [1, 1, 1, 0])
    with pytest.raises(InputError, match="4 entries"):
        gate.update(np.ones(3), np.ones(4), np.ones(4, bool), np.ones(4))


def test_impedance_gate_takes_the_rigid_model_where_the_tce_flags_rigid_ground() -> None:
    """A rigid window's stiffness is a lower bound (std F / std p), not an estimate: the leg takes the rigid
    model (fallback stiffness and damping), not the bound with the damping held from the last soft patch."""
    gate = ImpedanceGate(2e6, 400.0, min_confidence=0.1)
    soft = gate.update(np.full(4, 8000.0), np.full(4, 1000.0), np.ones(4, bool), np.full(4, 0.9))
    np.testing.assert_array_equal(soft.damping_normal, [1000.0] * 4)
    rigid = np.array([True, True, False, True])
    confidence = np.array([0.4, 0.05, 0.4, 0.4])
    out = gate.update(np.array([1.3e5, 1.9e6, 7000.0, 6e5]), np.full(4, np.nan), np.ones(4, bool), confidence, rigid)
    # LF, RH: rigid; RF: rigid but not confident enough (held); LH: a soft estimate (its damping NaN: held).
    np.testing.assert_array_equal(out.stiffness_normal, [2e6, 8000.0, 7000.0, 2e6])
    np.testing.assert_array_equal(out.damping_normal, [400.0, 1000.0, 1000.0, 400.0])
    np.testing.assert_array_equal(gate.rigid, [1, 0, 0, 1])
    with pytest.raises(InputError, match="4 entries"):
        gate.update(np.ones(4), np.ones(4), np.ones(4, bool), np.ones(4), np.ones(3, bool))


def test_impedance_gate_lets_a_held_estimate_expire() -> None:
    """A leg holds its last adopted estimate while the TCE is not confident, for at most hold_limit_s: a tce
    that lags behind a patch change must not leave a foot on rigid ground modelled as T2 for seconds."""
    gate = ImpedanceGate(2e6, 400.0, min_confidence=0.1, hold_limit_s=1.5)
    confident, doubtful = np.full(4, 0.9), np.array([0.0, 0.0, 0.9, 0.0])
    gate.update(np.full(4, 8000.0), np.full(4, 300.0), np.ones(4, bool), confident, t_s=10.0)
    held = gate.update(np.full(4, 2500.0), np.full(4, 250.0), np.ones(4, bool), doubtful, t_s=11.5)
    np.testing.assert_array_equal(held.stiffness_normal, [8000.0, 8000.0, 2500.0, 8000.0])
    expired = gate.update(np.full(4, 2500.0), np.full(4, 250.0), np.ones(4, bool), doubtful, t_s=11.504)
    np.testing.assert_array_equal(expired.stiffness_normal, [2e6, 2e6, 2500.0, 2e6])
    np.testing.assert_array_equal(expired.damping_normal, [400.0, 400.0, 250.0, 400.0])
    np.testing.assert_array_equal(gate.expired, [1, 1, 0, 1])
    gate.update(np.full(4, 2500.0), np.full(4, 250.0), np.ones(4, bool), doubtful, t_s=12.0)
    np.testing.assert_array_equal(gate.expired, [1, 1, 0, 1])     # the fallback does not expire again
    with pytest.raises(InputError, match="hold_limit_s"):
        ImpedanceGate(2e6, 400.0, hold_limit_s=0.0)


@pytest.mark.slow
def test_stance_trots_on_t1() -> None:
    """STANCE in a trot on T1 (3500 N/m): with the thesis' load ramps (0.51 s, longer than the 0.4 s
    stance) the c3WBC dropped HyQ within 1.1 s; capped at a quarter of the stance it trots."""
    log = run_closed_loop(controller_config("stance", name="stance_trot_t1", course="flat_t1", gait="trot",
                                            commands=((0.0, 0.0, 0.0, 0.0), (1.0, 0.2, 0.0, 0.0)),
                                            duration_s=6.0, progress=False))
    assert not log.fell and not np.any(log.fallback)
    assert log.base_position[-1, 0] > 0.6                          # 0.2 m/s from t = 1 s
    np.testing.assert_allclose(log.impedance_stiffness[-1], 3500.0, rtol=0.05)
    stance = log.stance & log.foot_contact & log.after(3.0)[:, None]
    assert np.mean(np.abs(log.penetration_des[stance] - log.penetration[stance])) < 0.005


def test_ramp_commands_follow_the_thesis_acceleration() -> None:
    commands = ramp_commands(2.0)
    t, vx = np.array([c[0] for c in commands]), np.array([c[1] for c in commands])
    assert vx[0] == pytest.approx(0.05) and vx[-1] == pytest.approx(0.3)
    slope = np.diff(vx[1:]) / np.diff(t[1:])
    np.testing.assert_allclose(slope, 0.005, rtol=1e-9)


@pytest.fixture(scope="module")
def stance_log() -> ClosedLoopLog:
    """STANCE crawling at 0.05 m/s on T1 for 5 s (about 7 s wall)."""
    return run_closed_loop(controller_config("stance", name="stance_t1", course="flat_t1",
                                             commands=((0.0, 0.05, 0.0, 0.0),), duration_s=5.0, progress=False))


@pytest.mark.slow
def test_stance_estimates_t1_and_stays_compliant_contact_consistent(stance_log: ClosedLoopLog) -> None:
    log = stance_log
    assert not log.fell and not np.any(log.fallback)
    final = log.tce_stiffness[-1]
    np.testing.assert_allclose(final, 3500.0, rtol=0.03)          # T1, ground-truth base state
    assert np.all(log.tce_confidence[-1] > 0.9)
    # The c3WBC uses the estimates once valid: its planned sinkage matches the real one within millimetres.
    stance = log.stance & log.foot_contact & log.after(2.0)[:, None]
    assert np.all(log.impedance_stiffness[-1] == final)
    gap = np.abs(log.penetration_des[stance] - log.penetration[stance])
    assert np.mean(gap) < 0.003 and np.mean(log.penetration[stance]) > 0.03
    error = grf_error(log, settle_s=2.0)
    assert error["samples"] > 100 and error["mae_n"] < 10.0
    assert contact_losses(log)["total"] == 0
