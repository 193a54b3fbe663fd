"""Datasets and recordings: read camera sequences with ground truth, read/write trajectories.

The core that capture (writes recordings, exports folders) and estimation (reads them) share.

Sequences (``base.py``)::

    from flightkit.datasets import open_sequence
    seq = open_sequence("/data/V1_01_easy")         # EuRoC, KITTI, TUM RGB-D, 7-Scenes, .mcap, video
    seq.kind, seq.name, len(seq), seq.intrinsics, seq.baseline_m, seq.depth_intrinsics
    for frame in seq.frames(start=0, stop=None, step=1):
        frame.stamp_ns           # int ns
        frame.gray               # uint8 (H, W), always
        frame.color_bgr          # uint8 (H, W, 3) or None
        frame.right_gray         # rectified right image or None
        frame.depth_m            # float32 metres (0 = invalid) or None; frame.depth_raw + depth_scale_m
        frame.T_world_camera     # flightkit.frames.Transform or None
    seq.groundtruth()            # Trajectory of the camera (DatasetError when absent)

Trajectories (``trajectory.py``)::

    traj = read_tum(path); write_tum(path, traj); read_kitti_poses(path, times_path=...)
    traj.stamps_ns (N,) int64, traj.positions (N, 3) m, traj.quats_wxyz (N, 4)
    a2, b2 = associate_trajectories(a, b, max_diff_s=0.01); traj.interpolate(stamps_ns)

Formats and conventions are described in each reader's module docstring and ``docs/datasets.md``.
"""

from flightkit.datasets.base import CameraIntrinsics, Frame, Sequence, SequenceKind, StereoRectification
from flightkit.datasets.registry import open_sequence
from flightkit.datasets.trajectory import (
    Trajectory,
    associate,
    associate_trajectories,
    read_kitti_poses,
    read_trajectory,
    read_tum,
    write_kitti_poses,
    write_tum,
)

__all__ = [
    "CameraIntrinsics",
    "Frame",
    "Sequence",
    "SequenceKind",
    "StereoRectification",
    "Trajectory",
    "associate",
    "associate_trajectories",
    "open_sequence",
    "read_kitti_poses",
    "read_trajectory",
    "read_tum",
    "write_kitti_poses",
    "write_tum",
]
