"""MavlinkLink: the pymavlink :class:`~flightkit.link.base.VehicleLink`, its connection and its calls.

Threads and timing:

* one **reader thread** per connection owns the transport's receive side: it parses
  MAVLink (pymavlink's codec, MAVLink 2 with the ArduPilot dialect, a superset of common),
  folds each message into the :class:`~flightkit.link.mavlink.telemetry.VehicleState`,
  sends our HEARTBEAT at 1 Hz, and wakes the coroutines waiting on the state;
* one **setpoint thread** while a setpoint stream runs
  (:class:`~flightkit.link.mavlink.stream.SetpointStream`);
* the asyncio API on top: commands with COMMAND_ACK handling and retries
  (:class:`~flightkit.link.mavlink.commands.CommandChannel`), state waits with timeouts.
  All time comes from the injected :class:`~flightkit.clock.Clock`, so a simulated lab at
  ``SimClock(speed=10)`` flies ten times faster.

Our identity on the link: system id ``link.source_system``, component id
``link.source_component``. The HEARTBEAT type follows the component id: 191-194
(MAV_COMP_ID_ONBOARD_COMPUTER..4) announce MAV_TYPE_ONBOARD_CONTROLLER, any other id
(e.g. 190, MAV_COMP_ID_MISSIONPLANNER) announces MAV_TYPE_GCS. PX4 only sends STATUSTEXT
to a link on which it heard a GCS heartbeat, so pick 190 when refusal texts from PX4
matter more than looking like a companion computer.

Frames: everything above this package is ENU/FLU; NED/FRD appear only in the encoders
(:mod:`flightkit.link.mavlink.encoding`) and the decoders
(:mod:`flightkit.link.mavlink.telemetry`).
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from flightkit.clock import Clock, WallClock
from flightkit.config import Autopilot, LinkConfig
from flightkit.errors import LinkError, LinkTimeout, SetpointError
from flightkit.link.base import (
    ExternalPose,
    ExternalPoseKind,
    FlightMode,
    LinkLifetime,
    Telemetry,
    VehicleInfo,
    VelocitySetpoint,
)
from flightkit.link.endpoints import Endpoint, parse_endpoint
from flightkit.link.mavlink.commands import CommandChannel
from flightkit.link.mavlink.connection import MavlinkConnection
from flightkit.link.mavlink.encoding import (
    FORCE_DISARM_MAGIC,
    MAV_RESULT_ACCEPTED,
    SetpointFields,
    encode_odometry,
    encode_setpoint_message,
    encode_vision_position_estimate,
    heartbeat_type_for_component,
    result_name,
)
from flightkit.link.mavlink.stream import SetpointStream
from flightkit.link.mavlink.telemetry import VehicleState
from flightkit.link.modes import set_mode_params
from flightkit.link.signing import SigningSettings, parse_signing_key

__all__ = ["LinkStats", "MavlinkLink"]

logger = logging.getLogger(__name__)

_PX4_OFFBOARD_WARMUP_S = 1.25  # PX4 wants a second of setpoints before OFFBOARD (plus margin)


@dataclass(frozen=True, slots=True)
class LinkStats:
    """Counters of one link (for status displays, tests and benchmarks)."""

    packets_received: int
    packets_rejected: int  # bad CRC, bad or missing signature
    packets_sent: int
    setpoints_sent: int
    stops_sent: int  # explicit zero-velocity setpoints sent because the caller was silent
    acks_received: int


class MavlinkLink(LinkLifetime):
    """A :class:`~flightkit.link.base.VehicleLink` over pymavlink.

    Args:
        cfg: the ``[link]`` config section.
        autopilot: the firmware named in config (``vehicle.autopilot``); the autopilot's
            HEARTBEAT decides how modes are decoded, and a mismatch is logged.
        clock: time source for every wait, rate and timestamp (WallClock by default).
        target_system: talk only to this MAVLink system id (default: the first autopilot
            whose heartbeat arrives).
        link_id: MAVLink 2 signing link id.
        max_pose_rate_hz: :meth:`send_vision_pose` drops poses that arrive faster than
            this (EKF2 wants 30-50 Hz; mocap gives 100-300 Hz); 0 disables the limit.
        config_path: the config file, for error messages.

    Use as ``async with MavlinkLink(cfg, Autopilot.PX4, clock) as link: ...``.
    """

    def __init__(
        self,
        cfg: LinkConfig,
        autopilot: Autopilot | None = None,
        clock: Clock | None = None,
        *,
        target_system: int | None = None,
        link_id: int = 1,
        max_pose_rate_hz: float = 50.0,
        config_path: str = "<config>",
    ) -> None:
        self._cfg = cfg
        self._expected_autopilot = autopilot
        self._clock: Clock = clock if clock is not None else WallClock()
        self.endpoint: Endpoint = parse_endpoint(cfg.url, cfg.baud)
        key = parse_signing_key(cfg.signing_key_hex, source=config_path)
        signing = SigningSettings(key, link_id) if key is not None else None
        self._max_pose_rate_hz = max_pose_rate_hz

        if target_system is None and cfg.system_id:
            target_system = cfg.system_id
        self._target_system = target_system
        self._state = VehicleState(self._clock, cfg.source_system, target_system, self._pin_autopilot)
        self._conn = MavlinkConnection(
            self.endpoint,
            self._clock,
            cfg.source_system,
            cfg.source_component,
            heartbeat_type_for_component(cfg.source_component),
            signing,
            self._state,
        )
        self._send = self._conn.send
        self._loop: asyncio.AbstractEventLoop | None = None
        self._setpoints = SetpointStream(self._clock, cfg.setpoint_timeout_s, self._send_setpoint)
        self._commands = CommandChannel(
            self._state, self._clock, self._send, self._require_target, cfg.command_timeout_s
        )
        self._t0_s = self._clock.monotonic_s()
        self._last_pose_s = -math.inf
        self._tasks: set[asyncio.Task[None]] = set()
        self._closed = False

    # ------------------------------------------------------------------ properties

    @property
    def info(self) -> VehicleInfo:
        """The connected autopilot; raises LinkError before :meth:`connect`."""
        with self._state.lock:
            info = self._state.info
        if info is None:
            raise LinkError(
                f"not connected to an autopilot on {self.endpoint.url}; call connect() (or use 'async with')"
            )
        return info

    @property
    def telemetry(self) -> Telemetry:
        """Latest vehicle state; returns immediately."""
        return self._state.telemetry()

    @property
    def statustext(self) -> tuple[str, ...]:
        """Recent STATUSTEXT lines from the autopilot (PX4's trailing tab stripped), oldest first."""
        with self._state.lock:
            return tuple(text for _, _, text in self._state.statustext)

    @property
    def stats(self) -> LinkStats:
        s = self._state
        with s.lock:
            rx, rej, acks = s.rx, s.rx_rejected, s.ack_seq
        return LinkStats(
            rx, rej, self._conn.packets_sent, self._setpoints.setpoints_sent, self._setpoints.stops_sent, acks
        )

    @property
    def local_port(self) -> int:
        """Our local UDP/TCP port (0 before connect and for serial)."""
        return self._conn.local_port

    @property
    def streaming(self) -> bool:
        """True while the setpoint stream runs."""
        return self._setpoints.running

    @property
    def clock(self) -> Clock:
        return self._clock

    # ------------------------------------------------------------------ lifetime

    async def connect(self) -> VehicleInfo:
        """Open the endpoint, start the reader thread and wait for the autopilot's HEARTBEAT.

        Blocks until the heartbeat arrives or ``link.heartbeat_timeout_s`` passes, then asks
        for telemetry streams and AUTOPILOT_VERSION in the background.

        Raises:
            EndpointError: the endpoint cannot be opened (port in use, no such device).
            LinkTimeout: no autopilot HEARTBEAT in time.
        """
        if self._closed:
            raise LinkError("this link was closed; create a new MavlinkLink to reconnect")
        if self._conn.opened:
            return self.info
        self._loop = asyncio.get_running_loop()
        await self._conn.open(self._cfg.heartbeat_timeout_s)
        timeout_s = self._cfg.heartbeat_timeout_s
        try:
            info = await self._state.wait_until(
                lambda: self._state.info, timeout_s, lambda: self._no_heartbeat_error(timeout_s)
            )
        except BaseException:
            await self.close()
            raise
        if self._expected_autopilot is not None and info.autopilot is not self._expected_autopilot:
            logger.warning(
                "config says vehicle.autopilot = %r but the heartbeat says %r; decoding modes as %s",
                self._expected_autopilot.value,
                info.autopilot.value,
                info.autopilot.value,
            )
        logger.info(
            "connected to %s autopilot (system %d) on %s",
            info.autopilot.value,
            info.system_id,
            self.endpoint.url,
        )
        self._spawn(self._commands.request_telemetry())
        return info

    def _no_heartbeat_error(self, timeout_s: float) -> LinkTimeout:
        s = self._state
        with s.lock:
            rx, rejected, others = s.rx, s.rx_rejected, s.rx_other_components
            other_systems = sorted(s.other_systems)
        where = self.endpoint.url
        if self.endpoint.listens and self.endpoint.port == 0 and self._conn.opened:
            where += f" (local port {self.local_port})"
        msg = f"no HEARTBEAT on {where} after {timeout_s:.1f} s; is the autopilot/simulator running and link.url right?"
        if other_systems:
            wanted = self._target_system
            msg = (
                f"no HEARTBEAT from system {wanted} on {where} after {timeout_s:.1f} s, but autopilot(s) with "
                f"system id {', '.join(map(str, other_systems))} answered; set link.system_id to the vehicle's "
                "id (its SYSID_THISMAV / MAV_SYS_ID) or check which vehicle is on this link"
            )
        elif rejected:
            msg += f" ({rejected} packets were dropped for a missing or wrong signature: check link.signing_key_hex)"
        elif rx:
            msg += f" ({rx} packets arrived but none was an autopilot heartbeat from component 1; {others} from others)"
        return LinkTimeout(msg, what="HEARTBEAT", timeout_s=timeout_s)

    async def close(self) -> None:
        """Stop the setpoint stream (sending one last zero setpoint), stop the reader and
        close the endpoint. Idempotent; returns when everything has stopped."""
        if self._closed:
            return
        self._closed = True
        await self.stop_setpoint_stream()
        for task in list(self._tasks):
            task.cancel()
        if self._tasks:
            await asyncio.gather(*self._tasks, return_exceptions=True)
        await self._conn.close()
        logger.debug("closed %s", self.endpoint.url)

    def _spawn(self, coro: Any) -> None:
        task: asyncio.Task[None] = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _pin_autopilot(self) -> None:
        """The first autopilot heartbeat arrived: reply to its address only (reader thread)."""
        self._conn.pin_last_sender()

    # ------------------------------------------------------------------ waiting

    async def wait_for(self, predicate: object, timeout_s: float, what: str) -> Telemetry:
        """Wait until ``predicate(telemetry)`` is true (checked on every message).

        Raises:
            LinkTimeout: not true after ``timeout_s`` of clock time; the message names
                ``what`` and the last state.
        """
        if not callable(predicate):
            raise TypeError("predicate must be a callable taking a Telemetry")

        def probe() -> Telemetry | None:
            tel = self.telemetry
            return tel if predicate(tel) else None

        def timeout() -> LinkTimeout:
            tel = self.telemetry
            pos = ", ".join(f"{x:.2f}" for x in tel.pos_local_enu_m)
            return LinkTimeout(
                f"{what} not reached after {timeout_s:.1f} s (mode {tel.mode.value}, armed {tel.armed}, "
                f"position ENU [{pos}] m, heartbeat age {tel.heartbeat_age_s:.1f} s)",
                what=what,
                timeout_s=timeout_s,
            )

        return await self._state.wait_until(probe, timeout_s, timeout)

    # ------------------------------------------------------------------ commands

    def _require_target(self) -> tuple[int, int]:
        with self._state.lock:
            target = self._state.target
        if target is None or not self._conn.opened or self._closed:
            raise LinkError(
                f"not connected to an autopilot on {self.endpoint.url}; call connect() (or use 'async with')"
            )
        return target

    async def command_long(
        self,
        command: int,
        params: tuple[float, ...] = (),
        *,
        attempts: int = 3,
        timeout_s: float | None = None,
    ) -> int:
        """Send COMMAND_LONG and return the final MAV_RESULT of its COMMAND_ACK (retries,
        IN_PROGRESS and errors as :meth:`CommandChannel.command_long
        <flightkit.link.mavlink.commands.CommandChannel.command_long>`)."""
        return await self._commands.command_long(command, params, attempts=attempts, timeout_s=timeout_s)

    async def read_params(self, names: Sequence[str]) -> dict[str, float]:
        """Read parameters by name (PARAM_REQUEST_READ, asked twice within ``link.command_timeout_s``);
        returns those that arrived, integers as whole floats (PX4's bytewise encoding decoded)."""
        self._require_target()
        return await self._commands.read_params(names, bytewise=self.info.autopilot is Autopilot.PX4)

    async def _wait_state(
        self, check: Callable[[Telemetry], bool], what: str, timeout_s: float | None = None
    ) -> None:
        await self.wait_for(check, self._cfg.command_timeout_s if timeout_s is None else timeout_s, what)

    async def arm(self) -> None:
        """Arm; returns when the HEARTBEAT shows the vehicle armed.

        Raises:
            CommandRejected: the autopilot refused (result name and its STATUSTEXT reasons).
            LinkTimeout: no ACK, or the armed flag did not appear in time.
        """
        self._require_target()
        if self.telemetry.armed:
            return
        await self._commands.checked(
            mavlink2.MAV_CMD_COMPONENT_ARM_DISARM,
            (1.0,),
            hint="check the pre-arm conditions the autopilot reports (position estimate, offboard signal, safety)",
        )
        await self._wait_state(
            lambda t: t.armed, "armed flag in HEARTBEAT after the autopilot accepted arming"
        )

    async def disarm(self, force: bool = False) -> None:
        """Disarm (``force``: even in the air, motors stop); returns when the HEARTBEAT shows disarmed."""
        self._require_target()
        if not self.telemetry.armed:
            return
        await self._commands.checked(
            mavlink2.MAV_CMD_COMPONENT_ARM_DISARM,
            (0.0, FORCE_DISARM_MAGIC if force else 0.0),
            hint="autopilots refuse to disarm in flight; land first or use force=True in an emergency",
        )
        await self._wait_state(lambda t: not t.armed, "disarmed flag in HEARTBEAT")

    async def set_mode(self, mode: FlightMode) -> None:
        """Switch the flight mode via MAV_CMD_DO_SET_MODE; returns when the HEARTBEAT shows it.

        PX4 OFFBOARD needs setpoints flowing first: the setpoint stream must be running, and
        this waits until it has run for a second (as PX4 wants) before asking.

        Raises:
            LinkError: the firmware has no such mode, or OFFBOARD without a setpoint stream.
            CommandRejected: the autopilot refused.
            LinkTimeout: no ACK, or the heartbeat did not show the mode in time.
        """
        self._require_target()
        autopilot = self.info.autopilot
        cmd = set_mode_params(autopilot, mode)
        if autopilot is Autopilot.PX4 and cmd.mode is FlightMode.OFFBOARD:
            started_s = self._setpoints.started_s
            if started_s is None:
                raise LinkError(
                    "PX4 refuses OFFBOARD without a setpoint stream; call start_setpoint_stream() before "
                    "set_mode(FlightMode.OFFBOARD)"
                )
            warm_s = _PX4_OFFBOARD_WARMUP_S - (self._clock.monotonic_s() - started_s)
            if warm_s > 0:
                await self._clock.sleep(warm_s)
        if self.telemetry.custom_mode == cmd.custom_mode:
            return
        await self._commands.checked(
            mavlink2.MAV_CMD_DO_SET_MODE, cmd.params, hint=f"the autopilot cannot enter {cmd.mode.value} now"
        )
        await self._wait_state(
            lambda t: t.custom_mode == cmd.custom_mode, f"mode {cmd.mode.value} in HEARTBEAT"
        )

    async def takeoff(self, altitude_m: float) -> None:
        """Take off to ``altitude_m`` above home; returns when the autopilot accepted it.

        The vehicle must be armed. PX4: MAV_CMD_NAV_TAKEOFF with NaN latitude/longitude (here)
        and an AMSL altitude computed from home (HOME_POSITION or GLOBAL_POSITION_INT); the
        vehicle enters AUTO.TAKEOFF. ArduPilot: switches to GUIDED if needed, then
        MAV_CMD_NAV_TAKEOFF with the altitude relative to home in param7, retried while the
        EKF is not ready ("Need Position Estimate") for up to max(5 s, command timeout).
        Wait for the altitude with :meth:`wait_for`.

        Raises:
            SetpointError: altitude outside 0.1-100 m.
            LinkError: not armed, or (PX4) no home altitude known (set the EKF origin).
            CommandRejected, LinkTimeout: as for every command.
        """
        if not (math.isfinite(altitude_m) and 0.1 <= altitude_m <= 100.0):
            raise SetpointError(
                f"take-off altitude {altitude_m!r} m is outside 0.1-100 m; give a height above home"
            )
        self._require_target()
        if not self.telemetry.armed:
            raise LinkError("the vehicle is not armed; call arm() before takeoff()")
        if self.info.autopilot is Autopilot.PX4:
            home = await self._home_amsl_m()
            await self._commands.checked(
                mavlink2.MAV_CMD_NAV_TAKEOFF,
                (math.nan, 0.0, 0.0, math.nan, math.nan, math.nan, home + altitude_m),
                hint="PX4 needs a position estimate and a home position to take off",
            )
            return
        if self.telemetry.mode is not FlightMode.GUIDED:
            await self.set_mode(FlightMode.GUIDED)
        retry_s = max(5.0, self._cfg.command_timeout_s)
        start = self._clock.monotonic_s()
        while True:
            sent_at = self._clock.monotonic_s()
            result = await self.command_long(
                mavlink2.MAV_CMD_NAV_TAKEOFF, (0.0, 0.0, 0.0, math.nan, 0.0, 0.0, altitude_m)
            )
            if result == MAV_RESULT_ACCEPTED:
                return
            if self._clock.monotonic_s() - start >= retry_s:
                raise await self._commands.rejection(
                    mavlink2.MAV_CMD_NAV_TAKEOFF,
                    result,
                    sent_at,
                    f"ArduPilot still refused after {retry_s:.0f} s; check the EKF has a position (mocap, origin)",
                )
            logger.debug("NAV_TAKEOFF refused (%s); retrying", result_name(result))
            await self._clock.sleep(0.5)

    async def _home_amsl_m(self) -> float:
        with self._state.lock:
            home = self._state.home_amsl_m
        if home is not None:
            return home
        target = self._require_target()
        self._send(
            mavlink2.MAVLink_command_long_message(
                target[0],
                target[1],
                mavlink2.MAV_CMD_REQUEST_MESSAGE,
                0,
                float(mavlink2.MAVLINK_MSG_ID_HOME_POSITION),
                0,
                0,
                0,
                0,
                0,
                0,
            )
        )

        def probe() -> float | None:
            with self._state.lock:
                return self._state.home_amsl_m

        return await self._state.wait_until(
            probe,
            self._cfg.command_timeout_s,
            lambda: LinkError(
                "PX4 reports no home altitude (no HOME_POSITION or GLOBAL_POSITION_INT); without GPS set the EKF "
                "origin first (set_ekf_origin) and wait for a position estimate"
            ),
        )

    async def land(self) -> None:
        """Land at the current position (LAND mode); returns when the HEARTBEAT shows LAND."""
        await self.set_mode(FlightMode.LAND)

    # ------------------------------------------------------------------ setpoint stream

    async def start_setpoint_stream(self, rate_hz: float | None = None) -> None:
        """Start streaming the current setpoint (initially zero velocity, world frame).

        Returns immediately; the stream runs on its own thread at ``rate_hz`` (default
        ``link.setpoint_rate_hz``) until :meth:`stop_setpoint_stream` or :meth:`close`
        (see :class:`~flightkit.link.mavlink.stream.SetpointStream`).
        """
        self._require_target()
        rate = self._cfg.setpoint_rate_hz if rate_hz is None else float(rate_hz)
        if not (math.isfinite(rate) and 1.0 <= rate <= 1000.0):
            raise SetpointError(f"setpoint rate {rate_hz!r} Hz is outside 1-1000 Hz")
        self._setpoints.start(rate, self._loop)

    async def stop_setpoint_stream(self) -> None:
        """Stop the stream and send one zero-velocity setpoint; idempotent."""
        await self._setpoints.stop()

    def set_velocity(self, setpoint: VelocitySetpoint, *, send_now: bool = False) -> None:
        """Replace the streamed setpoint; returns immediately.

        With ``send_now=True`` the setpoint also goes on the wire at once, from the calling
        thread (a control loop driven by mocap then adds no stream-period delay), unless a
        setpoint went out less than a quarter of a stream period ago; the stream thread skips
        its tick when a setpoint went out within the last period, so the rate on the wire stays
        about max(stream rate, caller rate).

        Raises:
            SetpointError: beyond the hard safety limits (see HARD_MAX_*).
            LinkError: the stream is not running.
        """
        self._setpoints.set(setpoint, send_now=send_now)

    def _send_setpoint(self, f: SetpointFields) -> None:
        with self._state.lock:
            target = self._state.target
        if target is None:
            return
        t_ms = int((self._clock.monotonic_s() - self._t0_s) * 1000.0) & 0xFFFFFFFF
        self._send(encode_setpoint_message(f, target, t_ms))

    # ------------------------------------------------------------------ external pose

    async def send_vision_pose(
        self, pose: ExternalPose, kind: ExternalPoseKind = ExternalPoseKind.VISION_POSITION_ESTIMATE
    ) -> None:
        """Send a mocap/VO pose to the autopilot's estimator; returns once sent.

        Poses closer together than ``1 / max_pose_rate_hz`` (clock time) are dropped, so a
        300 Hz mocap stream reaches the EKF at the 30-50 Hz it is tuned for.
        """
        self._require_target()
        now = self._clock.monotonic_s()
        if self._max_pose_rate_hz > 0 and now - self._last_pose_s < 0.95 / self._max_pose_rate_hz:
            return
        self._last_pose_s = now
        if kind is ExternalPoseKind.ODOMETRY:
            self._send(encode_odometry(pose))
        else:
            self._send(encode_vision_position_estimate(pose))

    async def set_ekf_origin(self, lat_deg: float, lon_deg: float, alt_m: float) -> None:
        """Send SET_GPS_GLOBAL_ORIGIN (the EKF origin of a vehicle without GPS); returns once sent."""
        if not (-90.0 <= lat_deg <= 90.0 and -180.0 <= lon_deg <= 180.0 and math.isfinite(alt_m)):
            raise SetpointError(
                f"EKF origin ({lat_deg}, {lon_deg}, {alt_m}) is not a valid latitude/longitude/altitude"
            )
        target = self._require_target()
        self._send(
            mavlink2.MAVLink_set_gps_global_origin_message(
                target[0],
                round(lat_deg * 1e7),
                round(lon_deg * 1e7),
                round(alt_m * 1000.0),
                self._clock.time_ns() // 1000,
            )
        )
