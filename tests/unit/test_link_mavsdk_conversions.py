"""Pure conversions of the MAVSDK backend: connection strings, setpoints, external poses."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from flightkit.errors import EndpointError, LinkError
from flightkit.frames import Transform, frd_to_flu, ned_to_enu, world_to_body_yaw
from flightkit.link.base import ExternalPose, SetpointFrame, VelocitySetpoint
from flightkit.link.mavsdk import (
    external_pose_to_ned,
    mavsdk_url,
    pose_covariance_upper,
    setpoint_to_mavsdk,
)
from flightkit.link.mavsdk.encoding import PVA_YAW_RATE_LEAD_S


@pytest.mark.parametrize(
    ("url", "expected"),
    [
        ("udpout:127.0.0.1:14540", "udpout://127.0.0.1:14540"),
        ("udpin:0.0.0.0:14550", "udpin://0.0.0.0:14550"),
        ("udp:0.0.0.0:14550", "udpin://0.0.0.0:14550"),
        ("udpin://:14540", "udpin://0.0.0.0:14540"),
        ("tcp:127.0.0.1:5760", "tcpout://127.0.0.1:5760"),
        ("tcpin:0.0.0.0:5760", "tcpin://0.0.0.0:5760"),
        ("/dev/ttyUSB0", "serial:///dev/ttyUSB0:57600"),
        ("/dev/ttyACM0:921600", "serial:///dev/ttyACM0:921600"),
        ("serial:/dev/ttyAMA0:115200", "serial:///dev/ttyAMA0:115200"),
    ],
)
def test_connection_strings_map_to_mavsdk_urls(url: str, expected: str) -> None:
    assert mavsdk_url(url, 57600) == expected


def test_serial_without_baud_takes_the_configured_one() -> None:
    assert mavsdk_url("/dev/ttyUSB1", 921600) == "serial:///dev/ttyUSB1:921600"


@pytest.mark.parametrize(
    "url", ["", "bogus:1.2.3.4:5", "udpout:127.0.0.1", "udpout:127.0.0.1:70000", "udpin:0.0.0.0:0"]
)
def test_bad_connection_strings_raise_endpoint_error(url: str) -> None:
    with pytest.raises(EndpointError):
        mavsdk_url(url)


# --------------------------------------------------------------------------- setpoints


def test_world_setpoint_with_yaw_becomes_velocity_ned_yaw() -> None:
    sp = VelocitySetpoint((1.0, 2.0, 0.5), SetpointFrame.WORLD, yaw_rad=0.0)  # facing east
    cmd = setpoint_to_mavsdk(sp, yaw_local_rad=math.nan)  # heading not needed
    assert cmd.kind == "ned"
    assert (cmd.a, cmd.b, cmd.c) == pytest.approx((2.0, 1.0, -0.5))  # north, east, down
    assert cmd.yaw_deg == pytest.approx(90.0)  # east is 90 deg clockwise from north


def test_world_setpoint_facing_north_has_ned_yaw_zero() -> None:
    cmd = setpoint_to_mavsdk(VelocitySetpoint((0.0, 0.0, 0.0), yaw_rad=math.pi / 2), math.nan)
    assert cmd.yaw_deg == pytest.approx(0.0, abs=1e-9)


def test_world_setpoint_with_yaw_rate_is_rotated_into_the_body_frame() -> None:
    # Vehicle heads north (ENU yaw 90 deg); a world velocity to the north is straight ahead.
    sp = VelocitySetpoint((0.0, 1.0, 0.2), SetpointFrame.WORLD, yaw_rate_rad_s=0.5)
    cmd = setpoint_to_mavsdk(sp, yaw_local_rad=math.pi / 2)
    assert cmd.kind == "body"
    assert (cmd.a, cmd.b, cmd.c) == pytest.approx((1.0, 0.0, -0.2), abs=1e-12)
    # counter-clockwise (ENU) rate is negative in NED/FRD
    assert cmd.yawspeed_deg_s == pytest.approx(-math.degrees(0.5))


def test_world_setpoint_to_the_west_while_facing_north_goes_left() -> None:
    cmd = setpoint_to_mavsdk(VelocitySetpoint((-1.0, 0.0, 0.0)), yaw_local_rad=math.pi / 2)
    assert (cmd.a, cmd.b, cmd.c) == pytest.approx((0.0, -1.0, 0.0), abs=1e-12)  # FRD: left = -right


def test_body_setpoint_flu_becomes_frd_with_flipped_rate() -> None:
    sp = VelocitySetpoint((1.0, 2.0, 3.0), SetpointFrame.BODY, yaw_rate_rad_s=-0.2)
    cmd = setpoint_to_mavsdk(sp, yaw_local_rad=1.0)
    assert cmd.kind == "body"
    assert (cmd.a, cmd.b, cmd.c) == pytest.approx((1.0, -2.0, -3.0))
    assert cmd.yawspeed_deg_s == pytest.approx(math.degrees(0.2))


def test_body_setpoint_with_absolute_yaw_is_rotated_into_ned() -> None:
    # Facing north, "forward" is north.
    sp = VelocitySetpoint((1.0, 0.0, 0.0), SetpointFrame.BODY, yaw_rad=math.pi)  # turn to face west
    cmd = setpoint_to_mavsdk(sp, yaw_local_rad=math.pi / 2)
    assert cmd.kind == "ned"
    assert (cmd.a, cmd.b, cmd.c) == pytest.approx((1.0, 0.0, 0.0), abs=1e-12)
    assert cmd.yaw_deg == pytest.approx(-90.0)  # west is 90 deg anticlockwise from north


def test_stop_needs_no_heading_but_horizontal_motion_does() -> None:
    cmd = setpoint_to_mavsdk(VelocitySetpoint.zero(), yaw_local_rad=math.nan)
    assert (cmd.a, cmd.b, cmd.c, cmd.yawspeed_deg_s) == (0.0, 0.0, 0.0, 0.0)
    climb = setpoint_to_mavsdk(VelocitySetpoint((0.0, 0.0, 0.5)), yaw_local_rad=math.nan)
    assert climb.c == pytest.approx(-0.5)
    with pytest.raises(LinkError, match="attitude"):
        setpoint_to_mavsdk(VelocitySetpoint((1.0, 0.0, 0.0)), yaw_local_rad=math.nan)


finite = st.floats(-5.0, 5.0, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(vx=finite, vy=finite, vz=finite, yaw=st.floats(-math.pi, math.pi), rate=st.floats(-1.0, 1.0))
def test_world_to_body_conversion_round_trips(
    vx: float, vy: float, vz: float, yaw: float, rate: float
) -> None:
    cmd = setpoint_to_mavsdk(VelocitySetpoint((vx, vy, vz), yaw_rate_rad_s=rate), yaw_local_rad=yaw)
    flu = frd_to_flu([cmd.a, cmd.b, cmd.c])
    back = world_to_body_yaw(flu, -yaw)  # body -> world
    np.testing.assert_allclose(back, [vx, vy, vz], atol=1e-9)


# --------------------------------------------------------------------------- external pose


def test_pose_covariance_is_the_upper_triangle_of_a_diagonal() -> None:
    cov = pose_covariance_upper(0.1, 0.2)
    assert len(cov) == 21
    diagonal_index = [0, 6, 11, 15, 18, 20]
    for k, v in enumerate(cov):
        if k in diagonal_index[:3]:
            assert v == pytest.approx(0.01)
        elif k in diagonal_index[3:]:
            assert v == pytest.approx(0.04)
        else:
            assert v == 0.0
    unknown = pose_covariance_upper(math.nan, 0.1)
    assert len(unknown) == 1 and math.isnan(unknown[0])


def test_external_pose_position_and_heading_in_ned() -> None:
    # Body at ENU (1, 2, 3), facing east (ENU yaw 0), level.
    pose = ExternalPose(stamp_ns=1, T_world_body=Transform.from_xyz_yaw([1.0, 2.0, 3.0], 0.0))
    ned = external_pose_to_ned(pose)
    assert ned.pos_ned_m == pytest.approx((2.0, 1.0, -3.0))
    roll, pitch, yaw = ned.rpy_ned_frd_rad
    assert roll == pytest.approx(0.0, abs=1e-9)
    assert pitch == pytest.approx(0.0, abs=1e-9)
    assert yaw == pytest.approx(math.pi / 2)  # east
    assert all(math.isnan(v) for v in ned.vel_frd_m_s)


def test_external_pose_attitude_round_trips_through_ned() -> None:
    R_enu_flu = Rotation.from_euler("ZYX", [0.7, 0.2, -0.3])
    pose = ExternalPose(
        stamp_ns=1, T_world_body=Transform(R_enu_flu, np.zeros(3)), vel_world_m_s=(0.5, -0.2, 0.1)
    )
    ned = external_pose_to_ned(pose)
    w, x, y, z = ned.quat_ned_frd_wxyz
    R_ned_frd = Rotation.from_quat([x, y, z, w])
    # Same physical vector through both attitudes: body x axis in the world.
    fwd_enu = R_enu_flu.apply([1.0, 0.0, 0.0])
    fwd_ned = R_ned_frd.apply([1.0, 0.0, 0.0])
    np.testing.assert_allclose(ned_to_enu(fwd_ned), fwd_enu, atol=1e-9)
    # Euler angles describe the same rotation as the quaternion.
    roll, pitch, yaw = ned.rpy_ned_frd_rad
    R_euler = Rotation.from_euler("ZYX", [yaw, pitch, roll])
    assert (R_euler.inv() * R_ned_frd).magnitude() < 1e-9
    # Velocity in the body frame maps back to the world velocity.
    v_world = ned_to_enu(R_ned_frd.apply(ned.vel_frd_m_s))
    np.testing.assert_allclose(v_world, [0.5, -0.2, 0.1], atol=1e-9)


def test_position_target_becomes_position_velocity_acceleration_ned() -> None:
    sp = VelocitySetpoint((0.1, 0.2, 0.3), yaw_rad=0.0, pos_m=(1.0, 2.0, 1.5), accel_m_s2=(0.4, -0.2, 0.1))
    cmd = setpoint_to_mavsdk(sp, yaw_local_rad=math.nan)
    assert cmd.kind == "pva"
    assert cmd.pos_ned_m == pytest.approx((2.0, 1.0, -1.5))
    assert (cmd.a, cmd.b, cmd.c) == pytest.approx((0.2, 0.1, -0.3))
    assert cmd.accel_ned_m_s2 == pytest.approx((-0.2, 0.4, -0.1))
    assert cmd.yaw_deg == pytest.approx(90.0)
    # MAVSDK's setter takes an absolute yaw: a rate leads the current heading by one stream period
    rate = VelocitySetpoint((0.0, 0.0, 0.0), yaw_rate_rad_s=1.0, pos_m=(0.0, 0.0, 1.0))
    assert setpoint_to_mavsdk(rate, math.pi / 2).yaw_deg == pytest.approx(-math.degrees(PVA_YAW_RATE_LEAD_S))
    with pytest.raises(LinkError, match="attitude is known"):
        setpoint_to_mavsdk(rate, math.nan)
