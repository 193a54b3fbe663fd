"""The robot end: report poses (and wall segments) to a mapping server over a serial port.

::

    async with Reporter("/dev/ttyACM0", robot_id=3, name="uav3", map_frame=frame) as rep:
        await rep.run(replay_samples(read_tum_samples("flight.tum"), clock), rate_hz=50)

A :class:`Reporter` owns a :class:`~.transport.SerialTransport` (one thread) running a
:class:`~.endpoints.RobotEndpoint`. :meth:`Reporter.report_pose` offers a pose (newest wins:
only the latest offered pose is sent when the line is free); :meth:`Reporter.report_segment`
queues a wall segment for reliable delivery; navigation orders from the server arrive in
:attr:`Reporter.nav_orders` and through the ``on_nav_order`` callback.

Pose sources are plain iterables or async iterables of :class:`PoseSample`, always in the world
frame; helpers read TUM trajectory files and MCAP ``geometry_msgs/msg/PoseStamped`` topics
(placed in the world by the frame each pose names, with the recording's ``T_world_mocap``),
read pose streams from the bus (likewise), replay them on a clock, and adapt a flightkit
:class:`~flightkit.mocap.base.MocapSource`.
"""
from __future__ import annotations

import asyncio
import logging
import math
import threading
import time
from collections.abc import AsyncIterable, AsyncIterator, Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Self

from flightkit.clock import Clock, WallClock
from flightkit.errors import DatasetError, ProtocolError
from flightkit.frames import Transform, WorldFrames
from flightkit.lifetime import Running
from flightkit.mocap.base import MocapSource
from flightkit.settings import setting

from .endpoints import RobotEndpoint
from .events import Connected, LinkLost, NavOrderReceived, PeerGoodbye
from .link_session import SessionConfig, SessionStats
from .mapframe import MapFrame, MapFrameConfig
from .messages import Capability, NavOrder, Segment
from .transport import PortLost, PortOpened, SerialTransport, TransportEvent

__all__ = [
    "PoseSample",
    "Reporter",
    "ReporterConfig",
    "mocap_samples",
    "read_mcap_samples",
    "read_tum_samples",
    "replay_samples",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class PoseSample:
    """A body pose to report.

    Attributes:
        stamp_ns: capture time, ns since the Unix epoch (or the recording's epoch).
        T_world_body: pose of the body in the world frame (ENU).
        quality: 0 (unusable) .. 255 (best), e.g. from a VO confidence.
    """

    stamp_ns: int
    T_world_body: Transform
    quality: int = 255


@dataclass(frozen=True, slots=True)
class ReporterConfig:
    """``[report]`` section of a config file."""

    port: str = setting("", help="serial port or URL, e.g. /dev/ttyACM0 or socket://host:port")
    baud: int = setting(115200, min=1200, max=4_000_000, help="serial baud rate")
    link_rate_bps: float = setting(0.0, min=0.0, max=1e8, help="pace at this rate instead of baud (0: baud)")
    robot_id: int = setting(1, min=1, max=254, help="this robot's id on the map")
    name: str = setting("uav1", help="this robot's name on the map (at most 32 bytes)")
    rate_hz: float = setting(20.0, min=0.1, max=1000.0, help="pose updates per second")
    map: MapFrameConfig = setting(default_factory=MapFrameConfig, help="the server's map frame")


@dataclass(frozen=True, slots=True)
class ReceivedOrder:
    """A navigation order, in map units and converted to the world frame (metres)."""

    order: NavOrder
    pos_world_m: tuple[float, float, float]  # z NaN: keep the current height
    heading_world_rad: float  # NaN: any heading


class Reporter(Running):
    """Report poses over ``port``; see the module docstring.

    Args:
        port: serial port or URL accepted by pyserial.
        robot_id, name: how the server knows us.
        baud: serial baud rate.
        map_frame: world -> map conversion.
        clock: protocol timers (default wall time).
        session_config: protocol timing.
        link_rate_bps: pace at this rate instead of ``baud``.
        on_nav_order: called (on the port thread) for each navigation order.
    """

    def __init__(
        self,
        port: str,
        *,
        robot_id: int = 1,
        name: str = "uav1",
        baud: int = 115200,
        map_frame: MapFrame | None = None,
        clock: Clock | None = None,
        session_config: SessionConfig | None = None,
        link_rate_bps: float | None = None,
        on_nav_order: Callable[[ReceivedOrder], None] | None = None,
    ) -> None:
        self.map_frame = map_frame or MapFrame()
        self.clock: Clock = clock or WallClock()
        self.endpoint = RobotEndpoint(
            robot_id, name, Capability.POSE | Capability.SEGMENTS | Capability.NAV_ORDERS, session_config
        )
        self.on_nav_order = on_nav_order
        self.nav_orders: list[ReceivedOrder] = []
        self.last_error = ""
        self._cond = threading.Condition()
        self.transport = SerialTransport(
            port,
            self.endpoint,
            baud=baud,
            clock=self.clock,
            link_rate_bps=link_rate_bps,
            on_event=self._on_event,
            queue_events=False,
        )

    @classmethod
    def from_config(cls, cfg: ReporterConfig, **kwargs: Any) -> Reporter:
        return cls(
            cfg.port,
            robot_id=cfg.robot_id,
            name=cfg.name,
            baud=cfg.baud,
            map_frame=MapFrame(cfg.map),
            link_rate_bps=cfg.link_rate_bps or None,
            **kwargs,
        )

    # ------------------------------------------------------------------ lifetime

    def start(self) -> Self:
        self.transport.start()
        return self

    def stop(self) -> None:
        """Say goodbye and close the port (undelivered reliable messages are dropped)."""
        self.transport.stop()

    async def __aenter__(self) -> Self:
        return self.start()

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await asyncio.to_thread(self.stop)

    # ------------------------------------------------------------------ state

    @property
    def connected(self) -> bool:
        return bool(self.transport.call(lambda ep: ep.session.established))

    @property
    def stats(self) -> SessionStats:
        return self.endpoint.session.stats

    @property
    def unacked(self) -> int:
        return int(self.transport.call(lambda ep: ep.session.unacked))

    def wait_connected(self, timeout_s: float) -> None:
        """Block until the handshake is done.

        Raises:
            ProtocolError: when no server answered within ``timeout_s``.
        """
        if not self._wait(lambda: self.endpoint.session.established, timeout_s):
            hint = f" ({self.last_error})" if self.last_error else ""
            raise ProtocolError(
                f"no mapping server answered on {self.transport.url} within {timeout_s:.1f} s{hint}; "
                "is `flightkit mapserver` running on the other end and are the baud rates equal?"
            )

    def wait_delivered(self, timeout_s: float) -> None:
        """Block until every segment sent so far is acknowledged.

        Raises:
            ProtocolError: when some are still unacknowledged after ``timeout_s``.
        """
        if not self._wait(lambda: self.endpoint.session.unacked == 0, timeout_s):
            raise ProtocolError(
                f"{self.endpoint.session.unacked} segments still unacknowledged after {timeout_s:.1f} s; "
                "the link to the mapping server is down or too lossy"
            )

    def _wait(self, cond: Callable[[], bool], timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                with self.transport._lock:
                    if cond():
                        return True
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(min(left, 0.05))

    # ------------------------------------------------------------------ sending

    def report_pose(self, sample: PoseSample) -> None:
        """Offer a pose; returns immediately (only the newest pending pose is sent)."""
        update = self.map_frame.pose_update(sample.stamp_ns, sample.T_world_body, sample.quality)
        self.transport.call(lambda ep: ep.session.send_pose(update))

    def report_segment(self, start_world_m: Sequence[float], end_world_m: Sequence[float]) -> int:
        """Queue a wall segment (world x, y in metres) for reliable delivery; returns its sequence number."""
        x0, y0, _ = self.map_frame.point_to_map(float(start_world_m[0]), float(start_world_m[1]))
        x1, y1, _ = self.map_frame.point_to_map(float(end_world_m[0]), float(end_world_m[1]))
        seg = Segment(x0, y0, x1, y1)
        return int(self.transport.call(lambda ep: ep.session.send_segment(seg)))

    async def run(
        self,
        source: Iterable[PoseSample] | AsyncIterable[PoseSample],
        rate_hz: float,
        *,
        until_s: float | None = None,
    ) -> int:
        """Report poses from ``source`` at ``rate_hz`` until it ends; returns the number offered.

        The newest sample is offered every ``1 / rate_hz`` seconds of the clock; samples that
        arrive faster are skipped, a source slower than the rate is reported as it comes.
        """
        if not rate_hz > 0:
            raise ProtocolError(f"rate {rate_hz} Hz must be positive; use e.g. 20")
        period_s = 1.0 / rate_hz
        offered = 0
        next_s = -math.inf
        start_s = self.clock.monotonic_s()
        pending: PoseSample | None = None
        async for sample in _aiter(source):
            pending = sample
            now = self.clock.monotonic_s()
            if now >= next_s:
                self.report_pose(sample)
                offered += 1
                pending = None
                next_s = max(next_s + period_s, now) if math.isfinite(next_s) else now + period_s
            if until_s is not None and now - start_s >= until_s:
                break
        if pending is not None:
            self.report_pose(pending)
            offered += 1
        return offered

    # ------------------------------------------------------------------ events

    def _on_event(self, ev: TransportEvent) -> None:
        if isinstance(ev, NavOrderReceived):
            o = ev.order
            pos = self.map_frame.point_to_world(o.x, o.y, o.z)
            heading = (
                self.map_frame.heading_to_world(o.heading_rad) if math.isfinite(o.heading_rad) else math.nan
            )
            received = ReceivedOrder(o, pos, heading)
            self.nav_orders.append(received)
            logger.info("navigation order %d: go to world (%.2f, %.2f) m", o.order_id, pos[0], pos[1])
            if self.on_nav_order is not None:
                self.on_nav_order(received)
        elif isinstance(ev, Connected):
            self.last_error = ""
        elif isinstance(ev, PortLost):
            self.last_error = ev.message
        elif isinstance(ev, PeerGoodbye):
            self.last_error = f"server said goodbye ({ev.reason.name.lower()})"
        elif isinstance(ev, LinkLost | PortOpened):
            pass
        with self._cond:
            self._cond.notify_all()


async def _aiter(source: Iterable[PoseSample] | AsyncIterable[PoseSample]) -> AsyncIterator[PoseSample]:
    if isinstance(source, AsyncIterable):
        async for s in source:
            yield s
    else:
        for s in source:
            yield s
            await asyncio.sleep(0)


# ----------------------------------------------------------------------------- sources


def read_tum_samples(path: str | Path) -> list[PoseSample]:
    """Poses of a TUM trajectory file (``t x y z qx qy qz qw`` per line).

    Raises:
        DatasetError: when the file cannot be read.
    """
    from flightkit.datasets.trajectory import read_tum

    traj = read_tum(path)
    return [PoseSample(int(traj.stamps_ns[i]), traj.transform(i)) for i in range(len(traj))]


def read_mcap_samples(
    path: str | Path, topic: str | None = None, *, T_world_mocap: Transform | None = None  # noqa: N803
) -> list[PoseSample]:
    """Poses of a ``geometry_msgs/msg/PoseStamped`` topic in an MCAP recording, in the world frame.

    Args:
        path: the .mcap file.
        topic: the topic; None takes the only PoseStamped topic (an error if there are several).
        T_world_mocap: overrides the recording's own mocap frame (its ``extrinsics`` metadata).

    Raises:
        DatasetError: when the file has no (or several, with ``topic`` None) pose topics.
        FrameError: a pose in a frame the recording cannot place in the world.
    """
    from flightkit.datasets.mcap_reader import RecordingReader

    rec = RecordingReader(path)
    pose_topics = rec.pose_topics()
    if topic is None:
        if len(pose_topics) != 1:
            raise DatasetError(
                f"{rec.path} has {len(pose_topics)} PoseStamped topics ({', '.join(pose_topics) or 'none'}); "
                "name one with --topic"
            )
        topic = pose_topics[0]
    elif topic not in pose_topics:
        raise DatasetError(
            f"{rec.path} has no PoseStamped topic {topic!r}; it has: {', '.join(pose_topics) or 'none'}"
        )
    traj = rec.pose_trajectory(topic, rec.world_frames(T_world_mocap))
    return [PoseSample(int(traj.stamps_ns[i]), traj.transform(i)) for i in range(len(traj))]


async def replay_samples(
    samples: Iterable[PoseSample], clock: Clock, *, speed: float = 1.0, restamp: bool = True
) -> AsyncIterator[PoseSample]:
    """Yield recorded samples spaced as they were recorded (divided by ``speed``) on ``clock``.

    With ``restamp`` the stamps are moved to the clock's ``time_ns`` at replay, keeping
    their spacing, so the server sees live times.
    """
    t0_rec: int | None = None
    t0_clock = clock.monotonic_s()
    t0_ns = clock.time_ns()
    for s in samples:
        if t0_rec is None:
            t0_rec = s.stamp_ns
        due = (s.stamp_ns - t0_rec) / 1e9 / speed
        wait = due - (clock.monotonic_s() - t0_clock)
        if wait > 0:
            await clock.sleep(wait)
        yield PoseSample(t0_ns + int(due * 1e9), s.T_world_body, s.quality) if restamp else s


async def bus_pose_samples(session: Any, key: str, frames: WorldFrames) -> AsyncIterator[PoseSample]:
    """Poses of a ``geometry_msgs/msg/PoseStamped`` stream on the bus (mocap poses, VO odometry),
    placed in the world by the frame each names; runs until cancelled.

    Raises:
        FrameError: a pose in a frame ``frames`` cannot place.
    """
    from flightkit.bus.pose_msgs import PoseStamped
    from flightkit.bus.pubsub import BusSubscriber
    from flightkit.mocap.bus_source import pose_is_valid

    sub = BusSubscriber(session, key)
    try:
        async for s in sub:
            if s.msgtype and s.msgtype != PoseStamped.TYPE:
                continue
            msg = PoseStamped.decode(s.payload)
            if not pose_is_valid(msg):
                continue  # a lost body
            T_world_body = frames.to_world(msg.header.frame_id, msg.to_transform())  # noqa: N806
            yield PoseSample(msg.header.stamp_ns or s.stamp_ns, T_world_body)
    finally:
        sub.close()


async def mocap_samples(source: MocapSource, body: str) -> AsyncIterator[PoseSample]:
    """Adapt a :class:`~flightkit.mocap.base.MocapSource` (already entered) to pose samples."""
    async for pose in source.poses(body):
        yield PoseSample(pose.stamp_ns, pose.T_world_body, 255 if pose.valid else 0)
