"""Decoding of the recording's messages straight from their CDR bytes: sensor_msgs/JointState,
sensor_msgs/Imu, nav_msgs/Odometry, tal_msgs/JointCommand and tal_msgs/ContactState, the fields
``measured.load_measured`` reads, as light named tuples with the rclpy messages' field names (decoded by rclpy,
an 8 s recording's 28,000 of them took 3.6 s of the workflow's time, issue 34).

The layout is ROS 2's XCDR1 little endian ("CDR_LE": a 4-byte encapsulation header 00 01 00 00, then every
primitive aligned to its size from the end of that header; a string is a uint32 length counting its NUL and
the bytes; a sequence a uint32 count and the elements). A message in another encapsulation, or one whose
fields do not end exactly at its last byte, decodes to None: the caller decodes it with rclpy instead.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

CDR_LE = b"\x00\x01"
_ORIGIN = 4  # alignment counts from the end of the encapsulation header
_U32 = struct.Struct("<I")
_STAMP = struct.Struct("<iI")
_IMU = struct.Struct("<37d")  # orientation 4, covariance 9, angular velocity 3, covariance 9, acceleration 3, 9
_ODOM = struct.Struct("<85d")  # position 3, orientation 4, covariance 36, linear 3, angular 3, covariance 36
_CONTACTS = struct.Struct("<60d")  # probability 4, force 12, foot position 12, velocity 12, normal 12, 4 + 4


class Stamp(NamedTuple):
    sec: int
    nanosec: int


class Header(NamedTuple):
    stamp: Stamp
    frame_id: str


class Vector3(NamedTuple):
    x: float
    y: float
    z: float


class Quaternion(NamedTuple):
    x: float
    y: float
    z: float
    w: float


class JointState(NamedTuple):
    header: Header
    name: list[str]
    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray


class JointCommand(NamedTuple):
    header: Header
    name: list[str]
    effort: np.ndarray


class ContactState(NamedTuple):
    header: Header
    in_contact: list[bool]
    force: list[Vector3]


class Imu(NamedTuple):
    header: Header
    orientation: Quaternion
    angular_velocity: Vector3
    linear_acceleration: Vector3


class Pose(NamedTuple):
    position: Vector3
    orientation: Quaternion


class PoseWithCovariance(NamedTuple):
    pose: Pose


class Twist(NamedTuple):
    linear: Vector3
    angular: Vector3


class TwistWithCovariance(NamedTuple):
    twist: Twist


class Odometry(NamedTuple):
    header: Header
    child_frame_id: str
    pose: PoseWithCovariance
    twist: TwistWithCovariance


def _align(offset: int, size: int) -> int:
    return offset + (-(offset - _ORIGIN)) % size


def _string(data: bytes, offset: int) -> tuple[str, int]:
    offset = _align(offset, 4)
    (length,) = _U32.unpack_from(data, offset)
    offset += 4
    if length < 1 or data[offset + length - 1] != 0:
        raise ValueError("not a NUL-terminated CDR string")
    return data[offset : offset + length - 1].decode("utf-8"), offset + length


def _header(data: bytes) -> tuple[Header, int]:
    if data[:2] != CDR_LE:
        raise ValueError("not little-endian CDR")
    sec, nanosec = _STAMP.unpack_from(data, _ORIGIN)
    frame_id, offset = _string(data, _ORIGIN + 8)
    return Header(Stamp(sec, nanosec), frame_id), offset


def _doubles(data: bytes, offset: int) -> tuple[np.ndarray, int]:
    """A float64 sequence: its count, then (when there are any) the values from the next 8-byte boundary."""
    offset = _align(offset, 4) + 4
    (count,) = _U32.unpack_from(data, offset - 4)
    if count == 0:
        return np.zeros(0), offset
    offset = _align(offset, 8)
    end = offset + 8 * count
    if end > len(data):
        raise ValueError("sequence runs past the message")
    return np.frombuffer(data, "<f8", count, offset).astype(float), end


def _check_end_after_sequences(data: bytes, offset: int, sequences: list[np.ndarray]) -> None:
    """The serialiser sizes a message before writing it and pads each empty float64 sequence to 8 bytes in
    that estimate, not in the bytes: a message with empty sequences can end in up to 4 unused bytes per
    empty sequence (a JointState without velocities and efforts: 8)."""
    spare = len(data) - offset
    empty = sum(1 for s in sequences if len(s) == 0)
    if spare != 0 and not (0 < spare <= 4 * empty):
        _check_end(data, offset)


def _strings(data: bytes, offset: int, last: list) -> tuple[list[str], int]:
    """A string sequence (joint names), from the bytes of the ``last`` one read ([offset, bytes, names], a
    message type's own) when they are the same: they are, message after message."""
    offset = _align(offset, 4)
    start, raw, names = last
    if start == offset and data[offset : offset + len(raw)] == raw:
        return list(names), offset + len(raw)
    (count,) = _U32.unpack_from(data, offset)
    end = offset + 4
    names = []
    for _ in range(count):
        name, end = _string(data, end)
        names.append(name)
    last[:] = [offset, data[offset:end], names]
    return list(names), end


_STATE_NAMES: list = [-1, b"", []]
_COMMAND_NAMES: list = [-1, b"", []]


def joint_state(data: bytes) -> JointState:
    header, offset = _header(data)
    names, offset = _strings(data, offset, _STATE_NAMES)
    position, offset = _doubles(data, offset)
    velocity, offset = _doubles(data, offset)
    effort, offset = _doubles(data, offset)
    _check_end_after_sequences(data, offset, [position, velocity, effort])
    return JointState(header, names, position, velocity, effort)


def joint_command(data: bytes) -> JointCommand:
    header, offset = _header(data)
    names, offset = _strings(data, offset, _COMMAND_NAMES)
    sequences = []
    for _ in range(5):  # effort, position, velocity, kp, kd (read past the last four)
        values, offset = _doubles(data, offset)
        sequences.append(values)
    _check_end_after_sequences(data, offset, sequences)
    return JointCommand(header, names, sequences[0])


def contact_state(data: bytes) -> ContactState:
    header, offset = _header(data)
    in_contact = [bool(b) for b in data[offset : offset + 4]]
    if any(b > 1 for b in data[offset : offset + 4]):
        raise ValueError("not CDR booleans")
    offset = _align(offset + 4, 8)
    v = _CONTACTS.unpack_from(data, offset)
    _check_end(data, offset + _CONTACTS.size)
    force = [Vector3(*v[4 + 3 * i : 7 + 3 * i]) for i in range(4)]
    return ContactState(header, in_contact, force)


def imu(data: bytes) -> Imu:
    header, offset = _header(data)
    offset = _align(offset, 8)
    v = _IMU.unpack_from(data, offset)
    _check_end(data, offset + _IMU.size)
    return Imu(header, Quaternion(*v[0:4]), Vector3(*v[13:16]), Vector3(*v[25:28]))


def odometry(data: bytes) -> Odometry:
    header, offset = _header(data)
    child_frame_id, offset = _string(data, offset)
    offset = _align(offset, 8)
    v = _ODOM.unpack_from(data, offset)
    _check_end(data, offset + _ODOM.size)
    pose = PoseWithCovariance(Pose(Vector3(*v[0:3]), Quaternion(*v[3:7])))
    twist = TwistWithCovariance(Twist(Vector3(*v[43:46]), Vector3(*v[46:49])))
    return Odometry(header, child_frame_id, pose, twist)


def _check_end(data: bytes, offset: int) -> None:
    if offset != len(data):
        raise ValueError(f"fields end at byte {offset} of {len(data)}")


DECODERS: dict[str, Callable[[bytes], NamedTuple]] = {
    "sensor_msgs/msg/JointState": joint_state,
    "sensor_msgs/msg/Imu": imu,
    "nav_msgs/msg/Odometry": odometry,
    "tal_msgs/msg/JointCommand": joint_command,
    "tal_msgs/msg/ContactState": contact_state,
}


def decode(type_name: str, data: bytes) -> NamedTuple | None:
    """The message of type ``type_name`` in ``data``, or None when it is not one of DECODERS' types or does
    not parse exactly (then rclpy decodes it)."""
    decoder = DECODERS.get(type_name)
    if decoder is None:
        return None
    try:
        return decoder(data)
    except (ValueError, struct.error, UnicodeDecodeError, IndexError):
        return None
