"""The keyframe methods' shared front end: tracking, the keyframe's points (detection, 3D from
``estimation.camera_geometry``, fusion) and the ORB relocalisation against the keyframe.

:class:`FrontEnd` holds the keyframe map (its points in the keyframe's camera frame, their
pixels there and where they were last tracked); the motion estimators
(``estimation.estimators``) read it through the camera geometry and the tracks handed to
them. Camera frames are OpenCV's; depths and points in metres.
"""

from __future__ import annotations

import logging
import math
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from estimation._kernels import fuse_points
from estimation.camera_geometry import CameraGeometry, depth_weight
from estimation.exposure import Integral, exposure_gain, integral, match_exposure
from estimation.features import DescriptorExtractor, Features, GridDetector, occupied_cells
from estimation.flow import track_klt
from estimation.matching import match_descriptors, match_stereo_rows
from estimation.motion import Motion, invert
from estimation.pnp import pnp
from estimation.revisit import StoredKeyframe
from estimation.rolling_shutter import CameraRate
from estimation.vo_options import VoOptions

__all__ = ["FallbackMatch", "FrontEnd", "grid_detector"]

logger = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
F32 = npt.NDArray[np.float32]
U8 = npt.NDArray[np.uint8]
Bool = npt.NDArray[np.bool_]


def grid_detector(geometry: CameraGeometry, options: VoOptions, score: str = "fast") -> GridDetector:
    """The grid corner detector of ``options`` (``max_features``, ``cell_px``: automatic from the
    image size, ``fast_threshold``, ``border_px``) for the camera of ``geometry``; ``score``:
    :class:`GridDetector`'s."""
    w, h = geometry.intr.width, geometry.intr.height
    cell = options.cell_px or max(12, int(math.sqrt(w * h / options.max_features) * 1.1))
    return GridDetector(options.max_features, cell, options.fast_threshold, border_px=options.border_px, score=score)


class FallbackMatch(NamedTuple):
    """The ORB fallback's result (:meth:`FrontEnd.orb_fallback`): the motion, its inliers over the
    matches, and the matches (keyframe points, current pixels, those pixels undistorted)."""

    motion: Motion
    X_kf: F64
    px_cur: F32
    und_cur: F64


class FrontEnd:
    """Detection, tracking and the keyframe's points for the keyframe methods.

    ``kf_und_lens`` holds the keyframe pixels ``kf_px`` with the lens distortion removed
    (``CameraGeometry.undistort`` without a rate), computed once per keyframe for the
    estimators, which move them to the keyframe's stamp (``CameraGeometry.at_stamp``).

    Args:
        geometry: the run's :class:`CameraGeometry`.
        options: the shared :class:`VoOptions`.
        stereo: 3D points come from the stereo pair (``stereo``); else from depth images.
    """

    def __init__(self, geometry: CameraGeometry, options: VoOptions, stereo: bool) -> None:
        self.geo = geometry
        self.opts = options
        self.stereo = stereo
        self.grid = grid_detector(geometry, options)
        self.orb = DescriptorExtractor("orb", 1000)
        # The keyframe: its points (keyframe camera frame, m), their pixels there, ids, fusion
        # weights, where they were tracked to last, and how many it started with.
        self.kf_X = np.empty((0, 3))
        self.kf_px = np.empty((0, 2), np.float32)
        self.kf_und_lens = np.empty((0, 2))
        self.kf_ids = np.empty(0, np.int64)
        self.kf_w = np.empty(0)
        self.trk_px = np.empty((0, 2), np.float32)
        self.kf_n0 = 0
        self.T_world_kf = np.eye(4)
        self.kf_gray: U8 | None = None
        self.kf_right: U8 | None = None
        self.kf_depth: F32 | None = None
        self.kf_rate: CameraRate | None = None
        self.next_id = 0
        self._kf_orb: tuple[Features, F64, Bool] | None = None
        self._integral: tuple[U8, Integral] | None = None
        """The last tracked image and its integral (exposure compensation)."""

    def track(self, prev: U8, cur: U8, guess: F32, trust_px: F64 | float) -> tuple[F32, Bool]:
        """Track the keyframe's points from the previous image into ``cur`` (LK, forward-backward
        checked, started at ``guess``, after undoing an exposure change: ``estimation.exposure``);
        tracks that leave the image are not ok."""
        if self.opts.exposure_compensation:
            cached = self._integral
            i_prev = cached[1] if (cached is not None and cached[0] is prev) else integral(prev)
            i_cur = integral(cur)
            self._integral = (cur, i_cur)  # the next frame's previous image
            gain = exposure_gain(i_prev, i_cur, self.trk_px, guess, self.grid.cell_px)
            prev, cur = match_exposure(prev, cur, gain)
        return self._lk(prev, cur, self.trk_px, guess, self.geo.klt_back_levels, trust_px)

    def _lk(
        self, prev: U8, cur: U8, px0: F32, guess: F32, back_levels: int, trust_px: F64 | float = 0.0
    ) -> tuple[F32, Bool]:
        """LK from ``px0`` in ``prev`` into ``cur``, started at ``guess``, with the front end's window,
        levels and forward-backward check; tracks that end outside ``cur`` are not ok."""
        g, o = self.geo, self.opts
        px, ok = track_klt(
            g.pyramids(prev),
            g.pyramids(cur),
            px0,
            o.fb_max_px,
            g.klt_win,
            g.klt_levels,
            guess=guess,
            back_levels=back_levels,
            max_iters=o.klt_iters,
            trust_guess_px=trust_px,
        )
        h, w = cur.shape
        ok &= (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        return px, ok

    def covered_fraction(self) -> float:
        """The image area the tracked points cover now over the area they covered in the keyframe,
        counted on cells of 2x2 detection cells (about four corners each): below 1 when the scene
        recedes and its points bunch together (the camera moving back from it)."""
        cell = 2 * self.grid.cell_px
        then = occupied_cells(self.kf_px, cell)
        return occupied_cells(self.trk_px, cell) / then if then else 1.0

    def keep(self, keep: Bool, px: F32) -> None:
        """Keep only the tracks ``keep`` (their current pixels ``px``)."""
        self.kf_X, self.kf_px, self.kf_ids = self.kf_X[keep], self.kf_px[keep], self.kf_ids[keep]
        self.kf_und_lens = self.kf_und_lens[keep]
        self.kf_w = self.kf_w[keep]
        self.trk_px = np.ascontiguousarray(px[keep])

    def make_keyframe(
        self,
        gray: U8,
        right_gray: U8 | None,
        depth_m: F32 | None,
        T_world_cam: F64,
        keep_X_cur: F64 | None,
        remeasure: bool = True,
        rate: CameraRate | None = None,
    ) -> None:
        """Turn the current frame (at ``T_world_cam``) into the keyframe: keep the tracked points
        (``trk_px``, with their fused 3D estimate ``keep_X_cur`` in this frame), add grid corners,
        measure their 3D points.

        With ``remeasure`` the kept points are measured again here and fused, else (this frame's
        measurement was already fused) only the new corners are measured. ``rate``: the camera's
        at this frame (a rolling shutter), kept as ``kf_rate``.
        """
        keep_px, keep_ids, keep_w = self.trk_px, self.kf_ids, self.kf_w
        n_keep = len(keep_px) if keep_X_cur is not None else 0
        if n_keep == 0:
            keep_px, keep_ids = np.empty((0, 2), np.float32), np.empty(0, np.int64)
        new_px = self.grid.detect(gray, existing=keep_px, budget=self.opts.max_features - n_keep)
        ids_new = np.arange(self.next_id, self.next_id + len(new_px))
        self.next_id += len(new_px)
        fb_init = 0.0
        d_keep = np.zeros(0, np.float32)
        rig = self.geo.rig
        if self.stereo and rig is not None and keep_X_cur is not None and n_keep:
            fb = rig.fx * rig.baseline_m
            d_keep = (fb / np.maximum(keep_X_cur[:, 2], 1e-3)).astype(np.float32)
            fb_init = float(np.median(d_keep))
        if remeasure or keep_X_cur is None or n_keep == 0:
            px_m = np.concatenate([keep_px.astype(np.float32), new_px]) if n_keep else new_px
            init: F32 | float = (
                np.concatenate([d_keep, np.full(len(new_px), fb_init, np.float32)]) if len(d_keep) else fb_init
            )
            X_m, ok_m = self.geo.points_3d(px_m, right_gray, gray, depth_m, init, rate=rate)
            X_k, ok_k = X_m[:n_keep], ok_m[:n_keep]
            X_n, ok_n = X_m[n_keep:], ok_m[n_keep:]
        else:
            X_n, ok_n = self.geo.points_3d(new_px, right_gray, gray, depth_m, fb_init, rate=rate)
            X_k, ok_k = np.empty((n_keep, 3)), np.zeros(n_keep, dtype=bool)
        # Kept points: fuse the fresh measurement (if any) with the carried estimate.
        if keep_X_cur is not None and n_keep:
            w_new = np.where(ok_k, depth_weight(np.where(ok_k, X_k[:, 2], 1.0)), 0.0)
            wsum = keep_w + w_new
            X_keep = (keep_X_cur * keep_w[:, None] + np.where(ok_k[:, None], X_k, 0.0) * w_new[:, None]) / wsum[:, None]
            ok_keep = np.isfinite(X_keep).all(axis=1) & (X_keep[:, 2] > self.opts.min_depth_m)
        else:
            X_keep, wsum, ok_keep = np.empty((0, 3)), np.empty(0), np.zeros(0, dtype=bool)
        w_n = depth_weight(np.where(ok_n, X_n[:, 2], 1.0))
        self.kf_X = np.concatenate([X_keep[ok_keep], X_n[ok_n]])
        self.kf_w = np.concatenate([wsum[ok_keep], w_n[ok_n]])
        self.kf_px = np.ascontiguousarray(
            np.concatenate([keep_px[ok_keep].astype(np.float32), new_px[ok_n]]), dtype=np.float32
        )
        self.kf_ids = np.concatenate([keep_ids[ok_keep], ids_new[ok_n]]).astype(np.int64)
        self.kf_und_lens = self.geo.undistort(self.kf_px)
        self.trk_px = self.kf_px.copy()
        self.kf_n0 = len(self.kf_X)
        self.T_world_kf = T_world_cam.copy()
        self.kf_gray = gray
        self.kf_right = right_gray
        self.kf_depth = depth_m
        self.kf_rate = rate
        self._kf_orb = None

    def set_keyframe_rate(self, rate: CameraRate) -> None:
        """Give a keyframe made without a known rate (the first) the camera's rate then, and move
        its points to its stamp with it (a rolling shutter; measured again from its depth image)."""
        g = self.geo
        if g.shutter is None or self.kf_rate is not None or not len(self.kf_X):
            return
        self.kf_rate = rate
        if self.kf_depth is not None and g.use_depth_images:
            X, ok = g.depth_points(self.kf_depth, self.kf_px, rate, self.kf_und_lens)
            self.kf_X = np.where(ok[:, None], X, self.kf_X)
        else:
            self.kf_X = g.shutter.points(self.kf_X, self.kf_px[:, 1], rate)
        self._kf_orb = None

    def snapshot(self) -> StoredKeyframe:
        """The keyframe as it stands (copies of its point arrays), for a :class:`KeyframeStore`."""
        assert self.kf_gray is not None, "snapshot of a front end that has no keyframe yet"
        return StoredKeyframe(
            self.T_world_kf.copy(),
            self.kf_X.copy(),
            self.kf_px.copy(),
            self.kf_ids.copy(),
            self.kf_w.copy(),
            self.kf_gray,
            self.kf_right,
            self.kf_depth,
            self.kf_rate,
        )

    def restore(self, kf: StoredKeyframe, gray: U8, T_world_cam: F64, rate: CameraRate | None = None) -> bool:
        """Return to a kept keyframe: track its points from its image into ``gray`` (LK from their
        projection at ``T_world_cam``, forward-backward checked) and make it the keyframe if at
        least the keyframe policy's share and count of them are tracked and agree on one pose
        (the others are dropped); else change nothing. ``rate``: the camera's at ``gray``."""
        g = self.geo
        T_cur_kf = invert(T_world_cam) @ kf.T_world_kf
        guess, vis = g.project(T_cur_kf, kf.X)
        px, ok = self._lk(kf.gray, gray, kf.px, np.where(vis[:, None], guess, kf.px), g.klt_levels)
        ok &= vis
        policy = self.opts.keyframes
        need = max(policy.min_tracked, policy.min_tracked_fraction * len(kf.X))
        if np.count_nonzero(ok) < need:
            return False
        # The tracks must agree on one pose (PnP RANSAC from the kept points): LK from another
        # viewpoint also lands on look-alike texture, and a return measured from those jumps.
        sel = np.flatnonzero(ok)
        check = pnp(
            kf.X[sel],
            g.undistort(px[sel], rate),
            g.K,
            method="iterative",
            reproj_px=self.opts.reproj_px,
            guess_T_cur_ref=T_cur_kf,
            ransac_kernel=self.opts.pnp_kernel,
        )
        if not check.ok or np.count_nonzero(check.inliers) < need:
            return False
        ok[:] = False
        ok[sel[check.inliers]] = True
        self.kf_X, self.kf_px, self.kf_ids, self.kf_w = kf.X[ok], kf.px[ok], kf.ids[ok], kf.w[ok]
        self.kf_und_lens = g.undistort(self.kf_px)
        self.trk_px = np.ascontiguousarray(px[ok])
        self.kf_n0 = len(kf.X)
        self.T_world_kf = kf.T_world_kf.copy()
        self.kf_gray, self.kf_right, self.kf_depth, self.kf_rate = kf.gray, kf.right, kf.depth, kf.rate
        self._kf_orb = None
        return True

    def fuse(self, gidx: npt.NDArray[np.intp], X_cur: F64, T_cur_kf: F64) -> None:
        """Fuse current-frame 3D measurements of keyframe points into ``kf_X`` (inverse variance)."""
        if not len(gidx):
            return
        if not (self.kf_X.flags.c_contiguous and self.kf_w.flags.c_contiguous):  # (updated in place)
            self.kf_X, self.kf_w = np.ascontiguousarray(self.kf_X), np.ascontiguousarray(self.kf_w)
        X_cur = np.ascontiguousarray(X_cur, dtype=np.float64)
        fuse_points(self.kf_X, self.kf_w, gidx, X_cur, depth_weight(X_cur[:, 2]), invert(T_cur_kf))

    def _keyframe_orb(self) -> tuple[Features, F64, Bool]:
        """ORB features of the keyframe with their 3D points (computed on first need)."""
        if self._kf_orb is None:
            assert self.kf_gray is not None
            g = self.geo
            f = self.orb.extract(self.kf_gray)
            if self.stereo:
                assert self.kf_right is not None and g.rig is not None
                # Row-consistent ORB matches give disparities; LK along the rows (started at
                # the ORB disparity, or the keyframe's median) fills in the rest.
                fr = self.orb.extract(self.kf_right)
                il, _, disp_orb = match_stereo_rows(f, fr, max_disparity_px=g.intr.width / 2)
                init = np.full(len(f), np.nan, np.float32)
                init[il] = disp_orb
                fb = g.rig.fx * g.rig.baseline_m
                med = float(np.median(fb / self.kf_X[:, 2])) if len(self.kf_X) else 0.0
                init = np.where(np.isfinite(init), init, med).astype(np.float32)
                # Far points too: recovering the pose matters more here than their depth noise.
                X, ok = g.points_3d(
                    f.pts_px, self.kf_right, self.kf_gray, None, init, self.opts.max_depth_m, rate=self.kf_rate
                )
            else:
                assert self.kf_depth is not None
                X, ok = g.depth_points(self.kf_depth, f.pts_px, self.kf_rate)
            self._kf_orb = (f, X, ok)
        return self._kf_orb

    @property
    def fallback_reproj_px(self) -> float:
        """The ORB fallback's inlier tolerance, px: 1.5x the tracked steps' (ORB corners on the
        blurred frames where tracking fails are less precise)."""
        return 1.5 * self.opts.reproj_px

    def orb_fallback(self, gray: U8, guess: F64, rate: CameraRate | None = None) -> FallbackMatch | None:
        """The keyframe-to-current motion from ORB matches against the keyframe (when tracking
        failed), with the matches for the caller's polish, or None; ``rate``: the camera's
        predicted rate at ``gray``."""
        f_kf, X_kf, ok_kf = self._keyframe_orb()
        f_cur = self.orb.extract(gray)
        ia, ib = match_descriptors(f_kf, f_cur, ratio=0.8, mutual=True)
        logger.debug("ORB fallback: %d matches, %d with 3D", len(ia), int(np.count_nonzero(ok_kf[ia])))
        keep = ok_kf[ia]
        ia, ib = ia[keep], ib[keep]
        o = self.opts
        if len(ia) < o.min_inliers:
            return None
        X, px = X_kf[ia], np.ascontiguousarray(f_cur.pts_px[ib], dtype=np.float32)
        und = self.geo.undistort(px, rate)
        m = pnp(
            X,
            und,
            self.geo.K,
            method=o.pnp_method,
            reproj_px=self.fallback_reproj_px,
            min_inliers=o.min_inliers,
            guess_T_cur_ref=guess,
            ransac_kernel=o.pnp_kernel,
        )
        return FallbackMatch(m, X, px, und) if m.ok else None
