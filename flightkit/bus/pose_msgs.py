"""The geometry messages: ``geometry_msgs/PoseStamped``, ``geometry_msgs/TransformStamped``,
``tf2_msgs/TFMessage`` and ``nav_msgs/Odometry``, with hand-written CDR codecs
(what they share: :mod:`flightkit.bus.msg_base`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from flightkit.bus.cdr import CdrReader, CdrWriter
from flightkit.bus.msg_base import Header, decode_payload, schema_text
from flightkit.errors import BusError
from flightkit.frames import Transform, Vec3Tuple

__all__ = [
    "Odometry",
    "PoseStamped",
    "TFMessage",
    "TransformStamped",
]

QuatTuple = tuple[float, float, float, float]


def _vec3(values: Any) -> Vec3Tuple:
    x, y, z = (float(v) for v in values)
    return (x, y, z)


def _quat(values: Any) -> QuatTuple:
    x, y, z, w = (float(v) for v in values)
    return (x, y, z, w)


@dataclass(frozen=True, slots=True)
class PoseStamped:
    """geometry_msgs/PoseStamped: the pose of something in ``header.frame_id``.

    Attributes:
        position_m: (x, y, z) in metres.
        quat_xyzw: orientation quaternion in ROS order x, y, z, w.
    """

    TYPE: ClassVar[str] = "geometry_msgs/msg/PoseStamped"
    SCHEMA: ClassVar[str] = schema_text(TYPE)

    header: Header
    position_m: Vec3Tuple = (0.0, 0.0, 0.0)
    quat_xyzw: QuatTuple = (0.0, 0.0, 0.0, 1.0)

    @staticmethod
    def from_transform(stamp_ns: int, frame_id: str, T: Transform) -> PoseStamped:
        return PoseStamped(Header(stamp_ns, frame_id), _vec3(T.translation), _quat(T.quat_xyzw))

    def to_transform(self) -> Transform:
        """The pose as ``T_frame_thing`` (raises ValueError on a zero quaternion)."""
        return Transform.from_quat_xyzw(self.position_m, self.quat_xyzw)

    def write(self, w: CdrWriter) -> None:
        self.header.write(w)
        w.f64s(self.position_m + self.quat_xyzw)

    @staticmethod
    def read(r: CdrReader) -> PoseStamped:
        header = Header.read(r)
        v = r.f64s(7)
        return PoseStamped(header, (v[0], v[1], v[2]), (v[3], v[4], v[5], v[6]))

    def encode(self) -> bytearray:
        w = CdrWriter()
        self.write(w)
        return w.buf

    @classmethod
    def decode(cls, payload: bytes | bytearray | memoryview) -> PoseStamped:
        return decode_payload(cls.TYPE, cls.read, payload)


@dataclass(frozen=True, slots=True)
class TransformStamped:
    """geometry_msgs/TransformStamped: ``T_parent_child`` with parent = ``header.frame_id``."""

    TYPE: ClassVar[str] = "geometry_msgs/msg/TransformStamped"
    SCHEMA: ClassVar[str] = schema_text(TYPE)

    header: Header
    child_frame_id: str
    translation_m: Vec3Tuple = (0.0, 0.0, 0.0)
    quat_xyzw: QuatTuple = (0.0, 0.0, 0.0, 1.0)

    @staticmethod
    def from_transform(stamp_ns: int, parent: str, child: str, T_parent_child: Transform) -> TransformStamped:
        return TransformStamped(
            Header(stamp_ns, parent), child, _vec3(T_parent_child.translation), _quat(T_parent_child.quat_xyzw)
        )

    def to_transform(self) -> Transform:
        return Transform.from_quat_xyzw(self.translation_m, self.quat_xyzw)

    def write(self, w: CdrWriter) -> None:
        self.header.write(w)
        w.string(self.child_frame_id)
        w.f64s(self.translation_m + self.quat_xyzw)

    @staticmethod
    def read(r: CdrReader) -> TransformStamped:
        header = Header.read(r)
        child = r.string()
        v = r.f64s(7)
        return TransformStamped(header, child, (v[0], v[1], v[2]), (v[3], v[4], v[5], v[6]))

    def encode(self) -> bytearray:
        w = CdrWriter()
        self.write(w)
        return w.buf

    @classmethod
    def decode(cls, payload: bytes | bytearray | memoryview) -> TransformStamped:
        return decode_payload(cls.TYPE, cls.read, payload)


@dataclass(frozen=True, slots=True)
class TFMessage:
    """tf2_msgs/TFMessage: a batch of transforms."""

    TYPE: ClassVar[str] = "tf2_msgs/msg/TFMessage"
    SCHEMA: ClassVar[str] = schema_text(TYPE)

    transforms: tuple[TransformStamped, ...] = ()

    def write(self, w: CdrWriter) -> None:
        w.u32(len(self.transforms))
        for t in self.transforms:
            t.write(w)

    @staticmethod
    def read(r: CdrReader) -> TFMessage:
        n = r.u32()
        if n > r.remaining:
            raise BusError(f"{r.msgtype} claims {n} transforms in {r.remaining} bytes; the payload is corrupt")
        return TFMessage(tuple(TransformStamped.read(r) for _ in range(n)))

    def encode(self) -> bytearray:
        w = CdrWriter()
        self.write(w)
        return w.buf

    @classmethod
    def decode(cls, payload: bytes | bytearray | memoryview) -> TFMessage:
        return decode_payload(cls.TYPE, cls.read, payload)


_ZERO36: tuple[float, ...] = (0.0,) * 36


@dataclass(frozen=True, slots=True)
class Odometry:
    """nav_msgs/Odometry: pose in ``header.frame_id``, twist in ``child_frame_id``.

    Attributes:
        pose_covariance, twist_covariance: row-major 6x6 (x, y, z, rot x, rot y, rot z).
    """

    TYPE: ClassVar[str] = "nav_msgs/msg/Odometry"
    SCHEMA: ClassVar[str] = schema_text(TYPE)

    header: Header
    child_frame_id: str = ""
    position_m: Vec3Tuple = (0.0, 0.0, 0.0)
    quat_xyzw: QuatTuple = (0.0, 0.0, 0.0, 1.0)
    pose_covariance: tuple[float, ...] = _ZERO36
    linear_m_s: Vec3Tuple = (0.0, 0.0, 0.0)
    angular_rad_s: Vec3Tuple = (0.0, 0.0, 0.0)
    twist_covariance: tuple[float, ...] = _ZERO36

    def __post_init__(self) -> None:
        for name in ("pose_covariance", "twist_covariance"):
            if len(getattr(self, name)) != 36:
                raise BusError(f"Odometry.{name} needs 36 values (6x6 row-major), got {len(getattr(self, name))}")

    def to_transform(self) -> Transform:
        return Transform.from_quat_xyzw(self.position_m, self.quat_xyzw)

    def write(self, w: CdrWriter) -> None:
        self.header.write(w)
        w.string(self.child_frame_id)
        w.f64s(self.position_m + self.quat_xyzw + tuple(self.pose_covariance))
        w.f64s(self.linear_m_s + self.angular_rad_s + tuple(self.twist_covariance))

    @staticmethod
    def read(r: CdrReader) -> Odometry:
        header = Header.read(r)
        child = r.string()
        p = r.f64s(43)
        t = r.f64s(42)
        return Odometry(
            header, child, (p[0], p[1], p[2]), (p[3], p[4], p[5], p[6]), p[7:],
            (t[0], t[1], t[2]), (t[3], t[4], t[5]), t[6:],
        )

    def encode(self) -> bytearray:
        w = CdrWriter()
        self.write(w)
        return w.buf

    @classmethod
    def decode(cls, payload: bytes | bytearray | memoryview) -> Odometry:
        return decode_payload(cls.TYPE, cls.read, payload)

