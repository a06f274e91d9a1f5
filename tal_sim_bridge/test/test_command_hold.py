"""Tests of tal_sim_bridge.command_hold: validation, canonical reordering and the held PD law."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tal_sim_bridge.command_hold import JointCommandHold
from tal_sim_bridge.errors import CommandRejectedError

JOINTS = tuple(f"{leg}_{kind}_joint" for leg in ("lf", "rf", "lh", "rh") for kind in ("haa", "hfe", "kfe"))
N = len(JOINTS)
FIELDS = ("effort", "position", "velocity", "kp", "kd")
SAFE_DAMPING = 5.0


def full_command(seed: int = 0) -> dict[str, np.ndarray]:
    """Every field filled with distinct values in canonical order (gains positive)."""
    rng = np.random.default_rng(seed)
    return {
        "effort": rng.uniform(-50.0, 50.0, N),
        "position": rng.uniform(-1.5, 1.5, N),
        "velocity": rng.uniform(-2.0, 2.0, N),
        "kp": rng.uniform(100.0, 2000.0, N),
        "kd": rng.uniform(1.0, 50.0, N),
    }


def submit(hold: JointCommandHold, stamp_ns: int, names, fields: dict) -> object:
    return hold.submit(stamp_ns, names, fields["effort"], fields.get("position", ()),
                       fields.get("velocity", ()), fields.get("kp", ()), fields.get("kd", ()))


@pytest.fixture()
def hold() -> JointCommandHold:
    return JointCommandHold(JOINTS, SAFE_DAMPING)


# --- accepted commands -------------------------------------------------------------------------------
def test_shuffled_joint_order_is_mapped_to_canonical_order(hold: JointCommandHold) -> None:
    canonical = full_command()
    perm = np.random.default_rng(1).permutation(N)
    assert not np.array_equal(perm, np.arange(N))
    names = [JOINTS[i] for i in perm]
    shuffled = {key: values[perm] for key, values in canonical.items()}
    held = submit(hold, 10, names, shuffled)
    assert held is hold.held
    assert held.stamp_ns == 10
    for key in FIELDS:
        np.testing.assert_array_equal(getattr(held, key), canonical[key], err_msg=key)
    assert hold.accepted == 1
    assert hold.rejected_total == 0


def test_held_torque_is_effort_plus_pd(hold: JointCommandHold) -> None:
    cmd = full_command(2)
    submit(hold, 0, JOINTS, cmd)
    rng = np.random.default_rng(3)
    for _ in range(5):
        q, qd = rng.uniform(-1.5, 1.5, N), rng.uniform(-3.0, 3.0, N)
        expected = cmd["effort"] + cmd["kp"] * (cmd["position"] - q) + cmd["kd"] * (cmd["velocity"] - qd)
        np.testing.assert_allclose(hold.torque(q, qd), expected, rtol=1e-12, atol=1e-9)


def test_held_torque_in_shuffled_order_matches_the_canonical_law(hold: JointCommandHold) -> None:
    cmd = full_command(4)
    perm = np.arange(N)[::-1]
    submit(hold, 0, [JOINTS[i] for i in perm], {k: v[perm] for k, v in cmd.items()})
    q, qd = np.linspace(-1.0, 1.0, N), np.linspace(2.0, -2.0, N)
    expected = cmd["effort"] + cmd["kp"] * (cmd["position"] - q) + cmd["kd"] * (cmd["velocity"] - qd)
    np.testing.assert_allclose(hold.torque(q, qd), expected, rtol=1e-12, atol=1e-9)


def test_effort_only_command_is_pure_feed_forward(hold: JointCommandHold) -> None:
    effort = np.arange(N, dtype=float) - 6.0
    held = hold.submit(0, JOINTS, effort)
    assert held.position is None and held.velocity is None and held.kp is None and held.kd is None
    np.testing.assert_array_equal(hold.torque(np.ones(N), np.full(N, 3.0)), effort)


def test_kd_without_velocity_targets_zero_velocity(hold: JointCommandHold) -> None:
    kd = np.full(N, 10.0)
    hold.submit(0, JOINTS, np.zeros(N), kd=kd)
    qd = np.linspace(-1.0, 1.0, N)
    np.testing.assert_allclose(hold.torque(np.zeros(N), qd), -10.0 * qd)


def test_before_any_command_the_joints_are_damped(hold: JointCommandHold) -> None:
    assert hold.held is None
    qd = np.linspace(-2.0, 2.0, N)
    np.testing.assert_allclose(hold.torque(np.full(N, 0.7), qd), -SAFE_DAMPING * qd)


def test_a_newer_command_replaces_the_held_one_and_equal_stamps_are_accepted(hold: JointCommandHold) -> None:
    submit(hold, 100, JOINTS, full_command(5))
    submit(hold, 100, JOINTS, full_command(6))
    newest = submit(hold, 200, JOINTS, full_command(7))
    assert hold.held is newest
    assert hold.accepted == 3


def test_held_arrays_are_copies_of_the_input(hold: JointCommandHold) -> None:
    cmd = full_command(8)
    submit(hold, 0, JOINTS, cmd)
    reference = hold.torque(np.zeros(N), np.zeros(N))
    for values in cmd.values():
        values[:] = 1e6
    np.testing.assert_array_equal(hold.torque(np.zeros(N), np.zeros(N)), reference)


# --- rejections ----------------------------------------------------------------------------------------
def _bad(field: str, size: int | None = None, value: float | None = None, index: int = 3):
    """A full command in canonical order with one field resized or one entry replaced."""
    def build() -> tuple[int, list[str], dict]:
        cmd = full_command(9)
        if size is not None:
            cmd[field] = cmd[field][:size] if size <= N else np.concatenate([cmd[field], np.ones(size - N)])
        if value is not None:
            cmd[field][index] = value
        return 2_000, list(JOINTS), cmd
    return build


def _names(names: list[str]):
    def build() -> tuple[int, list[str], dict]:
        cmd = full_command(9)
        if len(names) != N:
            cmd = {key: values[:len(names)] for key, values in cmd.items()}
        return 2_000, names, cmd
    return build


def _without(*fields: str):
    def build() -> tuple[int, list[str], dict]:
        cmd = full_command(9)
        for field in fields:
            cmd[field] = np.array([])
        return 2_000, list(JOINTS), cmd
    return build


def _stale():
    def build() -> tuple[int, list[str], dict]:
        return 999, list(JOINTS), full_command(9)
    return build


REJECTIONS = [
    ("empty", _names([]), r"no joint names"),
    ("unknown_joint", _names([*JOINTS[:-1], "tail_joint"]), r"unknown joint\(s\) \['tail_joint'\]"),
    ("duplicate_joint", _names([*JOINTS[:-1], JOINTS[0]]), r"repeats joint names"),
    ("out_of_order", _stale(), r"stamp 999 ns is older than the held command \(1000 ns\)"),
    *[("wrong_size", _bad(f, size=N - 1), rf"field '{f}' has 11 values for 12 names") for f in FIELDS],
    *[("wrong_size", _bad(f, size=N + 2), rf"field '{f}' has 14 values for 12 names") for f in FIELDS],
    *[("non_finite", _bad(field, value=math.nan), rf"field '{field}' has NaN or inf") for field in FIELDS],
    ("non_finite", _bad("effort", value=math.inf), r"field 'effort' has NaN or inf"),
    ("non_finite", _bad("kd", value=-math.inf), r"field 'kd' has NaN or inf"),
    ("negative_gain", _bad("kp", value=-1.0), r"field 'kp' has negative gains"),
    ("negative_gain", _bad("kd", value=-0.5), r"field 'kd' has negative gains"),
    ("wrong_size", _without("position"), r"kp without position targets"),
    ("wrong_size", _without("position", "velocity"), r"kp without position targets"),
    ("wrong_size", _names(list(JOINTS[:9])), r"names 9 joints, the robot has 12"),
    ("wrong_size", _names([JOINTS[0]]), r"names 1 joints, the robot has 12"),
]


@pytest.mark.parametrize(("reason", "build", "message"), REJECTIONS,
                         ids=[f"{r[0]}-{i}" for i, r in enumerate(REJECTIONS)])
def test_rejection_is_counted_and_keeps_the_held_command(hold: JointCommandHold, reason: str, build,
                                                          message: str) -> None:
    previous = submit(hold, 1_000, JOINTS, full_command(10))
    q, qd = np.full(N, 0.2), np.full(N, -0.3)
    torque_before = hold.torque(q, qd)
    stamp, names, cmd = build()
    with pytest.raises(CommandRejectedError, match=message) as info:
        submit(hold, stamp, names, cmd)
    assert info.value.reason == reason
    assert hold.rejections == {reason: 1}
    assert hold.rejected_total == 1
    assert hold.accepted == 1
    assert hold.held is previous
    np.testing.assert_array_equal(hold.torque(q, qd), torque_before)


def test_rejection_before_any_command_keeps_damping(hold: JointCommandHold) -> None:
    with pytest.raises(CommandRejectedError) as info:
        hold.submit(0, JOINTS, [math.nan] * N)
    assert info.value.reason == "non_finite"
    assert hold.held is None
    qd = np.ones(N)
    np.testing.assert_allclose(hold.torque(np.zeros(N), qd), -SAFE_DAMPING * qd)


def test_rejections_accumulate_per_reason(hold: JointCommandHold) -> None:
    submit(hold, 50, JOINTS, full_command(11))
    bad = [
        (lambda: hold.submit(10, JOINTS, np.zeros(N)), "out_of_order"),
        (lambda: hold.submit(60, JOINTS, np.zeros(N - 1)), "wrong_size"),
        (lambda: hold.submit(60, JOINTS, np.zeros(N), kp=np.ones(N)), "wrong_size"),
        (lambda: hold.submit(60, ["nope"], [0.0]), "unknown_joint"),
        (lambda: hold.submit(60, [], []), "empty"),
    ]
    for call, reason in bad:
        with pytest.raises(CommandRejectedError) as info:
            call()
        assert info.value.reason == reason
    assert hold.rejections == {"out_of_order": 1, "wrong_size": 2, "unknown_joint": 1, "empty": 1}
    assert hold.rejected_total == 5
    # A valid command still goes through afterwards.
    submit(hold, 60, JOINTS, full_command(12))
    assert hold.accepted == 2
