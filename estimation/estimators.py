"""The keyframe methods' motion estimators, one per method behind one interface.

Each takes the front end's tracks of the keyframe's 3D points (:class:`Tracks`, from
``estimation.frontend.FrontEnd``) and returns the keyframe-to-current motion:

* :class:`PnpEstimator` (``stereo``, ``rgbd-pnp``): PnP + RANSAC on the keyframe points (SQPnP
  without RANSAC when the prediction explains the tracks), then the depth polish;
* :class:`EssentialEstimator` (``rgbd-essential``): the essential matrix keyframe to current
  (from the prediction moved onto the tracks, or the 5-point RANSAC), its metric scale and
  cheirality from depth, checked on the keyframe points' reprojection; PnP when the parallax is
  too small;
* :class:`KabschEstimator` (``rgbd-kabsch``): 3D-3D Kabsch on the depth of both frames
  (from the prediction or a vectorised RANSAC), then the polish.

``flow`` has its own estimator (``estimation.flow_vo.FlowEstimator``): it keeps no keyframe.
Each estimator has its options object (``estimation.vo_options``) and reads the shared ones.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt

from estimation.camera_geometry import CameraGeometry
from estimation.essential import essential_from_prior, essential_metric
from estimation.motion import Motion, median
from estimation.pnp import pnp, refine_pose
from estimation.polish import PosePolisher
from estimation.rigid import ransac_rigid, rigid_from_prior, rigidity_inliers
from estimation.rolling_shutter import CameraRate
from estimation.vo_options import EssentialOptions, KabschOptions, Method, PnpOptions, VoOptions

__all__ = [
    "EssentialEstimator",
    "KabschEstimator",
    "MotionEstimator",
    "PnpEstimator",
    "Tracks",
    "keyframe_estimator",
]

F64 = npt.NDArray[np.float64]
F32 = npt.NDArray[np.float32]
U8 = npt.NDArray[np.uint8]

_LEAST_SQUARES_PX = 1e9
"""A Huber threshold no reprojection residual reaches: plain least squares."""

_PRIOR_STEPS = 3
"""Gauss-Newton steps that move a predicted motion onto the tracks before an epipolar prior check."""


@dataclass(frozen=True, slots=True, eq=False)
class Tracks:
    """The keyframe's points tracked into the current frame, with that frame's images.

    Attributes:
        X_kf: (N, 3) the points in the keyframe's camera frame, m.
        px_kf: (N, 2) their pixels in the keyframe.
        und_lens_kf: (N, 2) those pixels with the lens distortion removed (not moved to the
            keyframe's stamp: ``CameraGeometry.at_stamp`` does that with the points' depths).
        px_cur, und_lens_cur, und_cur: (N, 2) their pixels in the current frame (as tracked;
            without the lens distortion; that moved to the frame's stamp).
        guess: the predicted ``T_cur_kf`` (constant velocity).
        has_prior: the prediction comes from a measured motion (not the identity of a start).
        gray, right_gray, depth_m: the current frame's images (right or depth None when absent).
        var_kf: (N,) the points' keyframe disparity variance over one measurement's
            (``frontend.disparity_variance``), or None (``VoOptions.point_uncertainty`` off).
        rate, rate_kf: the camera's rate at the current frame and at the keyframe, for a rolling
            shutter (None: a global shutter or unknown).
        guess_inliers: ``guess`` is a motion measured from these tracks with this many inliers
            (the rolling shutter's second measurement), else None: a prediction.
    """

    X_kf: F64
    px_kf: F32
    und_lens_kf: F64
    px_cur: F32
    und_lens_cur: F64
    und_cur: F64
    guess: F64
    has_prior: bool
    gray: U8
    right_gray: U8 | None
    depth_m: F32 | None
    var_kf: F64 | None = None
    rate: CameraRate | None = None
    rate_kf: CameraRate | None = None
    guess_inliers: int | None = None

    def prior_fraction(self, fraction: float) -> float:
        """The share of the tracks a prior check needs: ``fraction``, or that share of the
        ``guess_inliers`` when the guess is a measured motion (its outliers stay outliers)."""
        if self.guess_inliers is None or not len(self.px_cur):
            return fraction
        return min(fraction, fraction * self.guess_inliers / len(self.px_cur))


class MotionEstimator(Protocol):
    """One keyframe method's motion estimation (see the module docstring)."""

    def estimate(self, t: Tracks) -> Motion:
        """The motion ``T_cur_kf`` of the tracked keyframe points, with its inliers (of ``t``)."""
        ...


class EssentialEstimator:
    """``rgbd-essential``: the essential matrix, metric scale and cheirality from depth."""

    def __init__(
        self, geo: CameraGeometry, polisher: PosePolisher, opts: VoOptions, eo: EssentialOptions, paths: Counter[str]
    ) -> None:
        self.geo, self.polisher, self.opts, self.eo, self.paths = geo, polisher, opts, eo, paths

    def estimate(self, t: Tracks) -> Motion:
        """See :meth:`MotionEstimator.estimate`."""
        geo, o, eo = self.geo, self.opts, self.eo
        X_kf, und_cur, guess = t.X_kf, t.und_cur, t.guess
        und_kf = geo.at_stamp(t.und_lens_kf, t.px_kf, t.rate_kf, t.X_kf[:, 2])
        d = und_cur - und_kf
        parallax = median(np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]))  # np.linalg.norm(d, axis=1)'s sums
        n = len(t.px_cur)
        m = Motion(guess, np.zeros(n, dtype=bool), False)
        m_prior = None
        if parallax >= eo.min_parallax_px:
            if eo.prior_gate_px > 0 and t.has_prior:
                # The constant-velocity prediction usually explains the tracks: then no RANSAC. A
                # prediction (not a measured motion) is first pulled onto the keyframe points'
                # reprojection, robustly at the gate: when the turn rate changes it is off by more
                # than the gate on many tracks (docs/estimation-log.md, twenty-second pass).
                start = (
                    guess
                    if t.guess_inliers is not None
                    else refine_pose(guess, X_kf, und_cur, geo.K, huber_px=eo.prior_gate_px, iterations=_PRIOR_STEPS)
                )
                m_prior = essential_from_prior(
                    und_kf,
                    und_cur,
                    geo.K,
                    X_kf,
                    start,
                    gate_px=eo.prior_gate_px,
                    threshold_px=eo.threshold_px,
                    min_fraction=t.prior_fraction(eo.prior_min_fraction),
                    min_inliers=o.min_inliers,
                    iterations=eo.prior_iterations,
                )
            self.paths["essential-prior" if m_prior is not None else "essential-ransac"] += 1
            m = (
                m_prior
                if m_prior is not None
                else essential_metric(
                    und_kf,
                    und_cur,
                    geo.K,
                    X_kf,
                    threshold_px=eo.threshold_px,
                    min_inliers=o.min_inliers,
                    cheirality=eo.cheirality,
                    agree_px=2.0 * o.reproj_px,
                )
            )
        if m.ok:
            # With little parallax or a mostly planar scene (the floor) the 5-point RANSAC can
            # settle on a wrong motion that a few points satisfy; the right one (with its metric
            # scale) also reprojects the 3D points of most tracks: those are the inliers.
            agree = geo.reproj_err2(m.T_cur_ref, X_kf, und_cur) < (2.0 * o.reproj_px) ** 2
            if np.count_nonzero(agree) < max(o.min_inliers, 0.5 * n):
                m = Motion(guess, np.zeros(n, dtype=bool), False)
            else:
                # Least squares on the reprojection of those points, inliers re-selected, before
                # the polish (the epipolar geometry pins a short translation's direction poorly).
                T_lm = refine_pose(
                    m.T_cur_ref, X_kf[agree], und_cur[agree], geo.K, huber_px=_LEAST_SQUARES_PX, iterations=20
                )
                mask = agree & (geo.reproj_err2(T_lm, X_kf, und_cur) < o.reproj_px**2)
                m = (
                    Motion(T_lm, mask, True)
                    if np.count_nonzero(mask) >= o.min_inliers
                    else Motion(m.T_cur_ref, agree, True)
                )
        if not m.ok and eo.pnp_prior_gate_px > 0 and o.refine_with_depth and t.has_prior:
            m_pp = self.polisher.pnp_from_prior(
                X_kf,
                t.px_cur,
                und_cur,
                guess,
                t.depth_m,
                t.gray,
                t.right_gray,
                eo.pnp_prior_gate_px,
                t.prior_fraction(eo.prior_min_fraction),
                t.var_kf,
                t.rate,
                t.und_lens_cur,
            )
            if m_pp is not None:
                self.paths["pnp-prior"] += 1
                return m_pp
        if not m.ok:
            self.paths["pnp"] += 1
            m = pnp(
                X_kf,
                und_cur,
                geo.K,
                method=o.pnp_method,
                reproj_px=o.reproj_px,
                min_inliers=o.min_inliers,
                guess_T_cur_ref=guess,
                ransac_kernel=o.pnp_kernel,
            )
        return self.polisher.polish(
            m,
            X_kf,
            t.px_cur,
            und_cur,
            t.depth_m,
            t.gray,
            t.right_gray,
            var_kf=t.var_kf,
            rate=t.rate,
            und_lens=t.und_lens_cur,
        )


class KabschEstimator:
    """``rgbd-kabsch``: 3D-3D Kabsch on the depth of both frames."""

    def __init__(
        self,
        geo: CameraGeometry,
        polisher: PosePolisher,
        opts: VoOptions,
        ko: KabschOptions,
        paths: Counter[str],
        rng: np.random.Generator,
    ) -> None:
        self.geo, self.polisher, self.opts, self.ko, self.paths, self.rng = geo, polisher, opts, ko, paths, rng

    def estimate(self, t: Tracks) -> Motion:
        """See :meth:`MotionEstimator.estimate`."""
        geo, o, ko = self.geo, self.opts, self.ko
        assert t.depth_m is not None
        X_cur, ok = geo.depth_points(t.depth_m, t.px_cur, t.rate, t.und_lens_cur)
        z = np.where(ok, X_cur[:, 2], np.nan)
        idx = np.flatnonzero(ok)
        all_ok = len(idx) == len(ok)  # usual: no copies of the pairs
        X_ref = t.X_kf if all_ok else t.X_kf[idx]
        X_cur = X_cur if all_ok else X_cur[idx]
        # Kinect-like depth noise grows with z^2: threshold scaled by the mean squared depth.
        zz = float(np.mean(X_ref[:, 2] ** 2)) if len(idx) else 1.0
        thr_m = ko.threshold_m * max(1.0, zz)
        m_rigid = None
        if ko.prior_gate > 0 and t.has_prior:
            # The constant-velocity prediction usually explains the 3D-3D pairs: then no RANSAC.
            m_rigid = rigid_from_prior(
                X_ref,
                X_cur,
                t.guess,
                threshold_m=thr_m,
                gate_m=ko.prior_gate * thr_m,
                min_fraction=t.prior_fraction(ko.prior_min_fraction),
                min_inliers=o.min_inliers,
            )
            self.paths["kabsch-prior" if m_rigid is not None else "kabsch-ransac"] += 1
        m = (
            m_rigid
            if m_rigid is not None
            else ransac_rigid(
                X_ref, X_cur, threshold_m=thr_m, min_inliers=o.min_inliers, rng=self.rng, first_batch=ko.first_batch
            )
        )
        mask = np.zeros(len(t.px_cur), dtype=bool)
        mask[idx] = m.inliers
        # The rigid fit weighs every point's depth noise (both frames) equally; polish it like
        # PnP (reprojection plus this frame's depth), which also keeps the depth for fusion.
        m = Motion(m.T_cur_ref, mask, m.ok)
        if not ko.polish:
            return m
        return self.polisher.polish(
            m, t.X_kf, t.px_cur, t.und_cur, t.depth_m, t.gray, t.right_gray, z, t.var_kf, t.rate
        )


class PnpEstimator:
    """``stereo`` and ``rgbd-pnp``: PnP on the keyframe's 3D points."""

    def __init__(
        self,
        geo: CameraGeometry,
        polisher: PosePolisher,
        opts: VoOptions,
        po: PnpOptions,
        method: Method,
        paths: Counter[str],
    ) -> None:
        self.geo, self.polisher, self.opts, self.po, self.paths = geo, polisher, opts, po, paths
        self.stereo = method is Method.STEREO

    def _rigid_subset(self, t: Tracks) -> npt.NDArray[np.bool_]:
        """Stereo, ``inliers="rigidity"``: the tracks whose distances to the others kept (max clique)."""
        o, geo = self.opts, self.geo
        n = len(t.px_cur)
        if t.right_gray is None or geo.rig is None:
            return np.ones(n, dtype=bool)
        init = (geo.rig.fx * geo.rig.baseline_m / np.maximum(t.X_kf[:, 2], 1e-3)).astype(np.float32)
        X_cur, ok = geo.points_3d(t.px_cur, t.right_gray, t.gray, None, init, rate=t.rate)
        sel = np.zeros(n, dtype=bool)
        idx = np.flatnonzero(ok)
        if len(idx) >= o.min_inliers:
            sel[idx[rigidity_inliers(t.X_kf[idx], X_cur[idx], tol_m=0.05, rel_tol=0.03)]] = True
        if np.count_nonzero(sel) < o.min_inliers:
            sel[:] = True
        return sel

    def estimate(self, t: Tracks) -> Motion:
        """See :meth:`MotionEstimator.estimate`."""
        o, po, geo = self.opts, self.po, self.geo
        n = len(t.px_cur)
        sel = self._rigid_subset(t) if self.stereo and po.inliers == "rigidity" else np.ones(n, dtype=bool)
        idx = np.flatnonzero(sel)
        # rgbd-pnp tries the prediction from the start (at rest the identity is right); stereo once a
        # motion was measured (its first step, often a large one, goes to RANSAC).
        if po.prior_gate_px > 0 and o.refine_with_depth and (t.has_prior or not self.stereo):
            # The constant-velocity prediction usually explains the tracks: then no RANSAC.
            m_prior = self.polisher.pnp_from_prior(
                t.X_kf[idx],
                t.px_cur[idx],
                t.und_cur[idx],
                t.guess,
                t.depth_m,
                t.gray,
                t.right_gray,
                po.prior_gate_px,
                t.prior_fraction(po.prior_min_fraction),
                None if t.var_kf is None else t.var_kf[idx],
                t.rate,
                t.und_lens_cur[idx],
            )
            if m_prior is not None:
                self.paths["pnp-prior"] += 1
                mask = np.zeros(n, dtype=bool)
                mask[idx] = m_prior.inliers
                self.polisher.remap(idx)
                return Motion(m_prior.T_cur_ref, mask, True)
        self.paths["pnp-ransac"] += 1
        m = pnp(
            t.X_kf[idx],
            t.und_cur[idx],
            geo.K,
            method=o.pnp_method,
            reproj_px=o.reproj_px,
            min_inliers=o.min_inliers,
            guess_T_cur_ref=t.guess,
            ransac_kernel=o.pnp_kernel,
        )
        mask = np.zeros(n, dtype=bool)
        mask[idx] = m.inliers
        T = m.T_cur_ref
        if m.ok and o.refine_with_depth:
            T = self.polisher.refine(
                T,
                t.X_kf[mask],
                t.px_cur[mask],
                t.und_cur[mask],
                t.depth_m,
                t.gray,
                t.right_gray,
                var_kf=None if t.var_kf is None else t.var_kf[mask],
                rate=t.rate,
                und_lens=t.und_lens_cur[mask],
            )
            self.polisher.remap(mask)
        return Motion(T, mask, m.ok)


def keyframe_estimator(
    method: Method,
    geo: CameraGeometry,
    polisher: PosePolisher,
    opts: VoOptions,
    paths: Counter[str],
    rng: np.random.Generator,
) -> MotionEstimator:
    """The estimator of a keyframe method (not ``flow``), with its options from ``opts``.

    Raises:
        EstimationError: ``opts.estimator`` belongs to another method.
    """
    mo = opts.estimator_options(method)
    if isinstance(mo, EssentialOptions):
        return EssentialEstimator(geo, polisher, opts, mo, paths)
    if isinstance(mo, KabschOptions):
        return KabschEstimator(geo, polisher, opts, mo, paths, rng)
    assert isinstance(mo, PnpOptions)
    return PnpEstimator(geo, polisher, opts, mo, method, paths)
