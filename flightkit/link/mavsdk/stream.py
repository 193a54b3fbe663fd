"""The background velocity-setpoint stream of the MAVSDK backend.

:class:`SetpointStream` runs one asyncio task while a stream is on: it hands the current
setpoint to MAVSDK's offboard plugin at absolute deadlines of the injected
:class:`~flightkit.clock.Clock`, and replaces it by an explicit zero-velocity stop when the
caller has been silent for ``link.setpoint_timeout_s``. :func:`send_offboard_setpoint` is the
one place a flightkit setpoint becomes an offboard call.

Offboard semantics that differ from the pymavlink backend, all because MAVSDK re-sends the
last offboard setpoint at 20 Hz by itself while offboard is active:

* stopping the stream (:meth:`~flightkit.link.mavsdk.link.MavsdkLink.stop_setpoint_stream`)
  sends a zero setpoint and then, if offboard is active, calls ``offboard.stop()``, which puts
  the vehicle in Hold. Otherwise MAVSDK would keep the vehicle in OFFBOARD on a repeated zero
  setpoint for ever.
* World-frame setpoints with a yaw *rate* (and the default "hold heading") are rotated into
  the yaw-aligned body frame with the latest attitude and sent as ``VelocityBodyYawspeed``,
  because MAVSDK's ``VelocityNedYaw`` only takes an absolute yaw. Body-frame setpoints with an
  absolute yaw are rotated into NED the same way and sent as ``VelocityNedYaw``
  (:func:`~flightkit.link.mavsdk.encoding.setpoint_to_mavsdk`).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from typing import Any

from flightkit.clock import Clock
from flightkit.config import LinkConfig
from flightkit.errors import LinkError
from flightkit.link.base import VelocitySetpoint
from flightkit.link.mavlink.encoding import check_hard_limits
from flightkit.link.mavsdk.encoding import setpoint_to_mavsdk

__all__ = ["SetpointStream", "send_offboard_setpoint"]

logger = logging.getLogger(__name__)


async def send_offboard_setpoint(offboard: Any, sp: VelocitySetpoint, yaw_local_rad: float) -> None:
    """Hand one setpoint to MAVSDK's offboard plugin (``yaw_local_rad``: current ENU heading).

    Raises:
        LinkError: MAVSDK refused it, or the frame has to change and the heading is unknown.
    """
    from mavsdk.asyncio.plugins.offboard import (
        AccelerationNed,
        OffboardError,
        PositionNedYaw,
        VelocityBodyYawspeed,
        VelocityNedYaw,
    )

    cmd = setpoint_to_mavsdk(sp, yaw_local_rad)
    try:
        if cmd.kind == "pva":
            await offboard.set_position_velocity_acceleration_ned(
                PositionNedYaw(*cmd.pos_ned_m, cmd.yaw_deg),
                VelocityNedYaw(cmd.a, cmd.b, cmd.c, cmd.yaw_deg),
                AccelerationNed(*cmd.accel_ned_m_s2),
            )
        elif cmd.kind == "ned":
            await offboard.set_velocity_ned(VelocityNedYaw(cmd.a, cmd.b, cmd.c, cmd.yaw_deg))
        else:
            await offboard.set_velocity_body(VelocityBodyYawspeed(cmd.a, cmd.b, cmd.c, cmd.yawspeed_deg_s))
    except OffboardError as exc:
        raise LinkError(f"MAVSDK refused the setpoint: {exc.result.name}") from exc


class SetpointStream:
    """The current setpoint and the task that keeps sending it.

    Args:
        cfg: link settings (``setpoint_rate_hz`` default, ``setpoint_timeout_s``).
        clock: time source of the stream's period and of the silence timeout.
        send: hands one setpoint to the autopilot; raises LinkError when that fails.
    """

    def __init__(
        self, cfg: LinkConfig, clock: Clock, send: Callable[[VelocitySetpoint], Awaitable[None]]
    ) -> None:
        self._cfg = cfg
        self._clock = clock
        self._send = send
        self.setpoint = VelocitySetpoint.zero()
        self._setpoint_stamp_s = 0.0
        self._task: asyncio.Task[None] | None = None
        self.started_s = 0.0
        self._rate_hz = cfg.setpoint_rate_hz
        self._stopped_for_silence = False
        self._send_failures = 0
        self.sent = 0

    @property
    def running(self) -> bool:
        """True while the stream task runs."""
        return self._task is not None

    async def send(self, sp: VelocitySetpoint) -> None:
        """Send one setpoint now and count it (raises LinkError as ``send`` does)."""
        await self._send(sp)
        self.sent += 1

    async def start(self, rate_hz: float) -> None:
        """Set the rate; if not running, send one zero setpoint and start the task."""
        self._rate_hz = rate_hz
        if self._task is not None:
            return
        self.setpoint = VelocitySetpoint.zero()
        self._setpoint_stamp_s = self.started_s = self._clock.monotonic_s()
        self._stopped_for_silence = False
        await self.send(self.setpoint)
        self._task = asyncio.create_task(self._loop(), name="mavsdk-setpoints")
        logger.info("setpoint stream started at %.1f Hz", rate_hz)

    async def stop(self) -> bool:
        """Cancel the task and wait for it; False if it was not running."""
        task, self._task = self._task, None
        if task is None:
            return False
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        return True

    def take_task(self) -> asyncio.Task[None] | None:
        """Hand over the running task (to cancel it with others); the stream is then stopped."""
        task, self._task = self._task, None
        return task

    def set(self, setpoint: VelocitySetpoint) -> None:
        """Replace the streamed setpoint; returns immediately.

        Raises:
            SetpointError: beyond the hard safety limits of the MAVLink backends.
            LinkError: the stream is not running.
        """
        check_hard_limits(setpoint)
        if self._task is None:
            raise LinkError("the setpoint stream is not running; call start_setpoint_stream() first")
        self.setpoint = setpoint
        self._setpoint_stamp_s = self._clock.monotonic_s()
        if self._stopped_for_silence:
            self._stopped_for_silence = False
            logger.info("setpoints resumed")

    async def _loop(self) -> None:
        clock = self._clock
        next_s = clock.monotonic_s()
        while True:
            period = 1.0 / self._rate_hz
            now = clock.monotonic_s()
            sp = self.setpoint
            if now - self._setpoint_stamp_s > self._cfg.setpoint_timeout_s:
                if not self._stopped_for_silence:
                    self._stopped_for_silence = True
                    logger.warning(
                        "no new setpoint for %.2f s (limit %.2f s); streaming an explicit stop",
                        now - self._setpoint_stamp_s,
                        self._cfg.setpoint_timeout_s,
                    )
                sp = VelocitySetpoint.zero(sp.frame)
            try:
                await self.send(sp)
            except LinkError as exc:
                self._send_failures += 1
                if self._send_failures in (1, 10, 100) or self._send_failures % 1000 == 0:
                    logger.warning("setpoint not sent (%d failures so far): %s", self._send_failures, exc)
            next_s += period
            delay = next_s - clock.monotonic_s()
            if delay < -period:  # fell behind (a stall); do not burst to catch up
                next_s = clock.monotonic_s()
                delay = 0.0
            await clock.sleep(max(0.0, delay))
