"""The ``flow`` method's motion estimator: optical-flow velocity from a reference frame.

Shi-Tomasi corners of a reference frame with a depth each (depth image, per-point stereo, or
the stereo altitude), tracked by LK into every new frame; the 6-DoF velocity over the interval
since the reference from the interaction matrix (3-point RANSAC, reweighted refits), polished
on the reference points' reprojection and integrated to a pose. Runs behind
:class:`~estimation.pipeline.VisualOdometry`, whose front end (tracker, stereo, depth lookup,
prediction, sanity check, output) it shares.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, cast

import cv2
import numpy as np
import numpy.typing as npt

from estimation.features import shi_tomasi
from estimation.flow import integrate_velocity, polish_motion, stereo_altitude_m, track_klt, velocity_ransac
from estimation.motion import invert
from estimation.vo_result import FramePose, FrameTimer, Quality
from flightkit.errors import EstimationError

if TYPE_CHECKING:
    from estimation.pipeline import VisualOdometry

__all__ = ["FlowEstimator"]

logger = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
F32 = npt.NDArray[np.float32]

_FLOW_POLISH_HUBER_PX = 0.25
"""Huber threshold of flow's reprojection polish: a few times the LK noise (~0.05 px on the
synthetic patterns). Measured against 1 px with flow_ref_px 15 (point-sampling renderer): ATE
lower on 5 of the 6 synthetic runs (e.g. the rectangle at 320x240 4.3 -> 3.8 mm), per-step
error 5-15 % lower on all six (docs/estimation-log.md, "ninth pass")."""


class FlowEstimator:
    """The state and steps of ``flow`` for one :class:`~estimation.pipeline.VisualOdometry`
    (its front end, ``vo``): the reference frame and the stereo altitude."""

    def __init__(self, vo: VisualOdometry) -> None:
        self.vo = vo
        self.ref: _FlowRef | None = None
        self.altitude_m = math.nan
        self._warned_altitude = False

    def process(
        self,
        stamp_ns: int,
        gray: npt.NDArray[np.uint8],
        right_gray: npt.NDArray[np.uint8] | None,
        depth_m: F32 | None,
    ) -> FramePose:
        """Flow: track the reference frame's points into this frame, the velocity over the
        interval since the reference from their motion, the pose = the reference pose moved
        by that velocity for that time. The reference moves on to this frame once the points
        moved ``flow_ref_px`` (median), too few remain, or the estimate failed."""
        vo = self.vo
        o = vo.opts
        timer = FrameTimer()
        per_point_stereo = depth_m is None and o.flow_depth == "stereo"
        if (
            depth_m is None
            and not per_point_stereo
            and (vo.index % max(1, o.altitude_every) == 0 or not math.isfinite(self.altitude_m))
        ):
            if right_gray is None or vo.rig is None:
                raise EstimationError("method 'flow' needs a depth image or a stereo pair (for the altitude)")
            z, _ = stereo_altitude_m(gray, right_gray, vo.rig.fx, vo.rig.baseline_m, vo.orb)
            if math.isfinite(z) and o.min_depth_m <= z <= o.max_depth_m:
                self.altitude_m = z
            elif not math.isfinite(self.altitude_m) and not self._warned_altitude:
                self._warned_altitude = True
                logger.warning(
                    "flow: no stereo altitude in %.1f-%.0f m from this pair (got %.2f m); the motion cannot be "
                    "estimated until there is one (flow_depth='altitude' needs a camera looking down at flat ground)",
                    o.min_depth_m,
                    o.max_depth_m,
                    z,
                )
        timer.lap("track")
        if self.ref is None:
            self._new_ref(stamp_ns, gray, right_gray, depth_m, np.empty((0, 2), np.float32), np.empty((0, 2)))
            timer.lap("keyframe")
            vo.prev_stamp_ns = stamp_ns
            return vo._emit(stamp_ns, 0, Quality.INIT, True, timer)
        ref = self.ref
        dt_s = max((stamp_ns - vo.prev_stamp_ns) * 1e-9, 1e-4)  # since the previous frame
        dt_ref_s = max((stamp_ns - ref.stamp_ns) * 1e-9, 1e-4)  # since the reference
        # Each track starts where it was in the previous frame, moved as it moved then (none
        # when the reference is the previous frame: LK's own pyramid finds the motion).
        one_step = ref.stamp_ns == vo.prev_stamp_ns
        px, ok = track_klt(
            ref.gray,
            gray,
            ref.pts,
            o.fb_max_px,
            vo.klt_win,
            vo.klt_levels,
            guess=None if one_step else (ref.trk + ref.step_px).astype(np.float32),
            back_levels=vo.klt_back_levels,
            max_iters=o.klt_iters,
        )
        tracked = np.flatnonzero(ok)
        idx = tracked[np.isfinite(ref.Z[tracked])]  # tracked with a depth: the velocity's points
        timer.lap("track")
        quality = Quality.PREDICTED
        n_inl = 0
        T_world_cur = vo.T_world_cam @ invert(vo._predict(dt_s))
        if len(idx) >= o.min_inliers:
            x0, x1 = ref.xn[idx], self._normalised(px[idx])
            thr = o.flow_threshold_px / vo.intr.fx / dt_ref_s
            twist, inl = velocity_ransac(
                x0, x1, ref.Z[idx], dt_ref_s, thr, rng=vo.rng, robust_iters=o.flow_robust_iters
            )
            if np.count_nonzero(inl) >= o.min_inliers:
                T_ref_cur = integrate_velocity(twist, dt_ref_s)
                if o.flow_polish:
                    T_ref_cur = polish_motion(
                        T_ref_cur, x0[inl], ref.Z[idx][inl], x1[inl], _FLOW_POLISH_HUBER_PX / vo.intr.fx
                    )
                T_cand = ref.T_world_cam @ T_ref_cur
                if vo._plausible(invert(T_cand) @ vo.T_world_cam, dt_s):
                    T_world_cur = T_cand
                    n_inl = int(np.count_nonzero(inl))
                    quality = Quality.GOOD if n_inl >= 2 * o.min_inliers else Quality.WEAK
        timer.lap("motion")
        if quality is not Quality.PREDICTED:
            vo.T_step, vo.step_dt_s = invert(T_world_cur) @ vo.T_world_cam, dt_s
        vo.T_world_cam = T_world_cur
        step_px = px[tracked] - ref.trk[tracked]
        moved = px[tracked] - ref.pts[tracked]
        renew = (
            quality is Quality.PREDICTED
            or len(tracked) < o.max_features // 2
            or float(np.median(np.einsum("ij,ij->i", moved, moved))) >= o.flow_ref_px * o.flow_ref_px
        )
        if renew:
            self._new_ref(stamp_ns, gray, right_gray, depth_m, px[tracked], step_px)
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
            )
        vo.prev_stamp_ns = stamp_ns
        return vo._emit(stamp_ns, n_inl, quality, renew, timer)

    def _normalised(self, px: F32) -> F64:
        """Normalised image coordinates ``K^-1 [u, v, 1]`` (undistorted) of pixels, (N, 2)."""
        vo = self.vo
        und = vo._undistort(px)
        return cast(F64, np.c_[(und[:, 0] - vo.intr.cx) / vo.intr.fx, (und[:, 1] - vo.intr.cy) / vo.intr.fy])

    def _new_ref(
        self,
        stamp_ns: int,
        gray: npt.NDArray[np.uint8],
        right_gray: npt.NDArray[np.uint8] | None,
        depth_m: F32 | None,
        kept_px: F32,
        kept_step_px: npt.NDArray[np.floating[Any]],
    ) -> None:
        """This frame becomes the flow reference: the tracks kept, topped up with new corners
        when fewer than half remain, each with its depth here."""
        vo = self.vo
        o = vo.opts
        pts = np.ascontiguousarray(kept_px, dtype=np.float32).reshape(-1, 2)
        step = np.asarray(kept_step_px, dtype=np.float64).reshape(-1, 2)
        if len(pts) < o.max_features // 2:
            mask = None
            if len(pts):
                mask = np.full(gray.shape, 255, np.uint8)
                for x, y in pts:
                    cv2.circle(mask, (int(x), int(y)), 8, 0, -1)
            new = shi_tomasi(gray, o.max_features - len(pts), 0.01, max(5.0, vo.intr.width / 60), mask)
            pts = np.concatenate([pts, new]) if len(pts) else new
            step = np.concatenate([step, np.zeros((len(new), 2))])
        if depth_m is not None:
            Z = vo._depth_at(depth_m, pts)
        elif o.flow_depth == "stereo":
            if right_gray is None or vo.rig is None:
                raise EstimationError("flow_depth='stereo' needs the right image in every frame")
            X, ok = vo._points_3d(pts, right_gray, gray, None, self._init_disparity())
            Z = np.where(ok, X[:, 2], np.nan)
        else:
            Z = np.full(len(pts), self.altitude_m)
        self.ref = _FlowRef(gray, stamp_ns, vo.T_world_cam.copy(), pts, self._normalised(pts), Z, pts, step)

    def _init_disparity(self) -> float:
        """Disparity to start sparse stereo from: that of the current reference's median depth."""
        vo = self.vo
        assert vo.rig is not None
        ref = self.ref
        z = ref.Z[np.isfinite(ref.Z)] if ref is not None else np.empty(0)
        return float(vo.rig.fx * vo.rig.baseline_m / np.median(z)) if len(z) else 0.0


@dataclass(frozen=True, slots=True, eq=False)
class _FlowRef:
    """The flow method's reference frame: its image, time and pose, its points (pixels,
    normalised coordinates, depth in metres, NaN where unknown), and where each point was
    last tracked to and how far it moved in that frame (the next frame's guess)."""

    gray: npt.NDArray[np.uint8]
    stamp_ns: int
    T_world_cam: F64
    pts: F32
    xn: F64
    Z: F64
    trk: F32
    step_px: npt.NDArray[np.floating[Any]]  # float32 from tracking, float64 when topped up
