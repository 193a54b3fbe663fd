"""2D-2D motion: the essential matrix (5-point RANSAC, or one Levenberg-Marquardt step on the
Sampson distance from a prediction) with the rotation, the translation's sign and its metric
scale from the reference frame's depths.

Functions:
    essential_metric(px_ref, px_cur, K, points_ref)    5-point RANSAC + cheirality + depth scale
    pose_from_essential(E, px_cur, points_ref, K, m)   the motion of E the depths support
    essential_from_prior(px_ref, px_cur, K, X, T)      no RANSAC when a prediction explains the matches
    refine_essential(R, t, x_ref, x_cur, f)            LM on the Sampson distance (5 DoF)
    sampson_px(R, t, x_ref, x_cur, f)                  Sampson distance in pixels
"""

from __future__ import annotations

import logging
import math

import cv2
import numpy as np
import numpy.typing as npt

from estimation import _essential_kernel, _kernels
from estimation.five_point import find_essential
from estimation.motion import Motion, failed_motion, make_T
from flightkit.errors import EstimationError

__all__ = ["essential_from_prior", "essential_metric", "pose_from_essential", "refine_essential", "sampson_px"]

logger = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
Mask = npt.NDArray[np.bool_]


def essential_metric(
    px_ref: npt.ArrayLike,
    px_cur: npt.ArrayLike,
    K: npt.ArrayLike,
    points_ref: npt.ArrayLike,
    threshold_px: float = 1.0,
    confidence: float = 0.999,
    min_inliers: int = 12,
    cheirality: str = "opencv",
    agree_px: float = 6.0,
) -> Motion:
    """Relative pose from 2D-2D matches (5-point RANSAC + ``recoverPose``), metric scale from depth.

    The essential matrix gives the rotation and the *direction* of translation. The scale
    comes from the reference depths: for each inlier with a valid 3D point X (reference
    frame) and normalised current ray x, ``x cross (R X + s t) = 0`` is linear in s; the
    scale is the median of those per-point solutions (robust to bad depths).

    Args:
        px_ref, px_cur: (N, 2) matched pixels in the reference and current images.
        K: (3, 3) intrinsics (both images).
        points_ref: (N, 3) reference-frame 3D points of ``px_ref`` from depth; rows with a
            non-finite or non-positive z are ignored for the scale.
        threshold_px: RANSAC epipolar threshold.
        cheirality: how the right one of the essential matrix's motions is chosen:
            ``"opencv"`` (``recoverPose``: triangulated points in front of both cameras and
            nearer than 50 baselines, so points 2-4 m away at a 2 cm baseline fail it) or
            ``"depth"`` (:func:`pose_from_essential`: each candidate rotation with its metric
            scale from depth, the one that reprojects most reference points within
            ``agree_px`` wins; the depth fixes the sign of the translation).
        agree_px: ``cheirality="depth"``: reprojection tolerance of the choice (pixels).

    Returns:
        :class:`Motion` (``ok`` False when RANSAC, the cheirality check or the scale fail).
    """
    if cheirality not in ("opencv", "depth"):
        raise EstimationError(f"essential_metric cheirality is {cheirality!r}; use 'opencv' or 'depth'")
    p0 = np.ascontiguousarray(px_ref, dtype=np.float64).reshape(-1, 2)
    p1 = np.ascontiguousarray(px_cur, dtype=np.float64).reshape(-1, 2)
    X = np.asarray(points_ref, dtype=np.float64).reshape(-1, 3)
    Km = np.asarray(K, dtype=np.float64)
    n = len(p0)
    if n < max(8, min_inliers):
        return failed_motion(n)
    # OpenCV's findEssentialMat (RANSAC) with the same samples, compiled (estimation.five_point).
    E, inl = find_essential(p0, p1, Km, threshold_px, confidence)
    if E is None:
        return failed_motion(n)
    emask = inl.astype(np.uint8).reshape(-1, 1)
    if cheirality == "depth":
        m = pose_from_essential(E, p1, X, Km, emask.ravel() > 0, agree_px)
        return m if m is not None and m.n_inliers >= min_inliers else failed_motion(n)
    _, R, t, pmask = cv2.recoverPose(E, p0, p1, Km, mask=emask.copy())
    mask = pmask.ravel() > 0
    if np.count_nonzero(mask) < min_inliers:
        return failed_motion(n)
    t = np.asarray(t, dtype=np.float64).ravel()
    s = _metric_scale_rays(np.asarray(R, dtype=np.float64), t, _normalised(p1, Km), X, mask)
    if s is None:
        return failed_motion(n)
    # A negative s means depth disagrees with recoverPose's sign choice (tiny baselines);
    # s * t is then the motion the depths support.
    return Motion(make_T(R, s * t), mask, True)


def _normalised(px: F64, Km: F64) -> F64:
    """(N, 2) pixels as normalised image coordinates ``((u - cx) / fx, (v - cy) / fy)``."""
    x = np.empty((len(px), 2))
    x[:, 0] = (px[:, 0] - Km[0, 2]) / Km[0, 0]
    x[:, 1] = (px[:, 1] - Km[1, 2]) / Km[1, 1]
    return x


def _metric_scale_rays(R: F64, t: F64, x_cur: F64, X: F64, mask: Mask) -> float | None:
    """The scale s of a unit translation ``t`` that the reference depths support, from the matches
    ``mask`` whose points ``X`` are valid (finite, z > 0) and their normalised current rays ``x_cur``
    ((N, 2) or (N, 3): ``u, v``): per match ``x cross (R X + s t) = 0`` is linear in s; the median,
    then a ``|x cross t|^2``-weighted mean over the solutions near it. The per-match part is one
    compiled call (``estimation._essential_kernel.scale_terms``, equal bit for bit to the numpy
    expressions it replaced). None when too few matches tell."""
    ok, s_med, s_near, w = _essential_kernel.scale_terms(
        np.ascontiguousarray(R, dtype=np.float64),
        np.ascontiguousarray(t, dtype=np.float64),
        x_cur,
        np.ascontiguousarray(X, dtype=np.float64),
        mask,
    )
    if not ok:
        return None
    wsum = float(w.sum())
    s = float(s_near @ w) / wsum if wsum > 0 else s_med
    return s if math.isfinite(s) else None


def _reproj_err2_px(T: F64, X: F64, p1: F64, Km: F64) -> F64:
    """Squared reprojection error (px^2) of reference points X in the current image (inf behind it)."""
    err2: F64 = _kernels.reproj_err2(
        np.ascontiguousarray(X),
        np.ascontiguousarray(T),
        np.ascontiguousarray(p1),
        float(Km[0, 0]),
        float(Km[1, 1]),
        float(Km[0, 2]),
        float(Km[1, 2]),
        1e-9,
    )
    return err2


def pose_from_essential(
    E: npt.ArrayLike,
    px_cur: npt.ArrayLike,
    points_ref: npt.ArrayLike,
    K: npt.ArrayLike,
    inliers: Mask,
    agree_px: float = 6.0,
) -> Motion | None:
    """The metric motion of an essential matrix that the reference depths support.

    ``E`` factors into two rotations and a unit translation of either sign. With depth the
    sign comes with the metric scale (:func:`_metric_scale_rays` solves it per rotation, a
    negative scale flips the translation), and the rotation is the one whose motion
    reprojects most reference points (of ``inliers``) within ``agree_px``: no
    triangulation, so no distance limit as in ``recoverPose`` (50 baselines). The returned
    inliers are those points. None when no candidate has a scale.
    """
    p1 = np.ascontiguousarray(px_cur, dtype=np.float64).reshape(-1, 2)
    X = np.asarray(points_ref, dtype=np.float64).reshape(-1, 3)
    Km = np.asarray(K, dtype=np.float64)
    R1, R2, t_col = cv2.decomposeEssentialMat(np.asarray(E, dtype=np.float64))
    t: F64 = np.asarray(t_col, dtype=np.float64).ravel()
    best: Motion | None = None
    ok_X = np.isfinite(X).all(axis=1) & (X[:, 2] > 0)
    x_cur = _normalised(p1, Km)
    inl = np.ascontiguousarray(inliers, dtype=np.bool_)
    for R_cand in (R1, R2):
        R = np.asarray(R_cand, dtype=np.float64)
        s = _metric_scale_rays(R, t, x_cur, X, inl)
        if s is None:
            continue
        T = make_T(R, s * t)
        mask = inliers & ok_X
        mask[mask] = _reproj_err2_px(T, X[mask], p1[mask], Km) < agree_px * agree_px
        if best is None or np.count_nonzero(mask) > best.n_inliers:
            best = Motion(T, mask, True)
    return best


def sampson_px(R: F64, t: F64, x_ref: F64, x_cur: F64, f_px: float) -> F64:
    """Sampson distance (pixels, ``f_px`` times the normalised-plane distance) of matches to
    the epipolar geometry of ``(R, t)``; ``x_ref``, ``x_cur``: (N, 3) normalised homogeneous
    rays (z = 1). A first-order distance of each match to the nearest pair that satisfies
    ``x_cur^T [t]x R x_ref = 0``, the test of OpenCV's essential-matrix RANSAC."""
    d: F64 = _kernels.sampson_distance(*_rays(R, t, x_ref, x_cur), float(f_px), False)
    return d


def _rays(R: F64, t: F64, x_ref: F64, x_cur: F64) -> tuple[F64, F64, F64, F64]:
    """The kernels' inputs: contiguous float64 (3, 3), (3,), (N, 3), (N, 3)."""
    return (
        np.ascontiguousarray(R, dtype=np.float64),
        np.ascontiguousarray(t, dtype=np.float64).reshape(3),
        np.ascontiguousarray(x_ref, dtype=np.float64),
        np.ascontiguousarray(x_cur, dtype=np.float64),
    )


def refine_essential(
    R: F64,
    t: F64,
    x_ref: F64,
    x_cur: F64,
    f_px: float,
    huber_px: float = 1.0,
    iterations: int = 5,
) -> tuple[F64, F64]:
    """Gauss-Newton on the Sampson distance over the 5 degrees of freedom of an essential
    matrix: a left rotation increment (3) and the unit translation moved in its tangent
    plane (2). Huber-weighted (IRLS, threshold in pixels), analytic Jacobian of the whole
    distance (numerator and denominator). A step is kept only when it lowers the robust cost
    (else it is damped, Levenberg-Marquardt), so the result is never worse than the start.
    One compiled call (``estimation._essential_kernel.essential_lm``); it agrees with the numpy
    loop it replaced to ~1e-12 relative, not bit for bit (the order of the normal equations'
    sums, the solve).

    Args:
        R, t: the start (t any length; only its direction is used).
        x_ref, x_cur: (N, 3) normalised homogeneous rays of the matches (N >= 5).
        f_px: focal length that turns normalised distances into pixels.
        huber_px: Huber threshold (pixels).
        iterations: at most this many accepted steps (stops earlier on convergence).

    Returns:
        ``(R, t)`` with ``|t| = 1``.
    """
    R_out: F64
    t_out: F64
    R_out, t_out = _essential_kernel.essential_lm(
        *_rays(R, t, x_ref, x_cur), float(f_px), float(huber_px), int(iterations)
    )
    return R_out, t_out


def essential_from_prior(
    px_ref: npt.ArrayLike,
    px_cur: npt.ArrayLike,
    K: npt.ArrayLike,
    points_ref: npt.ArrayLike,
    T_guess: F64,
    gate_px: float = 2.0,
    threshold_px: float = 1.0,
    min_fraction: float = 0.9,
    min_inliers: int = 12,
    iterations: int = 5,
) -> Motion | None:
    """The essential-matrix motion without RANSAC, when a predicted motion explains the matches.

    The matches within ``gate_px`` (Sampson distance) of the epipolar geometry of
    ``T_guess`` (e.g. a constant-velocity prediction) are fitted by
    :func:`refine_essential` (Gauss-Newton on the Sampson distance, 5 DoF, started at the
    prediction's rotation and translation direction); the inliers are the matches within
    ``threshold_px`` of the result; the metric scale comes from depth as in
    :func:`essential_metric`. None (the caller runs RANSAC) when fewer than
    ``max(min_inliers, min_fraction * N)`` matches pass the gate or the inlier test, when
    the prediction has no translation to give a direction, or when the depths give no scale.
    """
    p0 = np.ascontiguousarray(px_ref, dtype=np.float64).reshape(-1, 2)
    p1 = np.ascontiguousarray(px_cur, dtype=np.float64).reshape(-1, 2)
    X = np.asarray(points_ref, dtype=np.float64).reshape(-1, 3)
    Km = np.asarray(K, dtype=np.float64)
    n = len(p0)
    need = max(min_inliers, 8, min_fraction * n)
    t_g = T_guess[:3, 3]
    if n < need or float(t_g @ t_g) < 1e-12:
        return None
    # Normalised rays, the gate, the Gauss-Newton loop and the inlier test: one compiled call.
    ok, R, t, mask, x1 = _essential_kernel.essential_prior(
        p0,
        p1,
        float(Km[0, 0]),
        float(Km[1, 1]),
        float(Km[0, 2]),
        float(Km[1, 2]),
        np.ascontiguousarray(T_guess[:3, :3], dtype=np.float64),
        np.ascontiguousarray(t_g, dtype=np.float64),
        float(gate_px),
        float(threshold_px),
        float(need),
        int(iterations),
    )
    if not ok:
        return None
    s = _metric_scale_rays(R, t, x1, X, mask)
    if s is None:
        return None
    return Motion(make_T(R, s * t), mask, True)
