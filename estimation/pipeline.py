"""Visual odometry pipelines: RGB-D (PnP, essential matrix, Kabsch), stereo, optical-flow velocity.

Offline::

    from flightkit.datasets.registry import open_sequence
    from estimation.pipeline import run_vo

    result = run_vo(open_sequence("/data/kitti06"), "stereo", progress=lambda i, n: ...)
    result.write_tum("stereo.txt")                # T_world_camera, TUM format
    result.trajectory("body")                     # T_world_body through T_body_camera
    result.fps, result.stage_ms["motion"]         # speed and per-stage timings

Live (one frame at a time, e.g. from the bus; publish ``FramePose`` from ``on_pose``)::

    vo = VisualOdometry("rgbd-pnp", intrinsics, depth_intrinsics=intrinsics)
    pose = vo.process(stamp_ns, gray, depth_m=depth)

Methods (``Method``):
    ``rgbd-pnp``        keyframe 3D points (depth) -> current pixels, PnP + RANSAC
    ``rgbd-essential``  essential matrix keyframe -> current (from the constant-velocity
                        prediction when it explains the tracks, else 5-point RANSAC), metric
                        scale and cheirality from depth; kept when it reprojects the keyframe's
                        3D points (a floor makes the 5-point solution ambiguous), least
                        squares + depth polish on those
    ``rgbd-kabsch``     3D-3D (depth in both frames), Kabsch in a vectorised RANSAC
    ``stereo``          keyframe 3D points (sparse stereo) -> current pixels, PnP (RANSAC or
                        rigidity max-clique inliers)
    ``flow``            Shi-Tomasi + LK flow from a reference frame, 6-DoF velocity by
                        3-point RANSAC on the interaction matrix, depth from the depth
                        image or the stereo altitude Z = f B / d, integrated over the time
                        since the reference (and made exact by a reprojection polish)

Front end of the keyframe methods: grid-bucketed FAST corners, tracked by pyramidal LK with
a forward-backward check from frame to frame, the tracks predicted by a constant-velocity
prior; when tracking fails (fast motion) ORB features are matched between the keyframe
and the current image instead (Hamming norm, ratio test). ``rgbd-pnp`` skips RANSAC (and
the backward LK pass for tracks that land at their prediction) when the prior already
explains the tracks (``VoOptions.pnp_prior_*``). Every estimate passes a sanity
check (speed, turn rate, inliers); a failed one is replaced by the constant-velocity
prediction and flagged ``Quality.PREDICTED``, never silently dropped. Keyframes are chosen
by parallax and motion (:class:`~estimation.keyframes.KeyframePolicy`); an optional local
bundle adjustment refines the last N keyframes.

Frames: camera frames are OpenCV; the world frame is the first camera's unless
``T_world_camera0`` (or ``init_from_groundtruth``) says otherwise; body poses are
``T_world_body = T_world_camera @ inv(T_body_camera)``.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import numpy.typing as npt

from estimation import _kernels
from estimation.estimators import keyframe_estimator
from estimation.features import DescriptorExtractor, GridDetector, as_gray
from estimation.flow import track_klt
from estimation.flow_vo import FlowEstimator
from estimation.matching import match_descriptors, match_stereo_rows
from estimation.motion import (
    Motion,
    invert,
    make_T,
    median,
    pnp,
    refine_pose,
    rotation_angle_rad,
)
from estimation.stereo import StereoRig, sparse_disparity, triangulate
from estimation.vo_options import Method, VoOptions
from estimation.vo_result import MAX_FAILED_FRACTION, STAGES, FramePose, FrameTimer, Quality, VoResult, collect_result
from flightkit.errors import EstimationError
from flightkit.frames import Transform

if TYPE_CHECKING:
    from flightkit.datasets.base import CameraIntrinsics, Frame, Sequence

__all__ = [
    "MAX_FAILED_FRACTION",
    "STAGES",
    "FramePose",
    "FramePreparer",
    "Method",
    "Quality",
    "VisualOdometry",
    "VoOptions",
    "VoResult",
    "collect_result",
    "run_vo",
    "warm_up",
]

logger = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
F32 = npt.NDArray[np.float32]


# ---------------------------------------------------------------------------------------------
def _scale_motion(T_step: F64, factor: float) -> F64:
    """Scale a relative motion (constant velocity for a different dt)."""
    if abs(factor - 1.0) < 1e-3:
        return T_step.copy()
    rv = cv2.Rodrigues(T_step[:3, :3])[0] * factor
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rv)[0]
    T[:3, 3] = T_step[:3, 3] * factor
    return T


class VisualOdometry:
    """Streaming visual odometry for one camera (call :meth:`process` per frame, in order).

    Args:
        method: a :class:`Method` or its name.
        intrinsics: the camera of the (left / colour) images.
        baseline_m: stereo baseline (``stereo``, and ``flow`` without depth).
        depth_intrinsics: the camera of the depth images, when it differs from ``intrinsics``
            (7-Scenes); depth pixels are looked up through the two pinhole models.
        T_body_camera: camera mounting (default: identity, the camera is the body).
        T_world_camera0: the first camera pose (default: identity).
        options: :class:`VoOptions`.
        on_pose: called with every :class:`FramePose` (e.g. to publish on the bus).

    Raises:
        EstimationError: unknown method, or a method without the sensor it needs.
    """

    def __init__(
        self,
        method: Method | str,
        intrinsics: CameraIntrinsics,
        baseline_m: float | None = None,
        depth_intrinsics: CameraIntrinsics | None = None,
        T_body_camera: Transform | None = None,
        T_world_camera0: Transform | None = None,
        options: VoOptions | None = None,
        on_pose: Callable[[FramePose], None] | None = None,
    ) -> None:
        try:
            self.method = Method(method)
        except ValueError as exc:
            names = ", ".join(m.value for m in Method)
            raise EstimationError(f"unknown VO method {method!r}; use one of {names}") from exc
        self.opts = options or VoOptions()
        if self.method is Method.STEREO and not baseline_m:
            raise EstimationError("method 'stereo' needs a stereo baseline; the sequence has no right camera")
        self.intr = intrinsics
        self.K = intrinsics.K
        self.dist = intrinsics.dist_array if intrinsics.is_distorted else None
        self.rig = (
            StereoRig(intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy, float(baseline_m))
            if baseline_m
            else None
        )
        self.depth_intr = depth_intrinsics
        self.T_body_camera = (T_body_camera or Transform.identity()).as_matrix()
        self.T_camera_body = invert(self.T_body_camera)
        self.T_world_cam = (T_world_camera0 or Transform.identity()).as_matrix()
        self.on_pose = on_pose
        w, h = intrinsics.width, intrinsics.height
        # LK window and pyramid from the image size (the options may fix them).
        small = w <= 400
        self.klt_win = self.opts.klt_win_px or (9 if small else 11)
        ref_w = self.opts.parallax_ref_width_px
        self.parallax_scale = (
            max(1.0, ref_w / w) if ref_w and self.method in (Method.RGBD_PNP, Method.RGBD_ESSENTIAL) else 1.0
        )
        self.klt_levels = 3 if self.opts.klt_levels is None else self.opts.klt_levels
        self.klt_back_levels = min(self.opts.klt_back_levels, self.klt_levels)
        self.stereo_win = self.opts.stereo_win_px or self.klt_win
        cell = self.opts.cell_px or max(12, int(math.sqrt(w * h / self.opts.max_features) * 1.1))
        self.grid = GridDetector(self.opts.max_features, cell, self.opts.fast_threshold, border_px=8)
        self.orb = DescriptorExtractor("orb", 1000)
        self.rng = np.random.default_rng(self.opts.seed)
        self.index = 0
        self._waited_frames = 0  # frames an RGB-D method held its start pose for lack of depth
        # Frame-to-frame state
        self.prev_pyr: npt.NDArray[np.uint8] | None = None
        self.prev_stamp_ns = 0
        self.T_step: F64 | None = None  # last accepted T_cur_prev
        self.step_dt_s = 0.0
        # Keyframe state
        self.kf_X = np.empty((0, 3))
        self.kf_px = np.empty((0, 2), np.float32)
        self.kf_ids = np.empty(0, np.int64)
        self.trk_px = np.empty((0, 2), np.float32)
        self.kf_n0 = 0
        self.kf_w = np.empty(0)
        self._meas: tuple[npt.NDArray[np.intp], F64] | None = None
        self.T_world_kf = self.T_world_cam.copy()
        self.T_prev_kf = np.eye(4)
        self.kf_since = 0
        self.kf_gray: npt.NDArray[np.uint8] | None = None
        self.kf_right: npt.NDArray[np.uint8] | None = None
        self.kf_depth: F32 | None = None
        self.next_id = 0
        self.kf_orb: tuple[Any, F64, npt.NDArray[np.bool_]] | None = None
        # Flow state
        self._flow = FlowEstimator(self) if self.method is Method.FLOW else None
        self._estimator = keyframe_estimator(self) if self.method is not Method.FLOW else None
        # Local BA window: list of (T_world_kf, ids, px_undistorted, disparity_px)
        self.ba_window: list[tuple[F64, npt.NDArray[np.int64], F64, F64]] = []
        self.ba_baseline_m = float(baseline_m) if baseline_m else 0.1  # virtual baseline for depth
        self.landmarks: dict[int, F64] = {}
        # How the motion of each frame was found (diagnostics: "essential-prior", ...).
        self.path_counts: Counter[str] = Counter()

    # ------------------------------------------------------------------ helpers
    def _undistort(self, px: F32) -> F64:
        if self.dist is None or len(px) == 0:
            return np.asarray(px, dtype=np.float64)
        out = cv2.undistortPoints(px.reshape(-1, 1, 2).astype(np.float64), self.K, self.dist, P=self.K)
        return np.asarray(out.reshape(-1, 2), dtype=np.float64)

    def _backproject(self, px_undist: F64, z: F64) -> F64:
        X = np.empty((len(px_undist), 3))
        X[:, 0] = (px_undist[:, 0] - self.intr.cx) / self.intr.fx * z
        X[:, 1] = (px_undist[:, 1] - self.intr.cy) / self.intr.fy * z
        X[:, 2] = z
        return X

    def _depth_at(self, depth_m: F32, px: F32) -> F64:
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

    def _points_3d(
        self,
        px: F32,
        right_pyr: npt.NDArray[np.uint8] | None,
        left_pyr: npt.NDArray[np.uint8] | None,
        depth_m: F32 | None,
        init_disp: F32 | float = 0.0,
        max_depth_m: float | None = None,
    ) -> tuple[F64, npt.NDArray[np.bool_]]:
        """3D points (camera frame) for pixels, from stereo or depth."""
        if depth_m is not None and self.method is not Method.STEREO:
            z = self._depth_at(depth_m, px)
            ok = np.isfinite(z)
            X = self._backproject(self._undistort(px), np.where(ok, z, 1.0))
            return X, ok
        if right_pyr is None or left_pyr is None or self.rig is None:
            raise EstimationError(f"method {self.method.value!r} needs depth or a stereo pair in every frame")
        disp, ok = sparse_disparity(
            left_pyr,
            right_pyr,
            px,
            init_disp,
            fb_max_px=self.opts.fb_max_px if self.opts.stereo_fb_check else None,
            win_px=self.stereo_win,
            levels=self.klt_levels,
            min_disparity_px=self.opts.min_disparity_px,
        )
        zmax = self._max_stereo_depth_m() if max_depth_m is None else max_depth_m
        X, ok2 = triangulate(px, disp, self.rig, self.opts.min_depth_m, zmax)
        return X, ok & ok2

    def _max_stereo_depth_m(self) -> float:
        b = self.rig.baseline_m if self.rig is not None else 0.0
        return min(self.opts.max_depth_m, self.opts.max_depth_baselines * b) if b > 0 else self.opts.max_depth_m

    def _plausible(self, T_cur_prev: F64, dt_s: float) -> bool:
        dt = max(dt_s, 1e-3)
        t = T_cur_prev[:3, 3].copy()  # as np.linalg.norm: a contiguous copy, sqrt of its dot
        speed = math.sqrt(float(t.dot(t))) / dt
        rate = rotation_angle_rad(T_cur_prev[:3, :3]) / dt
        return speed <= self.opts.max_speed_m_s and rate <= self.opts.max_rate_rad_s

    def _predict(self, dt_s: float) -> F64:
        if self.T_step is None or self.step_dt_s <= 0:
            return np.eye(4)
        return _scale_motion(self.T_step, dt_s / self.step_dt_s)

    def _emit(self, stamp_ns: int, n_inl: int, q: Quality, kf: bool, timer: FrameTimer) -> FramePose:
        timer.ms["total"] = sum(v for k, v in timer.ms.items() if k != "total")
        pose = FramePose(
            self.index,
            stamp_ns,
            self.T_world_cam.copy(),
            self.T_world_cam @ self.T_camera_body,
            n_inl,
            q,
            kf,
            timer.ms,
            timer.cpu_ms(),
        )
        self.index += 1
        if self.on_pose is not None:
            self.on_pose(pose)
        return pose

    # ------------------------------------------------------------------ main entry
    def process(
        self,
        stamp_ns: int,
        gray: npt.NDArray[np.uint8],
        right_gray: npt.NDArray[np.uint8] | None = None,
        depth_m: F32 | None = None,
    ) -> FramePose:
        """Process one frame (images as taken at ``stamp_ns``) and return its pose.

        Blocks for the processing time only (no IO). Frames must come in time order.

        Raises:
            EstimationError: the frame lacks the depth or right image the method needs.
        """
        gray = as_gray(gray)
        if self.method.needs_depth and depth_m is None:
            raise EstimationError(
                f"method {self.method.value!r} needs a depth image in every frame; use 'stereo' or 'flow'"
            )
        if self._flow is not None:
            return self._flow.process(stamp_ns, gray, right_gray, depth_m)
        return self._process_keyframe(stamp_ns, gray, right_gray, depth_m)

    # ------------------------------------------------------------------ keyframe methods
    def _waiting_for_depth(self, depth_m: F32 | None) -> bool:
        """True while an RGB-D method waits for enough depth in range to start (logged once)."""
        o = self.opts
        if depth_m is None or not self.method.needs_depth or o.init_min_depth_fraction <= 0.0:
            return False
        in_range = float(np.count_nonzero((depth_m >= o.min_depth_m) & (depth_m <= o.max_depth_m))) / depth_m.size
        if in_range >= o.init_min_depth_fraction:
            if self._waited_frames:
                logger.info("VO started after %d frames of waiting for depth in range", self._waited_frames)
            return False
        if not self._waited_frames:
            logger.info(
                "VO waits for depth: %.0f %% of the image within %.2f-%.0f m, %.0f %% needed to start "
                "(the pose is held, flagged INIT)",
                100.0 * in_range,
                o.min_depth_m,
                o.max_depth_m,
                100.0 * o.init_min_depth_fraction,
            )
        self._waited_frames += 1
        return True

    def _make_keyframe(
        self,
        gray: npt.NDArray[np.uint8],
        pyr: npt.NDArray[np.uint8],
        right_gray: npt.NDArray[np.uint8] | None,
        depth_m: F32 | None,
        keep_px: F32,
        keep_ids: npt.NDArray[np.int64],
        keep_X_cur: F64 | None,
        keep_w: F64 | None,
        remeasure: bool = True,
    ) -> None:
        """Turn the current frame into the keyframe: keep tracked points, add grid corners, 3D.

        Kept points carry their fused 3D estimate (moved into the new keyframe's frame); with
        ``remeasure`` they are measured again here and fused, else (this frame's measurement
        was already fused) only the new corners are measured.
        """
        n_keep = len(keep_px)
        new_px = self.grid.detect(gray, existing=keep_px, budget=self.opts.max_features - n_keep)
        ids_new = np.arange(self.next_id, self.next_id + len(new_px))
        self.next_id += len(new_px)
        fb_init = 0.0
        d_keep = np.zeros(0, np.float32)
        if self.method is Method.STEREO and self.rig is not None and keep_X_cur is not None and n_keep:
            fb = self.rig.fx * self.rig.baseline_m
            d_keep = (fb / np.maximum(keep_X_cur[:, 2], 1e-3)).astype(np.float32)
            fb_init = float(np.median(d_keep))
        if remeasure or keep_X_cur is None or n_keep == 0:
            px_m = np.concatenate([keep_px.astype(np.float32), new_px]) if n_keep else new_px
            init: F32 | float = (
                np.concatenate([d_keep, np.full(len(new_px), fb_init, np.float32)]) if len(d_keep) else fb_init
            )
            X_m, ok_m = self._points_3d(px_m, right_gray, pyr, depth_m, init)
            X_k, ok_k = X_m[:n_keep], ok_m[:n_keep]
            X_n, ok_n = X_m[n_keep:], ok_m[n_keep:]
        else:
            X_n, ok_n = self._points_3d(new_px, right_gray, pyr, depth_m, fb_init)
            X_k, ok_k = np.empty((n_keep, 3)), np.zeros(n_keep, dtype=bool)
        # Kept points: fuse the fresh measurement (if any) with the carried estimate.
        if keep_X_cur is not None and n_keep:
            assert keep_w is not None
            w_new = np.where(ok_k, self._depth_weight(np.where(ok_k, X_k[:, 2], 1.0)), 0.0)
            wsum = keep_w + w_new
            X_keep = (keep_X_cur * keep_w[:, None] + np.where(ok_k[:, None], X_k, 0.0) * w_new[:, None]) / wsum[:, None]
            ok_keep = np.isfinite(X_keep).all(axis=1) & (X_keep[:, 2] > self.opts.min_depth_m)
        else:
            X_keep, wsum, ok_keep = np.empty((0, 3)), np.empty(0), np.zeros(0, dtype=bool)
        w_n = self._depth_weight(np.where(ok_n, X_n[:, 2], 1.0))
        self.kf_X = np.concatenate([X_keep[ok_keep], X_n[ok_n]])
        self.kf_w = np.concatenate([wsum[ok_keep], w_n[ok_n]])
        self.kf_px = np.ascontiguousarray(
            np.concatenate([keep_px[ok_keep].astype(np.float32), new_px[ok_n]]), dtype=np.float32
        )
        self.kf_ids = np.concatenate([keep_ids[ok_keep], ids_new[ok_n]]).astype(np.int64)
        self.trk_px = self.kf_px.copy()
        self.kf_n0 = len(self.kf_X)
        self.T_world_kf = self.T_world_cam.copy()
        self.T_prev_kf = np.eye(4)
        self.kf_since = 0
        self.kf_gray = gray
        self.kf_right = right_gray
        self.kf_depth = depth_m
        self.kf_orb = None

    def _kf_orb(self) -> tuple[Any, F64, npt.NDArray[np.bool_]]:
        """ORB features of the keyframe with their 3D points (computed on first need)."""
        if self.kf_orb is None:
            assert self.kf_gray is not None
            f = self.orb.extract(self.kf_gray)
            if self.method is Method.STEREO:
                assert self.kf_right is not None and self.rig is not None
                # Row-consistent ORB matches give disparities; LK along the rows (started at
                # the ORB disparity, or the keyframe's median) fills in the rest.
                fr = self.orb.extract(self.kf_right)
                il, _, disp_orb = match_stereo_rows(f, fr, max_disparity_px=self.intr.width / 2)
                init = np.full(len(f), np.nan, np.float32)
                init[il] = disp_orb
                fb = self.rig.fx * self.rig.baseline_m
                med = float(np.median(fb / self.kf_X[:, 2])) if len(self.kf_X) else 0.0
                init = np.where(np.isfinite(init), init, med).astype(np.float32)
                # Far points too: recovering the pose matters more here than their depth noise.
                X, ok = self._points_3d(f.pts_px, self.kf_right, self.kf_gray, None, init, self.opts.max_depth_m)
            else:
                assert self.kf_depth is not None
                z = self._depth_at(self.kf_depth, f.pts_px)
                ok = np.isfinite(z)
                X = self._backproject(self._undistort(f.pts_px), np.where(ok, z, 1.0))
            self.kf_orb = (f, X, ok)
        return self.kf_orb

    def _orb_fallback(self, gray: npt.NDArray[np.uint8], guess: F64) -> Motion | None:
        f_kf, X_kf, ok_kf = self._kf_orb()
        f_cur = self.orb.extract(gray)
        ia, ib = match_descriptors(f_kf, f_cur, ratio=0.8, mutual=True)
        logger.debug("ORB fallback: %d matches, %d with 3D", len(ia), int(np.count_nonzero(ok_kf[ia])))
        keep = ok_kf[ia]
        ia, ib = ia[keep], ib[keep]
        if len(ia) < self.opts.min_inliers:
            return None
        m = pnp(
            X_kf[ia],
            self._undistort(f_cur.pts_px[ib]),
            self.K,
            method=self.opts.pnp_method,
            reproj_px=self.opts.reproj_px * 1.5,
            min_inliers=self.opts.min_inliers,
            guess_T_cur_ref=guess,
            ransac_kernel=self.opts.pnp_kernel,
        )
        return m if m.ok else None

    def _estimate(
        self,
        X_kf: F64,
        px_kf: F32,
        px_cur: F32,
        depth_m: F32 | None,
        guess: F64,
        right_pyr: npt.NDArray[np.uint8] | None,
        pyr: npt.NDArray[np.uint8],
        right_gray: npt.NDArray[np.uint8] | None = None,
    ) -> Motion:
        """The keyframe-to-current motion by the method's estimator (``estimation.estimators``)."""
        assert self._estimator is not None
        und_cur = self._undistort(px_cur)
        return self._estimator.estimate(X_kf, px_kf, px_cur, und_cur, depth_m, guess, right_pyr, pyr, right_gray)

    def _pnp_from_prior(
        self,
        X_kf: F64,
        px_cur: F32,
        und_cur: F64,
        guess: F64,
        depth_m: F32 | None,
        pyr: npt.NDArray[np.uint8],
        right_gray: npt.NDArray[np.uint8] | None,
    ) -> Motion | None:
        """PnP without RANSAC when the constant-velocity prediction already explains the tracks.

        The tracks within ``pnp_prior_gate_px`` of their predicted position are fitted by
        SQPnP (a global solver: its answer does not depend on the prediction); the inliers
        are the tracks within ``reproj_px`` of that pose, which then gets the usual depth
        polish (:meth:`_refine`) on them. Accepted when at least ``pnp_prior_min_fraction``
        of the tracks pass both the gate and the inlier test (RANSAC finds 96-100 % inliers
        on the RGB-D sequences here); else None, and the caller runs RANSAC.

        Why not Gauss-Newton from the prediction: on a mostly planar scene (a floor) the
        reprojection cost has a flat valley, a fit started in it keeps most of the start's
        error, and the constant-velocity prediction then doubles that error every frame
        (measured: 4-6 cm ATE on the synthetic patterns instead of 4-5 mm).
        """
        o = self.opts
        n = len(X_kf)
        need = max(o.min_inliers, o.pnp_prior_min_fraction * n)
        gate = self._reproj_err2(guess, X_kf, und_cur) < o.pnp_prior_gate_px**2
        if np.count_nonzero(gate) < need:
            return None
        Xg = np.ascontiguousarray(X_kf[gate])
        ug = np.ascontiguousarray(und_cur[gate])
        ok, rvec, tvec = cv2.solvePnP(Xg, ug, self.K, None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            return None
        T = make_T(cv2.Rodrigues(rvec)[0], tvec.ravel())
        mask = self._reproj_err2(T, X_kf, und_cur) < o.reproj_px**2
        if np.count_nonzero(mask) < need:
            return None
        T = self._refine(T, X_kf[mask], px_cur[mask], und_cur[mask], depth_m, pyr, right_gray)
        if self._meas is not None:
            self._meas = (np.flatnonzero(mask)[self._meas[0]], self._meas[1])
        return Motion(T, mask, True)

    def _polish(
        self,
        m: Motion,
        X_kf: F64,
        px_cur: F32,
        und_cur: F64,
        depth_m: F32 | None,
        pyr: npt.NDArray[np.uint8],
        right_gray: npt.NDArray[np.uint8] | None,
        z_cur: F64 | None = None,
    ) -> Motion:
        """The same polish as PnP's for a motion found otherwise (5-point, Kabsch): reprojection
        of the keyframe points plus this frame's depth (``refine_with_depth``), inliers
        re-selected on the result; the depth measurements are kept for fusion. ``z_cur``: the
        depth at ``px_cur`` when the caller has looked it up already (Kabsch)."""
        o = self.opts
        if not (m.ok and o.refine_with_depth):
            return m
        mask = m.inliers.copy()
        T = self._refine(
            m.T_cur_ref,
            X_kf[mask],
            px_cur[mask],
            und_cur[mask],
            depth_m,
            pyr,
            right_gray,
            None if z_cur is None else z_cur[mask],
        )
        refined = mask & (self._reproj_err2(T, X_kf, und_cur) < o.reproj_px**2)
        if np.count_nonzero(refined) < o.min_inliers:
            self._meas = None
            return m
        if self._meas is not None:
            self._meas = (np.flatnonzero(mask)[self._meas[0]], self._meas[1])
            keep = refined[self._meas[0]]
            self._meas = (self._meas[0][keep], self._meas[1][keep])
        return Motion(T, refined, True)

    def _reproj_err2(self, T_cur_ref: F64, X_ref: F64, und_cur: F64) -> F64:
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

    def _refine(
        self,
        T: F64,
        X_kf: F64,
        px: F32,
        und: F64,
        depth_m: F32 | None,
        gray: npt.NDArray[np.uint8],
        right_gray: npt.NDArray[np.uint8] | None,
        z: F64 | None = None,
    ) -> F64:
        """Polish a PnP pose with the current frame's own depth (disparity residuals); ``z``:
        the depth at ``px`` if already looked up (:meth:`_depth_at` is per pixel)."""
        if self.method is Method.STEREO:
            if right_gray is None or self.rig is None:
                return refine_pose(T, X_kf, und, self.K)
            fb = self.rig.fx * self.rig.baseline_m
            z_pred = X_kf @ T[2, :3] + T[2, 3]
            init = (fb / np.maximum(z_pred, 1e-3)).astype(np.float32)
            disp, ok = sparse_disparity(
                gray,
                right_gray,
                px,
                init,
                fb_max_px=None,
                win_px=self.stereo_win,
                levels=1,  # the predicted disparity is close: a shallow pyramid is enough
                min_disparity_px=self.opts.min_disparity_px,
            )
            # A disparity far from the prediction is a mismatch, not a measurement.
            ok &= np.abs(disp - init) < np.maximum(2.0, 0.3 * init)
            d = np.where(ok, disp, np.nan)
        elif depth_m is not None:
            fb = self.intr.fx * self.ba_baseline_m
            if z is None:
                z = self._depth_at(depth_m, px)
            d = fb / z
        else:
            return refine_pose(T, X_kf, und, self.K)
        good = np.isfinite(d)
        X_meas = self._backproject(und[good], fb / d[good])
        self._meas = (np.flatnonzero(good), X_meas)
        return refine_pose(T, X_kf, und, self.K, d, fb, huber_px=1.0)

    def _depth_weight(self, z: F64) -> F64:
        """Inverse variance of a depth measurement (stereo and Kinect-like: sigma_z ~ z^2)."""
        return 1.0 / np.maximum(z, 1e-3) ** 4

    def _fuse(self, gidx: npt.NDArray[np.intp], X_cur: F64, T_cur_kf: F64) -> None:
        """Fuse current-frame 3D measurements of keyframe points into ``kf_X`` (inverse variance)."""
        if not len(gidx):
            return
        T_kf_cur = invert(T_cur_kf)
        X_new = X_cur @ T_kf_cur[:3, :3].T + T_kf_cur[:3, 3]
        w_new = self._depth_weight(X_cur[:, 2])
        w_old = self.kf_w[gidx]
        wsum = w_old + w_new
        self.kf_X[gidx] = (self.kf_X[gidx] * w_old[:, None] + X_new * w_new[:, None]) / wsum[:, None]
        self.kf_w[gidx] = wsum

    def _project(self, T_cur_kf: F64, X: F64) -> tuple[F32, npt.NDArray[np.bool_]]:
        """Pixels (float32) of keyframe points under ``T_cur_kf`` and which are in front and
        within 20 px of the image."""
        i = self.intr
        Xk = np.ascontiguousarray(X, dtype=np.float64)
        Tk = np.ascontiguousarray(T_cur_kf, dtype=np.float64)
        if self.dist is None:
            uv_k: F32
            inside_k: npt.NDArray[np.bool_]
            uv_k, inside_k = _kernels.project(Xk, Tk, i.fx, i.fy, i.cx, i.cy, float(i.width), float(i.height))
            return uv_k, inside_k
        Xc = _kernels.transform(Xk, Tk)
        front = Xc[:, 2] > 0.05
        pts, _ = cv2.projectPoints(Xc[:, None, :], np.zeros(3), np.zeros(3), self.K, self.dist)
        u, v = pts[:, 0, 0], pts[:, 0, 1]
        inside = front & (u > -20) & (u < self.intr.width + 20) & (v > -20) & (v < self.intr.height + 20)
        uv = np.empty((len(u), 2), np.float32)
        uv[:, 0] = u
        uv[:, 1] = v
        return uv, inside

    def _process_keyframe(
        self,
        stamp_ns: int,
        gray: npt.NDArray[np.uint8],
        right_gray: npt.NDArray[np.uint8] | None,
        depth_m: F32 | None,
    ) -> FramePose:
        o = self.opts
        if self.method is Method.STEREO and right_gray is None:
            raise EstimationError("method 'stereo' needs the right image in every frame")
        timer = FrameTimer()
        pyr = gray
        timer.lap("track")
        if self.prev_pyr is None:
            if self._waiting_for_depth(depth_m):
                timer.lap("keyframe")
                return self._emit(stamp_ns, 0, Quality.INIT, False, timer)
            self._make_keyframe(
                gray,
                pyr,
                right_gray,
                depth_m,
                np.empty((0, 2), np.float32),
                np.empty(0, np.int64),
                None,
                None,
            )
            self._ba_add_keyframe()
            timer.lap("keyframe")
            self.prev_pyr, self.prev_stamp_ns = pyr, stamp_ns
            return self._emit(stamp_ns, len(self.kf_X), Quality.INIT, True, timer)

        dt_s = max((stamp_ns - self.prev_stamp_ns) * 1e-9, 1e-4)
        T_pred_cur_prev = self._predict(dt_s)
        T_pred_cur_kf = T_pred_cur_prev @ self.T_prev_kf
        guess_px, vis = self._project(T_pred_cur_kf, self.kf_X)
        guess = np.where(vis[:, None], guess_px, self.trk_px)
        # The RGB-D methods with a motion prior: tracks that land near their predicted position
        # skip the backward check (the prior-guided fit below rejects what does not fit).
        prior = self.method.needs_depth and self.T_step is not None
        trust_px = np.where(vis, o.klt_trust_prior_px, 0.0) if prior else 0.0
        px, ok = track_klt(
            self.prev_pyr,
            pyr,
            self.trk_px,
            o.fb_max_px,
            self.klt_win,
            self.klt_levels,
            guess=guess,
            back_levels=self.klt_back_levels,
            max_iters=o.klt_iters,
            trust_guess_px=trust_px,
        )
        h, w = gray.shape
        ok &= (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        idx = np.flatnonzero(ok)
        timer.lap("track")

        right_pyr = None
        if self.method is Method.STEREO and o.inliers == "rigidity":
            assert right_gray is not None
            right_pyr = right_gray
        motion: Motion | None = None
        self._meas = None
        if len(idx) >= o.min_inliers:
            m = self._estimate(
                self.kf_X[idx], self.kf_px[idx], px[idx], depth_m, T_pred_cur_kf, right_pyr, pyr, right_gray
            )
            if m.ok:
                motion = m
        quality = Quality.GOOD
        fallback = False
        if motion is None and o.orb_fallback:
            motion = self._orb_fallback(gray, T_pred_cur_kf)
            fallback = motion is not None
            quality = Quality.FALLBACK
        T_cur_kf = T_pred_cur_kf
        n_inl = 0
        if motion is not None:
            T_cand = motion.T_cur_ref
            T_cur_prev = T_cand @ invert(self.T_prev_kf)
            if self._plausible(T_cur_prev, dt_s):
                T_cur_kf = T_cand
                n_inl = motion.n_inliers
                if quality is Quality.GOOD and n_inl < 2 * o.min_inliers:
                    quality = Quality.WEAK
            else:
                logger.debug(
                    "frame %d: implausible step rejected (%.3f m)",
                    self.index,
                    np.linalg.norm(T_cur_prev[:3, 3]),
                )
                motion = None
        if motion is None:
            quality = Quality.PREDICTED
        timer.lap("motion")

        # Accept the step.
        T_cur_prev = T_cur_kf @ invert(self.T_prev_kf)
        if quality is not Quality.PREDICTED:
            self.T_step, self.step_dt_s = T_cur_prev, dt_s
        self.T_world_cam = self.T_world_kf @ invert(T_cur_kf)
        self.T_prev_kf = T_cur_kf
        self.kf_since += 1
        fused = False
        if motion is not None and not fallback and self._meas is not None and o.fuse_depth:
            self._fuse(idx[self._meas[0]], self._meas[1], T_cur_kf)
            fused = True

        # Keep the inlier tracks (all valid tracks when the estimate was not from them).
        if motion is not None and not fallback:
            keep = np.zeros(len(self.trk_px), dtype=bool)
            keep[idx[motion.inliers]] = True
        else:
            keep = ok
        self.kf_X, self.kf_px, self.kf_ids = self.kf_X[keep], self.kf_px[keep], self.kf_ids[keep]
        self.kf_w = self.kf_w[keep]
        self.trk_px = np.ascontiguousarray(px[keep])
        parallax = np.linalg.norm(self.trk_px - self.kf_px, axis=1) if len(self.trk_px) else np.zeros(1)
        depth = median(self.kf_X[:, 2]) if len(self.kf_X) else float("inf")
        decision = o.keyframes.decide(
            parallax * self.parallax_scale, len(self.trk_px), self.kf_n0, T_cur_kf, self.kf_since, depth
        )
        is_kf = decision.new_keyframe or fallback
        if is_kf:
            X_cur = self.kf_X @ T_cur_kf[:3, :3].T + T_cur_kf[:3, 3]
            self._make_keyframe(
                gray,
                pyr,
                right_gray,
                depth_m,
                self.trk_px,
                self.kf_ids,
                X_cur,
                self.kf_w,
                remeasure=not fused,
            )
            logger.debug(
                "frame %d: keyframe (%s), %d points",
                self.index,
                decision.reason or "fallback",
                len(self.kf_X),
            )
            timer.lap("keyframe")
            if o.ba_window > 1:
                self._ba_add_keyframe()
                self._ba_run()
                timer.lap("ba")
        self.prev_pyr, self.prev_stamp_ns = pyr, stamp_ns
        return self._emit(stamp_ns, n_inl, quality, is_kf, timer)

    # ------------------------------------------------------------------ local bundle adjustment
    def _ba_add_keyframe(self) -> None:
        if self.opts.ba_window <= 1:
            return
        und = self._undistort(self.kf_px)
        disp = self.intr.fx * self.ba_baseline_m / self.kf_X[:, 2]
        self.ba_window.append((self.T_world_kf.copy(), self.kf_ids.copy(), und, disp))
        Xw = self.kf_X @ self.T_world_kf[:3, :3].T + self.T_world_kf[:3, 3]
        for i, lid in enumerate(self.kf_ids.tolist()):
            if lid not in self.landmarks:
                self.landmarks[lid] = Xw[i]
        if len(self.ba_window) > self.opts.ba_window:
            self.ba_window.pop(0)
            alive = set(np.concatenate([w[1] for w in self.ba_window]).tolist())
            self.landmarks = {k: v for k, v in self.landmarks.items() if k in alive}

    def _ba_run(self) -> None:
        from estimation.bundle import bundle_adjust

        if len(self.ba_window) < 2:
            return
        poses = np.stack([w[0] for w in self.ba_window])
        lids = np.array(sorted(self.landmarks), dtype=np.int64)
        if len(lids) < 10:
            return
        pos = {lid: i for i, lid in enumerate(lids.tolist())}
        cams, pts, uv, dd = [], [], [], []
        for c, (_, ids, und, disp) in enumerate(self.ba_window):
            for j, lid in enumerate(ids.tolist()):
                if lid in pos:
                    cams.append(c)
                    pts.append(pos[lid])
                    uv.append(und[j])
                    dd.append(disp[j])
        cams_a, pts_a, uv_a, d_a = np.array(cams), np.array(pts), np.array(uv), np.array(dd)
        # Only points seen from two or more keyframes constrain the poses.
        seen = np.bincount(pts_a, minlength=len(lids))
        multi = seen >= 2
        if np.count_nonzero(multi) < 10:
            return
        remap = np.cumsum(multi) - 1
        keep_obs = multi[pts_a]
        lids = lids[multi]
        P = np.stack([self.landmarks[int(k)] for k in lids])
        res = bundle_adjust(
            poses,
            P,
            cams_a[keep_obs],
            remap[pts_a[keep_obs]],
            uv_a[keep_obs],
            self.K,
            n_fixed=1,
            disparity_px=d_a[keep_obs],
            baseline_m=self.ba_baseline_m,
        )
        if res is None:
            return
        new_poses, new_P = res
        for i, lid in enumerate(lids.tolist()):
            self.landmarks[lid] = new_P[i]
        self.ba_window = [(new_poses[c], *w[1:]) for c, w in enumerate(self.ba_window)]
        # The newest keyframe is the current frame: move it and its points (in its own frame).
        T_new = new_poses[-1]
        self.T_world_kf = T_new.copy()
        self.T_world_cam = T_new.copy()
        T_kf_world = invert(T_new)
        Xw = np.stack(
            [self.landmarks.get(int(k), None) if int(k) in self.landmarks else np.full(3, np.nan) for k in self.kf_ids]
        )
        Xk = Xw @ T_kf_world[:3, :3].T + T_kf_world[:3, 3]
        good = np.isfinite(Xk).all(axis=1) & (Xk[:, 2] > self.opts.min_depth_m)
        self.kf_X = np.where(good[:, None], Xk, self.kf_X)


# ---------------------------------------------------------------------------------------------
def _resize_intrinsics(intr: CameraIntrinsics, size: tuple[int, int]) -> CameraIntrinsics:
    from flightkit.datasets.base import CameraIntrinsics

    w, h = size
    sx, sy = w / intr.width, h / intr.height
    return CameraIntrinsics(
        intr.fx * sx, intr.fy * sy, (intr.cx + 0.5) * sx - 0.5, (intr.cy + 0.5) * sy - 0.5, w, h, intr.dist
    )


@dataclass(frozen=True, slots=True, eq=False)
class PreparedFrame:
    """Images ready for :meth:`VisualOdometry.process` (decoded, resized, depth in metres)."""

    stamp_ns: int
    gray: npt.NDArray[np.uint8]
    right_gray: npt.NDArray[np.uint8] | None
    depth_m: F32 | None
    T_world_camera: Transform | None


class FramePreparer:
    """Converts dataset frames for a method and an optional processing size (reuses no
    buffers across frames: the frames own their images)."""

    def __init__(self, sequence: Sequence, method: Method, size: tuple[int, int] | None) -> None:
        self.method = method
        intr = sequence.intrinsics
        self.size = size if size is not None and size != (intr.width, intr.height) else None
        self.intrinsics = _resize_intrinsics(intr, self.size) if self.size else intr
        di = sequence.depth_intrinsics
        self.depth_intrinsics = _resize_intrinsics(di, self.size) if (self.size and di is not None) else di
        self.want_depth = method.needs_depth or (method is Method.FLOW and di is not None)
        self.want_right = method is Method.STEREO or (method is Method.FLOW and di is None)

    def __call__(self, frame: Frame) -> PreparedFrame:
        gray = frame.gray
        right = frame.right_gray if self.want_right else None
        depth = frame.depth_m if self.want_depth else None
        if self.size is not None:
            gray = cv2.resize(gray, self.size, interpolation=cv2.INTER_AREA)
            if right is not None:
                right = cv2.resize(right, self.size, interpolation=cv2.INTER_AREA)
            if depth is not None:
                depth = cv2.resize(depth, self.size, interpolation=cv2.INTER_NEAREST)
        return PreparedFrame(frame.stamp_ns, gray, right, depth, frame.T_world_camera)


def warm_up(method: Method | str) -> list[FramePose]:
    """Run ``method`` on five synthetic 320x240 frames (a blurred random texture at 2 m, moving
    2 px a frame) so that its compiled kernels (``estimation._kernels``) are loaded, or compiled
    on the first run after an install (~8.5 s of CPU; ~0.4 s to load them otherwise), before
    live frames arrive. The frames have the types and layouts of real ones, so the kernels a
    real run calls need no new compilation afterwards. Blocks; returns the five poses (the
    first ``INIT``, the others estimated)."""
    m = Method(method)
    w, h = 320, 240
    rng = np.random.default_rng(7)
    texture = cv2.GaussianBlur(rng.integers(0, 256, (h + 8, w + 32), dtype=np.uint8), (5, 5), 1.0)
    from flightkit.datasets.base import CameraIntrinsics

    intr = CameraIntrinsics(250.0, 250.0, w / 2, h / 2, w, h)
    depth = np.full((h, w), 2.0, np.float32)
    vo = VisualOdometry(m, intr, 0.1, intr)
    poses = []
    for i in range(5):
        gray = np.ascontiguousarray(texture[4 : 4 + h, 2 * i : 2 * i + w])
        # stereo: a point seen 12 px further left in the right image is 2.08 m away (0.1 m baseline)
        right = np.ascontiguousarray(texture[4 : 4 + h, 2 * i + 12 : 2 * i + 12 + w]) if m is Method.STEREO else None
        poses.append(vo.process(i * 33_333_333, gray, right, None if m is Method.STEREO else depth))
    return poses


def run_vo(
    sequence: Sequence,
    method: Method | str,
    *,
    options: VoOptions | None = None,
    size: tuple[int, int] | None = None,
    T_body_camera: Transform | None = None,
    init_from_groundtruth: bool = False,
    start: int = 0,
    stop: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    on_pose: Callable[[FramePose], None] | None = None,
) -> VoResult:
    """Run visual odometry over a sequence.

    Args:
        sequence: any :class:`~flightkit.datasets.base.Sequence` (TUM, 7-Scenes, EuRoC,
            KITTI, recording, simulator).
        method: a :class:`Method` or its name (``rgbd-pnp``, ``rgbd-essential``,
            ``rgbd-kabsch``, ``stereo``, ``flow``).
        options: pipeline tuning.
        size: process images resized to (width, height) (intrinsics scaled to match).
        T_body_camera: camera mounting, for ``T_world_body`` (default identity).
        init_from_groundtruth: start at the first frame's ground-truth camera pose (so the
            estimate overlays the ground truth without alignment); else at the identity.
        start, stop: frame range.
        progress: called as ``progress(frames_done, frames_total)`` after every frame.
        on_pose: called with every :class:`FramePose` (hook for live publishing).

    Returns:
        :class:`VoResult`. Blocks until the sequence is processed. Frames whose motion could
        not be estimated are flagged in ``quality`` and counted in a warning (logged);
        :meth:`VoResult.check` raises when they are most of the run.

    Raises:
        EstimationError: unknown method, or the sequence lacks depth/stereo for it.
        DatasetError: an image cannot be read.
    """
    try:
        m = Method(method)
    except ValueError as exc:
        names = ", ".join(x.value for x in Method)
        raise EstimationError(f"unknown VO method {method!r}; use one of {names}") from exc
    has_depth, has_stereo = sequence.depth_intrinsics is not None, bool(sequence.baseline_m)
    if not has_depth and not has_stereo:
        # A single camera (a plain video): no method here can give metric motion from it.
        raise EstimationError(
            f"{sequence.name} has one camera and neither depth images nor a stereo pair; every VO method "
            "needs one of them for metric scale (rgbd-* depth, stereo a pair, flow either): record with a "
            "depth or stereo camera"
        )
    if m.needs_depth and not has_depth:
        raise EstimationError(
            f"method {m.value!r} needs depth images but {sequence.name} has none; use 'stereo' or 'flow'"
        )
    if m is Method.STEREO and not has_stereo:
        raise EstimationError(
            f"method 'stereo' needs a stereo pair but {sequence.name} has none; use an rgbd method or 'flow'"
        )
    prep = FramePreparer(sequence, m, size)
    total = len(range(*slice(start, stop).indices(len(sequence))))
    t0 = time.perf_counter()
    vo: VisualOdometry | None = None
    poses: list[FramePose] = []
    incomplete = 0
    for i, frame in enumerate(sequence.frames(start, stop)):
        pf = prep(frame)
        if (m.needs_depth and pf.depth_m is None) or (m is Method.STEREO and pf.right_gray is None):
            # a partner image that was never recorded (dropped, or the recording stopped between the
            # colour and the depth image): skip the frame, count it, keep the run
            incomplete += 1
            continue
        if vo is None:
            T0 = pf.T_world_camera if (init_from_groundtruth and pf.T_world_camera is not None) else None
            vo = VisualOdometry(
                m,
                prep.intrinsics,
                sequence.baseline_m,
                prep.depth_intrinsics,
                T_body_camera,
                T0,
                options,
                on_pose,
            )
        poses.append(vo.process(pf.stamp_ns, pf.gray, pf.right_gray, pf.depth_m))
        if progress is not None:
            progress(i + 1, total)
    wall = time.perf_counter() - t0
    if incomplete:
        part = "depth" if m.needs_depth else "right"
        logger.warning(
            "%s: skipped %d of %d frames that have no %s image (dropped, or cut off when the recording stopped)",
            sequence.name,
            incomplete,
            total,
            part,
        )
        if not poses:
            raise EstimationError(
                f"none of the {total} frames of {sequence.name} has a {part} image; method {m.value!r} needs one"
            )
    result = collect_result(poses, m.value, sequence.name, wall, (prep.intrinsics.width, prep.intrinsics.height))
    if result.n_failed:
        logger.warning("%s", result.failure_message())
    return result
