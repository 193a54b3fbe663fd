"""The simulated lab on the bus: its mocap system and camera publish as a lab's drivers do.

:class:`SimLabPublishers` starts a :class:`~flightkit.sim.mocap.SimMocapSystem` sampling the
lab's vehicle (published in the mocap frame of the lab's *true* ``T_world_mocap``, the config's
unless a calibration error is simulated) and, when the camera is enabled, a
:class:`~flightkit.sim.camera_publisher.SimCameraPublisher` rendering from the vehicle's true
pose. ``flightkit sim``, the demo and the closed-loop flight use it::

    with SimLabPublishers(lab, cfg, session) as pubs:
        print(pubs.keys)
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import TYPE_CHECKING, Self

import zenoh

from flightkit.bus.clock_exchange import ClockServer
from flightkit.bus.keys import Keys
from flightkit.bus.streams import CameraStreamSelection
from flightkit.config import LabConfig
from flightkit.frames import Transform
from flightkit.lifetime import Running
from flightkit.sim.camera_publisher import SimCameraPublisher
from flightkit.sim.mocap import SimMocapPublisher, SimMocapSystem
from flightkit.sim.timing_errors import SimTimingErrors

if TYPE_CHECKING:
    from flightkit.sim.fleet import SimFleet
    from flightkit.sim.lab import SimLab

__all__ = ["SIM_CLOCK_HOST", "SimFleetPublishers", "SimLabPublishers", "SimPublishers"]

logger = logging.getLogger(__name__)


SIM_CLOCK_HOST = "sim"
"""The simulated lab's host name in the clock exchange (:mod:`flightkit.bus.clock_exchange`)."""


class SimPublishers(Running):
    """A mocap system's publisher and camera publishers on one session; started and stopped together.
    While started, the lab's clock is served on ``<ns>/clock/sim`` of every namespace in
    ``clock_keys``, so a recorder's clock exchange puts the simulated stamps on its time base."""

    def __init__(
        self,
        session: zenoh.Session,
        mocap_system: SimMocapSystem,
        mocap: SimMocapPublisher,
        cameras: list[SimCameraPublisher],
        owns_session: bool,
        clock_keys: Sequence[Keys] = (),
    ) -> None:
        self.session = session
        self.mocap_system = mocap_system
        self.mocap = mocap
        self.cameras = cameras
        self._owns_session = owns_session
        self._clock_keys = tuple(clock_keys)
        self._clock_servers: list[ClockServer] = []

    @property
    def camera(self) -> SimCameraPublisher | None:
        """The (first) vehicle's camera publisher, None without a camera."""
        return self.cameras[0] if self.cameras else None

    @property
    def keys(self) -> list[str]:
        """Every key published on."""
        return self.mocap.keys + [k for c in self.cameras for k in c.keys]

    def start(self) -> Self:
        """Start publishing; returns immediately."""
        if not self._clock_servers:
            self._clock_servers = [ClockServer(self.session, k, SIM_CLOCK_HOST, self.mocap_system.clock)
                                   for k in self._clock_keys]
        self.mocap.start()
        for c in self.cameras:
            c.start()
        return self

    def stop(self) -> None:
        """Stop publishing (and close the session when owned); idempotent."""
        for c in self.cameras:
            c.stop()
        self.mocap.stop()
        servers, self._clock_servers = self._clock_servers, []
        for server in servers:
            server.close()
        if self._owns_session:
            self._owns_session = False
            self.session.close()


class SimLabPublishers(SimPublishers):
    """Mocap (and camera) of a simulated lab, published on a bus session.

    Args:
        lab: the running simulated lab.
        lab_cfg: ``vehicle.namespace``, ``mocap.body`` and ``T_world_mocap``, ``sim`` (mocap rate,
            noise and latency, the camera's time offset, drift and true mount) and ``camera``.
        session: an open Zenoh session.
        camera: publish the camera (default: ``lab_cfg.camera.enabled``).
        streams: which camera streams (default: colour and depth, extrinsics on tf).
        true_T_world_mocap: where the mocap frame really is (default: the config's).
        owns_session: close ``session`` on :meth:`stop`.
        render_budget_s: the camera renders every frame within this much simulated time (the
            clock waits); None skips the frames it cannot render in time.

    Start with :meth:`start` or ``with``; both publishers run on their own threads.
    """

    def __init__(
        self,
        lab: SimLab,
        lab_cfg: LabConfig,
        session: zenoh.Session,
        *,
        camera: bool | None = None,
        streams: CameraStreamSelection | None = None,
        true_T_world_mocap: Transform | None = None,  # noqa: N803
        owns_session: bool = False,
        render_budget_s: float | None = None,
    ) -> None:
        keys = Keys(lab_cfg.vehicle.namespace)
        system = SimMocapSystem(
            lab.clock,
            {lab_cfg.mocap.body: lab.T_world_body},
            T_world_mocap=true_T_world_mocap or lab_cfg.mocap.T_world_mocap.to_transform(),
            rate_hz=lab_cfg.sim.mocap_rate_hz,
            noise_m=lab_cfg.sim.mocap_noise_m,
            latency_s=lab_cfg.sim.mocap_latency_ms / 1000.0,
        )
        use_camera = lab_cfg.camera.enabled if camera is None else camera
        sim = lab_cfg.sim
        self.timing = SimTimingErrors(
            sim.camera_time_offset_ms / 1000.0, sim.camera_drift_ppm, sim.mocap_latency_ms / 1000.0
        )
        true_mount = sim.true_T_body_camera.to_transform() if sim.true_T_body_camera is not None else None
        cameras = (
            [
                SimCameraPublisher(
                    session, keys, lab.T_world_body, lab_cfg.camera, lab.clock, streams=streams,
                    timing=self.timing, true_T_body_camera=true_mount, render_budget_s=render_budget_s,
                )
            ]
            if use_camera
            else []
        )
        super().__init__(session, system, SimMocapPublisher(session, keys, system), cameras, owns_session, [keys])


class SimFleetPublishers(SimPublishers):
    """Every vehicle of a simulated fleet on a bus session: its mocap system (each body under its
    vehicle's namespace) and, with ``camera``, one camera per vehicle. Arguments as
    :class:`SimLabPublishers`."""

    def __init__(
        self,
        fleet: SimFleet,
        session: zenoh.Session,
        *,
        camera: bool | None = None,
        streams: CameraStreamSelection | None = None,
        owns_session: bool = False,
    ) -> None:
        use_camera = fleet.config.camera.enabled if camera is None else camera
        cameras = [
            SimCameraPublisher(session, Keys(name), lab.T_world_body, lab.config.camera, lab.clock, streams=streams)
            for name, lab in fleet.labs.items()
            if use_camera
        ]
        mocap = SimMocapPublisher(session, fleet.keys_by_body(), fleet.mocap)
        super().__init__(session, fleet.mocap, mocap, cameras, owns_session, [Keys(name) for name in fleet.labs])
