"""TUM RGB-D folders (``rgb.txt``, ``depth.txt``, ``groundtruth.txt``) and two-frame TUM pair folders.

TUM RGB-D layout (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats)::

    rgbd_dataset_freiburg1_xyz/
        rgb.txt            "timestamp rgb/<stamp>.png" per line, '#' comments
        depth.txt          "timestamp depth/<stamp>.png"
        groundtruth.txt    TUM trajectory of the colour camera (mocap), optional
        rgb/  depth/

Colour and depth are associated by nearest stamp within 20 ms (TUM's ``associate.py``
default); depth is registered to colour and stored as uint16 with 5000 units per metre
(0 = no data). The per-frame ground truth is the mocap pose interpolated at the colour
stamp when a mocap sample lies within 20 ms.

Intrinsics are not stored in TUM's own folders; they are taken from a ``camera.yaml`` when
the folder has one (folders flightkit exports write it), else chosen from the folder name
(``freiburg1/2/3``, TUM's published calibration) unless given explicitly, with the ROS
default 525/525/319.5/239.5 for an unknown sensor.

Writing (what ``flightkit export --format tum`` uses): :func:`tum_associate` (TUM's
``associate.py``), :func:`to_tum_depth`, :func:`write_tum_camera_yaml` and
:func:`read_tum_camera_yaml`.

TUM pair layout (known-answer fixtures, e.g. ``tum_fr1xyz_pairs/case_1``)::

    img_prev.png img_curr.png dep_prev.png dep_curr.png pose_prev.txt pose_curr.txt

``pose_*.txt`` hold one ``tx ty tz qx qy qz qw`` row; stamps are looked up in a
``groundtruth_tum.txt`` of the parent folder (matching row), else nominal 0 and 1/30 s.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from flightkit.bus.image_msgs import CameraInfo
from flightkit.datasets.base import KINECT_READOUT_S, CameraIntrinsics, SequenceKind
from flightkit.datasets.files import FileSequence, FrameFiles, poses_at, require
from flightkit.datasets.trajectory import Trajectory, associate, parse_stamp_ns, read_tum
from flightkit.errors import DatasetError
from flightkit.frames import Transform

__all__ = [
    "TUM_DEPTH_FACTOR",
    "TUM_INTRINSICS",
    "is_tum_folder",
    "is_tum_pair_folder",
    "open_tum",
    "open_tum_pair",
    "read_tum_camera_yaml",
    "to_tum_depth",
    "tum_associate",
    "tum_intrinsics",
    "write_tum_camera_yaml",
]

logger = logging.getLogger(__name__)

TUM_DEPTH_FACTOR = 5000.0
"""Depth units per metre in TUM RGB-D depth PNGs."""
TUM_DEPTH_SCALE_M = 1.0 / TUM_DEPTH_FACTOR
_ASSOC_MAX_NS = 20_000_000

# TUM's published colour-camera calibration (the Kinects are 640x480) and the colour camera's
# rolling-shutter readout (KINECT_READOUT_S).
TUM_INTRINSICS: dict[str, CameraIntrinsics] = {
    "freiburg1": CameraIntrinsics(
        517.306408,
        516.469215,
        318.643040,
        255.313989,
        640,
        480,
        (0.262383, -0.953104, -0.005358, 0.002628, 1.163314),
        KINECT_READOUT_S,
    ),
    "freiburg2": CameraIntrinsics(
        520.908620,
        521.007327,
        325.141442,
        249.701764,
        640,
        480,
        (0.231222, -0.784899, -0.003257, -0.000105, 0.917205),
        KINECT_READOUT_S,
    ),
    "freiburg3": CameraIntrinsics(535.4, 539.2, 320.1, 247.6, 640, 480, (), KINECT_READOUT_S),
    # TUM's default: the Kinect's factory calibration (every TUM RGB-D sequence is a Kinect v1 or
    # the Xtion of the same design), so the Kinect's readout too.
    "default": CameraIntrinsics(525.0, 525.0, 319.5, 239.5, 640, 480, (), KINECT_READOUT_S),
}

_PAIR_FILES = (
    "img_prev.png",
    "img_curr.png",
    "dep_prev.png",
    "dep_curr.png",
    "pose_prev.txt",
    "pose_curr.txt",
)


def tum_intrinsics(path: Path) -> CameraIntrinsics:
    """The published intrinsics of the TUM sensor named in ``path`` (fr1/fr2/fr3), else the default."""
    text = str(path).lower()
    for key, short in (("freiburg1", "fr1"), ("freiburg2", "fr2"), ("freiburg3", "fr3")):
        if key in text or short in text:
            return TUM_INTRINSICS[key]
    return TUM_INTRINSICS["default"]


def is_tum_folder(path: Path) -> bool:
    return (path / "rgb.txt").is_file() or (path / "depth.txt").is_file()


def is_tum_pair_folder(path: Path) -> bool:
    return any((path / name).exists() for name in ("img_prev.png", "pose_prev.txt"))


def _read_list(path: Path) -> tuple[np.ndarray, list[Path]]:
    stamps: list[int] = []
    files: list[Path] = []
    for lineno, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) < 2:
            raise DatasetError(f"{path}:{lineno}: expected 'timestamp filename', got {line!r}")
        try:
            stamps.append(parse_stamp_ns(parts[0]))
        except DatasetError as exc:
            raise DatasetError(f"{path}:{lineno}: {exc}; the first column is the time in seconds") from exc
        files.append(path.parent / parts[1])
    return np.array(stamps, dtype=np.int64), files


def open_tum(path: Path, intrinsics: CameraIntrinsics | None = None, with_depth: bool = True) -> FileSequence:
    """Open a TUM RGB-D folder.

    Raises:
        DatasetError: ``rgb.txt`` (or ``depth.txt`` when ``with_depth``) is missing, or nothing associates.
    """
    kind = "TUM RGB-D"
    rgb_stamps, rgb_files = _read_list(require(path / "rgb.txt", "list of colour images", path, kind))
    depth_idx: dict[int, Path] = {}
    if with_depth:
        d_stamps, d_files = _read_list(require(path / "depth.txt", "list of depth images", path, kind))
        ia, ib = associate(rgb_stamps, d_stamps, _ASSOC_MAX_NS)
        depth_idx = {int(a): d_files[int(b)] for a, b in zip(ia, ib, strict=True)}
        keep = np.array(sorted(depth_idx), dtype=np.int64)
        if keep.size == 0:
            raise DatasetError(
                f"{kind} folder {path}: no colour and depth images are within 20 ms of each other"
            )
    else:
        keep = np.arange(rgb_stamps.size)
    gt = None
    gt_path = path / "groundtruth.txt"
    if gt_path.is_file():
        gt = read_tum(gt_path, name="groundtruth")
    poses = poses_at(gt, rgb_stamps[keep], _ASSOC_MAX_NS) if gt is not None else [None] * keep.size
    files = [
        FrameFiles(int(rgb_stamps[i]), rgb_files[i], depth=depth_idx.get(int(i)), T_world_camera=pose)
        for i, pose in zip(keep, poses, strict=True)
    ]
    if intrinsics is None and (path / "camera.yaml").is_file():
        intrinsics = read_tum_camera_yaml(path)
    K = intrinsics or tum_intrinsics(path)  # noqa: N806
    if K is TUM_INTRINSICS["default"]:
        logger.warning(
            "%s: its path names no TUM sensor (freiburg1/2/3 or fr1/2/3) and it has no camera.yaml; using TUM's "
            "default Kinect calibration (fx 525 px, readout 20 ms): put the sensor in the folder name or add a "
            "camera.yaml for another camera",
            path,
        )
    return FileSequence(
        name=path.name,
        kind=SequenceKind.TUM,
        path=path,
        files=files,
        intrinsics=K,
        color=True,
        depth_intrinsics=K if with_depth else None,
        depth_scale_m=TUM_DEPTH_SCALE_M,
        groundtruth=gt,
    )


def _read_pose_row(path: Path) -> np.ndarray:
    values = path.read_text(encoding="utf-8").split()
    if len(values) != 7:
        raise DatasetError(f"{path}: expected one row 'tx ty tz qx qy qz qw', got {len(values)} values")
    try:
        return np.array([float(v) for v in values])
    except ValueError as exc:
        raise DatasetError(f"{path}: {exc}; expected 7 numbers") from exc


def open_tum_pair(path: Path, intrinsics: CameraIntrinsics | None = None) -> FileSequence:
    """Open a two-frame TUM pair folder (``img_prev``/``img_curr`` + depth + pose rows).

    Raises:
        DatasetError: one of the six files is missing (names it).
    """
    for name in _PAIR_FILES:
        require(path / name, "TUM pair file", path, "TUM pair")
    rows = [_read_pose_row(path / "pose_prev.txt"), _read_pose_row(path / "pose_curr.txt")]
    stamps = _pair_stamps(path, rows)
    files = []
    for stamp, tag, row in zip(stamps, ("prev", "curr"), rows, strict=True):
        pose = Transform.from_quat_xyzw(row[:3], row[3:7])
        files.append(
            FrameFiles(stamp, path / f"img_{tag}.png", depth=path / f"dep_{tag}.png", T_world_camera=pose)
        )
    gt = Trajectory.from_transforms(
        stamps, [f.T_world_camera for f in files if f.T_world_camera], "groundtruth"
    )
    K = intrinsics or tum_intrinsics(path)  # noqa: N806
    if K is TUM_INTRINSICS["default"]:
        K = TUM_INTRINSICS["freiburg1"]  # noqa: N806 - the published pair fixtures are fr1
    return FileSequence(
        name=f"{path.parent.name}/{path.name}",
        kind=SequenceKind.TUM_PAIR,
        path=path,
        files=files,
        intrinsics=K,
        color=True,
        depth_intrinsics=K,
        depth_scale_m=TUM_DEPTH_SCALE_M,
        groundtruth=gt,
    )


def _pair_stamps(path: Path, rows: list[np.ndarray]) -> list[int]:
    nominal = [0, 33_333_333]
    gt_file = path.parent / "groundtruth_tum.txt"
    if not gt_file.is_file():
        return nominal
    try:
        gt = read_tum(gt_file)
    except DatasetError:
        return nominal
    from flightkit.frames import quat_wxyz_to_xyzw

    table = np.hstack([gt.positions, quat_wxyz_to_xyzw(gt.quats_wxyz)])
    found: list[int] = []
    for row in rows:
        q = row[3:7] / np.linalg.norm(row[3:7])
        cand = np.hstack([row[:3], q])
        err = np.abs(table - cand).max(axis=1)
        best = int(np.argmin(err))
        if err[best] > 1e-6:
            return nominal
        found.append(int(gt.stamps_ns[best]))
    return found


# --------------------------------------------------------------------------- writing


def tum_associate(
    stamps_a_ns: npt.ArrayLike, stamps_b_ns: npt.ArrayLike, max_diff_ns: int, offset_ns: int = 0
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """TUM ``associate.py``: unique pairs ``(i, j)`` with ``|a_i - (b_j + offset)| < max_diff``,
    taken greedily by increasing difference; returned sorted by ``i``."""
    a = np.asarray(stamps_a_ns, dtype=np.int64).reshape(-1)
    b = np.asarray(stamps_b_ns, dtype=np.int64).reshape(-1) + int(offset_ns)
    if a.size == 0 or b.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    order_b = np.argsort(b, kind="stable")
    bs = b[order_b]
    lo = np.searchsorted(bs, a - max_diff_ns, side="right")
    hi = np.searchsorted(bs, a + max_diff_ns, side="left")
    counts = hi - lo
    ii = np.repeat(np.arange(a.size), counts)
    starts = np.repeat(lo, counts)
    within = np.arange(ii.size) - np.repeat(np.cumsum(counts) - counts, counts)
    jj_sorted = starts + within
    diffs = np.abs(a[ii] - bs[jj_sorted])
    order = np.lexsort((jj_sorted, ii, diffs))
    used_a = np.zeros(a.size, bool)
    used_b = np.zeros(b.size, bool)
    out_i: list[int] = []
    out_j: list[int] = []
    for k in order:
        i, js = int(ii[k]), int(jj_sorted[k])
        if used_a[i] or used_b[js]:
            continue
        used_a[i] = used_b[js] = True
        out_i.append(i)
        out_j.append(int(order_b[js]))
    idx = np.argsort(out_i)
    return np.asarray(out_i, np.int64)[idx], np.asarray(out_j, np.int64)[idx]


def to_tum_depth(arr: npt.NDArray[Any], encoding: str) -> npt.NDArray[np.uint16]:
    """A depth image (16UC1 millimetres or 32FC1 metres) as TUM depth (uint16, 5000 per metre, 0 = none).

    Raises:
        DatasetError: another encoding.
    """
    scaled: npt.NDArray[np.float32]
    if encoding in ("16UC1", "mono16"):
        scaled = arr.astype(np.float32) * np.float32(TUM_DEPTH_FACTOR / 1000.0)  # mm -> 1/5000 m
    elif encoding == "32FC1":
        scaled = np.nan_to_num(arr.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0) * np.float32(TUM_DEPTH_FACTOR)
    else:
        raise DatasetError(f"depth encoding {encoding!r} cannot be exported; expected 16UC1 (mm) or 32FC1 (m)")
    return np.clip(np.rint(scaled), 0, 65535).astype(np.uint16)


def write_tum_camera_yaml(
    path: Path, info: CameraInfo, right: CameraInfo | None = None, readout_s: float = 0.0
) -> None:
    """Write ``camera.yaml`` (OpenCV FileStorage, ORB-SLAM style keys, DepthMapFactor 5000), with
    ``Camera.readout_s`` (rolling shutter, s) only when ``readout_s`` > 0, as :func:`read_tum_camera_yaml` reads it."""
    k = info.k
    d = list(info.d) + [0.0] * (5 - len(info.d))
    lines = [
        "%YAML:1.0",
        "---",
        "# Camera calibration (pinhole, OpenCV plumb_bob distortion), exported by flightkit",
        'Camera.type: "PinHole"',
        f"Camera.fx: {k[0]!r}",
        f"Camera.fy: {k[4]!r}",
        f"Camera.cx: {k[2]!r}",
        f"Camera.cy: {k[5]!r}",
        f"Camera.k1: {d[0]!r}",
        f"Camera.k2: {d[1]!r}",
        f"Camera.p1: {d[2]!r}",
        f"Camera.p2: {d[3]!r}",
        f"Camera.k3: {d[4]!r}",
        f"Camera.width: {info.width}",
        f"Camera.height: {info.height}",
        "Camera.RGB: 1",
        f"DepthMapFactor: {TUM_DEPTH_FACTOR!r}",
    ]
    if right is not None and right.p[0]:
        lines.append(f"Camera.bf: {-right.p[3]!r}")
    if readout_s > 0:
        lines.append(f"Camera.readout_s: {float(readout_s)!r}")
    path.write_text("\n".join(lines) + "\n")


def read_tum_camera_yaml(folder: str | Path) -> CameraIntrinsics:
    """The intrinsics in a TUM folder's ``camera.yaml`` (as :func:`write_tum_camera_yaml` writes it;
    an optional ``Camera.readout_s`` gives a rolling shutter's readout, s).

    Raises:
        DatasetError: the file is missing or incomplete.
    """
    path = Path(folder) / "camera.yaml"
    if not path.is_file():
        raise DatasetError(f"{path} does not exist; export the folder with 'flightkit export --format tum'")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        vals = {
            k: fs.getNode(f"Camera.{k}")
            for k in ("fx", "fy", "cx", "cy", "width", "height", "k1", "k2", "p1", "p2", "k3", "readout_s")
        }
        if any(vals[k].empty() for k in ("fx", "fy", "cx", "cy", "width", "height")):
            raise DatasetError(f"{path} lacks Camera.fx/fy/cx/cy/width/height; re-export the folder")
        dist = tuple(vals[k].real() for k in ("k1", "k2", "p1", "p2", "k3") if not vals[k].empty())
        return CameraIntrinsics(
            vals["fx"].real(),
            vals["fy"].real(),
            vals["cx"].real(),
            vals["cy"].real(),
            int(vals["width"].real()),
            int(vals["height"].real()),
            dist if any(dist) else (),
            0.0 if vals["readout_s"].empty() else vals["readout_s"].real(),
        )
    finally:
        fs.release()
