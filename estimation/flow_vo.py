"""The ``flow`` method's motion estimator: optical-flow velocity from a reference frame.

Corners of a reference frame (FAST on a grid, ranked by the Shi-Tomasi score) with a depth
each (depth image, per-point stereo, or the stereo altitude), tracked by LK into every new
frame; the 6-DoF velocity over the interval since the reference from the interaction matrix
(3-point RANSAC, reweighted refits), polished on the reference points' reprojection and
integrated to a pose. Runs behind
:class:`~estimation.pipeline.VisualOdometry`, sharing its camera geometry (tracking windows,
stereo, depth lookup) and pose track (prediction, sanity check).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from typing import Any, cast

import numpy as np
import numpy.typing as npt

from estimation.camera_geometry import CameraGeometry
from estimation.features import DescriptorExtractor
from estimation.flow import integrate_velocity, polish_motion, stereo_altitude_m, track_klt, velocity_ransac
from estimation.frontend import grid_detector
from estimation.motion import invert
from estimation.pose_track import PoseTrack
from estimation.rolling_shutter import CameraRate
from estimation.vo_options import FlowOptions, VoOptions
from estimation.vo_result import FrameTimer, Quality
from flightkit.errors import EstimationError

__all__ = ["FlowEstimator", "FlowStep"]

logger = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
F32 = npt.NDArray[np.float32]

_FLOW_POLISH_HUBER_PX = 0.25
"""Huber threshold of flow's reprojection polish: a few times the LK noise (~0.05 px on the
synthetic patterns). Measured against 1 px with flow_ref_px 15 (point-sampling renderer): ATE
lower on 5 of the 6 synthetic runs (e.g. the rectangle at 320x240 4.3 -> 3.8 mm), per-step
error 5-15 % lower on all six (docs/estimation-log.md, "ninth pass")."""


@dataclass(frozen=True, slots=True)
class FlowStep:
    """What one frame of ``flow`` gave: inliers, quality, and whether it became the reference."""

    n_inliers: int
    quality: Quality
    new_reference: bool


class FlowEstimator:
    """The state and steps of ``flow``: the reference frame and the stereo altitude.

    Args:
        geo: the run's camera (tracking windows, depth lookup, sparse stereo).
        opts: the shared options; ``fo``: flow's own.
        pose: the run's pose (moved by :meth:`process`).
        orb: ORB extractor (for the stereo altitude).
        rng: RANSAC's random generator.
    """

    def __init__(
        self,
        geo: CameraGeometry,
        opts: VoOptions,
        fo: FlowOptions,
        pose: PoseTrack,
        orb: DescriptorExtractor,
        rng: np.random.Generator,
    ) -> None:
        self.geo, self.opts, self.fo, self.pose, self.orb, self.rng = geo, opts, fo, pose, orb, rng
        self.ref: _FlowRef | None = None
        self.altitude_m = math.nan
        self._warned_altitude = False
        # Its tracks live from reference to reference: the corners LK tracks best, spread out.
        self.grid = grid_detector(geo, opts, score="shi-tomasi")

    def process(
        self,
        index: int,
        stamp_ns: int,
        gray: npt.NDArray[np.uint8],
        right_gray: npt.NDArray[np.uint8] | None,
        depth_m: F32 | None,
        timer: FrameTimer,
    ) -> FlowStep:
        """Frame ``index``: track the reference frame's points into this frame, the velocity over
        the interval since the reference from their motion, the pose = the reference pose moved
        by that velocity for that time (``pose`` updated, its stamp too). The reference moves on
        to this frame once the points moved ``ref_px`` (median), too few remain, or the estimate
        failed.

        Raises:
            EstimationError: neither depth nor a stereo pair.
        """
        geo, o, fo, pose = self.geo, self.opts, self.fo, self.pose
        per_point_stereo = depth_m is None and fo.depth == "stereo"
        if (
            depth_m is None
            and not per_point_stereo
            and (index % max(1, fo.altitude_every) == 0 or not math.isfinite(self.altitude_m))
        ):
            if right_gray is None or geo.rig is None:
                raise EstimationError("method 'flow' needs a depth image or a stereo pair (for the altitude)")
            z, _ = stereo_altitude_m(gray, right_gray, geo.rig.fx, geo.rig.baseline_m, self.orb)
            if math.isfinite(z) and o.min_depth_m <= z <= o.max_depth_m:
                self.altitude_m = z
            elif not math.isfinite(self.altitude_m) and not self._warned_altitude:
                self._warned_altitude = True
                logger.warning(
                    "flow: no stereo altitude in %.1f-%.0f m from this pair (got %.2f m); the motion cannot be "
                    "estimated until there is one (FlowOptions.depth='altitude' needs a camera looking down at "
                    "flat ground)",
                    o.min_depth_m,
                    o.max_depth_m,
                    z,
                )
        timer.lap("track")
        if self.ref is None:
            self._new_ref(stamp_ns, gray, right_gray, depth_m, np.empty((0, 2), np.float32), np.empty((0, 2)))
            timer.lap("keyframe")
            pose.prev_stamp_ns = stamp_ns
            return FlowStep(0, Quality.INIT, True)
        ref = self.ref
        dt_s = pose.dt_s(stamp_ns)  # since the previous frame
        dt_ref_s = max((stamp_ns - ref.stamp_ns) * 1e-9, 1e-4)  # since the reference
        # Each track starts where it was in the previous frame, moved as it moved then (none
        # when the reference is the previous frame: LK's own pyramid finds the motion).
        one_step = ref.stamp_ns == pose.prev_stamp_ns
        px, ok = track_klt(
            geo.pyramids(ref.gray),
            geo.pyramids(gray),
            ref.pts,
            o.fb_max_px,
            geo.klt_win,
            geo.klt_levels,
            guess=None if one_step else (ref.trk + ref.step_px).astype(np.float32),
            back_levels=geo.klt_back_levels,
            max_iters=o.klt_iters,
        )
        tracked = np.flatnonzero(ok)
        idx = tracked[np.isfinite(ref.Z[tracked])]  # tracked with a depth: the velocity's points
        timer.lap("track")
        quality = Quality.PREDICTED
        n_inl = 0
        T_pred_cur_prev = pose.predict(dt_s)
        T_world_cur = pose.T_world_cam @ invert(T_pred_cur_prev)
        # A rolling shutter: the current pixels moved to the stamp with the predicted rate, then
        # (for the polish) with the rate the estimate implies.
        rate = CameraRate.from_step(T_pred_cur_prev, dt_s) if geo.shutter and pose.T_step is not None else None
        if len(idx) >= o.min_inliers:
            und_lens = geo.undistort(px[idx])  # once: both rates move it to the stamp
            x0, x1 = ref.xn[idx], self._normalised(px[idx], rate, ref.Z[idx], und_lens)
            thr = fo.threshold_px / geo.intr.fx / dt_ref_s
            twist, inl = velocity_ransac(x0, x1, ref.Z[idx], dt_ref_s, thr, rng=self.rng, robust_iters=fo.robust_iters)
            if np.count_nonzero(inl) >= o.min_inliers:
                T_ref_cur = integrate_velocity(twist, dt_ref_s)
                if geo.shutter is not None:
                    T_step = invert(ref.T_world_cam @ T_ref_cur) @ pose.T_world_cam
                    rate = CameraRate.from_step(T_step, dt_s)
                    x1 = self._normalised(px[idx], rate, ref.Z[idx], und_lens)
                    if not ref.has_rate:
                        # The first reference was made before any motion: it gets this step's rate.
                        ref = replace(ref, xn=self._normalised(ref.pts, rate, ref.Z), has_rate=True)
                        self.ref = ref
                        x0 = ref.xn[idx]
                if fo.polish:
                    T_ref_cur = polish_motion(
                        T_ref_cur, x0[inl], ref.Z[idx][inl], x1[inl], _FLOW_POLISH_HUBER_PX / geo.intr.fx
                    )
                T_cand = ref.T_world_cam @ T_ref_cur
                if pose.plausible(invert(T_cand) @ pose.T_world_cam, dt_s):
                    T_world_cur = T_cand
                    n_inl = int(np.count_nonzero(inl))
                    quality = Quality.GOOD if n_inl >= 2 * o.min_inliers else Quality.WEAK
        timer.lap("motion")
        T_cur_prev = invert(T_world_cur) @ pose.T_world_cam
        if quality is not Quality.PREDICTED:
            pose.measured(T_cur_prev, dt_s)
        rate = CameraRate.from_step(T_cur_prev, dt_s) if geo.shutter is not None else None
        pose.T_world_cam = T_world_cur
        step_px = px[tracked] - ref.trk[tracked]
        moved = px[tracked] - ref.pts[tracked]
        renew = (
            quality is Quality.PREDICTED
            or len(tracked) < o.max_features // 2
            or float(np.median(np.einsum("ij,ij->i", moved, moved))) >= fo.ref_px * fo.ref_px
        )
        if renew:
            self._new_ref(stamp_ns, gray, right_gray, depth_m, px[tracked], step_px, rate)
            timer.lap("keyframe")
        else:
            self.ref = _FlowRef(
                ref.gray,
                ref.stamp_ns,
                ref.T_world_cam,
                ref.pts[tracked],
                ref.xn[tracked],
                ref.Z[tracked],
                px[tracked],
                step_px,
                ref.has_rate,
            )
        pose.prev_stamp_ns = stamp_ns
        return FlowStep(n_inl, quality, renew)

    def _normalised(
        self, px: F32, rate: CameraRate | None = None, z_m: F64 | None = None, und_lens: F64 | None = None
    ) -> F64:
        """Normalised image coordinates ``K^-1 [u, v, 1]`` (undistorted; at the stamp with the
        camera's ``rate``, a rolling shutter, ``z_m`` the points' depths) of pixels, (N, 2);
        ``und_lens``: their undistorted pixels when already computed."""
        geo = self.geo
        und = geo.undistort(px, rate, z_m) if und_lens is None else geo.at_stamp(und_lens, px, rate, z_m)
        return cast(F64, np.c_[(und[:, 0] - geo.intr.cx) / geo.intr.fx, (und[:, 1] - geo.intr.cy) / geo.intr.fy])

    def _new_ref(
        self,
        stamp_ns: int,
        gray: npt.NDArray[np.uint8],
        right_gray: npt.NDArray[np.uint8] | None,
        depth_m: F32 | None,
        kept_px: F32,
        kept_step_px: npt.NDArray[np.floating[Any]],
        rate: CameraRate | None = None,
    ) -> None:
        """This frame becomes the flow reference: the tracks kept, topped up with new corners
        when fewer than half remain, each with its depth here (``rate``: the camera's, for a
        rolling shutter)."""
        geo, o = self.geo, self.opts
        pts = np.ascontiguousarray(kept_px, dtype=np.float32).reshape(-1, 2)
        step = np.asarray(kept_step_px, dtype=np.float64).reshape(-1, 2)
        if len(pts) < o.max_features // 2:
            new = self.grid.detect(gray, existing=pts, budget=o.max_features - len(pts))
            pts = np.concatenate([pts, new]) if len(pts) else new
            step = np.concatenate([step, np.zeros((len(new), 2))])
        if depth_m is not None:
            X, ok = geo.depth_points(depth_m, pts, rate)
            Z = np.where(ok, X[:, 2], np.nan)
        elif self.fo.depth == "stereo":
            if right_gray is None or geo.rig is None:
                raise EstimationError("FlowOptions.depth='stereo' needs the right image in every frame")
            X, ok = geo.points_3d(pts, right_gray, gray, None, self._init_disparity(), rate=rate)
            Z = np.where(ok, X[:, 2], np.nan)
        else:
            Z = np.full(len(pts), self.altitude_m)
        xn = self._normalised(pts, rate, Z)
        self.ref = _FlowRef(gray, stamp_ns, self.pose.T_world_cam.copy(), pts, xn, Z, pts, step, rate is not None)

    def _init_disparity(self) -> float:
        """Disparity to start sparse stereo from: that of the current reference's median depth."""
        rig = self.geo.rig
        assert rig is not None
        ref = self.ref
        z = ref.Z[np.isfinite(ref.Z)] if ref is not None else np.empty(0)
        return float(rig.fx * rig.baseline_m / np.median(z)) if len(z) else 0.0


@dataclass(frozen=True, slots=True, eq=False)
class _FlowRef:
    """The flow method's reference frame: its image, time and pose, its points (pixels,
    normalised coordinates, depth in metres, NaN where unknown), and where each point was
    last tracked to and how far it moved in that frame (the next frame's guess); ``has_rate``:
    its points were moved to its stamp with the camera's rate (a rolling shutter)."""

    gray: npt.NDArray[np.uint8]
    stamp_ns: int
    T_world_cam: F64
    pts: F32
    xn: F64
    Z: F64
    trk: F32
    step_px: npt.NDArray[np.floating[Any]]  # float32 from tracking, float64 when topped up
    has_rate: bool = False
