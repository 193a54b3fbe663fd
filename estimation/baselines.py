"""Two plain OpenCV VO pipelines with fixed parameters: the bar the methods in
:mod:`estimation.pipeline` must clear (issue 15).

They are what a competent user writes in an afternoon, not tuned to any sequence, and they
run at whatever resolution the images come in:

* ``plain-stereo`` (:class:`PlainStereoVO`): the disparity of the *previous* rectified pair
  by ``cv2.StereoSGBM`` (``numDisparities=128``, ``blockSize=5``, ``P1=8*5*5``,
  ``P2=32*5*5``, ``uniquenessRatio=10``, ``speckleWindowSize=100``, ``speckleRange=2``,
  ``disp12MaxDiff=1``, ``MODE_SGBM``), Shi-Tomasi corners in the previous left image
  (``goodFeaturesToTrack``: 1500 corners, quality 0.01, 7 px apart), tracked into the current
  left image by pyramidal LK (21 px window, 4 levels), the 3D points (disparity above 1 px)
  against the tracked pixels by ``cv2.solvePnPRansac`` (iterative, 2 px, 200 iterations,
  confidence 0.999), frame to frame.
* ``plain-rgbd`` (:class:`PlainRgbdVO`): ORB (1500 features, OpenCV defaults otherwise) in
  the previous and the current image, brute-force Hamming matching with cross-check, the
  previous frame's depth at its keypoints (0.1-10 m), ``cv2.solvePnPRansac`` (iterative,
  3 px, 200 iterations, confidence 0.999), frame to frame.

A frame whose motion cannot be solved (fewer than 6 correspondences, or RANSAC fails) keeps
the last pose and is flagged ``Quality.PREDICTED``. The result is a
:class:`~estimation.pipeline.VoResult`, timed like :func:`~estimation.pipeline.run_vo`
(the per-frame time in the ``motion`` stage).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING, cast

import cv2
import numpy as np
import numpy.typing as npt

from estimation.frames import FramePreparer
from estimation.motion import invert, make_T
from estimation.pipeline import STAGES, FramePose, Method, Quality, VoResult, collect_result
from flightkit.errors import EstimationError

if TYPE_CHECKING:
    from flightkit.datasets.base import Sequence

__all__ = ["BASELINES", "PlainRgbdVO", "PlainStereoVO", "run_plain"]

F64 = npt.NDArray[np.float64]
U8 = npt.NDArray[np.uint8]

BASELINES = ("plain-stereo", "plain-rgbd")
"""The plain pipelines' names, as :func:`run_plain` takes them."""

_MIN_POINTS = 6


def _pnp(obj: F64, img: F64, K: F64, dist: F64 | None, reproj_px: float) -> tuple[F64 | None, int]:
    """``T_cur_prev`` from 3D points of the previous camera and their current pixels."""
    if len(obj) < _MIN_POINTS:
        return None, 0
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        obj.astype(np.float64),
        img.astype(np.float64),
        K,
        dist,
        iterationsCount=200,
        reprojectionError=reproj_px,
        confidence=0.999,
        flags=cv2.SOLVEPNP_ITERATIVE,
    )
    if not ok or inl is None or len(inl) < _MIN_POINTS:
        return None, 0
    return make_T(cv2.Rodrigues(rvec)[0], tvec.ravel()), len(inl)


class PlainStereoVO:
    """StereoSGBM of the previous pair + GFTT + KLT + solvePnPRansac, frame to frame (fixed
    parameters, see the module docstring)."""

    def __init__(self, K: F64, baseline_m: float) -> None:
        if baseline_m <= 0:
            raise EstimationError(f"plain-stereo needs a positive stereo baseline, got {baseline_m} m")
        self.K = K
        self.baseline_m = baseline_m
        self.sgbm = cv2.StereoSGBM.create(
            minDisparity=0,
            numDisparities=128,
            blockSize=5,
            P1=8 * 5 * 5,
            P2=32 * 5 * 5,
            disp12MaxDiff=1,
            uniquenessRatio=10,
            speckleWindowSize=100,
            speckleRange=2,
            mode=cv2.STEREO_SGBM_MODE_SGBM,
        )
        self.prev: tuple[U8, U8] | None = None
        self.T_world_cam = np.eye(4)

    def process(self, left: U8, right: U8) -> tuple[F64, int, bool]:
        """One frame; returns (T_world_camera, inliers, estimated)."""
        n_inl, ok = 0, False
        if self.prev is not None:
            T, n_inl = self._step(*self.prev, left)
            if T is not None:
                self.T_world_cam = self.T_world_cam @ invert(T)
                ok = True
        self.prev = (left, right)
        return self.T_world_cam.copy(), n_inl, ok

    def _step(self, left0: U8, right0: U8, left1: U8) -> tuple[F64 | None, int]:
        disp = self.sgbm.compute(left0, right0).astype(np.float32) / 16.0
        corners = cv2.goodFeaturesToTrack(left0, maxCorners=1500, qualityLevel=0.01, minDistance=7)
        if corners is None:
            return None, 0
        p0 = corners.reshape(-1, 2).astype(np.float32)
        u = np.clip(np.rint(p0[:, 0]).astype(int), 0, disp.shape[1] - 1)
        v = np.clip(np.rint(p0[:, 1]).astype(int), 0, disp.shape[0] - 1)
        d = disp[v, u].astype(np.float64)
        keep = d > 1.0
        p0, d = p0[keep], d[keep]
        if len(p0) < _MIN_POINTS:
            return None, 0
        p1, st, _ = cv2.calcOpticalFlowPyrLK(  # type: ignore[call-overload]  # the stub wants nextPts; None is valid
            left0,
            left1,
            p0.reshape(-1, 1, 2),
            None,
            winSize=(21, 21),
            maxLevel=3,
            criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
        )
        good = st.ravel() == 1
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        z = fx * self.baseline_m / d[good]
        q = p0[good].astype(np.float64)
        X = np.c_[(q[:, 0] - cx) / fx * z, (q[:, 1] - cy) / fy * z, z]
        return _pnp(X, p1.reshape(-1, 2)[good], self.K, None, 2.0)


class PlainRgbdVO:
    """ORB + brute-force Hamming (cross-check) + depth + solvePnPRansac, frame to frame (fixed
    parameters, see the module docstring)."""

    def __init__(self, K: F64, dist: F64 | None = None) -> None:
        self.K = K
        self.dist = dist
        self.orb = cv2.ORB.create(nfeatures=1500)
        self.bf = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
        self.prev: tuple[F64, npt.NDArray[np.uint8], F64] | None = None  # pixels, descriptors, 3D
        self.T_world_cam = np.eye(4)

    def process(self, gray: U8, depth_m: npt.NDArray[np.float32]) -> tuple[F64, int, bool]:
        """One frame; returns (T_world_camera, inliers, estimated)."""
        kps, desc = self.orb.detectAndCompute(gray, None)
        pts = np.array([k.pt for k in kps], dtype=np.float64) if kps else np.empty((0, 2))
        u = np.clip(np.rint(pts[:, 0]).astype(int), 0, depth_m.shape[1] - 1)
        v = np.clip(np.rint(pts[:, 1]).astype(int), 0, depth_m.shape[0] - 1)
        z = depth_m[v, u].astype(np.float64)
        z = np.where((z > 0.1) & (z < 10.0), z, np.nan)
        # normalised coordinates: the pixels undistorted (TUM's Kinect images are raw)
        if len(pts) and self.dist is not None:
            xy = cv2.undistortPoints(pts.reshape(-1, 1, 2), self.K, self.dist).reshape(-1, 2)
        else:
            xy = (pts - self.K[:2, 2]) / np.diag(self.K)[:2]
        X = np.c_[xy * z[:, None], z]
        n_inl, ok = 0, False
        if self.prev is not None and desc is not None and self.prev[1] is not None:
            p_pts, p_desc, p_X = self.prev
            matches = self.bf.match(p_desc, desc)
            i = np.array([m.queryIdx for m in matches], dtype=int)
            j = np.array([m.trainIdx for m in matches], dtype=int)
            if len(i):
                has = np.isfinite(p_X[i, 2])
                T, n_inl = _pnp(p_X[i[has]], pts[j[has]], self.K, self.dist, 3.0)
                if T is not None:
                    self.T_world_cam = self.T_world_cam @ invert(T)
                    ok = True
        self.prev = (pts, cast(npt.NDArray[np.uint8], desc), X)
        return self.T_world_cam.copy(), n_inl, ok


def run_plain(
    sequence: Sequence,
    name: str,
    *,
    size: tuple[int, int] | None = None,
    init_from_groundtruth: bool = False,
    stop: int | None = None,
) -> VoResult:
    """Run a plain pipeline (``"plain-stereo"`` or ``"plain-rgbd"``) over a sequence, at its
    native resolution unless ``size`` is given. Blocks until done.

    Raises:
        EstimationError: unknown name, or the sequence lacks the stereo pair / depth it needs.
    """
    if name not in BASELINES:
        raise EstimationError(f"unknown plain baseline {name!r}; use one of {', '.join(BASELINES)}")
    stereo = name == "plain-stereo"
    if stereo and not sequence.baseline_m:
        raise EstimationError(f"plain-stereo needs a stereo pair and {sequence.name} has none")
    if not stereo and sequence.depth_intrinsics is None:
        raise EstimationError(f"plain-rgbd needs depth images and {sequence.name} has none")
    prep = FramePreparer(sequence, Method.STEREO if stereo else Method.RGBD_PNP, size)
    intr = prep.intrinsics
    dist = intr.dist_array if intr.is_distorted else None
    vo: PlainStereoVO | PlainRgbdVO = (
        PlainStereoVO(intr.K, float(sequence.baseline_m or 0.0)) if stereo else PlainRgbdVO(intr.K, dist)
    )
    step: Callable[..., tuple[F64, int, bool]] = vo.process
    poses: list[FramePose] = []
    t0 = time.perf_counter()
    for i, frame in enumerate(sequence.frames(0, stop)):
        pf = prep(frame)
        if i == 0 and init_from_groundtruth and pf.T_world_camera is not None:
            vo.T_world_cam = pf.T_world_camera.as_matrix()
        other = pf.right_gray if stereo else pf.depth_m
        if other is None:
            continue
        t, c = time.perf_counter(), time.thread_time()
        T, n_inl, ok = step(pf.gray, other)
        ms = dict.fromkeys(STAGES, 0.0)
        ms["motion"] = ms["total"] = (time.perf_counter() - t) * 1e3
        cpu = (time.thread_time() - c) * 1e3
        q = Quality.INIT if i == 0 else (Quality.GOOD if ok else Quality.PREDICTED)
        poses.append(FramePose(i, pf.stamp_ns, T, T, n_inl, q, False, ms, cpu))
    return collect_result(poses, name, sequence.name, time.perf_counter() - t0, (intr.width, intr.height))
