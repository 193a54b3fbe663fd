"""What a protocol session reports to its owner (``Session.take_events``): a link up or lost,
a pose, a segment or a navigation order received, our reliable message acknowledged, the
peer's goodbye."""

from __future__ import annotations

from dataclasses import dataclass

from .messages import GoodbyeReason, MsgType, NavOrder, PoseUpdate, Segment

__all__ = [
    "Connected",
    "Delivered",
    "Event",
    "LinkLost",
    "NavOrderReceived",
    "PeerGoodbye",
    "PoseReceived",
    "SegmentReceived",
]


@dataclass(frozen=True, slots=True)
class Connected:
    robot_id: int
    peer_name: str
    capabilities: int
    resumed: bool  # same peer incarnation as before (a reconnection, not a restart)


@dataclass(frozen=True, slots=True)
class LinkLost:
    robot_id: int
    silent_s: float


@dataclass(frozen=True, slots=True)
class PoseReceived:
    robot_id: int
    seq: int
    pose: PoseUpdate
    received_s: float


@dataclass(frozen=True, slots=True)
class SegmentReceived:
    robot_id: int
    seq: int
    segment: Segment


@dataclass(frozen=True, slots=True)
class NavOrderReceived:
    robot_id: int
    seq: int
    order: NavOrder


@dataclass(frozen=True, slots=True)
class Delivered:
    """The peer acknowledged our reliable message ``seq``."""

    robot_id: int
    seq: int
    msg_type: MsgType


@dataclass(frozen=True, slots=True)
class PeerGoodbye:
    robot_id: int
    reason: GoodbyeReason
    text: str


Event = Connected | LinkLost | PoseReceived | SegmentReceived | NavOrderReceived | Delivered | PeerGoodbye
