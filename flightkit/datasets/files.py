"""A sequence backed by one image file per frame (TUM, 7-Scenes, EuRoC, KITTI folders).

Readers describe each frame by file paths (:class:`FrameFiles`); :class:`FileSequence`
implements the :class:`~flightkit.datasets.base.Sequence` protocol on top: images are
decoded with OpenCV one frame at a time, raw stereo is rectified when a
:class:`~flightkit.datasets.base.StereoRectification` is given.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import cv2
import numpy as np
import numpy.typing as npt

from flightkit.datasets.base import CameraIntrinsics, Frame, StereoRectification
from flightkit.datasets.trajectory import Trajectory
from flightkit.errors import DatasetError
from flightkit.frames import Transform

__all__ = ["FileSequence", "FrameFiles", "poses_at", "read_color", "read_depth", "read_gray", "require"]

logger = logging.getLogger(__name__)


def require(path: Path, what: str, folder: Path, kind: str) -> Path:
    """Return ``path`` if it exists, else raise DatasetError "<kind> folder <folder> lacks <rel>"."""
    if not path.exists():
        try:
            rel = path.relative_to(folder)
        except ValueError:
            rel = path
        raise DatasetError(f"{kind} folder {folder} lacks {rel} ({what})")
    return path


def _imread(path: Path, flags: int, what: str) -> npt.NDArray[np.generic]:
    img = cv2.imread(str(path), flags)
    if img is None:
        if not path.exists():
            raise DatasetError(f"{what} {path} does not exist; is the dataset folder complete?")
        raise DatasetError(f"{what} {path} cannot be decoded by OpenCV; is the file truncated?")
    return np.asarray(img)


def _u8(image: cv2.typing.MatLike) -> npt.NDArray[np.uint8]:
    """OpenCV's result of an operation on uint8 images, typed as what it is."""
    return cast("npt.NDArray[np.uint8]", image)


def read_gray(path: Path) -> npt.NDArray[np.uint8]:
    """8-bit grayscale image (colour files are converted)."""
    return _imread(path, cv2.IMREAD_GRAYSCALE, "image").astype(np.uint8, copy=False)


def read_color(path: Path) -> npt.NDArray[np.uint8]:
    """8-bit BGR image."""
    return _imread(path, cv2.IMREAD_COLOR, "image").astype(np.uint8, copy=False)


def read_depth(path: Path) -> npt.NDArray[np.uint16]:
    """16-bit depth image as stored (no scaling)."""
    img = _imread(path, cv2.IMREAD_UNCHANGED, "depth image")
    if img.dtype != np.uint16 or img.ndim != 2:
        raise DatasetError(
            f"depth image {path} is {img.dtype} with shape {img.shape}; expected a 16-bit single-channel PNG"
        )
    return img.astype(np.uint16, copy=False)


def poses_at(gt: Trajectory, stamps_ns: npt.NDArray[np.int64], max_diff_ns: int) -> list[Transform | None]:
    """Ground-truth poses at ``stamps_ns``: interpolated inside the ground truth's time span,
    the nearest sample just outside it; None where no sample lies within ``max_diff_ns``."""
    from flightkit.datasets.trajectory import associate

    out: list[Transform | None] = [None] * int(stamps_ns.size)
    ia, ib = associate(stamps_ns, gt.stamps_ns, max_diff_ns)
    if ia.size == 0:
        return out
    inside = (stamps_ns[ia] >= gt.stamps_ns[0]) & (stamps_ns[ia] <= gt.stamps_ns[-1])
    if len(gt) >= 2 and np.all(np.diff(gt.stamps_ns) > 0) and inside.any():
        interp = gt.interpolate(stamps_ns[ia[inside]])
        for k, i in enumerate(ia[inside]):
            out[int(i)] = interp.transform(k)
        for i, j in zip(ia[~inside], ib[~inside], strict=True):
            out[int(i)] = gt.transform(int(j))
    else:
        for i, j in zip(ia, ib, strict=True):
            out[int(i)] = gt.transform(int(j))
    return out


@dataclass(frozen=True, slots=True)
class FrameFiles:
    """The files of one frame.

    Attributes:
        stamp_ns: capture time, ns.
        image: colour or grayscale image of the (left) camera.
        right: right image of a stereo pair.
        depth: 16-bit depth image.
        T_world_camera: ground-truth pose of the camera (before rectification), if known.
    """

    stamp_ns: int
    image: Path
    right: Path | None = None
    depth: Path | None = None
    T_world_camera: Transform | None = None


class FileSequence:
    """:class:`~flightkit.datasets.base.Sequence` over per-frame image files.

    Args:
        name, kind, path: see the protocol.
        files: one entry per frame, in time order.
        intrinsics: camera of the yielded images (the rectified one when ``rectification``).
        color: decode ``image`` as colour (``Frame.color_bgr`` plus ``gray``) or as gray only.
        depth_scale_m: metres per depth unit.
        depth_invalid: a raw depth value that means "no data" besides 0 (7-Scenes: 65535).
        depth_registered: depth pixels are the colour pixels' (TUM); False when the depth camera
            is another camera whose pixels are only mapped through the two pinhole models (7-Scenes).
        groundtruth: trajectory of the camera (already in the yielded camera's frame).
    """

    def __init__(
        self,
        *,
        name: str,
        kind: str,
        path: Path,
        files: list[FrameFiles],
        intrinsics: CameraIntrinsics,
        color: bool,
        depth_intrinsics: CameraIntrinsics | None = None,
        depth_scale_m: float = 1.0,
        depth_invalid: int | None = None,
        depth_registered: bool = True,
        baseline_m: float | None = None,
        rectification: StereoRectification | None = None,
        groundtruth: Trajectory | None = None,
    ) -> None:
        if not files:
            raise DatasetError(f"{kind} folder {path} holds no frames; is it empty?")
        self.name = name
        self.kind = kind
        self.path = path
        self.intrinsics = intrinsics
        self.depth_intrinsics = depth_intrinsics
        self.depth_registered = depth_registered
        self.baseline_m = baseline_m
        self.rectification = rectification
        self._files = files
        self._color = color
        self._depth_scale_m = depth_scale_m
        self._depth_invalid = depth_invalid
        self._groundtruth = groundtruth
        self._stamps = np.array([f.stamp_ns for f in files], dtype=np.int64)

    def __len__(self) -> int:
        return len(self._files)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(kind={self.kind!r}, name={self.name!r}, frames={len(self)})"

    @property
    def files(self) -> list[FrameFiles]:
        """The per-frame file list (read-only by convention)."""
        return self._files

    def stamps_ns(self) -> npt.NDArray[np.int64]:
        return self._stamps.copy()

    def has_groundtruth(self) -> bool:
        return self._groundtruth is not None

    def groundtruth(self) -> Trajectory:
        if self._groundtruth is None:
            raise DatasetError(
                f"{self.kind} sequence {self.path} has no ground truth; add the ground-truth file "
                "or evaluate against a separate trajectory"
            )
        return self._groundtruth

    def frame(self, index: int) -> Frame:
        """Load one frame by index."""
        if not -len(self) <= index < len(self):
            raise DatasetError(f"frame index {index} is outside {self.name} (0..{len(self) - 1})")
        index %= len(self)
        f = self._files[index]
        color: npt.NDArray[np.uint8] | None = None
        if self._color:
            color = read_color(f.image)
            gray = cast("npt.NDArray[np.uint8]", cv2.cvtColor(color, cv2.COLOR_BGR2GRAY))
        else:
            gray = read_gray(f.image)
        right = read_gray(f.right) if f.right is not None else None
        rect = self.rectification
        T_world_camera = f.T_world_camera  # noqa: N806
        if rect is not None:
            gray = _u8(cv2.remap(gray, rect.maps_left[0], rect.maps_left[1], cv2.INTER_LINEAR))
            if right is not None:
                right = _u8(cv2.remap(right, rect.maps_right[0], rect.maps_right[1], cv2.INTER_LINEAR))
            if color is not None:
                color = _u8(cv2.remap(color, rect.maps_left[0], rect.maps_left[1], cv2.INTER_LINEAR))
            if T_world_camera is not None:
                T_world_camera = T_world_camera @ Transform.from_matrix(_rot4(rect.R_left_rect))  # noqa: N806
        depth = None
        if f.depth is not None:
            depth = read_depth(f.depth)
            if self._depth_invalid is not None:
                depth[depth == self._depth_invalid] = 0
        return Frame(
            index=index,
            stamp_ns=int(f.stamp_ns),
            gray=np.asarray(gray, dtype=np.uint8),
            color_bgr=color,
            right_gray=right,
            depth_raw=depth,
            depth_scale_m=self._depth_scale_m,
            T_world_camera=T_world_camera,
        )

    def frames(self, start: int = 0, stop: int | None = None, step: int = 1) -> Iterator[Frame]:
        for index in range(len(self))[start:stop:step]:
            yield self.frame(index)


def _rot4(R: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:  # noqa: N803
    m = np.eye(4)
    m[:3, :3] = R
    return m
