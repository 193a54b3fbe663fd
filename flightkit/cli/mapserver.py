"""``flightkit mapserver``: the reference mapping server.

``flightkit mapserver --port /dev/ttyACM0 [--port /dev/ttyACM1] --out maps/`` accepts
robots on each port, shows a live table, logs every event to ``maps/mapserver_log.jsonl``
and saves ``maps/map.png`` (tracks, robots, wall segments) periodically and at exit.
Navigation orders come from ``--orders FILE`` (``ROBOT X Y [Z] [HEADING_DEG]`` per line) or
``--order "ROBOT X Y"`` on the command line; they are delivered reliably once the robot is
connected.
"""

from __future__ import annotations

import argparse
from typing import Any

__all__ = ["register", "run"]


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "mapserver",
        help="run the reference mapping server",
        description="Accept robots reporting over serial/BLE, draw their tracks and segments, "
        "send navigation orders.",
    )
    p.add_argument(
        "--port", action="append", required=True, help="serial port or URL (repeat for several dongles)"
    )
    p.add_argument("--baud", type=int, default=115200, help="baud rate of every port (default 115200)")
    p.add_argument(
        "--out", default="mapserver", help="output folder for map.png and the log (default ./mapserver)"
    )
    p.add_argument(
        "--orders", metavar="FILE", help="navigation orders, one 'ROBOT X Y [Z] [HEADING_DEG]' per line"
    )
    p.add_argument("--order", action="append", default=[], metavar="'ROBOT X Y'", help="one navigation order")
    p.add_argument("--duration", type=float, help="stop after this many seconds (default: until Ctrl-C)")
    p.add_argument(
        "--map-every", type=float, default=5.0, metavar="S", help="save the map every S seconds (default 5)"
    )
    p.add_argument("--no-live", action="store_true", help="no live table (for logs and scripts)")
    p.set_defaults(func=run)


def _table(server: Any) -> Any:
    import math

    from rich.table import Table

    t = Table(title="flightkit mapserver", expand=False)
    for col in ("robot", "port", "state", "x", "y", "z", "heading", "poses", "segments", "orders", "age"):
        t.add_column(col, justify="right" if col not in ("robot", "port", "state") else "left")
    now = server.clock.monotonic_s()
    for r in sorted(server.robots(), key=lambda r: r.robot_id):
        p = r.pose
        age = now - r.last_seen_s if math.isfinite(r.last_seen_s) else math.nan
        t.add_row(
            r.label,
            r.port,
            "online" if r.online else "offline",
            *(f"{v:.2f}" for v in ((p.x, p.y, p.z) if p else (math.nan,) * 3)),
            f"{math.degrees(p.heading_rad):.0f}°" if p else "-",
            str(r.poses),
            str(len(r.segments)),
            f"{r.orders_acked}/{r.orders_sent}",
            f"{age:.1f}s",
        )
    for port, err in server.port_errors.items():
        t.add_row("-", port, f"[red]{err}[/red]")
    return t


def run(args: argparse.Namespace) -> int:
    import sys
    import time
    from pathlib import Path

    from flightkit.apps.report import MapServer, parse_orders
    from flightkit.errors import ConfigError

    orders = []
    if args.orders:
        try:
            text = Path(args.orders).read_text(encoding="utf-8")
        except OSError as exc:
            raise ConfigError(
                args.orders, "--orders", f"cannot read: {exc.strerror}", "check the path"
            ) from exc
        orders += parse_orders(text, args.orders)
    for i, line in enumerate(args.order):
        orders += parse_orders(line, f"--order #{i + 1}")

    server = MapServer(args.port, baud=args.baud, out_dir=args.out)
    end = time.monotonic() + args.duration if args.duration else float("inf")
    with server:
        server.queue_orders(orders)
        next_map = time.monotonic() + args.map_every
        try:
            if args.no_live:
                while time.monotonic() < end:
                    time.sleep(0.2)
                    if time.monotonic() >= next_map:
                        server.save_map()
                        next_map += args.map_every
            else:
                from rich.live import Live

                with Live(_table(server), refresh_per_second=4, transient=False) as live:
                    while time.monotonic() < end:
                        time.sleep(0.25)
                        live.update(_table(server))
                        if time.monotonic() >= next_map:
                            server.save_map()
                            next_map += args.map_every
        except KeyboardInterrupt:
            pass
        finally:
            png = server.save_map()
            print(f"map saved to {png}; log in {Path(args.out) / 'mapserver_log.jsonl'}", file=sys.stderr)
    return 0
