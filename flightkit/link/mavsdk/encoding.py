"""Pure conversions of the MAVSDK backend: flightkit values in MAVSDK's terms.

:func:`mavsdk_url` turns our endpoint strings into MAVSDK's; :func:`setpoint_to_mavsdk`
chooses between ``VelocityNedYaw`` and ``VelocityBodyYawspeed`` for a flightkit setpoint (ENU/FLU
in, NED/FRD out, through :mod:`flightkit.frames`); :func:`external_pose_to_ned` and
:func:`pose_covariance_upper` prepare a mocap/VO pose for the mocap plugin. No MAVSDK import
and no IO here, so they are unit-tested on their own (``tests/unit/test_link_mavsdk_conversions.py``).
This is the MAVSDK counterpart of :mod:`flightkit.link.mavlink.encoding`.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from flightkit.errors import (
    EndpointError,
    LinkError,
)
from flightkit.frames import (
    enu_to_ned,
    flu_to_frd,
    quat_xyzw_to_wxyz,
    rotation_ned_frd_from_enu_flu,
    world_to_body_yaw,
    yaw_enu_to_ned,
)
from flightkit.link.base import (
    ExternalPose,
    SetpointFrame,
    VelocitySetpoint,
)
from flightkit.link.endpoints import parse_endpoint

__all__ = ["NedPose", "external_pose_to_ned", "mavsdk_url", "pose_covariance_upper", "setpoint_to_mavsdk"]


def mavsdk_url(url: str, baud: int = 57600) -> str:
    """Translate a flightkit connection string (``link.url``) to MAVSDK's URL form.

    Parsing and validation are :func:`flightkit.link.endpoints.parse_endpoint`'s (the
    pymavlink backend uses the same), so both backends accept the same strings:

    =============================  ==================================
    flightkit                      MAVSDK
    =============================  ==================================
    ``udpin:0.0.0.0:14540``        ``udpin://0.0.0.0:14540``
    ``udpout:127.0.0.1:14540``     ``udpout://127.0.0.1:14540``
    ``tcp:127.0.0.1:5760``         ``tcpout://127.0.0.1:5760``
    ``tcpin:0.0.0.0:5760``         ``tcpin://0.0.0.0:5760``
    ``/dev/ttyUSB0`` (+ ``baud``)  ``serial:///dev/ttyUSB0:57600``
    =============================  ==================================

    Raises:
        EndpointError: the string is malformed, or asks for a listening port 0 (MAVSDK
            cannot report which port the system picked, so nobody could reach it).
    """
    endpoint = parse_endpoint(url, baud)
    if endpoint.listens and endpoint.port == 0:
        raise EndpointError(
            f"{url!r} asks for any free port, which MAVSDK cannot report back; give a fixed port, "
            "e.g. udpin:0.0.0.0:14540"
        )
    return endpoint.to_mavsdk_url()


# --------------------------------------------------------------------------- pure conversions


def pose_covariance_upper(pos_std_m: float, rot_std_rad: float) -> list[float]:
    """Row-major upper triangle (21 values) of a diagonal 6x6 pose covariance.

    Order is x, y, z, roll, pitch, yaw, as MAVLink's VISION_POSITION_ESTIMATE and ODOMETRY
    expect. A non-finite standard deviation gives MAVLink's "unknown" (a single NaN).
    """
    if not (math.isfinite(pos_std_m) and math.isfinite(rot_std_rad)):
        return [math.nan]
    diag = [pos_std_m**2] * 3 + [rot_std_rad**2] * 3
    out: list[float] = []
    for i in range(6):
        for j in range(i, 6):
            out.append(diag[i] if i == j else 0.0)
    return out


@dataclasses.dataclass(frozen=True, slots=True)
class NedPose:
    """An external pose as MAVLink wants it: the FRD body in the NED local frame.

    Attributes:
        pos_ned_m: position (north, east, down).
        rpy_ned_frd_rad: roll, pitch, yaw (intrinsic Z-Y-X Euler angles of R_ned_frd).
        quat_ned_frd_wxyz: the same attitude as a quaternion.
        vel_frd_m_s: velocity in the FRD body frame (NaN when the pose has none).
    """

    pos_ned_m: tuple[float, float, float]
    rpy_ned_frd_rad: tuple[float, float, float]
    quat_ned_frd_wxyz: tuple[float, float, float, float]
    vel_frd_m_s: tuple[float, float, float]


def external_pose_to_ned(pose: ExternalPose) -> NedPose:
    """Convert an FLU-in-ENU :class:`ExternalPose` to the FRD-in-NED numbers MAVLink carries."""
    T = pose.T_world_body
    p = enu_to_ned(T.translation)
    R = rotation_ned_frd_from_enu_flu(T.rotation)
    yaw, pitch, roll = R.as_euler("ZYX")
    q = quat_xyzw_to_wxyz(R.as_quat())
    if pose.vel_world_m_s is not None:
        v = R.inv().apply(enu_to_ned(pose.vel_world_m_s))
        vel = (float(v[0]), float(v[1]), float(v[2]))
    else:
        vel = (math.nan, math.nan, math.nan)
    return NedPose(
        (float(p[0]), float(p[1]), float(p[2])),
        (float(roll), float(pitch), float(yaw)),
        (float(q[0]), float(q[1]), float(q[2]), float(q[3])),
        vel,
    )


@dataclasses.dataclass(frozen=True, slots=True)
class _NedCommand:
    """A setpoint as MAVSDK takes it: VelocityNedYaw (``yaw_deg`` set), VelocityBodyYawspeed, or
    PositionNedYaw + VelocityNedYaw + AccelerationNed ("pva")."""

    kind: str  # "ned", "body" or "pva"
    a: float  # north / forward, m/s
    b: float  # east / right, m/s
    c: float  # down, m/s
    yaw_deg: float = 0.0  # "ned", "pva": absolute NED yaw, degrees clockwise from north
    yawspeed_deg_s: float = 0.0  # "body": yaw rate, degrees/s clockwise seen from above
    pos_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # "pva"
    accel_ned_m_s2: tuple[float, float, float] = (0.0, 0.0, 0.0)  # "pva"


# MAVSDK's position-velocity-acceleration setter takes an absolute yaw only: a yaw rate becomes
# the current heading advanced by the rate over this lead (one 10 Hz stream period).
PVA_YAW_RATE_LEAD_S = 0.1


def _ned3(v_enu: tuple[float, float, float]) -> tuple[float, float, float]:
    n = enu_to_ned(v_enu)
    return (float(n[0]), float(n[1]), float(n[2]))


def setpoint_to_mavsdk(sp: VelocitySetpoint, yaw_local_rad: float) -> _NedCommand:
    """Express a flightkit setpoint as the MAVSDK offboard command that means the same.

    Args:
        sp: the setpoint (ENU world or FLU body).
        yaw_local_rad: the vehicle's current heading in the autopilot's local frame (ENU),
            used when the frame has to change (see :mod:`flightkit.link.mavsdk.stream`); NaN if unknown.

    Raises:
        LinkError: the frame has to change and the heading is not known yet.
    """
    vx, vy, vz = sp.vel_m_s
    if sp.pos_m is not None:
        if sp.yaw_rad is not None:
            yaw_enu = sp.yaw_rad
        elif math.isfinite(yaw_local_rad):
            yaw_enu = yaw_local_rad + (sp.yaw_rate_rad_s or 0.0) * PVA_YAW_RATE_LEAD_S
        else:
            raise LinkError("cannot send a position target with a yaw rate before the attitude is known")
        n, e, d = _ned3(sp.vel_m_s)
        return _NedCommand(
            "pva",
            n,
            e,
            d,
            yaw_deg=math.degrees(yaw_enu_to_ned(yaw_enu)),
            pos_ned_m=_ned3(sp.pos_m),
            accel_ned_m_s2=_ned3(sp.accel_m_s2 or (0.0, 0.0, 0.0)),
        )
    if sp.frame is SetpointFrame.WORLD:
        if sp.yaw_rad is not None:
            n, e, d = enu_to_ned([vx, vy, vz])
            return _NedCommand(
                "ned", float(n), float(e), float(d), yaw_deg=math.degrees(yaw_enu_to_ned(sp.yaw_rad))
            )
        rate = sp.yaw_rate_rad_s or 0.0
        if vx == 0.0 and vy == 0.0:
            body = np.array([0.0, 0.0, vz])
        else:
            if not math.isfinite(yaw_local_rad):
                raise LinkError(
                    "cannot send a world-frame velocity with a yaw rate before the attitude is known"
                )
            body = world_to_body_yaw([vx, vy, vz], yaw_local_rad)
        f, r, d = flu_to_frd(body)
        return _NedCommand("body", float(f), float(r), float(d), yawspeed_deg_s=-math.degrees(rate))
    # BODY (yaw-aligned FLU)
    if sp.yaw_rad is not None:
        if vx == 0.0 and vy == 0.0:
            world = np.array([0.0, 0.0, vz])
        else:
            if not math.isfinite(yaw_local_rad):
                raise LinkError(
                    "cannot send a body-frame velocity with an absolute yaw before the attitude is known"
                )
            world = world_to_body_yaw([vx, vy, vz], -yaw_local_rad)
        n, e, d = enu_to_ned(world)
        return _NedCommand(
            "ned", float(n), float(e), float(d), yaw_deg=math.degrees(yaw_enu_to_ned(sp.yaw_rad))
        )
    f, r, d = flu_to_frd([vx, vy, vz])
    return _NedCommand(
        "body", float(f), float(r), float(d), yawspeed_deg_s=-math.degrees(sp.yaw_rate_rad_s or 0.0)
    )
