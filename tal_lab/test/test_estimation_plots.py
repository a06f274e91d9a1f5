"""The state-estimation study's figures are written from small synthetic recordings (no simulation)."""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

import numpy as np
from tal_lab.closed_loop import ClosedLoopLog
from tal_lab.estimation_experiments import Recording
from tal_lab.estimation_plots import plot_all, zoom_window
from tal_lab.offline_estimation import EstimateArrays, SensorArrays

T0_S, DURATION_S = 2.0, 3.0  # shorter than the zoom window's end: plot_all must clamp it
GAIT_HZ = 1.8
PER_LEG_3D = {
    "normals",
    "wbc_forces",
    "slacks",
    "foot_position",
    "foot_position_des",
    "contact_force",
    "foot_slip_velocity",
}
PER_LEG = {
    "stance",
    "foot_contact",
    "terrain_stiffness",
    "penetration",
    "penetration_des",
    "impedance_stiffness",
    "tce_stiffness",
    "tce_damping",
    "tce_confidence",
    "tce_in_contact",
}
JOINTS = {"tau_wbc", "tau_cmd", "tau_measured", "joint_position", "joint_velocity"}
SCALAR = {"t", "trunk_height", "qp_status", "qp_iterations", "fallback", "qp_solve_time", "body_contact", "power"}


def _trot_contact(t: np.ndarray) -> np.ndarray:
    """(N, 4) stance flags of a trot: LF + RH, then RF + LH."""
    first = np.sin(2 * np.pi * GAIT_HZ * t) > 0
    return np.stack([first, ~first, ~first, first], axis=1)


def _grf_z(t: np.ndarray, contact: np.ndarray, softness: float) -> np.ndarray:
    """(N, 4) z forces [N]: ~half the weight per stance leg, smoother on soft ground."""
    ramp = np.abs(np.sin(2 * np.pi * GAIT_HZ * t)) ** softness
    return contact * 425.0 * ramp[:, None]


def _log(t: np.ndarray, softness: float) -> ClosedLoopLog:
    n = len(t)

    def shape(name: str) -> tuple[int, ...]:
        for names, tail in ((PER_LEG_3D, (4, 3)), (PER_LEG, (4,)), (JOINTS, (12,)), (SCALAR, ())):
            if name in names:
                return (n, *tail)
        return (n, 3)

    arrays = {f.name: np.zeros(shape(f.name)) for f in fields(ClosedLoopLog) if f.name != "meta"}
    contact = _trot_contact(t)
    force = np.zeros((n, 4, 3))
    force[:, :, 2] = _grf_z(t, contact, softness)
    arrays.update(t=t, foot_contact=contact, contact_force=force)
    return ClosedLoopLog(**arrays, meta={"control_period_s": 0.004})


def _recording(surface: str, rng: np.random.Generator) -> Recording:
    t = T0_S + np.arange(int(DURATION_S * 1000)) * 1e-3
    n = len(t)
    f = np.tile([0.0, 0.0, 9.81], (n, 1)) + rng.normal(0, 0.05, (n, 3))
    f[:, 2] += 2.0 * np.sin(4 * np.pi * GAIT_HZ * t)
    q = np.tile([-0.1, 0.7, -1.4] * 4, (n, 1))
    sensors = SensorArrays(t, f, rng.normal(0, 0.002, (n, 3)), q, np.zeros((n, 12)), np.zeros((n, 12)))
    velocity = np.zeros((n, 3))
    velocity[:, 2] = 0.05 * np.cos(4 * np.pi * GAIT_HZ * t)
    position = np.cumsum(velocity, axis=0) * 1e-3 + [0.0, 0.0, 0.6]
    quat = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    softness = 1.0 if surface == "soft" else 0.2
    return Recording(surface, _log(t[::4], softness), sensors, position, quat, velocity)


def _estimate(rec: Recording, drift_m_s: float, rng: np.random.Generator) -> EstimateArrays:
    t = np.arange(rec.sensors.t[0] + 0.003, rec.sensors.t[-1], 0.003)
    n = len(t)
    index = np.searchsorted(rec.sensors.t, t)
    contact = _trot_contact(t)
    force = rng.normal(0, 10.0, (n, 4, 3))
    force[:, :, 2] += _grf_z(t, contact, 1.0)
    velocity = rec.true_velocity[index] + rng.normal(0, 0.01, (n, 3)) + [0.0, 0.0, drift_m_s]
    raw = velocity + rng.normal(0, 0.05, (n, 3))
    raw[::50] = np.nan  # flight: no support
    return EstimateArrays(
        t=t,
        position=rec.true_position[index] + np.cumsum(velocity - rec.true_velocity[index], axis=0) * 0.003,
        quat_xyzw=rec.true_quat[index],
        linear_velocity=velocity,
        angular_velocity_base=np.zeros((n, 3)),
        gyro_bias=np.zeros((n, 3)),
        position_std=np.full((n, 3), 0.01),
        contact=contact,
        contact_probability=contact.astype(float),
        force=force,
        leg_odometry_velocity=raw,
        support=contact.sum(axis=1).astype(float),
    )


def test_plot_all_writes_every_figure(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    recordings = {surface: _recording(surface, rng) for surface in ("rigid", "soft")}
    estimates = {}
    for surface, rec in recordings.items():
        for variant, drift in (("rigid", -0.01), ("terrain_aware_tce", -0.002), ("terrain_aware_true", 0.0)):
            estimates[(surface, variant)] = _estimate(rec, drift, rng)
    out = tmp_path / "estimation"
    paths = plot_all(recordings, estimates, out)
    expected = {
        "specific_force_z.png",
        "grf_z.png",
        "position_rigid.png",
        "position_soft.png",
        "velocity_rigid.png",
        "velocity_soft.png",
    }
    assert {p.name for p in paths} == expected
    for path in paths:
        assert path.parent == out
        assert path.stat().st_size > 1000
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_zoom_window_clamps_to_the_data() -> None:
    assert zoom_window(np.arange(0.0, 70.0, 0.001)) == (30.0, 32.0)
    start, end = zoom_window(np.arange(2.0, 5.0, 0.001))
    assert end <= 5.0 and abs((end - start) - 2.0) < 1e-9
    assert zoom_window(np.arange(2.0, 3.0, 0.001))[0] == 2.0
