"""Fly a TOML flight plan (circle, rectangle, lawnmower, ...) and plot it.

The same as ``flightkit fly PLAN --connect sim``, as a library call::

    python examples/fly_plan.py examples/rectangle.toml --speed 5
    python examples/fly_plan.py examples/lawnmower.toml --autopilot ardupilot --plot

Prints the summary (RMS and max tracking error per phase, faults); ``--plot`` writes the top
view and the error against time next to the flight log.
"""

from __future__ import annotations

import argparse
import asyncio
from pathlib import Path

from flightkit.apps.sim_session import fly_plan_in_sim
from trajectories.plan import load_plan
from trajectories.plots import plot_flight_log


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("plan", nargs="?", default=str(Path(__file__).with_name("circle.toml")))
    ap.add_argument("--autopilot", default="px4", choices=["px4", "ardupilot"])
    ap.add_argument("--backend", default="pymavlink", choices=["pymavlink", "mavsdk"])
    ap.add_argument("--speed", type=float, default=1.0, help="simulator speed")
    ap.add_argument("--log", default=None, help="flight log (default: flightlogs/<plan>-<time>.csv)")
    ap.add_argument("--plot", action="store_true", help="write PNG plots of the flight")
    args = ap.parse_args()

    plan = load_plan(args.plan)
    summary = asyncio.run(
        fly_plan_in_sim(
            plan,
            autopilot=args.autopilot,
            backend=args.backend,
            speed=args.speed,
            log_path=args.log,
            handle_signals=True,
        )
    )
    print(summary.format_table())
    if args.plot and summary.log_path:
        for path in plot_flight_log(summary.log_path):
            print(f"plot: {path}")
    return 0 if summary.outcome == "completed" else 1


if __name__ == "__main__":
    raise SystemExit(main())
