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


def _report_config(args: argparse.Namespace) -> Any:
    import dataclasses

    from estimation.report.reporter import ReporterConfig
    from flightkit.config import load_section, load_toml
    from flightkit.errors import ConfigError

    cfg = ReporterConfig()
    if args.config:
        table = load_toml(args.config).get("report", {})
        cfg = load_section(ReporterConfig, table, path=args.config, prefix="report")
    changes: dict[str, Any] = {}
    for arg, key in (
        ("port", "port"),
        ("baud", "baud"),
        ("rate", "rate_hz"),
        ("robot_id", "robot_id"),
        ("name", "name"),
    ):
        if getattr(args, arg) is not None:
            changes[key] = getattr(args, arg)
    cfg = dataclasses.replace(cfg, **changes)
    if not cfg.port:
        raise ConfigError(
            args.config or "<command line>", "report.port", "no serial port given", "pass --port PORT"
        )
    if not 1 <= cfg.robot_id <= 254:
        raise ConfigError(
            "<command line>", "report.robot_id", f"{cfg.robot_id} is out of range", "use 1..254"
        )
    if not cfg.rate_hz > 0:
        raise ConfigError(
            "<command line>", "report.rate_hz", f"{cfg.rate_hz} is not positive", "pass --rate 20"
        )
    return cfg


def run(args: argparse.Namespace) -> int:
    import asyncio
    import sys
    from pathlib import Path

    from estimation.report.reporter import (
        Reporter,
        read_mcap_samples,
        read_tum_samples,
        replay_samples,
    )
    from flightkit.clock import WallClock
    from flightkit.errors import ConfigError

    cfg = _report_config(args)
    clock = WallClock()
    source = args.source
    samples = []
    if source not in ("bus", "mocap"):
        path = Path(source)
        if not path.exists():
            raise ConfigError(
                "<command line>", "--source", f"{source!r} is not bus, mocap or a file", "check the path"
            )
        samples = read_mcap_samples(path, args.topic) if path.suffix == ".mcap" else read_tum_samples(path)

    async def main() -> int:
        async with Reporter.from_config(cfg, clock=clock) as rep:
            if source in ("bus", "mocap"):
                n = await _run_live(rep, source, args, cfg, clock)
            else:
                await asyncio.to_thread(rep.wait_connected, 10.0)
                n = await rep.run(
                    replay_samples(samples, clock, speed=args.speed), cfg.rate_hz, until_s=args.duration
                )
                await asyncio.to_thread(rep.wait_delivered, 5.0)
            st = rep.stats
            print(
                f"reported {n} poses to {rep.endpoint.session.peer_name or 'the server'} on {cfg.port}: "
                f"{st.poses_sent} sent, {st.poses_superseded} superseded, "
                f"{st.retransmissions} retransmissions",
                file=sys.stderr,
            )
        return 0

    return asyncio.run(main())


async def _run_live(rep: Any, source: str, args: argparse.Namespace, cfg: Any, clock: Any) -> int:
    """Report live poses: ``mocap`` = the lab's mocap source as configured ([mocap]); ``bus`` =
    a PoseStamped stream on the bus (``--topic KEY``, e.g. VO odometry), or mocap on the bus."""
    import dataclasses

    from estimation.report.reporter import bus_pose_samples, mocap_samples
    from flightkit.bus.keys import Keys
    from flightkit.config import MocapSourceKind, load_config
    from flightkit.mocap import open_mocap

    lab = load_config(args.config) if args.config else load_config()
    keys = Keys(lab.vehicle.namespace)
    if source == "bus" and args.topic:
        from flightkit.bus.session import open_session

        session = open_session(lab.bus)
        try:
            return int(await rep.run(bus_pose_samples(session, args.topic), cfg.rate_hz, until_s=args.duration))
        finally:
            session.close()
    mocap_cfg = lab.mocap
    if source == "bus":
        mocap_cfg = dataclasses.replace(mocap_cfg, source=MocapSourceKind.BUS)
    async with open_mocap(mocap_cfg, lab.bus, keys, clock) as mocap:
        return int(await rep.run(mocap_samples(mocap, lab.mocap.body), cfg.rate_hz, until_s=args.duration))
