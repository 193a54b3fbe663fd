"""``flightkit capture info|recover|calibrate|publish``: inspect, salvage and calibrate recordings, publish capture
sources."""

from __future__ import annotations

import argparse
import json
import logging
import math
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from flightkit.cli import calibrate as calibrate_cli

logger = logging.getLogger(__name__)


def register(sub: Any) -> None:
    p = sub.add_parser("capture", help="inspect or recover MCAP recordings")
    cs = p.add_subparsers(dest="capture_command", metavar="SUBCOMMAND", required=True)
    info = cs.add_parser("info", help="streams, counts, rates, duration, gaps and time span of each stream, "
                         "and the cameras' rolling-shutter readouts")
    info.add_argument("recording", help="an .mcap file")
    info.add_argument("--gap-factor", type=float, default=3.0, help="a gap is a silence longer than this many periods")
    info.add_argument("--json", action="store_true", help="print JSON instead of a table")
    info.set_defaults(func=run_info)
    rec = cs.add_parser("recover", help="salvage every complete chunk of a crashed recording into a valid file")
    rec.add_argument("crashed", help="the damaged .mcap file")
    rec.add_argument("-o", "--output", required=True, help="the repaired .mcap file to write")
    rec.add_argument("--force", action="store_true", help="overwrite the output if it exists")
    rec.set_defaults(func=run_recover)
    cal = cs.add_parser(
        "calibrate",
        help="calibrate a recording (time offset, hand-eye) and store the result: flightkit calibrate WHAT ...",
        description="The same command as 'flightkit calibrate time|handeye'; --write REC.mcap stores the result "
        "in the recording's metadata, --write FILE.json as a calibration file (docs/calibration.md).",
    )
    cal.add_argument("what", choices=("time", "handeye"), help="what to calibrate")
    calibrate_cli.add_options(cal)
    cal.set_defaults(func=calibrate_cli.run)
    pub = cs.add_parser(
        "publish",
        help="publish a camera, video, RealSense, recording/dataset replay or mocap system on the bus",
        description="SOURCE is camera:0 | camera:/dev/video2 | video:FILE | realsense | replay:RUN.mcap | "
        "replay:DATASET_DIR | mocap (the [mocap] system of --config). Runs until the source ends, "
        "--duration passes, or Ctrl-C/SIGTERM.",
    )
    pub.add_argument("source", metavar="SOURCE", help="what to publish (see above)")
    pub.add_argument("--config", metavar="LAB.toml", help="lab config (namespace, bus endpoints, [capture], [mocap])")
    pub.add_argument("--speed", type=float, default=1.0, metavar="X",
                     help="replay and video files: X times the recorded rate (inf: as fast as the bus takes it)")
    pub.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (wall clock)")
    pub.add_argument("--calibration", metavar="FILE",
                     help="camera calibration (JSON/YAML: fx, fy, cx, cy, width, height, dist)")
    pub.add_argument("--format", choices=("bgr8", "rgb8", "jpeg"), default="bgr8",
                     help="camera/video colour format on the bus (jpeg: CompressedImage only)")
    pub.add_argument("--jpeg-quality", type=int, metavar="Q",
                     help="JPEG quality (default [capture] jpeg_quality, or 90 with --format jpeg)")
    pub.add_argument("--rate", type=float, metavar="HZ", help="camera: frame rate to ask for; video: playback rate")
    pub.add_argument("--loop", action="store_true", help="video files: start again at the end")
    pub.add_argument("--name", default="color", help="camera name in the keys (<ns>/camera/<name>/image)")
    pub.add_argument("--key-prefix", default="", metavar="P", help="replay:RUN.mcap: publish under P/<topic>")
    pub.add_argument("--gt-body", default="groundtruth", metavar="NAME",
                     help="replay:DATASET_DIR: ground truth on <ns>/mocap/NAME/pose")
    pub.add_argument("--wait-subscribers", type=float, default=0.0, metavar="S",
                     help="wait up to S seconds for a subscriber (e.g. a recorder) before publishing")
    pub.add_argument("--connect", nargs="+", metavar="ENDPOINT", help="Zenoh endpoints to connect to")
    pub.add_argument("--listen", nargs="+", metavar="ENDPOINT", help="Zenoh endpoints to listen on")
    pub.set_defaults(func=run_publish)


def _iso(stamp_ns: int) -> str:
    return datetime.fromtimestamp(stamp_ns / 1e9, tz=UTC).strftime("%H:%M:%S.%f")[:-3]


def run_info(args: argparse.Namespace) -> int:
    """``flightkit capture info``: returns the exit code."""
    print_info(args.recording, gap_factor=args.gap_factor, as_json=args.json)
    return 0


def print_info(recording: str | Path, *, gap_factor: float = 3.0, as_json: bool = False) -> None:
    """Print what a recording holds: a table per vehicle namespace (or JSON)."""
    from rich.console import Console
    from rich.table import Table

    from flightkit.apps.capture import recording_info

    info = recording_info(recording, gap_factor=gap_factor)
    if as_json:
        print(
            json.dumps(
                {
                    "path": str(info.path),
                    "size_bytes": info.size_bytes,
                    "profile": info.profile,
                    "duration_s": info.duration_s,
                    "messages": info.messages,
                    "metadata": info.metadata,
                    "readouts_s": {k: None if math.isnan(v) else v for k, v in info.readouts_s.items()},
                    "vehicles": sorted(info.by_vehicle()),
                    "streams": [
                        {
                            "topic": s.topic,
                            "vehicle": s.namespace,
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
        return
    console = Console()
    if not console.is_terminal:
        console = Console(width=160)
    console.print(
        f"[bold]{info.path}[/]  {info.size_bytes / 1e6:.1f} MB, profile {info.profile or '-'}, "
        f"{info.messages} messages, {info.duration_s:.2f} s"
    )
    t0 = info.start_ns
    for vehicle, streams in info.by_vehicle().items():
        title = f"vehicle {vehicle}" if vehicle else "no namespace"
        table = Table(title=title, caption=f"times relative to the first message at {_iso(t0)} UTC")
        for col in ("topic", "type", "count", "rate Hz", "MB", "start s", "end s", "max gap s", "gaps", "missed"):
            text_col = col in ("topic", "type")
            table.add_column(col, justify="left" if text_col else "right", overflow="fold", no_wrap=not text_col)
        for s in streams:
            table.add_row(
                s.topic, s.msgtype, str(s.count), f"{s.rate_hz:.1f}", f"{s.bytes / 1e6:.2f}",
                f"{(s.first_ns - t0) / 1e9:.3f}", f"{(s.last_ns - t0) / 1e9:.3f}", f"{s.max_gap_s:.3f}",
                str(len(s.gaps)), str(s.missed_seq),
            )
        console.print(table)
    for topic, readout in sorted(info.readouts_s.items()):
        what = "malformed (see its calibration.<camera> record)" if math.isnan(readout) else f"{readout * 1e3:.4g} ms"
        console.print(f"rolling shutter: {topic.rsplit('/', 1)[0]} readout {what}", highlight=False)
    if info.metadata:
        console.print("metadata: " + ", ".join(sorted(info.metadata)))


def run_recover(args: argparse.Namespace) -> int:
    from flightkit.apps.capture import recover

    report = recover(args.crashed, args.output, allow_overwrite=args.force)
    print(f"{args.output}: {report.summary()}")
    return 0


# --------------------------------------------------------------------------- publish


def _wait_loop(source: Any, args: argparse.Namespace, stop: Any, console: Any) -> str:
    import time

    t0 = time.monotonic()
    deadline = t0 + args.duration if args.duration else None
    last = -1
    while True:
        if stop.is_set():
            return "signal"
        if source.finished:
            return "end of source"
        if deadline is not None and time.monotonic() >= deadline:
            return "duration"
        stop.wait(0.5 if deadline is None else max(0.0, min(0.5, deadline - time.monotonic())))
        if source.published != last and console.is_terminal:
            last = source.published
            rate = last / max(1e-9, time.monotonic() - t0)
            console.print(f"\r{last} {source.what} ({rate:.1f}/s)", end="")


def run_publish(args: argparse.Namespace) -> int:
    import signal
    import threading
    import time

    from rich.console import Console

    from flightkit.apps.capture import PublishOptions, open_publisher, parse_source
    from flightkit.bus.session import open_session
    from flightkit.config import load_config

    kind, arg = parse_source(args.source)
    lab = load_config(args.config) if args.config else load_config()
    bus_cfg = lab.bus.with_endpoints(args.connect, args.listen)
    stop = threading.Event()

    def on_signal(signum: int, _frame: Any) -> None:
        stop.set()

    console = Console(stderr=True)
    if kind == "mocap":
        return _run_mocap(args, lab, bus_cfg, console)
    opts = PublishOptions(
        speed=args.speed, calibration=args.calibration, color_format=args.format, jpeg_quality=args.jpeg_quality,
        rate_hz=args.rate, loop=args.loop, name=args.name, key_prefix=args.key_prefix, gt_body=args.gt_body,
    )
    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        with open_session(bus_cfg) as session:
            source = open_publisher(kind, arg, lab, session, opts)
            console.print(f"publishing {args.source} on {', '.join(source.keys)} (Ctrl-C to stop)")
            t0 = time.monotonic()
            try:
                wait_until = t0 + args.wait_subscribers
                while not getattr(source, "has_subscribers", True) and time.monotonic() < wait_until:
                    if stop.wait(0.01):
                        break
                source.start()
                why = _wait_loop(source, args, stop, console)
            finally:
                source.stop()
                time.sleep(0.2)  # let the last samples leave before the session closes
            elapsed = time.monotonic() - t0
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    if console.is_terminal:
        console.print()
    print(f"published {source.published} {source.what} in {elapsed:.1f} s ({why})")
    if source.error is not None:
        console.print(f"[red]flightkit: error: {source.error}[/]")
        return 1
    return 0


def _run_mocap(args: argparse.Namespace, lab: Any, bus_cfg: Any, console: Any) -> int:
    import asyncio
    import signal

    from flightkit.apps.capture import bridge_mocap

    async def bridge_main() -> tuple[int, str]:
        loop = asyncio.get_running_loop()
        task = asyncio.current_task()
        why = "end of source"

        def on_signal() -> None:
            nonlocal why
            why = "signal"
            if task is not None:
                task.cancel()

        for s in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(s, on_signal)
        try:
            published = await bridge_mocap(lab, bus_cfg, args.duration, on_start=console.print)
            if args.duration and why != "signal":
                why = "duration"
            return published, why
        finally:
            for s in (signal.SIGINT, signal.SIGTERM):
                loop.remove_signal_handler(s)

    published, why = asyncio.run(bridge_main())
    print(f"published {published} poses ({why})")
    return 0
