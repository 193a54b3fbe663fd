"""Local bundle adjustment (``VoOptions.ba_window``; ``estimation.bundle``, ``estimation.local_ba``):
a perturbed keyframe pose comes back to the one its observations imply, and points only the newest
keyframe sees stay where that keyframe measured them."""

from __future__ import annotations

import cv2
import numpy as np

from estimation.bundle import bundle_adjust
from estimation.local_ba import LocalBundleWindow
from estimation.motion import invert, make_T

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
BASELINE_M = 0.1


def _pose(yaw_deg: float, t: tuple[float, float, float]) -> np.ndarray:
    return make_T(cv2.Rodrigues(np.array([0.0, np.radians(yaw_deg), 0.0]))[0], np.array(t))


def _points_world(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-2.0, 2.0, n), rng.uniform(-1.5, 1.5, n), rng.uniform(4.0, 9.0, n)]


def _observe(T_world_cam: np.ndarray, Xw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points in the camera frame and their (undistorted) pixels."""
    T_cam_world = invert(T_world_cam)
    Xc = Xw @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    uv = (Xc[:, :2] / Xc[:, 2:3]) * K[0, 0] + K[:2, 2]
    return Xc, uv


def _error(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (deg) between two poses."""
    d = invert(T_a) @ T_b
    return float(np.linalg.norm(d[:3, 3])), float(np.degrees(np.linalg.norm(cv2.Rodrigues(d[:3, :3])[0])))


def test_bundle_adjust_brings_perturbed_cameras_back() -> None:
    Xw = _points_world(80, 1)
    truth = [_pose(0.0, (0.0, 0.0, 0.0)), _pose(2.0, (0.3, 0.0, 0.5)), _pose(4.0, (0.6, 0.05, 1.0))]
    cams, pts, uvs, disps = [], [], [], []
    for c, T in enumerate(truth):
        Xc, uv = _observe(T, Xw)
        cams.append(np.full(len(Xw), c))
        pts.append(np.arange(len(Xw)))
        uvs.append(uv)
        disps.append(K[0, 0] * BASELINE_M / Xc[:, 2])
    off = [_pose(0.0, (0.0, 0.0, 0.0)), _pose(0.5, (0.03, -0.02, 0.05)), _pose(-0.4, (-0.04, 0.02, 0.06))]
    start = np.stack([T @ d for T, d in zip(truth, off, strict=True)])
    res = bundle_adjust(
        start,
        Xw + 0.05,
        np.concatenate(cams),
        np.concatenate(pts),
        np.concatenate(uvs),
        K,
        disparity_px=np.concatenate(disps),
        baseline_m=BASELINE_M,
    )
    assert res is not None
    poses, _ = res
    np.testing.assert_array_equal(poses[0], truth[0])  # the gauge: the first camera is held
    for c in (1, 2):
        assert _error(start[c], truth[c])[0] > 0.05
        dt_m, dr_deg = _error(poses[c], truth[c])
        assert dt_m < 2e-3 and dr_deg < 0.02


def test_window_moves_the_newest_keyframe_and_keeps_its_own_new_points() -> None:
    """Two keyframes share 60 points; the newest also has 20 of its own. Its pose (perturbed by 4 cm)
    comes back, and its own points are returned where it measured them (camera frame)."""
    shared, own = _points_world(60, 2), _points_world(20, 3)
    T1, T2 = _pose(0.0, (0.0, 0.0, 0.0)), _pose(1.5, (0.2, 0.0, 0.6))
    window = LocalBundleWindow(3, K, K[0, 0], BASELINE_M)
    X1, uv1 = _observe(T1, shared)
    window.add_keyframe(T1, np.arange(60), uv1, X1)
    X2, uv2 = _observe(T2, np.r_[shared, own])
    ids2 = np.r_[np.arange(60), 100 + np.arange(20)]
    T2_est = T2 @ _pose(0.3, (0.03, -0.01, 0.02))
    window.add_keyframe(T2_est, ids2, uv2, X2)
    out = window.run(ids2, X2, min_depth_m=0.2)
    assert out is not None
    T2_ba, X2_ba = out
    assert _error(T2_est, T2)[0] > 0.03
    dt_m, dr_deg = _error(T2_ba, T2)
    assert dt_m < 2e-3 and dr_deg < 0.02
    np.testing.assert_allclose(X2_ba[60:], X2[60:])  # its own points, unmoved in its frame
    np.testing.assert_allclose(X2_ba[:60], X2[:60], atol=2e-3)  # the shared ones, refined
