"""The values every dataset reader returns: camera intrinsics, frames and the Sequence interface.

API (stable; estimation and capture both build on it)::

    seq = open_sequence("/data/V1_01_easy")        # any supported folder or file
    seq.name, seq.kind, len(seq)                      # kind: "euroc", "kitti", "tum", ...
    seq.intrinsics                                    # CameraIntrinsics of the images frames() yields
    seq.baseline_m                                    # stereo baseline (None for mono/RGB-D)
    seq.depth_intrinsics                              # camera of depth images (None without depth)
    for frame in seq.frames():                        # loads images lazily, one frame at a time
        frame.stamp_ns, frame.gray, frame.color_bgr, frame.right_gray
        frame.depth_m                                 # float32 metres, 0 = invalid
        frame.T_world_camera                          # ground-truth pose or None
    gt = seq.groundtruth()                            # Trajectory of the camera (raises if absent)

Conventions: the camera frame is OpenCV (x right, y down, z forward); ``T_world_camera``
maps camera coordinates into the dataset's world frame (the camera's pose in it). For a
rectified stereo pair the camera is the *rectified* left camera. Images are numpy arrays
owned by the frame (never reused buffers), colour is BGR (OpenCV order).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt

from flightkit.errors import DatasetError
from flightkit.frames import Transform

if TYPE_CHECKING:
    from flightkit.datasets.trajectory import Trajectory

__all__ = [
    "CameraIntrinsics",
    "Frame",
    "Sequence",
    "SequenceKind",
    "StereoRectification",
]

GrayImage = npt.NDArray[np.uint8]
"""Single-channel 8-bit image, shape (H, W)."""
ColorImage = npt.NDArray[np.uint8]
"""Three-channel 8-bit BGR image, shape (H, W, 3)."""


class SequenceKind:
    """The ``kind`` strings readers report (plain strings so new readers need no enum edit)."""

    TUM = "tum"
    TUM_PAIR = "tum_pair"
    SEVEN_SCENES = "7scenes"
    EUROC = "euroc"
    KITTI = "kitti"
    VIDEO = "video"
    MCAP = "mcap"


KINECT_READOUT_S = 0.020
"""Rolling-shutter readout of the Kinect v1 colour camera (and the PrimeSense-design Xtion), s:
measured on TUM fr1 and checked on 7-Scenes (docs/estimation.md, "Rolling shutter")."""


_DIST_LENGTHS = (0, 4, 5, 8, 12, 14)
"""The lengths of an OpenCV distortion vector (none, radial-tangential, + k3, rational, thin prism, tilt)."""


@dataclass(frozen=True, slots=True)
class CameraIntrinsics:
    """Pinhole intrinsics of one camera, in pixels.

    Attributes:
        fx, fy: focal lengths, px.
        cx, cy: principal point, px (OpenCV convention: pixel centres at integers).
        width, height: image size, px.
        dist: OpenCV distortion coefficients ``(k1, k2, p1, p2[, k3, ...])``; empty when the
            images are undistorted (rectified datasets, rectified EuRoC).
        readout_s: rolling-shutter readout, first row to last row, s; 0 for a global shutter.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    dist: tuple[float, ...] = ()
    readout_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            value = float(getattr(self, name))
            if not math.isfinite(value):
                raise DatasetError(f"camera intrinsic {name} is {value}; it must be a finite number")
            object.__setattr__(self, name, value)
        if self.fx <= 0 or self.fy <= 0:
            raise DatasetError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise DatasetError(f"image size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        dist = tuple(float(d) for d in self.dist)
        if len(dist) not in _DIST_LENGTHS or not all(math.isfinite(d) for d in dist):
            raise DatasetError(
                f"camera distortion {dist} has {len(dist)} coefficients; OpenCV's model takes "
                "4, 5, 8, 12 or 14 finite ones (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1-s4[, tau_x, tau_y]]]]) "
                "or none: give them in that order, zeros for the terms the calibration did not fit"
            )
        object.__setattr__(self, "dist", dist)
        readout = float(self.readout_s)
        if not (math.isfinite(readout) and readout >= 0.0):
            raise DatasetError(f"rolling-shutter readout_s is {readout}; it must be 0 (global shutter) or more")
        object.__setattr__(self, "readout_s", readout)

    @property
    def K(self) -> npt.NDArray[np.float64]:  # noqa: N802 - the usual name of the matrix
        """The 3x3 camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_array(self) -> npt.NDArray[np.float64]:
        """Distortion coefficients as an array (length 0, 4, 5, 8, ...), for OpenCV calls."""
        return np.asarray(self.dist, dtype=np.float64)

    @property
    def is_distorted(self) -> bool:
        return any(d != 0.0 for d in self.dist)

    @staticmethod
    def from_K(  # noqa: N802
        K: npt.ArrayLike,
        width: int,
        height: int,
        dist: tuple[float, ...] = (),  # noqa: N803
    ) -> CameraIntrinsics:
        m = np.asarray(K, dtype=np.float64)
        return CameraIntrinsics(m[0, 0], m[1, 1], m[0, 2], m[1, 2], width, height, dist)

    def scaled(self, factor: float) -> CameraIntrinsics:
        """Intrinsics of the image resized by ``factor`` (e.g. 0.5 for half resolution)."""
        return CameraIntrinsics(
            self.fx * factor,
            self.fy * factor,
            (self.cx + 0.5) * factor - 0.5,
            (self.cy + 0.5) * factor - 0.5,
            round(self.width * factor),
            round(self.height * factor),
            self.dist,
            self.readout_s,
        )

    def to_dict(self) -> dict[str, object]:
        return {
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "width": self.width,
            "height": self.height,
            "dist": list(self.dist),
            "readout_s": self.readout_s,
        }


@dataclass(frozen=True, slots=True, eq=False)
class StereoRectification:
    """How raw stereo images were rectified (EuRoC); rectified datasets (KITTI) have none.

    Attributes:
        left_raw, right_raw: the raw (distorted) cameras.
        R_left_rect: rotation (3x3) taking rectified-left coordinates into raw-left
            coordinates (the inverse of OpenCV's ``R1``), so
            ``T_world_rect = T_world_left @ Transform(R_left_rect)``.
        T_right_left: raw right camera from raw left camera (4x4), as calibrated.
        rectified: the common intrinsics of both rectified images (no distortion).
        baseline_m: distance between the rectified optical centres.
        maps_left, maps_right: ``cv2.remap`` maps (float32 x, float32 y), shape (H, W).
    """

    left_raw: CameraIntrinsics
    right_raw: CameraIntrinsics
    R_left_rect: npt.NDArray[np.float64]
    T_right_left: npt.NDArray[np.float64]
    rectified: CameraIntrinsics
    baseline_m: float
    maps_left: tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]] = field(repr=False)
    maps_right: tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]] = field(repr=False)


@dataclass(frozen=True, slots=True, eq=False)
class Frame:
    """One time step of a sequence: the images taken together, and the ground truth if known.

    Attributes:
        index: position in the sequence (0-based, counts every frame, also skipped ones).
        stamp_ns: capture time, integer nanoseconds (dataset clock; 7-Scenes and video use
            nominal times from the frame rate).
        gray: 8-bit grayscale image (H, W) of the (left) camera; always present.
        color_bgr: 8-bit BGR image (H, W, 3) when the sensor is colour, else None.
        right_gray: rectified right image (H, W) of a stereo pair, else None.
        depth_raw: depth image as stored (uint16 counts or float32 metres), else None.
        depth_scale_m: metres per ``depth_raw`` unit (TUM 1/5000, 7-Scenes/RealSense 1/1000).
        T_world_camera: ground-truth pose of the camera, or None.
    """

    index: int
    stamp_ns: int
    gray: GrayImage
    color_bgr: ColorImage | None = None
    right_gray: GrayImage | None = None
    depth_raw: npt.NDArray[np.uint16] | npt.NDArray[np.float32] | None = None
    depth_scale_m: float = 1.0
    T_world_camera: Transform | None = None

    @property
    def stamp_s(self) -> float:
        return self.stamp_ns * 1e-9

    @property
    def depth_m(self) -> npt.NDArray[np.float32] | None:
        """Depth in metres as float32 (H, W); 0 marks invalid pixels (no NaN).

        Computed from ``depth_raw`` on each access (about 1 ms for VGA), so keep the result.
        """
        if self.depth_raw is None:
            return None
        depth = self.depth_raw.astype(np.float32) * np.float32(self.depth_scale_m)
        if depth.dtype.kind == "f" and self.depth_raw.dtype.kind == "f":
            depth[~np.isfinite(depth)] = 0.0
        return depth


@runtime_checkable
class Sequence(Protocol):
    """A recorded camera sequence that can be replayed frame by frame.

    Attributes:
        name: short human name (the folder or file name).
        kind: one of :class:`SequenceKind` (``"euroc"``, ``"kitti"``, ...).
        path: where it was read from.
        intrinsics: the camera of ``Frame.gray`` / ``color_bgr`` (rectified when rectified).
        depth_intrinsics: the camera of ``Frame.depth_raw`` (None without depth). In 7-Scenes
            colour and depth are different cameras; in TUM the depth is registered to colour.
        baseline_m: stereo baseline of ``Frame.right_gray`` (None without stereo).
        rectification: how raw stereo was rectified (None when the data came rectified).
    """

    name: str
    kind: str
    path: Path
    intrinsics: CameraIntrinsics
    depth_intrinsics: CameraIntrinsics | None
    baseline_m: float | None
    rectification: StereoRectification | None

    def __len__(self) -> int:
        """Number of frames."""
        ...

    def stamps_ns(self) -> npt.NDArray[np.int64]:
        """Frame stamps (N,), without loading images."""
        ...

    def frames(self, start: int = 0, stop: int | None = None, step: int = 1) -> Iterator[Frame]:
        """Yield frames ``start:stop:step``, loading images one frame at a time.

        Raises:
            DatasetError: an image file is missing or cannot be decoded.
        """
        ...

    def has_groundtruth(self) -> bool:
        """True when :meth:`groundtruth` will return a trajectory."""
        ...

    def groundtruth(self) -> Trajectory:
        """Ground-truth camera poses ``T_world_camera`` at their own (mocap) stamps.

        Raises:
            DatasetError: the sequence has no ground truth.
        """
        ...
