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
    p.add_argument("plan", help="plan TOML file, e.g. examples/circle.toml, or a fleet plan (fleet_circle.toml)")
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
        "--allow-hover-on-companion-loss",
        action="store_true",
        help="arm even though the autopilot would hover armed until its battery runs out if flightkit stopped "
        "(its failsafe parameters say so; same as [safety] allow_hover_on_companion_loss = true)",
    )
    p.add_argument(
        "--mocap",
        choices=["bus", "motioncapture"],
        default=None,
        help="mocap source (overrides mocap.source)",
    )
    p.add_argument("--backend", choices=["pymavlink", "mavsdk"], default=None, help="MAVLink library")
    p.add_argument(
        "--log", default=None,
        help="flight log file (default: flightlogs/<plan>-<time>.csv; a fleet: a folder, flightlogs/<plan>-<time>/)",
    )
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--plot", action="store_true", help="write PNG plots of the flight log at the end")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import asyncio

    from flightkit.apps.fleet import is_fleet_plan
    from flightkit.apps.flight import Status, fly, lab_with_overrides, load_plan, plot_log
    from flightkit.config import load_config
    from flightkit.settings import load_toml

    if is_fleet_plan(load_toml(args.plan)):
        return _run_fleet(args)
    plan = load_plan(args.plan)
    if args.allow_hover_on_companion_loss:
        plan = plan.with_safety(allow_hover_on_companion_loss=True)
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


def _run_fleet(args: argparse.Namespace) -> int:
    """A fleet plan: one status line per vehicle, a summary table per vehicle and the fleet's figures."""
    import asyncio
    import dataclasses
    import time
    from pathlib import Path

    from flightkit.apps.fleet import fly_fleet, load_fleet_plan
    from flightkit.apps.flight import Status, lab_with_overrides
    from flightkit.config import load_config

    fplan = load_fleet_plan(args.plan)
    if args.allow_hover_on_companion_loss:
        fplan = dataclasses.replace(fplan, plan=fplan.plan.with_safety(allow_hover_on_companion_loss=True))
    sim = args.sim or args.connect == "sim"
    lab = lab_with_overrides(
        load_config(args.config) if args.config else load_config(),
        backend=args.backend,
        mocap_source=args.mocap,
        autopilot=args.autopilot,
    )
    shown: dict[str, float] = {}

    def on_status(name: str, s: Status) -> None:
        now = time.monotonic()
        if now - shown.get(name, 0.0) >= 1.0:
            shown[name] = now
            print(f"{name:>6}  {s.line()}", file=sys.stderr, flush=True)

    log_dir = args.log or str(
        Path(fplan.plan.settings.log_dir or "flightlogs") / f"{fplan.name}-{time.strftime('%Y%m%d-%H%M%S')}"
    )
    result = asyncio.run(
        fly_fleet(fplan, lab, sim=sim, speed=args.speed, arm=args.arm, log_dir=log_dir, on_status=on_status)
    )
    if args.json:
        import json

        print(
            json.dumps(
                {
                    "plan": result.name,
                    "outcome": result.outcome,
                    "min_separation_m": result.min_separation_m,
                    "start_skew_s": result.start_skew_s,
                    "fleet_faults": [{"time_s": t, "who": w, "message": m} for t, w, m in result.faults],
                    "vehicles": {n: s.to_dict() for n, s in result.summaries.items()},
                }
            )
        )
    else:
        print(result.format_table())
    return 0 if result.outcome == "completed" else 1
