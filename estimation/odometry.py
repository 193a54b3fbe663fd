"""The streaming visual odometry of one camera (:class:`VisualOdometry`): per frame it predicts,
tracks, estimates the motion (one estimator per method, ``estimation.estimators``; ``flow`` in
``estimation.flow_vo``), checks and accepts it, and makes keyframes. ``estimation.pipeline``
describes the methods and runs it over a sequence (``run_vo``).
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from estimation.camera_geometry import CameraGeometry, disparity_variance
from estimation.estimators import MotionEstimator, Tracks, keyframe_estimator
from estimation.features import as_gray
from estimation.flow_vo import FlowEstimator
from estimation.frontend import FrontEnd
from estimation.local_ba import LocalBundleWindow
from estimation.motion import Motion, invert, median
from estimation.polish import PosePolisher
from estimation.pose_track import PoseTrack
from estimation.revisit import KeyframeStore, StoredKeyframe
from estimation.rolling_shutter import CameraRate
from estimation.stereo_offset import DisparityOffset
from estimation.vo_options import FlowOptions, Method, VoOptions
from estimation.vo_result import FramePose, FrameTimer, Quality
from flightkit.errors import EstimationError
from flightkit.frames import Transform

if TYPE_CHECKING:
    from flightkit.datasets.base import CameraIntrinsics

__all__ = ["VisualOdometry"]

logger = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
F32 = npt.NDArray[np.float32]

_RATE_REDO_PX = 0.1
"""A rolling shutter: the motion is measured again with its own rate when that rate moves the
rows' pixels by more than this from the predicted rate's (px)."""


class VisualOdometry:
    """Streaming visual odometry for one camera (call :meth:`process` per frame, in order).

    Args:
        method: a :class:`Method` or its name.
        intrinsics: the camera of the (left / colour) images.
        baseline_m: stereo baseline (``stereo``, and ``flow`` without depth).
        depth_intrinsics: the camera of the depth images, when it differs from ``intrinsics``
            (7-Scenes); depth pixels are looked up through the two pinhole models.
        depth_registered: the depth images are registered to the colour images (TUM, the
            simulator); False for another depth camera (7-Scenes): its depth is weighed less.
        T_body_camera: camera mounting (default: identity, the camera is the body).
        T_world_camera0: the first camera pose (default: identity).
        options: :class:`VoOptions`.
        on_pose: called with every :class:`FramePose` (e.g. to publish on the bus).

    Raises:
        EstimationError: unknown method, a method without the sensor it needs, or options of
            another method's estimator.
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
        depth_registered: bool = True,
    ) -> None:
        try:
            self.method = Method(method)
        except ValueError as exc:
            names = ", ".join(m.value for m in Method)
            raise EstimationError(f"unknown VO method {method!r}; use one of {names}") from exc
        given = options or VoOptions()
        # The method's defaults for options left None; pixel options are given at REF_FOCAL_PX:
        # this camera's pixels from here on.
        self.opts = o = given.for_method(self.method).for_camera(
            math.sqrt(intrinsics.fx * intrinsics.fy), intrinsics.width
        )
        stereo = self.method is Method.STEREO
        if stereo and not baseline_m:
            raise EstimationError("method 'stereo' needs a stereo baseline; the sequence has no right camera")
        self.geo = CameraGeometry(
            intrinsics, baseline_m, depth_intrinsics, o, use_depth_images=not stereo, depth_registered=depth_registered
        )
        self.T_body_camera = (T_body_camera or Transform.identity()).as_matrix()
        self.T_camera_body = invert(self.T_body_camera)
        self.pose = PoseTrack((T_world_camera0 or Transform.identity()).as_matrix(), o.max_speed_m_s, o.max_rate_rad_s)
        self.on_pose = on_pose
        self.rng = np.random.default_rng(o.seed)
        self.index = 0
        self._waited_frames = 0  # frames an RGB-D method held its start pose for lack of depth
        self.prev_gray: npt.NDArray[np.uint8] | None = None
        self.T_prev_kf = np.eye(4)  # the previous frame's T_cur_kf
        self.kf_since = 0
        # How the motion of each frame was found (diagnostics: "essential-prior", ...).
        self.path_counts: Counter[str] = Counter()
        self.front = FrontEnd(self.geo, o, stereo)
        self.polisher = PosePolisher(self.geo, o, stereo)
        self._flow: FlowEstimator | None = None
        self._estimator: MotionEstimator | None = None
        if self.method is Method.FLOW:
            fo = o.estimator_options(self.method)
            assert isinstance(fo, FlowOptions)
            self._flow = FlowEstimator(self.geo, o, fo, self.pose, self.front.orb, self.rng)
        else:
            self._estimator = keyframe_estimator(self.method, self.geo, self.polisher, o, self.path_counts, self.rng)
        rig = self.geo.rig
        self.offset = (
            DisparityOffset(rig.fx, rig.fy, rig.cx, rig.cy, rig.baseline_m, o.track_sigma_px)
            if stereo and rig is not None and o.stereo_offset
            else None
        )
        self.ba = (
            LocalBundleWindow(o.ba_window, self.geo.K, intrinsics.fx, self.geo.virtual_baseline_m)
            if o.ba_window > 1
            else None
        )
        # Past keyframes to return to (not with local BA, whose window is the last keyframes made).
        self.store = KeyframeStore(o.revisit_keyframes) if o.revisit_keyframes > 0 and self.ba is None else None
        self._stored: StoredKeyframe | None = None  # the current keyframe's entry in the store

    def _emit(self, stamp_ns: int, n_inl: int, q: Quality, kf: bool, timer: FrameTimer) -> FramePose:
        timer.ms["total"] = sum(v for k, v in timer.ms.items() if k != "total")
        T = self.pose.T_world_cam
        pose = FramePose(
            self.index, stamp_ns, T.copy(), T @ self.T_camera_body, n_inl, q, kf, timer.ms, timer.cpu_ms()
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
            timer = FrameTimer()
            step = self._flow.process(self.index, stamp_ns, gray, right_gray, depth_m, timer)
            return self._emit(stamp_ns, step.n_inliers, step.quality, step.new_reference, timer)
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

    def _new_keyframe(
        self,
        gray: npt.NDArray[np.uint8],
        right_gray: npt.NDArray[np.uint8] | None,
        depth_m: F32 | None,
        X_cur: F64 | None,
        remeasure: bool = True,
        rate: CameraRate | None = None,
    ) -> None:
        self.front.make_keyframe(gray, right_gray, depth_m, self.pose.T_world_cam, X_cur, remeasure, rate)
        if self.offset is not None and self.offset.waiting:
            # The first keyframe (or one after a gap): its own disparities start the next pair.
            self._observe_offset(self.front.kf_ids, self.front.kf_X, None)
        self.T_prev_kf = np.eye(4)
        self.kf_since = 0
        if self.store is not None:
            self._stored = self.front.snapshot()
            self.store.add(self._stored)
        if self.ba is not None:
            f = self.front
            und_kf = self.geo.at_stamp(f.kf_und_lens, f.kf_px, f.kf_rate, f.kf_X[:, 2])
            self.ba.add_keyframe(f.T_world_kf, f.kf_ids, und_kf, f.kf_X)

    def _tracks(
        self,
        idx: npt.NDArray[np.intp],
        px: F32,
        und_lens: F64,
        T_guess_cur_kf: F64,
        has_prior: bool,
        rate: CameraRate | None,
        gray: npt.NDArray[np.uint8],
        right_gray: npt.NDArray[np.uint8] | None,
        depth_m: F32 | None,
    ) -> Tracks:
        """The tracked keyframe points ``idx`` (current pixels ``px[idx]``, ``und_lens`` undistorted)
        for the estimator, with the predicted motion ``T_guess_cur_kf``; their undistorted pixels at
        the frame's stamp with the camera's ``rate`` (a rolling shutter)."""
        front = self.front
        X_kf = front.kf_X[idx]
        px_cur = px[idx]
        var_kf = disparity_variance(front.kf_w[idx], X_kf[:, 2]) if self.opts.point_uncertainty else None
        return Tracks(
            X_kf,
            front.kf_px[idx],
            front.kf_und_lens[idx],
            px_cur,
            und_lens,
            self._at_stamp(X_kf, px_cur, und_lens, T_guess_cur_kf, rate),
            T_guess_cur_kf,
            has_prior,
            gray,
            right_gray,
            depth_m,
            var_kf,
            rate,
            front.kf_rate,
        )

    def _at_rate(self, t: Tracks, T_cur_kf: F64, rate: CameraRate, inliers: int) -> Tracks:
        """The same tracks for a second measurement from the motion ``T_cur_kf`` measured with
        ``inliers`` of them: their current pixels moved to the stamp with the camera's ``rate``."""
        und_cur = self._at_stamp(t.X_kf, t.px_cur, t.und_lens_cur, T_cur_kf, rate)
        return replace(t, und_cur=und_cur, guess=T_cur_kf, has_prior=True, rate=rate, guess_inliers=inliers)

    def _at_stamp(self, X_kf: F64, px_cur: F32, und_lens: F64, T_cur_kf: F64, rate: CameraRate | None) -> F64:
        """The tracks' undistorted current pixels moved to the frame's stamp with the camera's
        ``rate``, at the depths their keyframe points have under ``T_cur_kf``."""
        z_cur = X_kf @ T_cur_kf[2, :3] + T_cur_kf[2, 3] if rate is not None else None
        return self.geo.at_stamp(und_lens, px_cur, rate, z_cur)

    def _measure(
        self,
        idx: npt.NDArray[np.intp],
        px: F32,
        T_pred_cur_kf: F64,
        has_prior: bool,
        rate: CameraRate | None,
        dt_s: float,
        gray: npt.NDArray[np.uint8],
        right_gray: npt.NDArray[np.uint8] | None,
        depth_m: F32 | None,
    ) -> Motion | None:
        """The keyframe-to-current motion from the tracks ``idx`` (None: the estimator failed).
        With a rolling shutter the rate this motion implies replaces the predicted ``rate``, and
        the motion is measured again with it when that moves the rows' pixels."""
        assert self._estimator is not None
        shutter = self.geo.shutter
        und_lens = self.geo.undistort(px[idx])  # once: both measurements move it to the stamp
        tracks = self._tracks(idx, px, und_lens, T_pred_cur_kf, has_prior, rate, gray, right_gray, depth_m)
        m = self._estimator.estimate(tracks)
        if shutter is not None and m.ok:
            rate_m = CameraRate.from_step(m.T_cur_ref @ invert(self.T_prev_kf), dt_s)
            if self.front.kf_rate is None:
                # The first keyframe was made before any motion: it gets this step's rate (its
                # points move, so the tracks are gathered again).
                self.front.set_keyframe_rate(rate_m)
                rate = None
                tracks = self._tracks(idx, px, und_lens, T_pred_cur_kf, has_prior, rate, gray, right_gray, depth_m)
            if rate is None or shutter.max_shift_px(rate_m.minus(rate)) > _RATE_REDO_PX:
                meas = self.polisher.meas
                # From the first measurement, whose outliers stay outliers: the prior check needs
                # its share of inliers, not the options' (else it falls to RANSAC again).
                n_inl = int(np.count_nonzero(m.inliers))
                m2 = self._estimator.estimate(self._at_rate(tracks, m.T_cur_ref, rate_m, n_inl))
                if m2.ok:
                    m = m2
                else:
                    self.polisher.meas = meas
        return m if m.ok else None

    def _revisit(self, gray: npt.NDArray[np.uint8], rate: CameraRate | None) -> bool:
        """Instead of a new keyframe, return to a kept one the camera sees again, if any
        (``VoOptions.revisit_keyframes``); the next frames are measured against it."""
        if self.store is None:
            return False
        T_world_cam = self.pose.T_world_cam
        kf = self.store.best(T_world_cam, self.geo, self.opts.keyframes, self._stored)
        if kf is None or not self.front.restore(kf, gray, T_world_cam, rate):
            return False
        self._stored = kf
        self.T_prev_kf = invert(T_world_cam) @ kf.T_world_kf
        self.kf_since = 0
        return True

    def _observe_offset(self, ids: npt.NDArray[np.int64], X: F64, T_cur_prev: F64 | None) -> None:
        """Stereo: feed measured points (their ids, 3D in this camera from this frame's disparities)
        to the disparity-offset estimate; ``T_cur_prev``: the motion since its last observation."""
        assert self.offset is not None
        if not len(ids):
            self.offset.forget()
            return
        g = self.geo
        z = X[:, 2]
        und = np.c_[X[:, 0] / z * g.intr.fx + g.intr.cx, X[:, 1] / z * g.intr.fy + g.intr.cy]
        d_raw = self.offset.fb / z - g.disparity_offset_px
        self.offset.observe(ids, und, d_raw, T_cur_prev)
        g.disparity_offset_px = self.offset.offset_px

    def _process_keyframe(
        self,
        stamp_ns: int,
        gray: npt.NDArray[np.uint8],
        right_gray: npt.NDArray[np.uint8] | None,
        depth_m: F32 | None,
    ) -> FramePose:
        o = self.opts
        front, pose = self.front, self.pose
        if self.method is Method.STEREO and right_gray is None:
            raise EstimationError("method 'stereo' needs the right image in every frame")
        timer = FrameTimer()
        timer.lap("track")
        if self.prev_gray is None:
            if self._waiting_for_depth(depth_m):
                timer.lap("keyframe")
                return self._emit(stamp_ns, 0, Quality.INIT, False, timer)
            self._new_keyframe(gray, right_gray, depth_m, None)
            timer.lap("keyframe")
            self.prev_gray, pose.prev_stamp_ns = gray, stamp_ns
            return self._emit(stamp_ns, len(front.kf_X), Quality.INIT, True, timer)

        dt_s = pose.dt_s(stamp_ns)
        T_pred_cur_prev = pose.predict(dt_s)
        T_pred_cur_kf = T_pred_cur_prev @ self.T_prev_kf
        guess_px, vis = self.geo.project(T_pred_cur_kf, front.kf_X)
        guess = np.where(vis[:, None], guess_px, front.trk_px)
        # The RGB-D methods with a motion prior: tracks that land near their predicted position
        # skip the backward check (the prior-guided fit rejects what does not fit).
        has_prior = pose.T_step is not None
        prior = self.method.needs_depth and has_prior
        trust_px = np.where(vis, o.klt_trust_prior_px, 0.0) if prior else 0.0
        px, ok = front.track(self.prev_gray, gray, guess, trust_px)
        idx = np.flatnonzero(ok)
        timer.lap("track")

        motion: Motion | None = None
        self.polisher.meas = None
        shutter = self.geo.shutter
        rate = CameraRate.from_step(T_pred_cur_prev, dt_s) if shutter is not None and has_prior else None
        if len(idx) >= o.min_inliers:
            motion = self._measure(idx, px, T_pred_cur_kf, has_prior, rate, dt_s, gray, right_gray, depth_m)
        quality = Quality.GOOD
        fallback = False
        if motion is None and o.orb_fallback:
            found = front.orb_fallback(gray, T_pred_cur_kf, rate)
            if found is not None:
                # The same depth polish as the tracked steps get, at the fallback's tolerance; its
                # measurements index the ORB matches, not the tracks, so nothing is fused from them.
                motion = self.polisher.polish(
                    found.motion,
                    found.X_kf,
                    found.px_cur,
                    found.und_cur,
                    depth_m,
                    gray,
                    right_gray,
                    rate=rate,
                    reproj_px=front.fallback_reproj_px,
                )
                self.polisher.meas = None
                fallback = True
            quality = Quality.FALLBACK
        T_cur_kf = T_pred_cur_kf
        n_inl = 0
        if motion is not None:
            T_cand = motion.T_cur_ref
            T_cur_prev = T_cand @ invert(self.T_prev_kf)
            if pose.plausible(T_cur_prev, dt_s):
                T_cur_kf = T_cand
                n_inl = motion.n_inliers
                if quality is Quality.GOOD and n_inl < 2 * o.min_inliers:
                    quality = Quality.WEAK
            else:
                logger.debug(
                    "frame %d: implausible step rejected (%.3f m)", self.index, np.linalg.norm(T_cur_prev[:3, 3])
                )
                motion = None
        if motion is None:
            quality = Quality.PREDICTED
        timer.lap("motion")

        # Accept the step.
        T_cur_prev = T_cur_kf @ invert(self.T_prev_kf)
        if quality is not Quality.PREDICTED:
            pose.measured(T_cur_prev, dt_s)
        if shutter is not None:
            rate = CameraRate.from_step(T_cur_prev, dt_s)
        pose.T_world_cam = front.T_world_kf @ invert(T_cur_kf)
        self.T_prev_kf = T_cur_kf
        self.kf_since += 1
        fused = False
        meas = self.polisher.meas
        if motion is not None and not fallback and meas is not None and o.fuse_depth:
            front.fuse(idx[meas[0]], meas[1], T_cur_kf)
            fused = True
        if self.offset is not None:
            if meas is not None and motion is not None and not fallback:
                self._observe_offset(front.kf_ids[idx[meas[0]]], meas[1], T_cur_prev)
            else:
                self.offset.forget()

        # Keep the inlier tracks (all valid tracks when the estimate was not from them).
        if motion is not None and not fallback:
            keep = np.zeros(len(front.trk_px), dtype=bool)
            keep[idx[motion.inliers]] = True
        else:
            keep = ok
        front.keep(keep, px)
        parallax = np.linalg.norm(front.trk_px - front.kf_px, axis=1) if len(front.trk_px) else np.zeros(1)
        z_kf = front.kf_X[:, 2]
        if self.method is Method.STEREO and o.far_points != "drop":
            z_kf = np.minimum(z_kf, self.geo.near_depth_m())  # the baseline rule: the depth of the near points
        depth = median(z_kf) if len(z_kf) else float("inf")
        decision = o.keyframes.decide(
            parallax, len(front.trk_px), front.kf_n0, T_cur_kf, self.kf_since, depth, front.covered_fraction()
        )
        is_kf = decision.new_keyframe or fallback
        if is_kf and not fallback and self._revisit(gray, rate):
            logger.debug("frame %d: back to a kept keyframe (%s)", self.index, decision.reason)
            is_kf = False
            timer.lap("keyframe")
        elif is_kf:
            X_cur = front.kf_X @ T_cur_kf[:3, :3].T + T_cur_kf[:3, 3]
            self._new_keyframe(gray, right_gray, depth_m, X_cur, remeasure=not fused, rate=rate)
            logger.debug(
                "frame %d: keyframe (%s), %d points", self.index, decision.reason or "fallback", len(front.kf_X)
            )
            timer.lap("keyframe")
            if self.ba is not None:
                adjusted = self.ba.run(front.kf_ids, front.kf_X, o.min_depth_m)
                if adjusted is not None:
                    # The newest keyframe is the current frame: move it and its points.
                    front.T_world_kf = adjusted[0].copy()
                    pose.T_world_cam = adjusted[0].copy()
                    front.kf_X = adjusted[1]
                timer.lap("ba")
        self.prev_gray, pose.prev_stamp_ns = gray, stamp_ns
        return self._emit(stamp_ns, n_inl, quality, is_kf, timer)
