"""The one reader of MCAP recordings: every part of flightkit that reads a recording goes through it.

:class:`RecordingReader` opens a recording once (summary, header, metadata) and knows what its
topics are for, by the names the recorder writes (``/<ns>/...``)::

    /<ns>/camera/<name>/image              sensor_msgs/msg/Image
    /<ns>/camera/<name>/image/compressed   sensor_msgs/msg/CompressedImage (jpeg/png)
    /<ns>/camera/<name>/camera_info        sensor_msgs/msg/CameraInfo
    /<ns>/mocap/<body>/pose                geometry_msgs/msg/PoseStamped (frame_id "mocap")
    /<ns>/odometry/<method>                geometry_msgs/msg/PoseStamped (frame_id "world")
    /<ns>/tf                               tf2_msgs/msg/TFMessage

Frames are honoured here, once: :meth:`RecordingReader.world_frames` places the recording's
frames in the world from its ``extrinsics`` metadata (``T_world_mocap``, written by the
recorder from the lab config), and :meth:`RecordingReader.pose_trajectory` returns any pose
topic in the world frame, refusing a pose whose ``frame_id`` it cannot place.

Times: a message's header stamp is its capture time (the channel's :data:`CAPTURE_STAMP_KEY`
metadata says whether the device gave it), MCAP ``publish_time`` when it was put on the bus,
``log_time`` when the recorder received it.
:func:`decode_image` is the one image decoder.
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
from mcap.reader import McapReader, make_reader
from mcap.summary import Summary

from flightkit.bus.cdr import CdrReader
from flightkit.bus.image_msgs import CameraInfo, CompressedImage, Image
from flightkit.bus.msg_base import Header
from flightkit.bus.pose_msgs import PoseStamped, TFMessage
from flightkit.bus.streams import check_readout_s
from flightkit.calibration.clock_sync import CLOCK_OFFSETS_RECORD, ClockOffsetEstimate, offsets_from_metadata
from flightkit.calibration.result import METADATA_RECORD, CalibrationResult
from flightkit.datasets.trajectory import Trajectory
from flightkit.errors import BusError, CalibrationError, DatasetError
from flightkit.frames import Transform, WorldFrames, quat_xyzw_to_wxyz

__all__ = [
    "CAPTURE_STAMP_KEY",
    "DecodedImage",
    "RawMessage",
    "RecordingCalibration",
    "RecordingReader",
    "StreamInfo",
    "decode_image",
    "namespace_of",
    "transform_from_json",
    "transform_to_json",
]

logger = logging.getLogger(__name__)

CAPTURE_STAMP_KEY = "flightkit.capture_stamp"
"""Channel metadata: ``device`` (header stamps are the device's capture times), ``host`` (the
host's time at hand-over: the device gives none) or ``unknown``."""

_CAMERA = re.compile(r"camera/([^/]+)/(image|image/compressed|camera_info)$")
_MOCAP = re.compile(r"mocap/([^/]+)/pose$")
_TF = re.compile(r"(^|/)tf$")


def namespace_of(topic: str) -> str:
    """The vehicle namespace a topic belongs to (its first path element; "" for a bare name)."""
    parts = topic.strip("/").split("/")
    return parts[0] if len(parts) > 1 else ""


def transform_to_json(T: Transform) -> str:  # noqa: N803
    """A transform as JSON text for metadata: ``{"translation_m": [...], "quat_xyzw": [...]}``."""
    return json.dumps(
        {"translation_m": [float(v) for v in T.translation], "quat_xyzw": [float(v) for v in T.quat_xyzw]}
    )


def transform_from_json(text: str, what: str = "transform") -> Transform:
    """The inverse of :func:`transform_to_json`.

    Raises:
        DatasetError: malformed text (the message names ``what``).
    """
    try:
        data = json.loads(text)
        return Transform.from_quat_xyzw(data["translation_m"], data["quat_xyzw"])
    except (ValueError, KeyError, TypeError) as exc:
        raise DatasetError(
            f"the recording's {what} metadata is malformed ({exc}); re-record or give it explicitly"
        ) from exc


@dataclass(frozen=True, slots=True)
class StreamInfo:
    """One channel of a recording.

    Attributes:
        channel_id: the MCAP channel id.
        topic: the topic as recorded (``/uav1/camera/color/image``).
        schema_name: the ROS 2 type (``sensor_msgs/msg/Image``), "" without a schema.
        encoding: the message encoding (``cdr``).
        count: messages, from the summary's statistics (0 when the file has none).
        capture_stamp: where its header stamps come from, from the channel's
            :data:`CAPTURE_STAMP_KEY` metadata: ``device``, ``host``, ``unknown`` ("" when not recorded).
    """

    channel_id: int
    topic: str
    schema_name: str
    encoding: str
    count: int
    capture_stamp: str = ""

    @property
    def namespace(self) -> str:
        return namespace_of(self.topic)


@dataclass(frozen=True, slots=True)
class RawMessage:
    """One message as stored: the payload is not decoded.

    Attributes:
        topic, schema_name: its channel's.
        log_time_ns: when the recorder received it. publish_time_ns: the publisher's stamp.
        sequence: the publisher's sequence number.
        data: the CDR payload.
    """

    topic: str
    schema_name: str
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    data: bytes


@dataclass(frozen=True, slots=True)
class RecordingCalibration:
    """The frames and extrinsics a recording carries.

    Attributes:
        T_world_mocap: the mocap frame in the world (``extrinsics`` metadata); None when the
            recording does not say (recorded by another tool).
        T_body_camera: the camera's extrinsics (``extrinsics`` metadata, else the first
            ``base_link -> *_optical`` on tf); None when absent.
        mocap_body: the body the lab config flew (metadata), "" when absent.
        calibration: further calibration records stored with the recording (name -> fields).
    """

    T_world_mocap: Transform | None = None
    T_body_camera: Transform | None = None
    mocap_body: str = ""
    calibration: dict[str, dict[str, str]] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class DecodedImage:
    """An image message's pixels.

    Attributes:
        array: (H, W) or (H, W, C) pixels as published (a view when possible).
        encoding: the ROS encoding (``rgb8``, ``16UC1``, ...; ``bgr8`` for decoded JPEG/PNG).
        stamp_ns: the header stamp (capture time).
    """

    array: npt.NDArray[Any]
    encoding: str
    stamp_ns: int

    def bgr(self) -> npt.NDArray[Any]:
        """Colour as BGR (OpenCV's order); grey and depth images unchanged."""
        conv = {"rgb8": cv2.COLOR_RGB2BGR, "rgba8": cv2.COLOR_RGBA2BGR, "bgra8": cv2.COLOR_BGRA2BGR}.get(self.encoding)
        return np.asarray(cv2.cvtColor(self.array, conv)) if conv is not None else self.array

    def gray(self) -> npt.NDArray[np.uint8]:
        """8-bit grey (colour converted; a 16-bit image scaled to its maximum)."""
        arr = self.array
        if arr.ndim == 2:
            if arr.dtype == np.uint8:
                return arr
            return np.asarray(cv2.convertScaleAbs(arr, alpha=255.0 / max(1, int(arr.max()))), dtype=np.uint8)
        return np.asarray(cv2.cvtColor(self.bgr(), cv2.COLOR_BGR2GRAY), dtype=np.uint8)


def decode_image(topic: str, data: bytes | memoryview) -> DecodedImage:
    """Decode an Image or CompressedImage payload (by the topic's ``/compressed`` suffix).

    Raises:
        DatasetError: the payload cannot be decoded (names the topic).
    """
    try:
        if topic.endswith("/compressed"):
            msg = CompressedImage.decode(data)
            img = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise DatasetError(f"a compressed image on {topic} cannot be decoded; the file may be damaged")
            return DecodedImage(np.asarray(img), "bgr8" if img.ndim == 3 else "mono8", msg.header.stamp_ns)
        im = Image.decode(data)
        return DecodedImage(im.array(), im.encoding, im.header.stamp_ns)
    except BusError as exc:
        raise DatasetError(f"an image on {topic} cannot be decoded ({exc}); the file may be damaged") from exc


def header_stamp_ns(data: bytes | memoryview) -> int:
    """The header stamp of any stamped message, without decoding the rest."""
    return Header.read(CdrReader(data)).stamp_ns


class RecordingReader:
    """An MCAP recording opened for reading (see the module docstring).

    Args:
        path: the ``.mcap`` file.

    Raises:
        DatasetError: missing file, not MCAP, or no summary (a crashed recording: the message
            says to run ``flightkit capture recover``).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            with self.path.open("rb") as fh:
                reader = make_reader(fh)
                header = reader.get_header()
                summary = reader.get_summary()
                records = list(reader.iter_metadata())
                self.metadata: dict[str, dict[str, str]] = {m.name: dict(m.metadata) for m in records}
                # Each camera's calibration record by its camera_info topic: a fleet's recording holds
                # one ``calibration.color`` per vehicle, which ``metadata`` (by name) keeps one of.
                self._camera_records = {
                    m.metadata["topic"].strip("/"): (m.name, dict(m.metadata))
                    for m in records
                    if m.name.startswith("calibration.") and "topic" in m.metadata
                }
        except FileNotFoundError as exc:
            raise DatasetError(f"recording {self.path} does not exist; check the path") from exc
        except OSError as exc:
            raise DatasetError(f"cannot open recording {self.path}: {exc.strerror}; check the path") from exc
        except Exception as exc:  # mcap raises several exception types for damaged files
            raise DatasetError(
                f"{self.path} is not a readable MCAP recording ({exc}); if it was cut short, run "
                f"'flightkit capture recover {self.path} -o FIXED.mcap' first"
            ) from exc
        if summary is None:
            raise DatasetError(
                f"recording {self.path} has no summary section; run "
                f"'flightkit capture recover {self.path} -o FIXED.mcap' first"
            )
        self.profile = header.profile
        self.library = header.library
        self._summary: Summary = summary
        counts = dict(summary.statistics.channel_message_counts) if summary.statistics is not None else {}
        self.streams: list[StreamInfo] = []
        for cid, ch in sorted(summary.channels.items()):
            schema = summary.schemas.get(ch.schema_id)
            self.streams.append(
                StreamInfo(cid, ch.topic, schema.name if schema is not None else "", ch.message_encoding,
                           int(counts.get(cid, 0)), ch.metadata.get(CAPTURE_STAMP_KEY, ""))
            )
        self._schema_of = {s.topic: s.schema_name for s in self.streams}

    # ------------------------------------------------------------------ topics

    @property
    def topics(self) -> list[str]:
        return [s.topic for s in self.streams]

    def stream(self, topic: str) -> StreamInfo:
        """The channel of ``topic``.

        Raises:
            DatasetError: no such topic (names the ones there are).
        """
        for s in self.streams:
            if s.topic == topic:
                return s
        raise DatasetError(f"recording {self.path} has no topic {topic!r}; it has {', '.join(self.topics) or 'none'}")

    def cameras(self, namespace: str | None = None) -> dict[str, dict[str, str]]:
        """Camera name -> {"image" | "image/compressed" | "camera_info": topic} (of one namespace)."""
        out: dict[str, dict[str, str]] = {}
        for s in self.streams:
            if namespace is not None and s.namespace != namespace:
                continue
            if m := _CAMERA.search(s.topic.lstrip("/")):
                out.setdefault(m.group(1), {})[m.group(2)] = s.topic
        return out

    def mocap_topics(self, namespace: str | None = None) -> dict[str, str]:
        """Mocap body -> its pose topic (of one namespace)."""
        out: dict[str, str] = {}
        for s in self.streams:
            if namespace is not None and s.namespace != namespace:
                continue
            if m := _MOCAP.search(s.topic.lstrip("/")):
                out[m.group(1)] = s.topic
        return out

    def tf_topics(self) -> list[str]:
        return [s.topic for s in self.streams if _TF.search(s.topic.lstrip("/"))]

    def pose_topics(self) -> list[str]:
        """Every ``geometry_msgs/msg/PoseStamped`` topic, sorted."""
        return sorted(s.topic for s in self.streams if s.schema_name.endswith("PoseStamped"))

    def namespaces(self) -> list[str]:
        """The vehicle namespaces the topics belong to, sorted."""
        return sorted({s.namespace for s in self.streams})

    def camera_namespaces(self) -> list[str]:
        """The vehicles (namespaces) that have a camera image stream, sorted."""
        return [ns for ns in self.namespaces() if any("image" in t for t in self.cameras(ns).values())]

    # ------------------------------------------------------------------ messages

    def messages(self, topics: Sequence[str] | None = None, *, log_time_order: bool = True) -> Iterator[RawMessage]:
        """Every message of ``topics`` (None: all), undecoded; each call reads the file anew.

        Raises:
            DatasetError: the file cannot be read to the end.
        """
        if topics is not None and not topics:
            return
        try:
            with self.path.open("rb") as fh:
                reader: McapReader = make_reader(fh)
                for schema, channel, message in reader.iter_messages(
                    topics=list(topics) if topics is not None else None, log_time_order=log_time_order
                ):
                    yield RawMessage(
                        channel.topic, schema.name if schema is not None else "", message.log_time,
                        message.publish_time, message.sequence, message.data,
                    )
        except DatasetError:
            raise
        except Exception as exc:
            raise DatasetError(f"reading {self.path} failed ({exc}); the file may be damaged") from exc

    def camera_readout_s(self, info_topic: str) -> float:
        """The rolling-shutter readout (s) recorded for the camera of ``info_topic``: ``readout_s``
        of its ``calibration.<camera>`` record (the one whose ``topic`` it is, in a fleet's recording);
        0 (a global shutter) when the record has none.

        Raises:
            DatasetError: the recorded value is not a number >= 0 (names the record and the fix).
        """
        topic = info_topic.strip("/")
        if topic in self._camera_records:
            name, record = self._camera_records[topic]
        else:
            name = f"calibration.{topic.split('/')[-2]}"
            record = self.metadata.get(name, {})
            if "topic" in record:
                return 0.0  # the record is another vehicle's camera of that name
        text = record.get("readout_s")
        if text is None:
            return 0.0
        try:
            return check_readout_s(text)
        except BusError:
            raise DatasetError(
                f"recording {self.path}: record {name} gives readout_s {text!r}, not a readout in seconds >= 0; "
                "correct the record (flightkit.datasets.mcap_metadata.with_metadata) or remove it"
            ) from None

    def first_camera_info(self, topic: str) -> CameraInfo | None:
        """The first camera_info message on ``topic`` (None when there is none)."""
        for m in self.messages([topic], log_time_order=False):
            return CameraInfo.decode(m.data)
        return None

    # ------------------------------------------------------------------ frames

    def calibration(self) -> RecordingCalibration:
        """The frames and extrinsics the recording carries (metadata first, then tf).

        Raises:
            DatasetError: a malformed metadata record.
        """
        ext = self.metadata.get("extrinsics", {})
        T_wm = transform_from_json(ext["T_world_mocap"], "T_world_mocap") if "T_world_mocap" in ext else None  # noqa: N806
        T_bc = transform_from_json(ext["T_body_camera"], "T_body_camera") if "T_body_camera" in ext else None  # noqa: N806
        if T_bc is None:
            T_bc = self._tf_extrinsics()  # noqa: N806
        extra = {k: v for k, v in self.metadata.items() if k.startswith("calibration")}
        return RecordingCalibration(T_wm, T_bc, ext.get("mocap_body", ""), extra)

    def clock_offsets(self) -> dict[str, ClockOffsetEstimate]:
        """The clock of every other host on the bus against the recorder's (which stamps
        ``log_time``), as the recorder's clock exchange estimated it: host -> estimate
        (``remote_to_local_ns`` puts a host's stamps on the recorder's time base). Empty when
        the recording has none.

        Raises:
            DatasetError: the record is malformed.
        """
        try:
            return offsets_from_metadata(self.metadata.get(CLOCK_OFFSETS_RECORD, {}))
        except CalibrationError as exc:
            raise DatasetError(f"{self.path}: {exc}") from exc

    def measured_calibration(self) -> CalibrationResult | None:
        """The ``flightkit calibrate`` result stored in the recording (record
        :data:`~flightkit.calibration.result.METADATA_RECORD`), None when it has none.

        Raises:
            DatasetError: the record is malformed.
        """
        record = self.metadata.get(METADATA_RECORD)
        if record is None:
            return None
        try:
            return CalibrationResult.from_metadata(record)
        except CalibrationError as exc:
            raise DatasetError(f"{self.path}: the {METADATA_RECORD} record is unusable ({exc})") from exc

    def _tf_extrinsics(self) -> Transform | None:
        for m in self.messages(self.tf_topics(), log_time_order=False):
            try:
                transforms = TFMessage.decode(m.data).transforms
            except BusError as exc:
                raise DatasetError(f"{self.path}: a tf message cannot be decoded ({exc})") from exc
            for ts in transforms:
                if ts.header.frame_id.endswith("base_link") and ts.child_frame_id.endswith("_optical"):
                    return ts.to_transform()
        return None

    def world_frames(self, T_world_mocap: Transform | None = None) -> WorldFrames:  # noqa: N803
        """Where the recording's frames sit in the world: ``T_world_mocap`` as given, else the
        recording's own, else the identity (with a warning: a foreign recording's mocap frame
        is taken as the world)."""
        if T_world_mocap is None:
            T_world_mocap = self.calibration().T_world_mocap  # noqa: N806
            if T_world_mocap is None:
                logger.warning(
                    "%s does not say where its mocap frame is (no T_world_mocap metadata); taking it as the world",
                    self.path,
                )
        return WorldFrames(T_world_mocap or Transform.identity())

    def pose_trajectory(self, topic: str, frames: WorldFrames | None = None, name: str = "") -> Trajectory:
        """The poses of a PoseStamped ``topic`` as a world-frame trajectory, by header stamp
        (lost bodies, NaN poses, are left out; repeated stamps keep the first).

        Args:
            topic: the pose topic.
            frames: where the poses' frames sit (default :meth:`world_frames`).
            name: the trajectory's name (default the topic).

        Raises:
            DatasetError: not a pose topic, or no pose in it.
            FrameError: a pose in a frame ``frames`` cannot place.
        """
        if not self._schema_of.get(topic, "").endswith("PoseStamped"):
            known = ", ".join(self.pose_topics()) or "none"
            raise DatasetError(f"{self.path}: {topic!r} is not a PoseStamped topic; pose topics: {known}")
        wf = frames or self.world_frames()
        stamps: list[int] = []
        poses: list[Transform] = []
        for m in self.messages([topic], log_time_order=False):
            msg = PoseStamped.decode(m.data)
            vals = np.asarray(msg.position_m + msg.quat_xyzw)
            if not np.all(np.isfinite(vals)) or float(np.linalg.norm(vals[3:])) < 0.5:
                continue  # the body was lost
            stamps.append(msg.header.stamp_ns or m.log_time_ns)
            poses.append(wf.to_world(msg.header.frame_id, msg.to_transform()))
        if not stamps:
            raise DatasetError(f"{self.path}: topic {topic!r} holds no valid pose")
        order = np.argsort(np.asarray(stamps, dtype=np.int64), kind="stable")
        st = np.asarray(stamps, dtype=np.int64)[order]
        keep = np.concatenate([[True], np.diff(st) > 0])
        sel = order[keep]
        return Trajectory(
            st[keep],
            np.array([poses[i].translation for i in sel]),
            quat_xyzw_to_wxyz(np.array([poses[i].quat_xyzw for i in sel])),
            name or topic,
        )

    def __repr__(self) -> str:
        return f"RecordingReader({str(self.path)!r}, {len(self.streams)} topics)"
