"""The pose polish every keyframe estimator shares: a pose refined on the reprojection of the
keyframe's points plus this frame's own depth (stereo disparity or depth image), and PnP
from the constant-velocity prediction without RANSAC.

:class:`PosePolisher` keeps the depth it measured on the last polished pose (``meas``: which
tracks, their 3D points in the current camera) for the front end to fuse.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from estimation.camera_geometry import CameraGeometry
from estimation.motion import Motion, make_T
from estimation.pnp import refine_pose
from estimation.rolling_shutter import CameraRate
from estimation.stereo import sparse_disparity
from estimation.vo_options import VoOptions

__all__ = ["PosePolisher"]

F64 = npt.NDArray[np.float64]
F32 = npt.NDArray[np.float32]
U8 = npt.NDArray[np.uint8]
Meas = tuple[npt.NDArray[np.intp], F64]


class PosePolisher:
    """Pose refinement on reprojection plus the current frame's depth, for one VO run.

    Args:
        geometry: the run's camera (:class:`~estimation.camera_geometry.CameraGeometry`).
        options: the shared :class:`VoOptions`.
        stereo: the depth is measured by sparse stereo (else looked up in depth images).
    """

    def __init__(self, geometry: CameraGeometry, options: VoOptions, stereo: bool) -> None:
        self.geo = geometry
        self.opts = options
        self.stereo = stereo
        self.meas: Meas | None = None
        """The depth measured by the last polish: track indices (into the polished subset,
        remapped by :meth:`remap`) and their 3D points in the current camera; None if none."""

    def remap(self, subset: npt.NDArray[np.bool_] | npt.NDArray[np.intp]) -> None:
        """Express ``meas``' indices in the caller's tracks, the polished ones being ``subset``
        (a mask or indices of the caller's tracks)."""
        if self.meas is not None:
            idx: npt.NDArray[np.intp] = np.flatnonzero(subset) if subset.dtype == np.bool_ else subset.astype(np.intp)
            self.meas = (idx[self.meas[0]], self.meas[1])

    def pnp_from_prior(
        self,
        X_kf: F64,
        px_cur: F32,
        und_cur: F64,
        guess: F64,
        depth_m: F32 | None,
        gray: U8,
        right_gray: U8 | None,
        gate_px: float,
        min_fraction: float,
        var_kf: F64 | None = None,
        rate: CameraRate | None = None,
        und_lens: F64 | None = None,
    ) -> Motion | None:
        """PnP without RANSAC when the constant-velocity prediction already explains the tracks.

        The tracks within ``gate_px`` of their predicted position are fitted by SQPnP (a global
        solver: its answer does not depend on the prediction); the inliers are the tracks within
        ``reproj_px`` of that pose, which then gets the depth polish (:meth:`refine`). Accepted
        when at least ``min_fraction`` of the tracks pass both the gate and the inlier test;
        else None, and the caller runs RANSAC. (Why not Gauss-Newton from the prediction:
        docs/estimation-log.md.) ``und_lens``: ``px_cur`` without the lens distortion, if known
        (:meth:`refine`).
        """
        o = self.opts
        geo = self.geo
        need = max(o.min_inliers, min_fraction * len(X_kf))
        gate = geo.reproj_err2(guess, X_kf, und_cur) < gate_px**2
        if np.count_nonzero(gate) < need:
            return None
        Xg = np.ascontiguousarray(X_kf[gate])
        ug = np.ascontiguousarray(und_cur[gate])
        ok, rvec, tvec = cv2.solvePnP(Xg, ug, geo.K, None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            return None
        T = make_T(cv2.Rodrigues(rvec)[0], tvec.ravel())
        mask = geo.reproj_err2(T, X_kf, und_cur) < o.reproj_px**2
        if np.count_nonzero(mask) < need:
            return None
        T = self.refine(
            T,
            X_kf[mask],
            px_cur[mask],
            und_cur[mask],
            depth_m,
            gray,
            right_gray,
            var_kf=_subset(var_kf, mask),
            rate=rate,
            und_lens=_subset(und_lens, mask),
        )
        self.remap(mask)
        return Motion(T, mask, True)

    def polish(
        self,
        m: Motion,
        X_kf: F64,
        px_cur: F32,
        und_cur: F64,
        depth_m: F32 | None,
        gray: U8,
        right_gray: U8 | None,
        z_cur: F64 | None = None,
        var_kf: F64 | None = None,
        rate: CameraRate | None = None,
        und_lens: F64 | None = None,
        reproj_px: float | None = None,
    ) -> Motion:
        """The same polish as PnP's for a motion found otherwise (5-point, Kabsch): reprojection
        of the keyframe points plus this frame's depth (``refine_with_depth``), inliers
        re-selected on the result; the depth measurements are kept for fusion. ``z_cur``: the
        depth at ``px_cur`` (at the frame's stamp) when the caller has looked it up already
        (Kabsch); ``rate``: the camera's (a rolling shutter); ``und_lens``: ``px_cur`` without the
        lens distortion, if known (:meth:`refine`); ``reproj_px``: the re-selection's inlier
        tolerance (None: ``VoOptions.reproj_px``)."""
        o = self.opts
        if not (m.ok and o.refine_with_depth):
            return m
        mask = m.inliers.copy()
        T = self.refine(
            m.T_cur_ref,
            X_kf[mask],
            px_cur[mask],
            und_cur[mask],
            depth_m,
            gray,
            right_gray,
            _subset(z_cur, mask),
            _subset(var_kf, mask),
            rate,
            _subset(und_lens, mask),
        )
        tol = o.reproj_px if reproj_px is None else reproj_px
        refined = mask & (self.geo.reproj_err2(T, X_kf, und_cur) < tol**2)
        if np.count_nonzero(refined) < o.min_inliers:
            self.meas = None
            return m
        if self.meas is not None:
            self.remap(mask)
            assert self.meas is not None
            keep = refined[self.meas[0]]
            self.meas = (self.meas[0][keep], self.meas[1][keep])
        return Motion(T, refined, True)

    def refine(
        self,
        T: F64,
        X_kf: F64,
        px: F32,
        und: F64,
        depth_m: F32 | None,
        gray: U8,
        right_gray: U8 | None,
        z: F64 | None = None,
        var_kf: F64 | None = None,
        rate: CameraRate | None = None,
        und_lens: F64 | None = None,
    ) -> F64:
        """Polish a pose with the current frame's own depth (disparity residuals); ``z``: the
        depth at ``px`` (at the frame's stamp) if already looked up; ``var_kf``: the points'
        keyframe disparity variance (``Tracks.var_kf``; None: exact points); ``rate``: the camera's
        (a rolling shutter: the depths are moved to the frame's stamp); ``und_lens``: ``px``
        without the lens distortion, if known (else the depth lookup undistorts them again). Sets
        ``meas``."""
        geo = self.geo
        huber = self.opts.polish_huber_px
        if self.stereo:
            if right_gray is None or geo.rig is None:
                return refine_pose(T, X_kf, und, geo.K, huber_px=huber)
            fb = geo.rig.fx * geo.rig.baseline_m
            off = np.float32(geo.disparity_offset_px)
            z_pred = X_kf @ T[2, :3] + T[2, 3]
            init = (fb / np.maximum(z_pred, 1e-3)).astype(np.float32) - off
            # Only points whose measurement could pass both checks below (far points kept for the
            # rotation predict less than the minimum disparity: no LK for them).
            d_min = self.opts.min_disparity_px
            sel = np.flatnonzero(init > min(d_min - 2.0, d_min / 1.3))
            disp, ok = sparse_disparity(
                geo.pyramids(gray),
                geo.pyramids(right_gray),
                np.ascontiguousarray(px[sel]),
                init[sel],
                fb_max_px=None,
                win_px=geo.stereo_win,
                levels=1,  # the predicted disparity is close: a shallow pyramid is enough
                min_disparity_px=d_min,
            )
            # A disparity far from the prediction is a mismatch, not a measurement.
            ok &= np.abs(disp - init[sel]) < np.maximum(2.0, 0.3 * init[sel])
            d: npt.NDArray[Any] = np.full(len(px), np.nan, np.float32)  # float32, as the disparities
            d[sel] = np.where(ok, disp + off, np.nan)
        elif depth_m is not None:
            fb = geo.intr.fx * geo.virtual_baseline_m
            if z is None:
                X, ok = geo.depth_points(depth_m, px, rate, und_lens)
                z = np.where(ok, X[:, 2], np.nan)
            d = fb / z
        else:
            return refine_pose(T, X_kf, und, geo.K, huber_px=huber)
        good = np.isfinite(d)
        X_meas = geo.backproject(und[good], fb / d[good])
        self.meas = (np.flatnonzero(good), X_meas)
        tw = geo.translation_weight(z_pred) if self.stereo else None
        return refine_pose(T, X_kf, und, geo.K, d, fb, huber_px=huber, translation_weight=tw, point_var=var_kf)


def _subset(a: F64 | None, mask: npt.NDArray[np.bool_]) -> F64 | None:
    """``a[mask]``, or None for None."""
    return None if a is None else a[mask]
