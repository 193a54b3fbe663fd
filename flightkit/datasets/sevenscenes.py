"""Microsoft 7-Scenes sequence folders.

Layout (``seq-01/`` of the dataset, or a folder with a ``frames/`` subfolder)::

    frame-000000.color.png   8-bit colour 640x480
    frame-000000.depth.png   16-bit depth in millimetres; 0 and 65535 mean "no data"
    frame-000000.pose.txt    4x4 camera-to-world matrix (T_world_camera), metres
    camera-intrinsics.txt    optional 3x3 K (default fx = fy = 585, cx = 320, cy = 240)

7-Scenes has no timestamps: frames get nominal 30 Hz stamps counted from the first frame
(``round(i * 1e9 / 30)`` ns). Colour and depth come from different cameras and are **not**
registered; ``intrinsics`` and ``depth_intrinsics`` both hold the published approximate
depth-camera intrinsics (585/585/320/240), which is what the dataset provides.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import numpy.typing as npt

from flightkit.datasets.base import KINECT_READOUT_S, CameraIntrinsics, SequenceKind
from flightkit.datasets.files import FileSequence, FrameFiles, require
from flightkit.datasets.trajectory import Trajectory
from flightkit.errors import DatasetError
from flightkit.frames import Transform

__all__ = ["SEVEN_SCENES_INTRINSICS", "is_sevenscenes_folder", "open_sevenscenes"]

SEVEN_SCENES_INTRINSICS = CameraIntrinsics(585.0, 585.0, 320.0, 240.0, 640, 480)
SEVEN_SCENES_RATE_HZ = 30.0
_FRAME = re.compile(r"^frame-(\d+)\.color\.png$")


def _frame_dir(path: Path) -> Path:
    if (path / "frames").is_dir() and any((path / "frames").glob("frame-*.color.png")):
        return path / "frames"
    return path


def is_sevenscenes_folder(path: Path) -> bool:
    folder = _frame_dir(path)
    return any(folder.glob("frame-*.color.png")) or any(folder.glob("frame-*.pose.txt"))


def _read_matrix(path: Path, shape: tuple[int, int]) -> npt.NDArray[np.float64]:
    try:
        values = [float(v) for v in path.read_text(encoding="utf-8").split()]
    except ValueError as exc:
        raise DatasetError(f"{path}: {exc}; expected {shape[0]}x{shape[1]} numbers") from exc
    if len(values) != shape[0] * shape[1]:
        raise DatasetError(f"{path}: expected {shape[0] * shape[1]} numbers, got {len(values)}")
    return np.array(values).reshape(shape)


def open_sevenscenes(path: Path, intrinsics: CameraIntrinsics | None = None) -> FileSequence:
    """Open a 7-Scenes sequence folder.

    Raises:
        DatasetError: no ``frame-*.color.png``, or a frame lacks its depth or pose file.
    """
    folder = _frame_dir(path)
    numbers = sorted(int(m.group(1)) for p in folder.iterdir() if (m := _FRAME.match(p.name)))
    if not numbers:
        raise DatasetError(f"7-Scenes folder {path} lacks frame-XXXXXX.color.png images")
    width = len(next(p.name for p in folder.glob("frame-*.color.png")).split(".")[0]) - len("frame-")
    K = intrinsics  # noqa: N806
    if K is None:
        k_file = path / "camera-intrinsics.txt"
        if k_file.is_file():
            K_file = _read_matrix(k_file, (3, 3))  # noqa: N806
            K = CameraIntrinsics.from_K(K_file, 640, 480)  # noqa: N806
        else:
            K = SEVEN_SCENES_INTRINSICS  # noqa: N806
    files: list[FrameFiles] = []
    poses = []
    first = numbers[0]
    for n in numbers:
        stem = folder / f"frame-{n:0{width}d}"
        depth = require(Path(f"{stem}.depth.png"), "depth image", path, "7-Scenes")
        pose_file = require(Path(f"{stem}.pose.txt"), "camera-to-world pose", path, "7-Scenes")
        T = _read_matrix(pose_file, (4, 4))  # noqa: N806
        pose = Transform.from_matrix(T)
        poses.append(pose)
        stamp = round((n - first) * 1e9 / SEVEN_SCENES_RATE_HZ)
        files.append(FrameFiles(stamp, Path(f"{stem}.color.png"), depth=depth, T_world_camera=pose))
    gt = Trajectory.from_transforms([f.stamp_ns for f in files], poses, "groundtruth")
    return FileSequence(
        name=path.name,
        kind=SequenceKind.SEVEN_SCENES,
        path=path,
        files=files,
        intrinsics=dataclasses.replace(K, readout_s=KINECT_READOUT_S),  # the Kinect v1's colour camera
        color=True,
        depth_intrinsics=K,
        depth_scale_m=1e-3,
        depth_invalid=65535,
        depth_registered=False,
        groundtruth=gt,
    )
