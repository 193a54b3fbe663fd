"""Flying against the simulated lab in-process: one call sets up the lab, the link and mocap.

:func:`sim_session` starts a :class:`~flightkit.sim.lab.SimLab` (PX4-like or ArduPilot-like
autopilot on a real UDP port on loopback), connects a real :class:`VehicleLink` to it
(pymavlink or MAVSDK, over that UDP port) and starts a
:class:`~flightkit.sim.mocap.SimMocapSource` on the lab's clock. Flight code cannot
tell it from a lab: the runner, the supervisor and the scripts take the same objects.

:func:`fly_plan_in_sim` flies a whole plan that way (``flightkit fly PLAN --connect sim``,
``make demo`` and the examples use it)::

    summary = asyncio.run(fly_plan_in_sim(load_plan("examples/circle.toml"), LabConfig(), speed=5.0))
    print(summary.format_table())
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from flightkit.clock import ONE_PROCESS_WALL_STEP_S, Clock, SimClock
from flightkit.config import Autopilot, LabConfig, LinkBackend
from flightkit.link.base import VehicleLink
from flightkit.mocap.base import MocapSource
from flightkit.sim.lab import SimLab
from flightkit.sim.mocap import SimMocapSource
from trajectories.flightlog import FlightSummary
from trajectories.fly import fly_plan
from trajectories.plan import Plan
from trajectories.status import Status

if TYPE_CHECKING:
    from flightkit.sim.fleet import SimFleet
    from trajectories.fleet import Fleet

__all__ = ["SimSession", "fly_plan_in_sim", "sim_fleet_session", "sim_lab_config", "sim_session"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class SimSession:
    """What :func:`sim_session` yields.

    Attributes:
        lab: the simulated lab (fault injection: ``kill_link``, ``set_battery_remaining``, ...).
        link: a connected vehicle link to the lab's autopilot.
        mocap: the running simulated mocap source (``drop_for``, ``hide_body``, ...).
        clock: the lab's clock; give it to every loop of the flight.
        config: the lab config with ``link.url`` pointing at the simulator.
    """

    lab: SimLab
    link: VehicleLink
    mocap: SimMocapSource
    clock: Clock
    config: LabConfig


def sim_lab_config(
    lab_cfg: LabConfig | None = None,
    *,
    autopilot: Autopilot | str | None = None,
    backend: LinkBackend | str | None = None,
    speed: float | None = None,
) -> LabConfig:
    """``lab_cfg`` (default: built-in defaults) with the simulator's overrides applied."""
    cfg = lab_cfg or LabConfig()
    if autopilot is not None:
        cfg = dataclasses.replace(
            cfg, vehicle=dataclasses.replace(cfg.vehicle, autopilot=Autopilot(autopilot))
        )
    if backend is not None:
        cfg = dataclasses.replace(cfg, link=dataclasses.replace(cfg.link, backend=LinkBackend(backend)))
    if speed is not None:
        cfg = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, speed=float(speed)))
    return cfg


@contextlib.asynccontextmanager
async def sim_session(
    lab_cfg: LabConfig | None = None,
    *,
    autopilot: Autopilot | str | None = None,
    backend: LinkBackend | str | None = None,
    speed: float | None = None,
    clock: Clock | None = None,
    mocap_rate_hz: float | None = None,
    mocap_body: str | None = None,
    start_pos_enu_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
    start_yaw_rad: float = 0.0,
    heading_offset_rad: float | None = None,
) -> AsyncIterator[SimSession]:
    """Start a simulated lab, connect a link and start simulated mocap; all closed on exit.

    Args:
        lab_cfg: lab config; ``vehicle.autopilot``, ``link.backend``, ``sim`` (speed, mocap
            rate, noise and latency, dynamics) and ``mocap.body``/``T_world_mocap`` are used.
        autopilot / backend / speed: override the config's.
        clock: the clock (default ``SimClock(sim.speed)``); everything runs on it.
        mocap_rate_hz: override ``sim.mocap_rate_hz``.
        mocap_body: the name the simulated mocap gives the vehicle (default ``mocap.body``;
            a different name simulates a wrong body name in config).
        start_pos_enu_m / start_yaw_rad: where the vehicle stands.
        heading_offset_rad: rotation of the autopilot's local frame about world z.

    Blocks until the link has the autopilot's heartbeat.

    Raises:
        LinkTimeout: the link did not hear the simulator (should not happen on loopback).
    """
    cfg = sim_lab_config(lab_cfg, autopilot=autopilot, backend=backend, speed=speed)
    clock = clock or SimClock(cfg.sim.speed, max_wall_step_s=ONE_PROCESS_WALL_STEP_S)
    lab = SimLab(
        cfg,
        url="udpin:127.0.0.1:0",
        clock=clock,
        start_pos_enu_m=start_pos_enu_m,
        start_yaw_rad=start_yaw_rad,
        heading_offset_rad=heading_offset_rad,
        ready_after_s=0.0,
    )
    lab.start()
    try:
        cfg = dataclasses.replace(cfg, link=dataclasses.replace(cfg.link, url=lab.client_url))
        mocap = SimMocapSource(
            lab,
            body=mocap_body or cfg.mocap.body,
            rate_hz=mocap_rate_hz or cfg.sim.mocap_rate_hz,
            noise_m=cfg.sim.mocap_noise_m,
            T_world_mocap=cfg.mocap.T_world_mocap.to_transform(),
            latency_s=cfg.sim.mocap_latency_ms / 1000.0,
        )
        from flightkit.link import open_link

        link = open_link(cfg.link, cfg.vehicle.autopilot, clock)
        async with mocap, link:
            yield SimSession(lab, link, mocap, clock, cfg)
    finally:
        lab.stop()


async def fly_plan_in_sim(
    plan: Plan,
    lab_cfg: LabConfig | None = None,
    *,
    autopilot: Autopilot | str | None = None,
    backend: LinkBackend | str | None = None,
    speed: float | None = None,
    arm: bool = True,
    log_path: str | Path | None = None,
    on_status: Callable[[Status], None] | None = None,
    handle_signals: bool = False,
    on_session: Callable[[SimSession], None] | None = None,
    mocap_from_autopilot_hz: float = 0.0,
) -> FlightSummary:
    """Fly ``plan`` against an in-process simulated lab; blocks until the flight ends.

    Args:
        arm: arm from the script (default True: there is no pilot in the simulator).
        on_session: called with the session once connected (fault injection, watching).
        mocap_from_autopilot_hz: fly on the autopilot's own estimate (its position and attitude
            telemetry) republished at this rate, as a lab that puts the autopilot's EKF on the bus
            as mocap; 0 (default): on the simulated mocap.
        The rest as :func:`sim_session` and :func:`trajectories.fly.fly_plan`.

    Returns:
        The flight summary (``outcome`` tells how it ended).
    """
    async with sim_session(lab_cfg, autopilot=autopilot, backend=backend, speed=speed) as s:
        if on_session is not None:
            on_session(s)
        async with contextlib.AsyncExitStack() as stack:
            mocap: MocapSource = s.mocap
            if mocap_from_autopilot_hz > 0.0:
                from flightkit.mocap.telemetry_source import TelemetryPoseSource

                estimate = TelemetryPoseSource(
                    s.link, s.clock, s.config.mocap.body, rate_hz=mocap_from_autopilot_hz, repeat=True
                )
                mocap = await stack.enter_async_context(estimate)
            return await fly_plan(
                plan,
                s.config,
                link=s.link,
                mocap=mocap,
                clock=s.clock,
                arm=arm,
                log_path=log_path,
                on_status=on_status,
                handle_signals=handle_signals,
            )
    raise AssertionError("unreachable")  # pragma: no cover


@contextlib.asynccontextmanager
async def sim_fleet_session(
    lab_cfg: LabConfig | None = None,
    *,
    vehicles: int | None = None,
    speed: float | None = None,
    clock: Clock | None = None,
    shared_link: str | None = None,
    **fleet_options: Any,
) -> AsyncIterator[tuple[SimFleet, Fleet]]:
    """Start a simulated fleet and a :class:`~trajectories.fleet.Fleet` flying it; all closed on exit.

    Args:
        lab_cfg: the lab config (its ``[[vehicles]]``, or ``vehicles`` of them in a row).
        vehicles: fly this many vehicles ``uav1`` .. ``uavN`` (default: the config's).
        speed: override ``sim.speed``. clock: the clock (default the fleet's ``SimClock``).
        shared_link: every autopilot behind one endpoint (``udpin:HOST:PORT`` or ``pty``; see
            :class:`~flightkit.sim.fleet.SimFleet`).
        fleet_options: passed to :class:`Fleet` (``arm``, ``settings``, ``fleet_safety`` ...).

    Yields:
        (the simulated fleet, for fault injection; the connected, checked and started fleet).
    """
    from flightkit.sim.fleet import SimFleet, fleet_lab_config
    from trajectories.fleet import Fleet

    cfg = sim_lab_config(lab_cfg, speed=speed)
    if vehicles is not None:
        cfg = fleet_lab_config(cfg, vehicles)
    sim = SimFleet(cfg, clock=clock, ready_after_s=0.0, shared_link=shared_link).start()
    try:
        mocap = SimMocapSource(system=sim.mocap, T_world_mocap=cfg.mocap.T_world_mocap.to_transform())
        async with mocap, Fleet(sim.client_config(), clock=sim.clock, mocap=mocap, **fleet_options) as fleet:
            yield sim, fleet
    finally:
        sim.stop()
