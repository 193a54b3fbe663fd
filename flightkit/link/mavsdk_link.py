"""The MAVSDK backend of :class:`~flightkit.link.base.VehicleLink`.

:class:`MavsdkLink` drives an autopilot through MAVSDK 4.x (the native binding, asyncio API
under :mod:`mavsdk.asyncio`): the action plugin arms, takes off, lands and switches to Hold;
the offboard plugin carries velocity setpoints; the telemetry plugin keeps a state snapshot
current; the mocap plugin forwards external poses; and ``mavlink_direct`` covers what the
plugins cannot express (the raw HEARTBEAT with its ``custom_mode``, and MAV_CMD_DO_SET_MODE
for modes MAVSDK has no call for, such as ArduPilot BRAKE or PX4 POSCTL).

Frames: everything above this module speaks ENU/FLU; conversions to NED/FRD happen here,
through :mod:`flightkit.frames`.

Time: MAVSDK runs on wall time inside (its command retries, its 3 s connection timeout, its
20 Hz offboard re-send). This backend uses the injected :class:`~flightkit.clock.Clock` for
its own loops (setpoint stream, ``wait_for``) and wall time for MAVSDK's calls, so it works
with :class:`~flightkit.clock.WallClock` and with :class:`~flightkit.clock.SimClock` at
speeds near 1 (tests use 1-2). It cannot run under :class:`~flightkit.clock.LockstepClock`.

Offboard semantics that differ from the pymavlink backend, all because MAVSDK re-sends the
last offboard setpoint at 20 Hz by itself while offboard is active:

* :meth:`MavsdkLink.stop_setpoint_stream` sends a zero setpoint and then, if offboard is
  active, calls ``offboard.stop()``, which puts the vehicle in Hold. Otherwise MAVSDK would
  keep the vehicle in OFFBOARD on a repeated zero setpoint for ever.
* World-frame setpoints with a yaw *rate* (and the default "hold heading") are rotated into
  the yaw-aligned body frame with the latest attitude and sent as ``VelocityBodyYawspeed``,
  because MAVSDK's ``VelocityNedYaw`` only takes an absolute yaw. Body-frame setpoints with an
  absolute yaw are rotated into NED the same way and sent as ``VelocityNedYaw``.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import json
import logging
import math
import threading
from collections.abc import Awaitable, Callable
from types import TracebackType
from typing import Any, Self, TypeVar

from flightkit.clock import Clock
from flightkit.config import Autopilot, LinkConfig
from flightkit.errors import (
    CommandRejected,
    ConfigError,
    EndpointError,
    LinkError,
    LinkTimeout,
    SetpointError,
)
from flightkit.frames import (
    ned_to_enu,
    quat_wxyz_to_xyzw,
    quat_xyzw_to_wxyz,
    rotation_enu_flu_from_ned_frd,
    yaw_from_rotation,
)
from flightkit.link.base import (
    BatteryState,
    ExternalPose,
    ExternalPoseKind,
    FlightMode,
    LandedState,
    Telemetry,
    VehicleInfo,
    VelocitySetpoint,
    offboard_mode_for,
)
from flightkit.link.mavlink.encoding import check_hard_limits
from flightkit.link.mavsdk_conversions import (
    NedPose,
    external_pose_to_ned,
    mavsdk_url,
    pose_covariance_upper,
    setpoint_to_mavsdk,
)
from flightkit.link.modes import (
    MAV_MODE_FLAG_SAFETY_ARMED,
    autopilot_from_heartbeat,
    decode_mode,
    resolve_mode,
    set_mode_params,
)

__all__ = [
    "MavsdkLink",
    "NedPose",
    "external_pose_to_ned",
    "mavsdk_url",
    "pose_covariance_upper",
    "setpoint_to_mavsdk",
]

logger = logging.getLogger(__name__)
_core_logger = logging.getLogger(__name__ + ".core")

T = TypeVar("T")

MAV_CMD_DO_SET_MODE = 176
MAV_RESULT_NAMES = {
    0: "ACCEPTED",
    1: "TEMPORARILY_REJECTED",
    2: "DENIED",
    3: "UNSUPPORTED",
    4: "FAILED",
    5: "IN_PROGRESS",
    6: "CANCELLED",
}

# Seconds (wall) to wait after a refusal for the STATUSTEXT that explains it.
_REASON_GRACE_S = 0.3
# Clock seconds before a refusal whose STATUSTEXT still counts as its reason.
_REASON_WINDOW_S = 1.0
# Clock seconds between checks of a wait_for predicate.
_POLL_S = 0.02
# Extra wall seconds on top of MAVSDK's own command retries before we give up on a call.
_CALL_MARGIN_S = 2.0
# PX4 wants a second of setpoints before it accepts OFFBOARD (FACTS); a quarter second more covers the
# stream period and the hop through MAVSDK.
_PX4_OFFBOARD_WARMUP_S = 1.25
# ArduPilot refuses NAV_TAKEOFF until its EKF has a position; retry this long (clock seconds) at least.
_APM_TAKEOFF_RETRY_S = 5.0


# --------------------------------------------------------------------------- MAVSDK log folding

_log_lock = threading.Lock()
_log_installed = False


def _install_core_logging() -> None:
    """Route MAVSDK's own log lines (stdout by default) to ``flightkit.link.mavsdk_link.core``."""
    global _log_installed
    with _log_lock:
        if _log_installed:
            return
        from mavsdk.logging import LogLevel, log_subscribe

        levels = {
            LogLevel.DEBUG: logging.DEBUG,
            LogLevel.INFO: logging.DEBUG,  # MAVSDK's INFO is chatty (version banners, discoveries)
            LogLevel.WARN: logging.WARNING,
            LogLevel.ERROR: logging.ERROR,
        }

        def on_log(level: Any, message: str, file: str | None, line: int) -> bool:
            try:
                _core_logger.log(levels.get(level, logging.INFO), "%s", message)
            except Exception:  # never let an exception cross into C
                pass
            return True  # suppress MAVSDK's stdout printing

        log_subscribe(on_log)
        _log_installed = True


# --------------------------------------------------------------------------- the link


class MavsdkLink:
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

        self._mavsdk: Any = None
        self._system: Any = None
        self._action: Any = None
        self._offboard: Any = None
        self._telemetry: Any = None
        self._mocap: Any = None
        self._direct: Any = None
        self._info: VehicleInfo | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self._closed = False

        # Telemetry state (written by subscription tasks on the event loop).
        self._armed = False
        self._mode = FlightMode.UNKNOWN
        self._custom_mode = 0
        self._landed = LandedState.UNDEFINED
        self._pos_enu: tuple[float, float, float] = (math.nan, math.nan, math.nan)
        self._vel_enu: tuple[float, float, float] = (math.nan, math.nan, math.nan)
        self._quat_wxyz: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
        self._yaw = math.nan
        self._battery = BatteryState()
        self._stamp_s = 0.0
        self._last_heartbeat_s = -math.inf
        self._texts: collections.deque[tuple[float, str]] = collections.deque(maxlen=64)
        self._text_seq = 0
        self._text_arrived = asyncio.Event()

        # Setpoint stream state.
        self._setpoint = VelocitySetpoint.zero()
        self._setpoint_stamp_s = 0.0
        self._stream_task: asyncio.Task[None] | None = None
        self._stream_started_s = 0.0
        self._stream_rate_hz = cfg.setpoint_rate_hz
        self._stream_stopped_for_silence = False
        self._send_failures = 0
        self._sent_setpoints = 0

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
        now = self._clock.monotonic_s()
        return Telemetry(
            stamp_s=self._stamp_s,
            armed=self._armed,
            mode=self._mode,
            custom_mode=self._custom_mode,
            landed_state=self._landed,
            pos_local_enu_m=self._pos_enu,
            vel_local_enu_m_s=self._vel_enu,
            R_local_body_quat_wxyz=self._quat_wxyz,
            yaw_local_rad=self._yaw,
            battery=self._battery,
            heartbeat_age_s=max(0.0, now - self._last_heartbeat_s),
        )

    @property
    def statustext(self) -> tuple[str, ...]:
        """Recent STATUSTEXT lines from the autopilot, oldest first."""
        return tuple(t for _, t in self._texts)

    @property
    def clock(self) -> Clock:
        """The clock this link times its stream and waits with."""
        return self._clock

    @property
    def streaming(self) -> bool:
        """True while the setpoint stream runs."""
        return self._stream_task is not None

    @property
    def setpoints_sent(self) -> int:
        """How many setpoints the stream has handed to MAVSDK (for diagnostics and tests)."""
        return self._sent_setpoints

    # ------------------------------------------------------------------ lifetime

    async def __aenter__(self) -> Self:
        await self.connect()
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.close()

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
        _install_core_logging()
        from mavsdk.asyncio import Configuration, Mavsdk, MavsdkConnectionError
        from mavsdk.asyncio.plugins.action import ActionAsync
        from mavsdk.asyncio.plugins.mavlink_direct import MavlinkDirectAsync
        from mavsdk.asyncio.plugins.mocap import MocapAsync
        from mavsdk.asyncio.plugins.offboard import OffboardAsync
        from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

        conf = Configuration.create_manual(self._cfg.source_system, self._cfg.source_component, True)
        self._mavsdk = Mavsdk(conf)
        try:
            try:
                await self._mavsdk.add_any_connection(self._url)
            except MavsdkConnectionError as exc:
                raise EndpointError(
                    f"MAVSDK cannot open {self._url} (from link.url {self._cfg.url!r}): {exc}; "
                    "check the address, that the port is free, or the serial device exists"
                ) from exc
            timeout_s = self._cfg.heartbeat_timeout_s
            system = await self._mavsdk.first_autopilot(timeout_s=timeout_s)
            if system is None:
                raise LinkTimeout(
                    f"no autopilot HEARTBEAT on {self._url} after {timeout_s:.1f} s; "
                    "is the autopilot or simulator running and link.url right?",
                    what="HEARTBEAT",
                    timeout_s=timeout_s,
                )
            self._system = system
            self._action = ActionAsync(system)
            self._offboard = OffboardAsync(system)
            self._telemetry = TelemetryAsync(system)
            self._mocap = MocapAsync(system)
            self._direct = MavlinkDirectAsync(system)
            sysid = await system.get_system_id()

            loop = asyncio.get_running_loop()
            first_hb: asyncio.Future[dict[str, Any]] = loop.create_future()
            self._start_tasks(sysid, first_hb)
            try:
                hb = await asyncio.wait_for(first_hb, timeout=max(timeout_s, 1.5))
            except TimeoutError:
                raise LinkTimeout(
                    f"MAVSDK found system {sysid} on {self._url} but no HEARTBEAT from its autopilot "
                    f"reached us within {timeout_s:.1f} s; check the link",
                    what="HEARTBEAT",
                    timeout_s=timeout_s,
                ) from None
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
        if self._stream_task is not None and self._info is not None:
            with contextlib.suppress(LinkError):
                await self.stop_setpoint_stream()
        await self._teardown()
        if self._info is not None:
            logger.info("closed MAVSDK link to %s", self._url)

    async def _teardown(self) -> None:
        tasks = list(self._tasks)
        if self._stream_task is not None:
            tasks.append(self._stream_task)
            self._stream_task = None
        self._tasks.clear()
        for t in tasks:
            t.cancel()
        if tasks:
            await asyncio.gather(*tasks, return_exceptions=True)
        if self._mavsdk is not None:
            mav, self._mavsdk = self._mavsdk, None
            self._action = self._offboard = self._telemetry = self._mocap = self._direct = None
            self._system = None
            # destroy() joins MAVSDK's threads; keep the loop responsive meanwhile.
            await asyncio.get_running_loop().run_in_executor(None, mav.destroy)

    # ------------------------------------------------------------------ telemetry tasks

    def _start_tasks(self, sysid: int, first_hb: asyncio.Future[dict[str, Any]]) -> None:
        tel = self._telemetry

        async def heartbeats() -> None:
            async for msg in self._direct.subscribe_message("HEARTBEAT"):
                if msg.system_id != sysid or msg.component_id != 1:
                    continue  # another component of the vehicle (camera, gimbal, companion)
                try:
                    fields = json.loads(msg.fields_json)
                except ValueError:
                    logger.debug("unparsable HEARTBEAT fields %r", msg.fields_json)
                    continue
                self._on_heartbeat(fields)
                if not first_hb.done():
                    fields["_component_id"] = msg.component_id
                    first_hb.set_result(fields)

        async def position_velocity() -> None:
            async for pv in tel.subscribe_position_velocity_ned():
                p, v = pv.position, pv.velocity
                pe = ned_to_enu([p.north_m, p.east_m, p.down_m])
                ve = ned_to_enu([v.north_m_s, v.east_m_s, v.down_m_s])
                self._pos_enu = (float(pe[0]), float(pe[1]), float(pe[2]))
                self._vel_enu = (float(ve[0]), float(ve[1]), float(ve[2]))
                self._stamp_s = self._clock.monotonic_s()

        async def attitude() -> None:
            from scipy.spatial.transform import Rotation

            async for q in tel.subscribe_attitude_quaternion():
                wxyz = (q.w, q.x, q.y, q.z)
                if not all(math.isfinite(x) for x in wxyz) or sum(x * x for x in wxyz) < 0.5:
                    continue
                R_enu_flu = rotation_enu_flu_from_ned_frd(Rotation.from_quat(quat_wxyz_to_xyzw(wxyz)))
                qq = quat_xyzw_to_wxyz(R_enu_flu.as_quat())
                self._quat_wxyz = (float(qq[0]), float(qq[1]), float(qq[2]), float(qq[3]))
                self._yaw = yaw_from_rotation(R_enu_flu)
                self._stamp_s = self._clock.monotonic_s()

        async def landed() -> None:
            async for s in tel.subscribe_landed_state():
                try:
                    new = LandedState(int(s))
                except ValueError:
                    new = LandedState.UNDEFINED
                if new is not self._landed:
                    logger.info("landed state: %s", new.name)
                self._landed = new

        async def battery() -> None:
            async for b in tel.subscribe_battery():
                self._battery = BatteryState(
                    voltage_v=float(b.voltage_v), remaining_pct=float(b.remaining_percent)
                )

        async def status_text() -> None:
            async for st in tel.subscribe_status_text():
                text = st.text.strip()
                self._texts.append((self._clock.monotonic_s(), text))
                self._text_seq += 1
                self._text_arrived.set()
                logger.info("autopilot says: %s", text)

        for name, fn in (
            ("heartbeat", heartbeats),
            ("position_velocity_ned", position_velocity),
            ("attitude_quaternion", attitude),
            ("landed_state", landed),
            ("battery", battery),
            ("status_text", status_text),
        ):
            self._tasks.append(asyncio.create_task(self._guard(name, fn), name=f"mavsdk-{name}"))

    async def _guard(self, name: str, fn: Callable[[], Awaitable[None]]) -> None:
        """Run a subscription; log (not raise) if it fails, so one bad stream can't kill the link."""
        try:
            await fn()
        except asyncio.CancelledError:
            raise
        except Exception:
            logger.exception("MAVSDK %s subscription failed; that part of the telemetry stops updating", name)

    def _on_heartbeat(self, fields: dict[str, Any]) -> None:
        base = int(fields.get("base_mode", 0))
        custom = int(fields.get("custom_mode", 0))
        armed = bool(base & MAV_MODE_FLAG_SAFETY_ARMED)
        mode = decode_mode(self._autopilot, base, custom)
        if armed != self._armed:
            logger.info("%s", "armed" if armed else "disarmed")
        if mode is not self._mode:
            logger.info("mode: %s", mode.value)
        self._armed, self._mode, self._custom_mode = armed, mode, custom
        self._last_heartbeat_s = self._clock.monotonic_s()

    # ------------------------------------------------------------------ helpers

    def _require(self) -> None:
        if self._info is None or self._mavsdk is None:
            raise LinkError("not connected; call connect() or use 'async with' first")

    async def _call(self, what: str, coro: Awaitable[T]) -> T:
        """Await a MAVSDK call with an overall (wall) deadline on top of MAVSDK's own retries."""
        limit = self._cfg.command_timeout_s + _CALL_MARGIN_S
        try:
            return await asyncio.wait_for(coro, timeout=limit)
        except TimeoutError:
            raise LinkTimeout(
                f"MAVSDK {what} did not return within {limit:.1f} s; is the link still up?",
                what=what,
                timeout_s=limit,
            ) from None

    async def _reasons_since(self, seq0: int) -> tuple[str, ...]:
        """STATUSTEXT lines that explain a refusal: those since text number ``seq0`` (waiting
        briefly for a late one) plus any from the second before the command."""
        if self._text_seq == seq0:
            self._text_arrived.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._text_arrived.wait(), timeout=_REASON_GRACE_S)
        texts = list(self._texts)
        n_new = min(self._text_seq - seq0, len(texts))
        cut = len(texts) - n_new
        newest_old = texts[cut - 1][0] if cut > 0 else -math.inf
        window_start = (texts[cut][0] if n_new else self._clock.monotonic_s()) - _REASON_WINDOW_S
        before = [t for stamp, t in texts[:cut] if stamp >= window_start and stamp <= newest_old]
        return tuple(before + [t for _, t in texts[cut:]])

    async def _action_call(self, command: str, fn: Callable[[], Awaitable[Any]], hint: str = "") -> None:
        """Run an action-plugin call; ActionError -> CommandRejected with the autopilot's words."""
        from mavsdk.asyncio.plugins.action import ActionError, ActionResult

        seq0 = self._text_seq
        try:
            await self._call(command, fn())
        except ActionError as exc:
            result = exc.result
            reasons = await self._reasons_since(seq0)
            if result in (ActionResult.TIMEOUT, ActionResult.NO_SYSTEM, ActionResult.CONNECTION_ERROR):
                raise LinkTimeout(
                    f"no answer to {command} ({result.name}) from the autopilot on {self._url}; "
                    "is the link up?",
                    what=command,
                    timeout_s=self._cfg.command_timeout_s,
                ) from exc
            raise CommandRejected(command, result.name, reasons, hint) from exc

    async def _wait_state(
        self, predicate: Callable[[Telemetry], bool], timeout_s: float, what: str
    ) -> Telemetry:
        return await self.wait_for(predicate, timeout_s, what)

    # ------------------------------------------------------------------ commands

    async def arm(self) -> None:
        """Arm; returns when the heartbeat shows armed.

        Raises:
            CommandRejected: the autopilot refused (``result`` is MAVSDK's ActionResult name,
                ``statustext`` the autopilot's explanation if it sent one).
            LinkTimeout: no answer, or the heartbeat did not show armed in time.
        """
        self._require()
        if self._armed:
            return
        await self._action_call(
            "arm", self._action.arm, hint="check the pre-arm conditions the autopilot reported"
        )
        await self._wait_state(lambda t: t.armed, self._cfg.command_timeout_s, "heartbeat to show armed")

    async def disarm(self, force: bool = False) -> None:
        """Disarm; returns when the heartbeat shows disarmed. ``force`` disarms in the air (kill)."""
        self._require()
        if not self._armed:
            return
        if force:
            await self._action_call("kill", self._action.kill)
        else:
            await self._action_call(
                "disarm", self._action.disarm, hint="land first, or pass force=True to kill the motors"
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
        if self._mode is target:
            return
        if target is offboard_mode_for(ap) and (self._stream_task is not None or ap is Autopilot.PX4):
            await self._start_offboard()
        elif target is FlightMode.HOLD and ap is Autopilot.PX4:
            await self._action_call("hold", self._action.hold)
        elif target is FlightMode.LAND:
            await self._action_call("land", self._action.land)
        elif target is FlightMode.RTL:
            await self._action_call("return_to_launch", self._action.return_to_launch)
        else:
            await self._do_set_mode(target)
        await self._wait_state(
            lambda t: t.mode is target, self._cfg.command_timeout_s, f"heartbeat to show mode {target.value}"
        )

    async def _start_offboard(self) -> None:
        from mavsdk.asyncio.plugins.offboard import OffboardError, OffboardResult

        if self._stream_task is None:
            raise LinkError(
                f"{offboard_mode_for(self._autopilot).value} needs setpoints streaming first; "
                "call start_setpoint_stream() before set_mode()"
            )
        if self._autopilot is Autopilot.PX4:
            warm_s = _PX4_OFFBOARD_WARMUP_S - (self._clock.monotonic_s() - self._stream_started_s)
            if warm_s > 0:
                await self._clock.sleep(warm_s)
        seq0 = self._text_seq
        try:
            await self._call("offboard.start", self._offboard.start())
        except OffboardError as exc:
            reasons = await self._reasons_since(seq0)
            if exc.result in (
                OffboardResult.TIMEOUT,
                OffboardResult.NO_SYSTEM,
                OffboardResult.CONNECTION_ERROR,
            ):
                raise LinkTimeout(
                    f"no answer to offboard.start ({exc.result.name}) from the autopilot on {self._url}",
                    what="offboard.start",
                    timeout_s=self._cfg.command_timeout_s,
                ) from exc
            raise CommandRejected(
                "offboard.start",
                exc.result.name,
                reasons,
                "PX4 wants setpoints for about a second before OFFBOARD; keep the stream running and retry",
            ) from exc

    async def _do_set_mode(self, target: FlightMode) -> None:
        """MAV_CMD_DO_SET_MODE through mavlink_direct, for modes MAVSDK has no call for."""
        from mavsdk.plugins.mavlink_direct import MavlinkDirectError, MavlinkMessage

        cmd = set_mode_params(self._autopilot, target)
        info = self.info
        fields = {
            "target_system": info.system_id,
            "target_component": info.component_id,
            "command": MAV_CMD_DO_SET_MODE,
            "confirmation": 0,
            "param1": cmd.params[0],
            "param2": cmd.params[1],
            "param3": cmd.params[2],
            "param4": 0.0,
            "param5": 0.0,
            "param6": 0.0,
            "param7": 0.0,
        }
        msg = MavlinkMessage(
            message_name="COMMAND_LONG",
            system_id=self._cfg.source_system,
            component_id=self._cfg.source_component,
            target_system_id=info.system_id,
            target_component_id=info.component_id,
            fields_json=json.dumps(fields),
        )
        seq0 = self._text_seq
        what = f"MAV_CMD_DO_SET_MODE {target.value}"
        try:
            ack = await self._call(what, self._direct.send_command(msg))
        except MavlinkDirectError as exc:
            raise LinkTimeout(
                f"no COMMAND_ACK for {what} from the autopilot on {self._url} ({exc.result.name})",
                what=what,
                timeout_s=self._cfg.command_timeout_s,
            ) from exc
        try:
            result = int(json.loads(ack.fields_json).get("result", 0))
        except (ValueError, AttributeError):
            result = 0
        if result != 0:
            reasons = await self._reasons_since(seq0)
            raise CommandRejected("MAV_CMD_DO_SET_MODE", MAV_RESULT_NAMES.get(result, str(result)), reasons)

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
        if not self._armed:
            raise LinkError("the vehicle is not armed; call arm() before takeoff()")
        await self._action_call(
            "set_takeoff_altitude",
            lambda: self._action.set_takeoff_altitude(float(altitude_m)),
            hint="the autopilot did not accept the take-off altitude parameter",
        )
        retry_s = max(_APM_TAKEOFF_RETRY_S, self._cfg.command_timeout_s)
        start = self._clock.monotonic_s()
        while True:
            try:
                await self._action_call(
                    "takeoff", self._action.takeoff, hint="check the autopilot has a position estimate"
                )
                break
            except CommandRejected:
                if self._autopilot is not Autopilot.ARDUPILOT or self._clock.monotonic_s() - start >= retry_s:
                    raise
                logger.debug("take-off refused; retrying (ArduPilot's EKF may not have a position yet)")
                await self._clock.sleep(0.5)
        logger.info("take-off to %.2f m commanded", altitude_m)

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
        self._stream_rate_hz = rate
        if self._stream_task is not None:
            return
        self._setpoint = VelocitySetpoint.zero()
        self._setpoint_stamp_s = self._stream_started_s = self._clock.monotonic_s()
        self._stream_stopped_for_silence = False
        await self._send(self._setpoint)
        self._stream_task = asyncio.create_task(self._stream_loop(), name="mavsdk-setpoints")
        logger.info("setpoint stream started at %.1f Hz", rate)

    async def stop_setpoint_stream(self) -> None:
        """Stop streaming: send one zero setpoint and, if offboard is active, leave it (-> Hold).

        Idempotent. See the module docstring for why this leaves offboard.
        """
        task, self._stream_task = self._stream_task, None
        if task is None:
            return
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        if self._offboard is None:
            return
        with contextlib.suppress(LinkError):
            await self._send(VelocitySetpoint.zero(self._setpoint.frame))
        from mavsdk.asyncio.plugins.offboard import OffboardError

        try:
            active = await self._call("offboard.is_active", self._offboard.is_active())
            if active:
                await self._call("offboard.stop", self._offboard.stop())
                logger.info("offboard stopped (vehicle holds position)")
        except (OffboardError, LinkTimeout) as exc:
            logger.warning("could not stop MAVSDK offboard cleanly: %s", exc)
        logger.info("setpoint stream stopped")

    def set_velocity(self, setpoint: VelocitySetpoint) -> None:
        """Replace the streamed setpoint; returns immediately.

        Raises:
            SetpointError: beyond the hard safety limits of the MAVLink backends.
            LinkError: the stream is not running.
        """
        check_hard_limits(setpoint)
        if self._stream_task is None:
            raise LinkError("the setpoint stream is not running; call start_setpoint_stream() first")
        self._setpoint = setpoint
        self._setpoint_stamp_s = self._clock.monotonic_s()
        if self._stream_stopped_for_silence:
            self._stream_stopped_for_silence = False
            logger.info("setpoints resumed")

    async def _stream_loop(self) -> None:
        clock = self._clock
        next_s = clock.monotonic_s()
        while True:
            period = 1.0 / self._stream_rate_hz
            now = clock.monotonic_s()
            sp = self._setpoint
            if now - self._setpoint_stamp_s > self._cfg.setpoint_timeout_s:
                if not self._stream_stopped_for_silence:
                    self._stream_stopped_for_silence = True
                    logger.warning(
                        "no new setpoint for %.2f s (limit %.2f s); streaming an explicit stop",
                        now - self._setpoint_stamp_s,
                        self._cfg.setpoint_timeout_s,
                    )
                sp = VelocitySetpoint.zero(sp.frame)
            try:
                await self._send(sp)
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

    async def _send(self, sp: VelocitySetpoint) -> None:
        from mavsdk.asyncio.plugins.offboard import OffboardError, VelocityBodyYawspeed, VelocityNedYaw

        cmd = setpoint_to_mavsdk(sp, self._yaw)
        try:
            if cmd.kind == "ned":
                await self._offboard.set_velocity_ned(VelocityNedYaw(cmd.a, cmd.b, cmd.c, cmd.yaw_deg))
            else:
                await self._offboard.set_velocity_body(
                    VelocityBodyYawspeed(cmd.a, cmd.b, cmd.c, cmd.yawspeed_deg_s)
                )
        except OffboardError as exc:
            raise LinkError(f"MAVSDK refused the setpoint: {exc.result.name}") from exc
        self._sent_setpoints += 1

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
                await self._call(
                    "mocap.set_vision_position_estimate", self._mocap.set_vision_position_estimate(msg)
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
                await self._call("mocap.set_odometry", self._mocap.set_odometry(odo))
        except MocapError as exc:
            raise LinkError(f"MAVSDK refused the external pose ({kind.value}): {exc.result.name}") from exc

    async def set_ekf_origin(self, lat_deg: float, lon_deg: float, alt_m: float) -> None:
        """Set the EKF origin (SET_GPS_GLOBAL_ORIGIN) for a vehicle without GPS; returns once sent."""
        self._require()
        await self._action_call(
            "set_gps_global_origin", lambda: self._action.set_gps_global_origin(lat_deg, lon_deg, alt_m)
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
        deadline = self._clock.monotonic_s() + timeout_s
        while True:
            t = self.telemetry
            if predicate(t):
                return t
            if self._clock.monotonic_s() >= deadline:
                raise LinkTimeout(
                    f"timed out after {timeout_s:.1f} s waiting for {what} "
                    f"(mode {t.mode.value}, armed {t.armed}, landed {t.landed_state.name}, "
                    f"heartbeat age {t.heartbeat_age_s:.1f} s)",
                    what=what,
                    timeout_s=timeout_s,
                )
            await self._clock.sleep(_POLL_S)
