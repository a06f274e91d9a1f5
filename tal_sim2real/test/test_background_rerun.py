"""The report's nominal closed-loop re-run runs in a process of its own while the identification runs
(issue 34, the workflow's time): it must give the re-run's samples bit for bit, and a re-run that is not the
one asked for, or that failed, is run again in the workflow's process."""

from __future__ import annotations

import dataclasses

import numpy as np

from tal_sim2real.measured import BaseTrajectory, MeasuredData
from tal_sim2real.model import SimModel
from tal_sim2real.replay import BackgroundRerun, _base_path, _commands, _config, start_nominal_rerun

DT = 1e-3


def _recording(duration_s: float = 1.2) -> MeasuredData:
    """What the re-run reads from a recording: its duration, start position and velocity commands."""
    n = int(round(duration_s / DT)) + 1
    t = 5.0 + np.arange(n) * DT
    eye = np.tile(np.eye(3), (n, 1, 1))
    position = np.tile([0.3, -0.1, 0.55], (n, 1))
    base = BaseTrajectory(
        position, np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)), eye, np.zeros((n, 3)), np.zeros((n, 3)), "/ground_truth/odom"
    )
    zeros = np.zeros((n, 12))
    data = MeasuredData("rec", [f"j{i}" for i in range(12)], t, DT, zeros, zeros, zeros, base=base)
    data.cmd_vel_t_s = np.array([5.0, 5.4])
    data.cmd_vel = np.array([[0.0, 0.0, 0.0], [0.15, 0.0, 0.1]])
    return data


def test_the_background_re_run_is_the_re_run_bit_for_bit() -> None:
    data = _recording()
    model = SimModel.nominal("flat_rigid")
    background = start_nominal_rerun(model, data, "trot")
    assert background is not None
    try:
        config = _config(model, _commands(data), data, "trot")
        t_here, position_here = _base_path(config)
        t_there, position_there = background.result(config)
    finally:
        background.close()
    assert len(t_here) > 200 and np.ptp(position_here[:, 0]) > 0.01  # it walked
    np.testing.assert_array_equal(t_there, t_here)
    np.testing.assert_array_equal(position_there, position_here)


def test_a_background_re_run_of_another_model_or_one_that_failed_is_not_used() -> None:
    data = _recording(0.3)
    model = SimModel.nominal("flat_rigid")
    config = _config(model, _commands(data), data, "trot")
    heavier = _config(model.with_values({"payload_mass_kg": 5.0}), _commands(data), data, "trot")
    background = BackgroundRerun(config)
    try:
        assert background.result(heavier) is None
        assert background.result(dataclasses.replace(config, gait="crawl")) is None
    finally:
        background.close()
    failing = BackgroundRerun(dataclasses.replace(config, robot="no_such_robot"))
    try:
        failed = dataclasses.replace(config, robot="no_such_robot")
        assert failing.result(failed) is None  # reported; the caller runs it itself
    finally:
        failing.close()
    assert start_nominal_rerun(model, dataclasses.replace(data, cmd_vel=None), "trot") is None
