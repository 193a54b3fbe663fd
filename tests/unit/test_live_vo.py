"""The pure parts of live VO: uncertainty from quality, the vision pose sent, frame pairing."""

from __future__ import annotations

import math

import pytest

from estimation.live_config import LiveVoConfig, external_pose_from_frame, vision_uncertainty
from estimation.live_inputs import FramePairer, intrinsics_from_camera_info
from estimation.pipeline import FramePose, Quality
from flightkit.bus.image_msgs import CameraInfo
from flightkit.bus.msg_base import Header
from flightkit.errors import EstimationError
from flightkit.frames import Transform
from flightkit.link.mavlink import encode_vision_position_estimate


def frame_pose(T_world_body: Transform, stamp_ns: int, quality: Quality, n_inliers: int) -> FramePose:  # noqa: N803
    m = T_world_body.as_matrix()
    return FramePose(0, stamp_ns, m, m, n_inliers, quality, False, {})


# ------------------------------------------------------------------------- uncertainty


def test_good_estimate_with_enough_inliers_gets_the_base_deviation() -> None:
    assert vision_uncertainty(Quality.GOOD, 250) == (0.02, 0.01, 100)
    assert vision_uncertainty(Quality.INIT, 0) == (0.02, 0.01, 100)


def test_fewer_inliers_scale_with_the_square_root() -> None:
    pos, rot, pct = vision_uncertainty(Quality.GOOD, 25)
    assert pos == pytest.approx(0.04) and rot == pytest.approx(0.02)  # sqrt(100 / 25) = 2
    assert pct == 62
    # capped at 4x however few inliers
    assert vision_uncertainty(Quality.GOOD, 1)[0] == pytest.approx(0.08)


def test_weak_fallback_and_predicted_are_worse_than_good() -> None:
    good = vision_uncertainty(Quality.GOOD, 50)
    weak = vision_uncertainty(Quality.WEAK, 50)
    fallback = vision_uncertainty(Quality.FALLBACK, 50)
    assert weak[0] == pytest.approx(3 * good[0]) and weak[2] <= 30
    assert fallback[0] == pytest.approx(2 * good[0]) and fallback[2] <= 50
    assert vision_uncertainty(Quality.PREDICTED, 300) == (0.5, 0.2, 1)


def test_custom_base_deviation() -> None:
    pos, rot, _ = vision_uncertainty(
        Quality.GOOD, 10, base_pos_std_m=0.05, base_rot_std_rad=0.03, ref_inliers=40
    )
    assert pos == pytest.approx(0.1) and rot == pytest.approx(0.06)


# ------------------------------------------------------------------------- the pose sent


def test_vision_pose_carries_the_capture_stamp_and_the_covariance_on_the_wire() -> None:
    T = Transform.from_xyz_euler_deg([1.0, 2.0, 1.5], "ZYX", [40.0, 0.0, 0.0])  # noqa: N806
    stamp_ns = 1_700_000_123_456_789_000
    ext = external_pose_from_frame(frame_pose(T, stamp_ns, Quality.GOOD, 25))
    assert ext.stamp_ns == stamp_ns
    assert ext.T_world_body.almost_equal(T, 1e-12, 1e-12)
    assert ext.pos_std_m == pytest.approx(0.04) and ext.rot_std_rad == pytest.approx(0.02)
    assert ext.quality_pct == 62
    msg = encode_vision_position_estimate(ext)
    assert msg.usec == stamp_ns // 1000  # the frame's capture time, not the send time
    # NED: north = world y, east = world x, down = -z
    assert (msg.x, msg.y, msg.z) == pytest.approx((2.0, 1.0, -1.5))
    assert msg.yaw == pytest.approx(math.radians(90.0 - 40.0))
    # covariance upper triangle: diagonal entries are at 0, 6, 11, 15, 18, 20
    diag = [msg.covariance[i] for i in (0, 6, 11, 15, 18, 20)]
    assert diag == pytest.approx([0.04**2] * 3 + [0.02**2] * 3)


def test_config_base_deviation_reaches_the_pose() -> None:
    cfg = LiveVoConfig(base_pos_std_m=0.01, base_rot_std_rad=0.005)
    ext = external_pose_from_frame(frame_pose(Transform.identity(), 5, Quality.GOOD, 400), cfg)
    assert (ext.pos_std_m, ext.rot_std_rad, ext.quality_pct) == (0.01, 0.005, 100)


def test_config_is_validated() -> None:
    with pytest.raises(EstimationError, match="stereo pair"):
        LiveVoConfig(method="stereo")
    with pytest.raises(EstimationError, match="unknown VO method"):
        LiveVoConfig(method="orb-slam")
    with pytest.raises(EstimationError, match="vision_rate_hz"):
        LiveVoConfig(vision_rate_hz=100.0)


def test_intrinsics_from_camera_info() -> None:
    info = CameraInfo.from_intrinsics(Header(0, "cam"), 320, 240, 160.0, 161.0, 159.5, 119.5)
    intr = intrinsics_from_camera_info(info)
    assert (intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height) == (
        160.0,
        161.0,
        159.5,
        119.5,
        320,
        240,
    )
    assert intr.dist == ()  # all-zero plumb_bob = no distortion
    with pytest.raises(EstimationError, match="no focal length"):
        intrinsics_from_camera_info(CameraInfo(Header(0, "cam"), 240, 320))


# ------------------------------------------------------------------------- pairing


def test_pairs_in_either_arrival_order() -> None:
    p = FramePairer()
    assert p.add_color(100, "c100") is None
    assert p.add_depth(100, "d100") == (100, "c100", "d100")
    assert p.add_depth(200, "d200") is None
    assert p.add_color(200, "c200") == (200, "c200", "d200")
    assert p.paired == 2 and p.unmatched == 0


def test_tolerance_and_nearest_partner() -> None:
    p = FramePairer(tolerance_ns=10)
    p.add_depth(95, "d95")
    p.add_depth(103, "d103")
    assert p.add_color(100, "c100") == (100, "c100", "d103")  # nearest within 10 ns
    assert p.unmatched == 1  # d95 is older than the pair: it can never match now
    assert p.add_color(200, "c200") is None
    assert p.add_depth(211, "d211") is None  # 11 ns apart: not a pair


def test_lost_frames_are_counted_and_waiting_is_bounded() -> None:
    p = FramePairer(keep=2)
    for s in (1, 2, 3, 4):
        assert p.add_color(s, f"c{s}") is None
    assert p.unmatched == 2  # c1 and c2 pushed out
    assert p.add_depth(4, "d4") == (4, "c4", "d4")
    assert p.unmatched == 3  # c3 can no longer match
