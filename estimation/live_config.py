"""What live VO runs and what it tells the autopilot: :class:`LiveVoConfig`, and each estimate as
the autopilot's external pose with an uncertainty from how it was obtained."""

from __future__ import annotations

import math
from dataclasses import dataclass

from estimation.vo_options import Method
from estimation.vo_result import FramePose, Quality
from flightkit.errors import EstimationError
from flightkit.frames import Transform
from flightkit.link.base import ExternalPose, ExternalPoseKind

__all__ = ["MAX_VISION_RATE_HZ", "LiveVoConfig", "external_pose_from_frame", "vision_uncertainty"]

MAX_VISION_RATE_HZ = 50.0
"""Autopilot estimators are tuned for 30-50 Hz of external pose (PX4 EKF2)."""


@dataclass(frozen=True, slots=True)
class LiveVoConfig:
    """How :class:`LiveVo` runs and what it sends.

    Attributes:
        method: VO method (``rgbd-pnp``, ``rgbd-kabsch``, ``rgbd-essential``: they need depth).
        vision_rate_hz: most vision poses per second sent to the autopilot (<= 50); each VO
            estimate is sent at most once, so the rate is also bounded by the camera's.
        kind: VISION_POSITION_ESTIMATE or ODOMETRY.
        color_camera, depth_camera: camera names on the bus.
        pair_tolerance_ns: colour and depth whose stamps differ by more are not paired.
        base_pos_std_m, base_rot_std_rad: reported uncertainty of a good estimate.
        ref_inliers: inlier count at which an estimate counts as fully good.
        publish_odometry: publish each estimate on ``<ns>/odometry/<method>``.
        compute_budget_s: on a stall-limited simulated clock, one frame's estimate takes at most
            this much simulated time (the clock waits for a slower host); None: what it takes.
    """

    method: str = "rgbd-pnp"
    vision_rate_hz: float = 30.0
    kind: ExternalPoseKind = ExternalPoseKind.VISION_POSITION_ESTIMATE
    color_camera: str = "color"
    depth_camera: str = "depth"
    pair_tolerance_ns: int = 1_000_000
    base_pos_std_m: float = 0.02
    base_rot_std_rad: float = 0.01
    ref_inliers: int = 100
    publish_odometry: bool = True
    compute_budget_s: float | None = None

    def __post_init__(self) -> None:
        try:
            method = Method(self.method)
        except ValueError as exc:
            names = ", ".join(m.value for m in Method if m.needs_depth)
            raise EstimationError(f"unknown VO method {self.method!r}; live VO uses one of {names}") from exc
        if not method.needs_depth:
            names = ", ".join(m.value for m in Method if m.needs_depth)
            raise EstimationError(
                f"live VO method {self.method!r} needs a stereo pair, which LiveVo does not subscribe to; "
                f"use one of {names}"
            )
        if not (math.isfinite(self.vision_rate_hz) and 0.0 < self.vision_rate_hz <= MAX_VISION_RATE_HZ):
            raise EstimationError(
                f"vision_rate_hz {self.vision_rate_hz!r} is outside (0, {MAX_VISION_RATE_HZ:g}] Hz; "
                "autopilot estimators want 30-50 Hz"
            )
        if self.ref_inliers < 1 or self.base_pos_std_m <= 0 or self.base_rot_std_rad <= 0:
            raise EstimationError("ref_inliers, base_pos_std_m and base_rot_std_rad must be positive")
        if self.compute_budget_s is not None and not (0.0 < self.compute_budget_s < math.inf):
            raise EstimationError(
                f"compute_budget_s {self.compute_budget_s!r} must be a positive number of seconds or None"
            )


def vision_uncertainty(
    quality: Quality,
    n_inliers: int,
    *,
    base_pos_std_m: float = 0.02,
    base_rot_std_rad: float = 0.01,
    ref_inliers: int = 100,
) -> tuple[float, float, int]:
    """Standard deviations and a 0-100 quality for an estimate, from how it was obtained.

    A good estimate with at least ``ref_inliers`` inliers gets the base deviations; fewer
    inliers scale them by ``sqrt(ref_inliers / n)`` (at most 4x), as the error of a
    least-squares pose falls with the square root of the number of points. Weak estimates
    (few inliers) count three times worse, ORB-fallback ones twice; a constant-velocity
    prediction (tracking failed) gets 0.5 m / 0.2 rad and quality 1, the worst valid value
    (MAVLink ODOMETRY: 0 = unknown, -1 = failed), so an EKF can gate it out.

    Returns:
        ``(pos_std_m, rot_std_rad, quality_pct)``.
    """
    if quality is Quality.PREDICTED:
        return 0.5, 0.2, 1
    if quality is Quality.INIT:
        return base_pos_std_m, base_rot_std_rad, 100
    n = max(1, int(n_inliers))
    scale = min(4.0, max(1.0, math.sqrt(ref_inliers / n)))
    pct = 100 if n >= ref_inliers else int(round(50 + 50 * n / ref_inliers))
    if quality is Quality.WEAK:
        scale *= 3.0
        pct = min(pct, 30)
    elif quality is Quality.FALLBACK:
        scale *= 2.0
        pct = min(pct, 50)
    return base_pos_std_m * scale, base_rot_std_rad * scale, pct


def external_pose_from_frame(pose: FramePose, config: LiveVoConfig | None = None) -> ExternalPose:
    """The autopilot's view of one VO estimate: the body pose in the world, stamped with the
    frame's capture time (not the time the estimate was finished), with its uncertainty."""
    cfg = config or LiveVoConfig()
    pos_std, rot_std, pct = vision_uncertainty(
        pose.quality,
        pose.n_inliers,
        base_pos_std_m=cfg.base_pos_std_m,
        base_rot_std_rad=cfg.base_rot_std_rad,
        ref_inliers=cfg.ref_inliers,
    )
    return ExternalPose(
        stamp_ns=int(pose.stamp_ns),
        T_world_body=Transform.from_matrix(pose.T_world_body),
        pos_std_m=pos_std,
        rot_std_rad=rot_std,
        quality_pct=pct,
    )
