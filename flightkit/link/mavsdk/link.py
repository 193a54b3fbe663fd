"""MavsdkLink: the MAVSDK :class:`~flightkit.link.base.VehicleLink`, its connection and its calls.

:class:`MavsdkLink` drives an autopilot through MAVSDK 4.x (the native binding, asyncio API
under :mod:`mavsdk.asyncio`): the action plugin arms, takes off, lands and switches to Hold;
the offboard plugin carries velocity setpoints
(:class:`~flightkit.link.mavsdk.stream.SetpointStream`); the telemetry plugin keeps a state
snapshot current (:class:`~flightkit.link.mavsdk.telemetry.VehicleState`); the mocap plugin
forwards external poses; and ``mavlink_direct`` covers what the plugins cannot express (the raw
HEARTBEAT with its ``custom_mode``, and MAV_CMD_DO_SET_MODE for modes MAVSDK has no call for,
such as ArduPilot BRAKE or PX4 POSCTL; :class:`~flightkit.link.mavsdk.commands.CommandChannel`).

Frames: everything above this package speaks ENU/FLU; conversions to NED/FRD happen inside
it, through :mod:`flightkit.frames`.

Time: MAVSDK runs on wall time inside (its command retries, its 3 s connection timeout, its
20 Hz offboard re-send). This backend uses the injected :class:`~flightkit.clock.Clock` for
its own loops (setpoint stream, ``wait_for``) and wall time for MAVSDK's calls, so it works
with :class:`~flightkit.clock.WallClock` and with :class:`~flightkit.clock.SimClock` at
speeds near 1 (tests use 1-2). It cannot run under :class:`~flightkit.clock.LockstepClock`.

Offboard semantics differ from the pymavlink backend's; see :mod:`flightkit.link.mavsdk.stream`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections.abc import Callable, Sequence
from typing import Any

from flightkit.clock import Clock
from flightkit.config import Autopilot, LinkConfig
from flightkit.errors import (
    CommandRejected,
    ConfigError,
    LinkError,
    LinkTimeout,
    SetpointError,
)
from flightkit.link.base import (
    ExternalPose,
    ExternalPoseKind,
    FlightMode,
    LinkLifetime,
    Telemetry,
    VehicleInfo,
    VelocitySetpoint,
    offboard_mode_for,
)
from flightkit.link.mavsdk.commands import CommandChannel
from flightkit.link.mavsdk.connection import MavsdkConnection
from flightkit.link.mavsdk.encoding import external_pose_to_ned, mavsdk_url, pose_covariance_upper
from flightkit.link.mavsdk.stream import SetpointStream, send_offboard_setpoint
from flightkit.link.mavsdk.telemetry import VehicleState
from flightkit.link.modes import autopilot_from_heartbeat, resolve_mode

__all__ = ["MavsdkLink"]

logger = logging.getLogger(__name__)

# PX4 wants a second of setpoints before it accepts OFFBOARD (FACTS); a quarter second more covers the
# stream period and the hop through MAVSDK.
_PX4_OFFBOARD_WARMUP_S = 1.25
# ArduPilot refuses NAV_TAKEOFF until its EKF has a position; retry this long (clock seconds) at least.
_APM_TAKEOFF_RETRY_S = 5.0


class MavsdkLink(LinkLifetime):
    """A :class:`~flightkit.link.base.VehicleLink` over MAVSDK.

    Args:
        cfg: link settings (url, timeouts, setpoint rate, our system/component ids).
        autopilot: the firmware we expect (PX4 or ArduPilot); the heartbeat must agree.
        clock: time source for the setpoint stream and waits (wall time or SimClock near 1x).

    Use as ``async with MavsdkLink(cfg, autopilot, clock) as link:``.
    """

    def __init__(self, cfg: LinkConfig, autopilot: Autopilot, clock: Clock) -> None:
        self._cfg = cfg
        self._autopilot = autopilot
        self._clock = clock
        self._url = mavsdk_url(cfg.url, cfg.baud)  # fail fast on a bad string
        if cfg.signing_key_hex:
            raise ConfigError(
                "<link>",
                "link.signing_key_hex",
                "the MAVSDK backend cannot sign MAVLink 2 messages",
                "use link.backend = 'pymavlink' for a signed link, or clear the key",
            )
        self._conn = MavsdkConnection(cfg, self._url)
        self._state = VehicleState(autopilot, clock)
        self._commands = CommandChannel(cfg, self._conn, self._state)
        self._stream = SetpointStream(cfg, clock, self._send_setpoint)
        self._info: VehicleInfo | None = None
        self._closed = False

    # ------------------------------------------------------------------ properties

    @property
    def info(self) -> VehicleInfo:
        """The connected autopilot (raises LinkError before connect)."""
        if self._info is None:
            raise LinkError("not connected; call connect() or use 'async with' first")
        return self._info

    @property
    def telemetry(self) -> Telemetry:
        """Latest state; returns immediately."""
        return self._state.telemetry()

    @property
    def statustext(self) -> tuple[str, ...]:
        """Recent STATUSTEXT lines from the autopilot, oldest first."""
        return tuple(t for _, t in self._state.texts)

    @property
    def clock(self) -> Clock:
        """The clock this link times its stream and waits with."""
        return self._clock

    @property
    def streaming(self) -> bool:
        """True while the setpoint stream runs."""
        return self._stream.running

    @property
    def setpoints_sent(self) -> int:
        """How many setpoints the stream has handed to MAVSDK (for diagnostics and tests)."""
        return self._stream.sent

    # ------------------------------------------------------------------ lifetime

    async def connect(self) -> VehicleInfo:
        """Open the connection and wait for the autopilot's heartbeat.

        Blocks until the autopilot's HEARTBEAT has been seen and the telemetry subscriptions
        are running, or ``link.heartbeat_timeout_s`` (wall seconds) has passed.

        Raises:
            EndpointError: MAVSDK cannot open the connection (bad URL, port in use, no device).
            LinkTimeout: no autopilot heartbeat in time.
            LinkError: the heartbeat names a different autopilot than the config.
        """
        if self._info is not None:
            return self._info
        if self._closed:
            raise LinkError("this link was closed; create a new MavsdkLink to reconnect")
        try:
            sysid = await self._conn.open()
            timeout_s = self._cfg.heartbeat_timeout_s
            loop = asyncio.get_running_loop()
            first_hb: asyncio.Future[dict[str, Any]] = loop.create_future()
            self._state.start(self._conn.direct, self._conn.telemetry, sysid, first_hb)
            try:
                hb = await asyncio.wait_for(first_hb, timeout=max(timeout_s, 1.5))
            except TimeoutError:
                raise LinkTimeout(
                    f"MAVSDK found system {sysid} on {self._url} but no HEARTBEAT from its autopilot "
                    f"reached us within {timeout_s:.1f} s; check the link",
                    what="HEARTBEAT",
                    timeout_s=timeout_s,
                ) from None
            if self._cfg.system_id and sysid != self._cfg.system_id:
                raise LinkError(
                    f"the autopilot on {self._url} is system {sysid}, but link.system_id says "
                    f"{self._cfg.system_id}; MAVSDK drives the first system it finds, so give each "
                    "vehicle its own connection (or use backend = 'pymavlink', which picks by system id)"
                )
            seen = autopilot_from_heartbeat(int(hb.get("autopilot", 0)))
            if seen is not None and seen is not self._autopilot:
                raise LinkError(
                    f"the autopilot on {self._url} is {seen.value}, but the config says "
                    f"{self._autopilot.value}; set vehicle.autopilot to match"
                )
            self._info = VehicleInfo(
                system_id=sysid,
                component_id=int(hb.get("_component_id", 1)),
                autopilot=self._autopilot,
                vehicle_type=int(hb.get("type", 0)),
                our_system_id=self._cfg.source_system,
            )
        except BaseException:
            await self._teardown()
            raise
        logger.info(
            "connected to %s system %d (MAV_TYPE %d) via MAVSDK on %s",
            self._autopilot.value,
            self._info.system_id,
            self._info.vehicle_type,
            self._url,
        )
        return self._info

    async def close(self) -> None:
        """Stop the setpoint stream, cancel the telemetry tasks and close MAVSDK; idempotent."""
        if self._closed:
            return
        self._closed = True
        if self._stream.running and self._info is not None:
            with contextlib.suppress(LinkError):
                await self.stop_setpoint_stream()
        await self._teardown()
        if self._info is not None:
            logger.info("closed MAVSDK link to %s", self._url)

    async def _teardown(self) -> None:
        tasks = self._state.take_tasks()
        stream_task = self._stream.take_task()
        if stream_task is not None:
            tasks.append(stream_task)
        for t in tasks:
            t.cancel()
        if tasks:
            await asyncio.gather(*tasks, return_exceptions=True)
        await self._conn.close()

    # ------------------------------------------------------------------ helpers

    def _require(self) -> None:
        if self._info is None or not self._conn.is_open:
            raise LinkError("not connected; call connect() or use 'async with' first")

    async def _wait_state(
        self, predicate: Callable[[Telemetry], bool], timeout_s: float, what: str
    ) -> Telemetry:
        return await self._state.wait_for(predicate, timeout_s, what)

    # ------------------------------------------------------------------ commands

    async def arm(self) -> None:
        """Arm; returns when the heartbeat shows armed.

        Raises:
            CommandRejected: the autopilot refused (``result`` is MAVSDK's ActionResult name,
                ``statustext`` the autopilot's explanation if it sent one).
            LinkTimeout: no answer, or the heartbeat did not show armed in time.
        """
        self._require()
        if self._state.armed:
            return
        await self._commands.action(
            "arm", self._conn.action.arm, hint="check the pre-arm conditions the autopilot reported"
        )
        await self._wait_state(lambda t: t.armed, self._cfg.command_timeout_s, "heartbeat to show armed")

    async def disarm(self, force: bool = False) -> None:
        """Disarm; returns when the heartbeat shows disarmed. ``force`` disarms in the air (kill)."""
        self._require()
        if not self._state.armed:
            return
        if force:
            await self._commands.action("kill", self._conn.action.kill)
        else:
            await self._commands.action(
                "disarm", self._conn.action.disarm, hint="land first, or pass force=True to kill the motors"
            )
        await self._wait_state(
            lambda t: not t.armed, self._cfg.command_timeout_s, "heartbeat to show disarmed"
        )

    async def set_mode(self, mode: FlightMode) -> None:
        """Switch flight mode; returns when the heartbeat shows it.

        OFFBOARD (PX4) and GUIDED (ArduPilot) go through MAVSDK's offboard plugin, which needs
        the setpoint stream running (start it first); ArduPilot GUIDED without a stream is set
        with MAV_CMD_DO_SET_MODE. HOLD on PX4 uses ``action.hold()``, LAND ``action.land()``,
        RTL ``action.return_to_launch()``; every other mode of the firmware's table
        (:mod:`flightkit.link.modes`) is set with MAV_CMD_DO_SET_MODE through ``mavlink_direct``.

        Raises:
            LinkError: the firmware has no such mode, or OFFBOARD was asked without a stream.
            CommandRejected: the autopilot refused the switch.
            LinkTimeout: no answer, or the heartbeat did not show the mode in time.
        """
        self._require()
        ap = self._autopilot
        if mode is FlightMode.OFFBOARD and ap is Autopilot.ARDUPILOT:
            mode = FlightMode.GUIDED
        if mode is FlightMode.GUIDED and ap is Autopilot.PX4:
            mode = FlightMode.OFFBOARD
        target = resolve_mode(ap, mode)
        if self._state.mode is target:
            return
        action = self._conn.action
        if target is offboard_mode_for(ap) and (self._stream.running or ap is Autopilot.PX4):
            await self._start_offboard()
        elif target is FlightMode.HOLD and ap is Autopilot.PX4:
            await self._commands.action("hold", action.hold)
        elif target is FlightMode.LAND:
            await self._commands.action("land", action.land)
        elif target is FlightMode.RTL:
            await self._commands.action("return_to_launch", action.return_to_launch)
        else:
            await self._commands.do_set_mode(ap, self.info, target)
        await self._wait_state(
            lambda t: t.mode is target, self._cfg.command_timeout_s, f"heartbeat to show mode {target.value}"
        )

    async def _start_offboard(self) -> None:
        if not self._stream.running:
            raise LinkError(
                f"{offboard_mode_for(self._autopilot).value} needs setpoints streaming first; "
                "call start_setpoint_stream() before set_mode()"
            )
        if self._autopilot is Autopilot.PX4:
            warm_s = _PX4_OFFBOARD_WARMUP_S - (self._clock.monotonic_s() - self._stream.started_s)
            if warm_s > 0:
                await self._clock.sleep(warm_s)
        await self._commands.start_offboard()

    async def takeoff(self, altitude_m: float) -> None:
        """Command a take-off to ``altitude_m`` above home; returns when acknowledged.

        The vehicle must be armed. Uses ``action.set_takeoff_altitude`` (on PX4 this writes
        MIS_TAKEOFF_ALT, and MAVSDK's NAV_TAKEOFF leaves the altitude to it) and then
        ``action.takeoff``. On ArduPilot MAVSDK first switches to GUIDED and puts the altitude
        in NAV_TAKEOFF; a refusal is retried while the EKF is not ready, for up to
        max(5 s, ``link.command_timeout_s``). Wait for the altitude with :meth:`wait_for`.

        Raises:
            SetpointError: altitude outside 0.1-100 m.
            LinkError: not armed.
            CommandRejected, LinkTimeout: as for :meth:`arm`.
        """
        if not (math.isfinite(altitude_m) and 0.1 <= altitude_m <= 100.0):
            raise SetpointError(
                f"take-off altitude {altitude_m!r} m is outside 0.1-100 m; give a height above home"
            )
        self._require()
        if not self._state.armed:
            raise LinkError("the vehicle is not armed; call arm() before takeoff()")
        action = self._conn.action
        await self._commands.action(
            "set_takeoff_altitude",
            lambda: action.set_takeoff_altitude(float(altitude_m)),
            hint="the autopilot did not accept the take-off altitude parameter",
        )
        retry_s = max(_APM_TAKEOFF_RETRY_S, self._cfg.command_timeout_s)
        start = self._clock.monotonic_s()
        while True:
            try:
                await self._commands.action(
                    "takeoff", action.takeoff, hint="check the autopilot has a position estimate"
                )
                break
            except CommandRejected:
                if self._autopilot is not Autopilot.ARDUPILOT or self._clock.monotonic_s() - start >= retry_s:
                    raise
                logger.debug("take-off refused; retrying (ArduPilot's EKF may not have a position yet)")
                await self._clock.sleep(0.5)
        logger.info("take-off to %.2f m commanded", altitude_m)

    async def read_params(self, names: Sequence[str]) -> dict[str, float]:
        """Read parameters by name through MAVSDK's param plugin (which decodes PX4's bytewise
        integers); returns those that could be read, integers as whole floats."""
        self._require()
        return await self._commands.read_params(names)

    async def land(self) -> None:
        """Land at the current position (``action.land``); returns when the heartbeat shows LAND."""
        await self.set_mode(FlightMode.LAND)

    # ------------------------------------------------------------------ setpoints

    async def start_setpoint_stream(self, rate_hz: float | None = None) -> None:
        """Start streaming the current setpoint (initially zero velocity) in the background.

        Sends one setpoint before returning (MAVSDK's ``offboard.start`` needs one), then
        repeats at ``rate_hz`` (default ``link.setpoint_rate_hz``) of clock time. If the caller
        does not call :meth:`set_velocity` for ``link.setpoint_timeout_s`` the stream sends an
        explicit stop instead of the stale command. Idempotent (a second call changes the rate).
        """
        self._require()
        rate = float(rate_hz) if rate_hz is not None else self._cfg.setpoint_rate_hz
        if not (math.isfinite(rate) and 1.0 <= rate <= 1000.0):
            raise SetpointError(f"setpoint rate {rate_hz!r} Hz is outside 1-1000 Hz")
        await self._stream.start(rate)

    async def stop_setpoint_stream(self) -> None:
        """Stop streaming: send one zero setpoint and, if offboard is active, leave it (-> Hold).

        Idempotent. See :mod:`flightkit.link.mavsdk.stream` for why this leaves offboard.
        """
        if not await self._stream.stop():
            return
        offboard = self._conn.offboard
        if offboard is None:
            return
        with contextlib.suppress(LinkError):
            await self._stream.send(VelocitySetpoint.zero(self._stream.setpoint.frame))
        from mavsdk.asyncio.plugins.offboard import OffboardError

        try:
            active = await self._commands.call("offboard.is_active", offboard.is_active())
            if active:
                await self._commands.call("offboard.stop", offboard.stop())
                logger.info("offboard stopped (vehicle holds position)")
        except (OffboardError, LinkTimeout) as exc:
            logger.warning("could not stop MAVSDK offboard cleanly: %s", exc)
        logger.info("setpoint stream stopped")

    def set_velocity(self, setpoint: VelocitySetpoint, *, send_now: bool = False) -> None:
        """Replace the streamed setpoint; returns immediately (``send_now`` has no effect: MAVSDK
        sends on its own schedule).

        Raises:
            SetpointError: beyond the hard safety limits of the MAVLink backends.
            LinkError: the stream is not running.
        """
        self._stream.set(setpoint)

    async def _send_setpoint(self, sp: VelocitySetpoint) -> None:
        await send_offboard_setpoint(self._conn.offboard, sp, self._state.yaw)

    # ------------------------------------------------------------------ external pose

    async def send_vision_pose(
        self, pose: ExternalPose, kind: ExternalPoseKind = ExternalPoseKind.VISION_POSITION_ESTIMATE
    ) -> None:
        """Send an external pose to the autopilot's estimator through the mocap plugin; returns once queued.

        The FLU-in-ENU pose becomes FRD-in-NED; the covariance is diagonal from
        ``pos_std_m`` / ``rot_std_rad``. ``stamp_ns`` is sent as ``time_usec``.

        Raises:
            LinkError: MAVSDK refused the message (not connected, bad data).
        """
        self._require()
        from mavsdk.asyncio.plugins.mocap import (
            AngleBody,
            Covariance,
            MocapError,
            Odometry,
            PositionBody,
            Quaternion,
            SpeedBody,
            VisionPositionEstimate,
        )
        from mavsdk.plugins.mocap import AngularVelocityBody

        mocap = self._conn.mocap
        ned = external_pose_to_ned(pose)
        cov = Covariance(pose_covariance_upper(pose.pos_std_m, pose.rot_std_rad))
        time_usec = max(0, int(pose.stamp_ns) // 1000)
        position = PositionBody(*ned.pos_ned_m)
        try:
            if kind is ExternalPoseKind.VISION_POSITION_ESTIMATE:
                msg = VisionPositionEstimate(
                    time_usec=time_usec,
                    position_body=position,
                    angle_body=AngleBody(*ned.rpy_ned_frd_rad),
                    pose_covariance=cov,
                    reset_counter=int(pose.reset_counter),
                )
                await self._commands.call(
                    "mocap.set_vision_position_estimate", mocap.set_vision_position_estimate(msg)
                )
            else:
                q = ned.quat_ned_frd_wxyz
                speed = SpeedBody(*ned.vel_frd_m_s)
                vel_cov = Covariance([math.nan])  # velocity uncertainty unknown
                odo = Odometry(
                    time_usec=time_usec,
                    frame_id=Odometry.MavFrame.MOCAP_NED,
                    position_body=position,
                    q=Quaternion(*q),
                    speed_body=speed,
                    angular_velocity_body=AngularVelocityBody(math.nan, math.nan, math.nan),
                    pose_covariance=cov,
                    velocity_covariance=vel_cov,
                    reset_counter=int(pose.reset_counter),
                    estimator_type=Odometry.MavEstimatorType.VISION,
                    quality_percent=int(pose.quality_pct),
                )
                await self._commands.call("mocap.set_odometry", mocap.set_odometry(odo))
        except MocapError as exc:
            raise LinkError(f"MAVSDK refused the external pose ({kind.value}): {exc.result.name}") from exc

    async def set_ekf_origin(self, lat_deg: float, lon_deg: float, alt_m: float) -> None:
        """Set the EKF origin (SET_GPS_GLOBAL_ORIGIN) for a vehicle without GPS; returns once sent."""
        self._require()
        action = self._conn.action
        await self._commands.action(
            "set_gps_global_origin", lambda: action.set_gps_global_origin(lat_deg, lon_deg, alt_m)
        )

    # ------------------------------------------------------------------ waiting

    async def wait_for(self, predicate: object, timeout_s: float, what: str) -> Telemetry:
        """Wait until ``predicate(telemetry)`` is true (checked every 20 ms of clock time).

        Raises:
            LinkTimeout: not true after ``timeout_s`` clock seconds; the message names ``what``
                and the last state.
        """
        if not callable(predicate):
            raise TypeError(f"predicate must be callable, got {predicate!r}")
        return await self._state.wait_for(predicate, timeout_s, what)
