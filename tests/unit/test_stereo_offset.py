"""Known-answer tests of the online stereo disparity offset (``estimation.stereo_offset``)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimation.motion import make_T
from estimation.stereo import sparse_disparity
from estimation.stereo_offset import DisparityOffset
from flightkit.apps.sequences import synthetic_sequence

FX, CX, CY, B = 700.0, 600.0, 180.0, 0.5


def _observe_drive(offset_px: float, step_m: float, frames: int = 6, drift_px: float = 0.0) -> DisparityOffset:
    """A stereo camera driving forward ``step_m`` a frame past 300 points at 4-60 m, disparities
    measured ``offset_px`` short (0.1 px noise on pixels and disparities); every frame's pixels
    also move ``drift_px`` to the right that the motion does not explain (jitter)."""
    rng = np.random.default_rng(3)
    n = 300
    z = rng.uniform(4.0, 60.0, n)
    X = np.c_[rng.uniform(-0.8, 0.8, n) * z, rng.uniform(-0.2, 0.2, n) * z, z + frames * step_m]
    est = DisparityOffset(FX, FX, CX, CY, B, 0.5)
    T_step = make_T(Rotation.from_euler("y", 0.3, degrees=True).as_matrix(), np.array([0.0, 0.0, -step_m]))
    ids = np.arange(n, dtype=np.int64)
    for k in range(frames):
        uv = np.c_[FX * X[:, 0] / X[:, 2] + CX + k * drift_px, FX * X[:, 1] / X[:, 2] + CY] + rng.normal(0, 0.1, (n, 2))
        d = FX * B / X[:, 2] - offset_px + rng.normal(0, 0.1, n)
        est.observe(ids, uv, d, T_step if k else None)
        X = X @ T_step[:3, :3].T + T_step[:3, 3]
    return est


def test_a_disparity_offset_is_recovered_from_a_forward_drive() -> None:
    est = _observe_drive(0.3, 1.2)
    assert est.pairs == 5
    assert abs(est.offset_px - 0.3) < 0.05


def test_without_translation_the_offset_stays_at_its_prior() -> None:
    # Standing still: depths do not change, so the offset is not observable and stays ~0.
    est = _observe_drive(0.3, 0.0)
    assert abs(est.offset_px) < 0.05


def test_at_rest_a_common_image_motion_is_not_taken_for_an_offset() -> None:
    # At rest, 0.05 px of unexplained image motion a frame (EuRoC at rest at 320x240 shows such):
    # the pairs see no translation, are skipped, and the offset stays at 0.
    est = _observe_drive(0.3, 0.0, frames=12, drift_px=0.05)
    assert est.pairs == 0
    assert est.offset_px == 0.0
    # Creeping 1 cm a frame (|t| / B sqrt(n) = 0.35 < 0.5 px): still nothing to see the offset by.
    creep = _observe_drive(0.3, 0.01, frames=12, drift_px=0.05)
    assert creep.pairs == 0 and creep.offset_px == 0.0
    moving = _observe_drive(0.3, 1.2, frames=6, drift_px=0.05)
    assert moving.pairs == 5 and abs(moving.offset_px - 0.3) < 0.05


def test_on_a_render_with_little_image_motion_the_offset_stays_at_zero() -> None:
    # The lab render's stereo is exact (offset 0). Eight frame pairs of the rectangle pattern with
    # ~0.4 px of image motion: pixels from the true motion and depth, disparities measured by LK
    # (sparse_disparity). The earlier per-point fit found -0.088 px here; the linear fit ~0.
    seq = synthetic_sequence("rectangle", size=(320, 240), color=False)
    i = seq.intrinsics
    assert seq.baseline_m is not None
    est = DisparityOffset(i.fx, i.fy, i.cx, i.cy, seq.baseline_m, 0.5)
    flows = []
    for k in range(0, 24, 3):
        f0, f1 = seq.frame(k), seq.frame(k + 1)
        assert f0.depth_m is not None and f0.right_gray is not None and f1.right_gray is not None
        assert f0.T_world_camera is not None and f1.T_world_camera is not None
        T_1_0 = (f1.T_world_camera.inverse() @ f0.T_world_camera).as_matrix()
        uv0 = cv2.goodFeaturesToTrack(f0.gray, 300, 0.01, 7)[:, 0].round().astype(np.float64)
        z0 = f0.depth_m[uv0[:, 1].astype(int), uv0[:, 0].astype(int)].astype(np.float64)
        X1 = np.c_[(uv0[:, 0] - i.cx) / i.fx * z0, (uv0[:, 1] - i.cy) / i.fy * z0, z0] @ T_1_0[:3, :3].T + T_1_0[:3, 3]
        uv1 = np.c_[i.fx * X1[:, 0] / X1[:, 2] + i.cx, i.fy * X1[:, 1] / X1[:, 2] + i.cy]
        d0, ok0 = sparse_disparity(f0.gray, f0.right_gray, uv0.astype(np.float32))
        d1, ok1 = sparse_disparity(f1.gray, f1.right_gray, uv1.astype(np.float32))
        ok = ok0 & ok1 & (z0 > 0)
        ids = np.flatnonzero(ok).astype(np.int64)
        est.forget()
        est.observe(ids, uv0[ok], d0[ok].astype(np.float64), None)
        est.observe(ids, uv1[ok], d1[ok].astype(np.float64), T_1_0)
        flows.append(float(np.median(np.linalg.norm(uv1[ok] - uv0[ok], axis=1))))
    assert est.pairs == 8 and float(np.median(flows)) < 1.0
    assert abs(est.offset_px) < 0.02


def test_a_planar_scene_says_nothing_of_the_offset() -> None:
    # Every track at one depth (a wall, a floor seen straight on): image motion and disparity are
    # proportional for all of them, so the offset cannot be told from the translation's length; the
    # ill-conditioned pair fits are skipped instead of driving the estimate to its clip.
    rng = np.random.default_rng(5)
    n = 300
    X = np.c_[rng.uniform(-4.0, 4.0, n), rng.uniform(-1.5, 1.5, n), np.full(n, 6.0)]
    est = DisparityOffset(FX, FX, CX, CY, B, 0.5)
    T_step = make_T(np.eye(3), np.array([-0.2, 0.0, 0.0]))
    ids = np.arange(n, dtype=np.int64)
    for k in range(8):
        uv = np.c_[FX * X[:, 0] / X[:, 2] + CX, FX * X[:, 1] / X[:, 2] + CY] + rng.normal(0, 0.1, (n, 2))
        d = FX * B / X[:, 2] + rng.normal(0, 0.1, n)
        est.observe(ids, uv, d, T_step if k else None)
        X = X @ T_step[:3, :3].T + T_step[:3, 3]
    assert est.pairs == 0 and est.offset_px == 0.0


def test_a_keyframe_observation_starts_the_first_pair() -> None:
    # VisualOdometry observes a new keyframe's own disparities when no observation waits for its
    # pair (the start, or after a gap), so the first tracked frame already gives a pair.
    est = DisparityOffset(FX, FX, CX, CY, B, 0.5)
    assert est.waiting
    ids = np.arange(30, dtype=np.int64)
    uv = np.c_[np.linspace(100.0, 1100.0, 30), np.full(30, 180.0)]
    est.observe(ids, uv, np.full(30, 20.0), None)
    assert not est.waiting and est.pairs == 0
    est.forget()
    assert est.waiting


def _pair_moments_numpy(
    uv0: np.ndarray, d0: np.ndarray, uv1: np.ndarray, T: np.ndarray, offset_px: float, huber: float
) -> tuple[float, float]:
    """The pair fit written with a (2N, 6) design matrix (the reference the kernel must equal)."""
    n, fb, f = len(uv0), FX * B, np.array([FX, FX])
    R, t = T[:3, :3], T[:3, 3]
    q = np.c_[(uv0[:, 0] - CX) / FX, (uv0[:, 1] - CY) / FX, np.ones(n)] @ R.T
    m1 = np.c_[(uv1[:, 0] - CX) / FX, (uv1[:, 1] - CY) / FX]
    y = ((m1 * q[:, 2:3] - q[:, :2]) * f).T.ravel()
    X = np.zeros((2 * n, 6))
    for k in range(2):
        s, rows = f[k] / fb, slice(k * n, (k + 1) * n)
        X[rows, k], X[rows, 2], X[rows, 3 + k], X[rows, 5] = s * d0, -s * m1[:, k] * d0, s, -s * m1[:, k]
    g = q[:, 2] + t[2] * np.maximum(d0 + offset_px, 1e-3) / fb
    lever = np.concatenate([(f[k] / fb) * (t[k] - m1[:, k] * t[2]) for k in range(2)])
    w_noise = 1.0 / np.sqrt(np.tile(1.0 + g * g, 2) + lever * lever)
    w2, sigma = w_noise**2, 1.0
    for it in range(4):
        H = (X.T * w2) @ X
        theta = np.linalg.solve(H, (X.T * w2) @ y)
        if it < 3:
            a = np.abs(y - X @ theta) * w_noise
            sigma = max(1.4826 * float(np.median(a)), 1e-3)
            w2 = w_noise**2 * np.minimum(1.0, huber * sigma / np.maximum(a, 1e-12))
    cov = sigma**2 * np.linalg.inv(H)
    M = np.linalg.inv(cov[3:, 3:])
    tt, c = theta[:3], theta[3:]
    return float(tt @ M @ c - np.sum(M * cov[:3, 3:])), float(tt @ M @ tt - np.sum(M * cov[:3, :3]))


def test_the_compiled_pair_fit_equals_the_design_matrix_fit() -> None:
    from estimation._offset_kernel import offset_pair_moments

    rng = np.random.default_rng(5)
    n = 250
    z = rng.uniform(4.0, 60.0, n)
    X0 = np.c_[rng.uniform(-0.8, 0.8, n) * z, rng.uniform(-0.2, 0.2, n) * z, z]
    T = make_T(Rotation.from_euler("xyz", [0.2, 0.5, -0.1], degrees=True).as_matrix(), np.array([0.05, 0.02, -1.1]))
    X1 = X0 @ T[:3, :3].T + T[:3, 3]
    uv0 = np.c_[FX * X0[:, 0] / X0[:, 2] + CX, FX * X0[:, 1] / X0[:, 2] + CY] + rng.normal(0, 0.1, (n, 2))
    uv1 = np.c_[FX * X1[:, 0] / X1[:, 2] + CX, FX * X1[:, 1] / X1[:, 2] + CY] + rng.normal(0, 0.1, (n, 2))
    uv1[:20] += rng.normal(0, 8.0, (20, 2))  # gross outliers: the Huber reweighting has work to do
    d0 = FX * B / X0[:, 2] - 0.3 + rng.normal(0, 0.1, n)
    cam = np.array([FX, FX, CX, CY])
    num, den, ok = offset_pair_moments(uv0, d0, uv1, T[:3, :3].copy(), T[:3, 3].copy(), cam, FX * B, 0.1, 2.0)
    ref_num, ref_den = _pair_moments_numpy(uv0, d0, uv1, T, 0.1, 2.0)
    assert ok
    assert num == pytest.approx(ref_num, rel=1e-9) and den == pytest.approx(ref_den, rel=1e-9)
    assert 0.2 < num / den < 0.4  # the pair alone reads the 0.3 px offset
