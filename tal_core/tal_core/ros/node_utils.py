"""Small helpers shared by the thin ROS 2 node adapters of every tal package.

This and ``fault_injection`` (a relay node for fault tests) are the tal_core modules that import rclpy;
algorithm modules never import it. It holds what every node needs the same way: declaring validated
parameters with descriptions and ranges, stamp conversions, and the Jazzy ``main()`` pattern.
"""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import rclpy
from builtin_interfaces.msg import Time
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node

from tal_core.ticks import NS_PER_S, TICK_TOLERANCE_NS, reaches_tick, tick_after  # noqa: F401 (re-exported)


def stamp_from_ns(nanoseconds: int) -> Time:
    """builtin_interfaces/Time from integer nanoseconds."""
    sec, nanosec = divmod(int(nanoseconds), NS_PER_S)
    return Time(sec=sec, nanosec=nanosec)


def ns_from_stamp(stamp: Time) -> int:
    """Integer nanoseconds from builtin_interfaces/Time."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def declare(node: Node, name: str, default: Any, description: str, *,
            low: float | int | None = None, high: float | int | None = None,
            choices: Sequence[str] | None = None, on_change: Callable[[Any], None] | None = None) -> Any:
    """Declare a parameter with a description and an optional range or set of choices; return its value.

    Without ``on_change`` the parameter is read-only: ``ros2 param set`` is refused, never silently ignored.
    With ``on_change(value)`` it is live: a set at run time is checked against the same range and choices and
    then handed to ``on_change``, which applies it or raises ``ValueError``/``TypeError`` with the reason the
    set is rejected (``SetParametersResult.reason``). Out-of-range values given at start-up (overrides or
    YAML) raise ``ValueError`` naming the parameter.
    """
    descriptor = ParameterDescriptor(description=description, read_only=on_change is None)
    if choices is not None:
        descriptor.additional_constraints = f"one of: {', '.join(choices)}"
    if low is not None and high is not None:
        if isinstance(default, bool):
            pass
        elif isinstance(default, int):
            descriptor.integer_range = [IntegerRange(from_value=int(low), to_value=int(high), step=0)]
        elif isinstance(default, float):
            descriptor.floating_point_range = [FloatingPointRange(from_value=float(low), to_value=float(high),
                                                                  step=0.0)]
    try:
        value = node.declare_parameter(name, default, descriptor).value
    except Exception as exc:  # rclpy raises several exception types for invalid start-up values
        raise ValueError(f"parameter '{name}': {exc}") from exc
    check_value(name, value, low=low, high=high, choices=choices)
    if on_change is not None:
        _live_parameters(node).add(name, _LiveParameter(low, high, choices, on_change))
    return value


def check_value(name: str, value: Any, *, low: float | int | None = None, high: float | int | None = None,
                choices: Sequence[str] | None = None) -> None:
    """Raise ``ValueError`` naming ``name`` when ``value`` is outside ``choices`` or [low, high]."""
    if choices is not None and value not in choices:
        raise ValueError(f"parameter '{name}' must be one of {list(choices)}, got {value!r}")
    numeric = isinstance(value, (int, float)) and not isinstance(value, bool)
    if low is not None and numeric and value < low:
        raise ValueError(f"parameter '{name}' must be >= {low}, got {value!r}")
    if high is not None and numeric and value > high:
        raise ValueError(f"parameter '{name}' must be <= {high}, got {value!r}")


class _LiveParameter:
    def __init__(self, low, high, choices, apply: Callable[[Any], None]) -> None:
        self.low, self.high, self.choices, self.apply = low, high, choices, apply


class _LiveParameters:
    """The node's live parameters behind one on-set callback: each set value is checked, then applied in
    order; the first rejection stops there and its reason is returned to the caller."""

    def __init__(self, node: Node) -> None:
        self._entries: dict[str, _LiveParameter] = {}
        node.add_on_set_parameters_callback(self._on_set)

    def add(self, name: str, entry: _LiveParameter) -> None:
        self._entries[name] = entry

    def _on_set(self, parameters: list) -> SetParametersResult:
        for parameter in parameters:
            entry = self._entries.get(parameter.name)
            if entry is None:  # read-only ones are refused by rclpy itself; others belong to rclpy (use_sim_time)
                continue
            try:
                check_value(parameter.name, parameter.value, low=entry.low, high=entry.high, choices=entry.choices)
                entry.apply(parameter.value)
            except (ValueError, TypeError) as exc:
                return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)


def _live_parameters(node: Node) -> _LiveParameters:
    live = getattr(node, "_tal_live_parameters", None)
    if live is None:
        live = _LiveParameters(node)
        node._tal_live_parameters = live  # noqa: SLF001 (one registry per node, created on first use)
    return live


def run_node(factory: Callable[[], Node], args: Sequence[str] | None = None,
             until: Callable[[Node], bool] | None = None, name: str = "node",
             executor_factory: Callable[[], Executor] | None = None) -> int:
    """Jazzy main() pattern: init, spin until shutdown (or ``until(node)``), clean up. Returns an exit code.

    A configuration error raised while constructing the node (invalid parameter, bad course or robot
    file) is printed as one line naming the problem, and the exit code is 2 (no traceback).

    The executor is ``executor_factory`` when given, else rclpy's C++ EventsExecutor (rclpy.experimental),
    or the SingleThreadedExecutor when the environment sets TAL_EXECUTOR=single. Dispatching one 1 kHz
    JointState costs a node 205 us of CPU on the SingleThreadedExecutor (it rebuilds the wait set per
    message) and 53 us on the EventsExecutor (``bench/bench_messages.py``).
    """
    rclpy.init(args=args)
    node = None
    if executor_factory is None:
        executor_factory = SingleThreadedExecutor if os.environ.get("TAL_EXECUTOR") == "single" else _events_executor
    executor = executor_factory()
    code = 0
    try:
        try:
            node = factory()
        except (KeyboardInterrupt, ExternalShutdownException):
            raise
        except Exception as exc:  # start-up configuration errors of any tal package
            print(f"[{name}] start-up error: {type(exc).__name__}: {exc}", file=sys.stderr)
            return 2
        executor.add_node(node)
        while rclpy.ok() and not (until is not None and until(node)):
            try:
                executor.spin_once(timeout_sec=0.1)
            except Exception:
                # SIGINT/SIGTERM shut the context down while a callback was publishing (a real-time bridge
                # catching up publishes in a loop): rclpy raises "publisher's context is invalid". A stop.
                if rclpy.ok():
                    raise
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code


def _events_executor() -> Executor:
    """rclpy's C++ EventsExecutor (rclpy.experimental): the nodes' default."""
    from rclpy.experimental import EventsExecutor

    return EventsExecutor()


def write_summary(path: str, summary: dict, indent: int | None = 2) -> None:
    """Write a node's end-of-run summary as JSON to ``path`` (parents created); '' writes nothing."""
    if not path:
        return
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_text(json.dumps(summary, indent=indent) + "\n")
