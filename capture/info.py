"""What a recording holds: streams, counts, rates, duration, gaps, time spans and rolling-shutter readouts."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from flightkit.datasets.mcap_reader import RecordingReader, namespace_of
from flightkit.errors import CaptureError, DatasetError

__all__ = ["RecordingInfo", "StreamStats", "recording_info"]


@dataclass
class StreamStats:
    """One channel of a recording.

    Attributes:
        gaps: (start_ns, length_s) of every silence longer than ``gap_factor`` times the
            median period.
    """

    topic: str
    msgtype: str
    count: int = 0
    bytes: int = 0
    first_ns: int = 0
    last_ns: int = 0
    median_period_s: float = 0.0
    max_gap_s: float = 0.0
    missed_seq: int = 0
    gaps: list[tuple[int, float]] = field(default_factory=list)

    @property
    def duration_s(self) -> float:
        return (self.last_ns - self.first_ns) / 1e9

    @property
    def namespace(self) -> str:
        """The vehicle namespace of the topic."""
        return namespace_of(self.topic)

    @property
    def rate_hz(self) -> float:
        return (self.count - 1) / self.duration_s if self.count > 1 and self.duration_s > 0 else 0.0


@dataclass
class RecordingInfo:
    """A recording's summary.

    Attributes:
        readouts_s: camera_info topic -> the camera's rolling-shutter readout (s), for the cameras
            recorded with one > 0 (NaN: the recorded value is malformed).
    """

    path: Path
    size_bytes: int
    profile: str
    library: str
    streams: list[StreamStats]
    metadata: dict[str, dict[str, str]]
    readouts_s: dict[str, float] = field(default_factory=dict)

    def by_vehicle(self) -> dict[str, list[StreamStats]]:
        """The streams grouped by vehicle namespace (first element of the topic), sorted."""
        out: dict[str, list[StreamStats]] = {}
        for s in self.streams:
            out.setdefault(s.namespace, []).append(s)
        return dict(sorted(out.items()))

    @property
    def start_ns(self) -> int:
        return min((s.first_ns for s in self.streams if s.count), default=0)

    @property
    def end_ns(self) -> int:
        return max((s.last_ns for s in self.streams if s.count), default=0)

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / 1e9

    @property
    def messages(self) -> int:
        return sum(s.count for s in self.streams)


def recording_info(path: str | Path, gap_factor: float = 3.0) -> RecordingInfo:
    """Read every message header of ``path`` (payloads are not decoded).

    Raises:
        CaptureError: if the file is missing or not a readable MCAP file (with the fix).
    """
    p = Path(path)
    if not p.is_file():
        raise CaptureError(f"{p} does not exist; check the path")
    stamps: dict[str, list[int]] = {}
    seqs: dict[str, list[int]] = {}
    sizes: dict[str, int] = {}
    try:
        rec = RecordingReader(p)
        types = {s.topic: s.schema_name for s in rec.streams}
        for m in rec.messages(log_time_order=False):
            stamps.setdefault(m.topic, []).append(m.log_time_ns)
            seqs.setdefault(m.topic, []).append(m.sequence)
            sizes[m.topic] = sizes.get(m.topic, 0) + len(m.data)
    except DatasetError as exc:
        raise CaptureError(str(exc)) from exc
    streams = []
    for topic in sorted(stamps):
        ts = sorted(stamps[topic])
        info = StreamStats(topic, types.get(topic, ""), len(ts), sizes[topic], ts[0], ts[-1])
        if len(ts) > 1:
            periods = [(b - a) / 1e9 for a, b in zip(ts, ts[1:], strict=False)]
            srt = sorted(periods)
            info.median_period_s = srt[len(srt) // 2]
            info.max_gap_s = srt[-1]
            limit = gap_factor * info.median_period_s
            info.gaps = [(ts[i], d) for i, d in enumerate(periods) if limit > 0 and d > limit]
        sq = sorted(seqs[topic])
        if sq and sq[-1] > sq[0]:
            info.missed_seq = max(0, (sq[-1] - sq[0] + 1) - len(set(sq)))
        streams.append(info)
    readouts: dict[str, float] = {}
    for topic in (st.topic for st in rec.streams if st.topic.endswith("/camera_info")):  # every vehicle's
        try:
            readout = rec.camera_readout_s(topic)
        except DatasetError:
            readout = math.nan
        if not readout <= 0.0:
            readouts[topic] = readout
    return RecordingInfo(p, p.stat().st_size, rec.profile, rec.library, streams, rec.metadata, readouts)
