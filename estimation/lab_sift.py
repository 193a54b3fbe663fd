"""The lab's original VO pipeline, re-implemented as the benchmark's point of comparison.

What it does (deliberately unchanged from the lab's scripts, to measure against them):

* every ``frame_skip``-th frame: SIFT keypoints and descriptors (full image, OpenCV default
  parameters) of the previous processed frame and the current one (the previous frame's
  features are kept, not recomputed);
* brute-force L2 matching, k = 2, Lowe ratio 0.75;
* motion:
    - ``"pnp"``: 3D points of the previous frame (depth image, or SIFT left-right matches
      along rows for stereo) and ``cv2.solvePnPRansac`` with ``SOLVEPNP_ITERATIVE`` and the
      default RANSAC settings (8 px, 100 iterations);
    - ``"essential"``: ``cv2.findEssentialMat`` (RANSAC, 0.999, 1 px) + ``cv2.recoverPose``,
      the translation scaled by the median ratio of measured to triangulated depth;
* frame-to-frame chaining (no keyframes, no motion prior, no sanity check: a failed
  frame keeps the last pose).

It produces a :class:`~estimation.pipeline.VoResult` like :func:`~estimation.pipeline.run_vo`,
with the per-frame time in the ``motion`` stage (features + matching + solver) and
``track`` = 0.
"""

from __future__ import annotations

import logging
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

__all__ = ["BaselineVO", "run_baseline"]

logger = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]


class BaselineVO:
    """SIFT + brute force + solvePnP (iterative) / essential matrix, frame to frame."""

    def __init__(
        self, K: F64, mode: str = "pnp", baseline_m: float | None = None, dist: F64 | None = None
    ) -> None:
        if mode not in ("pnp", "essential"):
            raise EstimationError(f"baseline mode must be 'pnp' or 'essential', got {mode!r}")
        self.K = K
        self.dist = dist
        self.mode = mode
        self.baseline_m = baseline_m
        self.sift = cv2.SIFT.create()
        self.bf = cv2.BFMatcher(cv2.NORM_L2)
        self.prev: tuple[F64, npt.NDArray[np.float32] | None, F64] | None = None  # keypoints, descriptors, 3D
        self.T_world_cam = np.eye(4)

    def _match(
        self, d1: npt.NDArray[np.float32] | None, d2: npt.NDArray[np.float32] | None
    ) -> list[tuple[int, int]]:
        if d1 is None or d2 is None or len(d1) < 2 or len(d2) < 2:
            return []
        out = []
        for pair in self.bf.knnMatch(d1, d2, k=2):
            if len(pair) == 2 and pair[0].distance < 0.75 * pair[1].distance:
                out.append((pair[0].queryIdx, pair[0].trainIdx))
        return out

    def _points_3d(
        self,
        pts: F64,
        desc: npt.NDArray[np.float32] | None,
        depth_m: npt.NDArray[np.float32] | None,
        right: npt.NDArray[np.uint8] | None,
    ) -> F64:
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        z = np.full(len(pts), np.nan)
        if depth_m is not None:
            u = np.clip(np.rint(pts[:, 0]).astype(int), 0, depth_m.shape[1] - 1)
            v = np.clip(np.rint(pts[:, 1]).astype(int), 0, depth_m.shape[0] - 1)
            d = depth_m[v, u].astype(np.float64)
            z = np.where(d > 0, d, np.nan)
        elif right is not None and self.baseline_m:
            kr, dr_mat = self.sift.detectAndCompute(right, None)
            dr = cast("npt.NDArray[np.float32] | None", dr_mat)  # SIFT: (N, 128) float32, None if no keypoint
            pr = np.array([k.pt for k in kr]) if kr else np.empty((0, 2))
            for i, j in self._match(desc, dr):
                disp = pts[i, 0] - pr[j, 0]
                if abs(pts[i, 1] - pr[j, 1]) < 2.0 and disp > 0.5:
                    z[i] = fx * self.baseline_m / disp
        return np.column_stack(((pts[:, 0] - cx) / fx * z, (pts[:, 1] - cy) / fy * z, z))

    def process(
        self,
        gray: npt.NDArray[np.uint8],
        depth_m: npt.NDArray[np.float32] | None = None,
        right: npt.NDArray[np.uint8] | None = None,
    ) -> tuple[F64, int]:
        """Process one frame; returns (T_world_camera, inliers)."""
        kps, desc_mat = self.sift.detectAndCompute(gray, None)
        desc = cast("npt.NDArray[np.float32] | None", desc_mat)  # SIFT: (N, 128) float32, None if no keypoint
        pts = np.array([k.pt for k in kps], dtype=np.float64) if kps else np.empty((0, 2))
        X = (
            self._points_3d(pts, desc, depth_m, right)
            if self.mode == "pnp" or depth_m is not None or right is not None
            else None
        )
        n_inl = 0
        if self.prev is not None:
            p_pts, p_desc, p_X = self.prev
            matches = self._match(p_desc, desc)
            T = None
            if self.mode == "pnp":
                m = [(i, j) for i, j in matches if np.isfinite(p_X[i, 2])]
                if len(m) >= 6:
                    obj = np.array([p_X[i] for i, _ in m])
                    img = np.array([pts[j] for _, j in m])
                    ok, rvec, tvec, inl = cv2.solvePnPRansac(
                        obj, img, self.K, self.dist, flags=cv2.SOLVEPNP_ITERATIVE
                    )
                    if ok and inl is not None:
                        T = make_T(cv2.Rodrigues(rvec)[0], tvec.ravel())
                        n_inl = len(inl)
            elif len(matches) >= 8:
                p0 = np.array([p_pts[i] for i, _ in matches])
                p1 = np.array([pts[j] for _, j in matches])
                E, mask = cv2.findEssentialMat(p0, p1, self.K, method=cv2.RANSAC, prob=0.999, threshold=1.0)
                if E is not None and E.shape == (3, 3):
                    n_inl, R, t, mask = cv2.recoverPose(E, p0, p1, self.K, mask=mask)
                    inlier = mask.ravel() > 0
                if E is not None and E.shape == (3, 3) and np.count_nonzero(inlier) >= 5:
                    P0 = self.K @ np.eye(3, 4)
                    P1 = self.K @ np.c_[R, t]
                    Xh = cv2.triangulatePoints(P0, P1, p0[inlier].T, p1[inlier].T)
                    z_tri = Xh[2] / Xh[3]
                    z_meas = np.array([p_X[i, 2] for (i, _), k in zip(matches, inlier, strict=True) if k])
                    ok = np.isfinite(z_meas) & (z_tri > 0)
                    if np.count_nonzero(ok) >= 3:
                        s = float(np.median(z_meas[ok] / z_tri[ok]))
                        T = make_T(R, s * t.ravel())
            if T is not None:
                self.T_world_cam = self.T_world_cam @ invert(T)
        self.prev = (pts, desc, X if X is not None else np.full((len(pts), 3), np.nan))
        return self.T_world_cam.copy(), n_inl


def run_baseline(
    sequence: Sequence,
    mode: str = "pnp",
    frame_skip: int = 1,
    size: tuple[int, int] | None = None,
    stop: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    init_from_groundtruth: bool = False,
    sensor: str = "auto",
) -> VoResult:
    """Run the lab's original pipeline over a sequence (every ``frame_skip``-th frame).

    Stereo sequences use the left/right pair for depth, RGB-D sequences the depth image;
    ``sensor`` (``"auto"``, ``"depth"`` or ``"stereo"``) picks one on a sequence with both (the
    synthetic ones), so the stereo method can be compared with the lab's stereo pipeline.
    The output holds the processed frames only; ``init_from_groundtruth`` starts at the
    first frame's ground-truth pose (as :func:`~estimation.pipeline.run_vo`).

    Raises:
        EstimationError: the sequence has neither depth nor stereo, or not the ``sensor`` asked for.
    """
    if frame_skip < 1:
        raise EstimationError(f"frame_skip must be >= 1, got {frame_skip}")
    if sensor not in ("auto", "depth", "stereo"):
        raise EstimationError(f"baseline sensor must be 'auto', 'depth' or 'stereo', got {sensor!r}")
    has_depth, has_stereo = sequence.depth_intrinsics is not None, bool(sequence.baseline_m)
    if sensor == "depth" and not has_depth or sensor == "stereo" and not has_stereo:
        raise EstimationError(f"the baseline was asked for {sensor} input, and {sequence.name} has none")
    if has_depth and sensor != "stereo":
        method = Method.RGBD_PNP
    elif has_stereo:
        method = Method.STEREO
    else:
        raise EstimationError(f"the baseline needs depth or stereo, and {sequence.name} has neither")
    prep = FramePreparer(sequence, method, size)
    intr = prep.intrinsics
    vo = BaselineVO(intr.K, mode, sequence.baseline_m, intr.dist_array if intr.is_distorted else None)
    poses: list[FramePose] = []
    t0 = time.perf_counter()
    total = len(range(*slice(0, stop, frame_skip).indices(len(sequence))))
    for i, frame in enumerate(sequence.frames(0, stop, frame_skip)):
        pf = prep(frame)
        if i == 0 and init_from_groundtruth and pf.T_world_camera is not None:
            vo.T_world_cam = pf.T_world_camera.as_matrix()
        t, c = time.perf_counter(), time.thread_time()
        T, n_inl = vo.process(pf.gray, pf.depth_m, pf.right_gray)
        ms = dict.fromkeys(STAGES, 0.0)
        ms["motion"] = ms["total"] = (time.perf_counter() - t) * 1e3
        cpu = (time.thread_time() - c) * 1e3
        q = Quality.INIT if i == 0 else (Quality.GOOD if n_inl else Quality.PREDICTED)
        poses.append(FramePose(i, pf.stamp_ns, T, T, n_inl, q, False, ms, cpu))
        if progress is not None:
            progress(i + 1, total)
    return collect_result(
        poses, f"baseline-{mode}", sequence.name, time.perf_counter() - t0, (intr.width, intr.height)
    )
