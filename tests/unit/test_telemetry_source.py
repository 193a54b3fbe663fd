"""TelemetryPoseSource: the autopilot's local ENU estimate, placed in the world as mocap poses."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flightkit.clock import LockstepClock
from flightkit.errors import MocapError
from flightkit.frames import Transform, rotation_enu_flu_from_ned_frd
from flightkit.link.base import Telemetry
from flightkit.mocap.telemetry_source import AUTOPILOT_LOCAL_FRAME_ID, TelemetryPoseSource, pose_from_telemetry


def quat_wxyz(R: Rotation) -> tuple[float, float, float, float]:  # noqa: N803
    x, y, z, w = R.as_quat()
    return (float(w), float(x), float(y), float(z))


def tel(
    pos: tuple[float, float, float], R: Rotation, stamp_s: float = 1.0, hb_age_s: float = 0.1
) -> Telemetry:  # noqa: N803
    return Telemetry(
        stamp_s=stamp_s, pos_local_enu_m=pos, R_local_body_quat_wxyz=quat_wxyz(R), heartbeat_age_s=hb_age_s
    )


def test_identity_local_frame_gives_the_telemetry_pose() -> None:
    R = Rotation.from_euler("ZYX", [0.7, 0.05, -0.1])  # noqa: N806
    p = pose_from_telemetry(tel((1.0, -2.0, 1.5), R), "uav1", stamp_ns=123, seq=4)
    assert p is not None and p.valid and p.T_frame_body is not None
    assert p.body == "uav1" and p.stamp_ns == 123 and p.seq == 4 and p.received_s == 1.0
    assert p.frame_id == AUTOPILOT_LOCAL_FRAME_ID
    np.testing.assert_allclose(p.T_frame_body.translation, [1.0, -2.0, 1.5])
    assert (p.T_frame_body.rotation.inv() * R).magnitude() < 1e-12
    assert p.T_frame_body.yaw_rad == pytest.approx(0.7)


def test_local_frame_rotated_and_shifted_in_the_world() -> None:
    # the autopilot's local frame: origin at (2, 1, 0) in the world, its x axis pointing along world y
    T_world_local = Transform.from_xyz_yaw([2.0, 1.0, 0.0], math.pi / 2)  # noqa: N806
    R = Rotation.from_euler("z", 0.3)  # noqa: N806
    holder = _TelemetryHolder(tel((1.0, 0.0, 1.0), R))
    src = TelemetryPoseSource(holder, LockstepClock(), "uav1", T_world_local=T_world_local)  # type: ignore[arg-type]
    p = src.poll()
    assert p is not None
    np.testing.assert_allclose(p.T_world_body.translation, [2.0, 2.0, 1.0], atol=1e-12)
    assert p.T_world_body.yaw_rad == pytest.approx(math.pi / 2 + 0.3)
    assert p.T_mocap_body is not None  # the world pose in the (identity) mocap frame
    np.testing.assert_allclose(p.T_mocap_body.translation, [2.0, 2.0, 1.0], atol=1e-12)


def test_attitude_from_a_ned_frd_autopilot_round_trips() -> None:
    # what the link does with ATTITUDE_QUATERNION: NED/FRD -> ENU/FLU; a body yawed 30 deg east of north
    R_ned_frd = Rotation.from_euler("ZYX", [math.radians(30.0), 0.0, 0.0])  # noqa: N806
    R_enu_flu = rotation_enu_flu_from_ned_frd(R_ned_frd)  # noqa: N806
    p = pose_from_telemetry(tel((0.0, 0.0, 1.0), R_enu_flu), "b", stamp_ns=0)
    assert p is not None and p.T_frame_body is not None
    assert p.T_frame_body.yaw_rad == pytest.approx(math.radians(60.0))  # 30 deg from north = 60 deg from east


def test_no_position_yet_gives_none() -> None:
    assert pose_from_telemetry(Telemetry(), "uav1", stamp_ns=0) is None


def test_stale_heartbeat_or_bad_attitude_is_invalid() -> None:
    stale = pose_from_telemetry(tel((0.0, 0.0, 1.0), Rotation.identity(), hb_age_s=5.0), "u", stamp_ns=0)
    assert stale is not None and not stale.valid
    bad = Telemetry(
        stamp_s=1.0,
        pos_local_enu_m=(0.0, 0.0, 1.0),
        R_local_body_quat_wxyz=(0.0, 0.0, 0.0, 0.0),
        heartbeat_age_s=0.0,
    )
    p = pose_from_telemetry(bad, "u", stamp_ns=0)
    assert p is not None and not p.valid and p.T_frame_body is not None
    np.testing.assert_allclose(p.T_frame_body.translation, [0.0, 0.0, 1.0])


class _TelemetryHolder:
    """The one thing TelemetryPoseSource reads from a link: its latest ``telemetry`` snapshot."""

    def __init__(self, telemetry: Telemetry) -> None:
        self.telemetry = telemetry


def test_poll_hands_out_only_new_snapshots() -> None:
    clock = LockstepClock()
    holder = _TelemetryHolder(Telemetry())
    src = TelemetryPoseSource(holder, clock, "uav1")  # type: ignore[arg-type]
    assert src.poll() is None and src.bodies() == () and src.latest("uav1") is None
    holder.telemetry = tel((0.5, 0.0, 1.0), Rotation.identity(), stamp_s=2.0)
    first = src.poll()
    assert first is not None and first.seq == 1 and first.stamp_ns == clock.time_ns()
    assert src.poll() is None  # unchanged snapshot: nothing new
    clock.advance(0.02)
    holder.telemetry = tel((0.6, 0.0, 1.0), Rotation.identity(), stamp_s=2.02)
    second = src.poll()
    assert second is not None and second.seq == 2 and second.received_s == 2.02
    assert src.latest("uav1") is second and src.latest("other") is None
    assert src.bodies() == ("uav1",)


def test_rate_is_checked() -> None:
    with pytest.raises(MocapError, match="outside 1-1000 Hz"):
        TelemetryPoseSource(_TelemetryHolder(Telemetry()), LockstepClock(), "u", rate_hz=0.0)  # type: ignore[arg-type]


def test_repeat_republishes_the_last_snapshot_stamped_at_each_poll() -> None:
    # a bridge republishing the estimate at a fixed rate: every poll hands out a pose, the
    # unchanged ones with the old position, stamped and received at the poll
    clock = LockstepClock()
    holder = _TelemetryHolder(tel((0.5, 0.0, 1.0), Rotation.identity(), stamp_s=clock.monotonic_s()))
    src = TelemetryPoseSource(holder, clock, "uav1", repeat=True)  # type: ignore[arg-type]
    first = src.poll()
    clock.advance(0.01)
    held = src.poll()
    assert first is not None and held is not None
    assert held.seq == first.seq + 1 and held.stamp_ns == first.stamp_ns + 10_000_000
    assert held.received_s == pytest.approx(clock.monotonic_s())
    np.testing.assert_allclose(held.T_world_body.translation, first.T_world_body.translation)
    holder.telemetry = tel((0.6, 0.0, 1.0), Rotation.identity(), stamp_s=clock.monotonic_s())
    clock.advance(0.01)
    moved = src.poll()
    assert moved is not None and moved.T_world_body.translation[0] == pytest.approx(0.6)
