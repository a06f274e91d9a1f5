"""The open-loop VPA comparison (``vpa_open_loop``) and the optimiser's switch margin."""

from __future__ import annotations

import math

import numpy as np
import pytest
from tal_lab.vital.vpa_open_loop import PathSettings, markdown, rise_x, run, variation_per_metre

from tal_core.robot_model import RobotModel
from tal_perception.errors import VpaConfigError
from tal_perception.rbf import RbfBasis
from tal_perception.vpa_optimizer import HipHeightModel, PoseOptimizer, PoseSolution, Solver
from tal_perception.vpa_settings import VpaSettings


def test_variation_and_rise_measures() -> None:
    x = np.linspace(0.0, 1.0, 11)
    z = np.where(x > 0.45, 0.7, 0.6)  # one 0.1 m step at x = 0.5
    dz, dpitch = variation_per_metre(x, z, np.zeros_like(x))
    assert dz == pytest.approx(0.1) and dpitch == 0.0
    assert rise_x(x, z) == pytest.approx(0.5)
    assert math.isnan(rise_x(x, np.full_like(x, 0.6)))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"speed_mps": 0.0}, "speed_mps must be a finite value > 0"),
        ({"period_s": float("nan")}, "period_s must be a finite value > 0"),
        ({"start_x_m": 2.0, "end_x_m": 1.0}, "end_x_m .* must be finite and after start_x_m"),
    ],
)
def test_path_settings_reject_bad_values(kwargs: dict, match: str) -> None:
    with pytest.raises(VpaConfigError, match=match):
        PathSettings(**kwargs)


def test_unknown_variant_is_rejected(hyq: RobotModel) -> None:
    with pytest.raises(VpaConfigError, match="unknown variant"):
        run(PathSettings(end_x_m=0.1), hyq, variants=("receding_c_max",), progress=False)


@pytest.mark.slow
def test_both_horizons_climb_the_first_steps_and_the_receding_one_is_not_later(hyq: RobotModel) -> None:
    path = PathSettings(start_x_m=0.3, end_x_m=1.3)  # the first riser is at x = 1.0 m
    traces = run(path, hyq, variants=("receding_c_int", "single_c_int"), progress=False)
    for trace in traces.values():
        assert trace.pose[-1, 0] > trace.pose[0, 0] + 0.1  # the height reference climbs with the stairs
        assert np.degrees(trace.pose[:, 2]).min() < -5.0  # nose up on the way up
        assert (trace.thickness[np.isfinite(trace.thickness)] >= 0.0).all()
        summary = trace.summary()
        assert summary["updates"] == len(path.xs) and summary["nsf_at_optimum_mean"] > 100.0
    assert traces["receding_c_int"].summary()["rise_x_m"] <= traces["single_c_int"].summary()["rise_x_m"]
    assert "| receding_c_int |" in markdown(path, traces)


def _solution(poses: list[float], objective: float) -> PoseSolution:
    return PoseSolution(np.array([poses]), objective, True, 1, Solver.LBFGSB)


@pytest.mark.parametrize(("margin", "expected"), [(0.0, "far"), (0.02, "far"), (0.05, "near")])
def test_an_optimum_away_from_the_previous_pose_must_beat_the_margin(
    hyq: RobotModel, margin: float, expected: str
) -> None:
    settings = VpaSettings(switch_margin=margin)
    basis = RbfBasis(settings.hip_heights, settings.rbf_count, settings.rbf_intersection)
    optimizer = PoseOptimizer(settings, basis, HipHeightModel.from_model(hyq))
    previous = np.array([0.58, 0.0, 0.0])
    problem = type("Problem", (), {"previous": previous})()
    near, far = _solution([0.59, 0.0, 0.0], 1.00), _solution([0.50, 0.0, -0.2], 1.03)  # far: 3 % better
    chosen = optimizer._keep_or_switch(problem, far, near)
    assert chosen is (far if expected == "far" else near)


def test_switch_margin_must_not_be_negative() -> None:
    with pytest.raises(VpaConfigError, match="switch_margin must be >= 0"):
        VpaSettings(switch_margin=-0.1)
