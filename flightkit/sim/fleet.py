"""A simulated fleet: several vehicles, each with its own autopilot on its own UDP port (or all
behind one shared port or serial radio, :mod:`flightkit.sim.router`), under one mocap system that
tracks every body, all on one clock. One thread (:class:`~flightkit.sim.stepper.SimStepper`) ticks
every autopilot's physics and control; each keeps its own receive thread.

The vehicles come from the lab config's ``[[vehicles]]`` entries (:meth:`LabConfig.fleet`), or
from :func:`fleet_lab_config` for ``flightkit sim --vehicles N``. Each stands where its entry's
``start_m`` says (default: in a row along world y, :data:`SPAWN_SPACING_M` apart). Faults are
injected per vehicle as in a one-vehicle lab: ``fleet.labs[name].kill_link(...)``, a pilot's
mode change through that lab's autopilot, or ``fleet.mocap.hide_body(body)`` for a mocap
dropout of one body.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

from flightkit.bus.keys import Keys
from flightkit.clock import ONE_PROCESS_WALL_STEP_S, Clock, SimClock
from flightkit.config import FleetVehicleConfig, LabConfig
from flightkit.errors import ConfigError
from flightkit.lifetime import Running
from flightkit.sim.autopilot import AutopilotOptions
from flightkit.sim.lab import SimLab
from flightkit.sim.mocap import SimMocapSystem
from flightkit.sim.router import SimRouter
from flightkit.sim.stepper import SimStepper

__all__ = ["SPAWN_SPACING_M", "SimFleet", "fleet_lab_config"]

SPAWN_SPACING_M = 1.0
"""Default distance between simulated vehicles' start points (along world y)."""


def fleet_lab_config(base: LabConfig, n: int, *, spacing_m: float = SPAWN_SPACING_M) -> LabConfig:
    """``base`` with ``n`` vehicles ``uav1`` .. ``uavN`` (bodies of the same names, system ids 1 .. N),
    spawned in a row along world y ``spacing_m`` apart and centred on the origin.

    Raises:
        ConfigError: ``n`` is not 1-10.
    """
    if not 1 <= n <= 10:
        raise ConfigError(base.source_path, "vehicles", f"{n} vehicles", "fly 1 to 10 vehicles", n)
    y0 = -spacing_m * (n - 1) / 2.0
    entries = tuple(
        FleetVehicleConfig(name=f"uav{i + 1}", system_id=i + 1, start_m=(0.0, y0 + spacing_m * i, 0.0))
        for i in range(n)
    )
    return dataclasses.replace(base, vehicles=entries)


class SimFleet(Running):
    """Simulated vehicles of a fleet lab config, and one mocap system tracking them all.

    Args:
        config: the lab config with ``[[vehicles]]`` (a one-vehicle config gives one vehicle).
        clock: the shared clock (default ``SimClock(config.sim.speed)``).
        ready_after_s: the autopilots' estimator convergence time (0 for tests; None: default).
        urls: each vehicle's autopilot endpoint, in config order (default: a free loopback port each).
        shared_link: serve every autopilot behind one endpoint instead (``udpin:HOST:PORT`` or
            ``pty``, see :class:`~flightkit.sim.router.SimRouter`); each vehicle then needs its
            own system id (0 in the config gives its place in the fleet, 1 .. N).

    Attributes:
        labs: vehicle name -> its :class:`SimLab`.
        mocap: the mocap system (every body, in the frame ``mocap.T_world_mocap`` places).
    """

    def __init__(
        self,
        config: LabConfig,
        *,
        clock: Clock | None = None,
        ready_after_s: float | None = None,
        urls: Sequence[str] | None = None,
        shared_link: str | None = None,
    ) -> None:
        self.config = config
        self.clock: Clock = clock or SimClock(config.sim.speed, max_wall_step_s=ONE_PROCESS_WALL_STEP_S)
        self.labs: dict[str, SimLab] = {}
        self._bodies: dict[str, str] = {}
        configs = config.fleet()
        if urls is not None and len(urls) != len(configs):
            raise ConfigError(config.source_path, "vehicles", f"{len(urls)} URLs for {len(configs)} vehicles",
                              "give one autopilot URL per vehicle", list(urls))
        self.system_ids = _system_ids(config, configs, shared=shared_link is not None)
        for i, vcfg in enumerate(configs):
            name = vcfg.vehicle.namespace
            entry = config.vehicle_entry(name)
            start = entry.start_m if entry is not None and entry.start_m else (0.0, SPAWN_SPACING_M * i, 0.0)
            self.labs[name] = SimLab(
                vcfg,
                url=urls[i] if urls is not None and shared_link is None else "udpin:127.0.0.1:0",
                clock=self.clock,
                options=AutopilotOptions(system_id=self.system_ids[name]),
                start_pos_enu_m=start,
                ready_after_s=ready_after_s,
            )
            self._bodies[name] = vcfg.mocap.body
        self.mocap = SimMocapSystem(
            self.clock,
            {self._bodies[n]: lab.T_world_body for n, lab in self.labs.items()},
            T_world_mocap=config.mocap.T_world_mocap.to_transform(),
            rate_hz=config.sim.mocap_rate_hz,
            noise_m=config.sim.mocap_noise_m,
            latency_s=config.sim.mocap_latency_ms / 1000.0,
        )
        self._shared_link = shared_link
        self.router: SimRouter | None = None  # the shared endpoint, once started
        self.stepper: SimStepper | None = None  # the one thread ticking every autopilot, once started

    @property
    def names(self) -> tuple[str, ...]:
        """The vehicles' names, in config order."""
        return tuple(self.labs)

    def keys_by_body(self) -> dict[str, Keys]:
        """Mocap body -> the bus namespace of its vehicle (for :class:`SimMocapPublisher`)."""
        return {body: Keys(name) for name, body in self._bodies.items()}

    def body_of(self, name: str) -> str:
        """The mocap body of vehicle ``name``."""
        return self._bodies[name]

    def client_url(self, name: str) -> str:
        """Where the ground reaches vehicle ``name`` (the shared endpoint when there is one; after :meth:`start`)."""
        return self.router.client_url if self.router is not None else self.labs[name].client_url

    def client_config(self) -> LabConfig:
        """The whole fleet's lab config with every vehicle's link URL and system id resolved (after :meth:`start`)."""
        entries = tuple(
            dataclasses.replace(e, url=self.client_url(e.name), system_id=self.system_ids[e.name])
            for e in self.config.vehicles
        )
        if not entries:  # a one-vehicle lab
            only = next(iter(self.labs))
            link = dataclasses.replace(self.config.link, url=self.client_url(only))
            return dataclasses.replace(self.config, link=link)
        return dataclasses.replace(self.config, vehicles=entries)

    def start(self) -> SimFleet:
        """Start every autopilot, the shared endpoint if any, and the mocap system; returns immediately."""
        for lab in self.labs.values():
            lab.start(own_loop=False)
        if self.stepper is None:
            self.stepper = SimStepper(self.clock, [lab.autopilot for lab in self.labs.values()]).start()
        if self._shared_link is not None and self.router is None:
            behind = {self.system_ids[n]: lab.autopilot.bound_address for n, lab in self.labs.items()}
            self.router = SimRouter(behind, self._shared_link).start()
        self.mocap.start()
        return self

    def stop(self) -> None:
        """Stop the mocap system, the shared endpoint and every autopilot; idempotent."""
        self.mocap.stop()
        if self.stepper is not None:
            self.stepper.stop()
            self.stepper = None
        if self.router is not None:
            self.router.stop()
            self.router = None
        for lab in self.labs.values():
            lab.stop()


def _system_ids(config: LabConfig, configs: Sequence[LabConfig], *, shared: bool) -> dict[str, int]:
    """Each vehicle's autopilot system id: its config's, else 1 (own port) or its place 1 .. N (shared)."""
    ids = {c.vehicle.namespace: c.link.system_id or (i + 1 if shared else 1) for i, c in enumerate(configs)}
    if shared and len(set(ids.values())) != len(ids):
        raise ConfigError(config.source_path, "vehicles", f"system ids {ids}",
                          "give every vehicle behind a shared link its own system_id", ids)
    return ids
