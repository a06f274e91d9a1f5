"""Shared fixtures of the perception and ViTAL lab tests (a pytest plugin loaded by the root conftest): the HyQ
model, the FEC evaluator and the VFA selector, built once per session."""

from __future__ import annotations

import pytest

from tal_core.robot_model import RobotModel
from tal_perception.fec import FootholdEvaluator
from tal_perception.vfa import FootholdSelector


@pytest.fixture(scope="session")
def hyq() -> RobotModel:
    return RobotModel.from_name("hyq")


@pytest.fixture(scope="session")
def evaluator(hyq: RobotModel) -> FootholdEvaluator:
    return FootholdEvaluator(hyq)


@pytest.fixture(scope="session")
def selector(evaluator: FootholdEvaluator) -> FootholdSelector:
    return FootholdSelector(evaluator)


@pytest.fixture(scope="session")
def hip_height(hyq: RobotModel) -> float:
    """[m] world z of the HAA joints when HyQ stands in its nominal pose on flat ground at z = 0."""
    return float(hyq.nominal_base_height_m)
