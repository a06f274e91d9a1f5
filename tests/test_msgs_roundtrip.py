"""Every tal_msgs message survives a real rclpy publish/subscribe round trip unchanged.

Each message is filled, field by field, with non-default values by a generic filler that walks the
generated type description (``get_fields_and_field_types()`` and ``SLOT_TYPES``), so a field added to a
.msg file is covered without touching this test. Publisher and subscriber live in one node of a private
context; the executor is spun with ``spin_once`` until the message arrives or a deadline passes.
"""

from __future__ import annotations

import array
import importlib
import itertools
import os
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rosidl_parser.definition import (
    AbstractGenericString,
    AbstractNestedType,
    Array,
    BasicType,
    BoundedSequence,
    NamespacedType,
)

import tal_msgs.msg
from tal_msgs.msg import (
    BodyPoseReference,
    ContactState,
    Foothold,
    FootholdArray,
    GaitState,
    HeightMap,
    JointCommand,
    TerrainImpedance,
    WbcDiagnostics,
)

pytestmark = pytest.mark.ros

MESSAGE_TYPES = (JointCommand, ContactState, TerrainImpedance, HeightMap, GaitState, Foothold, FootholdArray,
                 BodyPoseReference, WbcDiagnostics)
MSG_DIR = Path(__file__).resolve().parents[1] / "tal_msgs" / "msg"
NUM_LEGS = 4
LEG_CONSTANTS = {"LF": 0, "RF": 1, "LH": 2, "RH": 3}
SEQUENCE_LENGTH = 3  # elements put into every unbounded sequence
DEADLINE_S = 5.0
REPUBLISH_PERIOD_S = 0.1
TOPIC_PREFIX = f"tal_roundtrip_{os.getpid()}"  # other test processes on this machine share the DDS domain


# --- generic filler ----------------------------------------------------------------------------------
def _message_class(slot_type: NamespacedType) -> type:
    return getattr(importlib.import_module(".".join(slot_type.namespaces)), slot_type.name)


class Filler:
    """Fills messages with values that differ from the defaults and from each other.

    A running counter makes every number unique within a message, so per-leg arrays get 4 distinct
    values and a field swapped with another would be noticed. Numbers are small multiples of 1/4 and so
    exact in float32 as well as float64; booleans alternate, starting with True.
    """

    def __init__(self) -> None:
        self._counter = itertools.count(1)

    def message(self, msg_class: type) -> object:
        msg = msg_class()
        fields = msg_class.get_fields_and_field_types()
        assert len(fields) == len(msg_class.SLOT_TYPES)
        for name, slot_type in zip(fields, msg_class.SLOT_TYPES, strict=True):
            setattr(msg, name, self.value(slot_type))
        return msg

    def value(self, slot_type) -> object:
        if isinstance(slot_type, NamespacedType):
            return self.message(_message_class(slot_type))
        if isinstance(slot_type, AbstractNestedType):
            if isinstance(slot_type, Array):
                size = slot_type.size
            elif isinstance(slot_type, BoundedSequence):
                size = min(SEQUENCE_LENGTH, slot_type.maximum_size)
            else:
                size = SEQUENCE_LENGTH
            return [self.value(slot_type.value_type) for _ in range(size)]
        if isinstance(slot_type, AbstractGenericString):
            return f"value_{next(self._counter)}"
        assert isinstance(slot_type, BasicType), f"unsupported field type {slot_type!r}"
        n = next(self._counter)
        typename = slot_type.typename
        if typename == "boolean":
            return n % 2 == 1
        if typename in ("float", "double", "long double"):
            return n + 0.25
        if typename == "octet":
            return bytes([n % 256])
        if typename == "char":
            return n % 128
        if typename.startswith("int"):
            return -(n % 100) - 1  # negative: checks the sign survives
        return n % 250 + 1  # uint8 .. uint64


# --- field-by-field comparison -------------------------------------------------------------------------
def _is_message(value: object) -> bool:
    return hasattr(type(value), "get_fields_and_field_types")


def assert_equal_fields(received: object, sent: object, path: str) -> None:
    """Compare recursively and name the first differing field (more helpful than ``==`` alone)."""
    if _is_message(sent):
        assert type(received) is type(sent), f"{path}: type {type(received)} != {type(sent)}"
        for name in type(sent).get_fields_and_field_types():
            assert_equal_fields(getattr(received, name), getattr(sent, name), f"{path}.{name}")
    elif isinstance(sent, (list, tuple, array.array, np.ndarray)):
        assert len(received) == len(sent), f"{path}: length {len(received)} != {len(sent)}"
        for i, (r, s) in enumerate(zip(received, sent, strict=True)):
            assert_equal_fields(r, s, f"{path}[{i}]")
    else:
        assert received == sent, f"{path}: received {received!r}, sent {sent!r}"


def differs_from(value: object, default: object) -> bool:
    """True when no part of ``value`` is left at the default (every leaf field was changed)."""
    if _is_message(value):
        return all(differs_from(getattr(value, f), getattr(default, f))
                   for f in type(value).get_fields_and_field_types())
    if isinstance(value, (list, tuple, array.array, np.ndarray)):
        if len(default) == 0:
            return len(value) > 0
        return any(differs_from(v, d) for v, d in zip(value, default, strict=True))
    return value != default


# --- ROS fixtures ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def ros(request: pytest.FixtureRequest):
    """(node, executor) on a private context, shut down by a finaliser."""
    ctx = rclpy.context.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("probe", context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)

    def finalise() -> None:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)

    request.addfinalizer(finalise)
    return node, executor


def round_trip(ros, msg_class: type, sent: object) -> object:
    node, executor = ros
    topic = f"{TOPIC_PREFIX}/{msg_class.__name__.lower()}"
    received: list[object] = []
    subscription = node.create_subscription(msg_class, topic, received.append, 10)
    publisher = node.create_publisher(msg_class, topic, 10)
    try:
        deadline = time.monotonic() + DEADLINE_S
        next_publish = 0.0
        while not received and time.monotonic() < deadline:
            if time.monotonic() >= next_publish:  # until discovery has matched the pair
                publisher.publish(sent)
                next_publish = time.monotonic() + REPUBLISH_PERIOD_S
            executor.spin_once(timeout_sec=0.02)
    finally:
        node.destroy_publisher(publisher)
        node.destroy_subscription(subscription)
    assert received, f"no {msg_class.__name__} received on {topic} within {DEADLINE_S} s"
    return received[0]


# --- tests ---------------------------------------------------------------------------------------------
def test_every_msg_file_is_covered() -> None:
    declared = {path.stem for path in MSG_DIR.glob("*.msg")}
    generated = {name for name in dir(tal_msgs.msg) if not name.startswith("_")}
    assert declared == {cls.__name__ for cls in MESSAGE_TYPES}
    assert generated == declared


@pytest.mark.parametrize("msg_class", MESSAGE_TYPES, ids=lambda c: c.__name__)
def test_filler_changes_every_field(msg_class: type) -> None:
    sent = Filler().message(msg_class)
    default = msg_class()
    for name in msg_class.get_fields_and_field_types():
        assert differs_from(getattr(sent, name), getattr(default, name)), f"{msg_class.__name__}.{name}"
    assert sent != default


@pytest.mark.parametrize("msg_class", MESSAGE_TYPES, ids=lambda c: c.__name__)
def test_message_round_trip(ros, msg_class: type) -> None:
    sent = Filler().message(msg_class)
    received = round_trip(ros, msg_class, sent)
    assert received is not sent
    assert_equal_fields(received, sent, msg_class.__name__)
    assert received == sent


@pytest.mark.parametrize("msg_class", MESSAGE_TYPES, ids=lambda c: c.__name__)
def test_fixed_arrays_are_per_leg(msg_class: type) -> None:
    msg = Filler().message(msg_class)
    fields = msg_class.get_fields_and_field_types()
    for (name, type_name), slot_type in zip(fields.items(), msg_class.SLOT_TYPES, strict=True):
        if isinstance(slot_type, Array):
            assert slot_type.size == NUM_LEGS, f"{msg_class.__name__}.{name} is {type_name}"
            assert len(getattr(msg, name)) == NUM_LEGS
            assert len(getattr(msg_class(), name)) == NUM_LEGS
            values = [repr(v) for v in getattr(msg, name)]
            if slot_type.value_type != BasicType("boolean"):
                assert len(set(values)) == NUM_LEGS, f"{msg_class.__name__}.{name}: {values}"


def test_per_leg_messages_have_fixed_arrays() -> None:
    per_leg = (ContactState, TerrainImpedance, GaitState, BodyPoseReference, WbcDiagnostics)
    for msg_class in per_leg:
        assert any(isinstance(t, Array) for t in msg_class.SLOT_TYPES), msg_class.__name__


@pytest.mark.parametrize("msg_class", [ContactState, Foothold], ids=lambda c: c.__name__)
def test_leg_constants_where_declared(msg_class: type) -> None:
    for name, value in LEG_CONSTANTS.items():
        assert getattr(msg_class, name) == value, f"{msg_class.__name__}.{name}"


@pytest.mark.parametrize("msg_class", MESSAGE_TYPES, ids=lambda c: c.__name__)
def test_leg_constants_are_all_or_nothing(msg_class: type) -> None:
    present = {name: getattr(msg_class, name) for name in LEG_CONSTANTS if hasattr(msg_class, name)}
    assert present in ({}, LEG_CONSTANTS), f"{msg_class.__name__}: {present}"


def test_foothold_array_round_trip_keeps_nested_order(ros) -> None:
    filler = Filler()
    sent = FootholdArray(header=filler.message(FootholdArray).header,
                         footholds=[filler.message(Foothold) for _ in range(NUM_LEGS)])
    for leg, foothold in zip(LEG_CONSTANTS.values(), sent.footholds, strict=True):
        foothold.leg = leg
    received = round_trip(ros, FootholdArray, sent)
    assert [f.leg for f in received.footholds] == [Foothold.LF, Foothold.RF, Foothold.LH, Foothold.RH]
    assert received == sent
