"""KITTI odometry sequence folders (rectified stereo).

Layout (``dataset/sequences/06/`` of the KITTI odometry benchmark)::

    image_0/000000.png ...   left grayscale (rectified)     image_2/  left colour (optional)
    image_1/000000.png ...   right grayscale (rectified)    image_3/  right colour
    calib.txt                "P0: 12 numbers", "P1: ..." (3x4 projection matrices)
    times.txt                one time in seconds per frame
    poses.txt                optional ground truth (else ../../poses/06.txt as in the benchmark)

The ground truth is ``T_world_camera`` of the left camera (cam0), with the world being cam0
at frame 0. ``baseline_m = -P1[0, 3] / P1[0, 0]``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flightkit.datasets.base import CameraIntrinsics, SequenceKind
from flightkit.datasets.files import FileSequence, FrameFiles, read_gray, require
from flightkit.datasets.trajectory import read_kitti_poses, read_kitti_times
from flightkit.errors import DatasetError

__all__ = ["is_kitti_folder", "open_kitti", "read_kitti_calib"]


def is_kitti_folder(path: Path) -> bool:
    return (path / "image_0").is_dir() or (path / "image_2").is_dir()


def read_kitti_calib(path: Path) -> dict[str, np.ndarray]:
    """Read ``calib.txt`` into ``{"P0": 3x4, "P1": 3x4, ...}``.

    Raises:
        DatasetError: a line that is not ``NAME: numbers``.
    """
    out: dict[str, np.ndarray] = {}
    for lineno, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        if not sep:
            raise DatasetError(f"{path}:{lineno}: expected 'P0: 12 numbers', got {line[:40]!r}")
        try:
            values = np.array([float(v) for v in rest.split()])
        except ValueError as exc:
            raise DatasetError(f"{path}:{lineno}: {exc}") from exc
        if values.size == 12:
            out[key.strip()] = values.reshape(3, 4)
        else:
            out[key.strip()] = values
    return out


def open_kitti(path: Path, color: bool = False) -> FileSequence:
    """Open a KITTI odometry sequence folder (stereo; colour cameras 2/3 when ``color``).

    Raises:
        DatasetError: the image folders, ``calib.txt`` or ``times.txt`` are missing, or the
            image and time counts differ.
    """
    kind = "KITTI"
    left_dir, right_dir, lp, rp = (
        ("image_2", "image_3", "P2", "P3") if color else ("image_0", "image_1", "P0", "P1")
    )
    left = sorted(require(path / left_dir, "left images", path, kind).glob("*.png"))
    right_folder = path / right_dir
    right = sorted(right_folder.glob("*.png")) if right_folder.is_dir() else []
    calib = read_kitti_calib(require(path / "calib.txt", "projection matrices P0..P3", path, kind))
    if lp not in calib:
        raise DatasetError(
            f"KITTI folder {path}: calib.txt lacks {lp}; it needs lines 'P0: ...' and 'P1: ...'"
        )
    stamps = read_kitti_times(require(path / "times.txt", "frame times", path, kind))
    if not left:
        raise DatasetError(f"KITTI folder {path} lacks images in {left_dir}/")
    if stamps.size != len(left):
        raise DatasetError(
            f"KITTI folder {path}: times.txt has {stamps.size} lines but {left_dir}/ holds {len(left)} images"
        )
    if right and len(right) != len(left):
        raise DatasetError(
            f"KITTI folder {path}: {left_dir}/ holds {len(left)} images but {right_dir}/ {len(right)}"
        )
    P_left = calib[lp]  # noqa: N806
    width, height = _image_size(left[0])
    K = CameraIntrinsics(P_left[0, 0], P_left[1, 1], P_left[0, 2], P_left[1, 2], width, height)  # noqa: N806
    baseline = None
    if right and rp in calib:
        P_right = calib[rp]  # noqa: N806
        # Both P matrices share the rectified camera; P[0,3] = -fx * (x of the camera centre).
        baseline = float((P_left[0, 3] - P_right[0, 3]) / P_right[0, 0])
    gt = None
    poses_file = path / "poses.txt"
    if not poses_file.is_file():
        poses_file = path.parent.parent / "poses" / f"{path.name}.txt"
    if poses_file.is_file():
        gt = read_kitti_poses(poses_file, stamps_ns=stamps, name="groundtruth")
        if color:
            # Ground truth is cam0; cam2 sits at x = -P2[0,3]/fx along the rectified x axis.
            from flightkit.frames import Transform

            offset = np.array([-(P_left[0, 3] - calib["P0"][0, 3]) / P_left[0, 0], 0.0, 0.0])
            gt = gt.right_multiplied(Transform(translation=offset))
    poses = gt.transforms() if gt is not None else [None] * len(left)
    files = [
        FrameFiles(int(s), lf, right=right[i] if right else None, T_world_camera=poses[i])
        for i, (s, lf) in enumerate(zip(stamps, left, strict=True))
    ]
    return FileSequence(
        name=path.name,
        kind=SequenceKind.KITTI,
        path=path,
        files=files,
        intrinsics=K,
        color=color,
        baseline_m=baseline,
        groundtruth=gt,
    )


def _image_size(path: Path) -> tuple[int, int]:
    img = read_gray(path)
    return int(img.shape[1]), int(img.shape[0])
