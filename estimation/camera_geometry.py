"""The camera of one VO run (and its stereo rig or depth camera): undistortion, the rolling
shutter's row timing, back-projection, projection, depth lookup and sparse stereo, with the
options' ranges and windows; and the depth measurements' weights. Camera frames are OpenCV's;
depths and points in metres.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import numpy.typing as npt
from numba import njit

from estimation import _kernels, _lens_kernel
from estimation.lk import PyramidCache
from estimation.rolling_shutter import CameraRate, RollingShutter, move_pixels
from estimation.stereo import StereoRig, row_disparity, sparse_disparity, triangulate
from estimation.vo_options import VoOptions
from flightkit.errors import EstimationError

if TYPE_CHECKING:
    from flightkit.datasets.base import CameraIntrinsics

__all__ = [
    "UNREGISTERED_DEPTH_BASELINE_M",
    "CameraGeometry",
    "depth_weight",
    "depth_weight_baseline_m",
    "disparity_variance",
]

F64 = npt.NDArray[np.float64]
F32 = npt.NDArray[np.float32]
U8 = npt.NDArray[np.uint8]
Bool = npt.NDArray[np.bool_]

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
        self._lens = None if self.dist is None else _lens_kernel.coefficients(self.dist)
        """The distortion for the compiled lens kernels (None: none, or terms only OpenCV models)."""
        self.rig = (
            StereoRig(intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy, float(baseline_m))
            if baseline_m
            else None
        )
        self.depth_intr = depth_intrinsics
        i, di = intrinsics, depth_intrinsics
        own = di is not None and (di.fx != i.fx or di.cx != i.cx or di.width != i.width)
        depth_pinhole = (di.fx, di.fy, di.cx, di.cy) if di is not None and own else (1.0, 1.0, 0.0, 0.0)
        depths = (options.min_depth_m, options.max_depth_m)
        self._depth_lookup = (*map(float, (i.fx, i.fy, i.cx, i.cy)), own, *map(float, (*depth_pinhole, *depths)))
        """The depth kernels' camera: the colour pinhole, whether the depth image has one of its own
        (pixels are mapped into it) and its fx, fy, cx, cy, and the depths accepted (m)."""
        self.use_depth_images = use_depth_images
        self.disparity_offset_px = 0.0
        """Added to every measured disparity before triangulation (``estimation.stereo_offset``)."""
        # A virtual baseline that turns depth-image depth into a disparity for the pose polish;
        # it sets the depth residuals' weight against the reprojection (depth_weight_baseline_m).
        self.virtual_baseline_m = (
            float(baseline_m) if baseline_m else depth_weight_baseline_m(intrinsics.fx, depth_registered, options)
        )
        self.klt_win = options.klt_win_px or 11
        self.klt_levels = 3 if options.klt_levels is None else options.klt_levels
        self.klt_back_levels = min(options.klt_back_levels, self.klt_levels)
        self.stereo_win = options.stereo_win_px or self.klt_win
        self.pyramids = PyramidCache(self.klt_levels, max(self.klt_win, self.stereo_win))
        """The LK pyramids of the run's last images (each built once, for tracking and stereo)."""
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
        elif self._lens is not None:
            i = self.intr
            und = _lens_kernel.undistort(np.ascontiguousarray(px), i.fx, i.fy, i.cx, i.cy, self._lens)
        else:
            out = cv2.undistortPoints(px.reshape(-1, 1, 2).astype(np.float64), self.K, self.dist, P=self.K)
            und = np.asarray(out.reshape(-1, 2), dtype=np.float64)
        return self.at_stamp(und, px, rate, z_m)

    def at_stamp(self, und: F64, px: F32, rate: CameraRate | None, z_m: F64 | None = None) -> F64:
        """:meth:`undistort`'s second half: undistorted pixels ``und`` of image pixels ``px`` moved
        from their rows' times to the stamp (unchanged without a shutter or a ``rate``)."""
        if self.shutter is None or rate is None:
            return und
        return self.shutter.pixels(und, px[:, 1], rate, z_m)

    def depth_points(
        self, depth_m: F32, px: F32, rate: CameraRate | None = None, und_lens: F64 | None = None
    ) -> tuple[F64, Bool]:
        """3D points (camera frame at the image's stamp) of image pixels from the depth image, and
        which have depth; ``rate``: the camera's at that image (a rolling shutter); ``und_lens``:
        :meth:`undistort` of ``px`` without a rate, when the caller has it (not recomputed)."""
        und = self.undistort(px) if und_lens is None else und_lens
        sh = self.shutter
        if sh is None or rate is None or not len(px):
            z = self.depth_at(depth_m, px)
            ok = np.isfinite(z)
            return self.backproject(und, np.where(ok, z, 1.0)), ok
        # The depth image is read where the point is at the stamp: taken as a global-shutter image
        # at the colour stamp, which measured better than giving it the colour rows' timing
        # (docs/estimation-log.md). Both lookups, the move and the back-projection: one compiled call.
        X: F64
        ok_s: Bool
        X, ok_s = _depth_points_at_stamp(
            np.ascontiguousarray(depth_m, dtype=np.float32),
            np.ascontiguousarray(px, dtype=np.float32),
            np.ascontiguousarray(und, dtype=np.float64),
            sh.mid_row_px,
            sh.row_s,
            rate.omega_rad_s,
            rate.velocity_m_s,
            self._depth_lookup,
        )
        return X, ok_s

    def backproject(self, px_undist: F64, z: F64) -> F64:
        """3D points (camera frame) of undistorted pixels at depths ``z``."""
        X = np.empty((len(px_undist), 3))
        X[:, 0] = (px_undist[:, 0] - self.intr.cx) / self.intr.fx * z
        X[:, 1] = (px_undist[:, 1] - self.intr.cy) / self.intr.fy * z
        X[:, 2] = z
        return X

    def depth_at(self, depth_m: F32, px: F32) -> F64:
        """Depth (metres, NaN where unknown or at a depth edge) at image pixels: the nearest pixel
        with depth whose 4 neighbours agree with it (no depth edge), in [min_depth_m, max_depth_m]
        (one compiled loop, ``estimation._kernels.depth_at``)."""
        if len(px) == 0:
            return np.empty(0)
        z: F64 = _depth_at_px(
            np.ascontiguousarray(depth_m, dtype=np.float32), np.ascontiguousarray(px), self._depth_lookup
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
            self.pyramids(left),
            self.pyramids(right),
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
        if self._lens is not None:
            uv_l: F32
            inside_l: Bool
            uv_l, inside_l = _lens_kernel.project(
                Xk, Tk, i.fx, i.fy, i.cx, i.cy, self._lens, float(i.width), float(i.height), m
            )
            return uv_l, inside_l
        Xc = _kernels.transform(Xk, Tk)
        front = Xc[:, 2] > 0.05
        pts, _ = cv2.projectPoints(Xc[:, None, :], np.zeros(3), np.zeros(3), self.K, self.dist)
        u, v = pts[:, 0, 0], pts[:, 0, 1]
        inside = front & (u > -m) & (u < i.width + m) & (v > -m) & (v < i.height + m)
        uv = np.empty((len(u), 2), np.float32)
        uv[:, 0] = u
        uv[:, 1] = v
        return uv, inside


@njit(cache=True)
def _depth_at_px(depth: Any, px: Any, lookup: Any) -> F64:
    """:meth:`CameraGeometry.depth_at` of (N, 2) pixels: as float64, mapped into the depth image's
    own pinhole when it has one (``(u - cx) * dfx / fx + dcx``); ``lookup``:
    ``CameraGeometry._depth_lookup``."""
    fx, fy, cx, cy, remap, dfx, dfy, dcx, dcy, min_m, max_m = lookup
    n = px.shape[0]
    u = np.empty(n)
    v = np.empty(n)
    for k in range(n):
        x = np.float64(px[k, 0])
        y = np.float64(px[k, 1])
        u[k] = (x - cx) * dfx / fx + dcx if remap else x
        v[k] = (y - cy) * dfy / fy + dcy if remap else y
    z: F64 = _kernels.depth_at(depth, u, v, min_m, max_m)
    return z


@njit(cache=True)
def _depth_points_at_stamp(
    depth: Any, px: Any, und: Any, mid_row: float, row_s: float, w: Any, v: Any, lookup: Any
) -> tuple[F64, Bool]:
    """:meth:`CameraGeometry.depth_points` with a rolling shutter in one compiled call, bit for bit
    its numpy steps: the depth at the pixels ``px`` (float32), the undistorted pixels ``und`` moved
    to the stamp with it (``move_pixels``), the depth again where the point is at the stamp, the
    back-projection (depth 1 where there is none) and which have depth."""
    fx, fy, cx, cy = lookup[0], lookup[1], lookup[2], lookup[3]
    n = px.shape[0]
    z = _depth_at_px(depth, px, lookup)
    rows = np.empty(n)
    for k in range(n):
        rows[k] = np.float64(px[k, 1])
    und_mid = move_pixels(und, rows, mid_row, row_s, z, True, w, v, fx, fy, cx, cy)
    moved = np.empty((n, 2), np.float32)
    for k in range(n):
        moved[k, 0] = np.float32(np.float64(px[k, 0]) + (und_mid[k, 0] - und[k, 0]))
        moved[k, 1] = np.float32(np.float64(px[k, 1]) + (und_mid[k, 1] - und[k, 1]))
    z = _depth_at_px(depth, moved, lookup)
    X = np.empty((n, 3))
    ok = np.empty(n, np.bool_)
    for k in range(n):
        ok[k] = np.isfinite(z[k])
        zk = z[k] if ok[k] else 1.0
        X[k, 0] = (und_mid[k, 0] - cx) / fx * zk
        X[k, 1] = (und_mid[k, 1] - cy) / fy * zk
        X[k, 2] = zk
    return X, ok
