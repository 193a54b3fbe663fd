"""Vehicle state of the pymavlink backend: decoding what the autopilot sends, and waiting on it.

:class:`VehicleState` is written by the link's reader thread (:meth:`VehicleState.handle`,
one call per received message, always under :attr:`VehicleState.lock`) and read by the
asyncio side: :meth:`VehicleState.telemetry` takes a snapshot, and
:meth:`VehicleState.wait_until` waits, with a clock timeout, for a probe to return
something; the reader thread calls :meth:`VehicleState.wake` after each batch of messages so
waiters re-check at once.

Frames: LOCAL_POSITION_NED and the attitude arrive in NED/FRD and are stored in ENU/FLU
(through :mod:`flightkit.frames`).
"""

from __future__ import annotations

import asyncio
import collections
import logging
import math
import threading
from collections.abc import Callable
from dataclasses import replace
from typing import Any, TypeVar

from scipy.spatial.transform import Rotation

from flightkit.clock import Clock
from flightkit.frames import (
    ned_to_enu,
    quat_wxyz_to_xyzw,
    quat_xyzw_to_wxyz,
    rotation_enu_flu_from_ned_frd,
    yaw_from_rotation,
)
from flightkit.link.base import BatteryState, FlightMode, LandedState, Telemetry, VehicleInfo
from flightkit.link.mavlink.encoding import (
    MAV_COMP_ID_AUTOPILOT1,
    MAV_TYPE_GCS,
    MAV_TYPE_ONBOARD_CONTROLLER,
    cmd_name,
    result_name,
)
from flightkit.link.modes import MAV_MODE_FLAG_SAFETY_ARMED, autopilot_from_heartbeat, decode_mode

__all__ = ["VehicleState"]

logger = logging.getLogger(__name__)

T = TypeVar("T")

_STATUSTEXT_KEEP = 200


class VehicleState:
    """Vehicle state written by the reader thread (always under ``lock``).

    Args:
        clock: time source of :meth:`telemetry` and :meth:`wait_until`.
        source_system: our system id (COMMAND_ACKs addressed elsewhere are ignored).
        target_system: accept only this autopilot system id (None: the first heartbeat's).
        on_target: called (under the lock, from the reader thread) when the first autopilot
            heartbeat picks the target.
    """

    def __init__(
        self,
        clock: Clock,
        source_system: int,
        target_system: int | None = None,
        on_target: Callable[[], None] | None = None,
    ) -> None:
        self._clock = clock
        self._source_system = source_system
        self._target_system = target_system
        self._on_target = on_target
        self._wakers: set[Callable[[], None]] = set()
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
        self.params: dict[str, tuple[float, int]] = {}  # PARAM_VALUE: name -> (wire value, MAV_PARAM_TYPE)
        self.rx = 0
        self.rx_rejected = 0
        self.rx_other_components = 0
        self.other_systems: set[int] = set()  # autopilots heard that are not the target

    def telemetry(self) -> Telemetry:
        """A snapshot of the latest state; returns immediately."""
        now = self._clock.monotonic_s()
        with self.lock:
            return Telemetry(
                stamp_s=self.newest_s,
                armed=self.armed,
                mode=self.mode,
                custom_mode=self.custom_mode,
                landed_state=self.landed,
                pos_local_enu_m=self.pos_enu,
                vel_local_enu_m_s=self.vel_enu,
                R_local_body_quat_wxyz=self.quat_wxyz,
                yaw_local_rad=self.yaw_enu,
                battery=BatteryState(self.voltage_v, self.remaining_pct),
                heartbeat_age_s=max(0.0, now - self.hb_time_s),
            )

    # ------------------------------------------------------------------ decoding (reader thread)

    def handle(self, msg: Any, now: float) -> None:
        """Fold one received message into the state (reader thread; takes the lock)."""
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            with self.lock:
                self.rx_rejected += 1
            return
        src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
        with self.lock:
            self.rx += 1
            if mtype == "HEARTBEAT":
                self._on_heartbeat(msg, src_sys, src_comp, now)
                return
            if self.target is None or src_sys != self.target[0]:
                return
            if mtype == "STATUSTEXT":
                text = str(msg.text).rstrip("\x00").rstrip()
                self.statustext.append((now, int(msg.severity), text))
                logger.info("autopilot: %s", text)
                return
            if src_comp != self.target[1]:
                return
            self.newest_s = now
            if mtype == "LOCAL_POSITION_NED":
                self.pos_enu = tuple(float(x) for x in ned_to_enu((msg.x, msg.y, msg.z)))  # type: ignore[assignment]
                self.vel_enu = tuple(float(x) for x in ned_to_enu((msg.vx, msg.vy, msg.vz)))  # type: ignore[assignment]
            elif mtype == "ATTITUDE_QUATERNION":
                self._set_attitude(Rotation.from_quat(quat_wxyz_to_xyzw([msg.q1, msg.q2, msg.q3, msg.q4])))
            elif mtype == "ATTITUDE":
                self._set_attitude(Rotation.from_euler("ZYX", [msg.yaw, msg.pitch, msg.roll]))
            elif mtype == "COMMAND_ACK":
                if msg.target_system in (0, self._source_system):
                    self.ack_seq += 1
                    self.acks[int(msg.command)] = (self.ack_seq, int(msg.result), now)
                    logger.debug("COMMAND_ACK %s: %s", cmd_name(msg.command), result_name(msg.result))
            elif mtype == "EXTENDED_SYS_STATE":
                try:
                    self.landed = LandedState(int(msg.landed_state))
                except ValueError:
                    self.landed = LandedState.UNDEFINED
            elif mtype == "SYS_STATUS":
                if msg.voltage_battery != 0xFFFF:
                    self.voltage_v = msg.voltage_battery / 1000.0
                self.remaining_pct = float(msg.battery_remaining) if msg.battery_remaining >= 0 else math.nan
            elif mtype == "BATTERY_STATUS":
                if msg.voltages[0] != 0xFFFF:
                    self.voltage_v = msg.voltages[0] / 1000.0
                self.remaining_pct = float(msg.battery_remaining) if msg.battery_remaining >= 0 else math.nan
            elif mtype == "PARAM_VALUE":
                name = msg.param_id.decode() if isinstance(msg.param_id, bytes) else str(msg.param_id)
                self.params[name.rstrip("\x00")] = (float(msg.param_value), int(msg.param_type))
            elif mtype == "GLOBAL_POSITION_INT":
                self.home_amsl_m = (msg.alt - msg.relative_alt) / 1000.0
            elif mtype == "HOME_POSITION":
                self.home_amsl_m = msg.altitude / 1000.0
            elif mtype == "AUTOPILOT_VERSION" and self.info is not None:
                v = int(msg.flight_sw_version)
                self.info = replace(
                    self.info, firmware_version=f"{(v >> 24) & 0xFF}.{(v >> 16) & 0xFF}.{(v >> 8) & 0xFF}"
                )

    def _on_heartbeat(self, msg: Any, src_sys: int, src_comp: int, now: float) -> None:
        """Called with the state lock held."""
        autopilot = autopilot_from_heartbeat(int(msg.autopilot))
        if (
            src_comp != MAV_COMP_ID_AUTOPILOT1
            or autopilot is None
            or msg.type in (MAV_TYPE_GCS, MAV_TYPE_ONBOARD_CONTROLLER)
        ):
            self.rx_other_components += 1
            return
        if self.target is None:
            if self._target_system is not None and src_sys != self._target_system:
                self.rx_other_components += 1
                self.other_systems.add(src_sys)
                return
            self.target = (src_sys, src_comp)
            self.info = VehicleInfo(src_sys, src_comp, autopilot, int(msg.type), our_system_id=self._source_system)
            if self._on_target is not None:
                self._on_target()
        elif (src_sys, src_comp) != self.target:
            self.rx_other_components += 1
            return
        self.newest_s = now
        self.hb_time_s = now
        armed = bool(msg.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)
        assert self.info is not None
        mode = decode_mode(self.info.autopilot, int(msg.base_mode), int(msg.custom_mode))
        if armed != self.armed:
            logger.info("vehicle %s", "armed" if armed else "disarmed")
        if mode != self.mode:
            logger.info("mode %s", mode.value)
        self.armed, self.mode = armed, mode
        self.base_mode, self.custom_mode = int(msg.base_mode), int(msg.custom_mode)

    def _set_attitude(self, R_ned_frd: Rotation) -> None:
        R_enu_flu = rotation_enu_flu_from_ned_frd(R_ned_frd)
        q = quat_xyzw_to_wxyz(R_enu_flu.as_quat())
        self.quat_wxyz = (float(q[0]), float(q[1]), float(q[2]), float(q[3]))
        self.yaw_enu = yaw_from_rotation(R_enu_flu)

    # ------------------------------------------------------------------ waiting (asyncio side)

    def wake(self) -> None:
        """Make every :meth:`wait_until` re-check its probe (any thread)."""
        for wake in list(self._wakers):
            wake()

    async def wait_until(
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
