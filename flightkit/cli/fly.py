"""``flightkit fly PLAN.toml``: fly a plan with the safety supervisor, a live status line and a summary.

``--connect sim`` (or ``--sim``) starts the simulated lab in this process and flies against it
over real UDP, with the simulator's mocap as the source (``trajectories.simulated``).
"""

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
    p.add_argument(
        "--connect",
        default=None,
        help="MAVLink connection string (overrides link.url), or 'sim' for the in-process simulator",
    )
    p.add_argument("--sim", action="store_true", help="same as --connect sim")
    p.add_argument(
        "--speed",
        type=float,
        default=None,
        help="simulator speed, simulated seconds per wall second (default: sim.speed)",
    )
    p.add_argument(
        "--autopilot",
        choices=["px4", "ardupilot"],
        default=None,
        help="autopilot (overrides vehicle.autopilot; with the simulator: its personality)",
    )
    p.add_argument(
        "--arm", action="store_true", help="arm and switch mode from the script (default: the pilot does)"
    )
    p.add_argument(
        "--mocap",
        choices=["bus", "motioncapture"],
        default=None,
        help="mocap source (overrides mocap.source)",
    )
    p.add_argument("--backend", choices=["pymavlink", "mavsdk"], default=None, help="MAVLink library")
    p.add_argument("--log", default=None, help="flight log file (default: flightlogs/<plan>-<time>.csv)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--plot", action="store_true", help="write PNG plots of the flight log at the end")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import asyncio

    from flightkit.config import Autopilot, LinkBackend, MocapSourceKind, load_config
    from trajectories.plan import load_plan
    from trajectories.runner import Status, fly_plan

    plan = load_plan(args.plan)
    lab = load_config(args.config) if args.config else load_config()
    sim = args.sim or args.connect == "sim"
    link = lab.link
    if args.connect and not sim:
        link = dataclasses.replace(link, url=args.connect)
    if args.backend:
        link = dataclasses.replace(link, backend=LinkBackend(args.backend))
    mocap = lab.mocap
    if args.mocap:
        mocap = dataclasses.replace(mocap, source=MocapSourceKind(args.mocap))
    lab = dataclasses.replace(lab, link=link, mocap=mocap)
    if args.autopilot:
        lab = dataclasses.replace(
            lab, vehicle=dataclasses.replace(lab.vehicle, autopilot=Autopilot(args.autopilot))
        )

    tty = sys.stderr.isatty()

    def on_status(s: Status) -> None:
        line = s.line()
        if tty:
            print("\r\033[K" + line, end="", file=sys.stderr, flush=True)
        else:
            print(line, file=sys.stderr)

    if sim:
        from trajectories.simulated import fly_plan_in_sim

        # nobody holds a transmitter in the simulator: the script arms
        flight = fly_plan_in_sim(
            plan, lab, speed=args.speed, arm=True, log_path=args.log, on_status=on_status, handle_signals=True
        )
    else:
        flight = fly_plan(
            plan, lab, arm=args.arm, log_path=args.log, on_status=on_status, handle_signals=True
        )
    summary = asyncio.run(flight)
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
