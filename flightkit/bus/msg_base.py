"""What every ROS 2 message type on the bus shares: the :class:`Message` protocol, the
``std_msgs/Header``, and the ``ros2msg`` schema texts.

Each message class carries ``TYPE`` (the ROS 2 name, ``"geometry_msgs/msg/PoseStamped"``)
and ``SCHEMA`` (the ``ros2msg`` text MCAP wants: the message definition followed by every
nested definition after a line of 80 ``=`` and ``MSG: pkg/Type``), so recordings open in
Foxglove, ``rosbags`` and ROS 2 tools. ``encode()`` returns the CDR payload (4-byte
encapsulation header included); ``decode(payload)`` reads one.

The message classes: :mod:`flightkit.bus.pose_msgs` (poses, transforms, odometry) and
:mod:`flightkit.bus.image_msgs` (images, camera info); decoding by type name:
:mod:`flightkit.bus.msgs`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar, Protocol, Self, TypeVar

from flightkit.bus.cdr import CdrReader, CdrWriter
from flightkit.errors import BusError

_M = TypeVar("_M")

__all__ = [
    "Header",
    "Message",
    "decode_payload",
    "schema_text",
]

# --------------------------------------------------------------------------- schemas

_DEFINITIONS: dict[str, str] = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "geometry_msgs/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/Pose": "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n",
    "geometry_msgs/PoseStamped": "std_msgs/Header header\ngeometry_msgs/Pose pose\n",
    "geometry_msgs/Transform": "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n",
    "geometry_msgs/TransformStamped": (
        "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform\n"
    ),
    "geometry_msgs/Twist": "geometry_msgs/Vector3 linear\ngeometry_msgs/Vector3 angular\n",
    "geometry_msgs/PoseWithCovariance": "geometry_msgs/Pose pose\nfloat64[36] covariance\n",
    "geometry_msgs/TwistWithCovariance": "geometry_msgs/Twist twist\nfloat64[36] covariance\n",
    "tf2_msgs/TFMessage": "geometry_msgs/TransformStamped[] transforms\n",
    "nav_msgs/Odometry": (
        "std_msgs/Header header\nstring child_frame_id\n"
        "geometry_msgs/PoseWithCovariance pose\ngeometry_msgs/TwistWithCovariance twist\n"
    ),
    "sensor_msgs/Image": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
        "uint8 is_bigendian\nuint32 step\nuint8[] data\n"
    ),
    "sensor_msgs/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data\n",
    "sensor_msgs/RegionOfInterest": (
        "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n"
    ),
    "sensor_msgs/CameraInfo": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\n"
        "float64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\n"
        "sensor_msgs/RegionOfInterest roi\n"
    ),
}

_SEPARATOR = "=" * 80


def _short(msgtype: str) -> str:
    """'geometry_msgs/msg/Pose' -> 'geometry_msgs/Pose'."""
    parts = msgtype.split("/")
    return f"{parts[0]}/{parts[-1]}" if len(parts) == 3 else msgtype


def _nested(short_name: str) -> list[str]:
    out: list[str] = []
    for line in _DEFINITIONS[short_name].splitlines():
        ftype = line.split()[0].split("[")[0]
        if "/" in ftype and ftype not in out:
            out.append(ftype)
    return out


def schema_text(msgtype: str) -> str:
    """The ``ros2msg`` schema text of ``msgtype`` (full or short name) for MCAP channels.

    Raises:
        BusError: for a type flightkit does not define.
    """
    short = _short(msgtype)
    if short not in _DEFINITIONS:
        known = ", ".join(sorted(_DEFINITIONS))
        raise BusError(f"no schema for message type {msgtype!r}; known types: {known}")
    deps: list[str] = []

    def visit(name: str) -> None:
        for dep in _nested(name):
            if dep not in deps:
                deps.append(dep)
                visit(dep)

    visit(short)
    parts = [_DEFINITIONS[short]]
    for dep in deps:
        parts.append(f"{_SEPARATOR}\nMSG: {dep}\n{_DEFINITIONS[dep]}")
    return "".join(parts)


# --------------------------------------------------------------------------- building blocks


class Message(Protocol):
    """What every message class offers."""

    TYPE: ClassVar[str]
    SCHEMA: ClassVar[str]

    def encode(self) -> bytearray: ...

    @classmethod
    def decode(cls, payload: bytes | bytearray | memoryview) -> Self: ...


@dataclass(frozen=True, slots=True)
class Header:
    """std_msgs/Header: stamp (ns since the epoch) and the frame the data is expressed in."""

    stamp_ns: int = 0
    frame_id: str = ""

    def write(self, w: CdrWriter) -> None:
        sec, nanosec = divmod(int(self.stamp_ns), 1_000_000_000)
        w.i32(sec)
        w.u32(nanosec)
        w.string(self.frame_id)

    @staticmethod
    def read(r: CdrReader) -> Header:
        sec = r.i32()
        nanosec = r.u32()
        return Header(sec * 1_000_000_000 + nanosec, r.string())


def decode_payload(type_name: str, read: Callable[[CdrReader], _M], payload: bytes | bytearray | memoryview) -> _M:
    """``read`` of a CDR payload of the message type ``type_name`` (the ``decode`` of every message class)."""
    return read(CdrReader(payload, type_name))
