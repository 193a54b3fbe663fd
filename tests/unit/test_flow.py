"""Optical-flow velocity: the interaction matrix, the 3-point RANSAC (exact twist without
noise, 50 % outliers rejected, reweighted refits), integration to a pose, KLT with the forward-backward check,
and the stereo altitude."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from estimation.flow import (
    integrate_velocity,
    interaction_matrix,
    polish_motion,
    stereo_altitude_m,
    track_klt,
    velocity_lstsq,
    velocity_ransac,
)
from estimation.motion import invert, rotation_angle_rad

TWIST = np.array([0.4, -0.2, 0.6, 0.05, -0.1, 0.2])  # m/s, rad/s (camera frame)


def points(n: int, seed: int = 0, flat_z: float | None = None) -> np.ndarray:
    rng = np.random.default_rng(seed)
    z = np.full(n, flat_z) if flat_z else rng.uniform(1.0, 5.0, n)
    x = rng.uniform(-0.6, 0.6, n)
    y = rng.uniform(-0.45, 0.45, n)
    return np.c_[x * z, y * z, z]


def observe(X_prev: np.ndarray, twist: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Normalised coordinates of static points before and after the camera moved."""
    T_prev_cur = integrate_velocity(twist, dt)
    T_cur_prev = invert(T_prev_cur)
    X_cur = X_prev @ T_cur_prev[:3, :3].T + T_cur_prev[:3, 3]
    return X_prev[:, :2] / X_prev[:, 2:], X_cur[:, :2] / X_cur[:, 2:]


def test_interaction_matrix_matches_the_point_velocity() -> None:
    X = points(20, 1)
    v, w = TWIST[:3], TWIST[3:]
    Xdot = -v - np.cross(w, X)  # a static point seen from a moving camera
    x, y, Z = X[:, 0] / X[:, 2], X[:, 1] / X[:, 2], X[:, 2]
    expected = np.c_[(Xdot[:, 0] - x * Xdot[:, 2]) / Z, (Xdot[:, 1] - y * Xdot[:, 2]) / Z]
    L = interaction_matrix(x, y, Z)
    np.testing.assert_allclose(np.einsum("nij,j->ni", L, TWIST), expected, atol=1e-12)
    np.testing.assert_allclose(velocity_lstsq(L, expected), TWIST, atol=1e-10)


def test_velocity_ransac_exact_for_small_steps() -> None:
    X = points(100, 2)
    dt = 1e-4
    x0, x1 = observe(X, TWIST, dt)
    twist, inl = velocity_ransac(x0, x1, X[:, 2], dt, threshold=0.01)
    assert inl.all()
    np.testing.assert_allclose(twist, TWIST, atol=2e-4)


def test_polish_makes_a_multi_frame_velocity_exact() -> None:
    # Ten frames at 15 Hz of a brisk motion: the first-order (interaction-matrix) velocity is
    # visibly off over the interval, its reprojection polish is exact.
    X = points(150, 4)
    dt = 10 / 15
    x0, x1 = observe(X, TWIST, dt)
    T_true = integrate_velocity(TWIST, dt)
    twist, inl = velocity_ransac(x0, x1, X[:, 2], dt, threshold=1.0)
    T_first_order = integrate_velocity(twist, dt)
    first_order_err_m = float(np.linalg.norm(T_first_order[:3, 3] - T_true[:3, 3]))
    assert first_order_err_m > 1e-3
    T = polish_motion(T_first_order, x0[inl], X[inl, 2], x1[inl], huber=1e-3)
    np.testing.assert_allclose(T, T_true, atol=1e-9)
    # Fewer than four points: returned as given.
    np.testing.assert_allclose(polish_motion(T_first_order, x0[:3], X[:3, 2], x1[:3], 1e-3), T_first_order, atol=1e-12)


def test_velocity_ransac_rejects_half_outliers_at_frame_rate() -> None:
    rng = np.random.default_rng(4)
    X = points(200, 3)
    dt = 1 / 30
    x0, x1 = observe(X, TWIST, dt)
    x1 = x1 + rng.normal(0, 0.3 / 500, x1.shape)  # 0.3 px noise at f = 500
    bad = rng.permutation(200)[:100]
    x1[bad] += rng.uniform(-0.05, 0.05, (100, 2))  # up to 25 px wrong
    thr = 1.5 / 500 / dt
    twist, inl = velocity_ransac(x0, x1, X[:, 2], dt, threshold=thr, max_iters=300)
    assert inl[bad].sum() <= 3
    assert inl[np.setdiff1d(np.arange(200), bad)].mean() > 0.9
    np.testing.assert_allclose(twist[:3], TWIST[:3], atol=0.05)
    np.testing.assert_allclose(twist[3:], TWIST[3:], atol=0.02)
    # The same data without RANSAC is far off: outliers really were the problem.
    L = interaction_matrix(*(0.5 * (x0 + x1)).T, X[:, 2])
    plain = velocity_lstsq(L, (x1 - x0) / dt)
    assert np.abs(plain - TWIST).max() > 0.1


def test_robust_refits_discount_tracks_that_disagree_within_the_threshold() -> None:
    # 0.2 px noise on every track, and a quarter of them off by 1.0-1.4 px in one direction
    # (drifted tracks that stay inside the 1.5 px threshold): every least-squares inlier counts
    # fully and the twist follows them; the reweighted refits count them less (~27 % lower
    # error over these five draws).
    dt = 1 / 30
    f = 500.0
    errs = {0: [], 3: []}
    for seed in range(5):
        rng = np.random.default_rng(10 + seed)
        X = points(200, 20 + seed)
        x0, x1 = observe(X, TWIST, dt)
        x1 = x1 + rng.normal(0, 0.2 / f, x1.shape)
        drift = rng.permutation(200)[:50]
        x1[drift, 0] += rng.uniform(1.0, 1.4, 50) / f
        for k in errs:
            twist, inl = velocity_ransac(x0, x1, X[:, 2], dt, threshold=1.5 / f / dt, robust_iters=k)
            assert inl.mean() > 0.9
            errs[k].append(np.linalg.norm(twist - TWIST))
    assert np.mean(errs[3]) < 0.8 * np.mean(errs[0])


def test_robust_refits_keep_an_exact_twist_exact() -> None:
    X = points(100, 2)
    dt = 1e-4
    x0, x1 = observe(X, TWIST, dt)
    twist, inl = velocity_ransac(x0, x1, X[:, 2], dt, threshold=0.01, robust_iters=3)
    assert inl.all()
    np.testing.assert_allclose(twist, TWIST, atol=2e-4)


def test_velocity_with_a_single_altitude_over_flat_ground() -> None:
    X = points(80, 5, flat_z=2.0)
    dt = 1 / 50
    x0, x1 = observe(X, TWIST, dt)
    twist, inl = velocity_ransac(x0, x1, 2.0, dt, threshold=0.5 / 400 / dt)
    assert inl.mean() > 0.95
    np.testing.assert_allclose(twist, TWIST, atol=0.02)


def test_integrate_velocity_moves_and_turns_as_commanded() -> None:
    T = integrate_velocity(TWIST, 0.5)
    assert rotation_angle_rad(T[:3, :3]) == pytest.approx(np.linalg.norm(TWIST[3:]) * 0.5)
    assert np.linalg.norm(T[:3, 3]) == pytest.approx(np.linalg.norm(TWIST[:3]) * 0.5)
    np.testing.assert_allclose(integrate_velocity(np.zeros(6), 1.0), np.eye(4))


def texture(h: int = 240, w: int = 320, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = cv2.resize(
        rng.uniform(0, 255, (h // 4, w // 4)).astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC
    )
    return np.clip(img, 0, 255).astype(np.uint8)


def shifted_scene(seed: int, dx_px: int, dy_px: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two 320x240 views of one texture, the content moved by (dx, dy) px, with a flat,
    featureless strip (x < 80) in the second where points cannot be tracked; and a 20 px grid
    of points in the first."""
    big = texture(300, 400, seed=seed)
    prev = np.ascontiguousarray(big[20:260, 20:340])
    cur = np.ascontiguousarray(big[20 - dy_px : 260 - dy_px, 20 - dx_px : 340 - dx_px])
    cur[:, :80] = 128
    grid = (
        np.stack(np.meshgrid(np.arange(20, 300, 20), np.arange(20, 220, 20)), -1)
        .reshape(-1, 2)
        .astype(np.float32)
    )
    return prev, cur, grid


def test_klt_tracks_a_shift_and_the_fb_check_drops_lost_points() -> None:
    prev, cur, grid = shifted_scene(0, 5, -3)
    pts, ok = track_klt(prev, cur, grid, fb_max_px=0.5, win_px=15, levels=3)
    moved = pts - grid
    inside = grid[:, 0] > 110
    assert ok[inside].mean() > 0.95
    np.testing.assert_allclose(
        moved[ok & inside], np.broadcast_to([5.0, -3.0], moved[ok & inside].shape), atol=0.1
    )
    assert ok[grid[:, 0] < 60].mean() < 0.1


@pytest.mark.parametrize("back_levels", [0, 1, 3])
def test_klt_backward_check_with_fewer_levels_still_drops_lost_points(back_levels: int) -> None:
    """The backward pass starts at the old position, so a shallow pyramid confirms good tracks,
    and points whose patch vanished (a flat strip) still fail to come back."""
    prev, cur, grid = shifted_scene(3, 9, -6)
    pts, ok = track_klt(prev, cur, grid, fb_max_px=0.5, win_px=9, levels=3, back_levels=back_levels, max_iters=10)
    inside = grid[:, 0] > 110
    assert ok[inside].mean() > 0.95
    moved = (pts - grid)[ok & inside]
    np.testing.assert_allclose(moved, np.broadcast_to([9.0, -6.0], moved.shape), atol=0.1)
    assert ok[grid[:, 0] < 60].mean() < 0.1


def test_klt_trusting_the_guess_checks_only_tracks_that_land_away_from_it() -> None:
    """With ``trust_guess_px``, tracks that end at their guess are kept without the backward
    pass; a track that ends away from its (wrong) guess is still checked, and one that cannot
    be tracked (its patch is gone) still fails."""
    prev, cur, grid = shifted_scene(5, 9, -6)
    guess = grid + np.float32([9.0, -6.0])
    wrong = np.zeros(len(grid), dtype=bool)
    wrong[::7] = True
    guess[wrong] += np.float32([4.0, 3.0])  # these tracks start 5 px off and must be checked
    full_pts, full_ok = track_klt(prev, cur, grid, 0.5, 9, 3, guess=guess, back_levels=1, max_iters=10)
    pts, ok = track_klt(
        prev, cur, grid, 0.5, 9, 3, guess=guess, back_levels=1, max_iters=10, trust_guess_px=1.0
    )
    inside = grid[:, 0] > 110
    np.testing.assert_array_equal(pts, full_pts)  # the forward pass is the same
    assert ok[inside].mean() > 0.95
    moved = (pts - grid)[ok & inside]
    np.testing.assert_allclose(moved, np.broadcast_to([9.0, -6.0], moved.shape), atol=0.1)
    # Inside the textured part the answers agree with the full check, wrong guesses included.
    np.testing.assert_array_equal(ok[inside], full_ok[inside])
    assert ok[inside & wrong].all()
    assert ok[grid[:, 0] < 60].mean() < 0.1


def test_stereo_altitude_from_row_consistent_orb_matches() -> None:
    big = texture(240, 400, seed=9)
    d = 16
    left, right = np.ascontiguousarray(big[:, 40:360]), np.ascontiguousarray(big[:, 40 + d : 360 + d])
    z, n = stereo_altitude_m(left, right, fx_px=300.0, baseline_m=0.1)
    assert n >= 10
    assert z == pytest.approx(300.0 * 0.1 / d, rel=0.02)
    z_none, _ = stereo_altitude_m(left, np.zeros_like(right), 300.0, 0.1)
    assert np.isnan(z_none)
