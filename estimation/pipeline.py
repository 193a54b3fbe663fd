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
and the current image instead (Hamming norm, ratio test). ``rgbd-pnp`` and ``stereo`` skip
RANSAC when the prior already explains the tracks (``PnpOptions.prior_gate_px``; the RGB-D
methods also skip the backward LK pass for tracks that land at their prediction,
``VoOptions.klt_trust_prior_px``). Every estimate passes a sanity
check (speed, turn rate, inliers); a failed one is replaced by the constant-velocity
prediction and flagged ``Quality.PREDICTED``, never silently dropped. Keyframes are chosen
by parallax and motion (:class:`~estimation.keyframes.KeyframePolicy`); an optional local
bundle adjustment refines the last N keyframes.

A rolling-shutter camera (``CameraIntrinsics.readout_s`` > 0, e.g. the Kinect's 20 ms) has every
measurement moved from its row's time to the frame's stamp with the camera's rate
(``estimation.rolling_shutter``); the keyframe methods measure the motion again with the rate
their first estimate implies.

Frames: camera frames are OpenCV; the world frame is the first camera's unless
``T_world_camera0`` (or ``init_from_groundtruth``) says otherwise; body poses are
``T_world_body = T_world_camera @ inv(T_body_camera)``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import cv2
import numpy as np

from estimation import _lens_kernel
from estimation.frames import FramePreparer
from estimation.lk import ImagePyramid, lk_track
from estimation.odometry import VisualOdometry
from estimation.p3p import pnp_ransac
from estimation.pose_track import scale_motion
from estimation.vo_options import (
    EssentialOptions,
    FlowOptions,
    KabschOptions,
    Method,
    PnpOptions,
    VoOptions,
)
from estimation.vo_result import MAX_FAILED_FRACTION, STAGES, FramePose, Quality, VoResult, collect_result
from flightkit.errors import EstimationError
from flightkit.frames import Transform

if TYPE_CHECKING:
    from flightkit.datasets.base import Sequence

__all__ = [
    "MAX_FAILED_FRACTION",
    "STAGES",
    "EssentialOptions",
    "FlowOptions",
    "FramePose",
    "KabschOptions",
    "Method",
    "PnpOptions",
    "Quality",
    "VisualOdometry",
    "VoOptions",
    "VoResult",
    "collect_result",
    "run_vo",
    "warm_up",
]

logger = logging.getLogger(__name__)



def warm_up(method: Method | str) -> list[FramePose]:
    """Run ``method`` on five synthetic 320x240 frames (a blurred random texture at 2 m, moving
    2 px a frame) so that its compiled kernels (``estimation._*kernel*``) are loaded, or compiled
    on the first run after an install (~50 s of CPU here; ~2 s to load them otherwise), before
    live frames arrive. The frames have the types and layouts of real ones, so the kernels a
    real run calls need no new compilation afterwards. Blocks; returns the five poses (the
    first ``INIT``, the others estimated)."""
    m = Method(method)
    w, h = 320, 240
    rng = np.random.default_rng(7)
    texture = np.asarray(
        cv2.GaussianBlur(rng.integers(0, 256, (h + 8, w + 32), dtype=np.uint8), (5, 5), 1.0), dtype=np.uint8
    )
    from flightkit.datasets.base import CameraIntrinsics

    # A rolling shutter too, so that its kernel (estimation.rolling_shutter) is loaded as well.
    intr = CameraIntrinsics(250.0, 250.0, w / 2, h / 2, w, h, (), 0.02)
    depth = np.full((h, w), 2.0, np.float32)
    vo = VisualOdometry(m, intr, 0.1, intr)
    poses = []
    for i in range(5):
        gray = np.ascontiguousarray(texture[4 : 4 + h, 2 * i : 2 * i + w])
        # stereo: a point seen 12 px further left in the right image is 2.08 m away (0.1 m baseline)
        right = np.ascontiguousarray(texture[4 : 4 + h, 2 * i + 12 : 2 * i + 12 + w]) if m is Method.STEREO else None
        poses.append(vo.process(i * 33_333_333, gray, right, None if m is Method.STEREO else depth))
    # The LK kernel is compiled once per window size: the default window is 9-11 px at any
    # focal length (VoOptions.for_camera), these frames use 9.
    pyr = ImagePyramid.build(gray, 1, 11)
    lk_track(pyr, pyr, np.full((1, 2), 50.0, np.float32), levels=1, win_px=11)
    # The prediction over an interval other than the last step's (these frames are evenly spaced).
    scale_motion(np.eye(4), 0.5)
    # The lens kernels of a distorted camera (these frames have none).
    k = np.zeros(_lens_kernel.MAX_COEFFS)
    _lens_kernel.undistort(np.zeros((1, 2), np.float32), intr.fx, intr.fy, intr.cx, intr.cy, k)
    _lens_kernel.project(np.ones((1, 3)), np.eye(4), intr.fx, intr.fy, intr.cx, intr.cy, k, float(w), float(h), 0.0)
    if m is not Method.FLOW:
        # PnP RANSAC (every keyframe method's fallback) may not run on these frames: once here.
        X = np.c_[rng.uniform(-1.0, 1.0, (8, 2)), rng.uniform(1.5, 3.0, 8)]
        pnp_ransac(X, X[:, :2] / X[:, 2:] * intr.fx + (intr.cx, intr.cy), vo.geo.K)
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
            if init_from_groundtruth and T0 is None:
                logger.warning(
                    "%s: frame %d has no ground-truth pose, so VO starts at the origin, not at the ground "
                    "truth; start at a frame that has one (start=...)",
                    sequence.name,
                    start + i,
                )
            vo = VisualOdometry(
                m,
                prep.intrinsics,
                sequence.baseline_m,
                prep.depth_intrinsics,
                T_body_camera,
                T0,
                options,
                on_pose,
                # sequences that do not say (TUM, the simulator, recordings) have registered depth
                depth_registered=bool(getattr(sequence, "depth_registered", True)),
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
