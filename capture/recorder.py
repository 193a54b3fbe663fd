"""The MCAP recorder: bus samples in, ROS 2-profile MCAP files out.

Samples arrive already CDR-encoded with their ROS 2 type name; the recorder never decodes
or re-encodes a payload. It writes each stream as one MCAP channel (``cdr`` encoding,
``ros2msg`` schema, ``offered_qos_profiles`` metadata) so Foxglove, ``ros2 bag`` and
``rosbags`` read the file as a ROS 2 bag.

Threading: :meth:`Recorder.offer` is called from bus callbacks and never blocks; a single
writer thread owns the file. If the disk stalls, the bounded queue fills and samples are
dropped *and counted* (the live display and the final report show them) instead of
back-pressuring the publishers. Chunks are closed every ``chunk_size`` bytes or
``chunk_max_age_s`` seconds, so a crash loses at most one chunk; before each chunk is
written the recorder checks the free space (and the process's file-size limit), and on a
full disk it stops with a clear message and leaves a valid file of everything written.

Writing: :class:`~flightkit.datasets.mcap_writer.FastMcapWriter` keeps each payload by reference and
hands a closed chunk to ``os.writev`` (or streams it through zstd/lz4), so the writer
thread copies no payload bytes with the GIL held and the bus callback threads of the
process are not starved (the ``mcap`` package's writer copied each payload twice).
"""

from __future__ import annotations

import logging
import os
import queue
import resource
import shutil
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from flightkit import __version__
from flightkit.datasets.mcap_reader import CAPTURE_STAMP_KEY
from flightkit.datasets.mcap_recovery import finalize_in_place
from flightkit.datasets.mcap_writer import CompressionType, FastMcapWriter
from flightkit.errors import CaptureError

__all__ = [
    "Compression",
    "Recorder",
    "RecordingReport",
    "StreamSample",
    "StreamStats",
    "qos_profile_yaml",
]


logger = logging.getLogger(__name__)

Compression = CompressionType
_COMPRESSION_NAMES = {CompressionType.NONE: "", CompressionType.ZSTD: "zstd", CompressionType.LZ4: "lz4"}
_RESERVE_BYTES = 64 << 10  # room kept free for the file's ending (+ 256 bytes per chunk written)


@dataclass(frozen=True, slots=True)
class StreamSample:
    """One message as it travels on the bus.

    Attributes:
        topic: the stream's key expression, e.g. ``uav1/camera/color/image``.
        msgtype: ROS 2 type name, e.g. ``sensor_msgs/msg/Image``.
        payload: CDR bytes (with the 4-byte encapsulation header).
        seq: the publisher's per-stream sequence number.
        publish_time_ns: when the publisher put it on the bus (bus time), ns since epoch; the
            capture time stays in the message's header stamp.
        log_time_ns: when we received it, ns since epoch.
        reliable: True for streams that must not drop (mocap), for the QoS metadata.
        stamp_source: where the header stamps come from (``device``, ``host``; ``""`` not said),
            recorded in the channel's metadata as ``flightkit.capture_stamp``.
    """

    topic: str
    msgtype: str
    payload: bytes | memoryview
    seq: int
    publish_time_ns: int
    log_time_ns: int
    reliable: bool = True
    stamp_source: str = ""


def qos_profile_yaml(reliable: bool) -> str:
    """The ``offered_qos_profiles`` string rosbag2 writes for a publisher (YAML list)."""
    reliability = 1 if reliable else 2  # RELIABLE / BEST_EFFORT
    return (
        "- history: 3\n"
        "  depth: 0\n"
        f"  reliability: {reliability}\n"
        "  durability: 2\n"
        "  deadline:\n    sec: 2147483647\n    nsec: 4294967295\n"
        "  lifespan:\n    sec: 2147483647\n    nsec: 4294967295\n"
        "  liveliness: 1\n"
        "  liveliness_lease_duration:\n    sec: 2147483647\n    nsec: 4294967295\n"
        "  avoid_ros_namespace_conventions: false\n"
    )


@dataclass
class StreamStats:
    """Per-stream counters, updated by the writer thread (read them via Recorder.snapshot)."""

    msgtype: str
    count: int = 0
    bytes: int = 0
    missed: int = 0  # sequence gaps: lost between publisher and us
    dropped: int = 0  # dropped by the recorder because the disk could not keep up
    first_ns: int = 0
    last_ns: int = 0
    max_gap_ns: int = 0
    last_seq: int = -1

    @property
    def duration_s(self) -> float:
        return (self.last_ns - self.first_ns) / 1e9 if self.count > 1 else 0.0

    @property
    def rate_hz(self) -> float:
        return (self.count - 1) / self.duration_s if self.duration_s > 0 else 0.0


@dataclass
class RecordingReport:
    """What was recorded, for the final report."""

    files: list[Path]
    streams: dict[str, StreamStats]
    error: str = ""

    @property
    def messages(self) -> int:
        return sum(s.count for s in self.streams.values())

    @property
    def missed(self) -> int:
        return sum(s.missed for s in self.streams.values())

    @property
    def dropped(self) -> int:
        return sum(s.dropped for s in self.streams.values())


@dataclass
class _OpenFile:
    path: Path
    fh: object
    writer: FastMcapWriter
    channels: dict[str, int] = field(default_factory=dict)
    schemas: dict[str, int] = field(default_factory=dict)
    opened_ns: int = 0
    unflushed: int = 0
    chunks: int = 0
    last_flush_s: float = 0.0


class Recorder:
    """Writes :class:`StreamSample` objects to MCAP.

    Args:
        path: output file (``RUN.mcap``); with splitting, ``RUN_0000.mcap``, ``RUN_0001.mcap``, ...
        schema_for: maps a ROS 2 type name to its ``ros2msg`` schema text.
        compression: per-chunk compression (zstd, lz4 or none).
        allow_overwrite: replace existing files instead of refusing.
        metadata: named string maps stored in the file (config, calibration, host, version).
        split_size_mb / split_duration_s: start a new file past this size or duration.
        chunk_size: bytes per chunk; chunk_max_age_s: close a chunk at least this often.
        queue_limit_bytes: memory the recorder may hold while the disk catches up.
        on_flush: called on the writer thread after each chunk reaches the OS, with the
            ``publish_time_ns`` of every message in it (for publish-to-disk latency figures).

    Raises:
        CaptureError: if the output exists (and overwriting was not allowed) or cannot be created.
    """

    def __init__(
        self,
        path: str | Path,
        schema_for: Callable[[str], str],
        *,
        compression: CompressionType = CompressionType.NONE,
        allow_overwrite: bool = False,
        metadata: Mapping[str, Mapping[str, str]] | None = None,
        split_size_mb: float | None = None,
        split_duration_s: float | None = None,
        chunk_size: int = 4 << 20,
        chunk_max_age_s: float = 0.5,
        queue_limit_bytes: int = 1 << 30,
        on_flush: Callable[[list[int]], None] | None = None,
    ) -> None:
        self._base = Path(path)
        if self._base.suffix != ".mcap":
            raise CaptureError(f"output {self._base} should end in .mcap; name it e.g. {self._base.name}.mcap")
        if not self._base.parent.is_dir():
            raise CaptureError(f"output folder {self._base.parent} does not exist; create it first")
        self._split = split_size_mb is not None or split_duration_s is not None
        if not allow_overwrite:
            clash = self._first_path() if not self._split else None
            if clash is not None and clash.exists():
                raise CaptureError(f"{clash} exists; choose another name or pass --force to overwrite it")
            if self._split and any(self._base.parent.glob(self._base.stem + "_[0-9][0-9][0-9][0-9].mcap")):
                raise CaptureError(
                    f"split files {self._base.stem}_NNNN.mcap exist in {self._base.parent}; "
                    "choose another name or pass --force"
                )
        self._schema_for = schema_for
        self._compression = compression
        self._metadata = {k: dict(v) for k, v in (metadata or {}).items()}
        self._metadata.setdefault("flightkit", {}).update(
            {"version": __version__, "host": os.uname().nodename, "pid": str(os.getpid())}
        )
        self._split_bytes = int(split_size_mb * 1e6) if split_size_mb else None
        self._split_ns = int(split_duration_s * 1e9) if split_duration_s else None
        self._chunk_size = chunk_size
        self._chunk_max_age_s = chunk_max_age_s
        self._queue_limit = queue_limit_bytes
        self._queued_bytes = 0
        self._on_flush = on_flush
        self._chunk_stamps: list[int] = []
        self._q: queue.SimpleQueue[StreamSample | _MetadataItem | None] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._stats: dict[str, StreamStats] = {}
        self._files: list[Path] = []
        self._file_index = 0
        self._error = ""
        self._stopped = threading.Event()
        self._current: _OpenFile | None = None
        self._open_next()  # fail early, in the caller's thread, if the file cannot be created
        self._thread = threading.Thread(target=self._run, name="mcap-writer", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ public

    @property
    def error(self) -> str:
        """Why recording stopped early ("" while fine)."""
        return self._error

    @property
    def stopped(self) -> bool:
        """True once the recorder has stopped (closed, or the disk filled up)."""
        return self._stopped.is_set()

    def offer(self, sample: StreamSample) -> bool:
        """Queue a sample for writing; never blocks. False if it was dropped (and counted)."""
        size = len(sample.payload)
        with self._lock:
            st = self._stats.get(sample.topic)
            if st is None:
                st = self._stats[sample.topic] = StreamStats(sample.msgtype)
            if self._stopped.is_set() or self._queued_bytes + size > self._queue_limit:
                st.dropped += 1
                return False
            self._queued_bytes += size
        self._q.put(sample)
        return True

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """Write a metadata record (e.g. a camera's calibration seen on the bus) into the current
        file, and into every later split file; returns immediately."""
        self._q.put(_MetadataItem(name, {str(k): str(v) for k, v in data.items()}))

    def snapshot(self) -> dict[str, StreamStats]:
        """A copy of the per-stream counters, for live display."""
        with self._lock:
            return {k: StreamStats(**vars(v)) for k, v in self._stats.items()}

    @property
    def queued_bytes(self) -> int:
        return self._queued_bytes

    def close(self, timeout_s: float = 30.0) -> RecordingReport:
        """Write what is queued, finish the file(s) and return the report; idempotent."""
        self._q.put(None)
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            raise CaptureError(f"the MCAP writer did not finish within {timeout_s:.0f} s; is the disk stalled?")
        return RecordingReport(list(self._files), self.snapshot(), self._error)

    # ------------------------------------------------------------------ writer thread

    def _first_path(self) -> Path:
        return self._base

    def _next_path(self) -> Path:
        if not self._split:
            return self._base
        return self._base.with_name(f"{self._base.stem}_{self._file_index:04d}.mcap")

    def _open_next(self) -> None:
        path = self._next_path()
        self._file_index += 1
        try:
            fh = path.open("wb", buffering=0)  # the writer hands whole chunks to os.writev
        except OSError as exc:
            raise CaptureError(f"cannot create {path}: {exc.strerror}; check the folder and permissions") from exc
        writer = FastMcapWriter(fh, _COMPRESSION_NAMES[self._compression])
        writer.start(profile="ros2", library=f"flightkit {__version__}")
        for name, data in self._metadata.items():
            writer.add_metadata(name, data)
        self._current = _OpenFile(path, fh, writer, opened_ns=0, last_flush_s=time.monotonic())
        self._files.append(path)
        logger.info("recording to %s", path)

    def _headroom_bytes(self, path: Path) -> int:
        free = shutil.disk_usage(path.parent).free
        soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
        if soft != resource.RLIM_INFINITY:
            free = min(free, soft - path.stat().st_size)
        return free

    def _flush_chunk(self) -> None:
        cur = self._current
        assert cur is not None
        if cur.unflushed == 0:
            cur.last_flush_s = time.monotonic()
            return
        # A compressed chunk is never larger than the raw bytes (+ small overhead).
        cur.chunks += 1
        if self._headroom_bytes(cur.path) < cur.unflushed + _RESERVE_BYTES + 256 * cur.chunks:
            raise _DiskFull(cur.path)
        cur.writer.flush_chunk()
        cur.unflushed = 0
        cur.last_flush_s = time.monotonic()
        if self._on_flush is not None and self._chunk_stamps:
            stamps, self._chunk_stamps = self._chunk_stamps, []
            self._on_flush(stamps)

    def _finish_current(self) -> None:
        cur = self._current
        if cur is None:
            return
        self._flush_chunk()
        cur.writer.finish()
        os.fsync(cur.fh.fileno())  # type: ignore[attr-defined]
        cur.fh.close()  # type: ignore[attr-defined]
        self._current = None

    def _write(self, s: StreamSample) -> None:
        cur = self._current
        assert cur is not None
        if self._split and cur.opened_ns and (
            (self._split_bytes is not None and cur.writer.bytes_written + cur.unflushed >= self._split_bytes)
            or (self._split_ns is not None and s.log_time_ns - cur.opened_ns >= self._split_ns)
        ):
            self._finish_current()
            self._open_next()
            cur = self._current
            assert cur is not None
        if not cur.opened_ns:
            cur.opened_ns = s.log_time_ns
        ch = cur.channels.get(s.topic)
        if ch is None:
            sid = cur.schemas.get(s.msgtype)
            if sid is None:
                text = self._schema_for(s.msgtype)
                sid = cur.writer.register_schema(s.msgtype, "ros2msg", text.encode())
                cur.schemas[s.msgtype] = sid
            topic = s.topic if s.topic.startswith("/") else "/" + s.topic
            ch = cur.writer.register_channel(topic, "cdr", sid, {
                "offered_qos_profiles": qos_profile_yaml(s.reliable),
                CAPTURE_STAMP_KEY: s.stamp_source or "unknown",
            })
            cur.channels[s.topic] = ch
        cur.writer.add_message(ch, s.log_time_ns, s.payload, s.publish_time_ns, s.seq & 0xFFFFFFFF)
        cur.unflushed += len(s.payload) + 31
        if self._on_flush is not None:
            self._chunk_stamps.append(s.publish_time_ns)
        with self._lock:
            st = self._stats[s.topic]
            if st.last_seq >= 0 and s.seq > st.last_seq + 1:
                st.missed += s.seq - st.last_seq - 1
            st.last_seq = max(st.last_seq, s.seq)
            if st.count:
                st.max_gap_ns = max(st.max_gap_ns, s.log_time_ns - st.last_ns)
            else:
                st.first_ns = s.log_time_ns
            st.last_ns = max(st.last_ns, s.log_time_ns)
            st.count += 1
            st.bytes += len(s.payload)
        if cur.unflushed >= self._chunk_size:
            self._flush_chunk()

    def _run(self) -> None:
        s: StreamSample | _MetadataItem | Literal[False] | None  # False: nothing arrived in time
        try:
            while True:
                try:
                    s = self._q.get(timeout=self._chunk_max_age_s / 2)
                except queue.Empty:
                    s = False
                if s is None:
                    break
                if isinstance(s, _MetadataItem):
                    self._metadata[s.name] = s.data
                    if self._current is not None:
                        self._current.writer.add_metadata(s.name, s.data)
                elif s is not False:
                    with self._lock:
                        self._queued_bytes -= len(s.payload)
                    self._write(s)
                cur = self._current
                if cur is not None and time.monotonic() - cur.last_flush_s >= self._chunk_max_age_s:
                    self._flush_chunk()
            self._finish_current()
        except (_DiskFull, OSError) as exc:
            self._stop_on_disk_error(exc)
        except Exception as exc:  # keep the file valid whatever happened
            logger.exception("recorder failed")
            self._stop_on_disk_error(exc)
        finally:
            self._stopped.set()
            self._drain_as_dropped()

    def _stop_on_disk_error(self, exc: BaseException) -> None:
        cur = self._current
        self._current = None
        path = cur.path if cur is not None else self._base
        if isinstance(exc, _DiskFull):
            self._error = (
                f"disk full while writing {path}; recording stopped and the file was closed with "
                "everything written so far; free some space or record to another disk"
            )
        else:
            self._error = f"writing {path} failed ({exc}); recording stopped, the file keeps what was written"
        logger.error("%s", self._error)
        if cur is None:
            return
        try:
            cur.fh.close()  # type: ignore[attr-defined]
        except OSError:
            pass  # the buffered tail could not be written; finalize cuts it off
        try:
            finalize_in_place(path)
        except Exception as fin_exc:  # noqa: BLE001
            self._error += (
                f"; closing the file also failed ({fin_exc}): run 'flightkit capture recover {path} -o FIXED.mcap' "
                "on a disk with space"
            )

    def _drain_as_dropped(self) -> None:
        while True:
            try:
                s = self._q.get_nowait()
            except queue.Empty:
                return
            if s is None or isinstance(s, _MetadataItem):
                continue
            with self._lock:
                self._queued_bytes -= len(s.payload)
                self._stats[s.topic].dropped += 1


@dataclass(frozen=True, slots=True)
class _MetadataItem:
    name: str
    data: dict[str, str]


class _DiskFull(Exception):
    def __init__(self, path: Path) -> None:
        super().__init__(f"no room left for {path}")
