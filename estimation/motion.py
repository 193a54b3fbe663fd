"""Frame-to-frame motion estimators: rigid 3D-3D (Kabsch/Umeyama + RANSAC), 3D-2D (PnP
+ RANSAC) and 2D-2D (essential matrix with metric scale from depth), and rigidity inliers.

Conventions: every estimator returns :class:`Motion` whose ``T_cur_ref`` (4x4) maps points
expressed in the *reference* camera frame (the earlier frame or keyframe) into the *current*
camera frame, ``X_cur = R @ X_ref + t``; camera frames are OpenCV (x right, y down, z
forward). The pose update is ``T_world_cur = T_world_ref @ inv(T_cur_ref)``.

Inputs are numpy arrays: 3D points (N, 3) metres, pixels (N, 2), the intrinsic matrix
``K`` (3, 3). Pure numpy except the PnP and essential-matrix solvers, which are OpenCV's.

Functions:
    umeyama(src, dst, with_scale) -> (R, t, s)        least squares, closed form (SVD)
    ransac_rigid(src, dst, threshold_m, ...) -> Motion vectorised 3-point RANSAC + refit
    rigidity_inliers(P, Q, tol_m) -> mask              max-clique of distance-preserving pairs
    pnp(points_ref, pts_px, K, method, ...) -> Motion  iterative / EPnP / SQPnP with RANSAC
    essential_metric(px_ref, px_cur, K, points_ref)    5-point RANSAC + recoverPose + depth scale
    refine_pose(T, points_ref, px, K, disparity_px)    Gauss-Newton on reprojection + disparity
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from flightkit.errors import EstimationError

__all__ = [
    "PNP_METHODS",
    "Motion",
    "essential_metric",
    "invert",
    "make_T",
    "median",
    "pnp",
    "ransac_iterations",
    "ransac_rigid",
    "refine_pose",
    "rigidity_inliers",
    "rotation_angle_rad",
    "umeyama",
]

logger = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
Mask = npt.NDArray[np.bool_]

PNP_METHODS: dict[str, int] = {
    "iterative": cv2.SOLVEPNP_ITERATIVE,
    "epnp": cv2.SOLVEPNP_EPNP,
    "sqpnp": cv2.SOLVEPNP_SQPNP,
}


@dataclass(frozen=True, slots=True, eq=False)
class Motion:
    """A relative motion estimate.

    Attributes:
        T_cur_ref: (4, 4) maps reference-camera points into the current camera frame.
        inliers: (N,) bool, which correspondences support the estimate.
        ok: False when the estimator could not produce a trustworthy motion (too few
            points or inliers); ``T_cur_ref`` is then the identity.
        scale: Umeyama similarity scale (1.0 for rigid estimates).
    """

    T_cur_ref: F64
    inliers: Mask
    ok: bool
    scale: float = 1.0

    @property
    def n_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))

    @property
    def R(self) -> F64:
        return self.T_cur_ref[:3, :3]

    @property
    def t(self) -> F64:
        return self.T_cur_ref[:3, 3]


def median(a: npt.NDArray[np.floating]) -> float:
    """``float(np.median(a))`` of a non-empty 1-D float array, bit for bit, without
    ``np.median``'s generic machinery (~4x cheaper on a few hundred values, where the VO
    calls it every frame). NaN when ``a`` holds a NaN."""
    n = len(a)
    h = n // 2
    if n % 2:
        p = np.partition(a, (h, n - 1))
        return float("nan") if p[-1] != p[-1] else float(p[h])
    p = np.partition(a, (h - 1, h, n - 1))
    # np.median's mean of the two middle values: their sum divided by 2.
    return float("nan") if p[-1] != p[-1] else float((p[h - 1] + p[h]) / 2)


_EYE4 = np.eye(4)
_EYE4.flags.writeable = False  # copied, never written (np.eye costs 5x a copy)


def make_T(R: npt.ArrayLike, t: npt.ArrayLike) -> F64:
    """4x4 homogeneous matrix from R (3, 3) and t (3,)."""
    T = _EYE4.copy()
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def invert(T: F64) -> F64:
    """Inverse of a rigid 4x4 transform (no general matrix inverse)."""
    Ti = _EYE4.copy()
    Rt = T[:3, :3].T
    Ti[:3, :3] = Rt
    Ti[:3, 3] = -Rt @ T[:3, 3]
    return Ti


def rotation_angle_rad(R: F64) -> float:
    """Angle of a rotation matrix, radians in [0, pi]."""
    c = (float(np.trace(R)) - 1.0) * 0.5
    return math.acos(min(1.0, max(-1.0, c)))


def _failed(n: int) -> Motion:
    return Motion(np.eye(4), np.zeros(n, dtype=bool), False)


def umeyama(src: npt.ArrayLike, dst: npt.ArrayLike, with_scale: bool = False) -> tuple[F64, F64, float]:
    """Least-squares ``dst ~ s * R @ src + t`` (Kabsch when ``with_scale`` is False, Umeyama 1991).

    Args:
        src, dst: (N, 3) corresponding points, N >= 3 and not all collinear.
        with_scale: also estimate the similarity scale s.

    Returns:
        ``(R, t, s)``; R is a proper rotation (det +1), s = 1.0 without scale.

    Raises:
        EstimationError: fewer than 3 points or mismatched shapes.
    """
    P = np.asarray(src, dtype=np.float64)
    Q = np.asarray(dst, dtype=np.float64)
    if P.shape != Q.shape or P.ndim != 2 or P.shape[1] != 3 or P.shape[0] < 3:
        raise EstimationError(f"umeyama needs two (N, 3) arrays with N >= 3, got {P.shape} and {Q.shape}")
    mp, mq = P.mean(axis=0), Q.mean(axis=0)
    Pc, Qc = P - mp, Q - mq
    H = Pc.T @ Qc / len(P)
    U, S, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    D = np.array([1.0, 1.0, d])
    R = (Vt.T * D) @ U.T
    s = 1.0
    if with_scale:
        var_p = float(np.mean(np.sum(Pc * Pc, axis=1)))
        if var_p <= 0.0:
            raise EstimationError("umeyama with scale needs source points that are not all identical")
        s = float(np.sum(S * D) / var_p)
    t = mq - s * R @ mp
    return R, t, s


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


def ransac_iterations(inlier_ratio: float, sample_size: int, confidence: float, max_iters: int) -> int:
    """Number of RANSAC draws for ``confidence`` of one all-inlier sample."""
    w = min(max(inlier_ratio, 1e-9), 1.0)
    p_good = w**sample_size
    if p_good >= 1.0 - 1e-12:
        return 1
    if p_good < 1e-12:
        return max_iters
    n = math.log(1.0 - confidence) / math.log(1.0 - p_good)
    return int(min(max_iters, max(1, math.ceil(n))))


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
        return _failed(n)
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
        return _failed(n)
    mask = best_mask
    R_b, t_b = np.eye(3), np.zeros(3)
    for _ in range(3):
        if np.count_nonzero(mask) < 3:
            return _failed(n)
        R_b, t_b, _ = umeyama(P[mask], Q[mask])
        r = P @ R_b.T + t_b - Q
        new_mask = np.einsum("ni,ni->n", r, r) < thr2
        if np.array_equal(new_mask, mask):
            break
        mask = new_mask
    ok = int(np.count_nonzero(mask)) >= min_inliers
    return Motion(make_T(R_b, t_b), mask, ok)


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


def pnp(
    points_ref: npt.ArrayLike,
    pts_px: npt.ArrayLike,
    K: npt.ArrayLike,
    method: str = "sqpnp",
    ransac: bool = True,
    reproj_px: float = 2.0,
    max_iters: int = 100,
    confidence: float = 0.999,
    min_inliers: int = 8,
    refine: bool = True,
    guess_T_cur_ref: F64 | None = None,
    ransac_kernel: str | None = None,
) -> Motion:
    """Pose of the current camera from reference-frame 3D points and their current pixels.

    Args:
        points_ref: (N, 3) points in the reference camera frame, metres.
        pts_px: (N, 2) their pixel positions in the current (undistorted) image.
        K: (3, 3) intrinsic matrix.
        method: ``"iterative"`` (Levenberg-Marquardt), ``"epnp"`` or ``"sqpnp"``; with
            RANSAC the minimal samples are solved by OpenCV's kernel and the final fit on
            all inliers by ``method``.
        ransac: reject outliers with RANSAC (threshold ``reproj_px``).
        refine: polish the inlier fit with ``cv2.solvePnPRefineLM``.
        guess_T_cur_ref: initial guess for the iterative method (e.g. constant velocity).
        ransac_kernel: solver of RANSAC's minimal samples: None (``method`` itself, as
            OpenCV does: 5-point samples), ``"p3p"`` or ``"ap3p"`` (4-point samples, about 3x
            cheaper per hypothesis). The fit on all inliers is then ``method`` (for
            ``"iterative"``: Levenberg-Marquardt from the RANSAC pose).

    Returns:
        :class:`Motion`; ``ok`` is False with fewer than ``min_inliers`` inliers.

    Raises:
        EstimationError: unknown method.
    """
    if method not in PNP_METHODS:
        raise EstimationError(f"unknown PnP method {method!r}; use one of {sorted(PNP_METHODS)}")
    obj = np.ascontiguousarray(points_ref, dtype=np.float64).reshape(-1, 3)
    img = np.ascontiguousarray(pts_px, dtype=np.float64).reshape(-1, 2)
    Km = np.asarray(K, dtype=np.float64)
    n = len(obj)
    if n < max(6, min_inliers):
        return _failed(n)
    flags = PNP_METHODS[method]
    if ransac_kernel not in (None, "p3p", "ap3p"):
        raise EstimationError(f"unknown PnP RANSAC kernel {ransac_kernel!r}; use None, 'p3p' or 'ap3p'")
    kernel_flags = flags if ransac_kernel is None else (
        cv2.SOLVEPNP_P3P if ransac_kernel == "p3p" else cv2.SOLVEPNP_AP3P
    )
    use_guess = guess_T_cur_ref is not None and method == "iterative" and ransac_kernel is None
    rvec0 = tvec0 = None
    if use_guess:
        assert guess_T_cur_ref is not None
        rvec0 = cv2.Rodrigues(guess_T_cur_ref[:3, :3])[0]
        tvec0 = guess_T_cur_ref[:3, 3].reshape(3, 1).copy()
    try:
        if ransac:
            ok, rvec, tvec, inl = cv2.solvePnPRansac(
                obj,
                img,
                Km,
                None,
                rvec=rvec0,
                tvec=tvec0,
                useExtrinsicGuess=use_guess,
                iterationsCount=max_iters,
                reprojectionError=reproj_px,
                confidence=confidence,
                flags=kernel_flags,
            )
            mask = np.zeros(n, dtype=bool)
            if ok and inl is not None:
                mask[inl.ravel()] = True
            if ok and kernel_flags != flags and method != "iterative" and np.count_nonzero(mask) >= 6:
                ok, rvec, tvec = cv2.solvePnP(obj[mask], img[mask], Km, None, flags=flags)
            elif ok and kernel_flags != flags and not refine:
                rvec, tvec = cv2.solvePnPRefineLM(obj[mask], img[mask], Km, None, rvec, tvec)
        else:
            ok, rvec, tvec = cv2.solvePnP(
                obj, img, Km, None, rvec=rvec0, tvec=tvec0, useExtrinsicGuess=use_guess, flags=flags
            )
            mask = np.ones(n, dtype=bool)
    except cv2.error as exc:
        logger.debug("PnP failed: %s", exc)
        return _failed(n)
    if not ok or np.count_nonzero(mask) < min_inliers:
        return _failed(n)
    if refine:
        rvec, tvec = cv2.solvePnPRefineLM(obj[mask], img[mask], Km, None, rvec, tvec)
        # Re-select inliers with the refined pose.
        proj, _ = cv2.projectPoints(obj, rvec, tvec, Km, None)
        err2 = ((proj.reshape(-1, 2) - img) ** 2).sum(axis=1)
        z = obj @ cv2.Rodrigues(rvec)[0][2] + float(tvec[2, 0])
        mask = (err2 < reproj_px * reproj_px) & (z > 0)
        if np.count_nonzero(mask) < min_inliers:
            return _failed(n)
    R = cv2.Rodrigues(rvec)[0]
    return Motion(make_T(R, tvec.ravel()), mask, True)


_GN_STOP = 1e-10
"""refine_pose stops when the squared step (m^2 + rad^2) falls below this: a 10 um / 10 urad
step. (1e-8 stopped a step early and cost 3 mm of ATE on the synthetic circle; 1e-14 ran
every iteration for nothing.)"""


def refine_pose(
    T_cur_ref: F64,
    points_ref: npt.ArrayLike,
    pts_px: npt.ArrayLike,
    K: npt.ArrayLike,
    disparity_px: npt.ArrayLike | None = None,
    fb_px_m: float = 0.0,
    huber_px: float = 1.0,
    iterations: int = 4,
) -> F64:
    """Gauss-Newton polish of a pose on reprojection and (optionally) disparity residuals.

    Per point: ``u, v`` reprojection residuals in the current image and, where a current
    disparity is measured (stereo, or depth as ``fb / z``), ``fb / z_pred - d``, which pins
    down the motion along the optical axis that image residuals alone constrain weakly.
    Huber-weighted (IRLS), analytic Jacobian, a left perturbation ``T <- exp(xi) T``.

    Args:
        T_cur_ref: (4, 4) initial pose (e.g. from PnP RANSAC), inliers only below.
        points_ref: (N, 3) reference-frame points.
        pts_px: (N, 2) current pixels.
        K: (3, 3) intrinsics.
        disparity_px: (N,) current disparities (NaN where unknown), or None.
        fb_px_m: ``fx * baseline`` of the disparities (pixel metres).
        huber_px: Huber threshold of all residuals.
        iterations: Gauss-Newton steps (stops early on convergence).

    Returns:
        The refined (4, 4) pose. Returns immediately (vectorised numpy).
    """
    X = np.asarray(points_ref, dtype=np.float64).reshape(-1, 3)
    uv = np.asarray(pts_px, dtype=np.float64).reshape(-1, 2)
    Km = np.asarray(K, dtype=np.float64)
    fx, fy, cx, cy = float(Km[0, 0]), float(Km[1, 1]), float(Km[0, 2]), float(Km[1, 2])
    n = len(X)
    if n < 4:
        return T_cur_ref
    d = None if disparity_px is None else np.asarray(disparity_px, dtype=np.float64).reshape(-1)
    has_d = np.zeros(n, dtype=bool) if d is None or fb_px_m <= 0 else np.isfinite(d)
    T = T_cur_ref.copy()
    di = np.flatnonzero(has_d)
    nd = len(di)
    all_d = nd == n
    dd = (d if all_d else d[di]) if d is not None and nd else np.zeros(0)
    u_obs, v_obs = uv[:, 0].copy(), uv[:, 1].copy()
    # Stacked rows: u (n), v (n), disparity (nd); Jacobian columns [rho (3), phi (3)] of a
    # left perturbation, written column by column into one buffer (the zero columns once),
    # every product in place: ~25 small numpy calls per step instead of ~45, the same
    # arithmetic in the same order (bit-identical results).
    m = 2 * n + nd
    J = np.empty((m, 6))
    Jw = np.empty((m, 6))
    r = np.empty(m)
    t1 = np.empty(n)
    Ju, Jv, Jd = J[:n], J[n : 2 * n], J[2 * n :]
    ru, rv, rd = r[:n], r[n : 2 * n], r[2 * n :]
    Ju[:, 1] = 0.0
    Jv[:, 0] = 0.0
    Jd[:, 0] = 0.0
    Jd[:, 1] = 0.0
    Jd[:, 5] = 0.0
    for _ in range(iterations):
        # The depth residuals reuse this projection's rows (the same values as projecting
        # the depth points alone).
        Xc = X @ T[:3, :3].T + T[:3, 3]
        x, y, z = Xc[:, 0], Xc[:, 1], Xc[:, 2]
        if (z <= 1e-6).any():
            break
        iz = 1.0 / z
        xz, yz = x * iz, y * iz
        np.multiply(fx, xz, out=ru)
        ru += cx
        ru -= u_obs
        np.multiply(fy, yz, out=rv)
        rv += cy
        rv -= v_obs
        np.multiply(fx, iz, out=Ju[:, 0])
        np.multiply(-fx, xz, out=t1)  # -fx * xz
        np.multiply(t1, iz, out=Ju[:, 2])
        np.multiply(t1, yz, out=Ju[:, 3])
        np.multiply(xz, xz, out=t1)
        t1 += 1.0
        np.multiply(fx, t1, out=Ju[:, 4])
        np.multiply(-fx, yz, out=Ju[:, 5])
        np.multiply(fy, iz, out=Jv[:, 1])
        np.multiply(-fy, yz, out=t1)
        np.multiply(t1, iz, out=Jv[:, 2])
        np.multiply(yz, yz, out=t1)
        t1 += 1.0
        np.multiply(-fy, t1, out=Jv[:, 3])
        np.multiply(fy, xz, out=t1)
        np.multiply(t1, yz, out=Jv[:, 4])
        np.multiply(fy, xz, out=Jv[:, 5])
        if nd:
            izd, xd, yd = (iz, x, y) if all_d else (iz[di], x[di], y[di])
            k = fb_px_m * izd * izd
            np.multiply(fb_px_m, izd, out=rd)
            rd -= dd
            np.negative(k, out=Jd[:, 2])
            np.multiply(-k, yd, out=Jd[:, 3])
            np.multiply(k, xd, out=Jd[:, 4])
        a = np.abs(r)
        if huber_px > 0:
            # huber / max(a, huber): exactly 1 where a <= huber, huber / a beyond.
            w = huber_px / np.maximum(a, huber_px)
        else:
            w = np.where(a <= huber_px, 1.0, huber_px / np.maximum(a, 1e-12))
        np.multiply(J, w[:, None], out=Jw)
        H = Jw.T @ J
        g = Jw.T @ r
        try:
            xi = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            break
        dT = _EYE4.copy()
        dT[:3, :3] = cv2.Rodrigues(xi[3:])[0]
        dT[:3, 3] = xi[:3]
        T = dT @ T
        if float(xi @ xi) < _GN_STOP:
            break
    return T


def essential_metric(
    px_ref: npt.ArrayLike,
    px_cur: npt.ArrayLike,
    K: npt.ArrayLike,
    points_ref: npt.ArrayLike,
    threshold_px: float = 1.0,
    confidence: float = 0.999,
    min_inliers: int = 12,
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

    Returns:
        :class:`Motion` (``ok`` False when RANSAC, the cheirality check or the scale fail).
    """
    p0 = np.ascontiguousarray(px_ref, dtype=np.float64).reshape(-1, 2)
    p1 = np.ascontiguousarray(px_cur, dtype=np.float64).reshape(-1, 2)
    X = np.asarray(points_ref, dtype=np.float64).reshape(-1, 3)
    Km = np.asarray(K, dtype=np.float64)
    n = len(p0)
    if n < max(8, min_inliers):
        return _failed(n)
    try:
        E, emask = cv2.findEssentialMat(
            p0, p1, Km, method=cv2.RANSAC, prob=confidence, threshold=threshold_px
        )
    except cv2.error as exc:
        logger.debug("findEssentialMat failed: %s", exc)
        return _failed(n)
    if E is None or emask is None:
        return _failed(n)
    E = E[:3]
    _, R, t, pmask = cv2.recoverPose(E, p0, p1, Km, mask=emask.copy())
    mask = pmask.ravel() > 0
    if np.count_nonzero(mask) < min_inliers:
        return _failed(n)
    t = t.ravel()
    Kinv = np.linalg.inv(Km)
    valid = mask & np.isfinite(X).all(axis=1) & (X[:, 2] > 0)
    if np.count_nonzero(valid) < 3:
        return _failed(n)
    x = np.c_[p1[valid], np.ones(np.count_nonzero(valid))] @ Kinv.T
    a = np.cross(x, X[valid] @ R.T)
    b = np.cross(x, np.broadcast_to(t, x.shape))
    bb = np.einsum("ni,ni->n", b, b)
    good = bb > 1e-12
    if np.count_nonzero(good) < 3:
        return _failed(n)
    s_all = -np.einsum("ni,ni->n", a[good], b[good]) / bb[good]
    # Median, then a weighted mean over the points near it (|b|^2 weights well-conditioned points).
    s_med = median(s_all)
    mad = median(np.abs(s_all - s_med)) + 1e-9
    near = np.abs(s_all - s_med) < 3.0 * 1.4826 * mad
    w = bb[good][near]
    s = float(np.sum(s_all[near] * w) / np.sum(w)) if w.sum() > 0 else s_med
    if not math.isfinite(s):
        return _failed(n)
    # A negative s means depth disagrees with recoverPose's sign choice (tiny baselines);
    # s * t is then the motion the depths support.
    return Motion(make_T(R, s * t), mask, True)
