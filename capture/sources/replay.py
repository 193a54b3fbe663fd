"""Replay a recording or a dataset folder on the bus, at recorded speed or faster.

Two sources, both paced on the injected clock (``speed`` times the recorded rate on top of
it; ``speed=inf`` publishes as fast as the bus takes it):

* :class:`McapReplayPublisher` -- an MCAP recording: every message is republished **as
  recorded** (the raw CDR payload, never decoded) with its channel's ROS 2 type on its
  original key (the topic without the leading ``/``, optionally under ``key_prefix``),
  with its header stamp as the capture stamp (the recorded ``publish_time`` for a message
  without one, e.g. tf), its recorded ``publish_time`` as the bus time and its channel's
  ``capture_stamp`` source, in ``log_time`` order. A recorder on the other side writes byte-identical payloads.
  Each camera's ``calibration.<camera>`` record is served on its calibration key
  (:mod:`flightkit.bus.camera_calibration`), so its rolling-shutter readout is recorded again.
* :class:`DatasetReplayPublisher` -- a dataset folder (TUM RGB-D, EuRoC, KITTI, 7-Scenes, a
  video; anything :func:`flightkit.datasets.open_sequence` reads): images are decoded and
  published like a camera driver would (``color`` bgr8, or ``left``/``right`` mono8 for
  stereo, ``gray`` for mono; ``depth`` 16UC1 mm; camera_info from the dataset's
  calibration, its rolling-shutter readout served beside it), and the ground truth as ``geometry_msgs/PoseStamped`` on
  ``<ns>/mocap/<gt_body>/pose`` (frame ``mocap``: the dataset's world frame), each at its
  own dataset stamp. A TUM folder exported by flightkit (with ``camera.yaml``) is read with
  its own calibration, so export -> replay -> record -> export round-trips.

Replay publishers are reliable and block rather than drop (offline data has no deadline):
a slow recorder slows the replay down instead of losing frames.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import zenoh

from capture.sources._runner import SourceThread
from capture.sources.realsense import depth_to_mm
from flightkit.bus.camera_calibration import CalibrationServer, calibration_key
from flightkit.bus.image_msgs import CameraInfo, CompressedImage, Image
from flightkit.bus.keys import Keys
from flightkit.bus.pose_msgs import Odometry, PoseStamped, TransformStamped
from flightkit.bus.pubsub import BusPublisher
from flightkit.bus.streams import CameraModel, CameraStream, PosePublisher, has_subscribers, optical_frame_id
from flightkit.clock import STAMP_DEVICE, STAMP_HOST, Clock
from flightkit.datasets.mcap_reader import RecordingReader, header_stamp_ns
from flightkit.errors import BusError, CaptureError, DatasetError

__all__ = ["DatasetReplayPublisher", "McapReplayPublisher", "open_replay"]

logger = logging.getLogger(__name__)

_HEADER_FIRST = frozenset(  # message types that start with a std_msgs/Header (their capture stamp)
    m.TYPE for m in (CameraInfo, CompressedImage, Image, Odometry, PoseStamped, TransformStamped)
)


def _check_speed(speed: float) -> float:
    if not speed > 0:
        raise CaptureError(f"replay speed {speed} must be positive (1 = as recorded, 10 = ten times faster)")
    return float(speed)


class _Pacer:
    """Maps recorded stamps to clock deadlines: ``t0 + (stamp - first) / speed``."""

    def __init__(self, owner: SourceThread, speed: float) -> None:
        self._owner = owner
        self._speed = speed
        self._first: int | None = None
        self._t0 = 0.0

    def wait(self, stamp_ns: int) -> bool:
        if self._first is None:
            self._first = stamp_ns
            self._t0 = self._owner.clock.monotonic_s()
            return not self._owner.stopping
        if math.isinf(self._speed):
            return not self._owner.stopping
        return self._owner._sleep_until(self._t0 + (stamp_ns - self._first) * 1e-9 / self._speed)  # noqa: SLF001


# --------------------------------------------------------------------------- MCAP


class McapReplayPublisher(SourceThread):
    """Republish an MCAP recording's raw payloads on their original keys.

    Args:
        session: an open Zenoh session.
        path: the ``.mcap`` file (complete; recover a crashed one first).
        clock: paces the replay.
        speed: recorded seconds per clock second (``inf``: no pacing).
        topics: only these topics (as recorded, with or without the leading ``/``).
        key_prefix: publish under ``<prefix>/<topic>`` (e.g. ``replay``) to keep clear of live streams.

    Raises:
        CaptureError: the file is unreadable or has no CDR channels.
    """

    thread_name = "mcap-replay"
    what = "messages"

    def __init__(
        self,
        session: zenoh.Session,
        path: str | os.PathLike[str],
        clock: Clock,
        *,
        speed: float = 1.0,
        topics: Sequence[str] | None = None,
        key_prefix: str = "",
    ) -> None:
        super().__init__(clock)
        self.path = Path(path)
        self.speed = _check_speed(speed)
        self.thread_name = f"mcap-replay {self.path.name}"
        try:
            self.reader = RecordingReader(self.path)
        except DatasetError as exc:
            raise CaptureError(str(exc)) from exc
        wanted = {t.lstrip("/") for t in topics} if topics else None
        prefix = key_prefix.strip("/")
        self.key_of: dict[str, str] = {}
        self.skipped: list[str] = []
        self._pubs: dict[str, BusPublisher] = {}
        self._header_stamped: set[str] = set()  # topics whose messages start with a std_msgs/Header
        for st in self.reader.streams:
            topic = st.topic.lstrip("/")
            if wanted is not None and topic not in wanted:
                continue
            if st.encoding != "cdr" or not st.schema_name:
                self.skipped.append(st.topic)
                logger.warning("not replaying %s: %s payloads are not ROS 2 CDR", st.topic, st.encoding)
                continue
            key = f"{prefix}/{topic}" if prefix else topic
            try:
                self._pubs[st.topic] = BusPublisher(
                    session, key, st.schema_name, reliable=True, drop_when_congested=False,
                    stamp_source=STAMP_DEVICE if st.capture_stamp == STAMP_DEVICE else STAMP_HOST,
                )
                if st.schema_name in _HEADER_FIRST:
                    self._header_stamped.add(st.topic)
            except BusError as exc:
                self.skipped.append(st.topic)
                logger.warning("not replaying %s: %s", st.topic, exc)
                continue
            self.key_of[st.topic] = key
        self._calibrations = self._serve_calibrations(session)
        if not self._pubs:
            raise CaptureError(
                f"{self.path} has no CDR channel to replay"
                + (f" among topics {sorted(wanted)}" if wanted else "")
                + "; check the recording with 'flightkit capture info'"
            )
        self.total = sum(st.count for st in self.reader.streams if st.topic in self._pubs)

    def _serve_calibrations(self, session: zenoh.Session) -> list[CalibrationServer]:
        """A server per replayed camera recorded with a readout > 0 (its ``calibration.<camera>`` record)."""
        servers: list[CalibrationServer] = []
        for topic, key in self.key_of.items():
            if not topic.endswith("/camera_info"):
                continue
            try:
                readout_s = self.reader.camera_readout_s(topic)
            except DatasetError as exc:
                logger.warning("replaying %s without its readout: %s", topic, exc)
                continue
            if readout_s > 0:
                servers.append(CalibrationServer(session, calibration_key(key), {"readout_s": repr(readout_s)}))
        return servers

    @property
    def keys(self) -> list[str]:
        return sorted(self.key_of.values())

    @property
    def has_subscribers(self) -> bool:
        """Whether every replayed key has a subscriber right now."""
        return all(has_subscribers(p) for p in self._pubs.values())

    def _run_loop(self) -> None:
        pacer = _Pacer(self, self.speed)
        pubs = self._pubs
        logger.info("replaying %s (%d messages) at %gx", self.path, self.total, self.speed)
        for m in self.reader.messages(sorted(pubs)):
            if not pacer.wait(m.log_time_ns):
                return
            stamp = header_stamp_ns(m.data) if m.topic in self._header_stamped else m.publish_time_ns
            pubs[m.topic].put(m.data, stamp, m.publish_time_ns)  # the recorded bus time
            self._count()
        logger.info("replay of %s finished: %d messages", self.path, self.published)

    def _close_outputs(self) -> None:
        for pub in self._pubs.values():
            pub.close()
        for server in self._calibrations:
            server.close()


# --------------------------------------------------------------------------- datasets


def _model(intr: Any, baseline_tx: float = 0.0) -> CameraModel:
    return CameraModel(
        intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy, tuple(intr.dist), baseline_tx, intr.readout_s
    )


def _open_dataset(path: Path, options: dict[str, Any]) -> Any:
    from flightkit.datasets import open_sequence

    try:
        return open_sequence(path, **options)
    except DatasetError as exc:
        raise CaptureError(str(exc)) from exc


class DatasetReplayPublisher(SourceThread):
    """Publish a dataset folder (or video) as camera streams plus ground truth.

    Args:
        session: an open Zenoh session.
        keys: the namespace to publish under.
        path: the dataset folder or file (anything :func:`~flightkit.datasets.open_sequence` opens).
        clock: paces the replay.
        speed: dataset seconds per clock second (``inf``: no pacing).
        gt_body: the body name of the ground truth on ``<ns>/mocap/<gt_body>/pose``.
        groundtruth: publish the ground truth (when the dataset has one).
        options: passed to ``open_sequence`` (e.g. ``rectify=False`` for EuRoC).

    Raises:
        CaptureError: the dataset cannot be opened or is empty.
    """

    thread_name = "dataset-replay"
    what = "frames"

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        path: str | os.PathLike[str],
        clock: Clock,
        *,
        speed: float = 1.0,
        gt_body: str = "groundtruth",
        groundtruth: bool = True,
        **options: Any,
    ) -> None:
        super().__init__(clock)
        self.path = Path(path)
        self.speed = _check_speed(speed)
        self.seq = _open_dataset(self.path, dict(options))
        self.thread_name = f"dataset-replay {self.seq.name}"
        if len(self.seq) == 0:
            raise CaptureError(f"dataset {self.path} has no frames to replay")
        first = next(iter(self.seq.frames(0, 1)))
        intr = self.seq.intrinsics
        stereo = first.right_gray is not None and self.seq.baseline_m is not None
        self.main_name = "color" if first.color_bgr is not None else ("left" if stereo else "gray")
        self.main_encoding = "bgr8" if first.color_bgr is not None else "mono8"
        main_model = _model(intr)
        self.main = CameraStream(session, keys, self.main_name, main_model, self.main_encoding)
        self.right: CameraStream | None = None
        if stereo:
            right_model = _model(intr, -intr.fx * float(self.seq.baseline_m))
            self.right = CameraStream(session, keys, "right", right_model, "mono8")
        self.depth: CameraStream | None = None
        if first.depth_raw is not None and self.seq.depth_intrinsics is not None:
            aligned = self.seq.depth_intrinsics == intr
            self.depth = CameraStream(
                session,
                keys,
                "depth",
                _model(self.seq.depth_intrinsics),
                "16UC1",
                frame_id=optical_frame_id(keys, self.main_name) if aligned else None,
            )
        for stream in (self.main, self.right, self.depth):
            if stream is not None:
                _make_reliable(session, stream)
        self.gt = self.seq.groundtruth() if groundtruth and self.seq.has_groundtruth() else None
        self.pose: PosePublisher | None = (
            PosePublisher(session, keys, gt_body) if self.gt is not None else None
        )
        self.poses_published = 0
        self._depth_mm: npt.NDArray[np.uint16] | None = None

    @property
    def keys(self) -> list[str]:
        out = [
            k for s in (self.main, self.right, self.depth) if s is not None for k in (s.image_key, s.info_key)
        ]
        if self.pose is not None:
            out.append(self.pose.key)
        return out

    @property
    def has_subscribers(self) -> bool:
        """Whether every published stream has a subscriber right now."""
        ok = all(s.has_subscribers for s in (self.main, self.right, self.depth) if s is not None)
        return ok and (self.pose is None or self.pose.has_subscribers)

    def _events(self) -> Iterator[tuple[int, int, Any]]:
        """(stamp, kind, item) in stamp order: kind 0 = ground-truth pose index, 1 = frame."""
        gt_stamps = self.gt.stamps_ns if self.gt is not None else np.zeros(0, np.int64)
        g = 0
        for frame in self.seq.frames():
            while g < gt_stamps.size and gt_stamps[g] <= frame.stamp_ns:
                yield int(gt_stamps[g]), 0, g
                g += 1
            yield frame.stamp_ns, 1, frame
        while g < gt_stamps.size:
            yield int(gt_stamps[g]), 0, g
            g += 1

    def _publish_frame(self, frame: Any) -> None:
        stamp = frame.stamp_ns
        self.main.publish(stamp, frame.color_bgr if self.main_encoding == "bgr8" else frame.gray)
        if self.right is not None and frame.right_gray is not None:
            self.right.publish(stamp, frame.right_gray)
        if self.depth is not None and frame.depth_raw is not None:
            self._depth_mm = depth_to_mm(frame.depth_raw, frame.depth_scale_m, self._depth_mm)
            self.depth.publish(stamp, self._depth_mm)

    def _run_loop(self) -> None:
        pacer = _Pacer(self, self.speed)
        logger.info(
            "replaying %s (%s, %d frames%s) at %gx",
            self.path,
            self.seq.kind,
            len(self.seq),
            f", {len(self.gt)} ground-truth poses" if self.gt is not None else "",
            self.speed,
        )
        for stamp, kind, item in self._events():
            if not pacer.wait(stamp):
                return
            if kind == 0:
                assert self.gt is not None and self.pose is not None
                self.pose.publish(stamp, self.gt.transform(item))
                self.poses_published += 1
            else:
                self._publish_frame(item)
                self._count()
        logger.info("replay of %s finished: %d frames", self.path, self.published)

    def _close_outputs(self) -> None:
        for s in (self.main, self.right, self.depth, self.pose):
            if s is not None:
                s.close()


def _make_reliable(session: zenoh.Session, stream: CameraStream) -> None:
    """Swap a camera stream's best-effort image publisher for a reliable, blocking one (replay
    must not drop frames; it has no deadline to keep)."""
    stream._image.close()  # noqa: SLF001
    stream._image = BusPublisher(  # noqa: SLF001
        session, stream.image_key, Image, reliable=True, drop_when_congested=False
    )


def open_replay(
    session: zenoh.Session,
    keys: Keys,
    path: str | os.PathLike[str],
    clock: Clock,
    *,
    speed: float = 1.0,
    key_prefix: str = "",
    gt_body: str = "groundtruth",
) -> McapReplayPublisher | DatasetReplayPublisher:
    """An MCAP file -> :class:`McapReplayPublisher` (under ``key_prefix``); anything else ->
    :class:`DatasetReplayPublisher` (ground truth as ``gt_body``)."""
    p = Path(path)
    if p.is_file() and p.suffix.lower() == ".mcap":
        return McapReplayPublisher(session, p, clock, speed=speed, key_prefix=key_prefix)
    return DatasetReplayPublisher(session, keys, p, clock, speed=speed, gt_body=gt_body)
