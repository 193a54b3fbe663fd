"""Message types and payload codecs of the pose-reporting protocol (version 1).

Payloads are little endian, fixed layout (see ``docs/protocol.md``):

============  =========  =====================================================================
type          reliable   payload
============  =========  =====================================================================
HELLO      0  handshake  incarnation u32, first_seq u16, capabilities u16, name (len u8 + utf-8)
HELLO_ACK  1  handshake  same layout as HELLO (the server's side)
HELLO_DONE 2  handshake  empty (third leg; the header ack carries the acknowledgement)
POSE       3  newest     stamp_us i64, x f32, y f32, z f32, heading_rad f32, quality u8
SEGMENT    4  yes        x0 f32, y0 f32, x1 f32, y1 f32
NAV_ORDER  5  yes        order_id u32, x f32, y f32, z f32 (NaN: keep height), heading f32 (NaN: any)
HEARTBEAT  6  no         empty
GOODBYE    7  no         reason u8, text (len u8 + utf-8)
ACK        8  no         empty (only the header ack matters)
============  =========  =====================================================================

Positions are in the server's 2D map frame and units (see :mod:`.mapframe`); heading is
counter-clockwise from the map x axis, radians.
"""

from __future__ import annotations

import enum
import math
import struct
from dataclasses import dataclass

from flightkit.errors import ProtocolError

__all__ = [
    "Capability",
    "GoodbyeReason",
    "Goodbye",
    "Hello",
    "MsgType",
    "NavOrder",
    "PoseUpdate",
    "Segment",
    "decode_goodbye",
    "decode_hello",
    "decode_nav_order",
    "decode_pose",
    "decode_segment",
    "encode_goodbye",
    "encode_hello",
    "encode_nav_order",
    "encode_pose",
    "encode_segment",
]

MAX_NAME_BYTES = 32


class MsgType(enum.IntEnum):
    HELLO = 0
    HELLO_ACK = 1
    HELLO_DONE = 2
    POSE = 3
    SEGMENT = 4
    NAV_ORDER = 5
    HEARTBEAT = 6
    GOODBYE = 7
    ACK = 8


RELIABLE_TYPES = frozenset({MsgType.SEGMENT, MsgType.NAV_ORDER})


class Capability(enum.IntFlag):
    """What an end can do; exchanged in the handshake."""

    NONE = 0
    POSE = 1  # sends pose updates
    SEGMENTS = 2  # sends wall segments
    NAV_ORDERS = 4  # accepts navigation orders (robot) / sends them (server)
    MAP = 8  # draws a map (server)


class GoodbyeReason(enum.IntEnum):
    SHUTDOWN = 0  # the peer is closing normally
    NO_SESSION = 1  # the server got data from a robot it has no session with: handshake again
    REJECTED = 2  # the server refuses this robot (e.g. id already taken by another name)


@dataclass(frozen=True, slots=True)
class Hello:
    """Handshake legs 1 and 2.

    Attributes:
        incarnation: random number fixed for the life of one process; a new value tells
            the peer to reset what it knows about our reliable stream.
        first_seq: oldest reliable sequence number we have not seen acknowledged (or the
            next one we will send).
        capabilities: :class:`Capability` bits.
        name: human-readable robot or server name (at most 32 UTF-8 bytes).
    """

    incarnation: int
    first_seq: int
    capabilities: int
    name: str


@dataclass(frozen=True, slots=True)
class PoseUpdate:
    """A pose in the map frame.

    Attributes:
        stamp_us: capture time, microseconds since the Unix epoch.
        x, y, z: position in map units (float32 on the wire).
        heading_rad: counter-clockwise from the map x axis.
        quality: 0 (unusable) .. 255 (best).
    """

    stamp_us: int
    x: float
    y: float
    z: float
    heading_rad: float
    quality: int = 255


@dataclass(frozen=True, slots=True)
class Segment:
    """A wall segment in the map frame, from (x0, y0) to (x1, y1), map units."""

    x0: float
    y0: float
    x1: float
    y1: float


@dataclass(frozen=True, slots=True)
class NavOrder:
    """A navigation order (server to robot): go to (x, y[, z]) in map units.

    ``z`` NaN means keep the current height; ``heading_rad`` NaN means any heading.
    """

    order_id: int
    x: float
    y: float
    z: float = math.nan
    heading_rad: float = math.nan


@dataclass(frozen=True, slots=True)
class Goodbye:
    reason: GoodbyeReason
    text: str = ""


_HELLO = struct.Struct("<IHH")
_POSE = struct.Struct("<qffffB")
_SEGMENT = struct.Struct("<ffff")
_NAV = struct.Struct("<Iffff")

POSE_PAYLOAD_SIZE = _POSE.size


def _short_text(text: str) -> bytes:
    raw = text.encode("utf-8")[:MAX_NAME_BYTES]
    # Do not cut a multi-byte character in half.
    return raw.decode("utf-8", errors="ignore").encode("utf-8")


def encode_hello(msg: Hello) -> bytes:
    name = _short_text(msg.name)
    return (
        _HELLO.pack(msg.incarnation & 0xFFFFFFFF, msg.first_seq & 0xFFFF, msg.capabilities & 0xFFFF)
        + bytes([len(name)])
        + name
    )


def decode_hello(payload: bytes) -> Hello:
    if len(payload) < _HELLO.size + 1:
        raise ProtocolError(
            f"HELLO payload of {len(payload)} bytes is too short; the peer speaks another protocol"
        )
    inc, first, caps = _HELLO.unpack_from(payload)
    n = payload[_HELLO.size]
    raw = payload[_HELLO.size + 1 : _HELLO.size + 1 + n]
    if len(raw) != n:
        raise ProtocolError(f"HELLO name length {n} exceeds the payload; the frame is malformed")
    return Hello(inc, first, caps, raw.decode("utf-8", errors="replace"))


def encode_pose(msg: PoseUpdate) -> bytes:
    return _POSE.pack(msg.stamp_us, msg.x, msg.y, msg.z, msg.heading_rad, max(0, min(255, msg.quality)))


def decode_pose(payload: bytes) -> PoseUpdate:
    if len(payload) != _POSE.size:
        raise ProtocolError(f"POSE payload has {len(payload)} bytes, expected {_POSE.size}")
    return PoseUpdate(*_POSE.unpack(payload))


def encode_segment(msg: Segment) -> bytes:
    return _SEGMENT.pack(msg.x0, msg.y0, msg.x1, msg.y1)


def decode_segment(payload: bytes) -> Segment:
    if len(payload) != _SEGMENT.size:
        raise ProtocolError(f"SEGMENT payload has {len(payload)} bytes, expected {_SEGMENT.size}")
    return Segment(*_SEGMENT.unpack(payload))


def encode_nav_order(msg: NavOrder) -> bytes:
    return _NAV.pack(msg.order_id & 0xFFFFFFFF, msg.x, msg.y, msg.z, msg.heading_rad)


def decode_nav_order(payload: bytes) -> NavOrder:
    if len(payload) != _NAV.size:
        raise ProtocolError(f"NAV_ORDER payload has {len(payload)} bytes, expected {_NAV.size}")
    return NavOrder(*_NAV.unpack(payload))


def encode_goodbye(msg: Goodbye) -> bytes:
    text = _short_text(msg.text)
    return bytes([int(msg.reason), len(text)]) + text


def decode_goodbye(payload: bytes) -> Goodbye:
    if len(payload) < 2:
        raise ProtocolError(f"GOODBYE payload has {len(payload)} bytes, expected at least 2")
    try:
        reason = GoodbyeReason(payload[0])
    except ValueError:
        reason = GoodbyeReason.SHUTDOWN
    return Goodbye(reason, payload[2 : 2 + payload[1]].decode("utf-8", errors="replace"))
