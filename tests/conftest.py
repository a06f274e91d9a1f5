"""Fixtures shared by the graph tests: a private rclpy context and a spin-until helper."""

from __future__ import annotations

import time
from collections.abc import Callable

import pytest
import rclpy


@pytest.fixture
def context():
    """A private rclpy context (nodes of one test never see another test's)."""
    ctx = rclpy.context.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.shutdown(context=ctx)


def _spin_until(executor, predicate: Callable[[], bool], timeout_s: float) -> bool:
    """Spin ``executor`` until ``predicate()`` holds or ``timeout_s`` [s] of wall time passed."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        executor.spin_once(timeout_sec=0.05)
    return predicate()


@pytest.fixture
def spin_until() -> Callable[..., bool]:
    return _spin_until
