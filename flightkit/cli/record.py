"""``flightkit record``: record bus streams to an MCAP file, with a live display and a final report."""

from __future__ import annotations

import argparse
from typing import Any


def register(sub: Any) -> None:
    p = sub.add_parser(
        "record",
        help="record bus streams (camera, mocap, tf, ...) to an MCAP file",
        description="Subscribe to key expressions and write every stream as an MCAP channel (ROS 2 profile, "
        "cdr payloads as published). Ctrl-C or SIGTERM finish the file cleanly.",
    )
    p.add_argument("-o", "--output", required=True, help="the .mcap file to write (RUN.mcap)")
    p.add_argument("--topics", nargs="+", metavar="PATTERN", help="key expressions (default: <namespace>/**)")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (wall clock)")
    split = p.add_mutually_exclusive_group()
    split.add_argument("--split-size", type=float, metavar="MB", help="start a new file every MB megabytes")
    split.add_argument("--split-duration", type=float, metavar="S", help="start a new file every S seconds")
    p.add_argument(
        "--compression", choices=("zstd", "lz4", "none"), help="chunk compression (default from config: zstd)"
    )
    p.add_argument("--force", action="store_true", help="overwrite existing output")
    p.add_argument("--config", metavar="LAB.toml", help="lab config (namespace, bus endpoints, metadata)")
    p.add_argument(
        "--connect", nargs="+", metavar="ENDPOINT", help="Zenoh endpoints to connect to, e.g. tcp/10.0.0.2:7447"
    )
    p.add_argument("--listen", nargs="+", metavar="ENDPOINT", help="Zenoh endpoints to listen on")
    p.add_argument("--quiet", action="store_true", help="no live display (the final report is still printed)")
    p.set_defaults(func=run)


def _table(rows: dict[str, Any], prev: dict[str, Any], dt_s: float, final: bool) -> Any:
    from rich.table import Table

    t = Table(title="recorded" if final else None, expand=False)
    for col in ("stream", "type", "count", "rate Hz", "MB/s" if not final else "MB", "missed", "dropped", "max gap s"):
        t.add_column(col, justify="left" if col in ("stream", "type") else "right")
    for topic in sorted(rows):
        st = rows[topic]
        old = prev.get(topic)
        if final:
            rate, bw = st.rate_hz, st.bytes / 1e6
        else:
            dc = st.count - (old.count if old else 0)
            db = st.bytes - (old.bytes if old else 0)
            rate, bw = (dc / dt_s, db / dt_s / 1e6) if dt_s > 0 else (0.0, 0.0)
        t.add_row(
            topic,
            st.msgtype.split("/")[-1],
            str(st.count),
            f"{rate:.1f}",
            f"{bw:.2f}",
            f"[red]{st.missed}[/]" if st.missed else "0",
            f"[red]{st.dropped}[/]" if st.dropped else "0",
            f"{st.max_gap_ns / 1e9:.3f}",
        )
    return t


def run(args: argparse.Namespace) -> int:
    import signal
    import threading
    import time

    from rich.console import Console
    from rich.live import Live

    from flightkit.apps.capture import start_recording
    from flightkit.config import load_config

    lab = load_config(args.config) if args.config else load_config()
    # A full disk or file-size limit must give EFBIG (handled: the file is closed cleanly), not kill us.
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    stop = threading.Event()
    why = {"reason": "done"}

    def on_signal(signum: int, _frame: Any) -> None:
        why["reason"] = signal.Signals(signum).name
        stop.set()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    console = Console(stderr=True)
    out = Console()
    if not out.is_terminal:
        out = Console(width=160)
    try:
        rec = start_recording(
            args.output,
            bus_cfg=lab.bus.with_endpoints(args.connect, args.listen),
            topics=args.topics,
            lab_cfg=lab,
            compression=args.compression,
            allow_overwrite=args.force,
            split_size_mb=args.split_size,
            split_duration_s=args.split_duration,
        )
        console.print(f"recording {', '.join(rec.topics)} to {args.output} (Ctrl-C to stop)")
        t_start = time.monotonic()
        deadline = t_start + args.duration if args.duration else None
        prev: dict[str, Any] = {}
        t_prev = t_start
        live = Live(console=console, refresh_per_second=2, transient=True) if not args.quiet else None
        try:
            if live is not None:
                live.start()
            while not stop.is_set() and not rec.stopped:
                if deadline is not None and time.monotonic() >= deadline:
                    break
                stop.wait(0.5 if deadline is None else max(0.0, min(0.5, deadline - time.monotonic())))
                if live is not None:
                    now = time.monotonic()
                    snap = rec.snapshot()
                    live.update(_table(snap, prev, now - t_prev, final=False))
                    prev, t_prev = snap, now
        finally:
            if live is not None:
                live.stop()
            report = rec.stop()
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    elapsed = time.monotonic() - t_start
    out.print(_table(report.streams, {}, elapsed, final=True))
    files = ", ".join(str(f) for f in report.files)
    out.print(
        f"{report.messages} messages in {elapsed:.1f} s to {files}; missed {report.missed}, dropped {report.dropped}"
        + (f" (stopped by {why['reason']})" if why["reason"] != "done" else "")
    )
    if report.error:
        console.print(f"[red]flightkit: error: {report.error}[/]")
        return 1
    return 0
