"""The autopilot's own pose estimate as a motion-capture source.

:class:`TelemetryPoseSource` turns a :class:`~flightkit.link.base.VehicleLink`'s local
position and attitude telemetry into :class:`~flightkit.mocap.base.MocapPose` values, so the
flight runner (which takes any :class:`~flightkit.mocap.base.MocapSource`) can fly on what the
autopilot believes instead of on mocap: with the autopilot fusing visual odometry, that is a
flight on the estimate alone ("closed loop").

Frames: the telemetry is measured in the autopilot's local frame (expressed ENU by the link,
``frame_id`` :data:`AUTOPILOT_LOCAL_FRAME_ID`), which maps into the world through
``T_world_local``. When the autopilot fuses an external pose given in the world frame (vision
position *and* yaw), its local frame *is* the world frame and ``T_world_local`` is the
identity (the default). Fly with the controller in ``local_ned`` output mode then: the
setpoints are in the same frame as the feedback.

Timing: the source polls ``link.telemetry`` at ``rate_hz`` of clock time and hands out a pose
whenever the telemetry snapshot has changed. ``received_s`` is the clock time of the newest
telemetry message (``Telemetry.stamp_s``), so a silent link shows as stale mocap to the
supervisor; ``stamp_ns`` is the clock's ``time_ns`` when the snapshot was read.

With ``repeat=True`` it hands out the latest snapshot at every poll instead, stamped and
received at the poll: what a bridge republishing the autopilot's estimate on the bus at a fixed
rate delivers (a zero-order hold of the telemetry, as old as the telemetry rate and the link
make it, that looks fresh). A dead link still shows: its poses turn invalid with the heartbeat.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import math

import numpy as np

from flightkit.clock import Clock
from flightkit.errors import MocapError
from flightkit.frames import Transform, WorldFrames
from flightkit.link.base import Telemetry, VehicleLink
from flightkit.mocap.base import MocapPose, MocapSample
from flightkit.mocap.source import WorldFrameSource

__all__ = ["AUTOPILOT_LOCAL_FRAME_ID", "TelemetryPoseSource", "pose_from_telemetry"]

logger = logging.getLogger(__name__)

AUTOPILOT_LOCAL_FRAME_ID = "autopilot_local"
"""``frame_id`` of the autopilot's local frame (its LOCAL_POSITION_NED origin, expressed ENU)."""


def pose_from_telemetry(
    tel: Telemetry, body: str, *, stamp_ns: int, seq: int = 0, max_heartbeat_age_s: float = 2.0
) -> MocapSample | None:
    """The body pose a telemetry snapshot describes, in the autopilot's local frame.

    ``T_local_body`` is built from the local ENU position and the FLU-in-ENU attitude quaternion.

    Returns:
        None when the snapshot has no position yet (NaN); a sample with ``valid=False`` when
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
    return MocapSample(int(stamp_ns), body, AUTOPILOT_LOCAL_FRAME_ID, T_local_body, valid, seq, float(tel.stamp_s))


class TelemetryPoseSource(WorldFrameSource):
    """A :class:`~flightkit.mocap.base.MocapSource` of one body: the autopilot's estimate.

    Args:
        link: a connected vehicle link (its telemetry is read, nothing is sent).
        clock: the flight's clock (polling, stamps).
        body: the name the poses carry (give the name the runner flies, e.g. ``mocap.body``).
        rate_hz: polling rate (the link's LOCAL_POSITION_NED stream is 50 Hz by default).
        T_world_local: the autopilot's local frame in the world (identity when it fuses a
            world-frame vision pose with yaw).
        max_heartbeat_age_s: poses are flagged invalid when the heartbeat is older.
        repeat: hand out the latest estimate at every poll, stamped then (a fixed-rate bridge).

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
        repeat: bool = False,
    ) -> None:
        if not (math.isfinite(rate_hz) and 1.0 <= rate_hz <= 1000.0):
            raise MocapError(f"telemetry pose rate {rate_hz!r} Hz is outside 1-1000 Hz; pick e.g. 50")
        frames = WorldFrames(extra=((AUTOPILOT_LOCAL_FRAME_ID, T_world_local or Transform.identity()),))
        super().__init__(clock, frames, name=f"autopilot estimate of {body!r}", fresh_within_s=max(0.5, 5.0 / rate_hz))
        self.link = link
        self.body = body
        self.rate_hz = float(rate_hz)
        self.max_heartbeat_age_s = float(max_heartbeat_age_s)
        self.repeat = repeat
        self._last_key: tuple[object, ...] | None = None
        self._seq = 0
        self._task: asyncio.Task[None] | None = None
        self.poses_published = 0

    async def _open(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._run(), name=f"telemetry-pose-{self.body}")

    async def _close(self) -> None:
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    def poll(self) -> MocapPose | None:
        """Read the telemetry once; returns the new pose if the snapshot changed (always with
        ``repeat``; also hands it to :meth:`poses` consumers), else None. The polling task calls
        this at ``rate_hz``."""
        tel = self.link.telemetry
        key = (tel.stamp_s, tel.pos_local_enu_m, tel.R_local_body_quat_wxyz)
        if key == self._last_key and not self.repeat:
            return None
        self._last_key = key
        sample = pose_from_telemetry(
            tel, self.body, stamp_ns=self.clock.time_ns(), seq=self._seq + 1,
            max_heartbeat_age_s=self.max_heartbeat_age_s,
        )
        if sample is None:
            return None
        if self.repeat:
            sample = dataclasses.replace(sample, received_s=self.clock.monotonic_s())
        self._seq += 1
        self.poses_published += 1
        return self._ingest(sample)

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
