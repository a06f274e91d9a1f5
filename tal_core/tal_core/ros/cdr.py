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


def _walk(msg: Any, prefix: str, pos: int, out: dict[str, tuple[int, str, int]],
          shape: list[tuple[int, bytes]] | None = None) -> int:
    """Lay out ``msg``'s fields from payload position ``pos``; record numeric leaves (offsets include the 4-byte
    encapsulation header); return the position after the message. ``shape`` collects (offset, bytes) of every
    string (length prefix and characters) and sequence length: what makes two messages' layouts differ."""
    for slot, slot_type in zip(msg.__slots__, msg.SLOT_TYPES):
        name = slot.lstrip("_")
        value = getattr(msg, name)
        path = f"{prefix}{name}"
        if isinstance(slot_type, definition.BasicType):
            pos = _leaf(path, slot_type.typename, 1, pos, out)
        elif isinstance(slot_type, definition.AbstractGenericString):
            pos = _string(value, pos, shape)
        elif isinstance(slot_type, definition.NamespacedType):
            pos = _walk(value, f"{path}.", pos, out, shape)
        elif isinstance(slot_type, definition.AbstractNestedType):
            if isinstance(slot_type, definition.AbstractSequence):
                pos = _align(pos, 4)
                if shape is not None:
                    shape.append((pos + 4, struct.pack("<I", len(value))))
                pos += 4
            item = slot_type.value_type
            if isinstance(item, definition.BasicType):
                pos = _leaf(path, item.typename, len(value), pos, out)
            elif isinstance(item, definition.AbstractGenericString):
                for text in value:
                    pos = _string(text, pos, shape)
            else:
                for i, element in enumerate(value):
                    pos = _walk(element, f"{path}[{i}].", pos, out, shape)
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


def _string(text: str, pos: int, shape: list[tuple[int, bytes]] | None = None) -> int:
    encoded = text.encode("utf-8") + b"\0"
    pos = _align(pos, 4)
    if shape is not None:
        shape.append((pos + 4, struct.pack("<I", len(encoded)) + encoded))
    return pos + 4 + len(encoded)


class CdrView:
    """The numeric fields of one serialised message, read in place (see ``CdrReader``): ``array(path)`` a
    read-only numpy view (a numeric leaf or array, as ``CdrTemplate.field``), ``vectors(path)`` an array of
    geometry_msgs Point/Vector3 as (n, 3), ``vector(path)`` one Point/Vector3 as (3,), ``stamp_ns``."""

    __slots__ = ("_layout", "data")

    def __init__(self, layout: _ReadLayout, data: bytes) -> None:
        self._layout = layout
        self.data = data

    @property
    def stamp_ns(self) -> int:
        return stamp_ns_of(self.data)

    @property
    def message(self) -> Any:
        """The message this view's layout was learnt from (its strings and sequence lengths are this
        message's; its numbers are not)."""
        return self._layout.message

    def per_layout(self, key: Any, compute: Callable[[Any], Any]) -> Any:
        """``compute(message)`` once per layout and ``key`` (what a reader derives from the strings and lengths
        alone, e.g. where each named joint goes), then the stored value for every message of that layout."""
        memo = self._layout.memo
        if key not in memo:
            memo[key] = compute(self._layout.message)
        return memo[key]

    def array(self, path: str) -> np.ndarray:
        offset, dtype, count = self._layout.slot(path)
        return np.frombuffer(self.data, dtype=dtype, count=count, offset=offset)

    def vectors(self, path: str) -> np.ndarray:
        offset, count = self._layout.xyz_array(path)
        return np.frombuffer(self.data, dtype="<f8", count=3 * count, offset=offset).reshape(count, 3)

    def vector(self, path: str) -> np.ndarray:
        offset = self._layout.xyz(path)
        return np.frombuffer(self.data, dtype="<f8", count=3, offset=offset)

    def quaternion(self, path: str) -> np.ndarray:
        """A geometry_msgs/Quaternion as (x, y, z, w)."""
        offset = self._layout.xyz(path, "xyzw")
        return np.frombuffer(self.data, dtype="<f8", count=4, offset=offset)


class _ReadLayout:
    def __init__(self, msg: Any, length: int) -> None:
        self.message = msg
        self.length = length
        self.offsets: dict[str, tuple[int, str, int]] = {}
        self.shape: list[tuple[int, bytes]] = []
        _walk(msg, "", 0, self.offsets, self.shape)
        self._xyz: dict[str, Any] = {}
        self.memo: dict[Any, Any] = {}

    def matches(self, data: bytes) -> bool:
        if len(data) != self.length:
            return False
        for offset, expected in self.shape:
            if data[offset:offset + len(expected)] != expected:
                return False
        return True

    def slot(self, path: str) -> tuple[int, str, int]:
        try:
            return self.offsets[path]
        except KeyError:
            raise KeyError(f"CdrReader({type(self.message).__name__}) has no numeric field '{path}'") from None

    def xyz(self, path: str, axes: str = "xyz") -> int:
        """Offset of the contiguous float64 leaves ``axes`` of the nested field ``path``."""
        key = f"{path}.{axes}"
        cached = self._xyz.get(key)
        if cached is None:
            slots = [self.slot(f"{path}.{axis}") for axis in axes]
            if any(slot[1] != "<f8" or slot[0] != slots[0][0] + 8 * i for i, slot in enumerate(slots)):
                raise KeyError(f"CdrReader: '{path}' is not {', '.join(axes)} float64")
            cached = self._xyz[key] = slots[0][0]
        return cached

    def xyz_array(self, path: str) -> tuple[int, int]:
        cached = self._xyz.get(path + "[]")
        if cached is None:
            count = 0
            while f"{path}[{count}].x" in self.offsets:
                count += 1
            first = self.xyz(f"{path}[0]") if count else 0
            if any(self.xyz(f"{path}[{i}]") != first + 24 * i for i in range(count)):
                raise KeyError(f"CdrReader: '{path}' is not an array of x, y, z float64")
            cached = self._xyz[path + "[]"] = (first, count)
        return cached


class CdrReader:
    """Reads serialised messages of one type without building Python messages (rclpy's conversion of a
    nested message, a Python object per Point or Vector3, dominated the cost of taking one).

    The layout of a message (where each numeric field lies) depends only on its strings and sequence
    lengths. ``read(data)`` checks them against the layouts learnt so far (a few byte comparisons) and
    returns a ``CdrView`` of the numbers in place; a message of a new shape is deserialised once to learn its
    layout (up to ``max_layouts`` are kept, the oldest forgotten). Little-endian CDR only; a big-endian or
    undecodable message raises (``InputError`` or rclpy's error), as deserialising it would."""

    def __init__(self, msg_type: Any, max_layouts: int = 4) -> None:
        self.msg_type = msg_type
        self.max_layouts = max_layouts
        self._layouts: list[_ReadLayout] = []
        self.layouts_learnt = 0

    def read(self, data: bytes) -> CdrView:
        for layout in self._layouts:
            if layout.matches(data):
                return CdrView(layout, data)
        return CdrView(self._learn(data), data)

    def _learn(self, data: bytes) -> _ReadLayout:
        if len(data) < 4 or not data[1] & 1:
            raise InputError("CdrReader: not a little-endian CDR message")
        msg = deserialize_message(data, self.msg_type)
        layout = _ReadLayout(msg, len(data))
        if not layout.matches(data):
            raise InputError(f"CdrReader({self.msg_type.__name__}): message layout not understood")
        self._layouts.insert(0, layout)
        del self._layouts[self.max_layouts:]
        self.layouts_learnt += 1
        return layout


def view_of(msg: Any) -> CdrView:
    """A ``CdrView`` of a Python message (serialised first): what a node's view callback gets for it."""
    return CdrReader(type(msg)).read(serialize_message(msg))


def subscribe_view(node: Node, msg_type: Any, topic: str, callback: Callable[[CdrView], None], qos: Any, *,
                   on_error: Callable[[Exception], None], wants: Callable[[int], bool] | None = None) -> Any:
    """A subscription whose callback gets a ``CdrView`` of each message (``CdrReader``), or of those whose
    header stamp ``wants``; a message that cannot be read goes to ``on_error`` (counted by the node)."""
    reader = CdrReader(msg_type)

    def on_raw(data: bytes) -> None:
        try:
            if wants is not None and not wants(stamp_ns_of(data)):
                return
            view = reader.read(data)
        except Exception as exc:  # a corrupt sample must not stop the node
            on_error(exc)
            return
        callback(view)

    return node.create_subscription(msg_type, topic, on_raw, qos, raw=True)
