"""A video file plus a calibration file, as a sequence (monocular, no ground truth unless given).

Calibration file: ``<video>.json`` / ``<video>.yaml`` beside the video (same stem), or
``calibration.json`` / ``calibration.yaml`` in its folder, or passed explicitly. JSON::

    {
      "fx": 615.2, "fy": 615.0, "cx": 320.4, "cy": 240.1,
      "width": 640, "height": 480,
      "dist": [0.1, -0.2, 0.0, 0.0, 0.05],          # OpenCV k1 k2 p1 p2 [k3 ...], optional
      "readout_s": 0.02,                             # optional: rolling-shutter readout, s
      "fps": 30.0,                                   # optional: overrides the container's rate
      "start_stamp_ns": 1700000000000000000,         # optional: stamp of frame 0 (default 0)
      "groundtruth": "gt_tum.txt"                    # optional: TUM file of T_world_camera
    }

YAML uses the same keys, or OpenCV's calibration output (``camera_matrix`` as an
``opencv-matrix``, ``distortion_coefficients``, ``image_width``, ``image_height``), read with
``cv2.FileStorage``. Frame ``i`` is stamped ``start_stamp_ns + round(i * 1e9 / fps)``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np
import numpy.typing as npt

from flightkit.datasets.base import CameraIntrinsics, Frame, SequenceKind, StereoRectification
from flightkit.datasets.files import poses_at
from flightkit.datasets.trajectory import Trajectory, read_tum
from flightkit.errors import DatasetError

__all__ = ["VideoSequence", "find_calibration", "open_video", "read_calibration"]


def find_calibration(video: Path) -> Path:
    """The calibration file that belongs to ``video`` (see the module docstring)."""
    candidates = [video.with_suffix(s) for s in (".json", ".yaml", ".yml")]
    candidates += [video.parent / f"calibration{s}" for s in (".json", ".yaml", ".yml")]
    for c in candidates:
        if c.is_file():
            return c
    raise DatasetError(
        f"video {video} lacks a calibration file; write {video.with_suffix('.json')} with fx, fy, cx, cy, "
        "width, height (see docs/datasets.md)"
    )


def _yaml_calibration(path: Path) -> dict[str, Any]:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        if not fs.isOpened():
            raise DatasetError(f"calibration file {path} cannot be opened as YAML")
        out: dict[str, Any] = {}
        cm = fs.getNode("camera_matrix")
        if not cm.empty():
            K = cm.mat()  # noqa: N806
            out.update(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2])
            dist = fs.getNode("distortion_coefficients")
            if not dist.empty():
                out["dist"] = [float(v) for v in dist.mat().reshape(-1)]
            out["width"] = fs.getNode("image_width").real()
            out["height"] = fs.getNode("image_height").real()
        for key in ("fx", "fy", "cx", "cy", "width", "height", "fps", "start_stamp_ns", "readout_s"):
            node = fs.getNode(key)
            if not node.empty():
                out[key] = node.real()
        node = fs.getNode("dist")
        if not node.empty():
            out["dist"] = [node.at(i).real() for i in range(node.size())]
        node = fs.getNode("groundtruth")
        if not node.empty():
            out["groundtruth"] = node.string()
        return out
    finally:
        fs.release()


def read_calibration(path: Path) -> dict[str, Any]:
    """Read a calibration file into a dict with at least fx, fy, cx, cy, width, height.

    Raises:
        DatasetError: unreadable file or a missing key (named).
    """
    data: dict[str, Any]
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            raise DatasetError(f"calibration file {path} is not valid JSON: {exc}") from exc
        if not isinstance(data, dict):
            raise DatasetError(f"calibration file {path} must hold a JSON object")
    else:
        data = _yaml_calibration(path)
    missing = [k for k in ("fx", "fy", "cx", "cy", "width", "height") if k not in data]
    if missing:
        raise DatasetError(f"calibration file {path} lacks {', '.join(missing)}")
    return data


class VideoSequence:
    """:class:`~flightkit.datasets.base.Sequence` over a video file decoded with OpenCV."""

    def __init__(self, path: Path, calibration: Path | None = None) -> None:
        self.path = path
        self.name = path.stem
        self.kind = SequenceKind.VIDEO
        self.depth_intrinsics: CameraIntrinsics | None = None
        self.baseline_m: float | None = None
        self.rectification: StereoRectification | None = None
        calib_path = calibration or find_calibration(path)
        calib = read_calibration(calib_path)
        self.intrinsics = CameraIntrinsics(
            calib["fx"],
            calib["fy"],
            calib["cx"],
            calib["cy"],
            int(calib["width"]),
            int(calib["height"]),
            tuple(calib.get("dist", ())),
            float(calib.get("readout_s", 0.0)),
        )
        cap = self._open()
        try:
            count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
            fps = float(calib.get("fps") or cap.get(cv2.CAP_PROP_FPS) or 0.0)
            size = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        finally:
            cap.release()
        if not math.isfinite(fps) or fps <= 0:
            raise DatasetError(f'video {path} reports no frame rate; add "fps" to {calib_path}')
        if size != (self.intrinsics.width, self.intrinsics.height):
            raise DatasetError(
                f"video {path} is {size[0]}x{size[1]} but {calib_path} describes "
                f"{self.intrinsics.width}x{self.intrinsics.height}; use the calibration of this resolution"
            )
        if count <= 0:
            raise DatasetError(f"video {path} reports no frames; is it a valid video file?")
        self.fps = fps
        start = int(calib.get("start_stamp_ns", 0))
        self._stamps = start + np.round(np.arange(count) * 1e9 / fps).astype(np.int64)
        self._gt: Trajectory | None = None
        if calib.get("groundtruth"):
            gt_path = Path(str(calib["groundtruth"]))
            self._gt = read_tum(
                gt_path if gt_path.is_absolute() else calib_path.parent / gt_path, "groundtruth"
            )

    def _open(self) -> cv2.VideoCapture:
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            raise DatasetError(f"video {self.path} cannot be opened by OpenCV; is the codec supported?")
        return cap

    def __len__(self) -> int:
        return int(self._stamps.size)

    def __repr__(self) -> str:
        return f"VideoSequence(name={self.name!r}, frames={len(self)}, fps={self.fps})"

    def stamps_ns(self) -> npt.NDArray[np.int64]:
        return self._stamps.copy()

    def has_groundtruth(self) -> bool:
        return self._gt is not None

    def groundtruth(self) -> Trajectory:
        if self._gt is None:
            raise DatasetError(
                f'video {self.path} has no ground truth; add "groundtruth" to its calibration file'
            )
        return self._gt

    def frames(self, start: int = 0, stop: int | None = None, step: int = 1) -> Iterator[Frame]:
        indices = range(len(self))[start:stop:step]
        if not indices:
            return
        poses = poses_at(self._gt, self._stamps, 20_000_000) if self._gt is not None else None
        cap = self._open()
        try:
            i = 0
            wanted = set(indices)
            last = max(indices)
            while i <= last:
                if i in wanted:
                    ok, img = cap.read()
                    if not ok:
                        break  # the container's frame count can overstate the stream
                    color = np.asarray(img, dtype=np.uint8)
                    yield Frame(
                        index=i,
                        stamp_ns=int(self._stamps[i]),
                        gray=cast("npt.NDArray[np.uint8]", cv2.cvtColor(color, cv2.COLOR_BGR2GRAY)),
                        color_bgr=color,
                        T_world_camera=poses[i] if poses is not None else None,
                    )
                elif not cap.grab():
                    break
                i += 1
        finally:
            cap.release()


def open_video(path: Path, calibration: str | Path | None = None) -> VideoSequence:
    """Open a video with its calibration (found beside it unless given)."""
    return VideoSequence(path, Path(calibration) if calibration is not None else None)
