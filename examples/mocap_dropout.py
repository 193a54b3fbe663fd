"""See the safety supervisor react to a mocap dropout in the simulator.

Flies a hold at 1 m, blacks out the mocap stream for ``--dropout`` seconds and prints what
the supervisor did: under 1 s the vehicle holds (zero velocity) and resumes; longer, it
hands over to the autopilot's LAND mode::

    python examples/mocap_dropout.py --dropout 0.5     # hold, then resume
    python examples/mocap_dropout.py --dropout 2.0     # land
"""

from __future__ import annotations

import argparse
import asyncio

from flightkit.apps.sim_session import sim_session
from flightkit.errors import SafetyAbort
from trajectories.script import Flight


async def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dropout", type=float, default=0.5, help="seconds without mocap")
    ap.add_argument("--autopilot", default="px4", choices=["px4", "ardupilot"])
    ap.add_argument("--speed", type=float, default=1.0, help="simulator speed")
    args = ap.parse_args()

    async with sim_session(autopilot=args.autopilot, speed=args.speed) as sim:
        async with Flight(
            sim.config, arm=True, link=sim.link, mocap=sim.mocap, clock=sim.clock, name="dropout"
        ) as flight:
            await flight.takeoff(1.0)
            await flight.hold(1.0)

            async def blackout() -> None:
                await sim.clock.sleep(1.0)
                print(f"mocap off for {args.dropout:.1f} s")
                sim.mocap.drop_for(args.dropout)

            task = asyncio.ensure_future(blackout())
            try:
                await flight.hold(3.0 + args.dropout)
                print("held through the dropout; landing")
                await flight.land()
            except SafetyAbort as exc:
                print(f"the supervisor ended the flight: {exc.reason}: {exc}")
            await task
        print(flight.summary.format_table())
        print(
            f"vehicle armed: {sim.lab.autopilot.armed}, mode {sim.lab.autopilot.mode.value}, "
            f"height {sim.lab.truth().pos_enu_m[2]:.2f} m"
        )


if __name__ == "__main__":
    asyncio.run(main())
