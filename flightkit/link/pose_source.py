"""The autopilot's own pose estimate as a motion-capture source.

:class:`TelemetryPoseSource` turns a :class:`~flightkit.link.base.VehicleLink`'s local
position and attitude telemetry into :class:`~flightkit.mocap.base.MocapPose` values, so the
flight runner (which takes any :class:`~flightkit.mocap.base.MocapSource`) can fly on what the
autopilot believes instead of on mocap: with the autopilot fusing visual odometry, that is a
flight on the estimate alone ("closed loop").

Frames: the autopilot's local frame (expressed ENU by the link) maps into the world through
``T_world_local``. When the autopilot fuses an external pose given in the world frame (vision
position *and* yaw), its local frame *is* the world frame and ``T_world_local`` is the
identity (the default). Fly with the controller in ``local_ned`` output mode then: the
setpoints are in the same frame as the feedback.

Timing: the source polls ``link.telemetry`` at ``rate_hz`` of clock time and hands out a pose
whenever the telemetry snapshot has changed. ``received_s`` is the clock time of the newest
telemetry message (``Telemetry.stamp_s``), so a silent link shows as stale mocap to the
supervisor; ``stamp_ns`` is the clock's ``time_ns`` when the snapshot was read.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections.abc import AsyncIterator
from types import TracebackType
from typing import Self

import numpy as np

from flightkit.clock import Clock
from flightkit.errors import MocapBodyMissing
from flightkit.frames import Transform
from flightkit.link.base import Telemetry, VehicleLink
from flightkit.mocap.base import MocapPose

__all__ = ["TelemetryPoseSource", "pose_from_telemetry"]

logger = logging.getLogger(__name__)

_QUEUE_SIZE = 64


def pose_from_telemetry(
    tel: Telemetry,
    body: str,
    *,
    stamp_ns: int,
    seq: int = 0,
    T_world_local: Transform | None = None,  # noqa: N803
    max_heartbeat_age_s: float = 2.0,
) -> MocapPose | None:
    """The body pose a telemetry snapshot describes, in the world frame.

    ``T_world_body = T_world_local @ T_local_body`` with ``T_local_body`` built from the
    local ENU position and the FLU-in-ENU attitude quaternion.

    Returns:
        None when the snapshot has no position yet (NaN); a pose with ``valid=False`` when
        the attitude is degenerate or the heartbeat is older than ``max_heartbeat_age_s``
        (the autopilot may be gone: do not fly on it).
    """
    pos = np.asarray(tel.pos_local_enu_m, dtype=np.float64)
    if not np.all(np.isfinite(pos)):
        return None
    q = np.asarray(tel.R_local_body_quat_wxyz, dtype=np.float64)
    norm = float(np.linalg.norm(q)) if np.all(np.isfinite(q)) else 0.0
    valid = 0.5 < norm < 1.5 and tel.heartbeat_age_s <= max_heartbeat_age_s
    if not 0.5 < norm < 1.5:
        q = np.array([1.0, 0.0, 0.0, 0.0])
    T_local_body = Transform.from_quat_wxyz(pos, q / np.linalg.norm(q))  # noqa: N806
    T = T_local_body if T_world_local is None else T_world_local @ T_local_body  # noqa: N806
    return MocapPose(int(stamp_ns), body, T, valid, seq, float(tel.stamp_s))


class TelemetryPoseSource:
    """A :class:`~flightkit.mocap.base.MocapSource` of one body: the autopilot's estimate.

    Args:
        link: a connected vehicle link (its telemetry is read, nothing is sent).
        clock: the flight's clock (polling, stamps).
        body: the name the poses carry (give the name the runner flies, e.g. ``mocap.body``).
        rate_hz: polling rate (the link's LOCAL_POSITION_NED stream is 50 Hz by default).
        T_world_local: the autopilot's local frame in the world (identity when it fuses a
            world-frame vision pose with yaw).
        max_heartbeat_age_s: poses are flagged invalid when the heartbeat is older.

    Use as ``async with source:`` from the event loop the link runs on.
    """

    def __init__(
        self,
        link: VehicleLink,
        clock: Clock,
        body: str,
        *,
        rate_hz: float = 50.0,
        T_world_local: Transform | None = None,  # noqa: N803
        max_heartbeat_age_s: float = 2.0,
    ) -> None:
        if not (math.isfinite(rate_hz) and 1.0 <= rate_hz <= 1000.0):
            raise ValueError(f"telemetry pose rate {rate_hz!r} Hz is outside 1-1000 Hz; pick e.g. 50")
        self.link = link
        self.clock = clock
        self.body = body
        self.rate_hz = float(rate_hz)
        self.T_world_local = T_world_local
        self.max_heartbeat_age_s = float(max_heartbeat_age_s)
        self._latest: MocapPose | None = None
        self._last_key: tuple[object, ...] | None = None
        self._seq = 0
        self._queues: list[asyncio.Queue[MocapPose]] = []
        self._task: asyncio.Task[None] | None = None
        self.poses_published = 0

    # ------------------------------------------------------------------ lifecycle

    async def __aenter__(self) -> Self:
        self.start()
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.close()

    def start(self) -> Self:
        """Start polling on the running event loop; returns immediately (idempotent)."""
        if self._task is None:
            self._task = asyncio.get_running_loop().create_task(
                self._run(), name=f"telemetry-pose-{self.body}"
            )
        return self

    async def close(self) -> None:
        """Stop polling; idempotent."""
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    # ------------------------------------------------------------------ MocapSource

    def bodies(self) -> tuple[str, ...]:
        """``(body,)`` once the autopilot has reported a position; returns immediately."""
        return (self.body,) if self._latest is not None else ()

    def latest(self, body: str) -> MocapPose | None:
        """Newest pose of ``body`` (None if never seen or another name); returns immediately."""
        return self._latest if body == self.body else None

    async def wait_for_body(self, body: str, timeout_s: float) -> MocapPose:
        """Wait until the autopilot reports a valid, fresh pose, for up to ``timeout_s`` of clock time.

        Raises:
            MocapBodyMissing: none in time (or ``body`` is not this source's body).
        """
        deadline = self.clock.monotonic_s() + timeout_s
        period = 1.0 / self.rate_hz
        while True:
            p = self._latest
            if (
                body == self.body
                and p is not None
                and p.valid
                and self.clock.monotonic_s() - p.received_s <= max(0.5, 5.0 * period)
            ):
                return p
            if self.clock.monotonic_s() >= deadline:
                raise MocapBodyMissing(body, self.bodies())
            await self.clock.sleep(min(period, max(0.0, deadline - self.clock.monotonic_s())))

    async def poses(self, body: str | None = None) -> AsyncIterator[MocapPose]:
        """New poses as they are read (of this body; another name yields nothing).

        A slow consumer loses the oldest (the queue holds 64); never ends on its own.
        """
        queue: asyncio.Queue[MocapPose] = asyncio.Queue(_QUEUE_SIZE)
        self._queues.append(queue)
        try:
            while True:
                p = await queue.get()
                if body is None or body == p.body:
                    yield p
        finally:
            self._queues.remove(queue)

    # ------------------------------------------------------------------ polling

    def poll(self) -> MocapPose | None:
        """Read the telemetry once; returns the new pose if the snapshot changed (also hands it
        to :meth:`poses` consumers), else None. The polling task calls this at ``rate_hz``."""
        tel = self.link.telemetry
        key = (tel.stamp_s, tel.pos_local_enu_m, tel.R_local_body_quat_wxyz)
        if key == self._last_key:
            return None
        self._last_key = key
        pose = pose_from_telemetry(
            tel,
            self.body,
            stamp_ns=self.clock.time_ns(),
            seq=self._seq + 1,
            T_world_local=self.T_world_local,
            max_heartbeat_age_s=self.max_heartbeat_age_s,
        )
        if pose is None:
            return None
        self._seq += 1
        self._latest = pose
        self.poses_published += 1
        for q in self._queues:
            if q.full():
                q.get_nowait()
            q.put_nowait(pose)
        return pose

    async def _run(self) -> None:
        period = 1.0 / self.rate_hz
        next_s = self.clock.monotonic_s()
        while True:
            try:
                self.poll()
            except Exception:  # keep polling; the supervisor sees staleness if this persists
                logger.exception("reading the telemetry pose failed")
            next_s += period
            now = self.clock.monotonic_s()
            if next_s < now - 5 * period:
                next_s = now
            await self.clock.sleep(max(0.0, next_s - now))

    def __repr__(self) -> str:
        return f"TelemetryPoseSource({self.body!r}, {self.rate_hz:g} Hz)"
