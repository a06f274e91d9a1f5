"""Closed-loop checks of the locomotion controller in the PyBullet simulation (ground-truth state, no ROS).

Short runs on flat rigid ground: stand, trot 0.3 m/s, crawl 0.1 m/s. About 15 s of simulated time in
total (~11-35 s wall on the 2-core machine, depending on load); each log is shared by the tests that read it.
"""

from __future__ import annotations

import numpy as np
import pytest
from tal_lab.closed_loop import ClosedLoopConfig, ClosedLoopLog, run_closed_loop

from tal_control.wbc import WbcSettings

pytestmark = pytest.mark.slow

SETTLE_S = 2.0
MU = WbcSettings().friction_coefficient
SOLVER_TOLERANCE_N = 0.5  # [N] OSQP residuals (eps 1e-4 on forces of hundreds of newtons) stay far below this


def _run(name: str, gait: str, vx: float, duration_s: float) -> ClosedLoopLog:
    return run_closed_loop(
        ClosedLoopConfig(name=name, gait=gait, commands=((0.5, vx, 0.0, 0.0),), duration_s=duration_s, progress=False)
    )


@pytest.fixture(scope="module")
def stand_log() -> ClosedLoopLog:
    return _run("stand", "stand", 0.0, 2.0)


@pytest.fixture(scope="module")
def trot_log() -> ClosedLoopLog:
    return _run("trot", "trot", 0.3, 6.0)


@pytest.fixture(scope="module")
def crawl_log() -> ClosedLoopLog:
    return _run("crawl", "crawl", 0.1, 6.0)


def _friction_excess(log: ClosedLoopLog) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per stance sample: cone excess |F_t| - mu F_n, pyramid excess max|F_t,i| - mu F_n [N], and F_n."""
    forces, normals = log.wbc_forces[log.stance], log.normals[log.stance]
    fn = np.einsum("nk,nk->n", forces, normals)
    tangential = forces - fn[:, None] * normals
    cone = np.linalg.norm(tangential, axis=1) - MU * fn
    t1 = np.cross(normals, np.cross(np.array([1.0, 0.0, 0.0]), normals))  # world x projected on the plane
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    pyramid = (
        np.maximum(np.abs(np.einsum("nk,nk->n", tangential, t1)), np.abs(np.einsum("nk,nk->n", tangential, t2)))
        - MU * fn
    )
    return cone, pyramid, fn


def test_stand_holds_height(stand_log: ClosedLoopLog) -> None:
    assert not stand_log.fell, stand_log.meta["fall_reason"]
    error = np.abs(stand_log.base_position_des[:, 2] - stand_log.base_position[:, 2])
    assert error.max() < 0.02, f"stand height error {error.max():.4f} m"
    assert not stand_log.fallback.any()


def test_trot_walks_at_commanded_speed(trot_log: ClosedLoopLog) -> None:
    assert not trot_log.fell, f"fell at {trot_log.meta['fall_time_s']} s: {trot_log.meta['fall_reason']}"
    settled = trot_log.after(SETTLE_S)
    vx = float(np.mean(trot_log.velocity_h[settled, 0]))
    assert abs(vx - 0.3) <= 0.3 * 0.3, f"mean forward velocity {vx:.3f} m/s for 0.3 m/s commanded"
    assert int(trot_log.fallback.sum()) == 0


def test_crawl_does_not_fall(crawl_log: ClosedLoopLog) -> None:
    assert not crawl_log.fell, f"fell at {crawl_log.meta['fall_time_s']} s: {crawl_log.meta['fall_reason']}"
    assert crawl_log.base_position[-1, 0] > 0.2, "the crawl did not move forward"


@pytest.mark.parametrize("gait", ["trot", "crawl"])
def test_wbc_forces_inside_friction_cone(gait: str, request: pytest.FixtureRequest) -> None:
    """|F_t| <= mu F_n for every stance force the WBC computed (the friction cone of the thesis)."""
    log: ClosedLoopLog = request.getfixturevalue(f"{gait}_log")
    cone, pyramid, fn = _friction_excess(log)
    worst = int(np.argmax(cone))
    assert cone[worst] <= SOLVER_TOLERANCE_N, (
        f"{gait}: stance force outside the friction cone by {cone[worst]:.2f} N "
        f"(|F_t|/F_n = {(cone[worst] + MU * fn[worst]) / fn[worst]:.3f} > mu = {MU}; "
        f"{int(np.sum(cone > SOLVER_TOLERANCE_N))} of {len(cone)} stance samples; "
        f"largest excess over the square pyramid {pyramid.max():.3f} N)"
    )


@pytest.mark.parametrize("gait", ["trot", "crawl"])
def test_wbc_forces_unilateral_and_swing_free(gait: str, request: pytest.FixtureRequest) -> None:
    log: ClosedLoopLog = request.getfixturevalue(f"{gait}_log")
    _, pyramid, fn = _friction_excess(log)
    assert fn.min() >= -SOLVER_TOLERANCE_N
    assert pyramid.max() <= SOLVER_TOLERANCE_N
    assert np.abs(log.wbc_forces[~log.stance]).max() <= SOLVER_TOLERANCE_N
