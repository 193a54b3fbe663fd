"""The compiled essential-matrix loop (estimation._essential_kernel) against the numpy loop it
replaced.

``_refine_essential_reference`` and ``_essential_from_prior_reference`` are that numpy code,
kept here (not in the package): Sampson residuals and Jacobian from the compiled kernels,
``J^T W J`` by BLAS, ``cv2.solve`` (Cholesky) and ``cv2.Rodrigues``. The compiled loop sums the
normal equations point by point and solves with OpenCV's Cholesky algorithm of its own, so the
two agree to rounding (~1e-12 relative), compared here at 1e-9.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimation import _essential_kernel, _kernels
from estimation.essential import _metric_scale_rays, essential_from_prior, refine_essential
from estimation.motion import Motion, make_T, median

F, CX, CY = 525.0, 319.5, 239.5
K = np.array([[F, 0.0, CX], [0.0, F + 0.5, CY], [0.0, 0.0, 1.0]])


def _sampson(R: np.ndarray, t: np.ndarray, x0: np.ndarray, x1: np.ndarray, f: float, signed: bool) -> np.ndarray:
    d: np.ndarray = _kernels.sampson_distance(
        np.ascontiguousarray(R), np.ascontiguousarray(t).reshape(3), x0, x1, float(f), signed
    )
    return d


def _unit_cross(a: np.ndarray | tuple[float, float, float], b: np.ndarray) -> np.ndarray:
    (a0, a1, a2), (b0, b1, b2) = np.asarray(a).tolist(), np.asarray(b).tolist()
    c = np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])
    return np.asarray(c / math.sqrt(float(c @ c)))


def _huber_cost(r: np.ndarray, huber: float) -> float:
    a = np.abs(r)
    m = np.minimum(a, huber)
    return 0.5 * float(m @ (a + a - m))


def _refine_essential_reference(  # noqa: PLR0913
    R: np.ndarray, t: np.ndarray, x_ref: np.ndarray, x_cur: np.ndarray, f_px: float, huber_px: float, iterations: int
) -> tuple[np.ndarray, np.ndarray]:
    """``estimation.essential.refine_essential`` as numpy wrote it (before the compiled loop)."""
    R = np.array(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(3)
    t = t / np.linalg.norm(t)
    if len(x_ref) < 5:
        return R, t

    def jac(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        J = np.empty((len(x_ref), 6))
        r = _kernels.sampson_jacobian(np.ascontiguousarray(R), np.ascontiguousarray(t), x_ref, x_cur, f_px, J)
        return r, J

    r, J6 = jac(R, t)
    cost = _huber_cost(r, huber_px)
    lam = 0.0
    B = np.empty((3, 2))
    for it in range(iterations):
        if it:
            r, J6 = jac(R, t)
        b1 = _unit_cross(t, (1.0, 0.0, 0.0) if abs(t[0]) < 0.9 else (0.0, 1.0, 0.0))
        B[:, 0] = b1
        B[:, 1] = _unit_cross(t, b1)
        J = np.empty((len(r), 5))
        J[:, :3] = J6[:, :3]
        J[:, 3:] = J6[:, 3:] @ B
        w = huber_px / np.maximum(np.abs(r), huber_px)
        Jw = J * w[:, None]
        H = Jw.T @ J
        g = (Jw.T @ r).reshape(5, 1)
        accepted = False
        for _ in range(4):
            A = H
            if lam > 0:
                A = H.copy()
                A.flat[::6] *= 1.0 + lam
            ok, sol = cv2.solve(A, g, flags=cv2.DECOMP_CHOLESKY)
            if not ok:
                break
            dx = -sol.ravel()
            R_n = cv2.Rodrigues(dx[:3])[0] @ R
            t_n = t + B @ dx[3:]
            t_n /= np.linalg.norm(t_n)
            cost_n = _huber_cost(_sampson(R_n, t_n, x_ref, x_cur, f_px, True), huber_px)
            if cost_n < cost:
                gain = cost - cost_n
                R, t, cost = R_n, t_n, cost_n
                lam *= 0.1
                accepted = True
                break
            lam = max(10.0 * lam, 1e-3)
        if not accepted or gain < 1e-4 * cost:
            break
    return R, t


def _metric_scale_rays_reference(
    R: np.ndarray, t: np.ndarray, xu: np.ndarray, xv: np.ndarray, X: np.ndarray
) -> float | None:
    """``estimation.essential._metric_scale_rays`` as numpy wrote it, on the valid points only."""
    if len(X) < 3:
        return None
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R.tolist()
    t0, t1, t2 = t.tolist()
    X0, X1, X2 = X[:, 0], X[:, 1], X[:, 2]
    y0 = r00 * X0 + r01 * X1 + r02 * X2
    y1 = r10 * X0 + r11 * X1 + r12 * X2
    y2 = r20 * X0 + r21 * X1 + r22 * X2
    a0, a1, a2 = xv * y2 - y1, y0 - xu * y2, xu * y1 - xv * y0
    b0, b1, b2 = xv * t2 - t1, t0 - xu * t2, xu * t1 - xv * t0
    bb = b0 * b0 + b1 * b1 + b2 * b2
    good = bb > 1e-12
    if np.count_nonzero(good) < 3:
        return None
    bb = bb[good]
    s_all = -(a0 * b0 + a1 * b1 + a2 * b2)[good] / bb
    s_med = median(s_all)
    dev = np.abs(s_all - s_med)
    near = dev < 3.0 * 1.4826 * (median(dev) + 1e-9)
    w = bb[near]
    wsum = float(w.sum())
    s = float(s_all[near] @ w) / wsum if wsum > 0 else s_med
    return s if math.isfinite(s) else None


def _essential_from_prior_reference(  # noqa: PLR0913
    p0: np.ndarray,
    p1: np.ndarray,
    X: np.ndarray,
    T_guess: np.ndarray,
    gate_px: float,
    threshold_px: float,
    min_fraction: float,
    min_inliers: int,
    iterations: int,
) -> Motion | None:
    """``estimation.essential.essential_from_prior`` as numpy wrote it (before the compiled loop)."""
    n = len(p0)
    need = max(min_inliers, 8, min_fraction * n)
    t_g = T_guess[:3, 3]
    if n < need or float(t_g @ t_g) < 1e-12:
        return None
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    f = 0.5 * (fx + fy)
    x0 = np.ones((n, 3))
    x0[:, 0] = (p0[:, 0] - cx) / fx
    x0[:, 1] = (p0[:, 1] - cy) / fy
    x1 = np.ones((n, 3))
    x1[:, 0] = (p1[:, 0] - cx) / fx
    x1[:, 1] = (p1[:, 1] - cy) / fy
    R, t = T_guess[:3, :3], t_g
    gate = _sampson(R, t, x0, x1, f, False) < gate_px
    if np.count_nonzero(gate) < need:
        return None
    R, t = _refine_essential_reference(R, t, x0[gate], x1[gate], f, threshold_px, iterations)
    mask = _sampson(R, t, x0, x1, f, False) < threshold_px
    if np.count_nonzero(mask) < need:
        return None
    valid = mask & np.isfinite(X).all(axis=1) & (X[:, 2] > 0)
    s = _metric_scale_rays_reference(R, t, x1[valid, 0], x1[valid, 1], X[valid])
    if s is None:
        return None
    return Motion(make_T(R, s * t), mask, True)


def _scene(
    rng: np.random.Generator, n: int, baseline_m: float, noise_px: float, outliers: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points 0.8-4 m ahead seen from the reference and a camera moved by a small motion: their
    pixels (noisy, a share ``outliers`` moved by 5-40 px), the points and the motion."""
    X = np.c_[rng.uniform(-1.5, 1.5, (n, 2)), rng.uniform(0.8, 4.0, n)]
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(scale=0.02, size=3)).as_matrix()
    d = rng.normal(size=3)
    T[:3, 3] = baseline_m * d / np.linalg.norm(d)

    def project(T: np.ndarray) -> np.ndarray:
        Xc = X @ T[:3, :3].T + T[:3, 3]
        uv = np.c_[K[0, 0] * Xc[:, 0] / Xc[:, 2] + CX, K[1, 1] * Xc[:, 1] / Xc[:, 2] + CY]
        return np.asarray(uv + rng.normal(scale=noise_px, size=uv.shape))

    p0, p1 = project(np.eye(4)), project(T)
    bad = rng.random(n) < outliers
    p1[bad] += rng.uniform(5.0, 40.0, (int(bad.sum()), 2)) * rng.choice([-1.0, 1.0], (int(bad.sum()), 2))
    return p0, p1, X, T


def _rays(p: np.ndarray) -> np.ndarray:
    return np.c_[(p[:, 0] - CX) / K[0, 0], (p[:, 1] - CY) / K[1, 1], np.ones(len(p))]


def _start(rng: np.random.Generator, T: np.ndarray, rot_deg: float, t_m: float) -> tuple[np.ndarray, np.ndarray]:
    dR = Rotation.from_rotvec(np.radians(rot_deg) * rng.normal(size=3)).as_matrix()
    return dR @ T[:3, :3], T[:3, 3] + rng.normal(scale=t_m, size=3)


@pytest.mark.parametrize("n", [5, 6, 12, 60, 200, 457])
@pytest.mark.parametrize("huber", [1.0, 1e9])
@pytest.mark.parametrize("iterations", [1, 5, 30])
def test_essential_lm_equals_numpy_loop(n: int, huber: float, iterations: int) -> None:
    rng = np.random.default_rng(1000 + n)
    for trial in range(8):
        p0, p1, _, T = _scene(rng, n, [0.005, 0.02, 0.1][trial % 3], 0.5, [0.0, 0.2][trial % 2])
        x0, x1 = _rays(p0), _rays(p1)
        R0, t0 = _start(rng, T, 0.3, 0.005)
        R_ref, t_ref = _refine_essential_reference(R0, t0, x0, x1, F, huber, iterations)
        R, t = refine_essential(R0, t0, x0, x1, F, huber_px=huber, iterations=iterations)
        assert np.allclose(R, R_ref, rtol=1e-9, atol=1e-9)
        assert np.allclose(t, t_ref, rtol=1e-9, atol=1e-9)
        assert abs(float(np.linalg.norm(t)) - 1.0) < 1e-12


def test_essential_lm_returns_the_start_without_enough_matches_or_a_solvable_system() -> None:
    rng = np.random.default_rng(7)
    p0, p1, _, T = _scene(rng, 40, 0.02, 0.5, 0.0)
    x0, x1 = _rays(p0), _rays(p1)
    t_start = 3.0 * T[:3, 3]
    for m in (0, 1, 4):  # fewer than 5 matches: the start, t normalised
        R, t = refine_essential(T[:3, :3], t_start, x0[:m], x1[:m], F)
        assert np.array_equal(R, T[:3, :3]) and np.allclose(t, T[:3, 3] / np.linalg.norm(T[:3, 3]), rtol=1e-15)
    # One match repeated: the normal equations are singular (rank 1), Cholesky refuses, no step.
    x0s, x1s = np.repeat(x0[:1], 10, axis=0), np.repeat(x1[:1], 10, axis=0)
    R, t = refine_essential(T[:3, :3], t_start, x0s, x1s, F)
    R_ref, t_ref = _refine_essential_reference(T[:3, :3], t_start, x0s, x1s, F, 1.0, 5)
    assert np.array_equal(R, T[:3, :3]) and np.allclose(R, R_ref, rtol=1e-12, atol=1e-12)
    assert np.allclose(t, t_ref, rtol=1e-12, atol=1e-12)


def test_cholesky_solve_is_cv2_solves() -> None:
    rng = np.random.default_rng(11)
    for trial in range(200):
        M = rng.normal(size=(8, 5)) * rng.uniform(0.1, 1e3, 5)
        A = M.T @ M if trial % 4 else M.T @ M - np.eye(5) * rng.uniform(0.0, 1e4)  # some not PD
        A = 0.5 * (A + A.T)
        b = rng.normal(size=5)
        ok_ref, x_ref = cv2.solve(A, b.reshape(5, 1), flags=cv2.DECOMP_CHOLESKY)
        A_k, x = A.copy(), b.copy()
        ok = _essential_kernel._cholesky_solve(A_k, x)
        assert ok == bool(ok_ref)
        if ok:
            assert np.allclose(x, x_ref.ravel(), rtol=1e-9, atol=1e-12 * np.abs(x_ref).max())


@pytest.mark.parametrize("n", [12, 40, 200, 457])
def test_essential_from_prior_equals_numpy(n: int) -> None:
    rng = np.random.default_rng(2000 + n)
    declined = 0
    for trial in range(12):
        p0, p1, X, T = _scene(rng, n, [0.005, 0.02, 0.1][trial % 3], 0.4, [0.0, 0.05, 0.3][trial % 3])
        X[rng.random(n) < 0.1, 2] = np.nan  # some points without depth
        R0, t0 = _start(rng, T, 0.2, 0.003)
        guess = make_T(R0, t0)
        args = (2.0, 1.0, [0.9, 0.5][trial % 2], 12, 5)
        m_ref = _essential_from_prior_reference(p0, p1, X, guess, *args)
        m = essential_from_prior(p0, p1, K, X, guess, *args)
        assert (m is None) == (m_ref is None)
        if m is None or m_ref is None:
            declined += 1
            continue
        assert np.array_equal(m.inliers, m_ref.inliers)
        assert np.allclose(m.T_cur_ref, m_ref.T_cur_ref, rtol=1e-9, atol=1e-9)
    assert declined < 12  # the prediction explained some of them


@pytest.mark.parametrize("n", [0, 2, 3, 4, 7, 8, 60, 201, 457])
def test_metric_scale_equals_numpy_bit_for_bit(n: int) -> None:
    rng = np.random.default_rng(3000 + n)
    for trial in range(20):
        p0, p1, X, T = _scene(rng, n, [0.005, 0.02, 0.1][trial % 3], 0.4, 0.2)
        X = X * rng.uniform(0.9, 1.1, (n, 1))  # depth noise
        X[rng.random(n) < 0.1, rng.integers(0, 3)] = [np.nan, np.inf, -1.0][trial % 3]
        mask = rng.random(n) < [1.0, 0.8, 0.1][trial % 3]
        R = T[:3, :3]
        t = T[:3, 3] / np.linalg.norm(T[:3, 3]) * [1.0, -1.0][trial % 2]
        x1 = _rays(p1)
        valid = mask & np.isfinite(X).all(axis=1) & (X[:, 2] > 0)
        s_ref = _metric_scale_rays_reference(R, t, x1[valid, 0], x1[valid, 1], X[valid])
        s = _metric_scale_rays(R, t, x1, X, mask)
        assert s == s_ref  # both None, or the same float
        if n >= 60 and trial % 3 == 0:
            assert s is not None and abs(abs(s) - np.linalg.norm(T[:3, 3])) < 0.2 * np.linalg.norm(T[:3, 3])
