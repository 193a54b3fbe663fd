"""The sans-IO session: handshake, reliability, newest-wins and link loss, on simulated time.

The two ends exchange real encoded frames through an in-memory line that drops, duplicates,
reorders, corrupts and delays frames; time is a plain number advanced in 1 ms steps.
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field

import pytest

from estimation.report.endpoints import RobotEndpoint, ServerEndpoint
from estimation.report.events import (
    Connected,
    Delivered,
    Event,
    LinkLost,
    NavOrderReceived,
    PeerGoodbye,
    PoseReceived,
    SegmentReceived,
)
from estimation.report.link_session import SessionConfig, SessionState
from estimation.report.messages import GoodbyeReason, NavOrder, PoseUpdate, Segment
from flightkit.errors import ProtocolError


@dataclass
class Line:
    """One direction of a faulty serial line: whole frames with faults, then bytes."""

    rng: random.Random
    drop: float = 0.0
    dup: float = 0.0
    reorder: float = 0.0
    corrupt: float = 0.0
    delay_s: float = 0.002
    up: bool = True
    in_flight: list[tuple[float, bytes]] = field(default_factory=list)

    def send(self, data: bytes, now_s: float) -> None:
        if not self.up or self.rng.random() < self.drop:
            return
        if self.rng.random() < self.corrupt:
            b = bytearray(data)
            b[self.rng.randrange(len(b))] ^= 1 << self.rng.randrange(8)
            data = bytes(b)
        t = now_s + self.delay_s + (self.rng.uniform(0.0, 0.03) if self.rng.random() < self.reorder else 0.0)
        self.in_flight.append((t, data))
        if self.rng.random() < self.dup:
            self.in_flight.append((t + 0.005, data))

    def due(self, now_s: float) -> list[bytes]:
        out = sorted((x for x in self.in_flight if x[0] <= now_s), key=lambda x: x[0])
        self.in_flight = [x for x in self.in_flight if x[0] > now_s]
        return [d for _, d in out]


class Harness:
    def __init__(self, seed: int = 1, **faults: float) -> None:
        self.rng = random.Random(seed)
        self.cfg = SessionConfig()
        self.robot = RobotEndpoint(7, "uav7", config=self.cfg, rng=random.Random(seed + 1))
        self.server = ServerEndpoint(config=self.cfg, rng=random.Random(seed + 2))
        self.up = Line(self.rng, **faults)
        self.down = Line(self.rng, **faults)
        self.now = 0.0
        self.robot_events: list[Event] = []
        self.server_events: list[Event] = []
        self.robot.start(self.now)

    def step(self, dt: float = 0.001, frames_per_step: int = 1) -> None:
        self.now += dt
        for data in self.up.due(self.now):
            self.server.receive_bytes(data, self.now)
        for data in self.down.due(self.now):
            self.robot.receive_bytes(data, self.now)
        for _ in range(frames_per_step):  # ~30 bytes/ms = a 300 kbaud line
            out = self.robot.next_bytes(self.now)
            if out:
                self.up.send(out, self.now)
            out = self.server.next_bytes(self.now)
            if out:
                self.down.send(out, self.now)
        self.robot_events += self.robot.take_events()
        self.server_events += self.server.take_events()

    def run(self, seconds: float, **kw: int) -> None:
        for _ in range(round(seconds / 0.001)):
            self.step(**kw)

    def run_until(self, cond, timeout_s: float) -> None:  # type: ignore[no-untyped-def]
        end = self.now + timeout_s
        while not cond():
            assert self.now < end, "condition not reached in simulated time"
            self.step()

    def of(self, events: list[Event], kind: type) -> list:  # type: ignore[type-arg]
        return [e for e in events if isinstance(e, kind)]


def _pose(i: int) -> PoseUpdate:
    return PoseUpdate(1_000_000 + i, float(i), 0.0, 1.0, 0.0, 200)


def test_three_way_handshake() -> None:
    h = Harness()
    h.run_until(lambda: h.robot.session.established and h.server.sessions[7].established, 1.0)
    (rc,) = h.of(h.robot_events, Connected)
    (sc,) = h.of(h.server_events, Connected)
    assert rc.peer_name == "mapserver" and sc.peer_name == "uav7"
    assert not rc.resumed and not sc.resumed


def test_clean_line_delivers_everything_in_order() -> None:
    h = Harness()
    h.run(0.05)
    seqs = [h.robot.session.send_segment(Segment(i, 0, i, 1)) for i in range(100)]
    orders = [h.server.session(7).send_nav_order(NavOrder(i, i, -i)) for i in range(20)]
    for i in range(300):
        h.robot.session.send_pose(_pose(i))
        h.step()
    h.run(0.5)
    got = [e.segment.x0 for e in h.of(h.server_events, SegmentReceived)]
    assert got == list(range(100))
    assert [e.order.order_id for e in h.of(h.robot_events, NavOrderReceived)] == list(range(20))
    assert [e.seq for e in h.of(h.robot_events, Delivered)] == seqs
    assert [e.seq for e in h.of(h.server_events, Delivered)] == orders
    assert h.robot.session.unacked == 0 and h.server.sessions[7].unacked == 0
    assert h.robot.session.stats.retransmissions == 0


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_faulty_line_loses_and_reorders_nothing_reliable(seed: int) -> None:
    h = Harness(seed, drop=0.15, dup=0.1, reorder=0.2, corrupt=0.05)
    h.run_until(lambda: h.robot.session.established, 5.0)
    for i in range(200):
        h.robot.session.send_segment(Segment(i, 0, 0, 0))
        if i % 5 == 0:
            h.server.session(7).send_nav_order(NavOrder(i, 0, 0))
        h.robot.session.send_pose(_pose(i))
        h.step()
    h.run_until(lambda: h.robot.session.unacked == 0 and h.server.sessions[7].unacked == 0, 30.0)
    assert [e.segment.x0 for e in h.of(h.server_events, SegmentReceived)] == list(range(200))
    assert [e.order.order_id for e in h.of(h.robot_events, NavOrderReceived)] == list(range(0, 200, 5))
    stamps = [e.pose.stamp_us for e in h.of(h.server_events, PoseReceived)]
    assert stamps == sorted(set(stamps)), "a pose arrived after a newer one"
    assert h.robot.session.stats.retransmissions > 0
    assert h.server.deframer.stats.crc_errors + h.server.deframer.stats.cobs_errors > 0


def test_newest_pose_wins_at_the_sender() -> None:
    h = Harness()
    h.run_until(lambda: h.robot.session.established, 1.0)
    h.run(0.01)
    for i in range(50):  # offered far faster than the line sends
        h.robot.session.send_pose(_pose(i))
    h.run(0.05)
    stamps = [e.pose.stamp_us for e in h.of(h.server_events, PoseReceived)]
    assert stamps == [_pose(49).stamp_us]
    assert h.robot.session.stats.poses_superseded == 49


def test_stale_pose_is_dropped_by_the_receiver() -> None:
    h = Harness(delay_s=0.0)
    h.run_until(lambda: h.robot.session.established, 1.0)
    h.run(0.01)
    frames = []
    for i in range(3):
        h.robot.session.send_pose(_pose(i))
        frames.append(h.robot.next_bytes(h.now))
    for data in (frames[0], frames[2], frames[1]):
        h.server.receive_bytes(data, h.now)
    h.server_events += h.server.take_events()
    assert [e.pose.x for e in h.of(h.server_events, PoseReceived)] == [0.0, 2.0]
    assert h.server.sessions[7].stats.poses_stale == 1


def test_link_loss_rehandshake_and_resume_without_loss_or_duplicates() -> None:
    h = Harness()
    h.run_until(lambda: h.robot.session.established, 1.0)
    for i in range(20):
        h.robot.session.send_segment(Segment(i, 0, 0, 0))
    h.run(0.003)
    h.up.up = h.down.up = False  # the radio drops out
    for i in range(20, 40):
        h.robot.session.send_segment(Segment(i, 0, 0, 0))
    h.run(2.0)
    assert h.of(h.robot_events, LinkLost) and h.of(h.server_events, LinkLost)
    assert h.robot.session.state is SessionState.CONNECTING
    assert h.server.sessions[7].state is SessionState.LOST
    h.up.up = h.down.up = True
    h.run_until(lambda: h.robot.session.unacked == 0, 10.0)
    assert [e.segment.x0 for e in h.of(h.server_events, SegmentReceived)] == list(range(40))
    reconnect = h.of(h.robot_events, Connected)[-1]
    assert reconnect.resumed


def test_robot_restart_is_a_new_incarnation() -> None:
    h = Harness()
    h.run_until(lambda: h.robot.session.established, 1.0)
    h.robot.session.send_segment(Segment(1, 0, 0, 0))
    h.run(0.1)
    h.robot = RobotEndpoint(7, "uav7", config=h.cfg, rng=random.Random(99))  # process restarted
    h.robot.start(h.now)
    h.robot.session.send_segment(Segment(2, 0, 0, 0))
    h.run_until(lambda: h.robot.session.unacked == 0, 3.0)
    assert [e.segment.x0 for e in h.of(h.server_events, SegmentReceived)] == [1.0, 2.0]
    assert not h.of(h.server_events, Connected)[-1].resumed


def test_server_restart_makes_the_robot_handshake_again() -> None:
    h = Harness()
    h.run_until(lambda: h.robot.session.established, 1.0)
    h.server = ServerEndpoint(config=h.cfg, rng=random.Random(77))  # forgot everything
    h.robot.session.send_segment(Segment(5, 0, 0, 0))
    for i in range(50):
        h.robot.session.send_pose(_pose(i))
        h.step()
    h.run_until(lambda: h.robot.session.unacked == 0, 3.0)
    assert any(e.reason is GoodbyeReason.NO_SESSION for e in h.of(h.robot_events, PeerGoodbye))
    assert [e.segment.x0 for e in h.of(h.server_events, SegmentReceived)] == [5.0]


def test_goodbye_closes_the_server_side() -> None:
    h = Harness()
    h.run_until(lambda: h.server.sessions.get(7) is not None and h.server.sessions[7].established, 1.0)
    h.robot.close()
    h.run(0.05)
    (bye,) = h.of(h.server_events, PeerGoodbye)
    assert bye.reason is GoodbyeReason.SHUTDOWN
    assert h.server.sessions[7].state is SessionState.LOST


def test_heartbeats_keep_an_idle_link_alive() -> None:
    h = Harness()
    h.run(5.0)
    assert not h.of(h.robot_events, LinkLost) and not h.of(h.server_events, LinkLost)
    assert h.robot.session.established


def test_retransmission_timeout_adapts_to_the_round_trip() -> None:
    h = Harness(delay_s=0.05)
    h.run_until(lambda: h.robot.session.established, 1.0)
    for i in range(30):
        h.robot.session.send_segment(Segment(i, 0, 0, 0))
        h.run(0.02)
    h.run(0.5)
    assert 0.1 <= h.robot.session.rto_s <= 0.5
    assert h.robot.session.stats.retransmissions == 0


def test_queue_limit_raises_a_clear_error() -> None:
    ep = RobotEndpoint(3, "x", config=SessionConfig(max_queued=5))
    for i in range(5):
        ep.session.send_segment(Segment(i, 0, 0, 0))
    with pytest.raises(ProtocolError, match="waiting"):
        ep.session.send_segment(Segment(9, 0, 0, 0))


def test_foreign_robot_frames_are_ignored() -> None:
    a = RobotEndpoint(1, "a")
    b = ServerEndpoint()
    a.start(0.0)
    hello = a.next_bytes(0.0)
    assert hello is not None
    b.receive_bytes(hello, 0.0)
    ack = b.next_bytes(0.0)
    other = RobotEndpoint(2, "b")
    other.start(0.0)
    assert ack is not None
    other.receive_bytes(ack, 0.0)
    assert other.foreign_frames == 1 and not other.session.established
    a.receive_bytes(ack, 0.0)
    assert a.session.established


def test_robot_id_range_is_checked() -> None:
    with pytest.raises(ProtocolError, match="1..254"):
        RobotEndpoint(0, "zero")
