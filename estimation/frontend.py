"""The keyframe methods' shared front end: camera geometry, stereo and depth lookup, tracking,
the keyframe's points (detection, 3D, fusion) and the ORB relocalisation against the keyframe.

:class:`FrontEnd` holds the keyframe map (its points in the keyframe's camera frame, their
pixels there and where they were last tracked); the motion estimators
(``estimation.estimators``) read it through :class:`CameraGeometry` and the tracks handed to
them. Camera frames are OpenCV's; depths and points in metres.
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING

import cv2
import numpy as np
import numpy.typing as npt

from estimation import _kernels
from estimation.features import DescriptorExtractor, Features, GridDetector
from estimation.flow import track_klt
from estimation.matching import match_descriptors, match_stereo_rows
from estimation.motion import Motion, invert
from estimation.pnp import pnp
from estimation.revisit import StoredKeyframe
from estimation.rolling_shutter import CameraRate, RollingShutter
from estimation.stereo import StereoRig, row_disparity, sparse_disparity, triangulate
from estimation.vo_options import VoOptions
from flightkit.errors import EstimationError

if TYPE_CHECKING:
    from flightkit.datasets.base import CameraIntrinsics

__all__ = ["CameraGeometry", "FrontEnd", "disparity_variance"]

logger = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
F32 = npt.NDArray[np.float32]
U8 = npt.NDArray[np.uint8]
Bool = npt.NDArray[np.bool_]


class CameraGeometry:
    """The camera (and stereo rig or depth camera) of one VO run: undistortion, back-projection,
    projection, depth lookup and sparse stereo, with the options' ranges and windows.

    Args:
        intrinsics: the camera of the (left / colour) images.
        baseline_m: stereo baseline (None: no right camera).
        depth_intrinsics: the depth camera, when it differs from ``intrinsics``.
        options: the shared :class:`VoOptions`.
        use_depth_images: 3D points come from depth images (else from stereo).
        depth_registered: the depth images are registered to the colour ones (weighs their depth
            by the sensor's noise model, :func:`depth_weight_baseline_m`).
    """

    def __init__(
        self,
        intrinsics: CameraIntrinsics,
        baseline_m: float | None,
        depth_intrinsics: CameraIntrinsics | None,
        options: VoOptions,
        use_depth_images: bool,
        depth_registered: bool = True,
    ) -> None:
        self.opts = options
        self.intr = intrinsics
        self.K = intrinsics.K
        self.dist = intrinsics.dist_array if intrinsics.is_distorted else None
        self.rig = (
            StereoRig(intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy, float(baseline_m))
            if baseline_m
            else None
        )
        self.depth_intr = depth_intrinsics
        self.use_depth_images = use_depth_images
        self.disparity_offset_px = 0.0
        """Added to every measured disparity before triangulation (``estimation.stereo_offset``)."""
        # A virtual baseline that turns depth-image depth into a disparity for the pose polish;
        # it sets the depth residuals' weight against the reprojection (depth_weight_baseline_m).
        self.virtual_baseline_m = float(baseline_m) if baseline_m else depth_weight_baseline_m(
            intrinsics.fx, depth_registered, options
        )
        self.klt_win = options.klt_win_px or 11
        self.klt_levels = 3 if options.klt_levels is None else options.klt_levels
        self.klt_back_levels = min(options.klt_back_levels, self.klt_levels)
        self.stereo_win = options.stereo_win_px or self.klt_win
        readout_s = intrinsics.readout_s if options.readout_s is None else options.readout_s
        self.shutter = (
            RollingShutter(readout_s, intrinsics.height, intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy)
            if readout_s > 0
            else None
        )
        """The rolling shutter's row timing (None: a global shutter)."""

    def undistort(self, px: F32, rate: CameraRate | None = None, z_m: F64 | None = None) -> F64:
        """Undistorted pixels (float64) of image pixels; with the camera's ``rate`` at that image,
        moved from their rows' times to the image's stamp (a rolling shutter; ``z_m``: their depths
        when known)."""
        if self.dist is None or len(px) == 0:
            und = np.asarray(px, dtype=np.float64)
        else:
            out = cv2.undistortPoints(px.reshape(-1, 1, 2).astype(np.float64), self.K, self.dist, P=self.K)
            und = np.asarray(out.reshape(-1, 2), dtype=np.float64)
        if self.shutter is not None and rate is not None:
            und = self.shutter.pixels(und, px[:, 1], rate, z_m)
        return und

    def depth_points(self, depth_m: F32, px: F32, rate: CameraRate | None = None) -> tuple[F64, Bool]:
        """3D points (camera frame at the image's stamp) of image pixels from the depth image, and
        which have depth; ``rate``: the camera's at that image (a rolling shutter)."""
        z = self.depth_at(depth_m, px)
        ok = np.isfinite(z)
        und = self.undistort(px)
        if self.shutter is None or rate is None or not len(px):
            return self.backproject(und, np.where(ok, z, 1.0)), ok
        # The depth image is read where the point is at the stamp: taken as a global-shutter image
        # at the colour stamp, which measured better than giving it the colour rows' timing
        # (docs/estimation-log.md).
        und_mid = self.shutter.pixels(und, px[:, 1], rate, np.where(ok, z, 1e9))
        z = self.depth_at(depth_m, (px + (und_mid - und)).astype(np.float32))
        ok = np.isfinite(z)
        return self.backproject(und_mid, np.where(ok, z, 1.0)), ok

    def backproject(self, px_undist: F64, z: F64) -> F64:
        """3D points (camera frame) of undistorted pixels at depths ``z``."""
        X = np.empty((len(px_undist), 3))
        X[:, 0] = (px_undist[:, 0] - self.intr.cx) / self.intr.fx * z
        X[:, 1] = (px_undist[:, 1] - self.intr.cy) / self.intr.fy * z
        X[:, 2] = z
        return X

    def depth_at(self, depth_m: F32, px: F32) -> F64:
        """Depth (metres, NaN where unknown or at a depth edge) at image pixels."""
        if len(px) == 0:
            return np.empty(0)
        uv = np.asarray(px, dtype=np.float64)
        di = self.depth_intr
        if di is not None and (di.fx != self.intr.fx or di.cx != self.intr.cx or di.width != self.intr.width):
            uv = np.c_[
                (uv[:, 0] - self.intr.cx) * di.fx / self.intr.fx + di.cx,
                (uv[:, 1] - self.intr.cy) * di.fy / self.intr.fy + di.cy,
            ]
        # The nearest pixel with depth whose 4 neighbours agree with it (no depth edge), in
        # [min_depth_m, max_depth_m]; one compiled loop (estimation._kernels.depth_at).
        z: F64 = _kernels.depth_at(
            np.ascontiguousarray(depth_m, dtype=np.float32),
            np.ascontiguousarray(uv[:, 0]),
            np.ascontiguousarray(uv[:, 1]),
            float(self.opts.min_depth_m),
            float(self.opts.max_depth_m),
        )
        return z

    def points_3d(
        self,
        px: F32,
        right: U8 | None,
        left: U8 | None,
        depth_m: F32 | None,
        init_disp: F32 | float = 0.0,
        max_depth_m: float | None = None,
        rate: CameraRate | None = None,
    ) -> tuple[F64, Bool]:
        """3D points (camera frame) for pixels, from the depth image or the stereo pair, and
        which are valid; ``rate``: the camera's at this image (a rolling shutter).

        Raises:
            EstimationError: neither depth nor a stereo pair.
        """
        if depth_m is not None and self.use_depth_images:
            return self.depth_points(depth_m, px, rate)
        if right is None or left is None or self.rig is None:
            raise EstimationError("this VO method needs depth or a stereo pair in every frame")
        keep_far = self.opts.far_points not in (None, "drop")
        d_min = _FAR_MIN_DISPARITY_PX if keep_far else self.opts.min_disparity_px
        matcher = self.opts.stereo_matcher
        if matcher == "lk":
            disp, ok = self._lk_disparity(left, right, px, init_disp, d_min)
        elif matcher == "row":
            disp, ok = self._row_disparity(left, right, px, d_min)
        else:
            # LK from the guess as before; where the row search found a match that LK missed or
            # contradicts, LK measures it again from that match (one level), as the polish would. A
            # row match below ``d_min`` also overrules LK: the point is then dropped.
            disp, ok = self._lk_disparity(left, right, px, init_disp, d_min)
            d_row, ok_row = self._row_disparity(left, right, px, None, refine_iters=0)
            redo = np.flatnonzero(ok_row & ~(ok & (np.abs(disp - d_row) < 1.0)))
            if len(redo):
                d_lk, ok_lk = self._lk_disparity(left, right, px[redo], d_row[redo], d_min, levels=1)
                agree = ok_lk & (np.abs(d_lk - d_row[redo]) < 1.0)
                disp[redo] = np.where(agree, d_lk, d_row[redo])
                ok[redo] = disp[redo] >= d_min
        zmax = self.max_stereo_depth_m() if max_depth_m is None else max_depth_m
        if keep_far:
            zmax = max(zmax, self.rig.fx * self.rig.baseline_m / _FAR_MIN_DISPARITY_PX)
        X, ok2 = triangulate(px, disp + np.float32(self.disparity_offset_px), self.rig, self.opts.min_depth_m, zmax)
        if self.shutter is not None and rate is not None and len(X):
            X = self.shutter.points(X, px[:, 1], rate)
        return X, ok & ok2

    def _row_disparity(
        self, left: U8, right: U8, px: F32, d_min: float | None, refine_iters: int = 3
    ) -> tuple[F32, Bool]:
        """Disparities by the row search (``row_disparity``) from just below zero to the rig's largest,
        kept from ``d_min`` (None: all): a match just below ``d_min`` is not replaced by a false one in
        range."""
        disp, ok = row_disparity(
            left,
            right,
            px,
            -_ROW_SEARCH_BELOW_PX,
            self.max_disparity_px(),
            win_px=self.stereo_win,
            refine_iters=refine_iters,
        )
        if d_min is not None:
            ok &= disp >= d_min
        return disp, ok

    def _lk_disparity(
        self, left: U8, right: U8, px: F32, init_disp: F32 | float, d_min: float, levels: int | None = None
    ) -> tuple[F32, Bool]:
        """Disparities by LK from ``init_disp`` into the right image, row-checked (``sparse_disparity``;
        ``levels``: pyramid levels, None: the tracking's)."""
        return sparse_disparity(
            left,
            right,
            np.ascontiguousarray(px),
            init_disp,
            fb_max_px=self.opts.fb_max_px if self.opts.stereo_fb_check else None,
            win_px=self.stereo_win,
            levels=self.klt_levels if levels is None else levels,
            min_disparity_px=d_min,
        )

    def max_disparity_px(self) -> float:
        """The largest disparity a stereo search looks at, px: that of ``min_depth_m``, at most the
        image width."""
        assert self.rig is not None
        return min(self.rig.fx * self.rig.baseline_m / self.opts.min_depth_m, float(self.intr.width))

    def max_stereo_depth_m(self) -> float:
        """The farthest stereo depth used, m."""
        b = self.rig.baseline_m if self.rig is not None else 0.0
        return min(self.opts.max_depth_m, self.opts.max_depth_baselines * b) if b > 0 else self.opts.max_depth_m

    def near_depth_m(self) -> float:
        """The farthest stereo depth with a full say in the translation, m (the depth cap and the
        minimum disparity; infinite without a stereo rig)."""
        if self.rig is None:
            return math.inf
        d_min = self.opts.min_disparity_px
        z_disp = self.rig.fx * self.rig.baseline_m / d_min if d_min > 0 else math.inf
        return min(self.max_stereo_depth_m(), z_disp)

    def translation_weight(self, z: F64) -> F64 | None:
        """Each stereo point's factor on its say in the translation (``VoOptions.far_points``): 1 up
        to :meth:`near_depth_m`, beyond it 0 (``"rotation"``) or near depth / z (``"weighted"``);
        None when every point has a full say."""
        mode = self.opts.far_points
        if mode in (None, "drop") or self.rig is None:
            return None
        z_near = self.near_depth_m()
        if mode == "rotation":
            return np.where(z <= z_near, 1.0, 0.0)
        w: F64 = np.minimum(1.0, z_near / np.maximum(z, 1e-9))
        return w

    def reproj_err2(self, T_cur_ref: F64, X_ref: F64, und_cur: F64) -> F64:
        """Squared reprojection error (px^2) of reference points in the current (undistorted)
        image; infinite behind the camera."""
        i = self.intr
        err2: F64 = _kernels.reproj_err2(
            np.ascontiguousarray(X_ref, dtype=np.float64),
            np.ascontiguousarray(T_cur_ref, dtype=np.float64),
            np.ascontiguousarray(und_cur, dtype=np.float64),
            i.fx,
            i.fy,
            i.cx,
            i.cy,
            1e-6,
        )
        return err2

    def project(self, T_cur_kf: F64, X: F64) -> tuple[F32, Bool]:
        """Pixels (float32) of keyframe points under ``T_cur_kf`` and which are in front and
        within ``project_margin_px`` of the image."""
        i = self.intr
        m = float(self.opts.project_margin_px)
        Xk = np.ascontiguousarray(X, dtype=np.float64)
        Tk = np.ascontiguousarray(T_cur_kf, dtype=np.float64)
        if self.dist is None:
            uv_k: F32
            inside_k: Bool
            uv_k, inside_k = _kernels.project(Xk, Tk, i.fx, i.fy, i.cx, i.cy, float(i.width), float(i.height), m)
            return uv_k, inside_k
        Xc = _kernels.transform(Xk, Tk)
        front = Xc[:, 2] > 0.05
        pts, _ = cv2.projectPoints(Xc[:, None, :], np.zeros(3), np.zeros(3), self.K, self.dist)
        u, v = pts[:, 0, 0], pts[:, 0, 1]
        inside = front & (u > -m) & (u < i.width + m) & (v > -m) & (v < i.height + m)
        uv = np.empty((len(u), 2), np.float32)
        uv[:, 0] = u
        uv[:, 1] = v
        return uv, inside


UNREGISTERED_DEPTH_BASELINE_M = 0.1
"""The virtual baseline of depth looked up across two unregistered cameras (no noise model)."""


def depth_weight_baseline_m(fx_px: float, registered: bool, options: VoOptions) -> float:
    """The virtual baseline (m) at which a depth image's disparity ``fx b / z`` has the tracks'
    noise: with ``sigma_z = depth_sigma_per_m2 z^2`` the disparity's noise is
    ``fx b depth_sigma_per_m2`` at every depth, so ``b = track_sigma_px / (fx depth_sigma_per_m2)``.
    Depth not ``registered`` to the colour image (another camera) has lookup errors this model
    lacks: ``UNREGISTERED_DEPTH_BASELINE_M``, as before."""
    if not registered or options.depth_sigma_per_m2 <= 0:
        return UNREGISTERED_DEPTH_BASELINE_M
    return options.track_sigma_px / (fx_px * options.depth_sigma_per_m2)


_FAR_MIN_DISPARITY_PX = 0.5
"""With far points kept: the smallest disparity accepted, px."""

_ROW_SEARCH_BELOW_PX = 2.0
"""The row search starts this far below zero disparity, px (a peak at the range's end is refused)."""


def depth_weight(z: F64) -> F64:
    """Inverse variance of a depth measurement (stereo and Kinect-like: sigma_z ~ z^2)."""
    w: F64 = 1.0 / np.maximum(z, 1e-3) ** 4
    return w


def disparity_variance(w: F64, z: F64) -> F64:
    """Variance of fused points' disparity ``fb / z`` over one measurement's, from their fusion
    weights ``w`` (sums of :func:`depth_weight`) and depths ``z``: 1 for a single measurement."""
    v: F64 = depth_weight(z) / w
    return v


class FrontEnd:
    """Detection, tracking and the keyframe's points for the keyframe methods.

    Args:
        geometry: the run's :class:`CameraGeometry`.
        options: the shared :class:`VoOptions`.
        stereo: 3D points come from the stereo pair (``stereo``); else from depth images.
    """

    def __init__(self, geometry: CameraGeometry, options: VoOptions, stereo: bool) -> None:
        self.geo = geometry
        self.opts = options
        self.stereo = stereo
        w, h = geometry.intr.width, geometry.intr.height
        cell = options.cell_px or max(12, int(math.sqrt(w * h / options.max_features) * 1.1))
        self.grid = GridDetector(
            options.max_features, cell, options.fast_threshold, border_px=options.border_px
        )
        self.orb = DescriptorExtractor("orb", 1000)
        # The keyframe: its points (keyframe camera frame, m), their pixels there, ids, fusion
        # weights, where they were tracked to last, and how many it started with.
        self.kf_X = np.empty((0, 3))
        self.kf_px = np.empty((0, 2), np.float32)
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

    def track(self, prev: U8, cur: U8, guess: F32, trust_px: F64 | float) -> tuple[F32, Bool]:
        """Track the keyframe's points from the previous image into ``cur`` (LK, forward-backward
        checked, started at ``guess``); tracks that leave the image are not ok."""
        return self._lk(prev, cur, self.trk_px, guess, self.geo.klt_back_levels, trust_px)

    def _lk(
        self, prev: U8, cur: U8, px0: F32, guess: F32, back_levels: int, trust_px: F64 | float = 0.0
    ) -> tuple[F32, Bool]:
        """LK from ``px0`` in ``prev`` into ``cur``, started at ``guess``, with the front end's window,
        levels and forward-backward check; tracks that end outside ``cur`` are not ok."""
        g, o = self.geo, self.opts
        px, ok = track_klt(
            prev,
            cur,
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

    def keep(self, keep: Bool, px: F32) -> None:
        """Keep only the tracks ``keep`` (their current pixels ``px``)."""
        self.kf_X, self.kf_px, self.kf_ids = self.kf_X[keep], self.kf_px[keep], self.kf_ids[keep]
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
        self.trk_px = self.kf_px.copy()
        self.kf_n0 = len(self.kf_X)
        self.T_world_kf = T_world_cam.copy()
        self.kf_gray = gray
        self.kf_right = right_gray
        self.kf_depth = depth_m
        self.kf_rate = rate
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
            ransac_kernel="ap3p",
        )
        if not check.ok or np.count_nonzero(check.inliers) < need:
            return False
        ok[:] = False
        ok[sel[check.inliers]] = True
        self.kf_X, self.kf_px, self.kf_ids, self.kf_w = kf.X[ok], kf.px[ok], kf.ids[ok], kf.w[ok]
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
        T_kf_cur = invert(T_cur_kf)
        X_new = X_cur @ T_kf_cur[:3, :3].T + T_kf_cur[:3, 3]
        w_new = depth_weight(X_cur[:, 2])
        w_old = self.kf_w[gidx]
        wsum = w_old + w_new
        self.kf_X[gidx] = (self.kf_X[gidx] * w_old[:, None] + X_new * w_new[:, None]) / wsum[:, None]
        self.kf_w[gidx] = wsum

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

    def orb_fallback(self, gray: U8, guess: F64, rate: CameraRate | None = None) -> Motion | None:
        """The keyframe-to-current motion from ORB matches against the keyframe (when tracking
        failed), or None; ``rate``: the camera's predicted rate at ``gray``."""
        f_kf, X_kf, ok_kf = self._keyframe_orb()
        f_cur = self.orb.extract(gray)
        ia, ib = match_descriptors(f_kf, f_cur, ratio=0.8, mutual=True)
        logger.debug("ORB fallback: %d matches, %d with 3D", len(ia), int(np.count_nonzero(ok_kf[ia])))
        keep = ok_kf[ia]
        ia, ib = ia[keep], ib[keep]
        o = self.opts
        if len(ia) < o.min_inliers:
            return None
        m = pnp(
            X_kf[ia],
            self.geo.undistort(f_cur.pts_px[ib], rate),
            self.geo.K,
            method=o.pnp_method,
            reproj_px=o.reproj_px * 1.5,
            min_inliers=o.min_inliers,
            guess_T_cur_ref=guess,
            ransac_kernel=o.pnp_kernel,
        )
        return m if m.ok else None
