"""Replayed sequences (flightkit.datasets.replay): time reversal, the rows' mirror, strides."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from flightkit.datasets.base import CameraIntrinsics
from flightkit.datasets.registry import open_sequence
from flightkit.datasets.replay import exposure_sequence, mirror_rows_intrinsics, reversed_sequence, strided_sequence
from flightkit.errors import DatasetError
from flightkit.frames import Transform

S = np.diag([1.0, -1.0, 1.0])


def test_mirrored_camera_sees_the_mirrored_world_upside_down() -> None:
    """Known answer: points and camera mirrored in y, projected through the mirrored intrinsics
    (with the fr1 lens' distortion), land on the original pixels' mirrored rows."""
    k = CameraIntrinsics(517.3, 516.5, 318.6, 255.3, 640, 480, dist=(0.2624, -0.9531, -0.0054, 0.0026, 1.1633))
    km = mirror_rows_intrinsics(k)
    rng = np.random.default_rng(3)
    X_world = rng.uniform([-1.0, -1.0, 2.0], [1.0, 1.0, 4.0], (50, 3))
    T_world_cam = Transform.from_xyz_euler_deg([0.1, -0.2, 0.3], "xyz", [5.0, -8.0, 20.0]).as_matrix()

    def project(K: CameraIntrinsics, T: np.ndarray, X: np.ndarray) -> np.ndarray:
        T_cam_world = np.linalg.inv(T)
        rvec, _ = cv2.Rodrigues(T_cam_world[:3, :3])
        px, _ = cv2.projectPoints(X, rvec, T_cam_world[:3, 3], K.K, np.array(K.dist))
        return px.reshape(-1, 2)

    S4 = np.diag([1.0, -1.0, 1.0, 1.0])
    px = project(k, T_world_cam, X_world)
    px_m = project(km, S4 @ T_world_cam @ S4, X_world @ S)
    assert np.all(np.abs(px[:, 1] - 250) < 400)  # the points are in view
    np.testing.assert_allclose(px_m[:, 0], px[:, 0], atol=1e-6)
    np.testing.assert_allclose(px_m[:, 1], k.height - 1 - px[:, 1], atol=1e-6)


@pytest.fixture
def rpy(shared_data: Path):  # type: ignore[no-untyped-def]
    return open_sequence(shared_data / "tum_fr1rpy_000_199")


def test_reversed_sequence_plays_backwards_on_increasing_stamps(rpy) -> None:  # type: ignore[no-untyped-def]
    rev = reversed_sequence(rpy)
    assert rev.name.endswith("reversed, rows mirrored")  # the Kinect has a rolling shutter: mirrored
    src_t, t = rpy.stamps_ns(), rev.stamps_ns()
    assert len(rev) == len(rpy) and np.all(np.diff(t) > 0)
    assert t[0] == src_t[0] and t[-1] == src_t[-1]
    np.testing.assert_array_equal(np.diff(t), np.diff(src_t)[::-1])
    assert rev.intrinsics.cy == pytest.approx(rpy.intrinsics.height - 1 - rpy.intrinsics.cy)
    assert rev.intrinsics.readout_s == rpy.intrinsics.readout_s
    first = next(iter(rev.frames(0, 1)))
    last_src = next(iter(rpy.frames(len(rpy) - 1, len(rpy))))
    assert first.index == 0 and first.stamp_ns == t[0]
    np.testing.assert_array_equal(first.gray, last_src.gray[::-1])
    np.testing.assert_array_equal(first.depth_raw, last_src.depth_raw[::-1])
    assert first.T_world_camera is not None and last_src.T_world_camera is not None
    S4 = np.diag([1.0, -1.0, 1.0, 1.0])
    np.testing.assert_allclose(first.T_world_camera.as_matrix(), S4 @ last_src.T_world_camera.as_matrix() @ S4)


def test_reversed_ground_truth_is_the_source_at_the_mirrored_time(rpy) -> None:  # type: ignore[no-untyped-def]
    gt, rev_gt = rpy.groundtruth(), reversed_sequence(rpy).groundtruth()
    assert np.all(np.diff(rev_gt.stamps_ns) > 0)
    t_sum = int(rpy.stamps_ns()[0]) + int(rpy.stamps_ns()[-1])
    i = len(gt) // 3
    j = int(np.flatnonzero(rev_gt.stamps_ns == t_sum - gt.stamps_ns[i])[0])
    np.testing.assert_allclose(rev_gt.positions[j], S @ gt.positions[i])
    R_src = Transform.from_quat_wxyz(gt.positions[i], gt.quats_wxyz[i]).as_matrix()[:3, :3]
    R_rev = Transform.from_quat_wxyz(rev_gt.positions[j], rev_gt.quats_wxyz[j]).as_matrix()[:3, :3]
    np.testing.assert_allclose(R_rev, S @ R_src @ S, atol=1e-12)
    # Unmirrored, the poses are the source's own.
    plain_rev = reversed_sequence(rpy, mirror_rows=False).groundtruth()
    np.testing.assert_allclose(plain_rev.positions[j], gt.positions[i])
    assert reversed_sequence(rpy, mirror_rows=False).intrinsics == rpy.intrinsics


def test_global_shutter_reverses_without_a_mirror(shared_data: Path) -> None:
    kitti = open_sequence(shared_data / "kitti06_stereo")
    rev = reversed_sequence(kitti)
    assert kitti.intrinsics.readout_s == 0 and rev.intrinsics == kitti.intrinsics
    assert rev.baseline_m == kitti.baseline_m and rev.name == "kitti06_stereo reversed"
    frame = next(iter(rev.frames(0, 1)))
    src = next(iter(kitti.frames(len(kitti) - 1, len(kitti))))
    np.testing.assert_array_equal(frame.right_gray, src.right_gray)


def test_strided_sequence_keeps_every_nth_frame(rpy) -> None:  # type: ignore[no-untyped-def]
    half = strided_sequence(rpy, 2, offset=1)
    assert len(half) == len(rpy) // 2
    np.testing.assert_array_equal(half.stamps_ns(), rpy.stamps_ns()[1::2])
    frames = list(half.frames(2, 4))
    assert [f.index for f in frames] == [2, 3]
    src = next(iter(rpy.frames(5, 6)))
    np.testing.assert_array_equal(frames[0].gray, src.gray)
    assert half.groundtruth().positions.shape == rpy.groundtruth().positions.shape
    with pytest.raises(DatasetError, match="stride"):
        strided_sequence(rpy, 2, offset=2)
    with pytest.raises(DatasetError, match="at least 2 frames"):
        strided_sequence(rpy, len(rpy))


def test_exposure_sequence_scales_the_images_and_leaves_depth(rpy) -> None:  # type: ignore[no-untyped-def]
    gains = np.ones(len(rpy))
    gains[1], gains[2] = 0.5, 2.0
    seq = exposure_sequence(rpy, gains)
    src = list(rpy.frames(0, 3))
    out = list(seq.frames(0, 3))
    np.testing.assert_array_equal(out[0].gray, src[0].gray)
    np.testing.assert_array_equal(out[1].gray, np.rint(src[1].gray * 0.5).astype(np.uint8))
    assert out[2].gray.max() == 255 and out[2].gray.dtype == np.uint8  # saturated, as a sensor is
    np.testing.assert_array_equal(out[2].gray, np.minimum(src[2].gray.astype(int) * 2, 255))
    np.testing.assert_array_equal(out[1].depth_raw, src[1].depth_raw)
    np.testing.assert_array_equal(seq.stamps_ns(), rpy.stamps_ns())
    with pytest.raises(DatasetError, match="one positive, finite gain per frame"):
        exposure_sequence(rpy, gains[:-1])
    with pytest.raises(DatasetError, match="one positive, finite gain per frame"):
        exposure_sequence(rpy, np.zeros(len(rpy)))
