"""Outbound telemetry of the simulated autopilot: the messages it streams and sends on request.

One builder per message (HEARTBEAT is in :mod:`.core`, as mode changes send it at once),
each turning the simulated state into the MAVLink message in NED; :data:`_STREAM_BUILDERS`
maps message ids to builders, and :meth:`_AutopilotTelemetry._send_streams` sends every
stream that is due at its client-set interval (SET_MESSAGE_INTERVAL).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from flightkit.frames import enu_to_ned, yaw_enu_to_ned
from flightkit.sim.autopilot.core import _EARTH_RADIUS_M
from flightkit.sim.autopilot.flight import _AutopilotFlight

mav = mavlink2  # enums and message classes


class _AutopilotTelemetry(_AutopilotFlight):
    """Message builders and stream scheduling."""

    def _battery(self) -> tuple[float, float]:
        """(remaining fraction, voltage V) of the simulated 4S battery."""
        if self._battery_override is not None:
            frac = self._battery_override
        else:
            frac = max(0.0, 1.0 - self._battery_used_s / self._battery_endurance_s())
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
            int(frac * self._battery_endurance_s()),
            mav.MAV_BATTERY_CHARGE_STATE_OK if frac > 0.2 else mav.MAV_BATTERY_CHARGE_STATE_LOW,
        )

    def _local_position_ned(self, now: float) -> Any:
        if not self._ready(now):
            return None
        pos = self._est_pos_local()
        vel = self._est_vel_local()
        pos_ned, vel_ned = enu_to_ned(pos), enu_to_ned(vel)
        return self._mav.local_position_ned_encode(self._time_boot_ms(now), *pos_ned, *vel_ned)

    def _attitude_ned(self) -> tuple[float, float, float, float]:
        st = self.dynamics.state()
        yaw_ned = yaw_enu_to_ned(st.yaw_rad - self.options.heading_offset_rad + self._yaw_bias)
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
        hdg = int(round(math.degrees(yaw_enu_to_ned(self._est_yaw_local())) % 360 * 100)) % 36000
        vel_ned = enu_to_ned(vel)
        return self._mav.global_position_int_encode(
            self._time_boot_ms(now),
            lat,
            lon,
            alt,
            rel,
            int(vel_ned[0] * 100),
            int(vel_ned[1] * 100),
            int(vel_ned[2] * 100),
            hdg,
        )

    def _home_position(self, now: float) -> Any:
        if not self._ready(now):
            return None
        h = self._home_local_enu
        lat, lon, alt = self._global_of_local(h)
        yaw_ned = yaw_enu_to_ned(self._home_yaw_local)
        q = (math.cos(yaw_ned / 2), 0.0, 0.0, math.sin(yaw_ned / 2))
        h_ned = enu_to_ned(h)
        return self._mav.home_position_encode(
            lat,
            lon,
            alt,
            float(h_ned[0]),
            float(h_ned[1]),
            float(h_ned[2]),
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
        hdg = int(round(math.degrees(yaw_enu_to_ned(self._est_yaw_local())))) % 360
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


_STREAM_BUILDERS: dict[int, Callable[[_AutopilotTelemetry, float], Any]] = {
    mav.MAVLINK_MSG_ID_HEARTBEAT: _AutopilotTelemetry._heartbeat,
    mav.MAVLINK_MSG_ID_SYS_STATUS: _AutopilotTelemetry._sys_status,
    mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: _AutopilotTelemetry._extended_sys_state,
    mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: _AutopilotTelemetry._local_position_ned,
    mav.MAVLINK_MSG_ID_ATTITUDE: _AutopilotTelemetry._attitude,
    mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: _AutopilotTelemetry._attitude_quaternion,
    mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: _AutopilotTelemetry._global_position_int,
    mav.MAVLINK_MSG_ID_BATTERY_STATUS: _AutopilotTelemetry._battery_status,
    mav.MAVLINK_MSG_ID_HOME_POSITION: _AutopilotTelemetry._home_position,
    mav.MAVLINK_MSG_ID_VFR_HUD: _AutopilotTelemetry._vfr_hud,
}
