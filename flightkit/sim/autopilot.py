"""A simulated PX4 / ArduPilot autopilot speaking real MAVLink 2 over UDP.

:class:`SimAutopilot` binds a real UDP socket and behaves, as seen from the wire, like the
firmware its :class:`~flightkit.sim.personality.Personality` describes: heartbeats with the
firmware's custom-mode numbers, message streams whose rates clients can change, commands
answered with COMMAND_ACK, the parameter protocol, arming checks, take-off, landing, RTL,
velocity / position setpoints with the firmware's rules (PX4 OFFBOARD stream requirements
and loss failsafe, ArduPilot GUIDED timeout), external vision fusion, and MAVLink 2 signing.
It drives a :class:`~flightkit.sim.dynamics.QuadDynamics` on a :class:`~flightkit.clock.Clock`,
so a whole flight can run many times faster than real time.

Frames: the dynamics live in the lab's world frame (ENU). The autopilot's local frame has its
origin at the vehicle's start position and is rotated by ``heading_offset_rad`` about z
(``R_world_local = Rz(heading_offset_rad)``), as a real autopilot's north need not be the
lab's x axis. On the wire the local frame is NED, as MAVLink wants.

Threads: one receives datagrams and handles each message at once (so COMMAND_ACKs go out
without waiting for a tick); one runs the control loop (physics, modes, streams). Both take
one lock; nothing else in the process needs to know.
"""

from __future__ import annotations

import logging
import math
import socket
import struct
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from flightkit.clock import Clock, WallClock
from flightkit.errors import EndpointError
from flightkit.frames import wrap_angle_rad
from flightkit.link.base import FlightMode, LandedState
from flightkit.sim.dynamics import DynamicsState, MotorState, QuadDynamics
from flightkit.sim.personality import (
    MAV_FRAME_BODY_NED,
    MAV_FRAME_BODY_OFFSET_NED,
    MAV_FRAME_LOCAL_OFFSET_NED,
    LossAction,
    ParamType,
    Personality,
)

__all__ = ["AutopilotOptions", "SimAutopilot", "parse_endpoint"]

logger = logging.getLogger(__name__)

mav = mavlink2  # enums and message classes

# type_mask bits of SET_POSITION_TARGET_LOCAL_NED
_IGNORE_POS = 0b111
_IGNORE_VEL = 0b111000
_IGNORE_ACC = 0b111000000
_IGNORE_YAW = 1024
_IGNORE_YAW_RATE = 2048

_FORCE_ARM_MAGIC = 2989
_FORCE_DISARM_MAGIC = 21196
_EARTH_RADIUS_M = 6_378_137.0

# message id -> default rate (Hz) of the streams every client gets
DEFAULT_STREAM_RATES_HZ: Mapping[int, float] = {
    mav.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mav.MAVLINK_MSG_ID_SYS_STATUS: 2.0,
    mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 2.0,
    mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 30.0,
    mav.MAVLINK_MSG_ID_ATTITUDE: 20.0,
    mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 20.0,
    mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 10.0,
    mav.MAVLINK_MSG_ID_BATTERY_STATUS: 1.0,
    mav.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
    mav.MAVLINK_MSG_ID_VFR_HUD: 4.0,
}

_HOLD_LIKE = frozenset(
    {
        FlightMode.POSCTL,
        FlightMode.HOLD,
        FlightMode.LOITER,
        FlightMode.BRAKE,
        FlightMode.ALTCTL,
        FlightMode.STABILIZED,
        FlightMode.MANUAL,
    }
)
_NEEDS_POSITION_ARDUPILOT = frozenset(
    {FlightMode.GUIDED, FlightMode.LOITER, FlightMode.POSCTL, FlightMode.RTL, FlightMode.BRAKE}
)


def parse_endpoint(url: str) -> tuple[str, str, int]:
    """Split ``udpin:HOST:PORT`` / ``udpout:HOST:PORT`` (``://`` forms too) into (kind, host, port).

    Raises:
        EndpointError: when the string is not one of those forms.
    """
    text = url.strip()
    kind, sep, rest = text.partition(":")
    rest = rest.removeprefix("//")
    kind = kind.lower()
    if kind == "udp":
        kind = "udpin"
    host, _, port_s = rest.rpartition(":")
    if not sep or kind not in ("udpin", "udpout") or not host or not port_s.isdigit():
        raise EndpointError(
            f"simulator endpoint {url!r} is not understood; "
            "use udpin:HOST:PORT (listen) or udpout:HOST:PORT (send)"
        )
    port = int(port_s)
    if port > 65535 or (kind == "udpout" and port == 0):
        raise EndpointError(
            f"port {port} in {url!r} is not usable; give a port from 1 to 65535 (0 only for udpin)"
        )
    return kind, host, port


@dataclass(frozen=True, slots=True)
class AutopilotOptions:
    """Knobs of the simulated autopilot that are not firmware behaviour.

    Attributes:
        url: ``udpin:HOST:PORT`` (listen; answer every sender) or ``udpout:HOST:PORT`` (send
            to a listening client, as PX4 SITL does). Port 0 with udpin picks a free port.
        local_port: with udpout, the local port to send from (0 = any; PX4 SITL uses 14580).
        system_id, component_id: our MAVLink ids.
        ready_after_s: the estimator "converges" this long after start; before that, arming
            is refused with the firmware's reason (0 for tests).
        signing_key: 32-byte MAVLink 2 signing key; None = signing off.
        origin_lat_deg, origin_lon_deg, origin_alt_m: global position of the local origin.
        heading_offset_rad: rotation of the autopilot's local frame about world z.
        params: parameter overrides, e.g. ``{"COM_OF_LOSS_T": 0.5}``.
        stream_rates_hz: stream-rate overrides by MAVLink message id (0 = off).
        tick_wall_s: wall-clock period of the control loop.
        battery_endurance_s: flight time on a full battery (armed time).
        client_timeout_s: a udpin client silent this long (sim time) is forgotten.
    """

    url: str = "udpin:127.0.0.1:14540"
    local_port: int = 0
    system_id: int = 1
    component_id: int = 1
    ready_after_s: float = 2.0
    signing_key: bytes | None = None
    origin_lat_deg: float = 47.397742
    origin_lon_deg: float = 8.545594
    origin_alt_m: float = 488.0
    heading_offset_rad: float = 0.0
    params: Mapping[str, float] = field(default_factory=dict)
    stream_rates_hz: Mapping[int, float] = field(default_factory=dict)
    tick_wall_s: float = 0.005
    battery_endurance_s: float = 1200.0
    client_timeout_s: float = 60.0


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


class _SendFile:
    """The ``file`` a pymavlink encoder writes to: every current client gets every message."""

    def __init__(self, owner: SimAutopilot) -> None:
        self._owner = owner

    def write(self, buf: bytes) -> None:
        self._owner._sendto_all(bytes(buf))


class SimAutopilot:
    """A simulated autopilot on a real UDP socket.

    Args:
        personality: PX4 or ArduPilot behaviour (:mod:`flightkit.sim.personality`).
        dynamics: the vehicle it flies; its start position becomes the local origin.
        clock: time source for everything (physics, streams, timeouts).
        options: endpoint and non-firmware knobs.
        on_event: called as ``on_event(kind, detail)`` on state changes (armed, disarmed,
            mode, takeoff, landed, failsafe, ...), from the simulator's threads.

    ``start()`` binds the socket and starts the threads; ``stop()`` ends them.
    """

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
            raise ValueError(f"MAVLink signing key must be 32 bytes, got {len(key)}")
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
                raise ValueError(
                    f"unknown {personality.autopilot.value} parameter {name!r}; "
                    f"known: {', '.join(self._param_names)}"
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
        self._text_id = 0
        self._frames_warned: set[int] = set()
        self._failsafe = False
        self._link_dead_until = -math.inf
        self._battery_used_s = 0.0
        self._battery_override: float | None = None

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

    # ================================================================== lifecycle

    @property
    def bound_address(self) -> tuple[str, int]:
        """(host, port) of our socket; with ``udpin:...:0`` this is the port to connect to."""
        if self._bound is None:
            raise RuntimeError("SimAutopilot is not started; call start() first")
        return self._bound

    @property
    def url(self) -> str:
        """The endpoint as started (port 0 resolved)."""
        if self._kind == "udpin":
            return f"udpin:{self._host}:{self.bound_address[1]}"
        return f"udpout:{self._host}:{self._port}"

    @property
    def client_url(self) -> str:
        """What a client passes to connect to us (pymavlink style): ``udpout:HOST:PORT`` or ``udpin:...``."""
        if self._kind == "udpin":
            return f"udpout:{self._host}:{self.bound_address[1]}"
        return f"udpin:{self._host}:{self._port}"

    def start(self) -> None:
        """Bind the socket and start the receive and control threads; returns immediately.

        Raises:
            EndpointError: the address is in use or cannot be bound.
        """
        if self._running.is_set():
            return
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            if self._kind == "udpin":
                sock.bind((self._host, self._port))
            else:
                sock.bind(("0.0.0.0", self.options.local_port))
        except OSError as exc:
            sock.close()
            where = (
                f"{self._host}:{self._port}"
                if self._kind == "udpin"
                else f"local port {self.options.local_port}"
            )
            raise EndpointError(
                f"cannot bind the simulated autopilot to {where}: {exc.strerror or exc}; "
                "stop whatever uses that port (another sim or SITL?) or pick another port"
            ) from exc
        sock.settimeout(0.05)
        self._sock = sock
        self._bound = sock.getsockname()[:2]
        now = self.clock.monotonic_s()
        with self._lock:
            self._t0 = now
            self._last_tick_s = now
            if self._kind == "udpout":
                addr = (self._host, self._port)
                self._clients[addr] = _Client(addr, self._new_parser(), now, fixed=True)
            self._next_due = {m: now for m in self._intervals}
        self._running.set()
        self._threads = [
            threading.Thread(target=self._rx_loop, name="sim-autopilot-rx", daemon=True),
            threading.Thread(target=self._control_loop, name="sim-autopilot-loop", daemon=True),
        ]
        for t in self._threads:
            t.start()
        logger.info(
            "simulated %s autopilot on %s (bound %s:%d)",
            self.personality.autopilot.value,
            self.options.url,
            *self._bound,
        )

    def stop(self) -> None:
        """Stop the threads and close the socket; idempotent."""
        if not self._running.is_set():
            return
        self._running.clear()
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads = []
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        logger.info("simulated autopilot stopped")

    def __enter__(self) -> SimAutopilot:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ================================================================== public state

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

    # ================================================================== frames

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

    # ================================================================== sending

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

    # ================================================================== threads

    def _rx_loop(self) -> None:
        while self._running.is_set():
            sock = self._sock
            if sock is None:
                break
            try:
                data, addr = sock.recvfrom(65535)
            except TimeoutError:
                continue
            except OSError:
                if not self._running.is_set():
                    break
                continue
            now = self.clock.monotonic_s()
            if now < self._link_dead_until:
                continue
            with self._lock:
                client = self._clients.get(addr)
                if client is None:
                    if self._kind == "udpout":
                        # replies from the client's socket may come from another port
                        client = _Client(addr, self._new_parser(), now)
                    else:
                        client = _Client(addr, self._new_parser(), now)
                    self._clients[addr] = client
                    logger.info("new MAVLink client %s:%d", *addr)
                client.last_heard_s = now
                try:
                    msgs = client.parser.parse_buffer(data) or []
                except Exception as exc:  # corrupt input must never stop the simulator
                    logger.debug("unparsable datagram from %s: %s", addr, exc)
                    self.rejected_messages += 1
                    continue
                for msg in msgs:
                    if msg.get_type() == "BAD_DATA":
                        self.rejected_messages += 1
                        continue
                    try:
                        self._handle(msg, now)
                    except Exception:
                        logger.exception("handling %s failed", msg.get_type())

    def _control_loop(self) -> None:
        speed = self.clock.speed
        tick_sim_s = self.options.tick_wall_s * speed if math.isfinite(speed) else 0.01
        while self._running.is_set():
            now = self.clock.monotonic_s()
            with self._lock:
                try:
                    self._tick(now)
                except Exception:
                    logger.exception("simulator tick failed")
            self.clock.sleep_blocking(tick_sim_s)

    # ================================================================== control loop

    def _tick(self, now: float) -> None:
        dt = min(max(0.0, now - self._last_tick_s), 0.25)
        self._last_tick_s = now
        self._update_modes(now)
        self._command_dynamics(now)
        self.dynamics.step(dt)
        if self._armed:
            self._battery_used_s += dt
        self._update_estimator(now)
        self._update_ground_state(now)
        self._forget_clients(now)
        self._send_streams(now)

    def _forget_clients(self, now: float) -> None:
        stale = [
            a
            for a, c in self._clients.items()
            if not c.fixed and now - c.last_heard_s > self.options.client_timeout_s
        ]
        for addr in stale:
            del self._clients[addr]
            logger.info("MAVLink client %s:%d silent, forgotten", *addr)

    def _set_mode(self, mode: FlightMode, why: str = "") -> None:
        if mode is self._mode:
            return
        old = self._mode
        self._mode = mode
        self._hold_target = None
        self._hold_yaw = None
        self._landing = mode is self.personality.land_mode
        self._rtl_phase = "climb" if mode is self.personality.rtl_mode else ""
        if mode is not self.personality.takeoff_mode:
            self._takeoff_alt_local_m = None
        if mode is not self.personality.setpoint_mode:
            self._guided_target = None
        self._failsafe = why == "failsafe"
        self._event("mode", f"{old.value} -> {mode.value}{' (' + why + ')' if why else ''}")
        self._send_heartbeat(self.clock.monotonic_s())

    def _loss_timeout_s(self) -> float:
        return self._params[self.personality.loss_timeout_param]

    def _offboard_signal_ok(self, now: float) -> bool:
        """PX4: a setpoint stream has run for stream_required_s and is still alive."""
        sp, start = self._setpoint, self._stream_start_s
        if sp is None or start is None:
            return False
        fresh = now - sp.received_s <= min(self.personality.stream_max_gap_s, self._loss_timeout_s())
        return fresh and sp.received_s - start >= self.personality.stream_required_s - 1e-6

    def _update_modes(self, now: float) -> None:
        p = self.personality
        if not self._armed:
            return
        if p.loss_action is LossAction.FAILSAFE_MODE and self._mode is p.setpoint_mode:
            sp = self._setpoint
            if sp is None or now - sp.received_s > self._loss_timeout_s():
                action = int(self._params.get("COM_OBL_RC_ACT", 0))
                target = {
                    0: FlightMode.POSCTL,
                    1: FlightMode.ALTCTL,
                    2: FlightMode.STABILIZED,
                    3: FlightMode.RTL,
                    4: FlightMode.LAND,
                    5: FlightMode.HOLD,
                }.get(action, FlightMode.HOLD)
                self._failsafe = True
                self._statustext(p.text("offboard_lost"), mav.MAV_SEVERITY_CRITICAL)
                self._set_mode(target, "failsafe")
                self._event("failsafe", "offboard signal lost")
        # auto-disarm on the ground
        if self.dynamics.on_ground:
            if self._touchdown_s is not None:
                delay = self._disarm_after_land_s()
                if delay >= 0 and now - self._touchdown_s >= delay:
                    self._disarm(now, p.text("auto_disarm_land"), "landed")
            elif not self._was_airborne:
                delay = self._disarm_preflight_s()
                if delay > 0 and now - self._armed_at_s >= delay and self._takeoff_alt_local_m is None:
                    self._disarm(now, p.text("auto_disarm_preflight"), "preflight timeout")

    def _disarm_after_land_s(self) -> float:
        p = self.personality
        if "COM_DISARM_LAND" in self._params:
            return self._params["COM_DISARM_LAND"]
        if self._mode in (p.land_mode, p.rtl_mode):
            return p.disarm_after_land_s
        return self._params.get("DISARM_DELAY", p.disarm_after_land_s)

    def _disarm_preflight_s(self) -> float:
        if "COM_DISARM_PRFLT" in self._params:
            return self._params["COM_DISARM_PRFLT"]
        return self._params.get("DISARM_DELAY", self.personality.disarm_preflight_s)

    def _hold_command(self, now: float) -> tuple[npt.NDArray[np.float64], float | None, float | None]:
        """Brake, then hold the position where the vehicle stopped (local ENU velocity)."""
        est = self._est_pos_local()
        if self.dynamics.on_ground and not self._landing:
            return np.zeros(3), None, 0.0
        if self._hold_target is None:
            if float(np.linalg.norm(self._est_vel_local())) > 0.15:
                return np.zeros(3), None, 0.0
            self._hold_target = est.copy()
            self._hold_yaw = self._est_yaw_local()
        return self._goto(self._hold_target, 2.0, 1.0), self._hold_yaw, None

    def _goto(
        self, target_local: npt.NDArray[np.float64], max_xy: float, max_z: float
    ) -> npt.NDArray[np.float64]:
        err = target_local - self._est_pos_local()
        v = 1.2 * err
        vh = math.hypot(v[0], v[1])
        if vh > max_xy:
            v[:2] *= max_xy / vh
        v[2] = max(-max_z, min(max_z, v[2]))
        return v

    def _command_dynamics(self, now: float) -> None:
        p = self.personality
        if not self._armed:
            return
        vel_local = np.zeros(3)
        yaw_local: float | None = None
        yaw_rate: float | None = 0.0
        mode = self._mode

        if self._takeoff_alt_local_m is not None:
            est = self._est_pos_local()
            climb = self._params.get("MPC_TKO_SPEED", self._params.get("WPNAV_SPEED_UP", 250.0) / 100.0)
            if self._hold_target is None:
                self._hold_target = est.copy()
                self._hold_yaw = self._est_yaw_local()
            if (
                self.dynamics.motor_state()[0] is MotorState.SPINUP
                or est[2] < self._takeoff_alt_local_m - 0.05
            ):
                vel_local = self._goto(
                    np.array([self._hold_target[0], self._hold_target[1], est[2]]), 1.0, 0.0
                )
                remaining = self._takeoff_alt_local_m - est[2]
                vel_local[2] = max(0.3, min(climb, 1.5 * remaining))
                yaw_local, yaw_rate = self._hold_yaw, None
            else:
                self._hold_target = np.array(
                    [self._hold_target[0], self._hold_target[1], self._takeoff_alt_local_m]
                )
                self._takeoff_alt_local_m = None
                self._event("takeoff", "complete")
                if p.takeoff_mode is not None and mode is p.takeoff_mode:
                    self._set_mode(p.hold_mode, "takeoff complete")
                    return
        elif mode is p.land_mode or (mode is p.rtl_mode and self._rtl_phase == "land"):
            est = self._est_pos_local()
            if self._hold_target is None:
                self._hold_target = est.copy()
                self._hold_yaw = self._est_yaw_local()
            vel_local = self._goto(np.array([self._hold_target[0], self._hold_target[1], est[2]]), 1.0, 0.0)
            vel_local[2] = -self._land_speed()
            yaw_local, yaw_rate = self._hold_yaw, None
        elif mode is p.rtl_mode:
            vel_local, yaw_local, yaw_rate = self._rtl_command()
        elif mode is p.setpoint_mode:
            vel_local, yaw_local, yaw_rate = self._setpoint_command(now)
        elif mode in _HOLD_LIKE:
            vel_local, yaw_local, yaw_rate = self._hold_command(now)

        vel_world = self._est_to_world_vec(vel_local)
        yaw_world = None
        if yaw_local is not None:
            yaw_world = wrap_angle_rad(yaw_local - self._yaw_bias + self.options.heading_offset_rad)
        self.dynamics.command(
            vel_world, yaw_rad=yaw_world, yaw_rate_rad_s=None if yaw_world is not None else yaw_rate
        )

    def _land_speed(self) -> float:
        if "MPC_LAND_SPEED" in self._params:
            return self._params["MPC_LAND_SPEED"]
        if "LAND_SPEED" in self._params:
            return self._params["LAND_SPEED"] / 100.0
        return self.personality.land_speed_m_s

    def _rtl_command(self) -> tuple[npt.NDArray[np.float64], float | None, float | None]:
        est = self._est_pos_local()
        alt = self._params.get("RTL_RETURN_ALT", self._params.get("RTL_ALT", 1500.0) / 100.0)
        if self._hold_yaw is None:
            self._hold_yaw = self._est_yaw_local()
        if self._rtl_phase == "climb":
            if est[2] >= alt - 0.1 or self.dynamics.on_ground:
                self._rtl_phase = "return"
                self._statustext(self.personality.text("rtl", alt=max(alt, est[2])))
            target = np.array([est[0], est[1], max(alt, est[2])])
            return self._goto(target, 0.5, 2.0), self._hold_yaw, None
        if self._rtl_phase == "return":
            target = np.array([self._home_local_enu[0], self._home_local_enu[1], max(alt, est[2] - 0.0)])
            if math.hypot(est[0] - target[0], est[1] - target[1]) < 0.2:
                self._rtl_phase = "land"
                self._landing = True
                self._hold_target = None
            return self._goto(target, 3.0, 1.0), self._hold_yaw, None
        return np.zeros(3), self._hold_yaw, None

    def _setpoint_command(self, now: float) -> tuple[npt.NDArray[np.float64], float | None, float | None]:
        p = self.personality
        if p.loss_action is LossAction.FAILSAFE_MODE:
            sp = self._setpoint
            if sp is None:
                return self._hold_command(now)
        else:
            sp = self._guided_target
            if sp is None:
                return self._hold_command(now)
            if sp.pos_local_enu_m is None and now - sp.received_s > self._loss_timeout_s():
                # GUID_TIMEOUT: stop, brake, hover in GUIDED
                self._guided_target = None
                self._hold_target = None
                self._statustext(p.text("offboard_lost"), mav.MAV_SEVERITY_WARNING)
                self._event("failsafe", "velocity command timeout, braking")
                return self._hold_command(now)
        self._hold_target = None
        if sp.pos_local_enu_m is not None:
            vel = self._goto(sp.pos_local_enu_m, 3.0, 1.5)
            if sp.vel_local_enu_m_s is not None:
                vel = vel + sp.vel_local_enu_m_s
        else:
            assert sp.vel_local_enu_m_s is not None
            vel = sp.vel_local_enu_m_s.copy()
        if sp.yaw_local_enu_rad is not None:
            return vel, sp.yaw_local_enu_rad, None
        if sp.yaw_rate_enu_rad_s is not None:
            return vel, None, sp.yaw_rate_enu_rad_s
        # yaw not commanded: hold the current heading
        if self._hold_yaw is None:
            self._hold_yaw = self._est_yaw_local()
        return vel, self._hold_yaw, None

    def _update_ground_state(self, now: float) -> None:
        on_ground = self.dynamics.on_ground
        if not on_ground and self._armed:
            if not self._was_airborne:
                self._was_airborne = True
                self._statustext(self.personality.text("takeoff_detected"))
                self._event("airborne", "")
            self._touchdown_s = None
        elif on_ground and self._was_airborne and self._touchdown_s is None:
            self._touchdown_s = now
            self._was_airborne = False
            self._takeoff_alt_local_m = None
            self._statustext(self.personality.text("landed"))
            self._event("landed", "")

    def _landed_state(self) -> LandedState:
        if self.dynamics.on_ground:
            return LandedState.ON_GROUND
        if self._takeoff_alt_local_m is not None:
            return LandedState.TAKEOFF
        if self._landing or (self._mode is self.personality.rtl_mode and self._rtl_phase == "land"):
            return LandedState.LANDING
        return LandedState.IN_AIR

    # ================================================================== estimator

    def _ev_pos_enabled(self) -> bool:
        if "EKF2_EV_CTRL" in self._params:
            return int(self._params["EKF2_EV_CTRL"]) & 1 == 1
        return self._params.get("VISO_TYPE", 0) > 0 and int(self._params.get("EK3_SRC1_POSXY", 3)) == 6

    def _ev_yaw_enabled(self) -> bool:
        if "EKF2_EV_CTRL" in self._params:
            return int(self._params["EKF2_EV_CTRL"]) & 8 == 8
        return self._params.get("VISO_TYPE", 0) > 0 and int(self._params.get("EK3_SRC1_YAW", 1)) == 6

    def _update_estimator(self, now: float) -> None:
        active = self._ev_pos_enabled() and now - self._ev_last_s < 1.0
        if active != self._ev_active:
            self._ev_active = active
            self._statustext(self.personality.text("ev_fusion_on" if active else "ev_fusion_off"))
            self._event("vision", "fusing" if active else "stopped")
        if not self._ev_active:
            wander_world = self.dynamics.sensed_pos_enu_m() - self.dynamics.pos_enu_m
            self._est_bias = _rot_z(self._yaw_bias) @ self._world_to_local_vec(wander_world)

    def _fuse_vision(self, now: float, pos_ned: npt.NDArray[np.float64], yaw_ned: float | None) -> None:
        if not np.all(np.isfinite(pos_ned)):
            return
        self._ev_last_s = now
        if not self._ev_pos_enabled():
            return
        gain = 0.3
        meas_local = np.array([pos_ned[1], pos_ned[0], -pos_ned[2]])
        if not self._ev_active:
            gain = 1.0  # first measurement: the estimate jumps onto the vision frame
        est = self._est_pos_local()
        self._est_bias = self._est_bias + gain * (meas_local - est)
        if yaw_ned is not None and math.isfinite(yaw_ned) and self._ev_yaw_enabled():
            # align the estimator's frame with the vision frame; keep the position estimate continuous
            meas_yaw = wrap_angle_rad(math.pi / 2.0 - yaw_ned)
            before = self._est_pos_local()
            self._yaw_bias = wrap_angle_rad(
                self._yaw_bias + gain * wrap_angle_rad(meas_yaw - self._est_yaw_local())
            )
            self._est_bias = self._est_bias + (before - self._est_pos_local())

    # ================================================================== message handling

    def _handle(self, msg: Any, now: float) -> None:
        mtype = msg.get_type()
        if mtype == "HEARTBEAT":
            if msg.type == mav.MAV_TYPE_GCS:
                if not self._gcs_heard:
                    self._gcs_heard = True
                    logger.info(
                        "heard a GCS heartbeat from %d/%d", msg.get_srcSystem(), msg.get_srcComponent()
                    )
            return
        target_system = getattr(msg, "target_system", None)
        if target_system not in (None, 0, self.options.system_id):
            return
        target_component = getattr(msg, "target_component", None)
        if target_component not in (None, 0, self.options.component_id) and mtype not in (
            "SET_POSITION_TARGET_LOCAL_NED",
        ):
            return
        handler = _HANDLERS.get(mtype)
        if handler is not None:
            handler(self, msg, now)

    # ---------------------------------------------------------------- commands

    def _on_command_long(self, msg: Any, now: float) -> None:
        params = [msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7]
        self._command(msg, msg.command, params, now, is_int=False)

    def _on_command_int(self, msg: Any, now: float) -> None:
        params = [msg.param1, msg.param2, msg.param3, msg.param4, msg.x, msg.y, msg.z]
        self._command(msg, msg.command, params, now, is_int=True)

    def _command(self, msg: Any, command: int, params: list[float], now: float, is_int: bool) -> None:
        handler = _COMMANDS.get(command)
        if handler is None:
            logger.debug("unsupported command %d", command)
            self._ack(msg, command, mav.MAV_RESULT_UNSUPPORTED)
            return
        try:
            result = handler(self, msg, params, now, is_int)
        except Exception:
            logger.exception("command %d failed", command)
            result = mav.MAV_RESULT_FAILED
        if result is not None:
            self._ack(msg, command, result)

    def _cmd_arm_disarm(self, msg: Any, params: list[float], now: float, is_int: bool) -> int | None:
        p = self.personality
        if params[0] >= 0.5:
            if self._armed:
                return mav.MAV_RESULT_ACCEPTED
            force = _as_int(params[1]) == _FORCE_ARM_MAGIC
            if not force:
                reason = self._arming_refusal(now)
                if reason is not None:
                    self._ack(msg, mav.MAV_CMD_COMPONENT_ARM_DISARM, p.reject_result)
                    self._statustext(reason, mav.MAV_SEVERITY_CRITICAL)
                    self._event("arm_refused", reason)
                    return None
            self._arm(now)
            return mav.MAV_RESULT_ACCEPTED
        if not self._armed:
            return mav.MAV_RESULT_ACCEPTED
        force = _as_int(params[1]) == _FORCE_DISARM_MAGIC
        if not self.dynamics.on_ground and not force:
            self._statustext("Disarming denied: not landed", mav.MAV_SEVERITY_CRITICAL)
            return p.reject_result
        self._disarm(now, p.text("disarmed"), "forced" if force else "command")
        return mav.MAV_RESULT_ACCEPTED

    def _arming_refusal(self, now: float) -> str | None:
        p = self.personality
        if not self._ready(now):
            if p.loss_action is LossAction.FAILSAFE_MODE or self._mode in _NEEDS_POSITION_ARDUPILOT:
                return p.text("not_ready")
        if p.stream_required_s > 0.0 and self._mode is p.setpoint_mode and not self._offboard_signal_ok(now):
            return p.text("no_offboard")
        return None

    def _arm(self, now: float) -> None:
        self._armed = True
        self._armed_at_s = now
        self._touchdown_s = None
        self._was_airborne = not self.dynamics.on_ground
        self._hold_target = None
        self._hold_yaw = None
        self._home_local_enu = self._est_pos_local().copy()
        self._home_yaw_local = self._est_yaw_local()
        self.dynamics.set_armed(True)
        self._statustext(self.personality.text("armed"))
        self._event("armed", self._mode.value)
        self._send_heartbeat(now)

    def _disarm(self, now: float, text: str, why: str) -> None:
        self._armed = False
        self._touchdown_s = None
        self._was_airborne = False
        self._takeoff_alt_local_m = None
        self._guided_target = None
        self.dynamics.set_armed(False)
        self._statustext(text)
        self._event("disarmed", why)
        self._send_heartbeat(now)

    def _cmd_do_set_mode(self, msg: Any, params: list[float], now: float, is_int: bool) -> int | None:
        p = self.personality
        base_mode = _as_int(params[0])
        if not base_mode & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return mav.MAV_RESULT_UNSUPPORTED
        if p.autopilot.value == "px4":
            main, sub = _as_int(params[1]), _as_int(params[2])
            custom = main if main > 255 else (main << 16) | (sub << 24)
        else:
            custom = _as_int(params[1])
        return self._request_mode(custom, now)

    def _on_set_mode(self, msg: Any, now: float) -> None:
        result = self._request_mode(int(msg.custom_mode), now)
        if self.personality.ack_set_mode_message:
            self._ack(msg, mav.MAVLINK_MSG_ID_SET_MODE, result)

    def _request_mode(self, custom_mode: int, now: float) -> int:
        p = self.personality
        mode = p.mode_of(custom_mode)
        if mode is None:
            logger.info("unknown custom mode %d refused", custom_mode)
            return mav.MAV_RESULT_UNSUPPORTED if p.autopilot.value == "px4" else mav.MAV_RESULT_FAILED
        if mode is self._mode:
            return mav.MAV_RESULT_ACCEPTED
        in_air = not self.dynamics.on_ground
        if mode is p.setpoint_mode and p.stream_required_s > 0.0:
            if (in_air or self._armed) and not self._offboard_signal_ok(now):
                self._statustext(p.text("offboard_refused"), mav.MAV_SEVERITY_CRITICAL)
                self._event("mode_refused", mode.value)
                return p.reject_result
        if p.autopilot.value == "ardupilot" and mode in _NEEDS_POSITION_ARDUPILOT and not self._ready(now):
            self._statustext(
                f"Mode change to {mode.value} failed: requires position", mav.MAV_SEVERITY_WARNING
            )
            return p.reject_result
        if mode is p.takeoff_mode:
            alt = self._params.get("MIS_TAKEOFF_ALT", 2.5)
            self._start_takeoff(self._est_pos_local()[2] + alt if in_air else alt)
        self._set_mode(mode, "command")
        if mode is p.setpoint_mode and p.loss_action is LossAction.KEEP_THEN_BRAKE:
            self._guided_target = None
        return mav.MAV_RESULT_ACCEPTED

    def _start_takeoff(self, alt_local_m: float) -> None:
        self._takeoff_alt_local_m = alt_local_m
        self._hold_target = None

    def _cmd_takeoff(self, msg: Any, params: list[float], now: float, is_int: bool) -> int | None:
        p = self.personality
        if not self._ready(now):
            self._statustext(p.text("not_ready"), mav.MAV_SEVERITY_CRITICAL)
            return p.reject_result
        if p.takeoff_requires_armed and not self._armed:
            self._statustext(p.texts.get("takeoff_not_armed", "Takeoff: not armed"), mav.MAV_SEVERITY_WARNING)
            return p.reject_result
        if p.takeoff_requires_mode and self._mode not in p.takeoff_requires_mode:
            self._statustext(
                p.texts.get("takeoff_wrong_mode", "Takeoff: wrong mode"), mav.MAV_SEVERITY_WARNING
            )
            return p.reject_result
        if p.autopilot.value == "ardupilot" and not self.dynamics.on_ground:
            return p.reject_result  # ArduPilot: "already flying"
        alt_param = params[6]
        if p.takeoff_param7_amsl:
            min_alt = self._params.get("MIS_TAKEOFF_ALT", 2.5)
            if math.isfinite(alt_param):
                rel = alt_param - (self.options.origin_alt_m + self._home_local_enu[2])
                if rel < min_alt - 0.1:
                    self._statustext(p.text("takeoff_low", alt=min_alt), mav.MAV_SEVERITY_CRITICAL)
                rel = max(rel, min_alt)
            else:
                rel = min_alt
        else:
            rel = alt_param if math.isfinite(alt_param) else 0.0
            if rel <= 0.0:
                self._statustext(p.text("takeoff_low", alt=1.0), mav.MAV_SEVERITY_WARNING)
                rel = 1.0
        self._ack(msg, mav.MAV_CMD_NAV_TAKEOFF, mav.MAV_RESULT_ACCEPTED)
        base = float(self._home_local_enu[2])
        if p.takeoff_mode is not None:
            self._set_mode(p.takeoff_mode, "takeoff command")
        self._start_takeoff(base + rel)
        self._guided_target = None
        self._event("takeoff", f"to {rel:.2f} m")
        return None

    def _cmd_land(self, msg: Any, params: list[float], now: float, is_int: bool) -> int | None:
        self._set_mode(self.personality.land_mode, "land command")
        self._statustext(self.personality.text("landing"))
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_rtl(self, msg: Any, params: list[float], now: float, is_int: bool) -> int | None:
        if self.personality.autopilot.value == "ardupilot" and not self._ready(now):
            return self.personality.reject_result
        self._set_mode(self.personality.rtl_mode, "rtl command")
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_loiter(self, msg: Any, params: list[float], now: float, is_int: bool) -> int | None:
        mode = self.personality.hold_mode if self.personality.autopilot.value == "px4" else FlightMode.LOITER
        self._set_mode(mode, "loiter command")
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_reposition(self, msg: Any, params: list[float], now: float, is_int: bool) -> int | None:
        if not self._armed or self.dynamics.on_ground:
            return self.personality.reject_result
        lat, lon, alt = params[4], params[5], params[6]
        if is_int:
            lat, lon = lat / 1e7, lon / 1e7
        self._set_mode(self.personality.hold_mode, "reposition")
        est = self._est_pos_local()
        target = est.copy()
        if math.isfinite(lat) and math.isfinite(lon) and (lat != 0.0 or lon != 0.0):
            north = math.radians(lat - self.options.origin_lat_deg) * _EARTH_RADIUS_M
            east = (
                math.radians(lon - self.options.origin_lon_deg)
                * _EARTH_RADIUS_M
                * math.cos(math.radians(self.options.origin_lat_deg))
            )
            target[0], target[1] = east, north
        if math.isfinite(alt):
            target[2] = alt - self.options.origin_alt_m
        self._hold_target = target
        self._hold_yaw = self._est_yaw_local()
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_accept(self, msg: Any, params: list[float], now: float, is_int: bool) -> int | None:
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_terminate(self, msg: Any, params: list[float], now: float, is_int: bool) -> int | None:
        if params[0] >= 0.5:
            self._disarm(now, "Flight termination active", "termination")
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_set_message_interval(
        self, msg: Any, params: list[float], now: float, is_int: bool
    ) -> int | None:
        msg_id, interval_us = _as_int(params[0]), params[1]
        if msg_id not in _STREAM_BUILDERS:
            return mav.MAV_RESULT_DENIED
        if interval_us < 0:
            self._intervals.pop(msg_id, None)
        elif interval_us == 0:
            hz = DEFAULT_STREAM_RATES_HZ.get(msg_id)
            if hz is None:
                self._intervals.pop(msg_id, None)
            else:
                self._intervals[msg_id] = 1.0 / hz
        else:
            self._intervals[msg_id] = max(interval_us * 1e-6, 0.001)
        self._next_due[msg_id] = now
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_get_message_interval(
        self, msg: Any, params: list[float], now: float, is_int: bool
    ) -> int | None:
        msg_id = _as_int(params[0])
        if msg_id not in _STREAM_BUILDERS:
            interval = 0
        elif msg_id in self._intervals:
            interval = int(self._intervals[msg_id] * 1e6)
        else:
            interval = -1
        self._ack(msg, mav.MAV_CMD_GET_MESSAGE_INTERVAL, mav.MAV_RESULT_ACCEPTED)
        self._send(self._mav.message_interval_encode(msg_id, interval))
        return None

    def _cmd_request_message(self, msg: Any, params: list[float], now: float, is_int: bool) -> int | None:
        out = self._build_message(_as_int(params[0]), now, on_request=True)
        if out is None:
            return (
                mav.MAV_RESULT_UNSUPPORTED
                if _as_int(params[0]) not in _STREAM_BUILDERS
                else mav.MAV_RESULT_DENIED
            )
        self._ack(msg, mav.MAV_CMD_REQUEST_MESSAGE, mav.MAV_RESULT_ACCEPTED)
        self._send(out)
        return None

    def _cmd_request_version(self, msg: Any, params: list[float], now: float, is_int: bool) -> int | None:
        self._ack(msg, mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, mav.MAV_RESULT_ACCEPTED)
        self._send(self._autopilot_version())
        return None

    def _cmd_request_protocol(self, msg: Any, params: list[float], now: float, is_int: bool) -> int | None:
        self._ack(msg, mav.MAV_CMD_REQUEST_PROTOCOL_VERSION, mav.MAV_RESULT_ACCEPTED)
        self._send(self._protocol_version())
        return None

    # ---------------------------------------------------------------- setpoints

    def _on_set_position_target_local_ned(self, msg: Any, now: float) -> None:
        p = self.personality
        frame = int(msg.coordinate_frame)
        if frame not in p.accepted_frames:
            if frame not in self._frames_warned:
                self._frames_warned.add(frame)
                self._statustext(p.text("frame_rejected", frame=frame), mav.MAV_SEVERITY_WARNING)
            return
        mask = int(msg.type_mask)
        use_pos = mask & _IGNORE_POS != _IGNORE_POS
        use_vel = mask & _IGNORE_VEL != _IGNORE_VEL
        if not use_pos and not use_vel:
            return  # acceleration / force setpoints are not simulated
        yaw_est = self._est_yaw_local()
        est = self._est_pos_local()
        body = frame in (MAV_FRAME_BODY_NED, MAV_FRAME_BODY_OFFSET_NED)
        offset = frame in (MAV_FRAME_LOCAL_OFFSET_NED, MAV_FRAME_BODY_OFFSET_NED)

        def to_local_enu(x: float, y: float, z: float) -> npt.NDArray[np.float64]:
            if body:  # forward, right, down relative to the current heading
                c, s = math.cos(yaw_est), math.sin(yaw_est)
                return np.array([c * x + s * y, s * x - c * y, -z])
            return np.array([y, x, -z])  # NED -> ENU

        pos = vel = None
        if use_pos:
            pos = to_local_enu(msg.x, msg.y, msg.z)
            if body or offset:
                pos = est + pos
        if use_vel:
            vel = to_local_enu(msg.vx, msg.vy, msg.vz)
        yaw = yaw_rate = None
        if not mask & _IGNORE_YAW and math.isfinite(msg.yaw):
            if p.autopilot.value == "ardupilot" and frame == MAV_FRAME_BODY_OFFSET_NED:
                yaw = wrap_angle_rad(yaw_est - msg.yaw)  # relative, clockwise positive
            else:
                yaw = wrap_angle_rad(math.pi / 2.0 - msg.yaw)
        elif not mask & _IGNORE_YAW_RATE and math.isfinite(msg.yaw_rate):
            yaw_rate = -float(msg.yaw_rate)
        if (pos is not None and not np.all(np.isfinite(pos))) or (
            vel is not None and not np.all(np.isfinite(vel))
        ):
            return
        sp = _Setpoint(now, pos, vel, yaw, yaw_rate)
        if p.loss_action is LossAction.FAILSAFE_MODE:
            prev = self._setpoint
            if prev is None or self._stream_start_s is None or now - prev.received_s > p.stream_max_gap_s:
                self._stream_start_s = now
            self._setpoint = sp
            if yaw is not None or yaw_rate is not None:
                self._hold_yaw = None
        else:
            if self._mode is not p.setpoint_mode or not self._armed:
                return
            if self.dynamics.on_ground and self._takeoff_alt_local_m is None:
                return  # ArduPilot needs NAV_TAKEOFF first
            if self._takeoff_alt_local_m is not None:
                self._takeoff_alt_local_m = None  # a new target replaces the take-off
            self._guided_target = sp
            self._hold_yaw = None if (yaw is not None or yaw_rate is not None) else self._hold_yaw

    # ---------------------------------------------------------------- parameters

    def _param_value_msg(self, name: str) -> Any:
        spec = self.personality.params[name]
        value = self._params[name]
        if spec.type is ParamType.REAL32:
            wire = float(value)
        elif self.personality.param_bytewise:
            wire = struct.unpack("<f", struct.pack("<i", int(value)))[0]
        else:
            wire = float(int(value))
        return self._mav.param_value_encode(
            name.encode(), wire, int(spec.type), len(self._param_names), self._param_names.index(name)
        )

    def _on_param_request_list(self, msg: Any, now: float) -> None:
        for name in self._param_names:
            self._send(self._param_value_msg(name))

    def _on_param_request_read(self, msg: Any, now: float) -> None:
        name = _param_name(msg.param_id)
        if msg.param_index >= 0:
            if msg.param_index < len(self._param_names):
                name = self._param_names[msg.param_index]
        if name in self._params:
            self._send(self._param_value_msg(name))

    def _on_param_set(self, msg: Any, now: float) -> None:
        name = _param_name(msg.param_id)
        spec = self.personality.params.get(name)
        if spec is None:
            logger.info("PARAM_SET of unknown parameter %r ignored", name)
            return
        if spec.type is ParamType.REAL32 or not self.personality.param_bytewise:
            value = float(msg.param_value)
        else:
            value = float(struct.unpack("<i", struct.pack("<f", msg.param_value))[0])
        if spec.type is not ParamType.REAL32:
            value = float(round(value))
        if math.isfinite(value) and spec.min <= value <= spec.max:
            self._params[name] = value
            self._event("param", f"{name} = {value:g}")
        else:
            self._statustext(f"Param {name}: {value:g} out of range", mav.MAV_SEVERITY_WARNING)
        self._send(self._param_value_msg(name))

    # ---------------------------------------------------------------- other inbound

    def _on_timesync(self, msg: Any, now: float) -> None:
        if msg.tc1 == 0:
            self._send(self._mav.timesync_encode(self.clock.time_ns(), msg.ts1))

    def _on_vision_position_estimate(self, msg: Any, now: float) -> None:
        self._fuse_vision(now, np.array([msg.x, msg.y, msg.z], dtype=np.float64), float(msg.yaw))

    def _on_odometry(self, msg: Any, now: float) -> None:
        w, x, y, z = (float(v) for v in msg.q)
        yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)) if math.isfinite(w) else None
        self._fuse_vision(now, np.array([msg.x, msg.y, msg.z], dtype=np.float64), yaw)

    def _on_set_gps_global_origin(self, msg: Any, now: float) -> None:
        self._send(self._mav.gps_global_origin_encode(msg.latitude, msg.longitude, msg.altitude, 0))

    # ================================================================== outbound messages

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

    def _battery(self) -> tuple[float, float]:
        """(remaining fraction, voltage V) of the simulated 4S battery."""
        if self._battery_override is not None:
            frac = self._battery_override
        else:
            frac = max(0.0, 1.0 - self._battery_used_s / self.options.battery_endurance_s)
        volts = 4.0 * (3.5 + 0.7 * frac)
        return frac, volts

    def _sys_status(self, now: float) -> Any:
        sensors = (
            mav.MAV_SYS_STATUS_SENSOR_3D_GYRO
            | mav.MAV_SYS_STATUS_SENSOR_3D_ACCEL
            | mav.MAV_SYS_STATUS_SENSOR_3D_MAG
            | mav.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
            | mav.MAV_SYS_STATUS_SENSOR_GPS
            | mav.MAV_SYS_STATUS_AHRS
            | mav.MAV_SYS_STATUS_SENSOR_BATTERY
        )
        present = sensors | mav.MAV_SYS_STATUS_PREARM_CHECK
        if self._ev_pos_enabled():
            present |= mav.MAV_SYS_STATUS_SENSOR_VISION_POSITION
        health = (
            present
            if self._ready(now)
            else sensors & ~(mav.MAV_SYS_STATUS_SENSOR_GPS | mav.MAV_SYS_STATUS_AHRS)
        )
        frac, volts = self._battery()
        current_ca = 1500 if self._armed else 50
        return self._mav.sys_status_encode(
            present,
            present,
            health,
            250,
            int(volts * 1000),
            current_ca,
            int(round(frac * 100)),
            0,
            0,
            0,
            0,
            0,
            0,
        )

    def _battery_status(self, now: float) -> Any:
        frac, volts = self._battery()
        cell_mv = int(volts * 1000 / 4)
        voltages = [cell_mv] * 4 + [65535] * 6
        consumed_mah = int(self._battery_used_s / 3600.0 * 15_000)
        return self._mav.battery_status_encode(
            0,
            mav.MAV_BATTERY_FUNCTION_ALL,
            mav.MAV_BATTERY_TYPE_LIPO,
            2500,
            voltages,
            1500 if self._armed else 50,
            consumed_mah,
            -1,
            int(round(frac * 100)),
            int(frac * self.options.battery_endurance_s),
            mav.MAV_BATTERY_CHARGE_STATE_OK if frac > 0.2 else mav.MAV_BATTERY_CHARGE_STATE_LOW,
        )

    def _local_position_ned(self, now: float) -> Any:
        if not self._ready(now):
            return None
        pos = self._est_pos_local()
        vel = self._est_vel_local()
        return self._mav.local_position_ned_encode(
            self._time_boot_ms(now), pos[1], pos[0], -pos[2], vel[1], vel[0], -vel[2]
        )

    def _attitude_ned(self) -> tuple[float, float, float, float]:
        st = self.dynamics.state()
        yaw_ned = wrap_angle_rad(
            math.pi / 2.0 - (st.yaw_rad - self.options.heading_offset_rad + self._yaw_bias)
        )
        # FLU roll/pitch -> FRD roll (same sign) / pitch (opposite sign: FLU +pitch is nose down)
        return st.roll_rad, -st.pitch_rad, yaw_ned, -st.yaw_rate_rad_s

    def _attitude(self, now: float) -> Any:
        roll, pitch, yaw, yaw_rate = self._attitude_ned()
        return self._mav.attitude_encode(self._time_boot_ms(now), roll, pitch, yaw, 0.0, 0.0, yaw_rate)

    def _attitude_quaternion(self, now: float) -> Any:
        roll, pitch, yaw, yaw_rate = self._attitude_ned()
        cr, sr = math.cos(roll / 2), math.sin(roll / 2)
        cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
        cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
        q = (
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        )
        return self._mav.attitude_quaternion_encode(self._time_boot_ms(now), *q, 0.0, 0.0, yaw_rate)

    def _global_of_local(self, pos_local_enu: npt.NDArray[np.float64]) -> tuple[int, int, int]:
        lat0 = self.options.origin_lat_deg
        lat = lat0 + math.degrees(pos_local_enu[1] / _EARTH_RADIUS_M)
        lon = self.options.origin_lon_deg + math.degrees(
            pos_local_enu[0] / (_EARTH_RADIUS_M * math.cos(math.radians(lat0)))
        )
        alt_mm = int(round((self.options.origin_alt_m + pos_local_enu[2]) * 1000))
        return int(round(lat * 1e7)), int(round(lon * 1e7)), alt_mm

    def _global_position_int(self, now: float) -> Any:
        if not self._ready(now):
            return None
        pos = self._est_pos_local()
        vel = self._est_vel_local()
        lat, lon, alt = self._global_of_local(pos)
        rel = int(round((pos[2] - self._home_local_enu[2]) * 1000))
        hdg = (
            int(round(math.degrees(wrap_angle_rad(math.pi / 2 - self._est_yaw_local())) % 360 * 100)) % 36000
        )
        return self._mav.global_position_int_encode(
            self._time_boot_ms(now),
            lat,
            lon,
            alt,
            rel,
            int(vel[1] * 100),
            int(vel[0] * 100),
            int(-vel[2] * 100),
            hdg,
        )

    def _home_position(self, now: float) -> Any:
        if not self._ready(now):
            return None
        h = self._home_local_enu
        lat, lon, alt = self._global_of_local(h)
        yaw_ned = wrap_angle_rad(math.pi / 2 - self._home_yaw_local)
        q = (math.cos(yaw_ned / 2), 0.0, 0.0, math.sin(yaw_ned / 2))
        return self._mav.home_position_encode(
            lat,
            lon,
            alt,
            float(h[1]),
            float(h[0]),
            float(-h[2]),
            q,
            0.0,
            0.0,
            0.0,
            self.clock.time_ns() // 1000,
        )

    def _extended_sys_state(self, now: float) -> Any:
        return self._mav.extended_sys_state_encode(mav.MAV_VTOL_STATE_UNDEFINED, self._landed_state().value)

    def _vfr_hud(self, now: float) -> Any:
        pos = self._est_pos_local()
        vel = self._est_vel_local()
        hdg = int(round(math.degrees(wrap_angle_rad(math.pi / 2 - self._est_yaw_local())))) % 360
        throttle = 0 if not self._armed else (50 if not self.dynamics.on_ground else 10)
        return self._mav.vfr_hud_encode(
            0.0,
            float(math.hypot(vel[0], vel[1])),
            hdg,
            throttle,
            float(self.options.origin_alt_m + pos[2]),
            float(vel[2]),
        )

    def _autopilot_version(self) -> Any:
        caps = (
            mav.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
            | mav.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
            | mav.MAV_PROTOCOL_CAPABILITY_MISSION_INT
            | mav.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
            | mav.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
            | mav.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
            | mav.MAV_PROTOCOL_CAPABILITY_MAVLINK2
        )
        caps |= (
            mav.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
            if self.personality.param_bytewise
            else mav.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
        )
        major, minor, patch = self.personality.firmware_version
        sw = (major << 24) | (minor << 16) | (patch << 8) | 0xFF  # FIRMWARE_VERSION_TYPE_OFFICIAL
        return self._mav.autopilot_version_encode(
            caps,
            sw,
            0,
            0,
            0,
            [0] * 8,
            [0] * 8,
            [0] * 8,
            0,
            0,
            0x51A0 + self.options.system_id,
            [0] * 18,
        )

    def _protocol_version(self) -> Any:
        return self._mav.protocol_version_encode(200, 100, 200, [0] * 8, [0] * 8)

    def _build_message(self, msg_id: int, now: float, on_request: bool = False) -> Any:
        builder = _STREAM_BUILDERS.get(msg_id)
        if builder is not None:
            return builder(self, now)
        if msg_id == mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return self._autopilot_version()
        if msg_id == mav.MAVLINK_MSG_ID_PROTOCOL_VERSION:
            return self._protocol_version()
        if msg_id == mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN and self._ready(now):
            lat, lon, alt = self._global_of_local(np.zeros(3))
            return self._mav.gps_global_origin_encode(lat, lon, alt, self.clock.time_ns() // 1000)
        return None

    def _send_streams(self, now: float) -> None:
        if not self._clients:
            return
        for msg_id, interval in list(self._intervals.items()):
            due = self._next_due.get(msg_id, now)
            if now + 1e-9 < due:
                continue
            # keep the cadence; after a stall (or a long tick) skip missed slots instead of bursting
            nxt = due + interval
            if nxt <= now:
                nxt = now + interval
            self._next_due[msg_id] = nxt
            out = self._build_message(msg_id, now)
            if out is not None:
                self._send(out)


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


_HANDLERS: dict[str, Callable[[SimAutopilot, Any, float], None]] = {
    "COMMAND_LONG": SimAutopilot._on_command_long,
    "COMMAND_INT": SimAutopilot._on_command_int,
    "SET_MODE": SimAutopilot._on_set_mode,
    "SET_POSITION_TARGET_LOCAL_NED": SimAutopilot._on_set_position_target_local_ned,
    "PARAM_REQUEST_LIST": SimAutopilot._on_param_request_list,
    "PARAM_REQUEST_READ": SimAutopilot._on_param_request_read,
    "PARAM_SET": SimAutopilot._on_param_set,
    "TIMESYNC": SimAutopilot._on_timesync,
    "VISION_POSITION_ESTIMATE": SimAutopilot._on_vision_position_estimate,
    "ODOMETRY": SimAutopilot._on_odometry,
    "SET_GPS_GLOBAL_ORIGIN": SimAutopilot._on_set_gps_global_origin,
}

_COMMANDS: dict[int, Callable[[SimAutopilot, Any, list[float], float, bool], int | None]] = {
    mav.MAV_CMD_COMPONENT_ARM_DISARM: SimAutopilot._cmd_arm_disarm,
    mav.MAV_CMD_DO_SET_MODE: SimAutopilot._cmd_do_set_mode,
    mav.MAV_CMD_NAV_TAKEOFF: SimAutopilot._cmd_takeoff,
    mav.MAV_CMD_NAV_LAND: SimAutopilot._cmd_land,
    mav.MAV_CMD_NAV_RETURN_TO_LAUNCH: SimAutopilot._cmd_rtl,
    mav.MAV_CMD_NAV_LOITER_UNLIM: SimAutopilot._cmd_loiter,
    mav.MAV_CMD_DO_REPOSITION: SimAutopilot._cmd_reposition,
    mav.MAV_CMD_DO_CHANGE_SPEED: SimAutopilot._cmd_accept,
    mav.MAV_CMD_DO_SET_HOME: SimAutopilot._cmd_accept,
    mav.MAV_CMD_DO_FLIGHTTERMINATION: SimAutopilot._cmd_terminate,
    mav.MAV_CMD_SET_MESSAGE_INTERVAL: SimAutopilot._cmd_set_message_interval,
    mav.MAV_CMD_GET_MESSAGE_INTERVAL: SimAutopilot._cmd_get_message_interval,
    mav.MAV_CMD_REQUEST_MESSAGE: SimAutopilot._cmd_request_message,
    mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: SimAutopilot._cmd_request_version,
    mav.MAV_CMD_REQUEST_PROTOCOL_VERSION: SimAutopilot._cmd_request_protocol,
}

_STREAM_BUILDERS: dict[int, Callable[[SimAutopilot, float], Any]] = {
    mav.MAVLINK_MSG_ID_HEARTBEAT: SimAutopilot._heartbeat,
    mav.MAVLINK_MSG_ID_SYS_STATUS: SimAutopilot._sys_status,
    mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: SimAutopilot._extended_sys_state,
    mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: SimAutopilot._local_position_ned,
    mav.MAVLINK_MSG_ID_ATTITUDE: SimAutopilot._attitude,
    mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: SimAutopilot._attitude_quaternion,
    mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: SimAutopilot._global_position_int,
    mav.MAVLINK_MSG_ID_BATTERY_STATUS: SimAutopilot._battery_status,
    mav.MAVLINK_MSG_ID_HOME_POSITION: SimAutopilot._home_position,
    mav.MAVLINK_MSG_ID_VFR_HUD: SimAutopilot._vfr_hud,
}
