"""``flightkit fly PLAN.toml``: fly a plan with the safety supervisor, a live status line and a summary."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from typing import Any

__all__ = ["register", "run"]


def register(subparsers: Any) -> None:
    p = subparsers.add_parser("fly", help="fly a TOML flight plan (circle, rectangle, lawnmower, ...)")
    p.add_argument("plan", help="plan TOML file, e.g. examples/circle.toml")
    p.add_argument("--config", default=None, help="lab config TOML (default: built-in defaults)")
    p.add_argument("--connect", default=None, help="MAVLink connection string (overrides link.url)")
    p.add_argument("--arm", action="store_true", help="arm and switch mode from the script (default: the pilot does)")
    p.add_argument("--mocap", choices=["bus", "motioncapture"], default=None, help="mocap source (overrides mocap.source)")
    p.add_argument("--backend", choices=["pymavlink", "mavsdk"], default=None, help="MAVLink library")
    p.add_argument("--log", default=None, help="flight log file (default: flightlogs/<plan>-<time>.csv)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--plot", action="store_true", help="write PNG plots of the flight log at the end")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import asyncio

    from flightkit.config import LinkBackend, MocapSourceKind, load_config
    from trajectories.plan import load_plan
    from trajectories.runner import Status, fly_plan

    plan = load_plan(args.plan)
    lab = load_config(args.config) if args.config else load_config()
    link = lab.link
    if args.connect:
        link = dataclasses.replace(link, url=args.connect)
    if args.backend:
        link = dataclasses.replace(link, backend=LinkBackend(args.backend))
    mocap = lab.mocap
    if args.mocap:
        mocap = dataclasses.replace(mocap, source=MocapSourceKind(args.mocap))
    lab = dataclasses.replace(lab, link=link, mocap=mocap)

    tty = sys.stderr.isatty()

    def on_status(s: Status) -> None:
        line = s.line()
        if tty:
            print("\r\033[K" + line, end="", file=sys.stderr, flush=True)
        else:
            print(line, file=sys.stderr)

    summary = asyncio.run(fly_plan(plan, lab, arm=args.arm, log_path=args.log, on_status=on_status,
                                   handle_signals=True))
    if tty:
        print(file=sys.stderr)
    if args.json:
        print(summary.to_json())
    else:
        print(summary.format_table())
    if args.plot and summary.log_path:
        from trajectories.plots import plot_flight_log

        for p in plot_flight_log(summary.log_path):
            print(f"plot: {p}")
    return 0 if summary.outcome == "completed" else 1
