"""Messages as CDR bytes, both ways: read a header stamp without deserialising (and deserialise only what a tick
uses), and publish a fixed-layout message by patching its serialised bytes instead of building a Python message.

Taking: a node that needs one joint state in four (a 250 Hz controller on a 1 kHz driver) or only the samples on its
tick grid still pays the executor's dispatch for every message, but not the Python message construction:
``subscribe_stamped`` peeks at ``header.stamp`` in the serialised bytes and deserialises a message only when
``wants(stamp_ns)`` says the node will use it (``bench/bench_messages.py`` measures the difference).

Publishing: ``CdrTemplate`` serialises a message once, with every string and sequence at its final length, and
computes where each numeric field lies in the bytes (plain CDR, XCDR1: primitives aligned to their size from the
start of the payload, strings and sequences prefixed by a uint32 length). A node then writes a tick's numbers
into numpy views of the buffer and publishes the bytes (rclpy publishes ``bytes`` as a serialised message);
rclpy's conversion of a Python message, which dominated the wbc's publishing, is not run at all.

Every message whose first field is ``std_msgs/Header`` starts, after the 4-byte CDR encapsulation header,
with ``stamp.sec`` (int32) and ``stamp.nanosec`` (uint32) in the byte order the encapsulation names.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Any

import numpy as np
from rclpy.node import Node
from rclpy.serialization import deserialize_message, serialize_message
from rosidl_parser import definition

from tal_core.errors import InputError
from tal_core.ticks import NS_PER_S

_LITTLE = struct.Struct("<iI")
_BIG = struct.Struct(">iI")


def stamp_ns_of(data: bytes) -> int:
    """``header.stamp`` [ns] of a serialised message whose first field is a std_msgs/Header."""
    if len(data) < 12:
        raise InputError(f"serialised message of {len(data)} bytes is too short for a header stamp")
    sec, nanosec = (_LITTLE if data[1] & 1 else _BIG).unpack_from(data, 4)
    return sec * NS_PER_S + nanosec


def subscribe_stamped(node: Node, msg_type: Any, topic: str, callback: Callable[[Any], None],
                      qos: Any, *, wants: Callable[[int], bool],
                      on_error: Callable[[Exception], None] | None = None) -> Any:
    """A subscription that deserialises a message of ``msg_type`` (a stamped type) only when ``wants`` of its
    header stamp is true, then calls ``callback(msg)``. A message too short or that fails to deserialise goes
    to ``on_error`` (counted by the node) instead of raising in the executor."""

    def on_raw(data: bytes) -> None:
        try:
            if not wants(stamp_ns_of(data)):
                return
            msg = deserialize_message(data, msg_type)
        except Exception as exc:  # a corrupt sample must not stop the node
            if on_error is None:
                raise
            on_error(exc)
            return
        callback(msg)

    return node.create_subscription(msg_type, topic, on_raw, qos, raw=True)


_FORMATS = {  # rosidl basic type -> (numpy dtype, size [B])
    "boolean": ("?", 1), "octet": ("u1", 1), "uint8": ("u1", 1), "char": ("u1", 1), "int8": ("i1", 1),
    "uint16": ("<u2", 2), "int16": ("<i2", 2), "uint32": ("<u4", 4), "int32": ("<i4", 4),
    "uint64": ("<u8", 8), "int64": ("<i8", 8), "float": ("<f4", 4), "double": ("<f8", 8),
}


class CdrTemplate:
    """A serialised message whose numeric fields are written in place (see the module docstring).

    ``field(path)`` is a writable numpy view of a numeric field: ``"step_frequency"`` (shape (1,)),
    ``"phase"`` (a fixed array or a sequence, shape (n,)), ``"liftoff_position"`` for an array of
    geometry_msgs/Point or Vector3 (shape (n, 3): the three float64 of each element are contiguous), or a
    nested leaf such as ``"base_twist.linear.x"``. Strings and sequence lengths are those of the message the
    template was made from; a message whose strings or lengths change needs another template.
    """

    def __init__(self, msg: Any) -> None:
        data = serialize_message(msg)
        if not data[1] & 1:
            raise InputError("CdrTemplate: big-endian serialisation is not supported")
        self.type_name = type(msg).__name__
        self.buffer = bytearray(data)
        self.offsets: dict[str, tuple[int, str, int]] = {}  # path -> (offset in buffer, dtype, count)
        end = _walk(msg, "", 0, self.offsets)
        if end + 4 > len(self.buffer):
            raise InputError(f"CdrTemplate({self.type_name}): layout of {end} bytes does not fit the "
                             f"{len(self.buffer) - 4} serialised ones")
        self._views: dict[str, np.ndarray] = {}

    def field(self, path: str) -> np.ndarray:
        view = self._views.get(path)
        if view is None:
            view = self._views[path] = self._view(path)
        return view

    def set_xyz(self, path: str, value) -> None:
        """The x, y, z leaves of a nested geometry_msgs/Point or Vector3 field (``"pose.pose.position"``)."""
        for axis, v in zip("xyz", value):
            self.field(f"{path}.{axis}")[0] = v

    def set_stamp(self, stamp_ns: int) -> None:
        """``header.stamp`` [ns]."""
        sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
        _LITTLE.pack_into(self.buffer, self.offsets["header.stamp.sec"][0], sec, nanosec)

    def data(self) -> bytes:
        """The serialised message as it stands (a copy: the template may be written again at once)."""
        return bytes(self.buffer)

    def _view(self, path: str) -> np.ndarray:
        if path in self.offsets:
            offset, dtype, count = self.offsets[path]
            return np.frombuffer(self.buffer, dtype=dtype, count=count, offset=offset)
        xs = [self.offsets.get(f"{path}[{i}].x") for i in range(len(self.offsets))]
        xs = [x for x in xs[: next((i for i, x in enumerate(xs) if x is None), len(xs))]]
        if not xs:
            raise KeyError(f"CdrTemplate({self.type_name}) has no numeric field '{path}'")
        first = xs[0][0]
        if any(x[0] != first + 24 * i or x[1] != "<f8" for i, x in enumerate(xs)) \
                or self.offsets[f"{path}[0].z"][0] != first + 16:
            raise KeyError(f"CdrTemplate({self.type_name}): '{path}' is not an array of x, y, z float64")
        return np.frombuffer(self.buffer, dtype="<f8", count=3 * len(xs), offset=first).reshape(len(xs), 3)


def _walk(msg: Any, prefix: str, pos: int, out: dict[str, tuple[int, str, int]]) -> int:
    """Lay out ``msg``'s fields from payload position ``pos``; record numeric leaves (offsets include the 4-byte
    encapsulation header); return the position after the message."""
    for slot, slot_type in zip(msg.__slots__, msg.SLOT_TYPES):
        name = slot.lstrip("_")
        value = getattr(msg, name)
        path = f"{prefix}{name}"
        if isinstance(slot_type, definition.BasicType):
            pos = _leaf(path, slot_type.typename, 1, pos, out)
        elif isinstance(slot_type, definition.AbstractGenericString):
            pos = _string(value, pos)
        elif isinstance(slot_type, definition.NamespacedType):
            pos = _walk(value, f"{path}.", pos, out)
        elif isinstance(slot_type, definition.AbstractNestedType):
            if isinstance(slot_type, definition.AbstractSequence):
                pos = _align(pos, 4) + 4
            item = slot_type.value_type
            if isinstance(item, definition.BasicType):
                pos = _leaf(path, item.typename, len(value), pos, out)
            elif isinstance(item, definition.AbstractGenericString):
                for text in value:
                    pos = _string(text, pos)
            else:
                for i, element in enumerate(value):
                    pos = _walk(element, f"{path}[{i}].", pos, out)
        else:
            raise InputError(f"CdrTemplate: field '{path}' has an unsupported type {slot_type}")
    return pos


def _align(pos: int, size: int) -> int:
    return (pos + size - 1) // size * size


def _leaf(path: str, typename: str, count: int, pos: int, out: dict[str, tuple[int, str, int]]) -> int:
    dtype, size = _FORMATS[typename]
    if count == 0:  # an empty sequence: its length prefix only, no alignment for elements
        return pos
    pos = _align(pos, min(size, 8))
    out[path] = (pos + 4, dtype, count)
    return pos + size * count


def _string(text: str, pos: int) -> int:
    return _align(pos, 4) + 4 + len(text.encode("utf-8")) + 1
