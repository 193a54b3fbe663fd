"""Dataset frames made ready for a VO method: the images it needs, resized to a processing size
(the intrinsics with them), depth in metres."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np
import numpy.typing as npt

from estimation.vo_options import Method
from flightkit.frames import Transform

if TYPE_CHECKING:
    from flightkit.datasets.base import CameraIntrinsics, Frame, Sequence

__all__ = ["FramePreparer", "PreparedFrame"]

F32 = npt.NDArray[np.float32]


def _resize_intrinsics(intr: CameraIntrinsics, size: tuple[int, int]) -> CameraIntrinsics:
    from flightkit.datasets.base import CameraIntrinsics

    w, h = size
    sx, sy = w / intr.width, h / intr.height
    return CameraIntrinsics(
        intr.fx * sx,
        intr.fy * sy,
        (intr.cx + 0.5) * sx - 0.5,
        (intr.cy + 0.5) * sy - 0.5,
        w,
        h,
        intr.dist,
        intr.readout_s,
    )


@dataclass(frozen=True, slots=True, eq=False)
class PreparedFrame:
    """Images ready for :meth:`VisualOdometry.process` (decoded, resized, depth in metres)."""

    stamp_ns: int
    gray: npt.NDArray[np.uint8]
    right_gray: npt.NDArray[np.uint8] | None
    depth_m: F32 | None
    T_world_camera: Transform | None


class FramePreparer:
    """Converts dataset frames for a method and an optional processing size (reuses no
    buffers across frames: the frames own their images)."""

    def __init__(self, sequence: Sequence, method: Method, size: tuple[int, int] | None) -> None:
        self.method = method
        intr = sequence.intrinsics
        self.size = size if size is not None and size != (intr.width, intr.height) else None
        self.intrinsics = _resize_intrinsics(intr, self.size) if self.size else intr
        di = sequence.depth_intrinsics
        self.depth_intrinsics = _resize_intrinsics(di, self.size) if (self.size and di is not None) else di
        self.want_depth = method.needs_depth or (method is Method.FLOW and di is not None)
        self.want_right = method is Method.STEREO or (method is Method.FLOW and di is None)

    def __call__(self, frame: Frame) -> PreparedFrame:
        gray = frame.gray
        right = frame.right_gray if self.want_right else None
        depth = frame.depth_m if self.want_depth else None
        if self.size is not None:
            gray = np.asarray(cv2.resize(gray, self.size, interpolation=cv2.INTER_AREA), dtype=np.uint8)
            if right is not None:
                right = np.asarray(cv2.resize(right, self.size, interpolation=cv2.INTER_AREA), dtype=np.uint8)
            if depth is not None:
                depth = np.asarray(cv2.resize(depth, self.size, interpolation=cv2.INTER_NEAREST), dtype=np.float32)
        return PreparedFrame(frame.stamp_ns, gray, right, depth, frame.T_world_camera)
