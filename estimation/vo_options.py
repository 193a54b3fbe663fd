"""Which VO method runs and how it is tuned: :class:`Method` and :class:`VoOptions`.

Each option is one line here; how each default was chosen is in docs/estimation-log.md
("VoOptions: why each default").
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

from estimation.keyframes import KeyframePolicy
from flightkit.errors import EstimationError

__all__ = ["Method", "VoOptions"]


class Method(enum.StrEnum):
    RGBD_PNP = "rgbd-pnp"
    RGBD_ESSENTIAL = "rgbd-essential"
    RGBD_KABSCH = "rgbd-kabsch"
    STEREO = "stereo"
    FLOW = "flow"

    @property
    def needs_depth(self) -> bool:
        return self in (Method.RGBD_PNP, Method.RGBD_ESSENTIAL, Method.RGBD_KABSCH)


@dataclass(frozen=True, slots=True)
class VoOptions:
    """Tuning of the pipelines (defaults suit 320x240 to 1280x720 at 10-60 Hz). How each default
    was chosen, with measurements: docs/estimation-log.md, "VoOptions: why each default".

    Attributes:
        max_features: corners kept per keyframe.
        cell_px: grid cell of the corner detector, px (0: from the image size and the budget).
        fast_threshold: FAST threshold (grey levels).
        klt_win_px, klt_levels: LK window, px (0: 9 up to 400 px wide, else 11); levels (None: 3).
        klt_back_levels: pyramid levels of the backward (checking) LK pass (at most ``klt_levels``).
        klt_iters: LK iterations per pyramid level at most.
        stereo_win_px: LK window of the left-right disparity search, px (0: the tracking window).
        fb_max_px: forward-backward tolerance of tracks, px.
        klt_trust_prior_px: RGB-D: tracks within this of their prediction skip the backward check.
        pnp_method: ``"iterative"``, ``"epnp"`` or ``"sqpnp"``: the fit on all inliers.
        pnp_kernel: PnP RANSAC's minimal solver: None (``pnp_method``), ``"ap3p"`` or ``"p3p"``.
        reproj_px: PnP RANSAC and inlier threshold, px.
        pnp_prior_gate_px, pnp_prior_min_fraction: rgbd-pnp skips RANSAC when this fraction of the
            tracks lies within the gate (px) of the prediction (0: always RANSAC).
        inliers: ``"ransac"`` or ``"rigidity"`` (stereo: max-clique of rigid pairs first).
        kabsch_threshold_m: rgbd-kabsch inlier threshold at 1 m (grows with depth squared).
        kabsch_polish: rgbd-kabsch: polish the rigid fit like PnP's pose and fuse the depth.
        kabsch_first_batch: rgbd-kabsch: hypotheses in RANSAC's first batch (then 64 per batch).
        kabsch_prior_gate, kabsch_prior_min_fraction: rgbd-kabsch skips RANSAC when the prediction
            explains this fraction of the pairs (gate in inlier thresholds; 0: always RANSAC).
        essential_threshold_px: epipolar (Sampson) inlier threshold, px.
        essential_min_parallax_px: rgbd-essential solves by PnP below this median parallax, px.
        essential_cheirality: rgbd-essential's pick of the four motions: ``"depth"`` or ``"opencv"``.
        essential_prior_gate_px, essential_prior_min_fraction, essential_prior_iterations: rgbd-essential
            refines the prediction (Sampson LM) instead of RANSAC when it explains this fraction.
        essential_pnp_prior: rgbd-essential's PnP steps try the prior-guided PnP before RANSAC.
        min_inliers: fewer inliers -> the estimate is rejected (the frame is ``PREDICTED``).
        max_speed_m_s, max_rate_rad_s: sanity limits of one step (faster -> ``PREDICTED``).
        min_depth_m, max_depth_m: accepted depth range (stereo and depth images), m.
        init_min_depth_fraction: RGB-D: hold the start pose (``INIT``) until this fraction of the
            depth image is in range (0: start at once).
        max_depth_baselines: stereo points farther than this many baselines are not used.
        min_disparity_px: stereo points with a smaller disparity are not used, px.
        refine_with_depth: polish poses on the current frame's depth too (``motion.refine_pose``).
        fuse_depth: fuse each frame's depth of tracked points into their 3D estimates.
        stereo_fb_check: also check left-right stereo matches right-to-left.
        orb_fallback: match ORB against the keyframe when tracking fails (``FALLBACK``).
        keyframes: the keyframe policy (:class:`~estimation.keyframes.KeyframePolicy`).
        parallax_ref_width_px: rgbd-pnp/-essential on narrower images: parallax scaled to this width.
        ba_window: local bundle adjustment over this many keyframes (0: off).
        flow_threshold_px: flow RANSAC threshold, px of image motion since the reference.
        flow_ref_px: flow's reference moves on once its points moved this far (median px; 0: always).
        flow_polish: flow: polish the motion since the reference on its points' reprojection.
        flow_robust_iters: flow: Cauchy-reweighted refits of the velocity after RANSAC.
        flow_depth: flow on stereo: ``"stereo"`` (each point's depth) or ``"altitude"`` (one, looking down).
        altitude_every: flow, ``flow_depth="altitude"``: recompute the altitude every N frames.
        seed: RANSAC random seed (repeatable runs).
    """

    max_features: int = 300
    cell_px: int = 0
    fast_threshold: int = 20
    klt_win_px: int = 0
    klt_levels: int | None = None
    klt_back_levels: int = 1
    klt_iters: int = 10
    stereo_win_px: int = 0
    fb_max_px: float = 1.0
    klt_trust_prior_px: float = 2.0
    pnp_method: str = "iterative"
    pnp_kernel: str | None = None
    reproj_px: float = 3.0
    pnp_prior_gate_px: float = 8.0
    pnp_prior_min_fraction: float = 0.9
    inliers: str = "ransac"
    kabsch_threshold_m: float = 0.02
    kabsch_polish: bool = True
    kabsch_first_batch: int = 8
    kabsch_prior_gate: float = 2.0
    kabsch_prior_min_fraction: float = 0.9
    essential_threshold_px: float = 1.0
    essential_min_parallax_px: float = 3.0
    essential_cheirality: str = "depth"
    essential_prior_gate_px: float = 2.0
    essential_prior_min_fraction: float = 0.9
    essential_prior_iterations: int = 1
    essential_pnp_prior: bool = False
    min_inliers: int = 12
    max_speed_m_s: float = 40.0
    max_rate_rad_s: float = 8.0
    min_depth_m: float = 0.2
    max_depth_m: float = 60.0
    init_min_depth_fraction: float = 0.0
    min_disparity_px: float = 3.0
    max_depth_baselines: float = 60.0
    refine_with_depth: bool = True
    fuse_depth: bool = True
    stereo_fb_check: bool = False
    orb_fallback: bool = True
    keyframes: KeyframePolicy = field(default_factory=KeyframePolicy)
    parallax_ref_width_px: int = 640
    ba_window: int = 0
    flow_threshold_px: float = 1.0
    flow_robust_iters: int = 3
    flow_depth: str = "stereo"
    flow_ref_px: float = 15.0
    flow_polish: bool = True
    altitude_every: int = 5
    seed: int = 0

    def __post_init__(self) -> None:
        if self.inliers not in ("ransac", "rigidity"):
            raise EstimationError(f"VoOptions.inliers is {self.inliers!r}; use 'ransac' or 'rigidity'")
        if self.pnp_method not in ("iterative", "epnp", "sqpnp"):
            raise EstimationError(f"VoOptions.pnp_method is {self.pnp_method!r}; use iterative, epnp or sqpnp")
        if self.pnp_kernel not in (None, "p3p", "ap3p"):
            raise EstimationError(f"VoOptions.pnp_kernel is {self.pnp_kernel!r}; use 'ap3p', 'p3p' or None")
        if self.flow_depth not in ("altitude", "stereo"):
            raise EstimationError(f"VoOptions.flow_depth is {self.flow_depth!r}; use 'altitude' or 'stereo'")
        if not self.flow_ref_px >= 0:
            raise EstimationError(
                f"VoOptions.flow_ref_px is {self.flow_ref_px}; use pixels >= 0 (0: track from the previous frame)"
            )
        if self.essential_cheirality not in ("opencv", "depth"):
            raise EstimationError(
                f"VoOptions.essential_cheirality is {self.essential_cheirality!r}; use 'opencv' or 'depth'"
            )
        if (
            self.essential_prior_gate_px < 0
            or not 0 < self.essential_prior_min_fraction <= 1
            or self.essential_prior_iterations < 1
        ):
            raise EstimationError(
                f"VoOptions.essential_prior_gate_px={self.essential_prior_gate_px}, "
                f"essential_prior_min_fraction={self.essential_prior_min_fraction}, "
                f"essential_prior_iterations={self.essential_prior_iterations}; use a distance >= 0 "
                "(0: off), a fraction in (0, 1] and at least 1 iteration"
            )
        if self.kabsch_prior_gate < 0 or not 0 < self.kabsch_prior_min_fraction <= 1:
            raise EstimationError(
                f"VoOptions.kabsch_prior_gate={self.kabsch_prior_gate}, kabsch_prior_min_fraction="
                f"{self.kabsch_prior_min_fraction}; use a gate >= 0 (0: off) and a fraction in (0, 1]"
            )
        if self.kabsch_first_batch < 1:
            raise EstimationError(
                f"VoOptions.kabsch_first_batch is {self.kabsch_first_batch}; use at least 1 (8 is typical)"
            )
        if self.max_features < 20:
            raise EstimationError(f"VoOptions.max_features is {self.max_features}; use at least 20 (300 is typical)")
        if (
            0 < self.klt_win_px < 5
            or self.klt_win_px < 0
            or (self.klt_levels is not None and self.klt_levels < 0)
            or self.klt_back_levels < 0
            or self.klt_iters < 1
        ):
            raise EstimationError(
                f"VoOptions.klt_win_px={self.klt_win_px}, klt_levels={self.klt_levels}, "
                f"klt_back_levels={self.klt_back_levels}, klt_iters={self.klt_iters}; use a window "
                ">= 5 px (0: automatic), levels >= 0 (None: automatic) and at least 1 iteration"
            )
        if self.pnp_prior_gate_px < 0 or self.klt_trust_prior_px < 0 or not 0 < self.pnp_prior_min_fraction <= 1:
            raise EstimationError(
                f"VoOptions.pnp_prior_gate_px={self.pnp_prior_gate_px}, klt_trust_prior_px="
                f"{self.klt_trust_prior_px}, pnp_prior_min_fraction={self.pnp_prior_min_fraction}; use "
                "distances >= 0 (0: off) and a fraction in (0, 1]"
            )
        if not 0.0 <= self.init_min_depth_fraction <= 1.0:
            raise EstimationError(
                f"VoOptions.init_min_depth_fraction is {self.init_min_depth_fraction}; use a fraction in [0, 1]"
            )
        if not 0 < self.min_depth_m < self.max_depth_m:
            raise EstimationError(
                f"VoOptions depth range [{self.min_depth_m}, {self.max_depth_m}] m is empty; set 0 < min < max"
            )
