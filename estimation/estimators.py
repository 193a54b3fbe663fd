"""The keyframe methods' motion estimators, one per method behind one interface.

Each takes the front end's tracks of the keyframe's 3D points (``estimation.pipeline.VisualOdometry``:
detection, tracking, stereo and depth lookup, keyframes, the pose polish and the depth fusion) and
returns the keyframe-to-current motion:

* :class:`PnpEstimator` (``stereo``, ``rgbd-pnp``): PnP + RANSAC on the keyframe points (rgbd-pnp:
  SQPnP without RANSAC when the prediction explains the tracks), then the depth polish;
* :class:`EssentialEstimator` (``rgbd-essential``): the essential matrix keyframe to current
  (from the prediction or the 5-point RANSAC), its metric scale and cheirality from depth,
  checked on the keyframe points' reprojection; PnP when the parallax is too small;
* :class:`KabschEstimator` (``rgbd-kabsch``): 3D-3D Kabsch on the depth of both frames
  (from the prediction or a vectorised RANSAC), then the polish.

``flow`` has its own estimator (``estimation.flow_vo.FlowEstimator``): it keeps no keyframe.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

import numpy as np
import numpy.typing as npt

from estimation.motion import (
    Motion,
    essential_from_prior,
    essential_metric,
    median,
    pnp,
    ransac_rigid,
    refine_pose,
    rigid_from_prior,
    rigidity_inliers,
)
from estimation.vo_options import Method

if TYPE_CHECKING:
    from estimation.pipeline import VisualOdometry

__all__ = ["EssentialEstimator", "KabschEstimator", "MotionEstimator", "PnpEstimator", "keyframe_estimator"]

F64 = npt.NDArray[np.float64]
F32 = npt.NDArray[np.float32]

_LEAST_SQUARES_PX = 1e9
"""A Huber threshold no reprojection residual reaches: plain least squares."""


class MotionEstimator(Protocol):
    """One keyframe method's motion estimation (see the module docstring)."""

    def estimate(
        self,
        X_kf: F64,
        px_kf: F32,
        px_cur: F32,
        und_cur: F64,
        depth_m: F32 | None,
        guess: F64,
        right_pyr: npt.NDArray[np.uint8] | None,
        pyr: npt.NDArray[np.uint8],
        right_gray: npt.NDArray[np.uint8] | None,
    ) -> Motion: ...


class EssentialEstimator:
    """``rgbd-essential``: the essential matrix, metric scale and cheirality from depth."""

    def __init__(self, vo: VisualOdometry) -> None:
        self.vo = vo

    def estimate(
        self,
        X_kf: F64,
        px_kf: F32,
        px_cur: F32,
        und_cur: F64,
        depth_m: F32 | None,
        guess: F64,
        right_pyr: npt.NDArray[np.uint8] | None,
        pyr: npt.NDArray[np.uint8],
        right_gray: npt.NDArray[np.uint8] | None,
    ) -> Motion:
        """The motion ``T_cur_kf`` of the keyframe points ``X_kf`` (keyframe frame, m) seen at
        ``px_kf`` in the keyframe and tracked to ``px_cur`` (``und_cur`` undistorted) now, from
        the prediction ``guess``; the images are this frame's."""
        vo = self.vo
        o = vo.opts
        und_kf = vo._undistort(px_kf)
        parallax = median(np.linalg.norm(und_cur - und_kf, axis=1))
        m = Motion(guess, np.zeros(len(px_cur), dtype=bool), False)
        m_prior = None
        if parallax >= o.essential_min_parallax_px:
            if o.essential_prior_gate_px > 0 and vo.T_step is not None:
                # The constant-velocity prediction usually explains the tracks: then no RANSAC.
                m_prior = essential_from_prior(
                    und_kf,
                    und_cur,
                    vo.K,
                    X_kf,
                    guess,
                    gate_px=o.essential_prior_gate_px,
                    threshold_px=o.essential_threshold_px,
                    min_fraction=o.essential_prior_min_fraction,
                    min_inliers=o.min_inliers,
                    iterations=o.essential_prior_iterations,
                )
            vo.path_counts["essential-prior" if m_prior is not None else "essential-ransac"] += 1
            m = (
                m_prior
                if m_prior is not None
                else essential_metric(
                    und_kf,
                    und_cur,
                    vo.K,
                    X_kf,
                    threshold_px=o.essential_threshold_px,
                    min_inliers=o.min_inliers,
                    cheirality=o.essential_cheirality,
                    agree_px=2.0 * o.reproj_px,
                )
            )
        if m.ok:
            # With little parallax or a mostly planar scene (the floor) the 5-point RANSAC
            # can settle on a wrong motion that a few points satisfy. The keyframe's depth
            # tells: the right motion (with its metric scale) also reprojects the 3D points
            # of most tracks, which passed the forward-backward check. The points that
            # reproject are the inliers (depth edges and holes, invisible to the epipolar
            # test, drop out here).
            agree = vo._reproj_err2(m.T_cur_ref, X_kf, und_cur) < (2.0 * o.reproj_px) ** 2
            if np.count_nonzero(agree) < max(o.min_inliers, 0.5 * len(px_cur)):
                m = Motion(guess, np.zeros(len(px_cur), dtype=bool), False)
            else:
                # Least squares on the reprojection of those points from the 5-point motion
                # (as PnP's final fit; Gauss-Newton, converged), inliers re-selected, before
                # the polish below. Needed after the prior-guided path too: at 1-5 cm
                # baselines the epipolar geometry pins the translation direction only to a
                # few degrees, and the depth polish alone (4 Huber steps) kept that error
                # (ATE 0.015-0.34 m).
                T_lm = refine_pose(
                    m.T_cur_ref, X_kf[agree], und_cur[agree], vo.K, huber_px=_LEAST_SQUARES_PX, iterations=20
                )
                mask = agree & (vo._reproj_err2(T_lm, X_kf, und_cur) < o.reproj_px**2)
                m = (
                    Motion(T_lm, mask, True)
                    if np.count_nonzero(mask) >= o.min_inliers
                    else Motion(m.T_cur_ref, agree, True)
                )
        if not m.ok and o.essential_pnp_prior and o.refine_with_depth and vo.T_step is not None:
            m_pp = vo._pnp_from_prior(X_kf, px_cur, und_cur, guess, depth_m, pyr, right_gray)
            if m_pp is not None:
                vo.path_counts["pnp-prior"] += 1
                return m_pp
        if not m.ok:
            vo.path_counts["pnp"] += 1
            m = pnp(
                X_kf,
                und_cur,
                vo.K,
                method=o.pnp_method,
                reproj_px=o.reproj_px,
                min_inliers=o.min_inliers,
                guess_T_cur_ref=guess,
                ransac_kernel=o.pnp_kernel,
            )
        return vo._polish(m, X_kf, px_cur, und_cur, depth_m, pyr, right_gray)


class KabschEstimator:
    """``rgbd-kabsch``: 3D-3D Kabsch on the depth of both frames."""

    def __init__(self, vo: VisualOdometry) -> None:
        self.vo = vo

    def estimate(
        self,
        X_kf: F64,
        px_kf: F32,
        px_cur: F32,
        und_cur: F64,
        depth_m: F32 | None,
        guess: F64,
        right_pyr: npt.NDArray[np.uint8] | None,
        pyr: npt.NDArray[np.uint8],
        right_gray: npt.NDArray[np.uint8] | None,
    ) -> Motion:
        """The motion ``T_cur_kf`` of the keyframe points ``X_kf`` (keyframe frame, m) seen at
        ``px_kf`` in the keyframe and tracked to ``px_cur`` (``und_cur`` undistorted) now, from
        the prediction ``guess``; the images are this frame's."""
        vo = self.vo
        o = vo.opts
        assert depth_m is not None
        z = vo._depth_at(depth_m, px_cur)
        ok = np.isfinite(z)
        X_cur = vo._backproject(und_cur, np.where(ok, z, 1.0))
        idx = np.flatnonzero(ok)
        all_ok = len(idx) == len(ok)  # usual: no copies of the pairs
        X_ref = X_kf if all_ok else X_kf[idx]
        X_cur = X_cur if all_ok else X_cur[idx]
        # Kinect-like depth noise grows with z^2: threshold scaled by the mean squared depth.
        zz = float(np.mean(X_ref[:, 2] ** 2)) if len(idx) else 1.0
        thr_m = o.kabsch_threshold_m * max(1.0, zz)
        m_rigid = None
        if o.kabsch_prior_gate > 0 and vo.T_step is not None:
            # The constant-velocity prediction usually explains the 3D-3D pairs: then no RANSAC.
            m_rigid = rigid_from_prior(
                X_ref,
                X_cur,
                guess,
                threshold_m=thr_m,
                gate_m=o.kabsch_prior_gate * thr_m,
                min_fraction=o.kabsch_prior_min_fraction,
                min_inliers=o.min_inliers,
            )
            vo.path_counts["kabsch-prior" if m_rigid is not None else "kabsch-ransac"] += 1
        m = (
            m_rigid
            if m_rigid is not None
            else ransac_rigid(
                X_ref,
                X_cur,
                threshold_m=thr_m,
                min_inliers=o.min_inliers,
                rng=vo.rng,
                first_batch=o.kabsch_first_batch,
            )
        )
        mask = np.zeros(len(px_cur), dtype=bool)
        mask[idx] = m.inliers
        # The rigid fit weighs every point's depth noise (both frames) equally; polish it
        # like PnP (reprojection plus this frame's depth), which also keeps the depth
        # measurements for fusion: the per-step error fell 23-55 % on every sequence.
        m = Motion(m.T_cur_ref, mask, m.ok)
        if not o.kabsch_polish:
            return m
        return vo._polish(m, X_kf, px_cur, und_cur, depth_m, pyr, right_gray, z)


class PnpEstimator:
    """``stereo`` and ``rgbd-pnp``: PnP on the keyframe's 3D points."""

    def __init__(self, vo: VisualOdometry) -> None:
        self.vo = vo

    def estimate(
        self,
        X_kf: F64,
        px_kf: F32,
        px_cur: F32,
        und_cur: F64,
        depth_m: F32 | None,
        guess: F64,
        right_pyr: npt.NDArray[np.uint8] | None,
        pyr: npt.NDArray[np.uint8],
        right_gray: npt.NDArray[np.uint8] | None,
    ) -> Motion:
        """The motion ``T_cur_kf`` of the keyframe points ``X_kf`` (keyframe frame, m) seen at
        ``px_kf`` in the keyframe and tracked to ``px_cur`` (``und_cur`` undistorted) now, from
        the prediction ``guess``; the images are this frame's."""
        vo = self.vo
        o = vo.opts
        sel = np.ones(len(px_cur), dtype=bool)
        if vo.method is Method.STEREO and o.inliers == "rigidity" and right_pyr is not None:
            init = (vo.rig.fx * vo.rig.baseline_m / np.maximum(X_kf[:, 2], 1e-3)).astype(np.float32)  # type: ignore[union-attr]
            X_cur, ok = vo._points_3d(px_cur, right_pyr, pyr, None, init)
            sel = np.zeros(len(px_cur), dtype=bool)
            idx = np.flatnonzero(ok)
            if len(idx) >= o.min_inliers:
                sel[idx[rigidity_inliers(X_kf[idx], X_cur[idx], tol_m=0.05, rel_tol=0.03)]] = True
            if np.count_nonzero(sel) < o.min_inliers:
                sel[:] = True
        idx = np.flatnonzero(sel)
        if o.pnp_prior_gate_px > 0 and o.refine_with_depth and vo.method is Method.RGBD_PNP:
            # The constant-velocity prediction usually explains the tracks: then no RANSAC.
            m_prior = vo._pnp_from_prior(X_kf[idx], px_cur[idx], und_cur[idx], guess, depth_m, pyr, right_gray)
            if m_prior is not None:
                mask = np.zeros(len(px_cur), dtype=bool)
                mask[idx] = m_prior.inliers
                if vo._meas is not None:
                    vo._meas = (idx[vo._meas[0]], vo._meas[1])
                return Motion(m_prior.T_cur_ref, mask, True)
        m = pnp(
            X_kf[idx],
            und_cur[idx],
            vo.K,
            method=o.pnp_method,
            reproj_px=o.reproj_px,
            min_inliers=o.min_inliers,
            guess_T_cur_ref=guess,
            ransac_kernel=o.pnp_kernel,
        )
        mask = np.zeros(len(px_cur), dtype=bool)
        mask[idx] = m.inliers
        T = m.T_cur_ref
        if m.ok and o.refine_with_depth:
            T = vo._refine(T, X_kf[mask], px_cur[mask], und_cur[mask], depth_m, pyr, right_gray)
            if vo._meas is not None:
                vo._meas = (np.flatnonzero(mask)[vo._meas[0]], vo._meas[1])
        return Motion(T, mask, m.ok)


def keyframe_estimator(vo: VisualOdometry) -> MotionEstimator:
    """The estimator of ``vo``'s method (not ``flow``)."""
    if vo.method is Method.RGBD_ESSENTIAL:
        return EssentialEstimator(vo)
    if vo.method is Method.RGBD_KABSCH:
        return KabschEstimator(vo)
    return PnpEstimator(vo)
