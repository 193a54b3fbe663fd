"""State, frames and sending of the simulated autopilot (the base its behaviour builds on).

:class:`_AutopilotCore` holds everything the simulated firmware knows (parameters, flight
state, estimator state, stream intervals, clients), the frame conversions between the lab's
world frame (ENU) and the autopilot's local frame, and the sending side: one pymavlink
encoder whose output goes to every current client, STATUSTEXT (chunked, PX4's GCS rule),
COMMAND_ACK, HEARTBEAT, and the event hook. The behaviour is layered on top of it, one
concern per module: :mod:`.flight` (modes, control, estimator) < :mod:`.telemetry`
(outbound messages and streams) < :mod:`.commands` (inbound messages) < :mod:`.server`
(:class:`~flightkit.sim.autopilot.SimAutopilot`: socket, threads, control loop).
"""

from __future__ import annotations

import logging
import math
import socket
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from flightkit.clock import Clock, WallClock
from flightkit.errors import SimError
from flightkit.frames import wrap_angle_rad
from flightkit.link.base import FlightMode
from flightkit.sim.autopilot.options import DEFAULT_STREAM_RATES_HZ, AutopilotOptions, parse_endpoint
from flightkit.sim.dynamics import DynamicsState, QuadDynamics
from flightkit.sim.personality import (
    Personality,
)
from flightkit.sim.posctl import VelocityShaper

logger = logging.getLogger(__name__)

mav = mavlink2  # enums and message classes


_EARTH_RADIUS_M = 6_378_137.0

_NEEDS_POSITION_ARDUPILOT = frozenset(
    {FlightMode.GUIDED, FlightMode.LOITER, FlightMode.POSCTL, FlightMode.RTL, FlightMode.BRAKE}
)


@dataclass(slots=True)
class _Client:
    addr: tuple[str, int]
    parser: Any
    last_heard_s: float
    fixed: bool = False


@dataclass(slots=True)
class _Setpoint:
    """A decoded SET_POSITION_TARGET_LOCAL_NED, in the local ENU frame."""

    received_s: float
    pos_local_enu_m: npt.NDArray[np.float64] | None
    vel_local_enu_m_s: npt.NDArray[np.float64] | None
    yaw_local_enu_rad: float | None
    yaw_rate_enu_rad_s: float | None
    accel_local_enu_m_s2: npt.NDArray[np.float64] | None = None


class _SendFile:
    """The ``file`` a pymavlink encoder writes to: every current client gets every message."""

    def __init__(self, owner: _AutopilotCore) -> None:
        self._owner = owner

    def write(self, buf: bytes) -> None:
        self._owner._sendto_all(bytes(buf))


def _as_int(value: float, default: int = 0) -> int:
    """A command parameter as an int; NaN (MAVLink's "unused") gives ``default``."""
    return int(round(value)) if math.isfinite(value) else default


def _param_name(raw: Any) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return str(raw).rstrip("\x00")


def _rot_z(angle_rad: float) -> npt.NDArray[np.float64]:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class _AutopilotCore:
    """State, frames and sending; see the module docstring and :class:`~flightkit.sim.autopilot.SimAutopilot`."""

    def __init__(
        self,
        personality: Personality,
        dynamics: QuadDynamics | None = None,
        clock: Clock | None = None,
        options: AutopilotOptions | None = None,
        on_event: Callable[[str, str], None] | None = None,
    ) -> None:
        self.personality = personality
        self.dynamics = dynamics or QuadDynamics()
        self.clock: Clock = clock or WallClock()
        self.options = options or AutopilotOptions()
        self._on_event = on_event
        self._lock = threading.RLock()
        self._send_lock = threading.Lock()
        self._running = threading.Event()
        self._threads: list[threading.Thread] = []
        self._sock: socket.socket | None = None
        self._clients: dict[tuple[str, int], _Client] = {}
        self._kind, self._host, self._port = parse_endpoint(self.options.url)
        self._bound: tuple[str, int] | None = None

        # encoder for everything we send
        self._mav = mavlink2.MAVLink(_SendFile(self), self.options.system_id, self.options.component_id)
        key = self.options.signing_key
        if key is not None and len(key) != 32:
            raise SimError(
                f"MAVLink signing key must be 32 bytes, got {len(key)}; give 64 hex digits as the signing key",
            )
        if key is not None:
            self._mav.signing.secret_key = key
            self._mav.signing.sign_outgoing = True
            self._mav.signing.link_id = 0
        self.rejected_messages = 0  # unsigned / badly signed / corrupt datagrams dropped

        # parameters
        self._param_names = sorted(personality.params)
        self._params: dict[str, float] = {n: float(s.default) for n, s in personality.params.items()}
        for name, value in self.options.params.items():
            if name not in self._params:
                raise SimError(
                    f"unknown {personality.autopilot.value} parameter {name!r}; "
                    f"use one of: {', '.join(self._param_names)}"
                )
            self._params[name] = float(value)

        # frames
        self._R_world_local = _rot_z(self.options.heading_offset_rad)
        self._origin_world = self.dynamics.pos_enu_m.copy()
        self._home_local_enu = np.zeros(3)
        self._home_yaw_local = 0.0

        # flight state
        self._t0 = 0.0
        self._last_tick_s = 0.0
        self._mode = personality.boot_mode
        self._armed = False
        self._armed_at_s = 0.0
        self._was_airborne = False
        self._touchdown_s: float | None = None
        self._takeoff_alt_local_m: float | None = None  # climbing to this (local up)
        self._landing = False
        self._rtl_phase = ""
        self._hold_target: npt.NDArray[np.float64] | None = None
        self._hold_yaw: float | None = None
        self._guided_target: _Setpoint | None = None
        self._setpoint: _Setpoint | None = None
        self._stream_start_s: float | None = None
        self._gcs_heard = False
        self._gcs_seen_s: float | None = None  # last HEARTBEAT from MAV_GCS_SYSID (ArduPilot)
        self._gcs_failsafe = False
        self._land_pause_until_s = -math.inf  # ArduCopter's failsafe LAND holds this long first
        self._text_id = 0
        self._frames_warned: set[int] = set()
        self._failsafe = False
        self._link_dead_until = -math.inf
        self._battery_used_s = 0.0
        self._battery_override: float | None = None
        self._takeoff_cmd_s = -math.inf
        self._shaper = VelocityShaper()
        self._shaper_last_s: float | None = None

        # estimator
        self._est_bias = np.zeros(3)  # local ENU, estimate - truth
        self._yaw_bias = 0.0
        self._ev_last_s = -math.inf
        self._ev_active = False

        # streams
        self._intervals: dict[int, float] = {}
        for msg_id, hz in DEFAULT_STREAM_RATES_HZ.items():
            self._intervals[msg_id] = 1.0 / hz
        for msg_id, hz in self.options.stream_rates_hz.items():
            if hz <= 0.0:
                self._intervals.pop(msg_id, None)
            else:
                self._intervals[msg_id] = 1.0 / hz
        self._next_due: dict[int, float] = {}

    @property
    def mode(self) -> FlightMode:
        with self._lock:
            return self._mode

    @property
    def armed(self) -> bool:
        with self._lock:
            return self._armed

    @property
    def custom_mode(self) -> int:
        with self._lock:
            return self.personality.custom_modes[self._mode]

    def param(self, name: str) -> float:
        with self._lock:
            return self._params[name]

    def set_param(self, name: str, value: float) -> None:
        """Set a parameter locally (as if a GCS had set it)."""
        with self._lock:
            if name not in self._params:
                raise KeyError(name)
            self._params[name] = float(value)

    def truth(self) -> DynamicsState:
        """The true vehicle state (world frame), consistent with the last tick."""
        with self._lock:
            return self.dynamics.state()

    def truth_stamped(self) -> tuple[DynamicsState, float]:
        """The true state and the clock time (``monotonic_s``) it belongs to."""
        with self._lock:
            return self.dynamics.state(), self._last_tick_s

    @property
    def vision_fusion_active(self) -> bool:
        """True while external vision poses drive the position estimate."""
        return self._ev_active

    def estimate_local_enu_m(self) -> npt.NDArray[np.float64]:
        """The autopilot's position estimate in its local frame, ENU."""
        with self._lock:
            return self._est_pos_local()

    @property
    def clients(self) -> list[tuple[str, int]]:
        with self._lock:
            return list(self._clients)

    def kill_link(self, duration_s: float) -> None:
        """Drop all MAVLink traffic, both ways, for ``duration_s`` of sim time."""
        with self._lock:
            self._link_dead_until = self.clock.monotonic_s() + duration_s
        self._event("link_killed", f"{duration_s:.2f} s")

    def inject_gust(self, peak_enu_m_s: npt.ArrayLike, duration_s: float = 2.0) -> None:
        with self._lock:
            self.dynamics.inject_gust(peak_enu_m_s, duration_s)

    def set_battery_remaining(self, fraction: float | None) -> None:
        """Override the battery charge (0-1); None returns to the simulated discharge."""
        with self._lock:
            self._battery_override = None if fraction is None else min(1.0, max(0.0, fraction))

    def _battery_endurance_s(self) -> float:
        endurance = self.options.battery_endurance_s
        return self.personality.battery_endurance_s if endurance is None else endurance

    def _world_to_local_vec(self, v_world: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        return self._R_world_local.T @ v_world

    def _local_to_world_vec(self, v_local: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        return self._R_world_local @ v_local

    def _truth_local(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], float]:
        d = self.dynamics
        pos = self._world_to_local_vec(d.pos_enu_m - self._origin_world)
        vel = self._world_to_local_vec(d.vel_enu_m_s)
        yaw = wrap_angle_rad(d.yaw_rad - self.options.heading_offset_rad)
        return pos, vel, yaw

    def _est_pos_local(self) -> npt.NDArray[np.float64]:
        """Position estimate: the truth seen in the estimator's frame (rotated by the
        vision yaw alignment), plus the estimator's error."""
        return _rot_z(self._yaw_bias) @ self._truth_local()[0] + self._est_bias

    def _est_vel_local(self) -> npt.NDArray[np.float64]:
        return _rot_z(self._yaw_bias) @ self._truth_local()[1]

    def _est_to_world_vec(self, v_est: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        return self._local_to_world_vec(_rot_z(-self._yaw_bias) @ v_est)

    def _est_yaw_local(self) -> float:
        return wrap_angle_rad(self._truth_local()[2] + self._yaw_bias)

    def _ready(self, now: float) -> bool:
        return now - self._t0 >= self.options.ready_after_s

    def _new_parser(self) -> Any:
        parser = mavlink2.MAVLink(None, 0, 0)
        parser.robust_parsing = True
        if self.options.signing_key is not None:
            parser.signing.secret_key = self.options.signing_key
            parser.signing.allow_unsigned_callback = None
        return parser

    def _sendto_all(self, buf: bytes) -> None:
        sock = self._sock
        if sock is None:
            return
        for addr in list(self._clients):
            try:
                sock.sendto(buf, addr)
            except OSError as exc:  # e.g. network unreachable; the client may come back
                logger.debug("send to %s failed: %s", addr, exc)

    def _send(self, msg: Any) -> None:
        if self.clock.monotonic_s() < self._link_dead_until or not self._clients:
            return
        with self._send_lock:
            if self._mav.signing.sign_outgoing:
                # signing timestamps: 10 us units since 2015-01-01
                stamp = (self.clock.time_ns() // 1000 - 1_420_070_400_000_000) // 10
                self._mav.signing.timestamp = max(self._mav.signing.timestamp, stamp)
            self._mav.send(msg)

    def _statustext(self, text: str, severity: int = mav.MAV_SEVERITY_INFO) -> None:
        logger.info("statustext: %s", text)
        if self.personality.statustext_needs_gcs and not self._gcs_heard:
            return
        data = (text + self.personality.statustext_suffix).encode("utf-8", "replace")
        if len(data) <= 50:
            self._send(self._mav.statustext_encode(severity, data))
            return
        # longer texts go out in 50-byte chunks sharing one id (MAVLink 2 STATUSTEXT chunking)
        self._text_id = self._text_id % 65535 + 1
        for seq, start in enumerate(range(0, len(data), 50)):
            self._send(self._mav.statustext_encode(severity, data[start : start + 50], self._text_id, seq))

    def _ack(self, msg: Any, command: int, result: int) -> None:
        self._send(
            self._mav.command_ack_encode(command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())
        )

    def _event(self, kind: str, detail: str = "") -> None:
        logger.info("sim %s %s", kind, detail)
        if self._on_event is not None:
            try:
                self._on_event(kind, detail)
            except Exception:  # an observer must not kill the simulator
                logger.exception("sim event hook failed for %s", kind)

    def _time_boot_ms(self, now: float) -> int:
        return int((now - self._t0) * 1000.0) & 0xFFFFFFFF

    def _send_heartbeat(self, now: float) -> None:
        self._send(self._heartbeat(now))

    def _heartbeat(self, now: float) -> Any:
        p = self.personality
        base = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self._armed:
            base |= mav.MAV_MODE_FLAG_SAFETY_ARMED
        if p.autopilot.value == "px4":
            if self._mode in (
                FlightMode.OFFBOARD,
                FlightMode.TAKEOFF,
                FlightMode.HOLD,
                FlightMode.LAND,
                FlightMode.RTL,
            ):
                base |= mav.MAV_MODE_FLAG_AUTO_ENABLED | mav.MAV_MODE_FLAG_GUIDED_ENABLED
            else:
                base |= mav.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
            base |= mav.MAV_MODE_FLAG_STABILIZE_ENABLED
        else:
            base |= mav.MAV_MODE_FLAG_STABILIZE_ENABLED | mav.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
            if self._mode is FlightMode.GUIDED:
                base |= mav.MAV_MODE_FLAG_GUIDED_ENABLED
        if self._failsafe and self._armed and p.autopilot.value == "px4":
            status = mav.MAV_STATE_CRITICAL
        else:
            status = mav.MAV_STATE_ACTIVE if self._armed else mav.MAV_STATE_STANDBY
        return self._mav.heartbeat_encode(
            mav.MAV_TYPE_QUADROTOR, p.mav_autopilot, base, p.custom_modes[self._mode], status, 3
        )
