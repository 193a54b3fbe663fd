"""Flying a plan from the command line or a notebook: the lab's link and mocap, or the simulated lab.

``flightkit fly`` and ``flightkit plot`` call these::

    summary = asyncio.run(fly(load_plan("examples/circle.toml"), load_config("lab.toml"), arm=True))
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

from flightkit.config import Autopilot, LabConfig, LinkBackend, MocapSourceKind
from trajectories.flightlog import FlightSummary
from trajectories.fly import fly_plan
from trajectories.plan import Plan, load_plan
from trajectories.plots import plot_flight_log
from trajectories.status import Status

__all__ = ["FlightSummary", "Plan", "Status", "fly", "lab_with_overrides", "load_plan", "plot_log"]


def lab_with_overrides(
    lab: LabConfig,
    *,
    url: str | None = None,
    backend: LinkBackend | str | None = None,
    mocap_source: MocapSourceKind | str | None = None,
    autopilot: Autopilot | str | None = None,
) -> LabConfig:
    """``lab`` with the command line's overrides: link URL and backend, mocap source, autopilot."""
    link = lab.link
    if url:
        link = dataclasses.replace(link, url=url)
    if backend:
        link = dataclasses.replace(link, backend=LinkBackend(backend))
    mocap = lab.mocap
    if mocap_source:
        mocap = dataclasses.replace(mocap, source=MocapSourceKind(mocap_source))
    lab = dataclasses.replace(lab, link=link, mocap=mocap)
    if autopilot:
        lab = dataclasses.replace(lab, vehicle=dataclasses.replace(lab.vehicle, autopilot=Autopilot(autopilot)))
    return lab


async def fly(
    plan: Plan,
    lab: LabConfig,
    *,
    sim: bool = False,
    speed: float | None = None,
    arm: bool = False,
    log_path: str | Path | None = None,
    on_status: Callable[[Status], None] | None = None,
    handle_signals: bool = False,
) -> FlightSummary:
    """Fly ``plan`` on the lab's link and mocap, or (``sim``) on the simulated lab in this process
    (where the script always arms: nobody holds a transmitter); blocks until the flight ends.

    Raises:
        MocapBodyMissing, SafetyAbort, LinkError, ConfigError: see ``trajectories.fly.fly_plan``.
    """
    if sim:
        from flightkit.apps.sim_session import fly_plan_in_sim

        return await fly_plan_in_sim(
            plan, lab, speed=speed, arm=True, log_path=log_path, on_status=on_status, handle_signals=handle_signals
        )
    return await fly_plan(
        plan, lab, arm=arm, log_path=log_path, on_status=on_status, handle_signals=handle_signals
    )


def plot_log(log: str | Path, out_dir: str | Path | None = None) -> list[Path]:
    """PNG plots of a flight log (top view, tracking error against time); returns their paths.

    Raises:
        ConfigError: the log is missing or not a flight log.
    """
    from flightkit.errors import ConfigError, DatasetError

    try:
        return [Path(p) for p in plot_flight_log(log, out_dir)]
    except FileNotFoundError:
        raise ConfigError(str(log), "(file)", "file not found", "give the path of a flight log") from None
    except DatasetError as exc:
        raise ConfigError(str(log), "(file)", str(exc), "give a log written by 'flightkit fly'") from None
