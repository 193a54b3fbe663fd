"""Pure MAVLink encoders of the pymavlink backend: flightkit values -> MAVLink messages.

Velocity setpoints become SET_POSITION_TARGET_LOCAL_NED fields, external poses become
VISION_POSITION_ESTIMATE or ODOMETRY; the constants name the MAVLink numbers the backend
uses. No IO and no state here: everything is a function of its arguments, so it is
unit-tested on its own (``tests/unit/test_link_encoding.py``).

Frames: the inputs are ENU/FLU; NED/FRD appear only in the outputs (through
:mod:`flightkit.frames`).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink2
from scipy.spatial.transform import Rotation

from flightkit.errors import SetpointError
from flightkit.frames import (
    enu_to_ned,
    flu_to_frd,
    quat_xyzw_to_wxyz,
    rotation_ned_frd_from_enu_flu,
    yaw_enu_to_ned,
)
from flightkit.link.base import ExternalPose, SetpointFrame, VelocitySetpoint

__all__ = [
    "HARD_MAX_ACCEL_M_S2",
    "HARD_MAX_HORIZONTAL_M_S",
    "HARD_MAX_VERTICAL_M_S",
    "HARD_MAX_YAW_RATE_RAD_S",
    "TYPE_MASK_PVA_YAW",
    "TYPE_MASK_PVA_YAW_RATE",
    "TYPE_MASK_VELOCITY_ONLY",
    "TYPE_MASK_VELOCITY_YAW",
    "TYPE_MASK_VELOCITY_YAW_RATE",
    "MavlinkMessage",
    "SetpointFields",
    "check_hard_limits",
    "cmd_name",
    "decode_param_value",
    "encode_odometry",
    "encode_setpoint_message",
    "encode_velocity_setpoint",
    "encode_vision_position_estimate",
    "heartbeat_type_for_component",
    "result_name",
]

class MavlinkMessage(Protocol):
    """An outgoing pymavlink message, as far as flightkit uses one (pymavlink ships no types)."""

    def get_type(self) -> str: ...

    def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes: ...


# Safety net on every velocity setpoint, whatever the caller's own limits: no indoor lab
# flight needs more, and a bigger number is a bug (units, frames) rather than a command.
HARD_MAX_HORIZONTAL_M_S = 15.0
HARD_MAX_VERTICAL_M_S = 5.0
HARD_MAX_YAW_RATE_RAD_S = 6.0
HARD_MAX_ACCEL_M_S2 = 8.0

# SET_POSITION_TARGET_LOCAL_NED type_mask (bit set = ignore the field).
TYPE_MASK_VELOCITY_YAW = 2503  # position, acceleration and yaw rate ignored
TYPE_MASK_VELOCITY_YAW_RATE = 1479  # position, acceleration and yaw ignored
TYPE_MASK_VELOCITY_ONLY = 3527  # yaw and yaw rate ignored too
_MASK_POSITION_AND_ACCEL = 0b111000111  # the ignore bits of x/y/z and afx/afy/afz
TYPE_MASK_PVA_YAW = TYPE_MASK_VELOCITY_YAW & ~_MASK_POSITION_AND_ACCEL  # 2048: yaw rate ignored
TYPE_MASK_PVA_YAW_RATE = TYPE_MASK_VELOCITY_YAW_RATE & ~_MASK_POSITION_AND_ACCEL  # 1024: yaw ignored

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


# MAV_PARAM_TYPE -> struct format of the integer held bytewise in PARAM_VALUE's float
_BYTEWISE_FORMATS = {1: "<B", 2: "<b", 3: "<H", 4: "<h", 5: "<I", 6: "<i"}


def decode_param_value(wire: float, param_type: int, bytewise: bool) -> float:
    """The value of a PARAM_VALUE: ``wire`` as sent, of MAV_PARAM_TYPE ``param_type``.

    ``bytewise``: integer parameters travel as their bytes inside the float (PX4,
    MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE); otherwise as the float of the integer
    (ArduPilot, C cast). Integer values come back as whole floats.
    """
    fmt = _BYTEWISE_FORMATS.get(int(param_type))
    if fmt is None:
        return float(wire)
    if not bytewise:
        return float(round(wire)) if math.isfinite(wire) else float(wire)
    raw = struct.pack("<f", wire)
    return float(struct.unpack(fmt, raw[: struct.calcsize(fmt)])[0])


def heartbeat_type_for_component(component_id: int) -> int:
    """MAV_TYPE we announce: ONBOARD_CONTROLLER for component ids 191-194, GCS otherwise."""
    return MAV_TYPE_ONBOARD_CONTROLLER if 191 <= component_id <= 194 else MAV_TYPE_GCS


def _enum_name(enum: str, value: int, prefix: str) -> str:
    entry = mavlink2.enums.get(enum, {}).get(value)
    return entry.name.removeprefix(prefix) if entry is not None else f"{prefix}{value}"


def cmd_name(command: int) -> str:
    return _enum_name("MAV_CMD", command, "")


# MAV_RESULT as the MAVLink common.xml of today defines it; pymavlink 2.4's table lacks
# CANCELLED (6) and calls 9 ENUM_END.
_MAV_RESULT = (
    "ACCEPTED", "TEMPORARILY_REJECTED", "DENIED", "UNSUPPORTED", "FAILED", "IN_PROGRESS", "CANCELLED",
    "COMMAND_LONG_ONLY", "COMMAND_INT_ONLY", "COMMAND_UNSUPPORTED_MAV_FRAME",
)


def result_name(result: int) -> str:
    """``"DENIED"`` for 2; ``"MAV_RESULT_42"`` for a code MAVLink does not define."""
    return _MAV_RESULT[result] if 0 <= result < len(_MAV_RESULT) else f"MAV_RESULT_{result}"



@dataclass(frozen=True, slots=True)
class SetpointFields:
    """SET_POSITION_TARGET_LOCAL_NED fields for a setpoint (NED/FRD, MAVLink units)."""

    coordinate_frame: int
    type_mask: int
    vx: float
    vy: float
    vz: float
    yaw: float
    yaw_rate: float
    pos_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    accel_ned_m_s2: tuple[float, float, float] = (0.0, 0.0, 0.0)


def check_hard_limits(setpoint: VelocitySetpoint) -> None:
    """Raise SetpointError when a setpoint exceeds the backend's safety net."""
    try:
        setpoint.check_limits(
            HARD_MAX_HORIZONTAL_M_S, HARD_MAX_VERTICAL_M_S, HARD_MAX_YAW_RATE_RAD_S, HARD_MAX_ACCEL_M_S2
        )
    except SetpointError as exc:
        raise SetpointError(
            f"{exc} (hard safety limit of the MAVLink link; this is almost surely a bug)"
        ) from None


def encode_velocity_setpoint(setpoint: VelocitySetpoint) -> SetpointFields:
    """Translate a flightkit velocity setpoint to SET_POSITION_TARGET_LOCAL_NED fields.

    WORLD (ENU) -> MAV_FRAME_LOCAL_NED with the velocity in NED; BODY (FLU) ->
    MAV_FRAME_BODY_NED with the velocity in FRD. A yaw is an ENU heading (counter-clockwise
    from x) and becomes a NED yaw (clockwise from north); a yaw rate changes sign (ENU
    counter-clockwise positive -> NED clockwise positive). Neither given: yaw rate 0. With a
    position target, the position and acceleration go in too (type_mask 2048 with a yaw, 1024
    with a yaw rate: position, velocity and acceleration all used, per the MAVLink spec).
    """
    if setpoint.frame is SetpointFrame.WORLD:
        frame = MAV_FRAME_LOCAL_NED
        v = enu_to_ned(setpoint.vel_m_s)
    else:
        frame = MAV_FRAME_BODY_NED
        v = flu_to_frd(setpoint.vel_m_s)
    vel = (float(v[0]), float(v[1]), float(v[2]))
    pva = setpoint.pos_m is not None
    pos = _ned_tuple(setpoint.pos_m or (0.0, 0.0, 0.0))
    acc = _ned_tuple(setpoint.accel_m_s2 or (0.0, 0.0, 0.0))
    if setpoint.yaw_rad is not None:
        mask = TYPE_MASK_PVA_YAW if pva else TYPE_MASK_VELOCITY_YAW
        return SetpointFields(frame, mask, *vel, yaw_enu_to_ned(setpoint.yaw_rad), 0.0, pos, acc)
    rate = 0.0 if setpoint.yaw_rate_rad_s is None else -float(setpoint.yaw_rate_rad_s)
    mask = TYPE_MASK_PVA_YAW_RATE if pva else TYPE_MASK_VELOCITY_YAW_RATE
    return SetpointFields(frame, mask, *vel, 0.0, rate + 0.0, pos, acc)


def _ned_tuple(v_enu: tuple[float, float, float]) -> tuple[float, float, float]:
    n = enu_to_ned(v_enu)
    return (float(n[0]), float(n[1]), float(n[2]))


def encode_setpoint_message(f: SetpointFields, target: tuple[int, int], time_boot_ms: int) -> MavlinkMessage:
    """SET_POSITION_TARGET_LOCAL_NED carrying ``f`` to ``target`` (system, component)."""
    msg: MavlinkMessage = mavlink2.MAVLink_set_position_target_local_ned_message(
        time_boot_ms,
        target[0],
        target[1],
        f.coordinate_frame,
        f.type_mask,
        *f.pos_ned_m,
        f.vx,
        f.vy,
        f.vz,
        *f.accel_ned_m_s2,
        f.yaw,
        f.yaw_rate,
    )
    return msg


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


def encode_vision_position_estimate(pose: ExternalPose) -> MavlinkMessage:
    """VISION_POSITION_ESTIMATE for ``pose``: NED position, FRD attitude as roll/pitch/yaw,
    usec timestamp from ``stamp_ns``, covariance from the pose's standard deviations."""
    pos_ned, R_ned_frd = _pose_ned_frd(pose)
    yaw, pitch, roll = R_ned_frd.as_euler("ZYX")
    cov = _upper_triangle_diag([pose.pos_std_m**2] * 3 + [pose.rot_std_rad**2] * 3)
    msg: MavlinkMessage = mavlink2.MAVLink_vision_position_estimate_message(
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
    return msg


def encode_odometry(pose: ExternalPose) -> MavlinkMessage:
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
    msg: MavlinkMessage = mavlink2.MAVLink_odometry_message(
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
    return msg
