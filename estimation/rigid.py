"""3D-3D motion: Kabsch/Umeyama in a vectorised 3-point RANSAC, from a prediction without
RANSAC, and rigidity inliers (the largest set of points whose mutual distances are preserved).

Functions:
    ransac_rigid(src, dst, threshold_m, ...) -> Motion vectorised 3-point RANSAC + refit
    rigid_from_prior(src, dst, T_prior, ...) -> Motion  no RANSAC when a prediction explains the pairs
    rigidity_inliers(P, Q, tol_m) -> mask              max-clique of distance-preserving pairs
    umeyama(src, dst, with_scale) -> (R, t, s)        least squares, closed form (SVD); from estimation.evaluation
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
from numba import njit

from estimation.evaluation import umeyama
from estimation.motion import Motion, failed_motion, make_T, ransac_iterations
from flightkit.errors import EstimationError

__all__ = ["ransac_rigid", "rigid_from_prior", "rigidity_inliers", "umeyama"]

F64 = npt.NDArray[np.float64]
Mask = npt.NDArray[np.bool_]


def _batch_kabsch(P: F64, Q: F64) -> tuple[F64, F64]:
    """Kabsch for a batch of point sets: P, Q (K, M, 3) -> R (K, 3, 3), t (K, 3)."""
    mp = P.mean(axis=1)
    mq = Q.mean(axis=1)
    H = np.einsum("kmi,kmj->kij", P - mp[:, None], Q - mq[:, None])
    U, _, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, 1, 2)
    d = np.sign(np.linalg.det(V @ np.swapaxes(U, 1, 2)))
    d[d == 0] = 1.0
    V[:, :, 2] *= d[:, None]
    R = V @ np.swapaxes(U, 1, 2)
    t = mq - np.einsum("kij,kj->ki", R, mp)
    return R, t


def ransac_rigid(
    src: npt.ArrayLike,
    dst: npt.ArrayLike,
    threshold_m: float = 0.05,
    max_iters: int = 256,
    confidence: float = 0.999,
    min_inliers: int = 6,
    rng: np.random.Generator | None = None,
    batch: int = 64,
    first_batch: int | None = None,
) -> Motion:
    """Rigid ``dst ~ R @ src + t`` that tolerates outliers: vectorised 3-point RANSAC.

    Hypotheses are drawn ``batch`` at a time and scored together with numpy (one batched
    SVD, one residual tensor); the draw count adapts to the best inlier ratio seen. The
    winner is re-fitted by Kabsch on its inliers twice (re-selecting inliers each time).

    Args:
        src, dst: (N, 3) corresponding points (reference frame, current frame), metres.
        threshold_m: a point is an inlier when ``|R src + t - dst| < threshold_m``.
        max_iters: cap on hypotheses.
        confidence: stop when an all-inlier sample was drawn with this probability.
        min_inliers: fewer inliers than this gives ``ok=False``.
        rng: random generator (seeded default for repeatable runs).
        batch: hypotheses scored per numpy pass.
        first_batch: hypotheses of the first pass (None: ``batch``). With mostly inliers a
            few draws reach the confidence, so a small first batch saves the rest.

    Returns:
        :class:`Motion` with ``T_cur_ref`` mapping src into dst. Returns immediately.
    """
    P = np.asarray(src, dtype=np.float64)
    Q = np.asarray(dst, dtype=np.float64)
    n = len(P)
    if P.shape != Q.shape or (n and P.shape[1] != 3):
        raise EstimationError(f"ransac_rigid needs two (N, 3) arrays, got {P.shape} and {Q.shape}")
    if n < max(3, min_inliers):
        return failed_motion(n)
    rng = rng if rng is not None else np.random.default_rng(0)
    thr2 = threshold_m * threshold_m
    best_count, best_mask = -1, np.zeros(n, dtype=bool)
    needed, drawn = max_iters, 0
    while drawn < needed:
        k = min(batch if drawn or first_batch is None else max(1, first_batch), needed - drawn)
        # Three distinct indices per hypothesis.
        idx = np.empty((k, 3), dtype=np.intp)
        idx[:, 0] = rng.integers(0, n, k)
        idx[:, 1] = (idx[:, 0] + rng.integers(1, n, k)) % n
        third = rng.integers(0, n - 2, k)
        lo = np.minimum(idx[:, 0], idx[:, 1])
        hi = np.maximum(idx[:, 0], idx[:, 1])
        third = third + (third >= lo)
        third = third + (third >= hi)
        idx[:, 2] = third
        R, t = _batch_kabsch(P[idx], Q[idx])
        # Residuals of every point under every hypothesis, (k, n, 3), and their squared
        # norms, spelled out as broadcast products (10x cheaper than the same einsums, which
        # sum in another order: the masks can differ only within 1e-14 of the threshold).
        res = R[:, None, :, 0] * P[None, :, 0, None]
        res += R[:, None, :, 1] * P[None, :, 1, None]
        res += R[:, None, :, 2] * P[None, :, 2, None]
        res += t[:, None, :]
        res -= Q
        d2 = res[..., 0] * res[..., 0]
        d2 += res[..., 1] * res[..., 1]
        d2 += res[..., 2] * res[..., 2]
        inl = d2 < thr2
        counts = inl.sum(axis=1)
        j = int(np.argmax(counts))
        if counts[j] > best_count:
            best_count, best_mask = int(counts[j]), inl[j]
            needed = ransac_iterations(best_count / n, 3, confidence, max_iters)
        drawn += k
    if best_count < 3:
        return failed_motion(n)
    fit = _refit_rigid(P, Q, best_mask, thr2, 3)
    if fit is None:
        return failed_motion(n)
    R_b, t_b, mask = fit
    ok = int(np.count_nonzero(mask)) >= min_inliers
    return Motion(make_T(R_b, t_b), mask, ok)


def _refit_rigid(P: F64, Q: F64, mask: Mask, thr2: float, min_count: float) -> tuple[F64, F64, Mask] | None:
    """Kabsch on the inliers, then the points within the threshold (squared, ``thr2``) as the new
    inliers, up to three times or until they stop changing; None when fewer than ``min_count``
    are left to fit. Shared by :func:`ransac_rigid` and :func:`rigid_from_prior` (one compiled
    pass: numpy's per-call costs were 0.2 ms of a 150-point refit)."""
    ok, R_b, t_b, mask = _refit_kernel(
        np.ascontiguousarray(P, dtype=np.float64),
        np.ascontiguousarray(Q, dtype=np.float64),
        np.ascontiguousarray(mask, dtype=np.bool_),
        float(thr2),
        float(min_count),
    )
    return (R_b, t_b, mask) if ok else None


@njit(cache=True)
def _refit_kernel(P: Any, Q: Any, mask: Any, thr2: float, min_count: float) -> Any:
    """:func:`_refit_rigid`'s loop: (fitted, R, t, inlier mask)."""
    n = P.shape[0]
    R = np.eye(3)
    t = np.zeros(3)
    for _ in range(3):
        if np.count_nonzero(mask) < min_count:
            return False, R, t, mask
        R, t = _kabsch_masked(P, Q, mask)
        new_mask = np.empty(n, dtype=np.bool_)
        same = True
        for i in range(n):
            d2 = 0.0
            for a in range(3):
                r = R[a, 0] * P[i, 0] + R[a, 1] * P[i, 1] + R[a, 2] * P[i, 2] + t[a] - Q[i, a]
                d2 += r * r
            new_mask[i] = d2 < thr2
            same &= new_mask[i] == mask[i]
        if same:
            break
        mask = new_mask
    return True, R, t, mask


@njit(cache=True)
def _kabsch_masked(P: Any, Q: Any, mask: Any) -> Any:
    """Kabsch (rotation, translation: ``Q ~ R P + t``) on the points ``mask``, never a reflection."""
    mp = np.zeros(3)
    mq = np.zeros(3)
    m = 0
    for i in range(P.shape[0]):
        if mask[i]:
            m += 1
            for a in range(3):
                mp[a] += P[i, a]
                mq[a] += Q[i, a]
    mp /= m
    mq /= m
    H = np.zeros((3, 3))
    for i in range(P.shape[0]):
        if mask[i]:
            for a in range(3):
                pa = P[i, a] - mp[a]
                for b in range(3):
                    H[a, b] += pa * (Q[i, b] - mq[b])
    U, _, Vt = np.linalg.svd(H / m)
    V = Vt.T.copy()
    R = V @ U.T
    if np.linalg.det(R) < 0.0:
        V[:, 2] = -V[:, 2]
        R = V @ U.T
    return R, mq - R @ mp


def rigid_from_prior(
    src: npt.ArrayLike,
    dst: npt.ArrayLike,
    T_guess: npt.ArrayLike,
    threshold_m: float,
    gate_m: float,
    min_fraction: float = 0.9,
    min_inliers: int = 6,
) -> Motion | None:
    """Rigid ``dst ~ R @ src + t`` without RANSAC when a predicted motion explains the points.

    The points within ``gate_m`` of ``T_guess`` (3D residual) are fitted by Kabsch, then, as
    after :func:`ransac_rigid`, the inliers (within ``threshold_m``) are re-selected and
    re-fitted up to three times. Accepted when at least ``min_fraction`` of the points (and
    ``min_inliers``) pass the gate and are inliers of the final fit; else None (run RANSAC).

    Args:
        src, dst: (N, 3) corresponding points (reference frame, current frame), metres.
        T_guess: (4, 4) predicted motion mapping src into dst (e.g. constant velocity).
        threshold_m: inlier threshold of the fit; gate_m: of the prediction.

    Returns:
        :class:`Motion` (``ok`` True) or None. Returns immediately.
    """
    P = np.asarray(src, dtype=np.float64)
    Q = np.asarray(dst, dtype=np.float64)
    T = np.asarray(T_guess, dtype=np.float64)
    n = len(P)
    if P.shape != Q.shape or (n and P.shape[1] != 3) or T.shape != (4, 4):
        raise EstimationError(
            f"rigid_from_prior needs two (N, 3) arrays and a 4x4 guess, got {P.shape}, {Q.shape}, {T.shape}"
        )
    need = max(3, min_inliers, min_fraction * n)
    if n < need:
        return None
    r = P @ T[:3, :3].T + T[:3, 3] - Q
    fit = _refit_rigid(P, Q, np.einsum("ni,ni->n", r, r) < gate_m * gate_m, threshold_m * threshold_m, need)
    if fit is None or np.count_nonzero(fit[2]) < need:
        return None
    R_b, t_b, mask = fit
    return Motion(make_T(R_b, t_b), mask, True)


def rigidity_inliers(P: npt.ArrayLike, Q: npt.ArrayLike, tol_m: float = 0.05, rel_tol: float = 0.02) -> Mask:
    """Largest set of points whose mutual distances are preserved between two frames.

    A rigid motion keeps every pairwise distance, so correspondences that agree form a
    clique in the graph "|P_i - P_j| == |Q_i - Q_j| within tolerance" (Howard 2008). The
    clique is grown greedily: start from the best-connected point, then repeatedly add the
    candidate connected to all members with the most connections among the candidates.

    Args:
        P, Q: (N, 3) the same points in the reference and current camera frames.
        tol_m: absolute distance tolerance; ``rel_tol`` adds a part proportional to the
            distance (stereo depth errors grow with range).

    Returns:
        (N,) bool mask of the clique members. Returns immediately (O(N^2) memory).
    """
    P = np.asarray(P, dtype=np.float64)
    Q = np.asarray(Q, dtype=np.float64)
    n = len(P)
    if n == 0:
        return np.zeros(0, dtype=bool)
    dP = np.sqrt(((P[:, None, :] - P[None, :, :]) ** 2).sum(-1))
    dQ = np.sqrt(((Q[:, None, :] - Q[None, :, :]) ** 2).sum(-1))
    A = np.abs(dP - dQ) <= (tol_m + rel_tol * np.maximum(dP, dQ))
    np.fill_diagonal(A, False)
    degree = A.sum(axis=1)
    members = np.zeros(n, dtype=bool)
    first = int(np.argmax(degree))
    members[first] = True
    candidates = A[first].copy()
    while candidates.any():
        # Among candidates, the one with most links to other candidates.
        cidx = np.flatnonzero(candidates)
        links = A[np.ix_(cidx, cidx)].sum(axis=1)
        pick = int(cidx[int(np.argmax(links))])
        members[pick] = True
        candidates &= A[pick]
        candidates[pick] = False
    return members
