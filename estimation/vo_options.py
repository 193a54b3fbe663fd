"""Which VO method runs and how it is tuned: :class:`Method`, the shared :class:`VoOptions` and
one options object per motion estimator (:class:`PnpOptions`, :class:`EssentialOptions`,
:class:`KabschOptions`, :class:`FlowOptions`).

Each option is one line here; how each default was chosen is in docs/estimation-log.md
("VoOptions: why each default").
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field, replace
from typing import TypeVar

from estimation.keyframes import KeyframePolicy
from flightkit.errors import EstimationError

_T = TypeVar("_T")

__all__ = ["EssentialOptions", "EstimatorOptions", "FlowOptions", "KabschOptions", "Method", "PnpOptions", "VoOptions"]


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
class PnpOptions:
    """``stereo`` and ``rgbd-pnp``: PnP on the keyframe's 3D points.

    Attributes:
        prior_gate_px, prior_min_fraction: skip RANSAC when this fraction of the tracks lies within
            the gate (px) of the prediction (0: always RANSAC; stereo once a motion was measured).
        inliers: ``"ransac"`` or ``"rigidity"`` (stereo: max-clique of rigid pairs first).
    """

    prior_gate_px: float = 8.0
    prior_min_fraction: float = 0.9
    inliers: str = "ransac"

    def __post_init__(self) -> None:
        if self.inliers not in ("ransac", "rigidity"):
            raise EstimationError(f"PnpOptions.inliers is {self.inliers!r}; use 'ransac' or 'rigidity'")
        if self.prior_gate_px < 0 or not 0 < self.prior_min_fraction <= 1:
            raise EstimationError(
                f"PnpOptions.prior_gate_px={self.prior_gate_px}, prior_min_fraction={self.prior_min_fraction}; "
                "use a distance >= 0 (0: off) and a fraction in (0, 1]"
            )


@dataclass(frozen=True, slots=True)
class EssentialOptions:
    """``rgbd-essential``: the essential matrix, metric scale and cheirality from depth.

    Attributes:
        threshold_px: epipolar (Sampson) inlier threshold, px.
        min_parallax_px: solve by PnP below this median parallax, px.
        cheirality: the pick of the four motions: ``"depth"`` or ``"opencv"``.
        prior_gate_px, prior_min_fraction, prior_iterations: refine the prediction (Sampson LM)
            instead of RANSAC when it explains this fraction of the tracks (gate 0: always RANSAC).
        pnp_prior_gate_px: the PnP steps first try PnP from the prediction with this gate, px (0: off).
    """

    threshold_px: float = 1.0
    min_parallax_px: float = 3.0
    cheirality: str = "depth"
    prior_gate_px: float = 2.0
    prior_min_fraction: float = 0.9
    prior_iterations: int = 1
    pnp_prior_gate_px: float = 0.0

    def __post_init__(self) -> None:
        if self.cheirality not in ("opencv", "depth"):
            raise EstimationError(f"EssentialOptions.cheirality is {self.cheirality!r}; use 'opencv' or 'depth'")
        if (
            self.prior_gate_px < 0
            or self.pnp_prior_gate_px < 0
            or not 0 < self.prior_min_fraction <= 1
            or self.prior_iterations < 1
        ):
            raise EstimationError(
                f"EssentialOptions.prior_gate_px={self.prior_gate_px}, pnp_prior_gate_px={self.pnp_prior_gate_px}, "
                f"prior_min_fraction={self.prior_min_fraction}, prior_iterations={self.prior_iterations}; "
                "use distances >= 0 (0: off), a fraction in (0, 1] and at least 1 iteration"
            )


@dataclass(frozen=True, slots=True)
class KabschOptions:
    """``rgbd-kabsch``: 3D-3D Kabsch on the depth of both frames.

    Attributes:
        threshold_m: inlier threshold at 1 m (grows with depth squared).
        polish: polish the rigid fit like PnP's pose and fuse the depth.
        first_batch: hypotheses in RANSAC's first batch (then 64 per batch).
        prior_gate, prior_min_fraction: skip RANSAC when the prediction explains this fraction
            of the pairs (gate in inlier thresholds; 0: always RANSAC).
    """

    threshold_m: float = 0.02
    polish: bool = True
    first_batch: int = 8
    prior_gate: float = 2.0
    prior_min_fraction: float = 0.9

    def __post_init__(self) -> None:
        if self.prior_gate < 0 or not 0 < self.prior_min_fraction <= 1:
            raise EstimationError(
                f"KabschOptions.prior_gate={self.prior_gate}, prior_min_fraction={self.prior_min_fraction}; "
                "use a gate >= 0 (0: off) and a fraction in (0, 1]"
            )
        if self.first_batch < 1:
            raise EstimationError(f"KabschOptions.first_batch is {self.first_batch}; use at least 1 (8 is typical)")


@dataclass(frozen=True, slots=True)
class FlowOptions:
    """``flow``: optical-flow velocity from a reference frame.

    Attributes:
        threshold_px: RANSAC threshold, px of image motion since the reference.
        robust_iters: Cauchy-reweighted refits of the velocity after RANSAC.
        depth: on stereo: ``"stereo"`` (each point's depth) or ``"altitude"`` (one, looking down).
        ref_px: the reference moves on once its points moved this far (median px; 0: always).
        polish: polish the motion since the reference on its points' reprojection.
        altitude_every: ``depth="altitude"``: recompute the altitude every N frames.
    """

    threshold_px: float = 1.0
    robust_iters: int = 3
    depth: str = "stereo"
    ref_px: float = 15.0
    polish: bool = True
    altitude_every: int = 5

    def __post_init__(self) -> None:
        if self.depth not in ("altitude", "stereo"):
            raise EstimationError(f"FlowOptions.depth is {self.depth!r}; use 'altitude' or 'stereo'")
        if not self.ref_px >= 0:
            raise EstimationError(
                f"FlowOptions.ref_px is {self.ref_px}; use pixels >= 0 (0: track from the previous frame)"
            )


EstimatorOptions = PnpOptions | EssentialOptions | KabschOptions | FlowOptions
"""The options object of one motion estimator."""

_OPTIONS_OF: dict[Method, type[EstimatorOptions]] = {
    Method.RGBD_PNP: PnpOptions,
    Method.STEREO: PnpOptions,
    Method.RGBD_ESSENTIAL: EssentialOptions,
    Method.RGBD_KABSCH: KabschOptions,
    Method.FLOW: FlowOptions,
}


REF_FOCAL_PX = 525.0
"""The focal length (px) at which every ``*_px`` option holds as written (:meth:`VoOptions.for_camera`)."""
REF_WIDTH_PX = 640
"""The image width (px) at which the keyframe parallax holds as written."""

_NOISE_PX: dict[type, tuple[str, ...]] = {
    PnpOptions: ("prior_gate_px",),
    EssentialOptions: ("threshold_px", "prior_gate_px", "pnp_prior_gate_px"),
    KabschOptions: (),
    FlowOptions: ("threshold_px", "ref_px"),
    KeyframePolicy: (),
}
"""Tolerances on measured pixels: they grow with the focal length above ``REF_FOCAL_PX`` and
never shrink below their value (tracking noise is about a pixel at any image size). Flow's
``ref_px`` is one too: it bounds how far LK tracks from one reference, in LK's pixels."""

_GEOMETRIC_PX: dict[type, tuple[str, ...]] = {
    PnpOptions: (),
    EssentialOptions: ("min_parallax_px",),
    KabschOptions: (),
    FlowOptions: (),
    KeyframePolicy: (),
}
"""Image motions (parallax): they are angles, so they scale with the focal length both ways.
(The keyframe parallax is a share of the image width instead: how much of the view has moved.)"""


def _odd_window(win_px: float, smallest: int) -> int:
    """An odd LK window of about ``win_px``, at least ``smallest``."""
    return max(smallest, int(round((win_px - 1) / 2)) * 2 + 1)


def _scale_px(obj: _T, scale: float, names: tuple[str, ...]) -> _T:
    """A copy of the options ``obj`` with the fields ``names`` (px) times ``scale``."""
    return replace(obj, **{n: getattr(obj, n) * scale for n in names}) if names else obj  # type: ignore[type-var]


@dataclass(frozen=True, slots=True)
class VoOptions:
    """Options shared by every method (front end, checks, keyframes), and the method's own.
    How each default was chosen, with measurements: docs/estimation-log.md.

    Every ``*_px`` option (here, in the estimator's options and in ``keyframes``) is in pixels of
    a camera with a focal length of ``REF_FOCAL_PX`` (525 px: a 640x480 Kinect-class camera);
    a run converts them to its camera by :meth:`for_camera` (the keyframe parallax at a
    640 px wide image), so the same defaults hold from
    320x240 to 1280x720.

    Attributes:
        estimator: the method's options (:class:`PnpOptions`, ...; None: the method's defaults).
        max_features: corners kept per keyframe.
        cell_px: grid cell of the corner detector, px (0: from the image size and the budget).
        fast_threshold: FAST threshold (grey levels).
        border_px: corners nearer the image border are not detected, px (not converted per camera: see the log).
        project_margin_px: tracks predicted up to this far outside the image still start LK there, px.
        klt_win_px, klt_levels: LK window, px (0: 11; never grows with the focal length, at least 9); levels (None: 3).
        klt_back_levels: pyramid levels of the backward (checking) LK pass (at most ``klt_levels``).
        klt_iters: LK iterations per pyramid level at most.
        stereo_win_px: window of the left-right disparity search, px (0: the tracking window).
        stereo_matcher: a new point's disparity: ``"row"`` (a ZNCC search along the row over the rig's
            range, ``estimation.stereo.row_disparity``), ``"lk"`` (pyramidal LK from a guess, then a row
            check) or ``"row+lk"`` (LK, measured again from the row search's match where LK missed or
            contradicts it).
        fb_max_px: forward-backward tolerance of tracks, px.
        klt_trust_prior_px: RGB-D: tracks within this of their prediction skip the backward check.
        pnp_method: ``"iterative"``, ``"epnp"`` or ``"sqpnp"``: PnP's fit on all inliers.
        pnp_kernel: PnP RANSAC: ``"p3p"`` (ours, compiled), None (OpenCV's, ``pnp_method`` samples) or ``"ap3p"``.
        reproj_px: PnP RANSAC and inlier threshold, px.
        min_inliers: fewer inliers -> the estimate is rejected (the frame is ``PREDICTED``).
        max_speed_m_s, max_rate_rad_s: sanity limits of one step (faster -> ``PREDICTED``).
        min_depth_m, max_depth_m: accepted depth range (stereo and depth images), m.
        init_min_depth_fraction: RGB-D: hold the start pose (``INIT``) until this fraction of the
            depth image is in range (0: start at once).
        max_depth_baselines: stereo points farther than this many baselines are not used (inf: all kept).
        min_disparity_px: stereo points with a smaller disparity are not used, px (the matching noise floor).
        far_points: stereo points beyond the depth cap: ``"drop"``, for the ``"rotation"`` only, or ``"weighted"``
            in the translation by cap / depth (None: ``"weighted"`` for ``stereo``, ``"drop"`` for ``flow``).
        refine_with_depth: polish poses on the current frame's depth too (``pnp.refine_pose``).
        depth_sigma_per_m2: depth images' noise: sigma_z = this x z^2 (Kinect v1: 1.425e-3 /m,
            Khoshelham & Elberink 2012); weighs registered depth in the polish (0: the fixed 0.1 m weight).
        track_sigma_px: the tracks' pixel noise, px: the depth residuals' weight, the offset's skip of pairs.
        polish_huber_px: the pose polish's Huber width, px (not converted per camera: see the log).
        point_uncertainty: the pose polish weighs each keyframe point by its own depth's noise
            (``pnp.refine_pose``; None: on for ``stereo``, off for the RGB-D methods).
        fuse_depth: fuse each frame's depth of tracked points into their 3D estimates.
        stereo_fb_check: also check left-right stereo matches right-to-left.
        stereo_offset: ``stereo``: estimate the pair's disparity offset online (``estimation.stereo_offset``;
            None: on for ``stereo``).
        orb_fallback: match ORB against the keyframe when tracking fails (``FALLBACK``).
        keyframes: the keyframe policy (:class:`~estimation.keyframes.KeyframePolicy`).
        ba_window: local bundle adjustment over this many keyframes (0: off).
        revisit_keyframes: keep this many past keyframes and return to one the camera sees again
            instead of making a new keyframe (``estimation.revisit``; 0: off).
        exposure_compensation: before tracking, undo a significant exposure (gain) change between
            the previous image and the current one (``estimation.exposure``; auto-exposure cameras).
        readout_s: rolling-shutter readout (first row to last, s) whose row timing is undone
            (``estimation.rolling_shutter``); None: the camera's ``CameraIntrinsics.readout_s``.
        seed: RANSAC random seed (repeatable runs).
    """

    estimator: EstimatorOptions | None = None
    max_features: int = 300
    cell_px: int = 0
    fast_threshold: int = 20
    border_px: int = 8
    project_margin_px: float = 20.0
    klt_win_px: int = 0
    klt_levels: int | None = None
    klt_back_levels: int = 1
    klt_iters: int = 10
    stereo_win_px: int = 0
    stereo_matcher: str = "row+lk"
    fb_max_px: float = 1.0
    klt_trust_prior_px: float = 2.0
    pnp_method: str = "iterative"
    pnp_kernel: str | None = "p3p"
    reproj_px: float = 3.0
    min_inliers: int = 12
    max_speed_m_s: float = 40.0
    max_rate_rad_s: float = 8.0
    min_depth_m: float = 0.2
    max_depth_m: float = 60.0
    init_min_depth_fraction: float = 0.0
    min_disparity_px: float = 3.0
    max_depth_baselines: float = 60.0
    far_points: str | None = None
    refine_with_depth: bool = True
    depth_sigma_per_m2: float = 1.425e-3
    track_sigma_px: float = 0.5
    polish_huber_px: float = 1.0
    point_uncertainty: bool | None = None
    fuse_depth: bool = True
    stereo_fb_check: bool = False
    stereo_offset: bool | None = None
    orb_fallback: bool = True
    keyframes: KeyframePolicy = field(default_factory=KeyframePolicy)
    ba_window: int = 0
    revisit_keyframes: int = 0
    exposure_compensation: bool = True
    readout_s: float | None = None
    seed: int = 0

    def for_camera(self, focal_px: float, width_px: int) -> VoOptions:
        """These options in the pixels of a camera with focal length ``focal_px`` and images
        ``width_px`` wide: image motions times ``focal_px / REF_FOCAL_PX``; tolerances on measured
        pixels (thresholds, gates, minimum disparity, the projection's margin) times that ratio
        when it is above 1; LK windows times that ratio when it is below 1 (odd, at least 9 px);
        the keyframe parallax times ``width_px / REF_WIDTH_PX``."""
        s = focal_px / REF_FOCAL_PX
        n = max(1.0, s)
        w = min(1.0, s)
        est = self.estimator
        if est is not None:
            est = _scale_px(_scale_px(est, n, _NOISE_PX[type(est)]), s, _GEOMETRIC_PX[type(est)])
        kf = self.keyframes
        return replace(
            self,
            estimator=est,
            keyframes=replace(kf, max_parallax_px=kf.max_parallax_px * width_px / REF_WIDTH_PX),
            cell_px=round(self.cell_px * s),
            klt_win_px=_odd_window((self.klt_win_px or 11) * w, 9),
            stereo_win_px=_odd_window(self.stereo_win_px * w, 9) if self.stereo_win_px else 0,
            fb_max_px=self.fb_max_px * n,
            klt_trust_prior_px=self.klt_trust_prior_px * n,
            reproj_px=self.reproj_px * n,
            track_sigma_px=self.track_sigma_px * n,
            project_margin_px=self.project_margin_px * n,
            min_disparity_px=self.min_disparity_px * n,
        )

    def for_method(self, method: Method) -> VoOptions:
        """These options with ``method``'s estimator options and its defaults for the options left
        None (``stereo``: far points weighted, offset on, point uncertainty on; others: off).

        Raises:
            EstimationError: ``estimator`` belongs to another method.
        """
        stereo = method is Method.STEREO
        return replace(
            self,
            estimator=self.estimator_options(method),
            far_points=self.far_points or ("weighted" if stereo else "drop"),
            stereo_offset=stereo if self.stereo_offset is None else self.stereo_offset,
            point_uncertainty=stereo if self.point_uncertainty is None else self.point_uncertainty,
        )

    def estimator_options(self, method: Method) -> EstimatorOptions:
        """The options of ``method``'s estimator: ``estimator`` when set, else that estimator's defaults.

        Raises:
            EstimationError: ``estimator`` belongs to another method.
        """
        want = _OPTIONS_OF[method]
        if self.estimator is None:
            return want()
        if not isinstance(self.estimator, want):
            raise EstimationError(
                f"VoOptions.estimator is a {type(self.estimator).__name__} but method {method.value!r} "
                f"takes {want.__name__}; pass {want.__name__}(...) or None"
            )
        return self.estimator

    def __post_init__(self) -> None:
        if self.pnp_method not in ("iterative", "epnp", "sqpnp"):
            raise EstimationError(f"VoOptions.pnp_method is {self.pnp_method!r}; use iterative, epnp or sqpnp")
        if self.stereo_matcher not in ("row", "lk", "row+lk"):
            raise EstimationError(f"VoOptions.stereo_matcher is {self.stereo_matcher!r}; use 'row', 'lk' or 'row+lk'")
        if self.far_points not in (None, "drop", "rotation", "weighted"):
            raise EstimationError(f"VoOptions.far_points is {self.far_points!r}; use 'drop', 'rotation' or 'weighted'")
        if self.pnp_kernel not in (None, "p3p", "ap3p"):
            raise EstimationError(
                f"VoOptions.pnp_kernel is {self.pnp_kernel!r}; use None (OpenCV's RANSAC), 'ap3p' (OpenCV's, AP3P "
                "samples) or 'p3p' (the compiled P3P RANSAC, estimation.p3p)"
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
        if self.klt_trust_prior_px < 0:
            raise EstimationError(f"VoOptions.klt_trust_prior_px is {self.klt_trust_prior_px}; use >= 0 (0: off)")
        if not 0.0 <= self.init_min_depth_fraction <= 1.0:
            raise EstimationError(
                f"VoOptions.init_min_depth_fraction is {self.init_min_depth_fraction}; use a fraction in [0, 1]"
            )
        if self.border_px < 0 or self.project_margin_px < 0 or not self.polish_huber_px > 0:
            raise EstimationError(
                f"VoOptions.border_px={self.border_px}, project_margin_px={self.project_margin_px}, "
                f"polish_huber_px={self.polish_huber_px}; use pixels >= 0 and a Huber width > 0 (1 px is typical)"
            )
        if self.depth_sigma_per_m2 < 0 or not self.track_sigma_px > 0:
            raise EstimationError(
                f"VoOptions.depth_sigma_per_m2={self.depth_sigma_per_m2}, track_sigma_px={self.track_sigma_px}; "
                "use a depth noise >= 0 per m^2 (0: fixed weight; Kinect v1 1.425e-3) and a pixel noise > 0"
            )
        if self.readout_s is not None and not (math.isfinite(self.readout_s) and self.readout_s >= 0):
            raise EstimationError(
                f"VoOptions.readout_s is {self.readout_s}; use the readout in seconds (0: global shutter)"
            )
        if self.revisit_keyframes < 0:
            raise EstimationError(f"VoOptions.revisit_keyframes is {self.revisit_keyframes}; use >= 0 (0: off)")
        if not 0 < self.min_depth_m < self.max_depth_m:
            raise EstimationError(
                f"VoOptions depth range [{self.min_depth_m}, {self.max_depth_m}] m is empty; set 0 < min < max"
            )
