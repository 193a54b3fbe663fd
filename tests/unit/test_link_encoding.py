"""Wire encoding of setpoints and external poses: fields, frames and exact bytes."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2
from scipy.spatial.transform import Rotation

from flightkit.errors import SetpointError
from flightkit.frames import Transform
from flightkit.link.base import ExternalPose, SetpointFrame, VelocitySetpoint
from flightkit.link.mavlink import (
    HARD_MAX_HORIZONTAL_M_S,
    TYPE_MASK_PVA_YAW,
    TYPE_MASK_PVA_YAW_RATE,
    TYPE_MASK_VELOCITY_YAW,
    TYPE_MASK_VELOCITY_YAW_RATE,
    check_hard_limits,
    encode_odometry,
    encode_velocity_setpoint,
    encode_vision_position_estimate,
    heartbeat_type_for_component,
)
from flightkit.link.mavlink.encoding import encode_setpoint_message


def _roundtrip(msg: object) -> object:
    """Pack with one MAVLink codec and parse with another (as the autopilot would)."""
    tx = mavlink2.MAVLink(None, 255, 191)
    buf = bytes(msg.pack(tx))  # type: ignore[attr-defined]
    rx = mavlink2.MAVLink(None, 1, 1)
    out = rx.parse_buffer(buf)
    assert out is not None and len(out) == 1
    return out[0]


def test_type_masks_are_the_documented_ones() -> None:
    assert TYPE_MASK_VELOCITY_YAW == 2503 == 0b1001_1100_0111
    assert TYPE_MASK_VELOCITY_YAW_RATE == 1479 == 0b0101_1100_0111


def test_world_enu_velocity_becomes_local_ned() -> None:
    f = encode_velocity_setpoint(VelocitySetpoint((1.0, 2.0, 0.5), SetpointFrame.WORLD, yaw_rad=0.0))
    assert f.coordinate_frame == mavlink2.MAV_FRAME_LOCAL_NED == 1
    assert (f.vx, f.vy, f.vz) == (2.0, 1.0, -0.5)  # north = ENU y, east = ENU x, down = -up
    assert f.type_mask == 2503
    assert f.yaw == pytest.approx(math.pi / 2)  # facing ENU x (east) is NED yaw +90 deg


def test_body_flu_velocity_becomes_body_frd() -> None:
    f = encode_velocity_setpoint(VelocitySetpoint((1.0, 0.3, 0.2), SetpointFrame.BODY, yaw_rate_rad_s=0.5))
    assert f.coordinate_frame == mavlink2.MAV_FRAME_BODY_NED == 8
    assert (f.vx, f.vy, f.vz) == (1.0, -0.3, -0.2)  # left -> right is negative, up -> down is negative
    assert f.type_mask == 1479
    assert f.yaw_rate == -0.5  # counter-clockwise (ENU) is negative about NED down


def test_no_yaw_means_zero_yaw_rate() -> None:
    f = encode_velocity_setpoint(VelocitySetpoint((0.0, 0.0, 0.0)))
    assert f.type_mask == 1479 and f.yaw_rate == 0.0 and math.copysign(1.0, f.yaw_rate) == 1.0


@pytest.mark.parametrize(("yaw_enu_deg", "yaw_ned_deg"), [(0, 90), (90, 0), (180, -90), (-90, 180), (45, 45)])
def test_yaw_conversion(yaw_enu_deg: float, yaw_ned_deg: float) -> None:
    f = encode_velocity_setpoint(VelocitySetpoint((0, 0, 0), yaw_rad=math.radians(yaw_enu_deg)))
    diff = (f.yaw - math.radians(yaw_ned_deg) + math.pi) % (2 * math.pi) - math.pi
    assert abs(diff) < 1e-12


def test_set_position_target_bytes() -> None:
    f = encode_velocity_setpoint(VelocitySetpoint((1.0, -2.0, 0.25), SetpointFrame.WORLD, yaw_rate_rad_s=0.1))
    msg = mavlink2.MAVLink_set_position_target_local_ned_message(
        1234, 1, 1, f.coordinate_frame, f.type_mask, 0, 0, 0, f.vx, f.vy, f.vz, 0, 0, 0, f.yaw, f.yaw_rate
    )
    tx = mavlink2.MAVLink(None, 255, 191)
    buf = bytes(msg.pack(tx))
    assert buf[0] == 0xFD  # MAVLink 2
    assert int.from_bytes(buf[7:10], "little") == 84  # SET_POSITION_TARGET_LOCAL_NED
    payload = buf[10 : 10 + buf[1]]
    # Wire order (sorted by size): time_boot_ms, x, y, z, vx, vy, vz, afx, afy, afz, yaw, yaw_rate,
    # type_mask, target_system, target_component, coordinate_frame.
    values = struct.unpack("<I11fHBBB", payload)
    assert values[0] == 1234
    assert values[4:7] == pytest.approx((-2.0, 1.0, -0.25))
    assert values[11] == pytest.approx(-0.1)
    assert values[12:] == (1479, 1, 1, 1)
    back = _roundtrip(msg)
    assert back.type_mask == 1479 and back.coordinate_frame == 1  # type: ignore[attr-defined]


def test_hard_limits_are_a_safety_net() -> None:
    check_hard_limits(VelocitySetpoint((3.0, 0.0, 1.0), yaw_rate_rad_s=1.0))
    with pytest.raises(SetpointError, match="horizontal speed 16.000 m/s exceeds the limit 15.000"):
        check_hard_limits(VelocitySetpoint((HARD_MAX_HORIZONTAL_M_S + 1.0, 0.0, 0.0)))
    with pytest.raises(SetpointError, match="vertical speed"):
        check_hard_limits(VelocitySetpoint((0.0, 0.0, -9.0)))
    with pytest.raises(SetpointError, match="yaw rate"):
        check_hard_limits(VelocitySetpoint((0.0, 0.0, 0.0), yaw_rate_rad_s=-20.0))
    with pytest.raises(SetpointError, match="finite"):
        VelocitySetpoint((math.nan, 0.0, 0.0))


def _pose(yaw_enu_deg: float, vel: tuple[float, float, float] | None = None) -> ExternalPose:
    T = Transform.from_xyz_yaw([1.0, 2.0, 3.0], math.radians(yaw_enu_deg))
    return ExternalPose(
        1_700_000_000_123_456_789,
        T,
        pos_std_m=0.01,
        rot_std_rad=0.02,
        vel_world_m_s=vel,
        quality_pct=90,
        reset_counter=3,
    )


def test_vision_position_estimate_is_ned_frd() -> None:
    msg = _roundtrip(encode_vision_position_estimate(_pose(90.0)))  # facing ENU y = north
    assert msg.usec == 1_700_000_000_123_456  # type: ignore[attr-defined]
    assert (msg.x, msg.y, msg.z) == pytest.approx((2.0, 1.0, -3.0))  # type: ignore[attr-defined]
    assert (msg.roll, msg.pitch, msg.yaw) == pytest.approx((0.0, 0.0, 0.0), abs=1e-6)  # type: ignore[attr-defined]
    cov = np.array(msg.covariance)  # type: ignore[attr-defined]
    diag_idx = [0, 6, 11, 15, 18, 20]
    assert cov[diag_idx] == pytest.approx([1e-4] * 3 + [4e-4] * 3)
    assert np.count_nonzero(np.delete(cov, diag_idx)) == 0
    assert msg.reset_counter == 3  # type: ignore[attr-defined]


def test_vision_attitude_with_roll_and_pitch() -> None:
    # FLU body pitched nose-down by 10 deg about its y (left) axis, heading east (ENU yaw 0).
    R_enu_flu = Rotation.from_euler("ZYX", [0.0, math.radians(10.0), 0.0])
    pose = ExternalPose(0, Transform(R_enu_flu, np.zeros(3)))
    msg = _roundtrip(encode_vision_position_estimate(pose))
    # Nose-down about FLU y (left) is nose-down in FRD too: NED pitch is -10 deg; NED yaw is 90 (east).
    assert msg.pitch == pytest.approx(math.radians(-10.0), abs=1e-6)  # type: ignore[attr-defined]
    assert msg.yaw == pytest.approx(math.radians(90.0), abs=1e-6)  # type: ignore[attr-defined]
    assert msg.roll == pytest.approx(0.0, abs=1e-6)  # type: ignore[attr-defined]


def test_odometry_quaternion_velocity_and_frames() -> None:
    msg = _roundtrip(encode_odometry(_pose(90.0, vel=(1.0, 0.0, 0.0))))  # facing north, moving east
    assert msg.frame_id == mavlink2.MAV_FRAME_LOCAL_NED  # type: ignore[attr-defined]
    assert msg.child_frame_id == mavlink2.MAV_FRAME_BODY_FRD  # type: ignore[attr-defined]
    assert msg.time_usec == 1_700_000_000_123_456  # type: ignore[attr-defined]
    assert list(msg.q) == pytest.approx([1.0, 0.0, 0.0, 0.0], abs=1e-6)  # type: ignore[attr-defined]
    assert (msg.vx, msg.vy, msg.vz) == pytest.approx((0.0, 1.0, 0.0), abs=1e-6)  # east is to the right  # type: ignore[attr-defined]
    assert msg.estimator_type == mavlink2.MAV_ESTIMATOR_TYPE_MOCAP and msg.quality == 90  # type: ignore[attr-defined]
    assert msg.pose_covariance[0] == pytest.approx(1e-4)  # type: ignore[attr-defined]


def test_odometry_without_velocity_marks_it_unknown() -> None:
    msg = _roundtrip(encode_odometry(_pose(0.0)))
    assert math.isnan(msg.vx) and math.isnan(msg.velocity_covariance[0])  # type: ignore[attr-defined]
    # heading east: NED yaw +90 deg -> quaternion about down by 90 deg
    expected = Rotation.from_euler("z", 90, degrees=True).as_quat()  # xyzw
    assert list(msg.q) == pytest.approx([expected[3], *expected[:3]], abs=1e-6)  # type: ignore[attr-defined]


def test_heartbeat_type_follows_component_id() -> None:
    assert heartbeat_type_for_component(191) == mavlink2.MAV_TYPE_ONBOARD_CONTROLLER
    assert heartbeat_type_for_component(194) == mavlink2.MAV_TYPE_ONBOARD_CONTROLLER
    assert heartbeat_type_for_component(190) == mavlink2.MAV_TYPE_GCS
    assert heartbeat_type_for_component(0) == mavlink2.MAV_TYPE_GCS


def test_position_velocity_acceleration_target_uses_all_three() -> None:
    """pva: the MAVLink spec's bits (0-2 position, 3-5 velocity, 6-8 acceleration, 10 yaw,
    11 yaw rate; set = ignore) with everything in local NED, on the wire."""
    assert TYPE_MASK_PVA_YAW == 2048 and TYPE_MASK_PVA_YAW_RATE == 1024
    sp = VelocitySetpoint(
        (0.1, 0.2, 0.3), SetpointFrame.WORLD, yaw_rate_rad_s=0.5, pos_m=(1.0, 2.0, 1.5), accel_m_s2=(0.4, -0.2, 0.1)
    )
    f = encode_velocity_setpoint(sp)
    assert f.coordinate_frame == 1 and f.type_mask == 1024
    assert f.pos_ned_m == (2.0, 1.0, -1.5) and (f.vx, f.vy, f.vz) == (0.2, 0.1, -0.3)
    assert f.accel_ned_m_s2 == (-0.2, 0.4, -0.1) and f.yaw_rate == -0.5
    msg = encode_setpoint_message(f, (1, 1), 0)
    back = _roundtrip(msg)
    assert (back.x, back.y, back.z) == pytest.approx((2.0, 1.0, -1.5))  # type: ignore[attr-defined]
    assert (back.afx, back.afy, back.afz) == pytest.approx((-0.2, 0.4, -0.1))  # type: ignore[attr-defined]
    assert encode_velocity_setpoint(VelocitySetpoint((0, 0, 0), yaw_rad=0.0, pos_m=(0, 0, 1))).type_mask == 2048


def test_position_targets_need_the_world_frame_and_bounded_acceleration() -> None:
    with pytest.raises(SetpointError, match="WORLD frame"):
        VelocitySetpoint((0, 0, 0), SetpointFrame.BODY, pos_m=(0.0, 0.0, 1.0))
    with pytest.raises(SetpointError, match="needs a position target"):
        VelocitySetpoint((0, 0, 0), accel_m_s2=(0.0, 0.0, 1.0))
    with pytest.raises(SetpointError, match="pos_m must be 3 finite"):
        VelocitySetpoint((0, 0, 0), pos_m=(0.0, math.nan, 1.0))
    with pytest.raises(SetpointError, match="acceleration 9.000 m/s\\^2 exceeds the limit 8.000"):
        check_hard_limits(VelocitySetpoint((0, 0, 0), pos_m=(0.0, 0.0, 1.0), accel_m_s2=(9.0, 0.0, 0.0)))
