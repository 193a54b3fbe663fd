"""``open_sequence``: recognise a dataset folder or recording file by its layout and open it.

Recognised (first match wins)::

    *.mcap                                 flightkit/ROS 2 recording     -> recording.open_mcap
    video file (*.mp4, *.avi, *.mkv, ...)  + calibration YAML/JSON       -> video.open_video
    folder with mav0/                      EuRoC (ASL)                   -> euroc.open_euroc
    folder with image_0/ or image_2/       KITTI odometry                -> kitti.open_kitti
    folder with rgb.txt / depth.txt        TUM RGB-D                     -> tum.open_tum
    folder with img_prev.png / pose_prev   TUM pair fixture              -> tum.open_tum_pair
    folder with frame-*.color.png          7-Scenes                      -> sevenscenes.open_sevenscenes

An unrecognised or incomplete folder raises DatasetError naming what is missing.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from flightkit.datasets.base import Sequence
from flightkit.errors import DatasetError

__all__ = ["VIDEO_SUFFIXES", "open_sequence"]

VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".webm", ".m4v", ".mpg", ".mpeg")


def open_sequence(path: str | os.PathLike[str], **options: Any) -> Sequence:
    """Open any supported dataset folder or recording as a :class:`Sequence`.

    ``options`` go to the matching reader (e.g. ``rectify=False`` for EuRoC, ``color=True``
    for KITTI, ``intrinsics=...`` for TUM/7-Scenes, ``calibration=...`` for video).

    Raises:
        DatasetError: the path does not exist, its layout is not recognised, or a required
            file is missing (the message names it).
    """
    p = Path(path).expanduser()
    if not p.exists():
        raise DatasetError(f"dataset path {p} does not exist; check the path")
    if p.is_file():
        suffix = p.suffix.lower()
        if suffix == ".mcap":
            from flightkit.datasets.recording import open_mcap

            return open_mcap(p, **options)
        if suffix in VIDEO_SUFFIXES:
            from flightkit.datasets.video import open_video

            return open_video(p, **options)
        raise DatasetError(
            f"{p} is a file of unknown type {suffix!r}; expected a .mcap recording, a video "
            f"({', '.join(VIDEO_SUFFIXES)}) or a dataset folder"
        )
    from flightkit.datasets import euroc, kitti, sevenscenes, tum

    if euroc.is_euroc_folder(p):
        return euroc.open_euroc(p, **options)
    if kitti.is_kitti_folder(p):
        return kitti.open_kitti(p, **options)
    if tum.is_tum_folder(p):
        return tum.open_tum(p, **options)
    if tum.is_tum_pair_folder(p):
        return tum.open_tum_pair(p, **options)
    if sevenscenes.is_sevenscenes_folder(p):
        return sevenscenes.open_sevenscenes(p, **options)
    pairs = sorted(c.name for c in p.iterdir() if c.is_dir() and tum.is_tum_pair_folder(c))
    if pairs:
        raise DatasetError(
            f"{p} holds {len(pairs)} separate TUM pair folders ({', '.join(pairs)}); open one of them"
        )
    raise DatasetError(
        f"{p} is not a recognised dataset folder: it has no mav0/ (EuRoC), image_0/ (KITTI), "
        "rgb.txt (TUM RGB-D), img_prev.png (TUM pair) or frame-*.color.png (7-Scenes)"
    )
