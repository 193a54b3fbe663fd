"""Flying a fleet plan from the command line or a notebook: the lab's vehicles, or a simulated fleet.

``flightkit fly FLEET.toml`` calls :func:`fly_fleet`::

    result = asyncio.run(fly_fleet(load_fleet_plan("examples/fleet_circle.toml"), lab, sim=True))
    print(result.format_table())
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

from flightkit.config import FleetVehicleConfig, LabConfig
from trajectories.fleet_plan import FleetPlan, FleetResult, fly_fleet_plan, is_fleet_plan, load_fleet_plan
from trajectories.status import Status

__all__ = ["FleetPlan", "FleetResult", "fly_fleet", "is_fleet_plan", "load_fleet_plan", "sim_fleet_config"]


def sim_fleet_config(fplan: FleetPlan, lab: LabConfig) -> LabConfig:
    """``lab`` with one simulated vehicle per vehicle of the plan (unless the lab lists them),
    each standing on the floor under its pattern's start point, as a lab would place them."""
    if lab.vehicles:
        return lab
    patterns = fplan.build_patterns()
    entries = []
    for name, pattern in patterns.items():
        start = pattern.reference(0.0).pos_m
        entries.append(FleetVehicleConfig(name=name, start_m=(start[0], start[1], 0.0)))
    return dataclasses.replace(lab, vehicles=tuple(entries))


async def fly_fleet(
    fplan: FleetPlan,
    lab: LabConfig,
    *,
    sim: bool = False,
    speed: float | None = None,
    arm: bool = False,
    log_dir: str | Path | None = None,
    on_status: Callable[[str, Status], None] | None = None,
) -> FleetResult:
    """Fly ``fplan`` on the lab's vehicles, or (``sim``) on a simulated fleet in this process (the
    script arms there); blocks until every vehicle has landed.

    Raises:
        PlanError: references too close or vehicles missing (nothing armed). LinkError,
        MocapBodyMissing, SafetyAbort (preflight): a vehicle is not ready.
    """
    if not sim:
        return await fly_fleet_plan(fplan, lab, arm=arm, log_dir=log_dir, on_status=on_status)
    from flightkit.apps.sim_session import sim_lab_config
    from flightkit.sim.fleet import SimFleet
    from flightkit.sim.mocap import SimMocapSource

    fplan.check_separation()  # before anything starts
    cfg = sim_fleet_config(fplan, sim_lab_config(lab, speed=speed))
    fleet = SimFleet(cfg, ready_after_s=0.0).start()
    try:
        mocap = SimMocapSource(system=fleet.mocap, T_world_mocap=cfg.mocap.T_world_mocap.to_transform())
        async with mocap:
            return await fly_fleet_plan(
                fplan, fleet.client_config(), clock=fleet.clock, mocap=mocap, arm=True, log_dir=log_dir,
                on_status=on_status,
            )
    finally:
        fleet.stop()
