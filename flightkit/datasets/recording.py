"""MCAP recordings (ROS 2 CDR) as sequences: camera images, depth, camera_info and mocap.

What is read (topic names as the flightkit recorder writes them, ``/<ns>/...``)::

    /<ns>/camera/<name>/image              sensor_msgs/msg/Image (mono8, bgr8, rgb8, 16UC1, 32FC1)
    /<ns>/camera/<name>/image/compressed   sensor_msgs/msg/CompressedImage (jpeg/png)
    /<ns>/camera/<name>/camera_info        sensor_msgs/msg/CameraInfo (K, D, size)
    /<ns>/mocap/<body>/pose                geometry_msgs/msg/PoseStamped

The main camera is ``camera`` (default: the first of color, left, gray, infra1, image,
else any non-depth camera); depth is the camera named ``depth`` (16UC1 in millimetres or
32FC1 in metres) and the stereo partner ``right``. A camera's rolling-shutter readout comes from
the recording's ``calibration.<camera>`` record (0, a global shutter, when it has none, as in
recordings made before readouts were recorded). Frames are the main camera's messages,
stamped with their header stamps; depth and right images are attached when their stamp
lies within ``max_diff_s`` (20 ms).

Ground truth, in the world frame: the mocap body poses placed in the world by the frame each
names (``T_world_mocap`` from the recording's metadata, see
:class:`~flightkit.datasets.mcap_reader.RecordingReader`), through the camera's extrinsics:
``T_world_camera = T_world_body @ T_body_camera``. Both transforms come from the recording
unless the caller gives them. A recording that carries a ``flightkit calibrate`` record
(``calibration.time_extrinsics``) is read with its measured ``T_body_camera`` and with the
ground truth moved onto the camera's clock by its measured time offset and drift.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from flightkit.bus.image_msgs import CameraInfo
from flightkit.calibration.result import CalibrationResult
from flightkit.datasets.base import CameraIntrinsics, Frame, SequenceKind, StereoRectification
from flightkit.datasets.files import poses_at
from flightkit.datasets.mcap_reader import RecordingReader, decode_image, header_stamp_ns
from flightkit.datasets.trajectory import Trajectory, associate
from flightkit.errors import DatasetError
from flightkit.frames import Transform

__all__ = ["McapSequence", "open_mcap"]

logger = logging.getLogger(__name__)

_MAIN_PREFERENCE = ("color", "left", "gray", "infra1", "image")


class McapSequence:
    """:class:`~flightkit.datasets.base.Sequence` over an MCAP recording (see the module docstring).

    Args:
        path: the recording.
        camera: the main camera's name (default: the first of color, left, gray, infra1, image).
        mocap_body: the ground-truth body (default: the recording's own, else the first).
        T_world_mocap: overrides the recording's mocap frame in the world.
        T_body_camera: overrides the recording's extrinsics (identity when it has none).
        max_diff_s: depth and right images are attached within this of the main image.
        use_calibration: apply the recording's ``flightkit calibrate`` record when it has one
            (its ``T_body_camera`` unless one is given, and its time offset, which moves the
            ground truth onto the camera's clock).
        calibration: a calibration result (e.g. a ``--calibration FILE.json``) used instead of
            the recording's own record.
        vehicle: the vehicle (bus namespace) whose camera and mocap body to read; needed when the
            recording holds several vehicles' cameras (a fleet's).

    Raises:
        DatasetError: unreadable recording, no camera, no intrinsics, a malformed readout record, unknown body,
            several vehicles' cameras and no ``vehicle`` named.
    """

    def __init__(
        self,
        path: Path,
        camera: str | None = None,
        mocap_body: str | None = None,
        T_world_mocap: Transform | None = None,  # noqa: N803
        T_body_camera: Transform | None = None,  # noqa: N803
        max_diff_s: float = 0.02,
        use_calibration: bool = True,
        calibration: CalibrationResult | None = None,
        vehicle: str | None = None,
    ) -> None:
        self.path = path
        self.name = path.stem
        self.kind = SequenceKind.MCAP
        self.rectification: StereoRectification | None = None
        self._max_diff_ns = round(max_diff_s * 1e9)
        self.reader = RecordingReader(path)
        with_cameras = self.reader.camera_namespaces()
        if vehicle is None and len(with_cameras) > 1:
            raise DatasetError(
                f"recording {path} holds the cameras of {', '.join(with_cameras)}; name the vehicle to read "
                f"(vehicle='{with_cameras[0]}'; flightkit vo run --vehicle {with_cameras[0]})"
            )
        if vehicle is not None:
            if vehicle not in with_cameras:
                raise DatasetError(
                    f"recording {path} has no camera of vehicle {vehicle!r}; it has cameras of "
                    f"{', '.join(with_cameras) or 'no vehicle'}"
                )
            if len(with_cameras) > 1:
                self.name = f"{path.stem}_{vehicle}"  # one output per vehicle of a fleet
        self.vehicle = vehicle
        cams = self.reader.cameras(vehicle)
        image_cams = {n: t for n, t in cams.items() if "image" in t or "image/compressed" in t}
        if not image_cams:
            raise DatasetError(f"recording {path} lacks camera image topics (…/camera/<name>/image)")
        if camera is None:
            camera = next((c for c in _MAIN_PREFERENCE if c in image_cams), None)
            if camera is None:
                camera = next((c for c in sorted(image_cams) if c not in ("depth", "right")), None)
            if camera is None:
                raise DatasetError(
                    f"recording {path} has only {sorted(image_cams)} cameras; name the main one"
                )
        if camera not in image_cams:
            raise DatasetError(f"recording {path} lacks camera {camera!r}; it has {sorted(image_cams)}")
        self._topics = {"main": _image_topic(image_cams[camera])}
        if "depth" in image_cams and camera != "depth":
            self._topics["depth"] = _image_topic(image_cams["depth"])
        if "right" in image_cams and camera != "right":
            self._topics["right"] = _image_topic(image_cams["right"])
        calib = self.reader.calibration()
        measured = calibration or (self.reader.measured_calibration() if use_calibration else None)
        from_record = measured.T_body_camera if measured is not None else None
        self.T_body_camera = T_body_camera or from_record or calib.T_body_camera or Transform()
        self._index(path, cams, camera)
        self._gt: Trajectory | None = None
        mocap = self.reader.mocap_topics(vehicle)
        body = mocap_body or (calib.mocap_body if calib.mocap_body in mocap else None)
        if body is None and mocap:
            body = sorted(mocap)[0]
        if body is not None and body not in mocap:
            raise DatasetError(f"recording {path} has no mocap body {body!r}; it has {sorted(mocap) or 'none'}")
        self.mocap_body = body
        if body is not None:
            frames = self.reader.world_frames(T_world_mocap)
            body_traj = self.reader.pose_trajectory(mocap[body], frames, name=f"mocap {body}")
            if measured is not None and measured.time_offset_ms is not None:  # onto the camera's clock
                body_traj = Trajectory(measured.mocap_to_camera_ns(body_traj.stamps_ns), body_traj.positions,
                                       body_traj.quats_wxyz, body_traj.name)
            self._gt = body_traj.right_multiplied(self.T_body_camera).renamed("groundtruth")

    # ------------------------------------------------------------------ indexing
    def _index(self, path: Path, cams: dict[str, dict[str, str]], camera: str) -> None:
        info_topics = {n: t["camera_info"] for n, t in cams.items() if "camera_info" in t}
        stamps: dict[str, list[int]] = {k: [] for k in self._topics}
        role_of = {t: k for k, t in self._topics.items()}
        for m in self.reader.messages(sorted(self._topics.values())):
            stamps[role_of[m.topic]].append(header_stamp_ns(m.data))
        infos: dict[str, CameraInfo] = {}
        for name, topic in info_topics.items():
            info = self.reader.first_camera_info(topic)
            if info is not None:
                infos[name] = info
        self._stamps = {k: np.array(v, dtype=np.int64) for k, v in stamps.items()}
        main = self._stamps["main"]
        if main.size == 0:
            raise DatasetError(f"recording {path} holds no images on {self._topics['main']}")
        self._links: dict[str, dict[int, int]] = {}
        for role in ("depth", "right"):
            if role in self._stamps:
                ia, ib = associate(main, self._stamps[role], self._max_diff_ns)
                self._links[role] = {int(b): int(a) for a, b in zip(ia, ib, strict=True)}
        if camera not in infos:
            raise DatasetError(
                f"recording {path} lacks camera {camera}'s camera_info (…/camera/{camera}/camera_info); "
                "intrinsics are needed to use the images"
            )
        readout = self.reader.camera_readout_s
        self.intrinsics = _intrinsics(infos[camera], readout(info_topics[camera]))
        self.depth_intrinsics = (
            _intrinsics(infos["depth"], readout(info_topics["depth"]))
            if "depth" in self._topics and "depth" in infos
            else (self.intrinsics if "depth" in self._topics else None)
        )
        self.baseline_m: float | None = None
        if "right" in self._topics and "right" in infos:
            p = infos["right"].p
            self.baseline_m = float(-p[3] / p[0]) if p[0] else None
        logger.debug("indexed %s: %d frames, topics %s", path, main.size, self._topics)

    # ------------------------------------------------------------------ protocol
    def __len__(self) -> int:
        return int(self._stamps["main"].size)

    def __repr__(self) -> str:
        return f"McapSequence(name={self.name!r}, frames={len(self)}, topics={self._topics})"

    def stamps_ns(self) -> npt.NDArray[np.int64]:
        return self._stamps["main"].copy()

    def has_groundtruth(self) -> bool:
        return self._gt is not None

    def groundtruth(self) -> Trajectory:
        if self._gt is None:
            raise DatasetError(
                f"recording {self.path} has no mocap poses (…/mocap/<body>/pose), so no ground truth"
            )
        return self._gt

    def frames(self, start: int = 0, stop: int | None = None, step: int = 1) -> Iterator[Frame]:
        order = list(range(len(self))[start:stop:step])
        if not order:
            return
        wanted = set(order)
        pending: dict[int, dict[str, object]] = {}
        counters = dict.fromkeys(self._topics, 0)
        role_of = {t: k for k, t in self._topics.items()}
        gt_poses = (
            poses_at(self._gt, self._stamps["main"], self._max_diff_ns) if self._gt is not None else None
        )
        pos = 0
        for m in self.reader.messages(sorted(self._topics.values())):
            role = role_of[m.topic]
            k = counters[role]
            counters[role] += 1
            idx = k if role == "main" else self._links.get(role, {}).get(k)
            if idx is None or idx not in wanted or idx < order[pos]:
                continue
            pending.setdefault(idx, {})[role] = decode_image(m.topic, m.data).bgr()
            while pos < len(order) and order[pos] in pending and self._complete(order[pos], pending[order[pos]]):
                i = order[pos]
                yield self._frame(i, pending.pop(i), gt_poses)
                pos += 1
            if pos == len(order):
                return
        for i in order[pos:]:  # frames whose partner images never arrived
            if i in pending and "main" in pending[i]:
                yield self._frame(i, pending.pop(i), gt_poses)

    def _complete(self, idx: int, parts: dict[str, object]) -> bool:
        if "main" not in parts:
            return False
        for role, links in self._links.items():
            if idx in links.values() and role not in parts:
                return False
        return True

    def _frame(self, idx: int, parts: dict[str, object], gt_poses: list[Transform | None] | None) -> Frame:
        main = parts["main"]
        assert isinstance(main, np.ndarray)
        color = None
        if main.ndim == 3:
            color = main
            gray = cv2.cvtColor(main, cv2.COLOR_BGR2GRAY)
        else:
            gray = main
        depth = parts.get("depth")
        right = parts.get("right")
        if isinstance(right, np.ndarray) and right.ndim == 3:
            right = cv2.cvtColor(right, cv2.COLOR_BGR2GRAY)
        scale = 1.0
        if isinstance(depth, np.ndarray) and depth.dtype == np.uint16:
            scale = 1e-3
        return Frame(
            index=idx,
            stamp_ns=int(self._stamps["main"][idx]),
            gray=np.asarray(gray, dtype=np.uint8),
            color_bgr=color,
            right_gray=right if isinstance(right, np.ndarray) else None,
            depth_raw=depth if isinstance(depth, np.ndarray) else None,
            depth_scale_m=scale,
            T_world_camera=gt_poses[idx] if gt_poses is not None else None,
        )


def _image_topic(topics: dict[str, str]) -> str:
    return topics.get("image") or topics["image/compressed"]


def _intrinsics(info: CameraInfo, readout_s: float) -> CameraIntrinsics:
    k = info.k
    return CameraIntrinsics(k[0], k[4], k[2], k[5], info.width, info.height, tuple(info.d), readout_s)


def open_mcap(path: Path, **options: object) -> McapSequence:
    """Open an MCAP recording (options: ``camera``, ``mocap_body``, ``T_world_mocap``,
    ``T_body_camera``, ``max_diff_s``, ``use_calibration``, ``calibration``)."""
    return McapSequence(path, **options)  # type: ignore[arg-type]
