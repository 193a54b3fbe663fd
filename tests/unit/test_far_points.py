"""Stereo points beyond the depth cap (``VoOptions.far_points``): kept for the rotation, with
little or no say in the translation, on a simulated forward drive whose far depths carry the
error of a disparity offset (known answers), and on a synthetic rectified pair."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from estimation.camera_geometry import CameraGeometry
from estimation.motion import make_T
from estimation.pnp import refine_pose
from estimation.vo_options import VoOptions
from flightkit.datasets.base import CameraIntrinsics
from flightkit.errors import EstimationError

INTR = CameraIntrinsics(700.0, 700.0, 600.0, 185.0, 1200, 370)
BASELINE_M = 0.54  # KITTI-like: 60 baselines = 32.4 m, 3 px at f = 700 px = 126 m


def geometry(far_points: str) -> CameraGeometry:
    o = VoOptions(far_points=far_points).for_camera(INTR.fx, INTR.width)
    return CameraGeometry(INTR, BASELINE_M, None, o, use_depth_images=False)


def drive(offset_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keyframe points (near: 5-30 m, exact; far: 40-300 m, their depths from disparities
    ``offset_px`` too small), their exact pixels after a 1.2 m step forward with a 0.5 deg turn,
    and that motion."""
    rng = np.random.default_rng(3)
    n_near, n_far = 120, 80
    z = np.r_[rng.uniform(5.0, 30.0, n_near), rng.uniform(40.0, 300.0, n_far)]
    u = rng.uniform(50.0, INTR.width - 50.0, len(z))
    v = rng.uniform(30.0, INTR.height - 30.0, len(z))
    X_true = np.c_[(u - INTR.cx) / INTR.fx * z, (v - INTR.cy) / INTR.fy * z, z]
    T = make_T(cv2.Rodrigues(np.array([0.0, np.radians(0.5), 0.0]))[0], np.array([0.02, 0.0, -1.2]))
    Y = X_true @ T[:3, :3].T + T[:3, 3]
    uv = np.c_[INTR.fx * Y[:, 0] / Y[:, 2] + INTR.cx, INTR.fy * Y[:, 1] / Y[:, 2] + INTR.cy]
    fb = INTR.fx * BASELINE_M
    z_meas = np.where(z > 32.0, fb / (fb / z - offset_px), z)  # up to +44 % at 300 m
    return X_true * (z_meas / z)[:, None], uv, T


def polish(far_points: str, offset_px: float) -> tuple[float, float]:
    """Translation error (m) and rotation error (deg) of the polish started at the identity."""
    X, uv, T = drive(offset_px)
    tw = geometry(far_points).translation_weight(X[:, 2])
    T_est = refine_pose(np.eye(4), X, uv, INTR.K, huber_px=1e9, iterations=20, translation_weight=tw)
    dR = T_est[:3, :3] @ T[:3, :3].T
    return float(np.linalg.norm(T_est[:3, 3] - T[:3, 3])), float(np.degrees(np.linalg.norm(cv2.Rodrigues(dR)[0])))


def test_far_points_have_no_say_in_the_translation() -> None:
    # Exact data: every mode finds the motion.
    for mode in ("drop", "rotation", "weighted"):
        t_err, r_err = polish(mode, 0.0)
        assert t_err < 1e-6 and r_err < 1e-6, mode
    # Far depths from disparities 0.3 px short: with a full say ("drop" weighs every point it is
    # given alike) they bend the translation (0.42 mm); for the rotation only, the near points fix
    # it and what is left (0.15 mm) comes through the rotation (0.0008 deg), which they share.
    t_all, _ = polish("drop", 0.3)
    t_rot, r_rot = polish("rotation", 0.3)
    t_weighted, _ = polish("weighted", 0.3)
    assert t_all > 3e-4
    assert t_rot < 0.4 * t_all and r_rot < 2e-3
    assert t_weighted < 0.5 * t_all


def test_translation_weight_follows_the_depth_cap() -> None:
    z = np.array([5.0, 30.0, 64.8, 129.6])
    assert geometry("drop").translation_weight(z) is None
    z_near = geometry("rotation").near_depth_m()
    assert z_near == pytest.approx(60 * BASELINE_M)
    np.testing.assert_array_equal(geometry("rotation").translation_weight(z), [1.0, 1.0, 0.0, 0.0])
    np.testing.assert_allclose(geometry("weighted").translation_weight(z), [1.0, 1.0, 0.5, 0.25])


def test_far_points_are_kept_by_stereo_only_when_asked() -> None:
    rng = np.random.default_rng(0)
    img = cv2.resize(rng.uniform(0, 255, (100, 310)).astype(np.float32), (1240, 400), interpolation=cv2.INTER_CUBIC)
    big = np.clip(cv2.GaussianBlur(img, (0, 0), 1.0), 0, 255).astype(np.uint8)
    left = np.ascontiguousarray(big[:370, 20:1220])
    right = np.ascontiguousarray(big[:370, 22:1222])  # 2 px: 189 m, beyond the cap and the 3 px floor
    px = np.array([[x, y] for x in range(100, 1100, 50) for y in range(60, 320, 50)], np.float32)
    _, ok_drop = geometry("drop").points_3d(px, right, left, None, 2.0)
    X, ok = geometry("weighted").points_3d(px, right, left, None, 2.0)
    assert not ok_drop.any()
    assert ok.mean() > 0.9
    np.testing.assert_allclose(X[ok, 2], INTR.fx * BASELINE_M / 2.0, rtol=0.03)


def test_far_points_option_is_checked() -> None:
    with pytest.raises(EstimationError, match="far_points"):
        VoOptions(far_points="keep")
