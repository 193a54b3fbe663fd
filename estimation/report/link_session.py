"""The protocol's state machine, sans-IO: frames in, frames out, events, driven by time.

Nothing here touches a port or a clock: every method takes ``now_s`` (a monotonic time in
seconds from the caller's :class:`~flightkit.clock.Clock`). A transport feeds received
bytes to an endpoint, asks it for the next bytes to write whenever the line is free, and
calls :meth:`poll` at :meth:`next_deadline_s`. That makes every timing rule (retransmission,
heartbeat, link loss, handshake retry) testable with plain numbers.

Rules (the full description is ``docs/protocol.md``):

* Three-way handshake, robot first: HELLO -> HELLO_ACK -> HELLO_DONE. Each side names an
  *incarnation* (random per process) and the first reliable sequence number it still
  needs delivered. A peer with the same incarnation resumes (duplicates are still
  recognised); a new incarnation resets what we know of its stream.
* Reliable messages (segments, navigation orders) are numbered, sent in a window of
  ``window`` outstanding frames, acknowledged cumulatively in every frame's ``ack`` field,
  retransmitted on a per-message timeout (RFC 6298 estimator, doubling back-off), buffered
  and re-ordered by the receiver and delivered exactly once, in order. They survive link
  loss and re-handshakes.
* Pose updates are "newest wins": the sender keeps one pending pose, replaced by each new
  one and sent only when the line is free; the receiver drops a pose older than the
  newest it has delivered.
* Heartbeats go out when nothing else was sent for ``heartbeat_s``; silence for
  ``link_timeout_s`` means the link is lost: the robot then handshakes again until the
  server answers, the server marks the robot lost and revives it on its next frame.
"""

from __future__ import annotations

import enum
import logging
import math
import random
from collections import OrderedDict, deque
from dataclasses import dataclass

from flightkit.errors import ConfigError, ProtocolError

from .events import (
    Connected,
    Delivered,
    Event,
    LinkLost,
    NavOrderReceived,
    PeerGoodbye,
    PoseReceived,
    SegmentReceived,
)
from .messages import (
    RELIABLE_TYPES,
    Goodbye,
    GoodbyeReason,
    Hello,
    MsgType,
    NavOrder,
    PoseUpdate,
    Segment,
    decode_goodbye,
    decode_hello,
    decode_nav_order,
    decode_pose,
    decode_segment,
    encode_goodbye,
    encode_hello,
    encode_nav_order,
    encode_pose,
    encode_segment,
)
from .protocol import Frame, seq_newer

__all__ = [
    "Role",
    "Session",
    "SessionConfig",
    "SessionState",
    "SessionStats",
]

logger = logging.getLogger(__name__)


class Role(enum.Enum):
    ROBOT = "robot"
    SERVER = "server"


class SessionState(enum.Enum):
    IDLE = "idle"  # robot: connect() not called yet
    CONNECTING = "connecting"  # robot: HELLO sent, waiting for HELLO_ACK
    HELLO_RECEIVED = "hello_received"  # server: HELLO_ACK sent, waiting for the third leg
    ESTABLISHED = "established"
    LOST = "lost"  # server: the robot fell silent (revives on its next frame)
    CLOSED = "closed"


@dataclass(frozen=True, slots=True)
class SessionConfig:
    """Timing and sizes of a session (seconds of the driving clock).

    Attributes:
        heartbeat_s: send a heartbeat after this much silence on our side.
        link_timeout_s: the link is lost after this much silence from the peer.
        hello_retry_s: first HELLO retry interval (doubles up to ``hello_retry_max_s``).
        rto_initial_s: retransmission timeout before any round trip was measured.
        rto_min_s, rto_max_s: bounds of the retransmission timeout.
        window: reliable frames in flight at most.
        max_queued: reliable messages waiting at most; more raises ProtocolError.
        rx_window: how far ahead of the next expected sequence number frames are buffered.
    """

    heartbeat_s: float = 0.25
    link_timeout_s: float = 1.5
    hello_retry_s: float = 0.2
    hello_retry_max_s: float = 2.0
    rto_initial_s: float = 0.25
    rto_min_s: float = 0.04
    rto_max_s: float = 2.0
    window: int = 16
    max_queued: int = 10_000
    rx_window: int = 1024

    def __post_init__(self) -> None:
        if self.link_timeout_s <= self.heartbeat_s:
            raise ConfigError(
                "<SessionConfig>",
                "link_timeout_s",
                f"{self.link_timeout_s} s must exceed heartbeat_s ({self.heartbeat_s} s)",
                "make link_timeout_s at least three heartbeats",
                self.link_timeout_s,
            )
        if not 1 <= self.window <= 1024:
            raise ConfigError(
                "<SessionConfig>",
                "window",
                f"{self.window} is out of range",
                "give 1..1024",
                self.window,
            )


# ----------------------------------------------------------------------------- events


@dataclass(slots=True)
class SessionStats:
    frames_tx: int = 0
    bytes_tx: int = 0
    frames_rx: int = 0
    poses_sent: int = 0
    poses_superseded: int = 0  # replaced by a newer pose before the line was free
    poses_received: int = 0
    poses_stale: int = 0  # arrived after a newer one; dropped
    reliable_sent: int = 0
    retransmissions: int = 0
    reliable_delivered: int = 0  # received and handed up, in order
    reliable_acked: int = 0  # ours, acknowledged by the peer
    duplicates: int = 0
    malformed: int = 0
    handshakes: int = 0
    links_lost: int = 0


@dataclass(slots=True)
class _Outstanding:
    seq: int
    msg_type: MsgType
    payload: bytes
    sent_s: float = math.nan
    deadline_s: float = math.inf
    rto_s: float = 0.0
    retransmitted: bool = False


# ----------------------------------------------------------------------------- session


class Session:
    """One robot<->server association, seen from one end.

    Args:
        role: which end we are.
        robot_id: the robot's id (1..254), the same on both ends.
        name: our name, sent in the handshake.
        capabilities: our :class:`Capability` bits.
        config: timing.
        incarnation: our process incarnation (random when None).
        rng: randomness for the incarnation and the initial sequence number.
    """

    def __init__(
        self,
        role: Role,
        robot_id: int,
        name: str,
        capabilities: int = 0,
        config: SessionConfig | None = None,
        *,
        incarnation: int | None = None,
        rng: random.Random | None = None,
    ) -> None:
        if not 1 <= robot_id <= 254:
            raise ProtocolError(f"robot id {robot_id} is out of range; use 1..254")
        rng = rng or random.Random()
        self.role = role
        self.robot_id = robot_id
        self.name = name
        self.capabilities = int(capabilities)
        self.config = config or SessionConfig()
        self.incarnation = rng.getrandbits(32) if incarnation is None else incarnation
        self.stats = SessionStats()
        self.state = SessionState.IDLE
        self.peer_name = ""
        self.peer_capabilities = 0
        self._peer_incarnation: int | None = None
        self._events: list[Event] = []
        self._control: deque[Frame] = deque()
        # our reliable stream
        self._tx_next_seq = rng.getrandbits(16)
        self._unacked: OrderedDict[int, _Outstanding] = OrderedDict()
        self._queued: deque[_Outstanding] = deque()
        self._srtt_s: float | None = None
        self._rttvar_s = 0.0
        self._rto_s = self.config.rto_initial_s
        # the peer's reliable stream
        self._rx_expected = 0
        self._rx_buffer: dict[int, tuple[MsgType, bytes]] = {}
        self._ack_owed = False
        # poses
        self._pending_pose: PoseUpdate | None = None
        self._pose_seq = 0
        self._last_pose_seq: int | None = None
        self._alternate = False
        # timers
        self._last_rx_s = -math.inf
        self._last_tx_s = -math.inf
        self._hello_next_s = math.inf
        self._hello_interval_s = self.config.hello_retry_s

    # ------------------------------------------------------------------ public API

    @property
    def established(self) -> bool:
        return self.state is SessionState.ESTABLISHED

    @property
    def unacked(self) -> int:
        """Reliable messages sent or queued and not yet acknowledged."""
        return len(self._unacked) + len(self._queued)

    @property
    def rto_s(self) -> float:
        return self._rto_s

    def connect(self, now_s: float) -> None:
        """Start (or restart) the handshake; robot only. Returns immediately."""
        if self.role is not Role.ROBOT:
            raise ProtocolError("only the robot end starts a handshake; the server answers HELLOs")
        self.state = SessionState.CONNECTING
        self._hello_interval_s = self.config.hello_retry_s
        self._hello_next_s = now_s

    def close(self) -> None:
        """Queue a GOODBYE and stop; the transport flushes it before closing."""
        if self.state in (SessionState.ESTABLISHED, SessionState.HELLO_RECEIVED, SessionState.CONNECTING):
            self._control.append(
                self._frame(MsgType.GOODBYE, encode_goodbye(Goodbye(GoodbyeReason.SHUTDOWN)), 0)
            )
        self.state = SessionState.CLOSED

    def send_pose(self, pose: PoseUpdate) -> None:
        """Offer a pose; it replaces any pose not yet on the wire (newest wins)."""
        if self._pending_pose is not None:
            self.stats.poses_superseded += 1
        self._pending_pose = pose

    def send_segment(self, segment: Segment) -> int:
        """Queue a wall segment for reliable delivery; returns its sequence number."""
        return self._queue_reliable(MsgType.SEGMENT, encode_segment(segment))

    def send_nav_order(self, order: NavOrder) -> int:
        """Queue a navigation order for reliable delivery; returns its sequence number."""
        return self._queue_reliable(MsgType.NAV_ORDER, encode_nav_order(order))

    def take_events(self) -> list[Event]:
        """Events since the last call, oldest first."""
        events, self._events = self._events, []
        return events

    # ------------------------------------------------------------------ timers

    def poll(self, now_s: float) -> None:
        """Run timers (handshake retry, link loss)."""
        st = self.state
        if st is SessionState.CONNECTING and now_s >= self._hello_next_s:
            self._control.append(self._hello_frame(MsgType.HELLO))
            self._hello_next_s = now_s + self._hello_interval_s
            self._hello_interval_s = min(self._hello_interval_s * 2.0, self.config.hello_retry_max_s)
        elif st in (SessionState.ESTABLISHED, SessionState.HELLO_RECEIVED):
            silent_s = now_s - self._last_rx_s
            if silent_s > self.config.link_timeout_s:
                self.stats.links_lost += 1
                self._events.append(LinkLost(self.robot_id, silent_s))
                logger.info("robot %d: link lost after %.2f s of silence", self.robot_id, silent_s)
                self._ack_owed = False
                if self.role is Role.ROBOT:
                    self.connect(now_s)
                    self.poll(now_s)
                else:
                    self.state = SessionState.LOST

    def next_deadline_s(self) -> float:
        """When :meth:`poll` or :meth:`next_frame` next has something to do (``-inf``: now)."""
        if self._control or (
            self.state is SessionState.ESTABLISHED and (self._pending_pose or self._ack_owed)
        ):
            return -math.inf
        st = self.state
        if st is SessionState.CONNECTING:
            return self._hello_next_s
        if st not in (SessionState.ESTABLISHED, SessionState.HELLO_RECEIVED):
            return math.inf
        deadline = self._last_rx_s + self.config.link_timeout_s
        if st is SessionState.ESTABLISHED:
            deadline = min(deadline, self._last_tx_s + self.config.heartbeat_s)
            if self._queued and len(self._unacked) < self.config.window:
                return -math.inf
            for out in self._unacked.values():
                deadline = min(deadline, out.deadline_s)
        return deadline

    # ------------------------------------------------------------------ transmit

    def next_frame(self, now_s: float) -> Frame | None:
        """The next frame to put on the wire, or None when there is nothing to send now."""
        frame = self._pick(now_s)
        if frame is not None:
            self._last_tx_s = now_s
            self._ack_owed = False
            self.stats.frames_tx += 1
        return frame

    def _pick(self, now_s: float) -> Frame | None:
        if self._control:
            return self._control.popleft()
        if self.state is not SessionState.ESTABLISHED:
            return None
        # Alternate poses with reliable traffic so neither starves the other.
        prefer_pose = self._alternate and self._pending_pose is not None
        if not prefer_pose:
            frame = self._pick_reliable(now_s)
            if frame is not None:
                self._alternate = True
                return frame
        if self._pending_pose is not None:
            pose, self._pending_pose = self._pending_pose, None
            self._pose_seq = (self._pose_seq + 1) & 0xFFFF
            self.stats.poses_sent += 1
            self._alternate = False
            return self._frame(MsgType.POSE, encode_pose(pose), self._pose_seq)
        frame = self._pick_reliable(now_s)
        if frame is not None:
            return frame
        if self._ack_owed:
            return self._frame(MsgType.ACK, b"", 0)
        if now_s - self._last_tx_s >= self.config.heartbeat_s:
            return self._frame(MsgType.HEARTBEAT, b"", 0)
        return None

    def _pick_reliable(self, now_s: float) -> Frame | None:
        for out in self._unacked.values():
            if out.deadline_s <= now_s:
                out.retransmitted = True
                out.rto_s = min(out.rto_s * 2.0, self.config.rto_max_s)
                out.sent_s = now_s
                out.deadline_s = now_s + out.rto_s
                self.stats.retransmissions += 1
                return self._frame(out.msg_type, out.payload, out.seq)
        if self._queued and len(self._unacked) < self.config.window:
            out = self._queued.popleft()
            out.sent_s = now_s
            out.rto_s = self._rto_s
            out.deadline_s = now_s + out.rto_s
            self._unacked[out.seq] = out
            self.stats.reliable_sent += 1
            return self._frame(out.msg_type, out.payload, out.seq)
        return None

    def _queue_reliable(self, msg_type: MsgType, payload: bytes) -> int:
        if self.unacked >= self.config.max_queued:
            raise ProtocolError(
                f"{self.unacked} reliable messages are waiting for robot {self.robot_id}; "
                "the link is down or too slow, wait for deliveries before sending more"
            )
        seq = self._tx_next_seq
        self._tx_next_seq = (seq + 1) & 0xFFFF
        self._queued.append(_Outstanding(seq, msg_type, payload))
        return seq

    def _frame(self, msg_type: MsgType, payload: bytes, seq: int) -> Frame:
        return Frame(int(msg_type), self.robot_id, seq, (self._rx_expected - 1) & 0xFFFF, payload)

    def _first_unacked_seq(self) -> int:
        if self._unacked:
            return next(iter(self._unacked))
        if self._queued:
            return self._queued[0].seq
        return self._tx_next_seq

    def _hello_frame(self, msg_type: MsgType) -> Frame:
        hello = Hello(self.incarnation, self._first_unacked_seq(), self.capabilities, self.name)
        return self._frame(msg_type, encode_hello(hello), 0)

    # ------------------------------------------------------------------ receive

    def handle_frame(self, frame: Frame, now_s: float) -> None:
        """Process one verified frame addressed to this session."""
        try:
            msg_type = MsgType(frame.msg_type)
        except ValueError:
            self.stats.malformed += 1
            return
        self.stats.frames_rx += 1
        try:
            self._dispatch(msg_type, frame, now_s)
        except ProtocolError as exc:
            self.stats.malformed += 1
            logger.debug("robot %d: dropped malformed %s: %s", self.robot_id, msg_type.name, exc)

    def _dispatch(self, msg_type: MsgType, frame: Frame, now_s: float) -> None:
        st = self.state
        if st is SessionState.CLOSED:
            return
        if msg_type is MsgType.GOODBYE:
            self._on_goodbye(decode_goodbye(frame.payload), now_s)
            return
        if self.role is Role.SERVER:
            if msg_type is MsgType.HELLO:
                self._on_hello(decode_hello(frame.payload), now_s)
                return
            if st is SessionState.IDLE:
                return
            if st in (SessionState.HELLO_RECEIVED, SessionState.LOST):
                # The third leg, or any later frame, completes (or revives) the association.
                resumed = st is SessionState.LOST
                self.state = SessionState.ESTABLISHED
                self._events.append(Connected(self.robot_id, self.peer_name, self.peer_capabilities, resumed))
                logger.info(
                    "robot %d (%s): %s", self.robot_id, self.peer_name, "back" if resumed else "connected"
                )
        else:
            if msg_type is MsgType.HELLO_ACK:
                self._last_rx_s = now_s
                self._on_hello_ack(decode_hello(frame.payload), frame, now_s)
                return
            if st is not SessionState.ESTABLISHED:
                return  # wait for the handshake; the server retransmits
        self._last_rx_s = now_s
        self._on_ack(frame.ack)
        if msg_type is MsgType.POSE:
            pose = decode_pose(frame.payload)
            if self._last_pose_seq is None or seq_newer(frame.seq, self._last_pose_seq):
                self._last_pose_seq = frame.seq
                self.stats.poses_received += 1
                self._events.append(PoseReceived(self.robot_id, frame.seq, pose, now_s))
            else:
                self.stats.poses_stale += 1
        elif msg_type in RELIABLE_TYPES:
            self._on_reliable(frame.seq, msg_type, frame.payload)

    def _on_hello(self, hello: Hello, now_s: float) -> None:
        if (
            self.state is SessionState.ESTABLISHED
            and self.peer_name
            and hello.name != self.peer_name
            and now_s - self._last_rx_s < self.config.link_timeout_s
        ):
            self._control.append(
                self._frame(MsgType.GOODBYE, encode_goodbye(Goodbye(GoodbyeReason.REJECTED, "id taken")), 0)
            )
            return
        self._last_rx_s = now_s
        self._apply_peer_hello(hello)
        self.state = SessionState.HELLO_RECEIVED
        self._control.append(self._hello_frame(MsgType.HELLO_ACK))

    def _on_hello_ack(self, hello: Hello, frame: Frame, now_s: float) -> None:
        if self.state is SessionState.CONNECTING:
            resumed = self._apply_peer_hello(hello)
            self._on_ack(frame.ack)
            self.state = SessionState.ESTABLISHED
            self._hello_next_s = math.inf
            self._events.append(Connected(self.robot_id, hello.name, hello.capabilities, resumed))
            logger.info("robot %d: connected to %s", self.robot_id, hello.name)
        if self.state is SessionState.ESTABLISHED:
            # (Re-)send the third leg; a lost HELLO_DONE makes the server repeat HELLO_ACK.
            self._control.append(self._frame(MsgType.HELLO_DONE, b"", 0))

    def _apply_peer_hello(self, hello: Hello) -> bool:
        self.peer_name = hello.name
        self.peer_capabilities = hello.capabilities
        self.stats.handshakes += 1
        resumed = self._peer_incarnation == hello.incarnation
        if not resumed:
            self._peer_incarnation = hello.incarnation
            self._rx_expected = hello.first_seq
            self._rx_buffer.clear()
            self._last_pose_seq = None
        elif seq_newer(hello.first_seq, self._rx_expected):
            self._rx_expected = hello.first_seq
            self._rx_buffer = {s: v for s, v in self._rx_buffer.items() if not seq_newer(hello.first_seq, s)}
        return resumed

    def _on_goodbye(self, bye: Goodbye, now_s: float) -> None:
        self._events.append(PeerGoodbye(self.robot_id, bye.reason, bye.text))
        logger.info("robot %d: peer said goodbye (%s %s)", self.robot_id, bye.reason.name, bye.text)
        if self.role is Role.ROBOT:
            # Keep trying: the server may come back (or restarted and forgot us).
            self.connect(now_s)
            if bye.reason is not GoodbyeReason.NO_SESSION:
                self._hello_next_s = now_s + self.config.hello_retry_max_s
        else:
            self.state = SessionState.LOST

    def _on_ack(self, ack: int) -> None:
        if not self._unacked:
            return
        last_sent = (self._tx_next_seq - 1 - len(self._queued)) & 0xFFFF
        if seq_newer(ack, last_sent):
            return  # acknowledges something never sent: a stale frame of another session
        while self._unacked:
            seq, out = next(iter(self._unacked.items()))
            if seq_newer(seq, ack):
                break
            del self._unacked[seq]
            self.stats.reliable_acked += 1
            if not out.retransmitted and math.isfinite(out.sent_s):
                self._rtt_sample(self._last_rx_s - out.sent_s)
            self._events.append(Delivered(self.robot_id, seq, out.msg_type))

    def _rtt_sample(self, rtt_s: float) -> None:
        rtt_s = max(rtt_s, 0.0)
        if self._srtt_s is None:
            self._srtt_s = rtt_s
            self._rttvar_s = rtt_s / 2.0
        else:
            self._rttvar_s = 0.75 * self._rttvar_s + 0.25 * abs(self._srtt_s - rtt_s)
            self._srtt_s = 0.875 * self._srtt_s + 0.125 * rtt_s
        rto = self._srtt_s + max(0.01, 4.0 * self._rttvar_s)
        self._rto_s = min(max(rto, self.config.rto_min_s), self.config.rto_max_s)

    def _on_reliable(self, seq: int, msg_type: MsgType, payload: bytes) -> None:
        self._ack_owed = True
        if seq == self._rx_expected:
            self._deliver(seq, msg_type, payload)
            self._rx_expected = (seq + 1) & 0xFFFF
            while self._rx_expected in self._rx_buffer:
                s = self._rx_expected
                t, p = self._rx_buffer.pop(s)
                self._deliver(s, t, p)
                self._rx_expected = (s + 1) & 0xFFFF
        elif (
            seq_newer(seq, self._rx_expected) and ((seq - self._rx_expected) & 0xFFFF) < self.config.rx_window
        ):
            if seq in self._rx_buffer:
                self.stats.duplicates += 1
            self._rx_buffer[seq] = (msg_type, payload)
        else:
            self.stats.duplicates += 1

    def _deliver(self, seq: int, msg_type: MsgType, payload: bytes) -> None:
        try:
            if msg_type is MsgType.SEGMENT:
                self._events.append(SegmentReceived(self.robot_id, seq, decode_segment(payload)))
            else:
                self._events.append(NavOrderReceived(self.robot_id, seq, decode_nav_order(payload)))
            self.stats.reliable_delivered += 1
        except ProtocolError as exc:
            # The sequence number still advances, or the stream would stall forever.
            self.stats.malformed += 1
            logger.warning(
                "robot %d: reliable message %d is malformed and was skipped: %s", self.robot_id, seq, exc
            )
