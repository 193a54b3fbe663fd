"""Past keyframes kept so that the keyframe methods can return to one instead of making a new one.

A camera that turns back and forth over the same view (a handheld RGB-D camera, a hovering
drone) would otherwise chain a new keyframe, and a new error, on every swing. When the keyframe
policy asks for a new keyframe, :meth:`KeyframeStore.best` looks for a kept keyframe the
policy would still accept from the current pose (its own limits on rotation, baseline, points
in view and parallax); the front end then tracks its points from its image into the current
one (``FrontEnd.restore``, which takes the return only when enough of those tracks agree on one
pose) and the next poses are measured against it, so the error made since it was current does
not add up. The pose jumps by that error when it returns (docs/estimation-log.md, "Issue 15,
eighth pass, RGB-D rotation" and "thirteenth pass").
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from estimation.keyframes import KeyframePolicy
from estimation.motion import invert, median

if TYPE_CHECKING:
    from estimation.camera_geometry import CameraGeometry
    from estimation.rolling_shutter import CameraRate

__all__ = ["KeyframeStore", "StoredKeyframe"]


F64 = npt.NDArray[np.float64]
F32 = npt.NDArray[np.float32]
U8 = npt.NDArray[np.uint8]


@dataclass(frozen=True, slots=True, eq=False)
class StoredKeyframe:
    """A keyframe as it was made: its pose, points (keyframe camera frame, m), their pixels,
    ids and fusion weights, its images (right or depth None when absent) and the camera's rate
    then (a rolling shutter)."""

    T_world_kf: F64
    X: F64
    px: F32
    ids: npt.NDArray[np.int64]
    w: F64
    gray: U8
    right: U8 | None
    depth: F32 | None
    rate: CameraRate | None = None


class KeyframeStore:
    """The last ``capacity`` keyframes, newest last.

    Args:
        capacity: keyframes kept (each holds its image and depth image by reference).
    """

    def __init__(self, capacity: int) -> None:
        self._kfs: deque[StoredKeyframe] = deque(maxlen=max(1, capacity))

    def __len__(self) -> int:
        return len(self._kfs)

    def add(self, kf: StoredKeyframe) -> None:
        """Keep a new keyframe (the oldest goes when full)."""
        self._kfs.append(kf)

    def best(
        self, T_world_cur: F64, geo: CameraGeometry, policy: KeyframePolicy, current: StoredKeyframe | None
    ) -> StoredKeyframe | None:
        """The kept keyframe (other than ``current``) to return to from a camera at ``T_world_cur``,
        or None: among those the policy would keep (within its rotation, baseline and parallax
        limits, at least its tracked fraction and count of the points in view), the one whose
        points moved least in the image."""
        best: StoredKeyframe | None = None
        best_par = float("inf")
        T_cur_world = invert(T_world_cur)
        for kf in self._kfs:
            if kf is current or not len(kf.X):
                continue
            T_cur_kf = T_cur_world @ kf.T_world_kf
            depth_m = median(kf.X[:, 2])
            # The policy's motion limits first (no parallax, every point in view): cheap.
            if policy.decide(0.0, len(kf.X), len(kf.X), T_cur_kf, 0, depth_m).new_keyframe:
                continue
            px, vis = geo.project(T_cur_kf, kf.X)
            if not vis.any():
                continue
            par = np.linalg.norm(px[vis] - kf.px[vis], axis=1)
            n_vis = int(np.count_nonzero(vis))
            if policy.decide(par, n_vis, len(kf.X), T_cur_kf, 0, depth_m).new_keyframe:
                continue
            m = median(par)
            if m < best_par:
                best, best_par = kf, m
        return best
