"""The pymavlink :class:`~flightkit.link.base.VehicleLink` backend.

Threads and timing:

* one **reader thread** per connection owns the transport's receive side: it parses
  MAVLink (pymavlink's codec, MAVLink 2 with the ArduPilot dialect, a superset of common),
  updates the vehicle state under a lock, sends our HEARTBEAT at 1 Hz, and wakes the
  coroutines waiting on the state (``loop.call_soon_threadsafe``);
* one **setpoint thread** while a setpoint stream runs: it sends the current velocity
  setpoint at absolute deadlines (no drift, low jitter), and replaces it by an explicit
  zero-velocity stop when the caller has been silent for ``link.setpoint_timeout_s``;
* the asyncio API on top: commands with COMMAND_ACK handling and retries, state waits
  with timeouts. All time comes from the injected :class:`~flightkit.clock.Clock`, so a
  simulated lab at ``SimClock(speed=10)`` flies ten times faster.

Our identity on the link: system id ``link.source_system``, component id
``link.source_component``. The HEARTBEAT type follows the component id: 191-194
(MAV_COMP_ID_ONBOARD_COMPUTER..4) announce MAV_TYPE_ONBOARD_CONTROLLER, any other id
(e.g. 190, MAV_COMP_ID_MISSIONPLANNER) announces MAV_TYPE_GCS. PX4 only sends STATUSTEXT
to a link on which it heard a GCS heartbeat, so pick 190 when refusal texts from PX4
matter more than looking like a companion computer.

Frames: everything above this module is ENU/FLU; NED/FRD appear only in the encoders
below (through :mod:`flightkit.frames`).
"""

from __future__ import annotations

import asyncio
import collections
import logging
import math
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from types import TracebackType
from typing import Any, Self, TypeVar

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink2
from scipy.spatial.transform import Rotation

from flightkit.clock import Clock, WallClock
from flightkit.config import Autopilot, LinkConfig
from flightkit.errors import CommandRejected, LinkError, LinkTimeout, SetpointError
from flightkit.frames import (
    enu_to_ned,
    flu_to_frd,
    ned_to_enu,
    quat_wxyz_to_xyzw,
    quat_xyzw_to_wxyz,
    rotation_enu_flu_from_ned_frd,
    rotation_ned_frd_from_enu_flu,
    yaw_enu_to_ned,
    yaw_from_rotation,
)
from flightkit.link.base import (
    BatteryState,
    ExternalPose,
    ExternalPoseKind,
    FlightMode,
    LandedState,
    SetpointFrame,
    Telemetry,
    VehicleInfo,
    VelocitySetpoint,
)
from flightkit.link.endpoints import Endpoint, Transport, open_transport, parse_endpoint
from flightkit.link.modes import (
    MAV_MODE_FLAG_SAFETY_ARMED,
    autopilot_from_heartbeat,
    decode_mode,
    set_mode_params,
)
from flightkit.link.signing import SigningSettings, apply_signing, parse_signing_key, signing_timestamp

__all__ = [
    "HARD_MAX_HORIZONTAL_M_S",
    "HARD_MAX_VERTICAL_M_S",
    "HARD_MAX_YAW_RATE_RAD_S",
    "TYPE_MASK_VELOCITY_ONLY",
    "TYPE_MASK_VELOCITY_YAW",
    "TYPE_MASK_VELOCITY_YAW_RATE",
    "LinkStats",
    "MavlinkLink",
    "SetpointFields",
    "encode_odometry",
    "encode_velocity_setpoint",
    "encode_vision_position_estimate",
    "heartbeat_type_for_component",
]

logger = logging.getLogger(__name__)

T = TypeVar("T")

# Safety net on every velocity setpoint, whatever the caller's own limits: no indoor lab
# flight needs more, and a bigger number is a bug (units, frames) rather than a command.
HARD_MAX_HORIZONTAL_M_S = 15.0
HARD_MAX_VERTICAL_M_S = 5.0
HARD_MAX_YAW_RATE_RAD_S = 6.0

# SET_POSITION_TARGET_LOCAL_NED type_mask (bit set = ignore the field).
TYPE_MASK_VELOCITY_YAW = 2503  # position, acceleration and yaw rate ignored
TYPE_MASK_VELOCITY_YAW_RATE = 1479  # position, acceleration and yaw ignored
TYPE_MASK_VELOCITY_ONLY = 3527  # yaw and yaw rate ignored too

MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_BODY_NED = 8
MAV_FRAME_BODY_FRD = 12
MAV_COMP_ID_AUTOPILOT1 = 1
MAV_TYPE_GCS = 6
MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_AUTOPILOT_INVALID = 8
MAV_STATE_ACTIVE = 4
MAV_RESULT_ACCEPTED = 0
MAV_RESULT_IN_PROGRESS = 5
FORCE_DISARM_MAGIC = 21196.0

# Telemetry we ask for (SET_MESSAGE_INTERVAL), as (message id, rate Hz).
_STREAMS: tuple[tuple[int, float], ...] = (
    (mavlink2.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 50.0),
    (mavlink2.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, 50.0),
    (mavlink2.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 5.0),
    (mavlink2.MAVLINK_MSG_ID_SYS_STATUS, 2.0),
    (mavlink2.MAVLINK_MSG_ID_BATTERY_STATUS, 1.0),
    (mavlink2.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 5.0),
    (mavlink2.MAVLINK_MSG_ID_HOME_POSITION, 0.5),
)

_STATUSTEXT_KEEP = 200
_READER_POLL_S = 0.01  # wall seconds per transport poll (bounds heartbeat jitter and close latency)
_PX4_OFFBOARD_WARMUP_S = 1.25  # PX4 wants a second of setpoints before OFFBOARD (plus margin)
_REJECT_TEXT_WINDOW_S = 1.0  # STATUSTEXT this long before a command belongs to its refusal
_REJECT_TEXT_GRACE_S = 0.2  # and texts arriving this long after the refusal


def heartbeat_type_for_component(component_id: int) -> int:
    """MAV_TYPE we announce: ONBOARD_CONTROLLER for component ids 191-194, GCS otherwise."""
    return MAV_TYPE_ONBOARD_CONTROLLER if 191 <= component_id <= 194 else MAV_TYPE_GCS


def _enum_name(enum: str, value: int, prefix: str) -> str:
    entry = mavlink2.enums.get(enum, {}).get(value)
    return entry.name.removeprefix(prefix) if entry is not None else f"{prefix}{value}"


def _cmd_name(command: int) -> str:
    return _enum_name("MAV_CMD", command, "")


def _result_name(result: int) -> str:
    return _enum_name("MAV_RESULT", result, "MAV_RESULT_")


# --------------------------------------------------------------------------- encoders (pure)


@dataclass(frozen=True, slots=True)
class SetpointFields:
    """SET_POSITION_TARGET_LOCAL_NED fields for a velocity setpoint (NED/FRD, MAVLink units)."""

    coordinate_frame: int
    type_mask: int
    vx: float
    vy: float
    vz: float
    yaw: float
    yaw_rate: float


def check_hard_limits(setpoint: VelocitySetpoint) -> None:
    """Raise SetpointError when a setpoint exceeds the backend's safety net."""
    try:
        setpoint.check_limits(HARD_MAX_HORIZONTAL_M_S, HARD_MAX_VERTICAL_M_S, HARD_MAX_YAW_RATE_RAD_S)
    except SetpointError as exc:
        raise SetpointError(
            f"{exc} (hard safety limit of the MAVLink link; this is almost surely a bug)"
        ) from None


def encode_velocity_setpoint(setpoint: VelocitySetpoint) -> SetpointFields:
    """Translate a flightkit velocity setpoint to SET_POSITION_TARGET_LOCAL_NED fields.

    WORLD (ENU) -> MAV_FRAME_LOCAL_NED with the velocity in NED; BODY (FLU) ->
    MAV_FRAME_BODY_NED with the velocity in FRD. A yaw is an ENU heading (counter-clockwise
    from x) and becomes a NED yaw (clockwise from north); a yaw rate changes sign (ENU
    counter-clockwise positive -> NED clockwise positive). Neither given: yaw rate 0.
    """
    if setpoint.frame is SetpointFrame.WORLD:
        frame = MAV_FRAME_LOCAL_NED
        v = enu_to_ned(setpoint.vel_m_s)
    else:
        frame = MAV_FRAME_BODY_NED
        v = flu_to_frd(setpoint.vel_m_s)
    if setpoint.yaw_rad is not None:
        return SetpointFields(
            frame,
            TYPE_MASK_VELOCITY_YAW,
            float(v[0]),
            float(v[1]),
            float(v[2]),
            yaw_enu_to_ned(setpoint.yaw_rad),
            0.0,
        )
    rate = 0.0 if setpoint.yaw_rate_rad_s is None else -float(setpoint.yaw_rate_rad_s)
    return SetpointFields(
        frame, TYPE_MASK_VELOCITY_YAW_RATE, float(v[0]), float(v[1]), float(v[2]), 0.0, rate + 0.0
    )


def _pose_ned_frd(pose: ExternalPose) -> tuple[np.ndarray, Rotation]:
    pos_ned = enu_to_ned(pose.T_world_body.translation)
    R_ned_frd = rotation_ned_frd_from_enu_flu(pose.T_world_body.rotation)
    return pos_ned, R_ned_frd


def _upper_triangle_diag(diag: Iterable[float]) -> list[float]:
    """A 6x6 covariance given by its diagonal, as MAVLink's 21-element upper triangle (row-major)."""
    d = list(diag)
    out: list[float] = []
    for row in range(6):
        for col in range(row, 6):
            out.append(float(d[row]) if row == col else 0.0)
    return out


def encode_vision_position_estimate(pose: ExternalPose) -> Any:
    """VISION_POSITION_ESTIMATE for ``pose``: NED position, FRD attitude as roll/pitch/yaw,
    usec timestamp from ``stamp_ns``, covariance from the pose's standard deviations."""
    pos_ned, R_ned_frd = _pose_ned_frd(pose)
    yaw, pitch, roll = R_ned_frd.as_euler("ZYX")
    cov = _upper_triangle_diag([pose.pos_std_m**2] * 3 + [pose.rot_std_rad**2] * 3)
    return mavlink2.MAVLink_vision_position_estimate_message(
        int(pose.stamp_ns) // 1000,
        float(pos_ned[0]),
        float(pos_ned[1]),
        float(pos_ned[2]),
        float(roll),
        float(pitch),
        float(yaw),
        cov,
        int(pose.reset_counter) & 0xFF,
    )


def encode_odometry(pose: ExternalPose) -> Any:
    """ODOMETRY for ``pose``: frame LOCAL_NED, child frame BODY_FRD (velocity in the body
    frame, as the message defines), quaternion w,x,y,z, covariances; unknown velocity and
    rates are NaN (a NaN first covariance element marks the velocity as unknown)."""
    pos_ned, R_ned_frd = _pose_ned_frd(pose)
    q_wxyz = quat_xyzw_to_wxyz(R_ned_frd.as_quat())
    if q_wxyz[0] < 0:
        q_wxyz = -q_wxyz
    pose_cov = _upper_triangle_diag([pose.pos_std_m**2] * 3 + [pose.rot_std_rad**2] * 3)
    if pose.vel_world_m_s is not None:
        v_frd = R_ned_frd.inv().apply(enu_to_ned(pose.vel_world_m_s))
        vel = [float(x) for x in v_frd]
        vel_cov = _upper_triangle_diag([(2.0 * pose.pos_std_m) ** 2] * 3 + [math.nan] * 3)
    else:
        vel = [math.nan] * 3
        vel_cov = [math.nan] + [0.0] * 20
    quality = int(pose.quality_pct) if 0 <= pose.quality_pct <= 100 else -1
    return mavlink2.MAVLink_odometry_message(
        int(pose.stamp_ns) // 1000,
        MAV_FRAME_LOCAL_NED,
        MAV_FRAME_BODY_FRD,
        float(pos_ned[0]),
        float(pos_ned[1]),
        float(pos_ned[2]),
        [float(x) for x in q_wxyz],
        vel[0],
        vel[1],
        vel[2],
        math.nan,
        math.nan,
        math.nan,
        pose_cov,
        vel_cov,
        int(pose.reset_counter) & 0xFF,
        mavlink2.MAV_ESTIMATOR_TYPE_MOCAP,
        quality,
    )


# --------------------------------------------------------------------------- state


@dataclass(frozen=True, slots=True)
class LinkStats:
    """Counters of one link (for status displays, tests and benchmarks)."""

    packets_received: int
    packets_rejected: int  # bad CRC, bad or missing signature
    packets_sent: int
    setpoints_sent: int
    stops_sent: int  # explicit zero-velocity setpoints sent because the caller was silent
    acks_received: int


class _State:
    """Vehicle state written by the reader thread (always under ``lock``)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.target: tuple[int, int] | None = None
        self.info: VehicleInfo | None = None
        self.hb_time_s = -math.inf
        self.base_mode = 0
        self.custom_mode = 0
        self.armed = False
        self.mode = FlightMode.UNKNOWN
        self.newest_s = 0.0
        self.landed = LandedState.UNDEFINED
        self.pos_enu = (math.nan, math.nan, math.nan)
        self.vel_enu = (math.nan, math.nan, math.nan)
        self.quat_wxyz = (1.0, 0.0, 0.0, 0.0)
        self.yaw_enu = math.nan
        self.voltage_v = math.nan
        self.remaining_pct = math.nan
        self.home_amsl_m: float | None = None
        self.statustext: collections.deque[tuple[float, int, str]] = collections.deque(
            maxlen=_STATUSTEXT_KEEP
        )
        self.ack_seq = 0
        self.acks: dict[int, tuple[int, int, float]] = {}  # command -> (seq, result, time)
        self.rx = 0
        self.rx_rejected = 0
        self.rx_other_components = 0


@dataclass(slots=True)
class _Stream:
    rate_hz: float
    setpoint: VelocitySetpoint
    fields: SetpointFields
    set_at_s: float
    started_s: float
    thread: threading.Thread
    stop: threading.Event
    sent_at_s: float = -math.inf  # last setpoint on the wire (stream thread or send_now)
    pushed_at_s: float = -math.inf  # last setpoint sent by set_velocity(send_now=True)


class _TransportWriter:
    """The file-like object pymavlink's MAVLink.send writes to."""

    def __init__(self, transport: Transport) -> None:
        self.transport = transport

    def write(self, data: bytes | bytearray) -> None:
        self.transport.send(bytes(data))


class MavlinkLink:
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
        self._target_system = target_system
        self.endpoint: Endpoint = parse_endpoint(cfg.url, cfg.baud)
        key = parse_signing_key(cfg.signing_key_hex, source=config_path)
        self._signing = SigningSettings(key, link_id) if key is not None else None
        self._max_pose_rate_hz = max_pose_rate_hz
        self._hb_type = heartbeat_type_for_component(cfg.source_component)

        self._state = _State()
        self._transport: Transport | None = None
        self._tx: Any = None  # pymavlink MAVLink used for sending (under _tx_lock)
        self._rx: Any = None  # pymavlink MAVLink used for parsing (reader thread only)
        self._tx_lock = threading.Lock()
        self._reader: threading.Thread | None = None
        self._stop_reader = threading.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._wakers: set[Callable[[], None]] = set()
        self._stream: _Stream | None = None
        self._stream_lock = threading.Lock()
        self._setpoints_sent = 0
        self._packets_sent = 0
        self._local_port = 0
        self._stops_sent = 0
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
        s = self._state
        now = self._clock.monotonic_s()
        with s.lock:
            return Telemetry(
                stamp_s=s.newest_s,
                armed=s.armed,
                mode=s.mode,
                custom_mode=s.custom_mode,
                landed_state=s.landed,
                pos_local_enu_m=s.pos_enu,
                vel_local_enu_m_s=s.vel_enu,
                R_local_body_quat_wxyz=s.quat_wxyz,
                yaw_local_rad=s.yaw_enu,
                battery=BatteryState(s.voltage_v, s.remaining_pct),
                heartbeat_age_s=max(0.0, now - s.hb_time_s),
            )

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
        return LinkStats(rx, rej, self._packets_sent, self._setpoints_sent, self._stops_sent, acks)

    @property
    def local_port(self) -> int:
        """Our local UDP/TCP port (0 before connect and for serial)."""
        return self._local_port

    @property
    def streaming(self) -> bool:
        """True while the setpoint stream runs."""
        return self._stream is not None

    @property
    def clock(self) -> Clock:
        return self._clock

    # ------------------------------------------------------------------ lifetime

    async def __aenter__(self) -> Self:
        await self.connect()
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.close()

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
        if self._transport is not None:
            return self.info
        self._loop = asyncio.get_running_loop()
        self._transport = await asyncio.to_thread(
            open_transport, self.endpoint, self._cfg.heartbeat_timeout_s
        )
        self._local_port = self._transport.local_port
        writer = _TransportWriter(self._transport)
        self._tx = mavlink2.MAVLink(writer, self._cfg.source_system, self._cfg.source_component)
        self._rx = mavlink2.MAVLink(None, self._cfg.source_system, self._cfg.source_component)
        self._rx.robust_parsing = True
        if self._signing is not None:
            now_ns = self._clock.time_ns()
            apply_signing(self._tx, self._signing, now_ns)
            apply_signing(self._rx, self._signing, now_ns)
        self._stop_reader.clear()
        self._reader = threading.Thread(
            target=self._read_loop, name=f"mavlink-reader {self.endpoint.url}", daemon=True
        )
        self._reader.start()
        logger.debug("listening on %s (local port %d)", self.endpoint.url, self.local_port)
        timeout_s = self._cfg.heartbeat_timeout_s
        try:
            info = await self._wait_until(
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
        self._spawn(self._request_streams())
        return info

    def _no_heartbeat_error(self, timeout_s: float) -> LinkTimeout:
        s = self._state
        with s.lock:
            rx, rejected, others = s.rx, s.rx_rejected, s.rx_other_components
        where = self.endpoint.url
        if self.endpoint.listens and self.endpoint.port == 0 and self._transport is not None:
            where += f" (local port {self._local_port})"
        msg = f"no HEARTBEAT on {where} after {timeout_s:.1f} s; is the autopilot/simulator running and link.url right?"
        if rejected:
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
        self._stop_reader.set()
        if self._reader is not None:
            await asyncio.to_thread(self._reader.join, 2.0)
            self._reader = None
        with self._tx_lock:
            self._tx = None
            if self._transport is not None:
                self._transport.close()
        logger.debug("closed %s", self.endpoint.url)

    def _spawn(self, coro: Any) -> None:
        task: asyncio.Task[None] = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    # ------------------------------------------------------------------ reader thread

    def _read_loop(self) -> None:
        transport = self._transport
        assert transport is not None
        next_hb_s = self._clock.monotonic_s()
        while not self._stop_reader.is_set():
            data = transport.recv(_READER_POLL_S)
            if data:
                try:
                    msgs = self._rx.parse_buffer(data) or []
                except Exception as exc:  # noqa: BLE001 - a bad packet must not kill the reader
                    logger.debug("MAVLink parse error: %s", exc)
                    msgs = []
                if msgs:
                    now = self._clock.monotonic_s()
                    for msg in msgs:
                        self._handle(msg, now)
                    self._wake()
            now = self._clock.monotonic_s()
            if now >= next_hb_s:
                self._send_heartbeat()
                next_hb_s = max(next_hb_s + 1.0, now + 0.5)

    def _send_heartbeat(self) -> None:
        self._send(
            mavlink2.MAVLink_heartbeat_message(
                self._hb_type, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE, 3
            )
        )

    def _handle(self, msg: Any, now: float) -> None:
        s = self._state
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            with s.lock:
                s.rx_rejected += 1
            return
        src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
        with s.lock:
            s.rx += 1
            if mtype == "HEARTBEAT":
                self._on_heartbeat(msg, src_sys, src_comp, now)
                return
            if s.target is None or src_sys != s.target[0]:
                return
            if mtype == "STATUSTEXT":
                text = str(msg.text).rstrip("\x00").rstrip()
                s.statustext.append((now, int(msg.severity), text))
                logger.info("autopilot: %s", text)
                return
            if src_comp != s.target[1]:
                return
            s.newest_s = now
            if mtype == "LOCAL_POSITION_NED":
                s.pos_enu = tuple(float(x) for x in ned_to_enu((msg.x, msg.y, msg.z)))  # type: ignore[assignment]
                s.vel_enu = tuple(float(x) for x in ned_to_enu((msg.vx, msg.vy, msg.vz)))  # type: ignore[assignment]
            elif mtype == "ATTITUDE_QUATERNION":
                self._set_attitude(Rotation.from_quat(quat_wxyz_to_xyzw([msg.q1, msg.q2, msg.q3, msg.q4])))
            elif mtype == "ATTITUDE":
                self._set_attitude(Rotation.from_euler("ZYX", [msg.yaw, msg.pitch, msg.roll]))
            elif mtype == "COMMAND_ACK":
                if msg.target_system in (0, self._cfg.source_system):
                    s.ack_seq += 1
                    s.acks[int(msg.command)] = (s.ack_seq, int(msg.result), now)
                    logger.debug("COMMAND_ACK %s: %s", _cmd_name(msg.command), _result_name(msg.result))
            elif mtype == "EXTENDED_SYS_STATE":
                try:
                    s.landed = LandedState(int(msg.landed_state))
                except ValueError:
                    s.landed = LandedState.UNDEFINED
            elif mtype == "SYS_STATUS":
                if msg.voltage_battery != 0xFFFF:
                    s.voltage_v = msg.voltage_battery / 1000.0
                s.remaining_pct = float(msg.battery_remaining) if msg.battery_remaining >= 0 else math.nan
            elif mtype == "BATTERY_STATUS":
                if msg.voltages[0] != 0xFFFF:
                    s.voltage_v = msg.voltages[0] / 1000.0
                s.remaining_pct = float(msg.battery_remaining) if msg.battery_remaining >= 0 else math.nan
            elif mtype == "GLOBAL_POSITION_INT":
                s.home_amsl_m = (msg.alt - msg.relative_alt) / 1000.0
            elif mtype == "HOME_POSITION":
                s.home_amsl_m = msg.altitude / 1000.0
            elif mtype == "AUTOPILOT_VERSION" and s.info is not None:
                v = int(msg.flight_sw_version)
                s.info = replace(
                    s.info, firmware_version=f"{(v >> 24) & 0xFF}.{(v >> 16) & 0xFF}.{(v >> 8) & 0xFF}"
                )

    def _on_heartbeat(self, msg: Any, src_sys: int, src_comp: int, now: float) -> None:
        """Called with the state lock held."""
        s = self._state
        autopilot = autopilot_from_heartbeat(int(msg.autopilot))
        if (
            src_comp != MAV_COMP_ID_AUTOPILOT1
            or autopilot is None
            or msg.type in (MAV_TYPE_GCS, MAV_TYPE_ONBOARD_CONTROLLER)
        ):
            s.rx_other_components += 1
            return
        if s.target is None:
            if self._target_system is not None and src_sys != self._target_system:
                s.rx_other_components += 1
                return
            s.target = (src_sys, src_comp)
            s.info = VehicleInfo(src_sys, src_comp, autopilot, int(msg.type))
            sender = self._transport.last_sender if self._transport is not None else None
            if sender is not None and self._transport is not None:
                self._transport.pin_peer(sender)
        elif (src_sys, src_comp) != s.target:
            s.rx_other_components += 1
            return
        s.newest_s = now
        s.hb_time_s = now
        armed = bool(msg.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)
        assert s.info is not None
        mode = decode_mode(s.info.autopilot, int(msg.base_mode), int(msg.custom_mode))
        if armed != s.armed:
            logger.info("vehicle %s", "armed" if armed else "disarmed")
        if mode != s.mode:
            logger.info("mode %s", mode.value)
        s.armed, s.mode = armed, mode
        s.base_mode, s.custom_mode = int(msg.base_mode), int(msg.custom_mode)

    def _set_attitude(self, R_ned_frd: Rotation) -> None:
        R_enu_flu = rotation_enu_flu_from_ned_frd(R_ned_frd)
        q = quat_xyzw_to_wxyz(R_enu_flu.as_quat())
        self._state.quat_wxyz = (float(q[0]), float(q[1]), float(q[2]), float(q[3]))
        self._state.yaw_enu = yaw_from_rotation(R_enu_flu)

    def _send(self, msg: Any) -> None:
        """Send one message (any thread)."""
        with self._tx_lock:
            if self._tx is None:
                return
            if self._signing is not None:
                # pymavlink counts the timestamp up by one per packet; keep it at least at "now"
                # so an autopilot that restarts still accepts us as a fresh stream.
                self._tx.signing.timestamp = max(
                    self._tx.signing.timestamp, signing_timestamp(self._clock.time_ns())
                )
            self._tx.send(msg)
            self._packets_sent += 1

    # ------------------------------------------------------------------ waiting

    def _wake(self) -> None:
        for wake in list(self._wakers):
            wake()

    async def _wait_until(
        self, probe: Callable[[], T | None], timeout_s: float, on_timeout: Callable[[], BaseException]
    ) -> T:
        """Wait until ``probe()`` returns something other than None (re-checked whenever a
        message arrives); raise ``on_timeout()`` after ``timeout_s`` of clock time."""
        result = probe()
        if result is not None:
            return result
        loop = asyncio.get_running_loop()
        event = asyncio.Event()

        def wake() -> None:
            try:
                loop.call_soon_threadsafe(event.set)
            except RuntimeError:  # loop closed
                pass

        self._wakers.add(wake)
        deadline = asyncio.ensure_future(self._clock.sleep(timeout_s))
        try:
            while True:
                event.clear()
                result = probe()
                if result is not None:
                    return result
                waiter = asyncio.ensure_future(event.wait())
                try:
                    await asyncio.wait({waiter, deadline}, return_when=asyncio.FIRST_COMPLETED)
                finally:
                    waiter.cancel()
                if deadline.done():
                    result = probe()
                    if result is not None:
                        return result
                    raise on_timeout()
        finally:
            self._wakers.discard(wake)
            deadline.cancel()

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

        return await self._wait_until(probe, timeout_s, timeout)

    # ------------------------------------------------------------------ commands

    def _require_target(self) -> tuple[int, int]:
        with self._state.lock:
            target = self._state.target
        if target is None or self._transport is None or self._closed:
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
        """Send COMMAND_LONG and return the final MAV_RESULT of its COMMAND_ACK.

        The command is re-sent (``confirmation`` counting up) when no ACK arrives within
        ``timeout_s / attempts``; IN_PROGRESS ACKs stop the retries and extend the wait
        by ``timeout_s`` for the final answer.

        Raises:
            LinkTimeout: no ACK after all attempts.
        """
        target = self._require_target()
        total_s = self._cfg.command_timeout_s if timeout_s is None else timeout_s
        per_attempt_s = total_s / max(1, attempts)
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        name = _cmd_name(command)
        for confirmation in range(attempts):
            with self._state.lock:
                seen = self._state.acks.get(command, (0, 0, 0.0))[0]
            self._send(
                mavlink2.MAVLink_command_long_message(target[0], target[1], command, confirmation & 0xFF, *p)
            )
            logger.debug("sent %s (attempt %d) params %s", name, confirmation + 1, p)
            try:
                seq, result = await self._wait_ack(command, seen, per_attempt_s)
            except LinkTimeout:
                continue
            while result == MAV_RESULT_IN_PROGRESS:
                seq, result = await self._wait_ack(command, seq, total_s)
            return result
        raise LinkTimeout(
            f"no COMMAND_ACK for {name} after {attempts} attempts in {total_s:.1f} s "
            f"(heartbeat age {self.telemetry.heartbeat_age_s:.1f} s); check the link and raise link.command_timeout_s "
            "if it is slow",
            what=f"COMMAND_ACK {name}",
            timeout_s=total_s,
        )

    async def _wait_ack(self, command: int, after_seq: int, timeout_s: float) -> tuple[int, int]:
        def probe() -> tuple[int, int] | None:
            with self._state.lock:
                entry = self._state.acks.get(command)
            if entry is None or entry[0] <= after_seq:
                return None
            return entry[0], entry[1]

        return await self._wait_until(
            probe,
            timeout_s,
            lambda: LinkTimeout(f"no COMMAND_ACK for {_cmd_name(command)}", "COMMAND_ACK", timeout_s),
        )

    async def _command_checked(
        self, command: int, params: tuple[float, ...], hint: str = "", **kw: Any
    ) -> None:
        """command_long, raising CommandRejected (with nearby STATUSTEXT) unless ACCEPTED."""
        sent_at = self._clock.monotonic_s()
        result = await self.command_long(command, params, **kw)
        if result != MAV_RESULT_ACCEPTED:
            raise await self._rejection(command, result, sent_at, hint)

    async def _rejection(self, command: int, result: int, sent_at: float, hint: str) -> CommandRejected:
        await self._clock.sleep(_REJECT_TEXT_GRACE_S)  # texts often trail the ACK by a few ms
        with self._state.lock:
            texts = tuple(
                t for when, _, t in self._state.statustext if when >= sent_at - _REJECT_TEXT_WINDOW_S
            )
        logger.info("%s refused: %s %s", _cmd_name(command), _result_name(result), "; ".join(texts))
        return CommandRejected(_cmd_name(command), _result_name(result), texts, hint)

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
        await self._command_checked(
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
        await self._command_checked(
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
            stream = self._stream
            if stream is None:
                raise LinkError(
                    "PX4 refuses OFFBOARD without a setpoint stream; call start_setpoint_stream() before "
                    "set_mode(FlightMode.OFFBOARD)"
                )
            warm_s = _PX4_OFFBOARD_WARMUP_S - (self._clock.monotonic_s() - stream.started_s)
            if warm_s > 0:
                await self._clock.sleep(warm_s)
        if self.telemetry.custom_mode == cmd.custom_mode:
            return
        await self._command_checked(
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
            await self._command_checked(
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
                raise await self._rejection(
                    mavlink2.MAV_CMD_NAV_TAKEOFF,
                    result,
                    sent_at,
                    f"ArduPilot still refused after {retry_s:.0f} s; check the EKF has a position (mocap, origin)",
                )
            logger.debug("NAV_TAKEOFF refused (%s); retrying", _result_name(result))
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

        return await self._wait_until(
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
        ``link.setpoint_rate_hz``) until :meth:`stop_setpoint_stream` or :meth:`close`.
        """
        self._require_target()
        rate = self._cfg.setpoint_rate_hz if rate_hz is None else float(rate_hz)
        if not (math.isfinite(rate) and 1.0 <= rate <= 1000.0):
            raise SetpointError(f"setpoint rate {rate_hz!r} Hz is outside 1-1000 Hz")
        with self._stream_lock:
            if self._stream is not None:
                return
            zero = VelocitySetpoint.zero()
            now = self._clock.monotonic_s()
            stop = threading.Event()
            thread = threading.Thread(target=self._stream_loop, name="mavlink-setpoints", daemon=True)
            self._stream = _Stream(rate, zero, encode_velocity_setpoint(zero), now, now, thread, stop)
            thread.start()
        logger.info("setpoint stream started at %.0f Hz", rate)

    async def stop_setpoint_stream(self) -> None:
        """Stop the stream and send one zero-velocity setpoint; idempotent."""
        with self._stream_lock:
            stream = self._stream
            self._stream = None
        if stream is None:
            return
        stream.stop.set()
        if stream.thread is not threading.current_thread():
            await asyncio.to_thread(stream.thread.join, 2.0)
        self._send_setpoint(encode_velocity_setpoint(VelocitySetpoint.zero(stream.setpoint.frame)))
        logger.info("setpoint stream stopped")

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
        check_hard_limits(setpoint)
        stream = self._stream
        if stream is None:
            raise LinkError("the setpoint stream is not running; call start_setpoint_stream() first")
        fields = encode_velocity_setpoint(setpoint)
        # One attribute write each; the stream thread reads them without a lock (fields first).
        stream.fields = fields
        stream.setpoint = setpoint
        now = self._clock.monotonic_s()
        stream.set_at_s = now
        if send_now and now - stream.sent_at_s >= 0.25 / stream.rate_hz:
            stream.sent_at_s = stream.pushed_at_s = now
            self._send_setpoint(fields)
            self._setpoints_sent += 1

    def _stream_loop(self) -> None:
        stream = self._stream
        assert stream is not None
        clock = self._clock
        period = 1.0 / stream.rate_hz
        timeout_s = self._cfg.setpoint_timeout_s
        next_s = clock.monotonic_s()
        stale_logged = False
        stops: dict[SetpointFrame, SetpointFields] = {
            f: encode_velocity_setpoint(VelocitySetpoint.zero(f)) for f in SetpointFrame
        }
        loop = self._loop
        while not stream.stop.is_set():
            if loop is not None and loop.is_closed():
                logger.warning("the event loop that owns the link is gone; stopping the setpoint stream")
                break
            now = clock.monotonic_s()
            if now - stream.set_at_s > timeout_s:
                if not stale_logged:
                    logger.warning(
                        "no set_velocity() for %.2f s (link.setpoint_timeout_s); sending zero velocity until the "
                        "next setpoint",
                        now - stream.set_at_s,
                    )
                    stale_logged = True
                self._send_setpoint(stops[stream.setpoint.frame])
                self._stops_sent += 1
                stream.sent_at_s = now
                self._setpoints_sent += 1
            elif now - stream.pushed_at_s >= period * 0.9:  # no send_now within the last period
                stale_logged = False
                stream.sent_at_s = now
                self._send_setpoint(stream.fields)
                self._setpoints_sent += 1
            else:
                stale_logged = False
            next_s += period
            now = clock.monotonic_s()
            if next_s < now - period:  # fell behind by more than a period (e.g. suspended): resync
                next_s = now
            clock.sleep_blocking(next_s - now)

    def _send_setpoint(self, f: SetpointFields) -> None:
        with self._state.lock:
            target = self._state.target
        if target is None:
            return
        t_ms = int((self._clock.monotonic_s() - self._t0_s) * 1000.0) & 0xFFFFFFFF
        self._send(
            mavlink2.MAVLink_set_position_target_local_ned_message(
                t_ms,
                target[0],
                target[1],
                f.coordinate_frame,
                f.type_mask,
                0.0,
                0.0,
                0.0,
                f.vx,
                f.vy,
                f.vz,
                0.0,
                0.0,
                0.0,
                f.yaw,
                f.yaw_rate,
            )
        )

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

    # ------------------------------------------------------------------ background

    async def _request_streams(self) -> None:
        """Ask for the telemetry we decode and for AUTOPILOT_VERSION; failures are logged only."""

        async def one(command: int, params: tuple[float, ...]) -> None:
            try:
                result = await self.command_long(command, params, attempts=2)
            except LinkError as exc:
                logger.debug("%s %s: %s", _cmd_name(command), params, exc)
                return
            if result != MAV_RESULT_ACCEPTED:
                logger.debug("%s %s refused: %s", _cmd_name(command), params, _result_name(result))

        await one(mavlink2.MAV_CMD_REQUEST_MESSAGE, (float(mavlink2.MAVLINK_MSG_ID_AUTOPILOT_VERSION),))
        for msg_id, rate in _STREAMS:
            await one(mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, (float(msg_id), 1e6 / rate))
