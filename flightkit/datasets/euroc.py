"""EuRoC MAV (ASL layout) folders: raw stereo, rectified on the fly.

Layout::

    <seq>/mav0/cam0/data.csv        "#timestamp [ns],filename"
    <seq>/mav0/cam0/data/<ns>.png   raw (distorted) 752x480 grayscale
    <seq>/mav0/cam0/sensor.yaml     T_BS (camera in body), intrinsics fu fv cu cv, radial-tangential,
                                    and flightkit's optional readout_s (rolling shutter, s)
    <seq>/mav0/cam1/...             right camera, same files
    <seq>/mav0/state_groundtruth_estimate0/data.csv   body pose in the world (ASL csv), or
    <seq>/groundtruth_tum.txt                         the same as a TUM file

Ground truth is the body (IMU) pose ``T_WB``; the camera pose is ``T_WB @ T_BS`` (cam0), and
for rectified images ``T_WB @ T_BS @ R_left_rect`` (the rectified camera is rotated by
``R1`` from OpenCV's ``stereoRectify``). Frame poses are interpolated at the image stamps
when a ground-truth sample lies within 20 ms; ``groundtruth()`` returns the camera
trajectory at the ground-truth stamps.

Rectification uses ``cv2.stereoRectify`` with ``CALIB_ZERO_DISPARITY`` and ``alpha=0`` (only
valid pixels), then ``cv2.initUndistortRectifyMap``; both rectified images share
``intrinsics`` and lie on the same rows.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import cast

import cv2
import numpy as np
import numpy.typing as npt

from flightkit.bus.image_msgs import CameraInfo
from flightkit.calibration.result import CalibrationResult
from flightkit.datasets.base import CameraIntrinsics, SequenceKind, StereoRectification
from flightkit.datasets.files import FileSequence, FrameFiles, poses_at, require
from flightkit.datasets.trajectory import Trajectory, associate, read_tum
from flightkit.errors import DatasetError
from flightkit.frames import Transform

__all__ = [
    "EurocCamera",
    "euroc_sensor_yaml",
    "is_euroc_folder",
    "open_euroc",
    "read_euroc_camera",
    "stereo_rectification",
    "write_euroc_groundtruth",
]

logger = logging.getLogger(__name__)

_GT_MAX_NS = 20_000_000
_STEREO_MAX_NS = 1_000_000


def is_euroc_folder(path: Path) -> bool:
    return (path / "mav0").is_dir() or ((path / "cam0" / "data.csv").is_file() and path.name == "mav0")


class EurocCamera:
    """One camera's ``sensor.yaml``: intrinsics (with distortion) and ``T_body_camera``."""

    def __init__(self, intrinsics: CameraIntrinsics, T_body_camera: Transform) -> None:  # noqa: N803
        self.intrinsics = intrinsics
        self.T_body_camera = T_body_camera

    def __repr__(self) -> str:
        return f"EurocCamera({self.intrinsics}, T_body_camera={self.T_body_camera})"


def _yaml_numbers(fs: cv2.FileStorage, key: str, path: Path, count: int | None = None) -> list[float]:
    node = fs.getNode(key)
    if node.empty():
        raise DatasetError(f"EuRoC sensor file {path} lacks the key {key!r}")
    if node.isMap():
        node = node.getNode("data")
    values = [float(node.at(i).real()) for i in range(node.size())]
    if count is not None and len(values) != count:
        raise DatasetError(f"EuRoC sensor file {path}: {key} has {len(values)} values, expected {count}")
    return values


def read_euroc_camera(path: Path) -> EurocCamera:
    """Parse an EuRoC camera ``sensor.yaml`` (with flightkit's ``readout_s`` when present, else 0).

    Raises:
        DatasetError: missing keys, or a camera model other than pinhole/radial-tangential.
    """
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        if not fs.isOpened():
            raise DatasetError(f"EuRoC sensor file {path} cannot be opened as YAML")
        T_BS = np.array(_yaml_numbers(fs, "T_BS", path, 16)).reshape(4, 4)  # noqa: N806
        fu, fv, cu, cv = _yaml_numbers(fs, "intrinsics", path, 4)
        width, height = (int(v) for v in _yaml_numbers(fs, "resolution", path, 2))
        model = fs.getNode("distortion_model").string() or "radial-tangential"
        if model not in ("radial-tangential", "radtan", "plumb_bob"):
            raise DatasetError(
                f"EuRoC sensor file {path}: distortion model {model!r} is not supported; "
                "only radial-tangential (OpenCV k1 k2 p1 p2) is"
            )
        dist = tuple(_yaml_numbers(fs, "distortion_coefficients", path))
        readout = fs.getNode("readout_s")
        readout_s = 0.0 if readout.empty() else readout.real()
    finally:
        fs.release()
    return EurocCamera(CameraIntrinsics(fu, fv, cu, cv, width, height, dist, readout_s), Transform.from_matrix(T_BS))


def stereo_rectification(left: EurocCamera, right: EurocCamera) -> StereoRectification:
    """Rectify a calibrated stereo pair (OpenCV ``stereoRectify``, zero disparity, alpha 0)."""
    T_right_left = (right.T_body_camera.inverse() @ left.T_body_camera).as_matrix()  # noqa: N806
    size = (left.intrinsics.width, left.intrinsics.height)
    R1, R2, P1, P2, _Q, _roi1, _roi2 = cv2.stereoRectify(  # noqa: N806
        left.intrinsics.K,
        left.intrinsics.dist_array,
        right.intrinsics.K,
        right.intrinsics.dist_array,
        size,
        T_right_left[:3, :3].copy(),
        T_right_left[:3, 3].reshape(3, 1).copy(),
        flags=cv2.CALIB_ZERO_DISPARITY,
        alpha=0.0,
    )
    maps_left = cv2.initUndistortRectifyMap(
        left.intrinsics.K, left.intrinsics.dist_array, R1, P1, size, cv2.CV_32FC1
    )
    maps_right = cv2.initUndistortRectifyMap(
        right.intrinsics.K, right.intrinsics.dist_array, R2, P2, size, cv2.CV_32FC1
    )
    rectified = CameraIntrinsics(  # rectification keeps the rows' order: the readout stays the left camera's
        P1[0, 0], P1[1, 1], P1[0, 2], P1[1, 2], size[0], size[1], readout_s=left.intrinsics.readout_s
    )
    baseline = float(-P2[0, 3] / P2[0, 0])
    return StereoRectification(
        left_raw=left.intrinsics,
        right_raw=right.intrinsics,
        R_left_rect=np.asarray(R1, dtype=np.float64).T.copy(),
        T_right_left=T_right_left,
        rectified=rectified,
        baseline_m=baseline,
        maps_left=(_f32(maps_left[0]), _f32(maps_left[1])),
        maps_right=(_f32(maps_right[0]), _f32(maps_right[1])),
    )


def _f32(m: cv2.typing.MatLike) -> npt.NDArray[np.float32]:
    """A CV_32FC1 map from OpenCV, typed as what it is."""
    return cast("npt.NDArray[np.float32]", m)


def _read_image_csv(path: Path) -> tuple[np.ndarray, list[Path]]:
    stamps: list[int] = []
    files: list[Path] = []
    for lineno, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = [p.strip() for p in line.split(",")]
        if len(parts) < 2:
            raise DatasetError(f"{path}:{lineno}: expected 'timestamp_ns,filename', got {line!r}")
        try:
            stamps.append(int(parts[0]))
        except ValueError as exc:
            raise DatasetError(f"{path}:{lineno}: the timestamp {parts[0]!r} is not an integer (ns)") from exc
        files.append(path.parent / "data" / parts[1])
    return np.array(stamps, dtype=np.int64), files


def _read_asl_groundtruth(path: Path) -> Trajectory:
    """ASL ``state_groundtruth_estimate0/data.csv``: t_ns, p xyz, q wxyz, (v, biases ignored)."""
    stamps: list[int] = []
    rows: list[list[float]] = []
    for lineno, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split(",")
        if len(parts) < 8:
            raise DatasetError(f"{path}:{lineno}: expected at least 8 columns 't_ns, p_xyz, q_wxyz'")
        try:
            stamps.append(int(parts[0]))
            rows.append([float(v) for v in parts[1:8]])
        except ValueError as exc:
            raise DatasetError(f"{path}:{lineno}: {exc}") from exc
    arr = np.array(rows)
    return Trajectory(np.array(stamps, dtype=np.int64), arr[:, :3], arr[:, 3:7], "groundtruth")


def _body_groundtruth(seq: Path, mav0: Path) -> Trajectory | None:
    asl = mav0 / "state_groundtruth_estimate0" / "data.csv"
    if asl.is_file():
        return _read_asl_groundtruth(asl)
    tum = seq / "groundtruth_tum.txt"
    if tum.is_file():
        return read_tum(tum, name="groundtruth")
    return None


def open_euroc(path: Path, rectify: bool = True, stereo: bool = True) -> FileSequence:
    """Open an EuRoC (ASL) folder; ``path`` may be the sequence folder or its ``mav0``.

    Args:
        rectify: yield undistorted, stereo-rectified images (``intrinsics`` is then the
            rectified camera without distortion); else raw images with the raw cam0 intrinsics.
        stereo: also load ``cam1`` as ``Frame.right_gray``.

    Raises:
        DatasetError: a required file is missing ("EuRoC folder /x lacks mav0/cam1/data.csv").
    """
    seq = path.parent if path.name == "mav0" else path
    mav0 = seq / "mav0"
    kind = "EuRoC"
    cam0_csv = require(mav0 / "cam0" / "data.csv", "left image list", seq, kind)
    cam0 = read_euroc_camera(require(mav0 / "cam0" / "sensor.yaml", "left calibration", seq, kind))
    stamps, left_files = _read_image_csv(cam0_csv)
    right_files: list[Path | None] = [None] * len(left_files)
    rect: StereoRectification | None = None
    intrinsics = cam0.intrinsics
    baseline = None
    keep = np.arange(stamps.size)
    if stereo or rectify:
        cam1_csv = require(mav0 / "cam1" / "data.csv", "right image list", seq, kind)
        cam1 = read_euroc_camera(require(mav0 / "cam1" / "sensor.yaml", "right calibration", seq, kind))
        if stereo:
            r_stamps, r_files = _read_image_csv(cam1_csv)
            ia, ib = associate(stamps, r_stamps, _STEREO_MAX_NS)
            order = np.argsort(ia)
            keep = ia[order]
            right_files = [None] * len(left_files)
            for a, b in zip(ia, ib, strict=True):
                right_files[int(a)] = r_files[int(b)]
            if keep.size < stamps.size:
                logger.info("EuRoC %s: %d left images have no right partner", seq, stamps.size - keep.size)
        if rectify:
            rect = stereo_rectification(cam0, cam1)
            intrinsics = rect.rectified
            baseline = rect.baseline_m
        else:
            baseline = float(np.linalg.norm((cam1.T_body_camera.inverse() @ cam0.T_body_camera).translation))
    body_gt = _body_groundtruth(seq, mav0)
    cam_gt = None
    poses: list[Transform | None] = [None] * len(left_files)
    if body_gt is not None:
        T_body_cam = cam0.T_body_camera  # noqa: N806
        if rect is not None:
            T_body_cam = T_body_cam @ Transform.from_matrix(_rot4(rect.R_left_rect))  # noqa: N806
        cam_gt = body_gt.right_multiplied(T_body_cam)
        poses = [None if p is None else p @ cam0.T_body_camera for p in poses_at(body_gt, stamps, _GT_MAX_NS)]
    files = [
        FrameFiles(int(stamps[i]), left_files[i], right=right_files[i], T_world_camera=poses[i]) for i in keep
    ]
    return FileSequence(
        name=seq.name,
        kind=SequenceKind.EUROC,
        path=seq,
        files=files,
        intrinsics=intrinsics,
        color=False,
        baseline_m=baseline,
        rectification=rect,
        groundtruth=cam_gt,
    )


def _rot4(R: np.ndarray) -> np.ndarray:  # noqa: N803
    m = np.eye(4)
    m[:3, :3] = R
    return m


# --------------------------------------------------------------------------- writing


def euroc_sensor_yaml(
    info: CameraInfo, T_body_camera: Transform, rate_hz: float, comment: str,  # noqa: N803
    timing: CalibrationResult | None = None, readout_s: float = 0.0,
) -> str:
    """A camera's ``sensor.yaml`` (``T_BS`` = ``T_body_camera``, pinhole, radial-tangential), with
    the measured camera-to-mocap time offset and drift of ``timing`` when given (the exported
    ground truth is already on the camera's clock, so Kalibr's ``timeshift_cam_imu`` left is 0),
    and an extra ``readout_s`` key (rolling shutter, s) only when ``readout_s`` > 0."""
    k = info.k
    d = (list(info.d) + [0.0] * 4)[:4]
    T = T_body_camera.as_matrix().reshape(-1)  # noqa: N806
    text = (
        "%YAML:1.0\n"
        "# General sensor definitions.\n"
        "sensor_type: camera\n"
        f"comment: {comment}\n\n"
        "# Sensor extrinsics wrt. the body-frame.\n"
        "T_BS:\n  cols: 4\n  rows: 4\n"
        "  data: [" + ", ".join(repr(float(v)) for v in T) + "]\n\n"
        "# Camera specific definitions.\n"
        f"rate_hz: {rate_hz:.6g}\n"
        f"resolution: [{info.width}, {info.height}]\n"
        "camera_model: pinhole\n"
        f"intrinsics: [{k[0]!r}, {k[4]!r}, {k[2]!r}, {k[5]!r}] #fu, fv, cu, cv\n"
        "distortion_model: radial-tangential\n"
        "distortion_coefficients: [" + ", ".join(repr(float(v)) for v in d) + "]\n"
    )
    if readout_s > 0:
        text += f"readout_s: {float(readout_s)!r} # rolling-shutter readout, first row to last, s (flightkit)\n"
    if timing is not None and timing.time_offset_ms is not None:
        text += (
            "\n# Time, measured by flightkit calibrate: camera stamp - mocap stamp = offset + drift * (t - ref).\n"
            "# The ground truth of this folder is already on the camera's clock (moved by it).\n"
            f"time_offset_s: {timing.time_offset_ms * 1e-3!r}\n"
            f"time_offset_uncertainty_s: {(timing.time_offset_uncertainty_ms or 0.0) * 1e-3!r}\n"
            f"time_drift_ppm: {float(timing.drift_ppm or 0.0)!r}\n"
            f"time_ref_ns: {int(timing.ref_ns or 0)}\n"
            "timeshift_cam_imu: 0.0 # s, left between cam0 and state_groundtruth_estimate0 stamps\n"
        )
    return text


def write_euroc_groundtruth(folder: Path, body_traj: Trajectory) -> None:
    """``state_groundtruth_estimate0/``: ``data.csv`` (17 columns as EuRoC; velocities from the
    positions, biases zero) and its ``sensor.yaml``."""
    folder.mkdir(parents=True, exist_ok=True)
    t_s = (body_traj.stamps_ns - body_traj.stamps_ns[0]) * 1e-9
    vel = np.gradient(body_traj.positions, t_s, axis=0) if len(body_traj) > 1 else np.zeros((len(body_traj), 3))
    header = (
        "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
        "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], "
        "b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], "
        "b_a_RS_S_z [m s^-2]\n"
    )
    lines = [
        f"{int(t)}," + ",".join(f"{v:.9f}" for v in (*p, *q, *v)) + ",0,0,0,0,0,0\n"
        for t, p, q, v in zip(body_traj.stamps_ns, body_traj.positions, body_traj.quats_wxyz, vel, strict=True)
    ]
    (folder / "data.csv").write_text(header + "".join(lines))
    (folder / "sensor.yaml").write_text(
        "%YAML:1.0\nsensor_type: visual-inertial\ncomment: mocap body pose exported by flightkit\n"
        "T_BS:\n  cols: 4\n  rows: 4\n  data: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, "
        "0.0, 0.0, 0.0, 1.0]\n"
    )
