"""Salvaging MCAP files: scan what is intact, and give it a valid ending.

A recording that was cut short (SIGKILL, power loss, a full disk) holds a valid prefix
(magic, header, metadata, complete chunks each followed by its message indexes) and then
perhaps a torn record. :func:`scan` walks the records without trusting any index, checks
each chunk's CRC, and finds where the intact prefix ends. :func:`recover` copies that prefix
to a new file and appends a summary (schemas, channels, statistics, chunk and metadata
indexes) and footer, so every complete chunk is readable by any MCAP reader.
:func:`finalize_in_place` does the same without a copy (truncate, then append), which is
what the recorder does when the disk fills up.
"""

from __future__ import annotations

import logging
import os
import struct
import zlib
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import BinaryIO

from mcap.data_stream import ReadDataStream, RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.stream_reader import breakup_chunk

from flightkit.errors import DatasetError

__all__ = ["RecoveryReport", "ScanResult", "finalize_in_place", "recover", "scan"]

logger = logging.getLogger(__name__)

MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEADER = struct.Struct("<BQ")


@dataclass
class _ChunkInfo:
    index: ChunkIndex
    counts: dict[int, int]


@dataclass
class ScanResult:
    """What an MCAP file holds, as far as it is intact.

    Attributes:
        good_end: byte offset where the intact prefix ends (everything after is lost).
        file_size: size of the file scanned.
        complete: True when the file already has a valid footer.
        lost_chunks: chunks found but unusable (torn or failing their CRC).
    """

    good_end: int = 0
    file_size: int = 0
    complete: bool = False
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    chunks: list[_ChunkInfo] = field(default_factory=list)
    metadata: list[MetadataIndex] = field(default_factory=list)
    lost_chunks: int = 0
    message_start_ns: int = 0
    message_end_ns: int = 0

    @property
    def message_count(self) -> int:
        return sum(sum(c.counts.values()) for c in self.chunks)

    @property
    def lost_bytes(self) -> int:
        return self.file_size - self.good_end


@dataclass(frozen=True, slots=True)
class RecoveryReport:
    """What :func:`recover` salvaged."""

    messages: int
    chunks: int
    lost_bytes: int
    lost_chunks: int
    duration_s: float
    was_complete: bool

    def summary(self) -> str:
        if self.was_complete:
            return f"file was already complete: {self.messages} messages in {self.chunks} chunks"
        return (
            f"salvaged {self.messages} messages in {self.chunks} complete chunks "
            f"({self.duration_s:.1f} s of data); lost {self.lost_bytes} bytes at the end"
            + (f" and {self.lost_chunks} damaged chunk(s)" if self.lost_chunks else "")
        )


def _read_record(fh: BinaryIO, size: int) -> tuple[int, int, bytes] | None:
    """(opcode, offset, content) of the next record, or None if it is torn."""
    offset = fh.tell()
    head = fh.read(_RECORD_HEADER.size)
    if len(head) < _RECORD_HEADER.size:
        return None
    opcode, length = _RECORD_HEADER.unpack(head)
    if length > size - offset - _RECORD_HEADER.size:
        return None
    content = fh.read(length)
    if len(content) < length:
        return None
    return opcode, offset, content


def scan(path: str | Path) -> ScanResult:
    """Walk the records of ``path`` and find its intact prefix.

    Raises:
        DatasetError: if the file is not an MCAP file at all.
    """
    p = Path(path)
    try:
        fh = p.open("rb")
    except OSError as exc:
        raise DatasetError(f"cannot open {p}: {exc.strerror}; check the path") from exc
    res = ScanResult(file_size=p.stat().st_size)
    with fh:
        if fh.read(len(MAGIC)) != MAGIC:
            raise DatasetError(f"{p} is not an MCAP file (bad magic); nothing to recover")
        res.good_end = len(MAGIC)
        pending: _ChunkInfo | None = None  # a chunk whose message indexes may still follow
        while True:
            rec = _read_record(fh, res.file_size)
            if rec is None:
                break
            opcode, offset, content = rec
            end = fh.tell()
            if opcode != Opcode.MESSAGE_INDEX and pending is not None:
                res.chunks.append(pending)
                pending = None
            stream = ReadDataStream(BytesIO(content))
            if opcode == Opcode.HEADER:
                res.good_end = end
            elif opcode == Opcode.CHUNK:
                try:
                    chunk = Chunk.read(stream)
                    records = breakup_chunk(chunk, validate_crc=True)
                except Exception as exc:  # corrupt chunk: CRC, compression or framing
                    logger.warning("chunk at offset %d is damaged (%s); skipping it", offset, exc)
                    res.lost_chunks += 1
                    break
                counts: dict[int, int] = {}
                for r in records:
                    if isinstance(r, Schema):
                        res.schemas.setdefault(r.id, r)
                    elif isinstance(r, Channel):
                        res.channels.setdefault(r.id, r)
                    elif isinstance(r, Message):
                        counts[r.channel_id] = counts.get(r.channel_id, 0) + 1
                index = ChunkIndex(
                    message_start_time=chunk.message_start_time,
                    message_end_time=chunk.message_end_time,
                    chunk_start_offset=offset,
                    chunk_length=end - offset,
                    message_index_offsets={},
                    message_index_length=0,
                    compression=chunk.compression,
                    compressed_size=len(chunk.data),
                    uncompressed_size=chunk.uncompressed_size,
                )
                pending = _ChunkInfo(index, counts)
                res.good_end = end
            elif opcode == Opcode.MESSAGE_INDEX and pending is not None:
                mi = MessageIndex.read(stream)
                pending.index.message_index_offsets[mi.channel_id] = offset
                pending.index.message_index_length = end - (
                    pending.index.chunk_start_offset + pending.index.chunk_length
                )
                res.good_end = end
            elif opcode == Opcode.SCHEMA:
                s = Schema.read(stream)
                res.schemas.setdefault(s.id, s)
                res.good_end = end
            elif opcode == Opcode.CHANNEL:
                c = Channel.read(stream)
                res.channels.setdefault(c.id, c)
                res.good_end = end
            elif opcode == Opcode.METADATA:
                m = Metadata.read(stream)
                res.metadata.append(MetadataIndex(offset=offset, length=end - offset, name=m.name))
                res.good_end = end
            elif opcode == Opcode.DATA_END:
                # The data section ended properly; a footer should follow.
                tail = fh.read()
                res.complete = tail.endswith(MAGIC)
                break
            else:
                res.good_end = end  # attachments and other records are kept as they are
        if pending is not None:
            res.chunks.append(pending)
    if res.chunks:
        res.message_start_ns = min(c.index.message_start_time for c in res.chunks)
        res.message_end_ns = max(c.index.message_end_time for c in res.chunks)
    return res


def _write_ending(out: BinaryIO, res: ScanResult) -> None:
    """Append DataEnd, the summary section and the footer at the current position."""
    rb = RecordBuilder()
    DataEnd(0).write(rb)
    out.write(rb.end())
    summary_start = out.tell()
    sb = RecordBuilder()
    offsets: list[SummaryOffset] = []

    def group(opcode: int, records: list[object]) -> None:
        start = sb.count
        for r in records:
            r.write(sb)  # type: ignore[attr-defined]
        offsets.append(SummaryOffset(opcode, summary_start + start, sb.count - start))

    counts: dict[int, int] = {}
    for c in res.chunks:
        for ch, n in c.counts.items():
            counts[ch] = counts.get(ch, 0) + n
    stats = Statistics(
        message_count=sum(counts.values()),
        schema_count=len(res.schemas),
        channel_count=len(res.channels),
        attachment_count=0,
        metadata_count=len(res.metadata),
        chunk_count=len(res.chunks),
        message_start_time=res.message_start_ns,
        message_end_time=res.message_end_ns,
        channel_message_counts=counts,
    )
    group(Opcode.SCHEMA, list(res.schemas.values()))
    group(Opcode.CHANNEL, list(res.channels.values()))
    group(Opcode.STATISTICS, [stats])
    group(Opcode.CHUNK_INDEX, [c.index for c in res.chunks])
    group(Opcode.METADATA_INDEX, list(res.metadata))
    offset_start = summary_start + sb.count
    for o in offsets:
        o.write(sb)
    data = sb.end()
    crc = zlib.crc32(data)
    crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, offset_start), crc)
    out.write(data)
    fb = RecordBuilder()
    Footer(summary_start=summary_start, summary_offset_start=offset_start, summary_crc=crc).write(fb)
    out.write(fb.end())
    out.write(MAGIC)


def recover(src: str | Path, dst: str | Path, allow_overwrite: bool = False) -> RecoveryReport:
    """Copy every complete chunk of ``src`` into a valid MCAP file ``dst``.

    Raises:
        DatasetError: if ``src`` is not MCAP, or ``dst`` exists and ``allow_overwrite`` is False.
    """
    src, dst = Path(src), Path(dst)
    if dst.exists() and not allow_overwrite:
        raise DatasetError(f"{dst} exists; choose another output path or pass --force to overwrite it")
    if src.resolve() == dst.resolve():
        raise DatasetError("recover writes a new file; give an output path different from the input")
    res = scan(src)
    with src.open("rb") as fin, dst.open("wb") as fout:
        remaining = res.good_end
        while remaining > 0:
            buf = fin.read(min(remaining, 8 << 20))
            if not buf:
                break
            fout.write(buf)
            remaining -= len(buf)
        _write_ending(fout, res)
        fout.flush()
        os.fsync(fout.fileno())
    return RecoveryReport(
        messages=res.message_count,
        chunks=len(res.chunks),
        lost_bytes=0 if res.complete else res.lost_bytes,
        lost_chunks=res.lost_chunks,
        duration_s=(res.message_end_ns - res.message_start_ns) / 1e9 if res.chunks else 0.0,
        was_complete=res.complete,
    )


def finalize_in_place(path: str | Path) -> ScanResult:
    """Cut ``path`` back to its intact prefix and append a valid ending (no copy is made).

    Used when the disk is full: truncating frees the torn tail, and the ending is small.
    """
    p = Path(path)
    res = scan(p)
    if res.complete:
        return res
    with p.open("r+b") as fh:
        fh.truncate(res.good_end)
        fh.seek(res.good_end)
        _write_ending(fh, res)
        fh.flush()
        os.fsync(fh.fileno())
    return res
