"""Terrain Compliance Estimator: windowed weighted least squares and contact-state estimation."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from tal_core.errors import InputError
from tal_core.legs import Leg
from tal_core.robot_model import RobotModel
from tal_estimation.tce import (
    ContactSample,
    FiniteDifferenceAcceleration,
    KelvinVoigtWindows,
    TceSettings,
    TerrainComplianceEstimator,
    WindowedKelvinVoigtFit,
)


def stance_samples(k: float, d: float, n: int, seed: int = 0, noise_n: float = 2.0):
    """Synthetic stance: penetration oscillating around the static sinkage, F = k p + d dp/dt + noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.004
    p = 200.0 / k + 0.3 * 200.0 / k * np.sin(2 * np.pi * 1.5 * t)
    rate = np.gradient(p, t)
    force = k * p + d * rate + rng.normal(0.0, noise_n, n)
    return force, p, rate


@pytest.mark.parametrize("k", [3500.0, 8000.0, 10000.0])
def test_recovers_stiffness_within_one_percent(k) -> None:
    fit = WindowedKelvinVoigtFit(TceSettings())
    for f, p, r in zip(*stance_samples(k, 0.0, 400)):
        fit.add(f, p, r)
    est = fit.fit()
    assert est.valid and not est.clamped and not est.stale
    assert est.stiffness_n_per_m == pytest.approx(k, rel=0.01)
    assert est.samples == 250 and est.confidence > 0.9


def test_estimates_damping_when_asked() -> None:
    fit = WindowedKelvinVoigtFit(TceSettings(estimate_damping=True))
    for f, p, r in zip(*stance_samples(8000.0, 400.0, 300, noise_n=0.5)):
        fit.add(f, p, r)
    est = fit.fit()
    assert est.stiffness_n_per_m == pytest.approx(8000.0, rel=0.01)
    assert est.damping_ns_per_m == pytest.approx(400.0, rel=0.05)


def test_too_few_samples_give_no_estimate() -> None:
    fit = WindowedKelvinVoigtFit(TceSettings(min_samples=50))
    for f, p, r in list(zip(*stance_samples(3500.0, 0.0, 49))):
        fit.add(f, p, r)
    est = fit.fit()
    assert not est.valid and est.confidence == 0.0 and np.isnan(est.stiffness_n_per_m)


def test_degenerate_window_keeps_previous_estimate_with_lower_confidence() -> None:
    fit = WindowedKelvinVoigtFit(TceSettings(window=100, min_samples=20, estimate_damping=True))
    for f, p, r in zip(*stance_samples(3500.0, 0.0, 100)):
        fit.add(f, p, r)
    first = fit.fit()
    k_first, confidence_first = first.stiffness_n_per_m, first.confidence
    for _ in range(100):                 # a window of identical samples: no variation, singular fit
        fit.add(100.0, 0.03, 0.0)
    est = fit.fit()
    assert est.stale and est.stiffness_n_per_m == k_first and est.confidence < confidence_first


def test_rigid_ground_is_reported_rigid_not_fitted_to_noise() -> None:
    """Stance on rigid ground: the force swings 0-450 N while the measured sinkage is 0.2 mm plus 0.5 mm of
    kinematic noise. The LS slope is noise (R^2 ~ 0); the window is reported rigid, at least 5e4 N/m, with
    the fill ratio as confidence, and a soft window that follows it is fitted again."""
    rng = np.random.default_rng(3)
    fit = WindowedKelvinVoigtFit(TceSettings(window=200, min_samples=20))
    t = np.arange(200) * 0.004
    force = 225.0 + 225.0 * np.sin(2 * np.pi * 1.5 * t)
    pen = force / 2e6 + rng.normal(0.0, 5e-4, t.size)
    for f, p in zip(force, pen):
        fit.add(f, p, 0.0)
    est = fit.fit()
    assert est.valid and est.rigid and est.stiffness_n_per_m >= 5e4 and est.confidence == 1.0
    for f, p, r in zip(*stance_samples(3500.0, 0.0, 200)):
        fit.add(f, p, r)
    est = fit.fit()
    assert not est.rigid and est.stiffness_n_per_m == pytest.approx(3500.0, rel=0.02)


def test_out_of_range_fit_is_clamped_and_flagged() -> None:
    settings = TceSettings(stiffness_range_n_per_m=(1000.0, 5000.0))
    fit = WindowedKelvinVoigtFit(settings)
    for f, p, r in zip(*stance_samples(8000.0, 0.0, 300)):
        fit.add(f, p, r)
    est = fit.fit()
    assert est.clamped and est.stiffness_n_per_m == 5000.0 and est.confidence <= 0.5


def test_non_finite_samples_are_ignored() -> None:
    fit = WindowedKelvinVoigtFit(TceSettings(min_samples=10))
    fit.add(float("nan"), 0.01, 0.0)
    fit.add(100.0, float("inf"), 0.0)
    assert fit.fit().samples == 0


def test_invalid_settings_are_rejected() -> None:
    with pytest.raises(InputError, match="min_samples"):
        TceSettings(window=10, min_samples=20)
    with pytest.raises(InputError, match="weighting"):
        TceSettings(weighting="exotic")


@pytest.fixture(scope="module")
def model() -> RobotModel:
    return RobotModel.from_name("hyq")


def test_contact_states_recover_forces_and_penetration(model) -> None:
    """Torques that balance known foot forces at a sunk stance give back those forces and sinkage."""
    sink = 0.03
    q = model.neutral_q()
    q[2] -= sink                                   # feet 3 cm below the surface z = 0
    v = np.zeros(model.nv)
    model.update(q, v)
    forces = np.array([[0, 0, 250.0], [0, 0, 220.0], [0, 0, 0.0], [5.0, 0, 180.0]])
    tau = np.zeros(12)
    h = model.nonlinear_effects()
    to_v = model.canonical_joint_v_indices()
    for leg in Leg:
        tau_leg = model.leg_torques_for_foot_force(leg, forces[leg])
        for j, vi in enumerate(model.leg_joint_v_indices(leg)):
            tau[int(np.flatnonzero(to_v == vi)[0])] = tau_leg[j] + h[vi]
    tce = TerrainComplianceEstimator(model)
    samples = tce.contact_states(q, v, tau, height=lambda x, y: 0.0)
    for leg in Leg:
        np.testing.assert_allclose(samples[leg].force_n, forces[leg], atol=1e-6)
        assert samples[leg].penetration_m == pytest.approx(sink, abs=1e-9)
    assert [s.in_contact for s in samples] == [True, True, False, True]
    estimates = tce.update(samples)
    assert estimates[Leg.LH].samples == 0 and estimates[Leg.LF].samples == 1   # swing legs are not fed
    with pytest.raises(InputError, match="joint torques"):
        tce.contact_states(q, v, np.full(12, np.nan), height=lambda x, y: 0.0)


def test_stance_samples_at_a_step_edge_are_left_out(model) -> None:
    """A foot 2 cm from a 0.1 m riser: one height under its centre is not the surface it presses, so its
    samples are counted as edge samples and never enter the fit; on the flat tread they do."""
    q = model.neutral_q()
    q[2] -= 0.01
    v = np.zeros(model.nv)
    model.update(q, v)
    lf_x = float(model.foot_positions()[Leg.LF, 0])
    tau = np.zeros(12)
    h = model.nonlinear_effects()
    to_v = model.canonical_joint_v_indices()
    for leg in Leg:
        tau_leg = model.leg_torques_for_foot_force(leg, np.array([0.0, 0.0, 200.0]))
        for j, vi in enumerate(model.leg_joint_v_indices(leg)):
            tau[int(np.flatnonzero(to_v == vi)[0])] = tau_leg[j] + h[vi]

    def stairs(x: float, y: float) -> float:   # a riser 2 cm in front of LF's foot only
        return 0.1 if (x > lf_x + 0.02 and y > 0.0) else 0.0

    tce = TerrainComplianceEstimator(model)
    samples = tce.contact_states(q, v, tau, height=stairs)
    assert samples[Leg.LF].surface_relief_m == pytest.approx(0.1)
    assert all(samples[leg].surface_relief_m == 0.0 for leg in (Leg.RF, Leg.LH, Leg.RH))
    estimates = tce.update(samples)
    assert estimates[Leg.LF].samples == 0 and estimates[Leg.RF].samples == 1
    np.testing.assert_array_equal(tce.edge_samples, [1, 0, 0, 0])
    unknown = tce.contact_states(q, v, tau, height=lambda x, y: np.nan if x > lf_x + 0.02 else 0.0)
    tce.update(unknown)                             # relief next to unknown cells is NaN: left out too
    assert tce.edge_samples[Leg.LF] == 2
    with pytest.raises(InputError, match="max_surface_relief_m"):
        TceSettings(max_surface_relief_m=float("nan"))


def test_contact_states_from_a_heightmap_in_one_look_up_equal_the_point_by_point_ones(model) -> None:
    """GridHeights' batched look-up (surface and relief points of the four feet at once) gives the same
    samples, bit for bit, as the same heights asked one point at a time."""
    from tal_core.heightmap import GridHeights, HeightMapGrid

    q = model.neutral_q()
    q[2] -= 0.01
    v = np.zeros(model.nv)
    model.update(q, v)
    feet = model.foot_positions()
    rng = np.random.default_rng(5)
    heights = rng.normal(0.0, 0.01, (41, 41)).astype(np.float32)
    heights[20:, 30:] = np.nan                        # unknown cells near one foot
    grid = HeightMapGrid(center_xy=tuple(feet[:, :2].mean(axis=0)), yaw=0.2, resolution_m=0.025, heights=heights)
    tau = np.zeros(12)
    h = model.nonlinear_effects()
    to_v = model.canonical_joint_v_indices()
    for leg in Leg:
        tau_leg = model.leg_torques_for_foot_force(leg, np.array([0.0, 0.0, 150.0 + 20.0 * leg]))
        for j, vi in enumerate(model.leg_joint_v_indices(leg)):
            tau[int(np.flatnonzero(to_v == vi)[0])] = tau_leg[j] + h[vi]
    batched = TerrainComplianceEstimator(model).contact_states(q, v, tau, height=GridHeights(grid))
    single = TerrainComplianceEstimator(model).contact_states(q, v, tau, height=lambda x, y: float(grid.height_at(x, y)))
    for a, b in zip(batched, single, strict=True):
        assert a.in_contact == b.in_contact
        np.testing.assert_array_equal([a.penetration_m, a.surface_relief_m], [b.penetration_m, b.surface_relief_m])
    assert all(s.in_contact for s in batched) and any(s.surface_relief_m > 0.0 for s in batched)


def test_batched_windows_match_single_channel_fits() -> None:
    """All legs fitted together give the same estimates as one window per leg, samples fed per leg."""
    settings = TceSettings(window=120, min_samples=30)
    batched = KelvinVoigtWindows(settings, 4)
    singles = [WindowedKelvinVoigtFit(settings) for _ in range(4)]
    data = [stance_samples(k, 400.0, 300, seed=leg) for leg, k in enumerate((3500.0, 8000.0, 10000.0, 2e5))]
    rng = np.random.default_rng(3)
    for i in range(300):
        mask = rng.random(4) < 0.7                       # legs in stance at different times
        force = np.array([d[0][i] for d in data])
        pen = np.array([d[1][i] for d in data])
        rate = np.array([d[2][i] for d in data])
        batched.add(mask, force, pen, rate)
        for leg in np.flatnonzero(mask):
            singles[leg].add(force[leg], pen[leg], rate[leg])
    for leg, estimate in enumerate(batched.fit()):
        single = singles[leg].fit()
        assert estimate.samples == single.samples
        assert estimate.stiffness_n_per_m == pytest.approx(single.stiffness_n_per_m, rel=1e-9)
        assert estimate.damping_ns_per_m == pytest.approx(single.damping_ns_per_m, rel=1e-9, nan_ok=True)
        assert estimate.confidence == pytest.approx(single.confidence, rel=1e-9)


def test_linear_weights_favour_recent_samples() -> None:
    """After a switch from T1 to T2 half a window ago, linear weights sit closer to T2 than uniform ones."""
    estimates = {}
    for weighting in ("linear", "uniform"):
        fit = WindowedKelvinVoigtFit(TceSettings(window=200, weighting=weighting, estimate_damping=False))
        for k, seed in ((3500.0, 1), (8000.0, 2)):
            for f, p, r in zip(*stance_samples(k, 0.0, 100, seed=seed, noise_n=0.0)):
                fit.add(f, p, r)
        estimates[weighting] = fit.fit().stiffness_n_per_m
    assert 3500.0 < estimates["uniform"] < estimates["linear"] < 8000.0


def test_constant_penetration_window_gives_no_new_estimate() -> None:
    fit = WindowedKelvinVoigtFit(TceSettings(window=100, min_samples=20, estimate_damping=False))
    for _ in range(100):
        fit.add(105.0, 0.03, 0.0)                  # standing still: no variation, k not identifiable
    est = fit.fit()
    assert not est.valid and est.stale is False and est.confidence == 0.0


def test_contact_states_use_the_inertial_term_when_given_accelerations(model) -> None:
    """With vdot the force comes from J^T F = M vdot + h - tau: torques that include M vdot give F back."""
    q = model.neutral_q()
    q[2] -= 0.02
    v = np.zeros(model.nv)
    model.update(q, v)
    vdot = np.zeros(model.nv)
    vdot[6:] = np.linspace(-3.0, 3.0, model.nv - 6)   # joint accelerations [rad/s^2]
    force = np.array([0.0, 0.0, 200.0])
    inertial = model.mass_matrix() @ vdot + model.nonlinear_effects()
    to_v = model.canonical_joint_v_indices()
    tau = np.zeros(12)
    for leg in Leg:
        tau_leg = model.leg_torques_for_foot_force(leg, force)
        for j, vi in enumerate(model.leg_joint_v_indices(leg)):
            tau[int(np.flatnonzero(to_v == vi)[0])] = tau_leg[j] + inertial[vi]
    tce = TerrainComplianceEstimator(model)
    with_inertia = tce.contact_states(q, v, tau, height=lambda x, y: 0.0, vdot=vdot)
    static = tce.contact_states(q, v, tau, height=lambda x, y: 0.0)
    for leg in Leg:
        np.testing.assert_allclose(with_inertia[leg].force_n, force, atol=1e-6)
    assert max(np.linalg.norm(s.force_n - force) for s in static) > 1.0
    with pytest.raises(InputError, match="vdot"):
        tce.contact_states(q, v, tau, height=lambda x, y: 0.0, vdot=np.full(model.nv, np.nan))


def test_tangential_windows_fit_a_lateral_spring(model) -> None:
    """A stance foot displaced along x against F_x = -k_t dx gives k_t back from the pooled window."""
    tce = TerrainComplianceEstimator(model, TceSettings(estimate_tangential=True, estimate_damping=False,
                                                        min_samples=20))
    up = np.array([0.0, 0.0, 1.0])
    anchor = np.array([0.4, 0.2, 0.0])
    for i in range(200):
        dx = 0.004 * np.sin(0.1 * i)
        foot = anchor + np.array([dx, 0.5 * dx, 0.0])
        forces = np.array([-2.0e4 * dx, -2.0e4 * 0.5 * dx, 300.0])
        sample = ContactSample(True, forces, up, 0.01 + 1e-3 * np.cos(0.1 * i), 0.0, foot, np.zeros(3))
        tce.update([sample] * 4)
    tangential = tce.tangential_estimates
    assert tangential is not None and tangential[0].valid
    assert tangential[0].stiffness_n_per_m == pytest.approx(2.0e4, rel=0.02)


def test_finite_difference_accelerations_skip_gaps() -> None:
    acc = FiniteDifferenceAcceleration(max_gap_s=0.006)
    assert acc.update(0.0, np.zeros(3)) is None
    np.testing.assert_allclose(acc.update(0.004, np.array([0.004, 0.0, -0.008])), [1.0, 0.0, -2.0])
    assert acc.update(0.020, np.ones(3)) is None          # a skipped tick: no difference across the gap
    assert acc.update(0.010, np.ones(3)) is None          # out of order


def offset_stances(k: float, offsets: list[float], n: int = 60, noise_n: float = 2.0, seed: int = 0):
    """Stances from touchdown (p = 0) to lift-off on a Kelvin-Voigt ground of stiffness k, the force a half
    sine to 400 N, every penetration of stance i read ``offsets[i]`` too deep (a base-height or map error)."""
    rng = np.random.default_rng(seed)
    s = np.sin(np.pi * np.arange(n) / (n - 1))
    force = np.concatenate([400.0 * s + rng.normal(0.0, noise_n, n) for _ in offsets])
    pen = np.concatenate([400.0 * s / k + off for off in offsets])
    rate = np.concatenate([np.gradient(400.0 * s / k, 0.004) for _ in offsets])
    return force, pen, rate


def test_a_window_with_offset_penetrations_is_not_confident() -> None:
    """A TCE on a base estimate 2 cm too low reads every penetration 2 cm too deep: the fit through the
    origin gives 2841 N/m on 3500 N/m ground, and the thesis' confidence (fill x R^2) was 0.92. The offset
    fit finds the 2 cm and the estimate is not confident; without the offset it is, and accurate."""
    for offset, confident in ((0.02, False), (0.0, True)):
        fit = WindowedKelvinVoigtFit(TceSettings(window=250, min_samples=50))
        for f, p, r in zip(*offset_stances(3500.0, [offset] * 4)):
            fit.add(f, p, r)
        estimate = fit.fit()
        assert estimate.penetration_offset_m == pytest.approx(offset, abs=1e-3)
        assert (estimate.confidence >= 0.5) is confident, estimate
        if confident:
            assert estimate.stiffness_n_per_m == pytest.approx(3500.0, rel=0.01)


def test_a_drifting_base_over_rigid_ground_gives_no_confident_soft_estimate() -> None:
    """Rigid ground (2e6 N/m) under a base estimate sinking 3 mm a stance (the terrain-aware odometry's
    runaway on graph_tour): the window reads ~1.5e4 N/m, which must not be confident."""
    fit = WindowedKelvinVoigtFit(TceSettings(window=250, min_samples=50))
    for f, p, r in zip(*offset_stances(2e6, [0.010, 0.013, 0.016, 0.019])):
        fit.add(f, p, r)
    estimate = fit.fit()
    assert estimate.stiffness_n_per_m < 5e4 and not estimate.rigid
    assert estimate.confidence < 0.1


def test_the_offset_check_can_be_disabled() -> None:
    fit = WindowedKelvinVoigtFit(TceSettings(window=250, min_samples=50, max_penetration_offset_m=float("inf")))
    for f, p, r in zip(*offset_stances(3500.0, [0.02] * 4)):
        fit.add(f, p, r)
    estimate = fit.fit()
    assert estimate.confidence > 0.5 and estimate.penetration_offset_m == 0.0
    with pytest.raises(InputError):
        TceSettings(max_penetration_offset_m=-0.01)


def test_lost_ticks_age_the_window_as_their_samples_would_have() -> None:
    """A window fed one tick in three, the lost ones skipped, holds the same time span as one fed every tick:
    after a switch from T1 to T2 it forgets T1 as fast (the estimates agree), with a third of the samples."""
    settings = TceSettings(window=150, estimate_damping=False, min_samples=20)
    every, some = KelvinVoigtWindows(settings, 1), KelvinVoigtWindows(settings, 1)
    stance = np.array([True])
    for k, seed in ((3500.0, 1), (8000.0, 2)):
        for i, (f, p, r) in enumerate(zip(*stance_samples(k, 0.0, 150, seed=seed, noise_n=0.0))):
            every.add(stance, [f], [p], [r])
            if i % 3 == 0:
                some.add(stance, [f], [p], [r])
            else:
                some.skip(stance, 1)
    full, sparse = every.fit()[0], some.fit()[0]
    assert full.stiffness_n_per_m == pytest.approx(8000.0, rel=1e-6)          # T1 has left the full window
    assert sparse.stiffness_n_per_m == pytest.approx(8000.0, rel=1e-6) and sparse.samples == 50
    assert some.samples().tolist() == [50]
    never = KelvinVoigtWindows(settings, 1)                                     # without the skips: T1 stays
    for k, seed in ((3500.0, 1), (8000.0, 2)):
        for f, p, r in list(zip(*stance_samples(k, 0.0, 150, seed=seed, noise_n=0.0)))[::3]:
            never.add(stance, [f], [p], [r])
    assert never.fit()[0].stiffness_n_per_m < 7000.0


def feed_stances(windows: KelvinVoigtWindows, stances: list[tuple[float, int]], seed: int = 0,
                 noise_n: float = 2.0, rigid_noise_m: float = 2e-4) -> list:
    """Stances (stiffness [N/m], samples) from touchdown to lift-off on a Kelvin-Voigt ground (damping 300 N s/m),
    each followed by a swing tick, the window refitted every tick as the TCE does; the estimate after every
    stance sample. Rigid ground (>= 1e6 N/m): sub-millimetre sinkage under kinematic noise."""
    rng = np.random.default_rng(seed)
    stance, swing = np.array([True]), np.array([False])
    estimates = []
    for k, n in stances:
        s = np.sin(np.pi * np.arange(n) / (n - 1))
        pen = 450.0 * s / k
        rate = np.gradient(pen, 0.004)
        force = k * pen + (300.0 * rate if k < 1e6 else 0.0) + rng.normal(0.0, noise_n, n)
        pen = pen + (rng.normal(0.0, rigid_noise_m, n) if k >= 1e6 else 0.0)
        for f, p, r in zip(force, pen, rate):
            windows.add(stance, [f], [p], [r])
            estimates.append(replace(windows.fit(stance)[0]))
        windows.add(swing, [0.0], [0.0], [0.0])
        windows.fit(stance)
    return estimates


@pytest.mark.parametrize("before", [2e6, 8000.0])
def test_a_stance_on_new_terrain_restarts_the_window(before: float) -> None:
    """Three stances on rigid ground (or T2), then one on T1 (3500 N/m): the window mixes the two, a fit no
    spring explains (confidence ~0, or the stiffness between the two) until the old samples leave it, a
    second on graph_tour. With window_restart the stance's own fit takes over once it holds min_samples."""
    settings = TceSettings(window=250, min_samples=50)
    plan = [(before, 100)] * 3 + [(3500.0, 100)]
    restarting, mixed = KelvinVoigtWindows(settings, 1), KelvinVoigtWindows(replace(settings, window_restart=False), 1)
    new = feed_stances(restarting, plan)[300:]
    old = feed_stances(mixed, plan)[300:]
    assert restarting.restarts.tolist() == [1]
    at = settings.min_samples - 1      # the stance's 50th sample
    assert new[at].confidence >= 0.1 and new[at].stiffness_n_per_m == pytest.approx(3500.0, rel=0.03)
    assert new[-1].confidence >= 0.3 and new[-1].stiffness_n_per_m == pytest.approx(3500.0, rel=0.02)
    assert all(e.confidence < 0.1 or not e.stiffness_n_per_m == pytest.approx(3500.0, rel=0.1) for e in old[:at + 1])


def test_steady_terrain_never_restarts_the_window() -> None:
    """Twelve stances on T1 (noise, sinusoidal loading), then twelve on rigid ground: one restart, at the
    change; none within either terrain."""
    windows = KelvinVoigtWindows(TceSettings(window=250, min_samples=50), 1)
    estimates = feed_stances(windows, [(3500.0, 100)] * 12, seed=4, noise_n=5.0)
    assert windows.restarts.tolist() == [0]
    assert estimates[-1].confidence > 0.9 and estimates[-1].stiffness_n_per_m == pytest.approx(3500.0, rel=0.01)
    estimates = feed_stances(windows, [(2e6, 100)] * 12, seed=5, noise_n=5.0)
    assert windows.restarts.tolist() == [1] and estimates[-1].rigid


def drifting_base_stances(tce: TerrainComplianceEstimator, k: float, d: float, drift_per_stance_m: float,
                          stances: int = 8, n: int = 60, drift_within_stance_m: float = 0.0) -> None:
    """Stances on a Kelvin-Voigt ground (force a half sine to 400 N from a landing at 0.3 m/s, one swing sample
    between stances) seen from a base estimate whose height drifts by ``drift_per_stance_m`` from one stance
    to the next: every penetration of stance i reads i x drift too deep."""
    up = np.array([0.0, 0.0, 1.0])
    t = np.arange(n) * 0.004
    force = 400.0 * np.sin(np.pi * np.arange(n) / (n - 1)) + 20.0
    # p from k p + d dp/dt = F (explicit Euler from the landing), so the samples obey the ground's law.
    pen = np.zeros(n)
    for i in range(1, n):
        pen[i] = pen[i - 1] + (t[1] - t[0]) * (force[i - 1] - k * pen[i - 1]) / d
    rate = np.gradient(pen, t)
    swing = ContactSample(False, np.zeros(3), up, -0.05, 0.0, np.zeros(3), np.zeros(3))
    for stance in range(stances):
        for i in range(n):
            drift = stance * drift_per_stance_m + drift_within_stance_m * i / (n - 1)
            sample = ContactSample(True, force[i] * up, up, pen[i] + drift, rate[i], np.zeros(3), np.zeros(3))
            tce.update([sample] * 4)
        tce.update([swing] * 4)


@pytest.mark.parametrize("reference", ["surface", "touchdown"])
def test_touchdown_referenced_penetration_ignores_a_drifting_base_height(model, reference) -> None:
    """A base estimate whose height drifts 2 cm from one stance to the next shifts a surface-referenced window
    stance by stance (not confident, or wrong); a touchdown-referenced one sees each stance's own sinking and
    gives the ground's stiffness back."""
    tce = TerrainComplianceEstimator(model, TceSettings(penetration_reference=reference))
    drifting_base_stances(tce, k=3500.0, d=400.0, drift_per_stance_m=0.02)
    estimate = tce.estimates[0]
    if reference == "touchdown":
        assert estimate.valid and estimate.confidence > 0.5, estimate
        assert estimate.stiffness_n_per_m == pytest.approx(3500.0, rel=0.05)
    else:
        assert not (estimate.confidence > 0.5 and estimate.stiffness_n_per_m == pytest.approx(3500.0, rel=0.05))
    steady = TerrainComplianceEstimator(model, TceSettings(penetration_reference=reference))
    drifting_base_stances(steady, k=3500.0, d=400.0, drift_per_stance_m=0.0)
    assert steady.estimates[0].stiffness_n_per_m == pytest.approx(3500.0, rel=0.05)   # either way without drift
    with pytest.raises(InputError, match="penetration_reference"):
        TceSettings(penetration_reference="map")


def test_the_offset_check_does_not_apply_to_touchdown_referenced_windows(model) -> None:
    """A base estimate that moves 2 cm during each stance: the offset fit of a touchdown-referenced window sees
    an offset, which there says that the estimate moved, not that the foot's depth is unknown; the window stays
    confident (its stiffness biased: 3500 N/m reads ~2800) so that the odometry models most of the sinking."""
    tce = TerrainComplianceEstimator(model, TceSettings(penetration_reference="touchdown"))
    drifting_base_stances(tce, k=3500.0, d=400.0, drift_per_stance_m=0.0, drift_within_stance_m=0.02)
    estimate = tce.estimates[0]
    assert estimate.confidence > 0.5 and estimate.penetration_offset_m == 0.0
    assert 0.6 * 3500.0 < estimate.stiffness_n_per_m < 3500.0
    surface = TerrainComplianceEstimator(model, TceSettings(penetration_reference="surface"))
    drifting_base_stances(surface, k=3500.0, d=400.0, drift_per_stance_m=0.0, drift_within_stance_m=0.02)
    assert surface.estimates[0].penetration_offset_m != 0.0


@pytest.mark.parametrize("within_m", [-0.02, 0.02])
def test_the_base_drift_fit_reads_the_ground_through_a_base_velocity_error(model, within_m) -> None:
    """A base estimate whose vertical velocity is off reads each stance's sinking too shallow (or deep) by the
    drift since touchdown: the touchdown-referenced fit is biased by tens of percent, the drift fit recovers
    the ground's stiffness (and, on rigid ground, calls it rigid)."""
    plain = TerrainComplianceEstimator(model, TceSettings(penetration_reference="touchdown"))
    drifting_base_stances(plain, k=3500.0, d=400.0, drift_per_stance_m=0.0, drift_within_stance_m=within_m)
    assert plain.estimates[0].stiffness_n_per_m != pytest.approx(3500.0, rel=0.15)
    settings = TceSettings(penetration_reference="touchdown", base_drift_fit=True)
    drift = TerrainComplianceEstimator(model, settings)
    drifting_base_stances(drift, k=3500.0, d=400.0, drift_per_stance_m=0.003, drift_within_stance_m=within_m)
    estimate = drift.estimates[0]
    assert estimate.valid and not estimate.rigid and estimate.confidence > 0.5, estimate
    assert estimate.stiffness_n_per_m == pytest.approx(3500.0, rel=0.05)   # the samples' own law: ~3 % off
    still = TerrainComplianceEstimator(model, settings)                     # the same as with a true base
    drifting_base_stances(still, k=3500.0, d=400.0, drift_per_stance_m=0.0)
    assert estimate.stiffness_n_per_m == pytest.approx(still.estimates[0].stiffness_n_per_m, rel=0.005)
    rigid = TerrainComplianceEstimator(model, settings)
    drifting_base_stances(rigid, k=2e6, d=2e4, drift_per_stance_m=0.0, drift_within_stance_m=within_m)
    assert rigid.estimates[0].rigid and rigid.estimates[0].stiffness_n_per_m >= 5e4
    surface = TerrainComplianceEstimator(model, TceSettings(base_drift_fit=True))   # the surface reference:
    drifting_base_stances(surface, k=3500.0, d=400.0, drift_per_stance_m=0.0)      # the thesis' fit, unchanged
    assert surface.estimates[0].stiffness_n_per_m == pytest.approx(3500.0, rel=0.05)


def test_the_base_drift_fit_is_not_confident_where_p_carries_only_noise(model) -> None:
    """A leg standing on rigid ground under a noisy estimate: its force barely varies (no rigid verdict) and
    its penetration is noise; the drift fit must not hand a confident soft stiffness to the c3WBC."""
    rng = np.random.default_rng(1)
    up = np.array([0.0, 0.0, 1.0])
    tce = TerrainComplianceEstimator(model, TceSettings(penetration_reference="touchdown", base_drift_fit=True))
    for i in range(400):
        force = 210.0 + 5.0 * np.sin(0.05 * i) + rng.normal(0.0, 2.0)
        sample = ContactSample(True, force * up, up, rng.normal(0.0, 2e-4) + 1e-5 * i, rng.normal(0.0, 5e-3),
                               np.zeros(3), np.zeros(3))
        tce.update([sample] * 4)
    estimate = tce.estimates[0]
    assert not estimate.rigid and estimate.clamped and estimate.stiffness_n_per_m == 100.0   # the range's floor
    assert estimate.confidence == 0.0, estimate   # a clamped drift fit is never adopted
