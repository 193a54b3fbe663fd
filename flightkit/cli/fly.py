"""``flightkit fly PLAN.toml``: fly a plan with the safety supervisor, a live status line and a summary.

``--connect sim`` (or ``--sim``) starts the simulated lab in this process and flies against it
over real UDP, with the simulator's mocap as the source (``flightkit.apps.sim_session``).
"""

from __future__ import annotations

import argparse
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

    from flightkit.apps.flight import Status, fly, lab_with_overrides, load_plan, plot_log
    from flightkit.config import load_config

    plan = load_plan(args.plan)
    sim = args.sim or args.connect == "sim"
    lab = lab_with_overrides(
        load_config(args.config) if args.config else load_config(),
        url=None if sim else args.connect,
        backend=args.backend,
        mocap_source=args.mocap,
        autopilot=args.autopilot,
    )
    tty = sys.stderr.isatty()

    def on_status(s: Status) -> None:
        line = s.line()
        if tty:
            print("\r\033[K" + line, end="", file=sys.stderr, flush=True)
        else:
            print(line, file=sys.stderr)

    summary = asyncio.run(
        fly(plan, lab, sim=sim, speed=args.speed, arm=args.arm, log_path=args.log, on_status=on_status,
            handle_signals=True)
    )
    if tty:
        print(file=sys.stderr)
    if args.json:
        print(summary.to_json())
    else:
        print(summary.format_table())
    if args.plot and summary.log_path:
        for p in plot_log(summary.log_path):
            print(f"plot: {p}")
    return 0 if summary.outcome == "completed" else 1
