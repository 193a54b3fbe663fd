"""Add (or replace) a metadata record of an MCAP recording.

MCAP files are written once, so a record is added by copying the recording: every schema,
channel, message (payloads untouched, in log-time order) and metadata record goes to a new
file, with the record ``name`` replaced or added. Writing to the source path itself goes through
a temporary file beside it and an atomic rename, so a failure leaves the original intact.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from pathlib import Path

from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from flightkit.errors import CaptureError, DatasetError

__all__ = ["with_metadata"]

logger = logging.getLogger(__name__)


def with_metadata(
    src: str | os.PathLike[str],
    dst: str | os.PathLike[str],
    name: str,
    record: Mapping[str, str],
    *,
    allow_overwrite: bool = False,
) -> Path:
    """Copy ``src`` to ``dst`` with the metadata record ``name`` set to ``record``; returns ``dst``.

    ``dst`` may be ``src`` (replaced atomically); another existing ``dst`` needs ``allow_overwrite``.
    Blocks until the copy is written (about the time it takes to read the file).

    Raises:
        DatasetError: ``src`` cannot be read. CaptureError: ``dst`` exists, or cannot be written.
    """
    src_p, dst_p = Path(src), Path(dst)
    in_place = dst_p.exists() and src_p.exists() and os.path.samefile(src_p, dst_p)
    if dst_p.exists() and not in_place and not allow_overwrite:
        raise CaptureError(f"{dst_p} exists; pass allow_overwrite=True (--force) or choose another path")
    tmp = dst_p.with_name(f".{dst_p.name}.{os.getpid()}.tmp")
    try:
        with src_p.open("rb") as fin, tmp.open("wb") as fout:
            reader = make_reader(fin)
            header = reader.get_header()
            summary = reader.get_summary()
            if summary is None:
                raise DatasetError(f"{src_p} has no summary; run 'flightkit capture recover' on it first")
            writer = Writer(fout, compression=CompressionType.ZSTD)
            writer.start(header.profile, header.library)
            schema_ids = {
                sid: writer.register_schema(s.name, s.encoding, s.data) for sid, s in sorted(summary.schemas.items())
            }
            channel_ids = {
                cid: writer.register_channel(
                    c.topic, c.message_encoding, schema_ids.get(c.schema_id, 0), dict(c.metadata)
                )
                for cid, c in sorted(summary.channels.items())
            }
            for _, channel, message in reader.iter_messages(log_time_order=True):
                writer.add_message(channel_ids[channel.id], message.log_time, message.data, message.publish_time,
                                   message.sequence)
            for m in reader.iter_metadata():
                if m.name != name:
                    writer.add_metadata(m.name, dict(m.metadata))
            writer.add_metadata(name, {str(k): str(v) for k, v in record.items()})
            writer.finish()
        os.replace(tmp, dst_p)
    except DatasetError:
        raise
    except OSError as exc:
        raise CaptureError(f"cannot write {dst_p}: {exc.strerror}; check the path and free space") from exc
    except Exception as exc:  # the mcap library raises several types for damaged files
        raise DatasetError(f"{src_p} cannot be copied ({exc}); the file may be damaged") from exc
    finally:
        if tmp.exists():
            tmp.unlink()
    logger.info("wrote %s with metadata record %r", dst_p, name)
    return dst_p
