"""flightkit.sim.sequence: body poses with quadrotor attitude, and the lazily rendered SimSequence."""

from __future__ import annotations

import math
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flightkit.config import CameraConfig
from flightkit.datasets.base import Sequence
from flightkit.errors import DatasetError, SimError
from flightkit.frames import Transform
from flightkit.sim.camera import PinholeModel, Scene, SimCamera
from flightkit.sim.sequence import (
    GRAVITY_M_S2,
    ImagingOptions,
    SimSequence,
    body_poses_along,
    quadrotor_attitude,
)
from trajectories.patterns import Circle

G = GRAVITY_M_S2
SMALL = CameraConfig(width_px=160, height_px=120)


def _line_path(accel_m_s2: float, yaw_rad: float = 0.0):  # type: ignore[no-untyped-def]
    """Constant acceleration along the heading from (-1, 0, 1.5): ``t -> (pos, yaw)``."""
    d = np.array([math.cos(yaw_rad), math.sin(yaw_rad), 0.0])

    def fn(t_s: float) -> tuple[np.ndarray, float]:
        return np.array([-1.0, 0.0, 1.5]) + 0.5 * accel_m_s2 * t_s * t_s * d, yaw_rad

    return fn


class _PatternLike:
    """Anything with ``reference(t)`` and ``duration_s`` is a path (duck-typed, like the patterns)."""

    duration_s = 2.0

    def reference(self, t_s: float) -> SimpleNamespace:
        return SimpleNamespace(pos_m=(0.1 * t_s, 0.0, 1.2), yaw_rad=0.25 * t_s)


# ----------------------------------------------------------------------------- attitude
def test_attitude_at_rest_is_the_heading_only() -> None:
    R = quadrotor_attitude([0.0, 0.0, 0.0], 0.7)
    assert (R.inv() * Rotation.from_euler("z", 0.7)).magnitude() < 1e-12


@pytest.mark.parametrize("yaw_rad", [0.0, 1.0, -2.5])
def test_forward_acceleration_pitches_the_nose_down_by_atan_a_over_g(yaw_rad: float) -> None:
    a = 2.0
    R = quadrotor_attitude([a * math.cos(yaw_rad), a * math.sin(yaw_rad), 0.0], yaw_rad)
    x_b, y_b, z_b = R.as_matrix().T
    assert math.degrees(math.asin(-x_b[2])) == pytest.approx(math.degrees(math.atan2(a, G)), abs=1e-9)
    assert abs(y_b[2]) < 1e-12  # no roll
    # The thrust axis is along a + g, and the nose points along the heading.
    np.testing.assert_allclose(z_b, np.array([a * math.cos(yaw_rad), a * math.sin(yaw_rad), G]) / math.hypot(a, G))
    assert math.atan2(x_b[1], x_b[0]) == pytest.approx(yaw_rad)


def test_sideways_acceleration_rolls() -> None:
    R = quadrotor_attitude([0.0, 1.0, 0.0], 0.0)  # accelerate to the left (+y in FLU at yaw 0)
    roll, pitch, _ = R.as_euler("xyz")
    assert roll == pytest.approx(-math.atan2(1.0, G))  # left side down: negative roll about x
    assert pitch == pytest.approx(0.0, abs=1e-12)


def test_free_fall_has_no_attitude() -> None:
    with pytest.raises(SimError, match="free fall"):
        quadrotor_attitude([0.0, 0.0, -G], 0.0)


# ----------------------------------------------------------------------------- body poses
def test_body_poses_from_a_callable_carry_the_tilt_and_stamps() -> None:
    poses = body_poses_along(_line_path(1.5, yaw_rad=0.4), 10.0, start_s=1.0, duration_s=2.0, stamp0_ns=5_000)
    assert len(poses) == 21
    stamps = np.array([s for s, _ in poses])
    np.testing.assert_array_equal(stamps, 5_000 + np.round((1.0 + np.arange(21) / 10.0) * 1e9).astype(np.int64))
    for k, (_, T) in enumerate(poses):
        t = 1.0 + k / 10.0
        s = 0.75 * t * t
        np.testing.assert_allclose(T.translation, [-1.0 + s * math.cos(0.4), s * math.sin(0.4), 1.5])
        # Constant acceleration: the second difference is exact, so is the tilt.
        tilt = math.acos(T.rotation.apply([0.0, 0.0, 1.0])[2])
        assert tilt == pytest.approx(math.atan2(1.5, G), abs=1e-9)
        assert T.yaw_rad == pytest.approx(0.4, abs=1e-9)


def test_body_poses_level_without_tilt_and_from_a_pattern_like_object() -> None:
    poses = body_poses_along(_PatternLike(), 5.0, tilt=False)
    assert len(poses) == 11  # 0 .. 2 s at 5 Hz, both ends
    _, T_last = poses[-1]
    np.testing.assert_allclose(T_last.translation, [0.2, 0.0, 1.2])
    assert (T_last.rotation.inv() * Rotation.from_euler("z", 0.5)).magnitude() < 1e-12


def test_circle_tilts_towards_the_centre_by_the_centripetal_acceleration() -> None:
    circle = Circle(radius_m=1.0, period_s=8.0, height_m=1.5)  # faster than the lab's, for a visible tilt
    v = circle.cruise_speed_m_s
    poses = body_poses_along(circle, 10.0, start_s=2.0, duration_s=2.0)
    for _, T in poses:
        z_b = T.rotation.apply([0.0, 0.0, 1.0])
        horizontal = z_b[:2] / np.linalg.norm(z_b[:2])
        to_centre = -T.translation[:2] / np.linalg.norm(T.translation[:2])
        assert float(horizontal @ to_centre) > 0.999
        # The window of the second difference shortens the chord a little: within 1 %.
        assert math.atan2(np.linalg.norm(z_b[:2]), z_b[2]) == pytest.approx(math.atan2(v * v / 1.0, G), rel=0.01)


def test_body_poses_reject_bad_arguments() -> None:
    with pytest.raises(SimError, match="rate_hz"):
        body_poses_along(_PatternLike(), 0.0)
    with pytest.raises(SimError, match="duration_s"):
        body_poses_along(_line_path(0.0), 10.0)
    with pytest.raises(TypeError, match="reference"):
        body_poses_along(42, 10.0)


# ----------------------------------------------------------------------------- the sequence
@pytest.fixture(scope="module")
def seq() -> SimSequence:
    poses = body_poses_along(_line_path(0.4), 10.0, duration_s=0.5)
    return SimSequence.from_config(SMALL, poses, name="line")


def test_sequence_protocol_and_metadata(seq: SimSequence) -> None:
    assert isinstance(seq, Sequence)
    assert (seq.kind, seq.name, len(seq)) == ("sim", "line", 6)
    assert seq.intrinsics.K == pytest.approx(SimCamera.from_config(SMALL).model.K)
    assert seq.depth_intrinsics == seq.intrinsics
    assert seq.baseline_m == pytest.approx(SMALL.stereo_baseline_m)
    assert seq.rectification is None
    np.testing.assert_array_equal(seq.stamps_ns(), np.arange(6) * 100_000_000)


def test_ground_truth_is_the_body_pose_through_the_mount(seq: SimSequence) -> None:
    T_body_camera = SMALL.T_body_camera.to_transform()
    gt = seq.groundtruth()
    body = seq.body_groundtruth()
    for i, (T_wc, T_wb) in enumerate(zip(gt.transforms(), body.transforms(), strict=True)):
        assert T_wc.almost_equal(T_wb @ T_body_camera, 1e-9, 1e-9)
        assert seq.T_world_camera(i).almost_equal(T_wc, 1e-9, 1e-9)


def test_frames_render_images_depth_and_stereo_consistent_with_the_pose(seq: SimSequence) -> None:
    frames = list(seq.frames(1, 6, 2))
    assert [f.index for f in frames] == [1, 3, 5]
    f = frames[0]
    h, w = 120, 160
    assert f.gray.shape == (h, w) and f.gray.dtype == np.uint8
    assert f.color_bgr is not None and f.color_bgr.shape == (h, w, 3)
    assert f.right_gray is not None and f.right_gray.shape == (h, w)
    assert f.T_world_camera is not None and f.T_world_camera.almost_equal(seq.T_world_camera(1))
    assert f.gray.std() > 20  # textured, not blank
    depth = f.depth_m
    assert depth is not None and depth.dtype == np.float32 and np.all(depth > 0)
    # Back-projecting the top rows lands on the floor, z = 0 in the world. (The lab's mount
    # holds the camera upside down, looking forward-down: the top of the image is the floor
    # just ahead of the vehicle, the bottom the far floor and the walls.)
    K = seq.intrinsics.K
    v, u = np.mgrid[0:20:4, 0:w:8]
    z = depth[v, u].astype(np.float64)
    pts_cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=-1).reshape(-1, 3)
    pts_world = f.T_world_camera.apply(pts_cam)
    assert np.abs(pts_world[:, 2]).max() < 0.005  # depth is rounded to mm, ~1.3 m away
    # The right image is the left one shifted by the disparity f B / z along the rows.
    fx, B = K[0, 0], seq.baseline_m
    assert B is not None
    left, right = f.gray.astype(np.float32), f.right_gray.astype(np.float32)
    vc, uc = 15, w // 2
    d_true = fx * B / float(depth[vc, uc])
    patch = left[vc - 5 : vc + 6, uc - 5 : uc + 6]
    costs = [np.abs(right[vc - 5 : vc + 6, uc - d - 5 : uc - d + 6] - patch).mean() for d in range(0, 12)]
    assert abs(int(np.argmin(costs)) - d_true) <= 1.0


def test_frames_are_rendered_lazily_and_cached_on_request() -> None:
    poses = body_poses_along(_line_path(0.0), 10.0, duration_s=0.2)
    lazy = SimSequence.from_config(SMALL, poses, stereo=False, color=False)
    assert lazy.render_s == 0.0  # nothing rendered on construction
    a, b = lazy.frame(0), lazy.frame(0)
    assert a is not b and np.array_equal(a.gray, b.gray)
    assert a.right_gray is None and a.color_bgr is None and lazy.baseline_m is None
    cached = SimSequence.from_config(SMALL, poses, stereo=False, cache=True)
    assert cached.frame(-1) is cached.frame(2)
    with pytest.raises(IndexError):
        cached.frame(3)


def test_noise_is_seeded_per_frame_and_has_the_requested_spread() -> None:
    poses = body_poses_along(_line_path(0.0), 10.0, duration_s=0.1)
    clean = SimSequence.from_config(SMALL, poses, stereo=False)
    noisy = SimSequence.from_config(SMALL, poses, stereo=False, imaging=ImagingOptions(noise_std=4.0, seed=3))
    again = SimSequence.from_config(SMALL, poses, stereo=False, imaging=ImagingOptions(noise_std=4.0, seed=3))
    other = SimSequence.from_config(SMALL, poses, stereo=False, imaging=ImagingOptions(noise_std=4.0, seed=4))
    c, n = clean.frame(0).color_bgr, noisy.frame(0).color_bgr
    assert c is not None and n is not None
    diff = n.astype(np.float64) - c.astype(np.float64)
    assert diff.std() == pytest.approx(4.0, rel=0.1)
    assert np.array_equal(n, again.frame(0).color_bgr)
    assert not np.array_equal(n, other.frame(0).color_bgr)
    assert not np.array_equal(n, noisy.frame(1).color_bgr)


def test_depth_noise_grows_with_range_squared() -> None:
    poses = body_poses_along(_line_path(0.0), 10.0, duration_s=0.0)
    clean = SimSequence.from_config(SMALL, poses, stereo=False).frame(0).depth_m
    noisy = (
        SimSequence.from_config(SMALL, poses, stereo=False, imaging=ImagingOptions(depth_noise_m_per_m2=0.01))
        .frame(0)
        .depth_m
    )
    assert clean is not None and noisy is not None
    z = clean.astype(np.float64)
    err = (noisy - clean).astype(np.float64) / (z * z)
    assert err.std() == pytest.approx(0.01, rel=0.15)


def test_motion_blur_smears_a_fast_pan_and_keeps_depth_sharp() -> None:
    def spin(t_s: float) -> tuple[list[float], float]:
        return [0.0, 0.0, 1.5], 3.0 * t_s  # 3 rad/s yaw: ~5 px per 10 ms at 160 px

    poses = body_poses_along(spin, 10.0, duration_s=0.1, tilt=False)
    sharp = SimSequence.from_config(SMALL, poses, stereo=False).frame(1)
    blurred = SimSequence.from_config(
        SMALL, poses, stereo=False, imaging=ImagingOptions(exposure_s=0.02, blur_samples=5)
    ).frame(1)
    sharpness = [cv2.Laplacian(f.gray, cv2.CV_64F).var() for f in (sharp, blurred)]
    assert sharpness[1] < 0.7 * sharpness[0]
    assert blurred.depth_raw is not None and sharp.depth_raw is not None
    assert np.array_equal(blurred.depth_raw, sharp.depth_raw)


def test_bad_poses_are_clear_errors() -> None:
    cam = SimCamera(Scene.default_lab(), PinholeModel.from_fov(160, 120))
    with pytest.raises(DatasetError, match="no poses"):
        SimSequence(cam, [], Transform())
    with pytest.raises(DatasetError, match="stamps must increase"):
        SimSequence(cam, [(10, Transform()), (10, Transform())], Transform())
    with pytest.raises(SimError, match="blur_samples"):
        ImagingOptions(blur_samples=1)
