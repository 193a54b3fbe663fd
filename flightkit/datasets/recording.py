"""MCAP recordings (ROS 2 CDR) as sequences: camera images, depth, camera_info and mocap.

What is read (topic names as the flightkit recorder writes them, ``/<ns>/...``)::

    /<ns>/camera/<name>/image              sensor_msgs/msg/Image (mono8, bgr8, rgb8, 16UC1, 32FC1)
    /<ns>/camera/<name>/image/compressed   sensor_msgs/msg/CompressedImage (jpeg/png)
    /<ns>/camera/<name>/camera_info        sensor_msgs/msg/CameraInfo (K, D, size)
    /<ns>/mocap/<body>/pose                geometry_msgs/msg/PoseStamped

The main camera is ``camera`` (default: the first of color, left, gray, infra1, image,
else any non-depth camera); depth is the camera named ``depth`` (16UC1 in millimetres or
32FC1 in metres) and the stereo partner ``right``. Frames are the main camera's messages,
stamped with their header stamps; depth and right images are attached when their stamp
lies within ``max_diff_s`` (20 ms).

Ground truth: the mocap body poses (``T_mocap_body``); ``groundtruth()`` gives
``T_world_camera = T_world_mocap @ T_mocap_body @ T_body_camera`` with both transforms given
by the caller (identity by default, i.e. the body trajectory in the mocap frame).
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from flightkit.bus.cdr import CdrReader
from flightkit.bus.msgs import CameraInfo, CompressedImage, Header, Image, PoseStamped
from flightkit.datasets.base import CameraIntrinsics, Frame, SequenceKind, StereoRectification
from flightkit.datasets.files import poses_at
from flightkit.datasets.trajectory import Trajectory, associate
from flightkit.errors import DatasetError
from flightkit.frames import Transform, quat_xyzw_to_wxyz

__all__ = ["McapSequence", "open_mcap"]

logger = logging.getLogger(__name__)

_CAMERA = re.compile(r"camera/([^/]+)/(image|image/compressed|camera_info)$")
_MOCAP = re.compile(r"mocap/([^/]+)/pose$")
_MAIN_PREFERENCE = ("color", "left", "gray", "infra1", "image")


def _reader(fh):  # type: ignore[no-untyped-def]
    from mcap.reader import make_reader

    return make_reader(fh)


class McapSequence:
    """:class:`~flightkit.datasets.base.Sequence` over an MCAP recording (see the module docstring)."""

    def __init__(
        self,
        path: Path,
        camera: str | None = None,
        mocap_body: str | None = None,
        T_world_mocap: Transform | None = None,  # noqa: N803
        T_body_camera: Transform | None = None,  # noqa: N803
        max_diff_s: float = 0.02,
    ) -> None:
        self.path = path
        self.name = path.stem
        self.kind = SequenceKind.MCAP
        self.rectification: StereoRectification | None = None
        self._max_diff_ns = round(max_diff_s * 1e9)
        try:
            with path.open("rb") as fh:
                summary = _reader(fh).get_summary()
        except Exception as exc:  # mcap raises several exception types for damaged files
            raise DatasetError(
                f"recording {path} cannot be read as MCAP ({exc}); if it was cut short, run "
                "`flightkit capture recover` first"
            ) from exc
        if summary is None:
            raise DatasetError(f"recording {path} has no summary section; recover it first")
        cams: dict[str, dict[str, str]] = {}
        mocap: dict[str, str] = {}
        for ch in summary.channels.values():
            topic = ch.topic.lstrip("/")
            if m := _CAMERA.search(topic):
                cams.setdefault(m.group(1), {})[m.group(2)] = ch.topic
            elif m := _MOCAP.search(topic):
                mocap[m.group(1)] = ch.topic
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
        self._index(path, cams, camera, mocap, mocap_body)
        T_wm = T_world_mocap or Transform()  # noqa: N806
        T_bc = T_body_camera or Transform()  # noqa: N806
        self._gt: Trajectory | None = None
        if self._mocap_traj is not None:
            self._gt = self._mocap_traj.left_multiplied(T_wm).right_multiplied(T_bc).renamed("groundtruth")

    # ------------------------------------------------------------------ indexing
    def _index(
        self,
        path: Path,
        cams: dict[str, dict[str, str]],
        camera: str,
        mocap: dict[str, str],
        body: str | None,
    ) -> None:
        info_topics = {n: t["camera_info"] for n, t in cams.items() if "camera_info" in t}
        if body is None and mocap:
            body = sorted(mocap)[0]
        if body is not None and body not in mocap:
            raise DatasetError(
                f"recording {path} has no mocap body {body!r}; it has {sorted(mocap) or 'none'}"
            )
        mocap_topic = mocap.get(body) if body else None
        wanted = (
            set(self._topics.values()) | set(info_topics.values()) | ({mocap_topic} if mocap_topic else set())
        )
        stamps: dict[str, list[int]] = {k: [] for k in self._topics}
        infos: dict[str, CameraInfo] = {}
        poses: list[PoseStamped] = []
        role_of = {t: k for k, t in self._topics.items()}
        info_role = {t: n for n, t in info_topics.items()}
        with path.open("rb") as fh:
            for _schema, channel, message in _reader(fh).iter_messages(
                topics=sorted(wanted), log_time_order=True
            ):
                topic = channel.topic
                if topic in role_of:
                    stamps[role_of[topic]].append(_stamp_of(channel.topic, message.data))
                elif topic in info_role and info_role[topic] not in infos:
                    infos[info_role[topic]] = CameraInfo.decode(message.data)
                elif topic == mocap_topic:
                    poses.append(PoseStamped.decode(message.data))
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
        self.intrinsics = _intrinsics(infos[camera])
        self.depth_intrinsics = (
            _intrinsics(infos["depth"])
            if "depth" in self._topics and "depth" in infos
            else (self.intrinsics if "depth" in self._topics else None)
        )
        self.baseline_m: float | None = None
        if "right" in self._topics and "right" in infos:
            p = infos["right"].p
            self.baseline_m = float(-p[3] / p[0]) if p[0] else None
        self._mocap_traj = None
        if poses:
            poses.sort(key=lambda m: m.header.stamp_ns)
            self._mocap_traj = Trajectory(
                np.array([m.header.stamp_ns for m in poses], dtype=np.int64),
                np.array([m.position_m for m in poses]),
                quat_xyzw_to_wxyz(np.array([m.quat_xyzw for m in poses])),
                f"mocap {body}",
            )
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
        with self.path.open("rb") as fh:
            for _schema, channel, message in _reader(fh).iter_messages(
                topics=sorted(self._topics.values()), log_time_order=True
            ):
                role = role_of[channel.topic]
                k = counters[role]
                counters[role] += 1
                idx = k if role == "main" else self._links.get(role, {}).get(k)
                if idx is None or idx not in wanted or idx < order[pos]:
                    continue
                pending.setdefault(idx, {})[role] = _decode_image(channel.topic, message.data)
                while (
                    pos < len(order)
                    and order[pos] in pending
                    and self._complete(order[pos], pending[order[pos]])
                ):
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


def _stamp_of(topic: str, data: bytes) -> int:
    """The header stamp of any stamped message, without decoding the rest."""
    return Header.read(CdrReader(data)).stamp_ns


def _decode_image(topic: str, data: bytes) -> npt.NDArray[np.generic]:
    if topic.endswith("/compressed"):
        payload = CompressedImage.decode(data).data
        img = cv2.imdecode(np.frombuffer(payload, np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise DatasetError(f"a compressed image on {topic} cannot be decoded")
        return np.asarray(img)
    msg = Image.decode(data)
    arr = msg.array()
    if msg.encoding in ("rgb8",):
        arr = cv2.cvtColor(arr, cv2.COLOR_RGB2BGR)
    elif msg.encoding in ("bgra8",):
        arr = cv2.cvtColor(arr, cv2.COLOR_BGRA2BGR)
    elif msg.encoding in ("rgba8",):
        arr = cv2.cvtColor(arr, cv2.COLOR_RGBA2BGR)
    return np.asarray(arr)


def _intrinsics(info: CameraInfo) -> CameraIntrinsics:
    k = info.k
    return CameraIntrinsics(k[0], k[4], k[2], k[5], info.width, info.height, tuple(info.d))


def open_mcap(path: Path, **options: object) -> McapSequence:
    """Open an MCAP recording (options: ``camera``, ``mocap_body``, ``T_world_mocap``,
    ``T_body_camera``, ``max_diff_s``)."""
    return McapSequence(path, **options)  # type: ignore[arg-type]
