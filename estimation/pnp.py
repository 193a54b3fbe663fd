"""3D-2D motion: PnP with RANSAC (OpenCV's solvers, or the compiled P3P RANSAC of
``estimation.p3p``) and the Gauss-Newton pose polish on reprojection plus disparity residuals.

Functions:
    pnp(points_ref, pts_px, K, method, ...) -> Motion  iterative / EPnP / SQPnP with RANSAC
    refine_pose(T, points_ref, px, K, disparity_px)    Gauss-Newton on reprojection + disparity
"""

from __future__ import annotations

import logging

import cv2
import numpy as np
import numpy.typing as npt

from estimation import _pose_kernel
from estimation.motion import Motion, failed_motion, make_T
from estimation.p3p import pnp_ransac
from flightkit.errors import EstimationError

__all__ = ["PNP_METHODS", "pnp", "refine_pose"]

logger = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
Mask = npt.NDArray[np.bool_]

PNP_METHODS: dict[str, int] = {
    "iterative": cv2.SOLVEPNP_ITERATIVE,
    "epnp": cv2.SOLVEPNP_EPNP,
    "sqpnp": cv2.SOLVEPNP_SQPNP,
}


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
        ransac_kernel: the RANSAC and its minimal solver: None (OpenCV's RANSAC with ``method``
            itself on 5-point samples), ``"p3p"`` (the compiled P3P RANSAC of
            ``estimation.p3p``, 4-point samples) or ``"ap3p"`` (OpenCV's RANSAC with its AP3P
            kernel, 4-point samples). With a 4-point kernel the fit on all inliers is then
            ``method`` (for ``"iterative"``: Levenberg-Marquardt from the RANSAC pose) and
            ``guess_T_cur_ref`` is not used.

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
        return failed_motion(n)
    flags = PNP_METHODS[method]
    if ransac_kernel not in (None, "p3p", "ap3p"):
        raise EstimationError(f"unknown PnP RANSAC kernel {ransac_kernel!r}; use None, 'p3p' or 'ap3p'")
    four_point = ransac and ransac_kernel is not None
    use_guess = guess_T_cur_ref is not None and method == "iterative" and ransac_kernel is None
    rvec0 = tvec0 = None
    if use_guess:
        assert guess_T_cur_ref is not None
        rvec0 = cv2.Rodrigues(guess_T_cur_ref[:3, :3])[0]
        tvec0 = guess_T_cur_ref[:3, 3].reshape(3, 1).copy()
    try:
        if ransac and ransac_kernel != "p3p":
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
                flags=flags if ransac_kernel is None else cv2.SOLVEPNP_AP3P,
            )
            mask = np.zeros(n, dtype=bool)
            if ok and inl is not None:
                mask[inl.ravel()] = True
        elif ransac:
            ok, R_cur_ref, t_cur_ref, mask = pnp_ransac(obj, img, Km, reproj_px, confidence, max_iters)
            rvec, tvec = cv2.Rodrigues(R_cur_ref)[0], t_cur_ref.reshape(3, 1).copy()
        else:
            ok, rvec, tvec = cv2.solvePnP(
                obj, img, Km, None, rvec=rvec0, tvec=tvec0, useExtrinsicGuess=use_guess, flags=flags
            )
            mask = np.ones(n, dtype=bool)
        # After a 4-point kernel: the fit on all inliers with ``method`` (the iterative one by
        # the refine block below, or here without it).
        if ok and four_point and method != "iterative" and np.count_nonzero(mask) >= 6:
            ok, rvec, tvec = cv2.solvePnP(obj[mask], img[mask], Km, None, flags=flags)
        elif ok and four_point and not refine:
            rvec, tvec = cv2.solvePnPRefineLM(obj[mask], img[mask], Km, None, rvec, tvec)
    except cv2.error as exc:
        logger.debug("PnP failed: %s", exc)
        return failed_motion(n)
    if not ok or np.count_nonzero(mask) < min_inliers:
        return failed_motion(n)
    if refine:
        rvec, tvec = cv2.solvePnPRefineLM(obj[mask], img[mask], Km, None, rvec, tvec)
        # Re-select inliers with the refined pose.
        proj, _ = cv2.projectPoints(obj, rvec, tvec, Km, None)
        err2 = ((proj.reshape(-1, 2) - img) ** 2).sum(axis=1)
        z = obj @ cv2.Rodrigues(rvec)[0][2] + float(tvec[2, 0])
        mask = (err2 < reproj_px * reproj_px) & (z > 0)
        if np.count_nonzero(mask) < min_inliers:
            return failed_motion(n)
    R = cv2.Rodrigues(rvec)[0]
    return Motion(make_T(R, tvec.ravel()), mask, True)


_NONE = np.empty(0)
"""refine_pose's empty optional per-point arrays (the kernel reads empty as none given)."""

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
    translation_weight: npt.ArrayLike | None = None,
    point_var: npt.ArrayLike | None = None,
) -> F64:
    """Gauss-Newton polish of a pose on reprojection and (optionally) disparity residuals.

    Per point: ``u, v`` reprojection residuals in the current image and, where a current
    disparity is measured (stereo, or depth as ``fb / z``), ``fb / z_pred - d``, which pins
    down the motion along the optical axis that image residuals alone constrain weakly.
    Huber-weighted (IRLS), analytic Jacobian, a left perturbation ``T <- exp(xi) T``.

    Args:
        T_cur_ref: (4, 4) initial pose (e.g. from PnP RANSAC), inliers only below. A rotation
            that drifted off SO(3) (a start chained from earlier estimates) is replaced by the
            nearest rotation first.
        points_ref: (N, 3) reference-frame points.
        pts_px: (N, 2) current pixels.
        K: (3, 3) intrinsics.
        disparity_px: (N,) current disparities (NaN where unknown), or None.
        fb_px_m: ``fx * baseline`` of the disparities (pixel metres).
        huber_px: Huber threshold of all residuals (> 0; a huge one is plain least squares).
        iterations: Gauss-Newton steps (stops early on convergence).
        translation_weight: (N,) factor in [0, 1] on each point's say in the translation (and on
            its disparity row): 0 lets a point fix the rotation only; None: 1 for every point.
        point_var: (N,) variance of each point's own disparity ``fb / z`` (its depth in the
            reference frame) over the tracks' pixel variance: its residuals are whitened by the
            covariance that error adds (``estimation._pose_kernel``; needs ``fb_px_m`` > 0);
            None: the points are exact.

    Returns:
        The refined (4, 4) pose: a new array (``T_cur_ref`` itself with fewer than 4 points).
    """
    X = np.ascontiguousarray(points_ref, dtype=np.float64).reshape(-1, 3)
    uv = np.ascontiguousarray(pts_px, dtype=np.float64).reshape(-1, 2)
    Km = np.asarray(K, dtype=np.float64)
    fx, fy, cx, cy = float(Km[0, 0]), float(Km[1, 1]), float(Km[0, 2]), float(Km[1, 2])
    n = len(X)
    if not huber_px > 0:
        raise EstimationError(f"refine_pose huber_px is {huber_px}; use a positive threshold (1 px is typical)")
    # (empty: no disparities, every translation weight 1)
    if disparity_px is None or fb_px_m <= 0:
        disp = _NONE
    else:
        disp = np.ascontiguousarray(disparity_px, dtype=np.float64).reshape(-1)
    tw = _NONE if translation_weight is None else np.ascontiguousarray(translation_weight, dtype=np.float64).reshape(-1)
    if len(uv) != n:
        raise EstimationError(f"refine_pose got {n} points and {len(uv)} pixels; give one pixel per point")
    if disp is not _NONE and len(disp) != n:
        raise EstimationError(f"refine_pose got {n} points and {len(disp)} disparities; give one per point (or None)")
    if tw is not _NONE and len(tw) != n:
        raise EstimationError(f"refine_pose got {n} points and {len(tw)} translation weights; give one per point")
    var = _NONE if point_var is None else np.ascontiguousarray(point_var, dtype=np.float64).reshape(-1)
    if point_var is not None and (len(var) != n or not fb_px_m > 0 or not np.all(var >= 0.0)):
        raise EstimationError(
            f"refine_pose got {n} points, {len(var)} point variances (all >= 0: {bool(np.all(var >= 0.0))}) "
            f"and fb_px_m={fb_px_m}; give one variance per point (each >= 0) and the disparities' positive "
            "fx * baseline"
        )
    if n < 4:
        return T_cur_ref
    # The start's rotation projected onto SO(3) (OpenCV's Rodrigues takes the nearest
    # rotation): a start made by chaining earlier estimates drifts off it, the steps below
    # multiply onto it and would keep that drift, and it compounds frame after frame.
    T0 = np.array(T_cur_ref, dtype=np.float64)
    if _pose_kernel.rotation_error(T0) > 1e-12:
        T0[:3, :3] = cv2.Rodrigues(cv2.Rodrigues(T0[:3, :3])[0])[0]
    # Per step: reprojection rows u, v and a disparity row where one is measured, their
    # Jacobian in a left perturbation [rho, phi], Huber weights, the normal equations, the
    # 6x6 solve and the update, all in one compiled call (estimation._pose_kernel); with
    # point_var the rows are whitened first.
    T: F64 = _pose_kernel.pose_gauss_newton(
        X,
        T0,
        uv,
        disp,
        tw,
        var,
        fx,
        fy,
        cx,
        cy,
        float(fb_px_m),
        float(huber_px),
        int(iterations),
        _GN_STOP,
        6,
    )
    return T
