"""``flightkit report``: send the vehicle's pose to a mapping server over a serial port.

``flightkit report --port /dev/ttyACM0 --source flight.tum --rate 20`` replays a recorded
trajectory (TUM file, or a PoseStamped topic of an MCAP file) and reports it; ``--source
mocap`` or ``--source bus`` reports live poses from the lab's mocap source (config
``[mocap]``). The port is anything pyserial opens: /dev/tty*, rfc2217://, socket://, loop://.
Map frame, robot id and name come from the ``[report]`` table of ``--config``.
"""

from __future__ import annotations

import argparse
from typing import Any

__all__ = ["register", "run"]


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "report",
        help="report poses to a mapping server over serial/BLE",
        description="Report poses to a flightkit mapping server over a serial port, "
        "BLE UART dongle or TCP bridge.",
    )
    p.add_argument(
        "--port", help="serial port or URL (/dev/ttyACM0, socket://host:port, rfc2217://..., loop://)"
    )
    p.add_argument("--baud", type=int, help="baud rate (default 115200 or [report] baud)")
    p.add_argument("--source", default="mocap", help="bus, mocap, or a .tum/.txt/.mcap file (default mocap)")
    p.add_argument(
        "--topic",
        help="PoseStamped topic of an MCAP source (default: the only one), or a bus key with --source bus",
    )
    p.add_argument("--rate", type=float, help="pose updates per second (default 20 or [report] rate_hz)")
    p.add_argument("--speed", type=float, default=1.0, help="replay speed of a file source (default 1)")
    p.add_argument("--robot-id", type=int, help="robot id on the map (default [report] robot_id)")
    p.add_argument("--name", help="robot name on the map (default [report] name)")
    p.add_argument(
        "--config", metavar="TOML", help="config with a [report] table (and [mocap]/[bus] for live sources)"
    )
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import asyncio
    import sys

    from flightkit.apps.report import report_poses, reporter_config
    from flightkit.config import load_config

    cfg = reporter_config(
        args.config,
        {"port": args.port, "baud": args.baud, "rate_hz": args.rate, "robot_id": args.robot_id, "name": args.name},
    )
    lab = load_config(args.config) if args.config else load_config()
    out = asyncio.run(report_poses(cfg, args.source, lab, topic=args.topic, speed=args.speed, duration_s=args.duration))
    st = out.stats
    print(
        f"reported {out.offered} poses to {out.server} on {cfg.port}: {st.poses_sent} sent, "
        f"{st.poses_superseded} superseded, {st.retransmissions} retransmissions",
        file=sys.stderr,
    )
    return 0
