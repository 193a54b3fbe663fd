"""The pose polish with each keyframe point's depth uncertainty (``VoOptions.point_uncertainty``,
``refine_pose(point_var=...)``): on a simulated stereo drive whose keyframe depths come from noisy
disparities (known noise, seeded trials) it finds the motion better than the polish that takes the
points as exact; with zero variances it is the same polish."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from estimation.camera_geometry import depth_weight, disparity_variance
from estimation.motion import make_T
from estimation.pnp import refine_pose
from flightkit.datasets.base import CameraIntrinsics
from flightkit.errors import EstimationError

INTR = CameraIntrinsics(700.0, 700.0, 600.0, 185.0, 1200, 370)
FB_PX_M = INTR.fx * 0.54  # KITTI-like rig
SIGMA_PX = 0.5  # track and disparity noise


def trial(rng: np.random.Generator, n: int = 150) -> tuple[np.ndarray, ...]:
    """Keyframe points (4-80 m, depths from disparities with SIGMA_PX noise, fused over 1-3
    measurements), their noisy pixels and disparities after a ~1 m step forward, that motion, a
    start 5 cm off it, and the points' disparity variance over one measurement's."""
    z = 1.0 / rng.uniform(1.0 / 80.0, 1.0 / 4.0, n)
    u = rng.uniform(0.0, INTR.width, n)
    v = rng.uniform(0.0, INTR.height, n)
    X_true = np.c_[(u - INTR.cx) / INTR.fx * z, (v - INTR.cy) / INTR.fy * z, z]
    n_meas = rng.integers(1, 4, n)
    d_true = FB_PX_M / z
    d_kf = d_true + rng.normal(scale=SIGMA_PX, size=n) / np.sqrt(n_meas)
    X_kf = X_true * (d_true / d_kf)[:, None]
    T = make_T(cv2.Rodrigues(rng.normal(scale=0.01, size=3))[0], np.array([0.02, 0.01, -1.0]))
    Y = X_true @ T[:3, :3].T + T[:3, 3]
    uv = np.c_[INTR.fx * Y[:, 0] / Y[:, 2] + INTR.cx, INTR.fy * Y[:, 1] / Y[:, 2] + INTR.cy]
    uv += rng.normal(scale=SIGMA_PX, size=uv.shape)
    d_cur = FB_PX_M / Y[:, 2] + rng.normal(scale=SIGMA_PX, size=n)
    d_cur[d_cur < 3.0] = np.nan  # too small to measure
    T0 = T.copy()
    T0[:3, 3] += rng.normal(scale=0.05, size=3)
    return X_kf, uv, d_cur, T, T0, 1.0 / n_meas


def test_weighted_polish_finds_the_motion_better() -> None:
    rng = np.random.default_rng(15)
    err_plain, err_weighted = [], []
    for _ in range(60):
        X_kf, uv, d_cur, T, T0, var = trial(rng)
        plain = refine_pose(T0, X_kf, uv, INTR.K, d_cur, FB_PX_M, iterations=10)
        weighted = refine_pose(T0, X_kf, uv, INTR.K, d_cur, FB_PX_M, iterations=10, point_var=var)
        err_plain.append(np.linalg.norm(plain[:3, 3] - T[:3, 3]))
        err_weighted.append(np.linalg.norm(weighted[:3, 3] - T[:3, 3]))
    rms_plain = float(np.sqrt(np.mean(np.square(err_plain))))
    rms_weighted = float(np.sqrt(np.mean(np.square(err_weighted))))
    assert rms_weighted < 0.9 * rms_plain, (rms_weighted, rms_plain)


def test_zero_variance_is_the_plain_polish() -> None:
    rng = np.random.default_rng(16)
    for _ in range(5):
        X_kf, uv, d_cur, _, T0, _ = trial(rng)
        plain = refine_pose(T0, X_kf, uv, INTR.K, d_cur, FB_PX_M)
        same = refine_pose(T0, X_kf, uv, INTR.K, d_cur, FB_PX_M, point_var=np.zeros(len(X_kf)))
        np.testing.assert_allclose(same, plain, rtol=1e-9, atol=1e-12)
        # A variance moves the result (the whitening is not a no-op).
        moved = refine_pose(T0, X_kf, uv, INTR.K, d_cur, FB_PX_M, point_var=np.ones(len(X_kf)))
        assert np.abs(moved - plain).max() > 1e-6


def test_disparity_variance_follows_fusion() -> None:
    z = np.array([2.0, 10.0, 40.0])
    w1 = depth_weight(z)
    np.testing.assert_allclose(disparity_variance(w1, z), 1.0)
    np.testing.assert_allclose(disparity_variance(3.0 * w1, z), 1.0 / 3.0)


def test_point_variances_must_match_the_points() -> None:
    X_kf, uv, d_cur, _, T0, var = trial(np.random.default_rng(17), 20)
    with pytest.raises(EstimationError, match="one variance per point"):
        refine_pose(T0, X_kf, uv, INTR.K, d_cur, FB_PX_M, point_var=var[:5])
    with pytest.raises(EstimationError, match="positive fx"):
        refine_pose(T0, X_kf, uv, INTR.K, point_var=var)
    for bad in (-1.0, np.nan):
        with pytest.raises(EstimationError, match="each >= 0"):
            refine_pose(T0, X_kf, uv, INTR.K, d_cur, FB_PX_M, point_var=np.where(np.arange(len(var)) == 3, bad, var))
