"""The two ends of one port: a deframer plus the protocol sessions behind it (bytes in, bytes
out). A robot's port carries its one :class:`~.link_session.Session`; a server's port one per
robot id, created by the robot's HELLO. Sans-IO like the sessions: every method takes ``now_s``."""

from __future__ import annotations

import math
import random
from collections import deque
from dataclasses import dataclass, field

from .events import Event
from .link_session import Role, Session, SessionConfig, SessionState
from .messages import Capability, Goodbye, GoodbyeReason, MsgType, encode_goodbye
from .protocol import Deframer, Frame, encode_frame

__all__ = ["RobotEndpoint", "ServerEndpoint"]



class RobotEndpoint:
    """The robot end of one port: a deframer plus one :class:`Session` (bytes in, bytes out)."""

    def __init__(
        self,
        robot_id: int,
        name: str,
        capabilities: int = Capability.POSE | Capability.SEGMENTS | Capability.NAV_ORDERS,
        config: SessionConfig | None = None,
        *,
        rng: random.Random | None = None,
    ) -> None:
        self.session = Session(Role.ROBOT, robot_id, name, capabilities, config, rng=rng)
        self.deframer = Deframer()
        self.foreign_frames = 0

    def start(self, now_s: float) -> None:
        self.session.connect(now_s)

    def receive_bytes(self, data: bytes, now_s: float) -> None:
        for frame in self.deframer.feed(data):
            if frame.robot_id != self.session.robot_id:
                self.foreign_frames += 1  # another robot's traffic on a shared radio channel
                continue
            self.session.handle_frame(frame, now_s)

    def next_bytes(self, now_s: float) -> bytes | None:
        self.session.poll(now_s)
        frame = self.session.next_frame(now_s)
        if frame is None:
            return None
        data = encode_frame(frame)
        self.session.stats.bytes_tx += len(data)
        return data

    def poll(self, now_s: float) -> None:
        self.session.poll(now_s)

    def next_deadline_s(self) -> float:
        return self.session.next_deadline_s()

    def take_events(self) -> list[Event]:
        return self.session.take_events()

    def on_port_reset(self) -> None:
        self.deframer.reset()

    def close(self) -> None:
        self.session.close()


@dataclass(slots=True)
class ServerEndpoint:
    """The server end of one port: a deframer and one :class:`Session` per robot id.

    Robots are created by their HELLO; data from an unknown robot is answered with a
    GOODBYE(NO_SESSION) so it handshakes again (e.g. after a server restart).
    """

    name: str = "mapserver"
    capabilities: int = Capability.MAP | Capability.NAV_ORDERS
    config: SessionConfig = field(default_factory=SessionConfig)
    rng: random.Random = field(default_factory=random.Random)
    sessions: dict[int, Session] = field(default_factory=dict)
    deframer: Deframer = field(default_factory=Deframer)
    _rr: int = 0
    _nosession: deque[Frame] = field(default_factory=deque)
    _nosession_last: dict[int, float] = field(default_factory=dict)
    _incarnation: int = -1

    def __post_init__(self) -> None:
        self._incarnation = self.rng.getrandbits(32)

    def session(self, robot_id: int) -> Session:
        """The session of ``robot_id``, created on first use (e.g. to queue an order early)."""
        sess = self.sessions.get(robot_id)
        if sess is None:
            sess = Session(
                Role.SERVER,
                robot_id,
                self.name,
                self.capabilities,
                self.config,
                incarnation=self._incarnation,
                rng=self.rng,
            )
            self.sessions[robot_id] = sess
        return sess

    def receive_bytes(self, data: bytes, now_s: float) -> None:
        for frame in self.deframer.feed(data):
            if not 1 <= frame.robot_id <= 254:
                continue
            sess = self.sessions.get(frame.robot_id)
            if frame.msg_type == MsgType.HELLO:
                self.session(frame.robot_id).handle_frame(frame, now_s)
            elif sess is None or sess.state is SessionState.IDLE:
                if frame.msg_type in (MsgType.GOODBYE, MsgType.HELLO_ACK):
                    continue
                if now_s - self._nosession_last.get(frame.robot_id, -math.inf) >= 0.1:
                    self._nosession_last[frame.robot_id] = now_s
                    bye = encode_goodbye(Goodbye(GoodbyeReason.NO_SESSION, "handshake again"))
                    self._nosession.append(Frame(int(MsgType.GOODBYE), frame.robot_id, 0, 0, bye))
            else:
                sess.handle_frame(frame, now_s)

    def next_bytes(self, now_s: float) -> bytes | None:
        if self._nosession:
            return encode_frame(self._nosession.popleft())
        sessions = list(self.sessions.values())
        n = len(sessions)
        for i in range(n):
            sess = sessions[(self._rr + i) % n]
            sess.poll(now_s)
            frame = sess.next_frame(now_s)
            if frame is not None:
                self._rr = (self._rr + i + 1) % n
                data = encode_frame(frame)
                sess.stats.bytes_tx += len(data)
                return data
        return None

    def poll(self, now_s: float) -> None:
        for sess in self.sessions.values():
            sess.poll(now_s)

    def next_deadline_s(self) -> float:
        if self._nosession:
            return -math.inf
        return min((s.next_deadline_s() for s in self.sessions.values()), default=math.inf)

    def take_events(self) -> list[Event]:
        events: list[Event] = []
        for sess in self.sessions.values():
            events.extend(sess.take_events())
        return events

    def on_port_reset(self) -> None:
        self.deframer.reset()

    def close(self) -> None:
        for sess in self.sessions.values():
            sess.close()
