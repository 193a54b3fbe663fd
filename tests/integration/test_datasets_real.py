"""Every reader end to end on the real sequences in ../shared/data (read in place)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from flightkit.datasets import open_sequence, read_kitti_poses, read_tum
from flightkit.datasets.euroc import read_euroc_camera
from flightkit.datasets.files import FileSequence
from flightkit.errors import DatasetError
from flightkit.frames import Transform


def test_kitti06_stereo(shared_data: Path) -> None:
    seq = open_sequence(shared_data / "kitti06_stereo")
    assert seq.kind == "kitti" and len(seq) == 51
    k = seq.intrinsics
    assert (k.fx, k.fy, k.cx, k.cy, k.width, k.height) == (707.0912, 707.0912, 601.8873, 183.1104, 1226, 370)
    assert seq.baseline_m == pytest.approx(0.537151, abs=1e-6)
    frames = list(seq.frames(0, None, 10))
    assert [f.index for f in frames] == [0, 10, 20, 30, 40, 50]
    f = frames[1]
    assert f.gray.shape == (370, 1226) and f.right_gray is not None and f.right_gray.shape == (370, 1226)
    line11 = (shared_data / "kitti06_stereo" / "times.txt").read_text().splitlines()[10]
    assert f.stamp_ns == round(float(line11) * 1e9)
    # Ground truth equals poses.txt, and the TUM conversion shipped beside it.
    gt = seq.groundtruth()
    poses = read_kitti_poses(shared_data / "kitti06_stereo" / "poses.txt")
    assert np.allclose(gt.positions, poses.positions) and len(gt) == 51
    tum = read_tum(shared_data / "kitti06_stereo" / "groundtruth_tum.txt")
    assert np.allclose(tum.positions, gt.positions, atol=1e-6)
    assert abs(gt.path_length_m() - 59.9) < 0.1
    assert f.T_world_camera is not None and f.T_world_camera.almost_equal(gt.transform(10), 1e-12, 1e-12)
    # The crosscheck image from pyslam is pixel-identical to frame 12.
    ref = cv2.imread(
        str(shared_data / "kitti06_stereo" / "crosscheck_pyslam" / "kitti06-12.png"), cv2.IMREAD_GRAYSCALE
    )
    if ref is not None:
        assert np.array_equal(seq.frame(12).gray, ref)  # type: ignore[attr-defined]


def test_sevenscenes_depth_in_mm_and_camera_to_world_poses(shared_data: Path) -> None:
    seq = open_sequence(shared_data / "sevenscenes_tsdf50")
    assert seq.kind == "7scenes" and len(seq) == 50
    assert (seq.intrinsics.fx, seq.intrinsics.fy, seq.intrinsics.cx, seq.intrinsics.cy) == (
        585,
        585,
        320,
        240,
    )
    assert seq.depth_intrinsics is not None
    assert isinstance(seq, FileSequence) and not seq.depth_registered  # another camera: VO weighs its depth less
    frames = list(seq.frames(0, 10, 5))
    f0, f5 = frames
    assert f0.color_bgr is not None and f0.color_bgr.shape == (480, 640, 3)
    assert f0.depth_raw is not None and f0.depth_raw.dtype == np.uint16
    depth = f0.depth_m
    assert depth is not None and depth.dtype == np.float32
    valid = depth > 0
    assert np.array_equal(~valid, f0.depth_raw == 0)  # 0 = invalid stays 0
    assert np.allclose(depth[valid], f0.depth_raw[valid] / 1000.0)
    assert 1.5 < float(np.median(depth[valid])) < 2.8  # README: median 2.13 m
    assert f5.stamp_ns == round(5 * 1e9 / 30)
    # Stamps and poses agree with groundtruth_tum.txt.
    tum = read_tum(shared_data / "sevenscenes_tsdf50" / "groundtruth_tum.txt")
    gt = seq.groundtruth()
    assert np.abs(tum.stamps_ns - gt.stamps_ns).max() < 1000
    assert np.allclose(tum.positions, gt.positions, atol=1e-6)
    # Pose convention: back-project frame 5's depth, move it into frame 0: it lands on frame 0's depth.
    assert f0.T_world_camera is not None and f5.T_world_camera is not None
    T_0_5 = f0.T_world_camera.inverse() @ f5.T_world_camera  # noqa: N806
    d5 = f5.depth_m
    assert d5 is not None
    v, u = np.nonzero(d5 > 0)
    sel = slice(None, None, 97)
    z = d5[v[sel], u[sel]]
    k = seq.intrinsics
    pts5 = np.column_stack([(u[sel] - k.cx) / k.fx * z, (v[sel] - k.cy) / k.fy * z, z])
    pts0 = T_0_5.apply(pts5)
    u0 = np.round(pts0[:, 0] / pts0[:, 2] * k.fx + k.cx).astype(int)
    v0 = np.round(pts0[:, 1] / pts0[:, 2] * k.fy + k.cy).astype(int)
    inside = (u0 >= 0) & (u0 < 640) & (v0 >= 0) & (v0 < 480)
    d0 = depth[v0[inside], u0[inside]]
    ok = d0 > 0
    dz = np.abs(d0[ok] - pts0[inside][ok, 2])
    assert np.median(dz) < 0.02  # README: 8.1 mm with camera-to-world poses


def test_tum_pairs_depth_scale_and_stamps(shared_data: Path) -> None:
    seq = open_sequence(shared_data / "tum_fr1xyz_pairs" / "case_1")
    assert seq.kind == "tum_pair" and len(seq) == 2
    k = seq.intrinsics
    assert (round(k.fx, 1), round(k.fy, 1), round(k.cx, 1), round(k.cy, 1)) == (517.3, 516.5, 318.6, 255.3)
    prev, curr = seq.frames()
    assert (prev.stamp_ns, curr.stamp_ns) == (1305031102_215900000, 1305031102_275800000)
    assert prev.depth_raw is not None and prev.depth_m is not None
    valid = prev.depth_raw > 0
    assert np.allclose(prev.depth_m[valid], prev.depth_raw[valid] / 5000.0)
    assert 0.9 < float(np.median(prev.depth_m[valid])) < 1.3  # README: medians 1.09-1.18 m
    assert 0.6 < valid.mean() < 0.9
    # Motion between the pair: 21.6 mm, 1.38 degrees (SOURCE.md).
    assert prev.T_world_camera is not None and curr.T_world_camera is not None
    rel = prev.T_world_camera.inverse() @ curr.T_world_camera
    assert abs(np.linalg.norm(rel.translation) - 0.0216) < 0.0005
    assert abs(np.degrees(rel.rotation.magnitude()) - 1.38) < 0.02
    with pytest.raises(DatasetError, match="case_1, case_2"):
        open_sequence(shared_data / "tum_fr1xyz_pairs")


def test_euroc_groundtruth_is_body_times_T_BS(shared_data: Path) -> None:
    root = shared_data / "euroc_v101_static"
    raw = open_sequence(root, rectify=False)
    assert raw.kind == "euroc" and len(raw) == 20
    cam0 = read_euroc_camera(root / "mav0" / "cam0" / "sensor.yaml")
    k = raw.intrinsics
    assert (k.fx, k.fy, k.cx, k.cy, k.width, k.height) == (458.654, 457.296, 367.215, 248.375, 752, 480)
    assert k.dist == (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
    body = read_tum(root / "groundtruth_tum.txt")
    f = next(raw.frames())
    assert f.stamp_ns == 1403715273262142976 and f.right_gray is not None
    # The nearest body pose is 2.9 us away; at rest T_WC = T_WB @ T_BS to well under a millimetre.
    j = int(np.argmin(np.abs(body.stamps_ns - f.stamp_ns)))
    expected = body.transform(j) @ cam0.T_body_camera
    assert f.T_world_camera is not None and f.T_world_camera.almost_equal(expected, 1e-4, 1e-4)
    gt = raw.groundtruth()
    assert len(gt) == len(body)
    assert gt.transform(3).almost_equal(body.transform(3) @ cam0.T_body_camera, 1e-9, 1e-9)
    # The MAV stands still: the camera moves less than 2 mm over the excerpt.
    assert np.ptp(gt.positions, axis=0).max() < 0.002


def test_euroc_rectified_stereo_is_row_aligned(shared_data: Path) -> None:
    root = shared_data / "euroc_v101_static"
    seq = open_sequence(root)
    rect = seq.rectification
    assert rect is not None and seq.intrinsics.dist == ()
    assert seq.baseline_m == pytest.approx(0.110, abs=0.002)  # EuRoC VI-sensor: ~11 cm
    f = next(seq.frames())
    assert f.right_gray is not None
    orb = cv2.ORB.create(1500) if hasattr(cv2, "ORB") else cv2.ORB_create(1500)
    kp1, d1 = orb.detectAndCompute(f.gray, None)
    kp2, d2 = orb.detectAndCompute(f.right_gray, None)
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(d1, d2)
    dy = np.array([kp1[m.queryIdx].pt[1] - kp2[m.trainIdx].pt[1] for m in matches])
    dx = np.array([kp1[m.queryIdx].pt[0] - kp2[m.trainIdx].pt[0] for m in matches])
    good = np.abs(dy) < 20
    assert good.sum() > 100
    assert float(np.median(np.abs(dy[good]))) < 1.0
    assert float(np.median(dx[good])) > 0  # left image points lie right of their right-image partners
    # Raw images are not row-aligned this well (the rectification did something).
    raw = next(open_sequence(root, rectify=False).frames())
    assert raw.right_gray is not None
    k1, e1 = orb.detectAndCompute(raw.gray, None)
    k2, e2 = orb.detectAndCompute(raw.right_gray, None)
    m2 = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(e1, e2)
    dy_raw = np.array([k1[m.queryIdx].pt[1] - k2[m.trainIdx].pt[1] for m in m2])
    assert float(np.median(np.abs(dy_raw[np.abs(dy_raw) < 20]))) > float(np.median(np.abs(dy[good])))
    # Rectified camera pose = raw camera pose rotated by R_left_rect.
    gt_rect = seq.groundtruth()
    gt_raw = open_sequence(root, rectify=False).groundtruth()
    expected = gt_raw.transform(0) @ Transform.from_matrix(
        np.block([[rect.R_left_rect, np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]])
    )
    assert gt_rect.transform(0).almost_equal(expected, 1e-9, 1e-9)


def test_missing_parts_name_what_is_missing(shared_data: Path, tmp_path: Path) -> None:
    import shutil

    root = tmp_path / "euroc"
    (root / "mav0" / "cam0").mkdir(parents=True)
    shutil.copy(shared_data / "euroc_v101_static" / "mav0" / "cam0" / "data.csv", root / "mav0" / "cam0")
    shutil.copy(shared_data / "euroc_v101_static" / "mav0" / "cam0" / "sensor.yaml", root / "mav0" / "cam0")
    with pytest.raises(DatasetError, match=r"EuRoC folder .*euroc lacks mav0/cam1/data.csv"):
        open_sequence(root)
