"""``flightkit capture info|recover``: inspect and salvage recordings."""

from __future__ import annotations

import argparse
import json
from datetime import UTC, datetime
from typing import Any


def register(sub: Any) -> None:
    p = sub.add_parser("capture", help="inspect or recover MCAP recordings")
    cs = p.add_subparsers(dest="capture_command", metavar="SUBCOMMAND", required=True)
    info = cs.add_parser("info", help="streams, counts, rates, duration, gaps and time span of each stream")
    info.add_argument("recording", help="an .mcap file")
    info.add_argument("--gap-factor", type=float, default=3.0, help="a gap is a silence longer than this many periods")
    info.add_argument("--json", action="store_true", help="print JSON instead of a table")
    info.set_defaults(func=run_info)
    rec = cs.add_parser("recover", help="salvage every complete chunk of a crashed recording into a valid file")
    rec.add_argument("crashed", help="the damaged .mcap file")
    rec.add_argument("-o", "--output", required=True, help="the repaired .mcap file to write")
    rec.add_argument("--force", action="store_true", help="overwrite the output if it exists")
    rec.set_defaults(func=run_recover)


def _iso(stamp_ns: int) -> str:
    return datetime.fromtimestamp(stamp_ns / 1e9, tz=UTC).strftime("%H:%M:%S.%f")[:-3]


def run_info(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from capture.info import recording_info

    info = recording_info(args.recording, gap_factor=args.gap_factor)
    if args.json:
        print(
            json.dumps(
                {
                    "path": str(info.path),
                    "size_bytes": info.size_bytes,
                    "profile": info.profile,
                    "duration_s": info.duration_s,
                    "messages": info.messages,
                    "metadata": info.metadata,
                    "streams": [
                        {
                            "topic": s.topic,
                            "type": s.msgtype,
                            "count": s.count,
                            "bytes": s.bytes,
                            "rate_hz": s.rate_hz,
                            "first_ns": s.first_ns,
                            "last_ns": s.last_ns,
                            "max_gap_s": s.max_gap_s,
                            "gaps": len(s.gaps),
                            "missed_seq": s.missed_seq,
                        }
                        for s in info.streams
                    ],
                },
                indent=2,
            )
        )
        return 0
    console = Console()
    if not console.is_terminal:
        console = Console(width=160)
    console.print(
        f"[bold]{info.path}[/]  {info.size_bytes / 1e6:.1f} MB, profile {info.profile or '-'}, "
        f"{info.messages} messages, {info.duration_s:.2f} s"
    )
    t0 = info.start_ns
    table = Table(caption=f"times relative to the first message at {_iso(t0)} UTC")
    for col in ("topic", "type", "count", "rate Hz", "MB", "start s", "end s", "max gap s", "gaps", "missed"):
        text_col = col in ("topic", "type")
        table.add_column(col, justify="left" if text_col else "right", overflow="fold", no_wrap=not text_col)
    for s in info.streams:
        table.add_row(
            s.topic, s.msgtype, str(s.count), f"{s.rate_hz:.1f}", f"{s.bytes / 1e6:.2f}",
            f"{(s.first_ns - t0) / 1e9:.3f}", f"{(s.last_ns - t0) / 1e9:.3f}", f"{s.max_gap_s:.3f}",
            str(len(s.gaps)), str(s.missed_seq),
        )
    console.print(table)
    if info.metadata:
        console.print("metadata: " + ", ".join(sorted(info.metadata)))
    return 0


def run_recover(args: argparse.Namespace) -> int:
    from capture.mcapfile import recover

    report = recover(args.crashed, args.output, allow_overwrite=args.force)
    print(f"{args.output}: {report.summary()}")
    return 0
