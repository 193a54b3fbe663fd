"""Recording from the bus: subscribe to key expressions and write every sample to MCAP.

::

    from capture.bus_recorder import start_recording
    rec = start_recording("run.mcap", session=s, topics=["uav1/**"], lab_cfg=cfg)
    ...                        # fly
    report = rec.stop()        # finishes the file; RecordingReport with counts and gaps

Payloads are written as they arrived (CDR bytes, never decoded and re-encoded); each
stream becomes an MCAP channel with its ros2msg schema (:func:`flightkit.bus.msg_base.schema_text`)
and QoS metadata (images best effort, everything else reliable). Each message keeps three times:
its header stamp (the capture time, as the device gave it or not: the channel's
``flightkit.capture_stamp`` says), MCAP ``publish_time`` (when it was put on the bus) and
``log_time`` (when the recorder received it). The recording carries
metadata records: ``flightkit`` (version, host), ``config`` (the lab config), ``extrinsics``
(``T_body_camera``, ``T_world_mocap``), and ``calibration.<camera>`` for every camera whose
camera_info was seen on the bus. CameraInfo has no rolling-shutter readout, so the recorder asks the
camera for it on the bus (``.../calibration``, :mod:`flightkit.bus.camera_calibration`) and keeps its
``readout_s`` in that record: it reaches a recorder in another process with no CameraInfo field misused.

Threads: Zenoh delivers samples on its own threads; :meth:`BusRecorder._on_sample` only
wraps the payload and offers it to the recorder's queue (never blocks), so a stalled disk
cannot back-pressure any publisher.
"""

from __future__ import annotations

import dataclasses
import enum
import json
import logging
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, Self

import zenoh

from capture.config import CaptureConfig
from capture.recorder import Compression, Recorder, RecordingReport, StreamSample, StreamStats
from flightkit.bus.camera_calibration import ask_calibration, calibration_key
from flightkit.bus.clock_exchange import ClockWatch, bus_host_name
from flightkit.bus.image_msgs import CameraInfo
from flightkit.bus.keys import Keys
from flightkit.bus.msg_base import schema_text
from flightkit.bus.pubsub import BusSample, BusSubscriber
from flightkit.bus.session import open_session
from flightkit.bus.streams import check_readout_s, is_best_effort
from flightkit.calibration.clock_sync import CLOCK_OFFSETS_RECORD
from flightkit.clock import WallClock
from flightkit.config import BusConfig, LabConfig
from flightkit.datasets.mcap_reader import transform_to_json
from flightkit.errors import BusError, CaptureError

__all__ = ["BusRecorder", "compression_from_name", "recording_metadata", "start_recording"]

logger = logging.getLogger(__name__)

_ASK_TIMEOUT_S = 2.0  # a camera's answer to the calibration query (loopback: ~1 ms; none: at once)


def compression_from_name(name: str) -> Compression:
    """``"zstd"``, ``"lz4"`` or ``"none"`` -> the MCAP compression.

    Raises:
        CaptureError: for another name.
    """
    table = {"zstd": Compression.ZSTD, "lz4": Compression.LZ4, "none": Compression.NONE}
    if name not in table:
        raise CaptureError(f"compression {name!r} is not known; use zstd, lz4 or none")
    return table[name]


def _plain(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    return value


def recording_metadata(lab_cfg: LabConfig | None) -> dict[str, dict[str, str]]:
    """Metadata records describing the set-up: the config and the extrinsics (config, not secrets:
    TLS key paths are kept, their contents are not read)."""
    if lab_cfg is None:
        return {}
    sections = {
        f.name: _plain(getattr(lab_cfg, f.name))
        for f in dataclasses.fields(lab_cfg)
        if f.name not in ("source_path", "capability_tables")
    }
    sections["link"].pop("signing_key_hex", None)
    config = {name: json.dumps(table, sort_keys=True) for name, table in sections.items()}
    config["source_path"] = lab_cfg.source_path
    for name, table in lab_cfg.capability_tables.items():
        config[name] = json.dumps(_plain(table), sort_keys=True)
    cam = lab_cfg.camera
    fx, fy, cx, cy = cam.intrinsics()
    return {
        "config": config,
        "extrinsics": {
            "T_body_camera": transform_to_json(cam.T_body_camera.to_transform()),
            "T_world_mocap": transform_to_json(lab_cfg.mocap.T_world_mocap.to_transform()),
            "mocap_body": lab_cfg.mocap.body,
            "camera_frame": "opencv (x right, y down, z forward)",
            "body_frame": "flu",
            "world_frame": "enu",
        },
        "calibration": {
            "width": str(cam.width_px),
            "height": str(cam.height_px),
            "fx": repr(fx),
            "fy": repr(fy),
            "cx": repr(cx),
            "cy": repr(cy),
            "stereo_baseline_m": repr(cam.stereo_baseline_m),
            "rate_hz": repr(cam.rate_hz),
            "source": "config",
        },
    }


class BusRecorder:
    """Record everything published on ``topics`` to MCAP.

    Args:
        session: an open Zenoh session (not closed by the recorder).
        path: output ``.mcap`` (``RUN_0000.mcap``... when splitting).
        topics: key expressions, e.g. ``["uav1/**"]``.
        compression, allow_overwrite, split_size_mb, split_duration_s, chunk_size,
        chunk_max_age_s, queue_limit_bytes, on_flush: as for :class:`~capture.recorder.Recorder`.
        metadata: extra metadata records.
        time_ns: receive-time source for MCAP ``log_time`` (default: wall clock).
        clock_watch: a :class:`~flightkit.bus.clock_exchange.ClockWatch` on this recorder's clock:
            started with the recording, and its offsets of every other host's clock are written
            into the file when it stops (record ``clock_offsets``), so the hosts share one time base.

    Raises:
        CaptureError: the output exists (without ``allow_overwrite``) or cannot be created.
        BusError: a key expression is refused.
    """

    def __init__(
        self,
        session: zenoh.Session,
        path: str | Path,
        topics: Sequence[str],
        *,
        compression: Compression | str = Compression.ZSTD,
        allow_overwrite: bool = False,
        metadata: Mapping[str, Mapping[str, str]] | None = None,
        split_size_mb: float | None = None,
        split_duration_s: float | None = None,
        chunk_size: int = 4 << 20,
        chunk_max_age_s: float = 0.5,
        queue_limit_bytes: int = 1 << 30,
        on_flush: Callable[[list[int]], None] | None = None,
        time_ns: Callable[[], int] = time.time_ns,
        clock_watch: ClockWatch | None = None,
    ) -> None:
        if not topics:
            raise CaptureError("no topics to record; give key expressions such as 'uav1/**'")
        if isinstance(compression, str):
            compression = compression_from_name(compression)
        self.path = Path(path)
        self.topics = tuple(topics)
        self._time_ns = time_ns
        self._schemas: dict[str, str] = {}
        self._seen_info: set[str] = set()
        self._session = session
        self._lock = threading.Lock()
        self._asking = threading.Condition(self._lock)
        self._asked = 0  # calibration queries not answered yet
        self._calibrated: set[str] = set()
        self.recorder = Recorder(
            path,
            self._schema_for,
            compression=compression,
            allow_overwrite=allow_overwrite,
            metadata=metadata,
            split_size_mb=split_size_mb,
            split_duration_s=split_duration_s,
            chunk_size=chunk_size,
            chunk_max_age_s=chunk_max_age_s,
            queue_limit_bytes=queue_limit_bytes,
            on_flush=on_flush,
        )
        self.started_ns = time_ns()
        self.unknown_types: set[str] = set()
        self._subs: list[BusSubscriber] = []
        self.clock_watch = clock_watch
        try:
            for t in self.topics:
                self._subs.append(BusSubscriber(session, t, callback=self._on_sample))
            if clock_watch is not None:
                clock_watch.start()
        except BusError:
            self.stop()
            raise
        logger.info("recording %s to %s", ", ".join(self.topics), self.path)

    def _schema_for(self, msgtype: str) -> str:
        return schema_text(msgtype)

    def _on_sample(self, s: BusSample) -> None:
        """Zenoh thread: wrap and queue; never blocks."""
        if not s.msgtype:
            return  # not a typed flightkit/ROS 2 sample: no schema to record it with
        if s.msgtype not in self._schemas:
            try:
                self._schemas[s.msgtype] = schema_text(s.msgtype)
            except BusError:
                if s.msgtype not in self.unknown_types:
                    logger.warning("not recording %s: message type %s has no known schema", s.key, s.msgtype)
                    self.unknown_types.add(s.msgtype)
                return
        now = self._time_ns()
        self.recorder.offer(
            StreamSample(
                s.key,
                s.msgtype,
                s.payload,
                max(s.seq, 0),
                s.bus_ns or s.stamp_ns or now,
                now,
                reliable=not is_best_effort(s.msgtype),
                stamp_source=s.stamp_source,
            )
        )
        if s.msgtype == CameraInfo.TYPE and s.key not in self._seen_info:
            self._note_calibration(s)

    def _note_calibration(self, s: BusSample) -> None:
        with self._lock:
            if s.key in self._seen_info:
                return
            self._seen_info.add(s.key)
        try:
            info = CameraInfo.decode(s.payload)
        except BusError:
            return
        camera = s.key.rstrip("/").split("/")[-2]
        record = {
            "topic": s.key,
            "width": str(info.width),
            "height": str(info.height),
            "distortion_model": info.distortion_model,
            "d": " ".join(repr(v) for v in info.d),
            "k": " ".join(repr(v) for v in info.k),
            "p": " ".join(repr(v) for v in info.p),
            "frame_id": info.header.frame_id,
            "source": "camera_info",
        }
        with self._lock:
            self._asked += 1
        try:
            key = calibration_key(s.key)
        except BusError:  # not a flightkit camera key: nobody to ask
            self._write_calibration(camera, record, {})
            return
        ask_calibration(self._session, key,
                        lambda fields: self._write_calibration(camera, record, fields), _ASK_TIMEOUT_S)

    def _write_calibration(self, camera: str, record: dict[str, str], fields: Mapping[str, str]) -> None:
        """Zenoh thread: the camera's answer is in (``{}``: none); write ``calibration.<camera>``."""
        if "readout_s" in fields:
            try:
                record["readout_s"] = repr(check_readout_s(fields["readout_s"]))
            except BusError as exc:
                logger.warning("camera %s: not recording its readout: %s", record["topic"], exc)
        self.recorder.add_metadata(f"calibration.{camera}", record)
        with self._lock:
            self._asked -= 1
            self._calibrated.add(record["topic"])
            self._asking.notify_all()

    # ------------------------------------------------------------------ status

    def snapshot(self) -> dict[str, StreamStats]:
        """Per-stream counters for a live display."""
        return self.recorder.snapshot()

    @property
    def calibrated(self) -> frozenset[str]:
        """The camera_info keys whose ``calibration.<camera>`` record is written (with the camera's
        answer to the calibration query, or without one when it gave none)."""
        with self._lock:
            return frozenset(self._calibrated)

    @property
    def stopped(self) -> bool:
        """True when the recorder stopped by itself (disk full) or was stopped."""
        return self.recorder.stopped

    @property
    def error(self) -> str:
        return self.recorder.error

    def wait_for(self, predicate: Callable[[dict[str, StreamStats]], bool], timeout_s: float) -> None:
        """Block until ``predicate(snapshot)`` holds (wall-clock timeout, polled every 10 ms).

        Raises:
            CaptureError: not within ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        while not predicate(self.snapshot()):
            if time.monotonic() > deadline:
                counts = {k: v.count for k, v in self.snapshot().items()}
                raise CaptureError(f"recording did not reach the expected state within {timeout_s:g} s: {counts}")
            time.sleep(0.01)

    def stop(self, timeout_s: float = 30.0) -> RecordingReport:
        """Unsubscribe, write what is queued and finish the file; returns the report. Idempotent."""
        for sub in self._subs:
            sub.close()
        self._subs = []
        with self._asking:  # a camera's calibration record waits for its answer (a query times out)
            self._asking.wait_for(lambda: self._asked == 0, _ASK_TIMEOUT_S + 1.0)
        watch, self.clock_watch = self.clock_watch, None
        if watch is not None:
            watch.stop()
            offsets = watch.to_metadata()
            self.recorder.add_metadata(CLOCK_OFFSETS_RECORD, offsets)
            logger.info("clock offsets of %d other host(s) recorded", len(offsets) - 1)
        return self.recorder.close(timeout_s)

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()


class _OwnedSessionRecorder(BusRecorder):
    """A BusRecorder that also closes the session it opened."""

    _owned: zenoh.Session | None = None

    def stop(self, timeout_s: float = 30.0) -> RecordingReport:
        report = super().stop(timeout_s)
        s, self._owned = self._owned, None
        if s is not None:
            s.close()
        return report


def start_recording(
    path: str | Path,
    *,
    session: zenoh.Session | None = None,
    bus_cfg: BusConfig | None = None,
    topics: Sequence[str] | None = None,
    lab_cfg: LabConfig | None = None,
    compression: str | None = None,
    allow_overwrite: bool = False,
    clock_host: str | None = "",
    **options: Any,
) -> BusRecorder:
    """Start recording in the background; call ``.stop()`` on the result to finish the file.

    Args:
        path: the ``.mcap`` file.
        session: a Zenoh session to use; None opens one from ``bus_cfg`` (or ``lab_cfg.bus``,
            or the embedded default) and closes it on stop.
        topics: key expressions; default ``[capture] topics`` or ``<ns>/**`` of every vehicle of
            the lab (its ``[[vehicles]]``).
        lab_cfg: the lab config (namespace, metadata, ``[capture]`` defaults).
        compression: ``zstd``, ``lz4`` or ``none`` (default from ``[capture]``).
        clock_host: this host's name in the clock exchange (``""``: from the host name; None: no
            exchange): the recorder serves its clock on ``<ns>/clock/<host>`` and records the
            offsets of every other host's clock (see :class:`BusRecorder`).
        options: passed to :class:`BusRecorder` (split, chunk and queue settings).

    Returns immediately.

    Raises:
        CaptureError, BusError: see :class:`BusRecorder` and :func:`flightkit.bus.session.open_session`.
    """
    cap = lab_cfg.section("capture", CaptureConfig) if lab_cfg is not None else CaptureConfig()
    namespaces = [c.vehicle.namespace for c in lab_cfg.fleet()] if lab_cfg is not None else ["uav1"]
    topics = list(topics or cap.topics or [Keys(ns).everything() for ns in namespaces])
    meta = recording_metadata(lab_cfg)
    meta.update(options.pop("metadata", None) or {})
    options.setdefault("chunk_size", int(cap.chunk_size_mb * (1 << 20)))
    options.setdefault("chunk_max_age_s", cap.chunk_max_age_s)
    options.setdefault("queue_limit_bytes", int(cap.queue_limit_mb * (1 << 20)))
    owned = None
    if session is None:
        owned = session = open_session(bus_cfg or (lab_cfg.bus if lab_cfg is not None else None))
    try:
        watch = None
        if clock_host is not None:
            watch = ClockWatch(session, Keys(namespaces[0]), clock_host or bus_host_name(), WallClock())
        rec = _OwnedSessionRecorder(
            session,
            path,
            topics,
            compression=compression or cap.compression,
            allow_overwrite=allow_overwrite,
            metadata=meta,
            clock_watch=watch,
            **options,
        )
    except BaseException:
        if owned is not None:
            owned.close()
        raise
    rec._owned = owned
    return rec
