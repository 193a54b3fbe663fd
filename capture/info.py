"""What a recording holds: streams, counts, rates, duration, gaps and time spans."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from mcap.reader import make_reader

from flightkit.errors import CaptureError

__all__ = ["RecordingInfo", "StreamInfo", "recording_info"]


@dataclass
class StreamInfo:
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
    def rate_hz(self) -> float:
        return (self.count - 1) / self.duration_s if self.count > 1 and self.duration_s > 0 else 0.0


@dataclass
class RecordingInfo:
    path: Path
    size_bytes: int
    profile: str
    library: str
    streams: list[StreamInfo]
    metadata: dict[str, dict[str, str]]

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
    stamps: dict[int, list[int]] = {}
    seqs: dict[int, list[int]] = {}
    sizes: dict[int, int] = {}
    try:
        with p.open("rb") as fh:
            reader = make_reader(fh)
            header = reader.get_header()
            metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
            channels = {}
            for schema, channel, message in reader.iter_messages(log_time_order=False):
                channels[channel.id] = (channel.topic, schema.name if schema else "")
                stamps.setdefault(channel.id, []).append(message.log_time)
                seqs.setdefault(channel.id, []).append(message.sequence)
                sizes[channel.id] = sizes.get(channel.id, 0) + len(message.data)
    except CaptureError:
        raise
    except Exception as exc:
        raise CaptureError(
            f"{p} is not a readable MCAP file ({exc}); if the recording crashed, run "
            f"'flightkit capture recover {p} -o FIXED.mcap'"
        ) from exc
    streams = []
    for cid, (topic, msgtype) in sorted(channels.items(), key=lambda kv: kv[1][0]):
        ts = sorted(stamps[cid])
        info = StreamInfo(topic, msgtype, len(ts), sizes[cid], ts[0], ts[-1])
        if len(ts) > 1:
            periods = [(b - a) / 1e9 for a, b in zip(ts, ts[1:], strict=False)]
            srt = sorted(periods)
            info.median_period_s = srt[len(srt) // 2]
            info.max_gap_s = srt[-1]
            limit = gap_factor * info.median_period_s
            info.gaps = [(ts[i], d) for i, d in enumerate(periods) if limit > 0 and d > limit]
        sq = sorted(seqs[cid])
        if sq and sq[-1] > sq[0]:
            info.missed_seq = max(0, (sq[-1] - sq[0] + 1) - len(set(sq)))
        streams.append(info)
    return RecordingInfo(p, p.stat().st_size, header.profile, header.library, streams, metadata)
