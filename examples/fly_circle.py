"""Fly a circle with the Python scripting API (``trajectories.script.Flight``).

Take off to 1.5 m, hold, two laps of a 1 m circle looking inward, come back to the centre,
land. Against the in-process simulator by default::

    python examples/fly_circle.py                  # simulated PX4, real time
    python examples/fly_circle.py --speed 5        # five times faster
    python examples/fly_circle.py --config lab.toml --arm   # a real vehicle (the script arms it)

Without ``--arm`` on a real vehicle the script waits for the pilot to arm and switch to
OFFBOARD/GUIDED from the transmitter.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import math

from flightkit.apps.sim_session import sim_session
from flightkit.config import LabConfig, load_config
from trajectories.patterns import Circle
from trajectories.script import Flight


async def fly(flight: Flight, laps: int, period_s: float, hold_s: float) -> None:
    await flight.takeoff(1.5)  # blocks until at 1.5 m
    await flight.hold(hold_s)  # blocks hold_s seconds
    await flight.fly(Circle(radius_m=1.0, period_s=period_s, height_m=1.5), laps=laps)  # blocks until done
    await flight.goto((0.0, 0.0, 1.5), yaw_rad=0.0)  # blocks until there
    await flight.land()  # blocks until disarmed


async def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", help="lab config of a real vehicle (default: the simulator)")
    ap.add_argument("--arm", action="store_true", help="arm from the script (real vehicle)")
    ap.add_argument("--autopilot", default="px4", choices=["px4", "ardupilot"], help="simulated autopilot")
    ap.add_argument("--speed", type=float, default=1.0, help="simulator speed")
    ap.add_argument("--laps", type=int, default=2)
    ap.add_argument("--period", type=float, default=40.0, help="seconds per lap")
    ap.add_argument("--hold", type=float, default=5.0, help="seconds to hold before the circle")
    args = ap.parse_args()

    if args.config:
        lab = load_config(args.config)
        async with Flight(lab, arm=args.arm, name="circle") as flight:
            await fly(flight, args.laps, args.period, args.hold)
    else:
        async with sim_session(LabConfig(), autopilot=args.autopilot, speed=args.speed) as sim:
            async with Flight(
                sim.config, arm=True, link=sim.link, mocap=sim.mocap, clock=sim.clock, name="circle"
            ) as flight:
                await fly(flight, args.laps, args.period, args.hold)
    print(flight.summary.format_table())
    pattern = flight.summary.phase("pattern")
    print(
        f"circle: RMS {pattern.rms_error_m * 1000:.1f} mm, max {pattern.max_error_m * 1000:.1f} mm, "
        f"{math.degrees(2 * math.pi * flight.summary.laps_completed):.0f} deg flown"
    )


if __name__ == "__main__":
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(main())
