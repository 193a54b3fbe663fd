"""Inbound MAVLink of the simulated autopilot: commands, setpoints, parameters, external poses.

:meth:`_AutopilotInbound._handle` dispatches each received message (:data:`_HANDLERS`);
COMMAND_LONG / COMMAND_INT go through :data:`_COMMANDS` and are answered with COMMAND_ACK
(arming checks, DO_SET_MODE with the firmware's rules, take-off, land, RTL, reposition,
message intervals and requests). SET_POSITION_TARGET_LOCAL_NED becomes the current setpoint
in the local ENU frame; the parameter protocol follows the firmware's encoding.
"""

from __future__ import annotations

import logging
import math
import struct
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from flightkit.frames import ned_to_enu, wrap_angle_rad, yaw_ned_to_enu
from flightkit.link.base import FlightMode
from flightkit.sim.autopilot.core import (
    _EARTH_RADIUS_M,
    _NEEDS_POSITION_ARDUPILOT,
    _as_int,
    _param_name,
    _Setpoint,
)
from flightkit.sim.autopilot.options import DEFAULT_STREAM_RATES_HZ
from flightkit.sim.autopilot.telemetry import _STREAM_BUILDERS, _AutopilotTelemetry
from flightkit.sim.personality import (
    MAV_FRAME_BODY_NED,
    MAV_FRAME_BODY_OFFSET_NED,
    MAV_FRAME_LOCAL_OFFSET_NED,
    LossAction,
    ParamType,
)

logger = logging.getLogger(__name__)

mav = mavlink2  # enums and message classes

# The results the command handlers return, typed (pymavlink ships no types).
_RESULT_ACCEPTED: int = mav.MAV_RESULT_ACCEPTED
_RESULT_DENIED: int = mav.MAV_RESULT_DENIED
_RESULT_FAILED: int = mav.MAV_RESULT_FAILED
_RESULT_UNSUPPORTED: int = mav.MAV_RESULT_UNSUPPORTED


# type_mask bits of SET_POSITION_TARGET_LOCAL_NED
_IGNORE_POS = 0b111

_IGNORE_VEL = 0b111000

_IGNORE_ACC = 0b111000000

_IGNORE_YAW = 1024

_IGNORE_YAW_RATE = 2048


_FORCE_ARM_MAGIC = 2989

_FORCE_DISARM_MAGIC = 21196


class _AutopilotInbound(_AutopilotTelemetry):
    """Handling of every message the simulated autopilot receives."""

    def _handle(self, msg: Any, now: float) -> None:
        mtype = msg.get_type()
        if mtype == "HEARTBEAT":
            if msg.get_srcSystem() == int(self._params.get("MAV_GCS_SYSID", -1)):
                self._gcs_seen_s = now  # ArduCopter's GCS failsafe watches this system only
                self._gcs_failsafe = False
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
            self._ack(msg, command, _RESULT_UNSUPPORTED)
            return
        try:
            result = handler(self, msg, params, now, is_int)
        except Exception:
            logger.exception("command %d failed", command)
            result = _RESULT_FAILED
        if result is not None:
            self._ack(msg, command, result)

    def _cmd_arm_disarm(self, msg: Any, params: list[float], now: float, is_int: bool) -> int | None:
        p = self.personality
        if params[0] >= 0.5:
            if self._armed:
                return _RESULT_ACCEPTED
            force = _as_int(params[1]) == _FORCE_ARM_MAGIC
            if not force:
                reason = self._arming_refusal(now)
                if reason is not None:
                    self._ack(msg, mav.MAV_CMD_COMPONENT_ARM_DISARM, p.reject_result)
                    self._statustext(reason, mav.MAV_SEVERITY_CRITICAL)
                    self._event("arm_refused", reason)
                    return None
            self._arm(now)
            return _RESULT_ACCEPTED
        if not self._armed:
            return _RESULT_ACCEPTED
        force = _as_int(params[1]) == _FORCE_DISARM_MAGIC
        if not self.dynamics.on_ground and not force:
            self._statustext("Disarming denied: not landed", mav.MAV_SEVERITY_CRITICAL)
            return p.reject_result
        self._disarm(now, p.text("disarmed"), "forced" if force else "command")
        return _RESULT_ACCEPTED

    def _cmd_do_set_mode(self, msg: Any, params: list[float], now: float, is_int: bool) -> int | None:
        p = self.personality
        base_mode = _as_int(params[0])
        if not base_mode & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return _RESULT_UNSUPPORTED
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
            return _RESULT_UNSUPPORTED if p.autopilot.value == "px4" else _RESULT_FAILED
        if mode is self._mode:
            return _RESULT_ACCEPTED
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
        return _RESULT_ACCEPTED

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
        self._ack(msg, mav.MAV_CMD_NAV_TAKEOFF, _RESULT_ACCEPTED)
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
        return _RESULT_ACCEPTED

    def _cmd_rtl(self, msg: Any, params: list[float], now: float, is_int: bool) -> int | None:
        if self.personality.autopilot.value == "ardupilot" and not self._ready(now):
            return self.personality.reject_result
        self._set_mode(self.personality.rtl_mode, "rtl command")
        return _RESULT_ACCEPTED

    def _cmd_loiter(self, msg: Any, params: list[float], now: float, is_int: bool) -> int | None:
        mode = self.personality.hold_mode if self.personality.autopilot.value == "px4" else FlightMode.LOITER
        self._set_mode(mode, "loiter command")
        return _RESULT_ACCEPTED

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
        return _RESULT_ACCEPTED

    def _cmd_accept(self, msg: Any, params: list[float], now: float, is_int: bool) -> int | None:
        return _RESULT_ACCEPTED

    def _cmd_terminate(self, msg: Any, params: list[float], now: float, is_int: bool) -> int | None:
        if params[0] >= 0.5:
            self._disarm(now, "Flight termination active", "termination")
        return _RESULT_ACCEPTED

    def _cmd_set_message_interval(
        self, msg: Any, params: list[float], now: float, is_int: bool
    ) -> int | None:
        msg_id, interval_us = _as_int(params[0]), params[1]
        if msg_id not in _STREAM_BUILDERS:
            return _RESULT_DENIED
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
        return _RESULT_ACCEPTED

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
        self._ack(msg, mav.MAV_CMD_GET_MESSAGE_INTERVAL, _RESULT_ACCEPTED)
        self._send(self._mav.message_interval_encode(msg_id, interval))
        return None

    def _cmd_request_message(self, msg: Any, params: list[float], now: float, is_int: bool) -> int | None:
        out = self._build_message(_as_int(params[0]), now, on_request=True)
        if out is None:
            return (
                _RESULT_UNSUPPORTED
                if _as_int(params[0]) not in _STREAM_BUILDERS
                else _RESULT_DENIED
            )
        self._ack(msg, mav.MAV_CMD_REQUEST_MESSAGE, _RESULT_ACCEPTED)
        self._send(out)
        return None

    def _cmd_request_version(self, msg: Any, params: list[float], now: float, is_int: bool) -> int | None:
        self._ack(msg, mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, _RESULT_ACCEPTED)
        self._send(self._autopilot_version())
        return None

    def _cmd_request_protocol(self, msg: Any, params: list[float], now: float, is_int: bool) -> int | None:
        self._ack(msg, mav.MAV_CMD_REQUEST_PROTOCOL_VERSION, _RESULT_ACCEPTED)
        self._send(self._protocol_version())
        return None

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
        use_acc = mask & _IGNORE_ACC != _IGNORE_ACC
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
            return ned_to_enu((x, y, z))

        pos = vel = acc = None
        if use_acc:
            acc = to_local_enu(msg.afx, msg.afy, msg.afz)
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
                yaw = yaw_ned_to_enu(msg.yaw)
        elif not mask & _IGNORE_YAW_RATE and math.isfinite(msg.yaw_rate):
            yaw_rate = -float(msg.yaw_rate)
        if any(v is not None and not np.all(np.isfinite(v)) for v in (pos, vel, acc)):
            return
        sp = _Setpoint(now, pos, vel, yaw, yaw_rate, acc)
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


_HANDLERS: dict[str, Callable[[_AutopilotInbound, Any, float], None]] = {
    "COMMAND_LONG": _AutopilotInbound._on_command_long,
    "COMMAND_INT": _AutopilotInbound._on_command_int,
    "SET_MODE": _AutopilotInbound._on_set_mode,
    "SET_POSITION_TARGET_LOCAL_NED": _AutopilotInbound._on_set_position_target_local_ned,
    "PARAM_REQUEST_LIST": _AutopilotInbound._on_param_request_list,
    "PARAM_REQUEST_READ": _AutopilotInbound._on_param_request_read,
    "PARAM_SET": _AutopilotInbound._on_param_set,
    "TIMESYNC": _AutopilotInbound._on_timesync,
    "VISION_POSITION_ESTIMATE": _AutopilotInbound._on_vision_position_estimate,
    "ODOMETRY": _AutopilotInbound._on_odometry,
    "SET_GPS_GLOBAL_ORIGIN": _AutopilotInbound._on_set_gps_global_origin,
}


_COMMANDS: dict[int, Callable[[_AutopilotInbound, Any, list[float], float, bool], int | None]] = {
    mav.MAV_CMD_COMPONENT_ARM_DISARM: _AutopilotInbound._cmd_arm_disarm,
    mav.MAV_CMD_DO_SET_MODE: _AutopilotInbound._cmd_do_set_mode,
    mav.MAV_CMD_NAV_TAKEOFF: _AutopilotInbound._cmd_takeoff,
    mav.MAV_CMD_NAV_LAND: _AutopilotInbound._cmd_land,
    mav.MAV_CMD_NAV_RETURN_TO_LAUNCH: _AutopilotInbound._cmd_rtl,
    mav.MAV_CMD_NAV_LOITER_UNLIM: _AutopilotInbound._cmd_loiter,
    mav.MAV_CMD_DO_REPOSITION: _AutopilotInbound._cmd_reposition,
    mav.MAV_CMD_DO_CHANGE_SPEED: _AutopilotInbound._cmd_accept,
    mav.MAV_CMD_DO_SET_HOME: _AutopilotInbound._cmd_accept,
    mav.MAV_CMD_DO_FLIGHTTERMINATION: _AutopilotInbound._cmd_terminate,
    mav.MAV_CMD_SET_MESSAGE_INTERVAL: _AutopilotInbound._cmd_set_message_interval,
    mav.MAV_CMD_GET_MESSAGE_INTERVAL: _AutopilotInbound._cmd_get_message_interval,
    mav.MAV_CMD_REQUEST_MESSAGE: _AutopilotInbound._cmd_request_message,
    mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: _AutopilotInbound._cmd_request_version,
    mav.MAV_CMD_REQUEST_PROTOCOL_VERSION: _AutopilotInbound._cmd_request_protocol,
}
