"""``flightkit sim``: the simulated lab served to other processes until stopped.

:func:`serve_sim_lab` runs a :class:`~flightkit.sim.lab.SimLab` (its autopilot on a real UDP
port) and publishes its mocap and camera on the bus (:class:`~flightkit.sim.publish.SimLabPublishers`,
camera streams from the ``[capture]`` section), until ``stop`` is set.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from flightkit.bus.streams import CameraStreamSelection
from flightkit.config import Autopilot, LabConfig
from flightkit.sim.autopilot import AutopilotOptions
from flightkit.sim.lab import SimEvent, SimLab
from flightkit.sim.publish import SimLabPublishers, SimPublishers

if TYPE_CHECKING:
    import zenoh

    from flightkit.sim.fleet import SimFleet
    from flightkit.sim.publish import SimFleetPublishers

__all__ = ["SimFleetServed", "SimLabServed", "camera_streams", "serve_sim_fleet", "serve_sim_lab"]


def camera_streams(lab_cfg: LabConfig) -> CameraStreamSelection:
    """Which camera streams the lab's ``[capture]`` section asks for."""
    from capture.config import CaptureConfig

    return lab_cfg.section("capture", CaptureConfig).streams()


@dataclass(frozen=True, slots=True)
class SimLabServed:
    """What :func:`serve_sim_lab` started, handed to ``on_ready``.

    Attributes:
        lab: the running lab.
        keys: the bus keys its mocap and camera publish on (empty without them).
        camera_error: why the camera could not start ("" when it runs or was not asked for).
    """

    lab: SimLab
    keys: tuple[str, ...]
    camera_error: str = ""


def serve_sim_lab(
    lab_cfg: LabConfig,
    options: AutopilotOptions,
    stop: threading.Event,
    *,
    autopilot: Autopilot | str | None = None,
    mocap: bool = True,
    camera: bool = True,
    on_event: Callable[[SimEvent], None] | None = None,
    on_ready: Callable[[SimLabServed], None] | None = None,
) -> None:
    """Run the simulated lab until ``stop`` is set; blocks.

    Args:
        lab_cfg: the lab (``sim`` speed and mocap, ``camera``, ``bus``, ``vehicle``).
        options: the autopilot's endpoint, readiness, heading offset and signing key.
        stop: set it (e.g. on Ctrl-C) to stop.
        autopilot: overrides ``vehicle.autopilot``.
        mocap, camera: publish them on the bus (the camera only when ``camera.enabled``).
        on_event: called with every simulator event (from simulator threads).
        on_ready: called once everything runs.

    Raises:
        EndpointError: the autopilot's port is in use. BusError: the bus cannot be opened.
    """
    from flightkit.clock import SimClock

    lab = SimLab(lab_cfg, autopilot=autopilot, clock=SimClock(lab_cfg.sim.speed), options=options)
    if on_event is not None:
        lab.events.append(on_event)
    with lab:

        def make(session: zenoh.Session, use_camera: bool) -> SimLabPublishers:
            streams = camera_streams(lab_cfg) if use_camera else None
            return SimLabPublishers(lab, lab_cfg, session, camera=use_camera, streams=streams, owns_session=True)

        def ready(keys: tuple[str, ...], camera_error: str) -> None:
            if on_ready is not None:
                on_ready(SimLabServed(lab, keys, camera_error))

        _publish_until_stopped(lab_cfg, stop, mocap or camera, camera, make, ready)


@dataclass(frozen=True, slots=True)
class SimFleetServed:
    """What :func:`serve_sim_fleet` started, handed to ``on_ready``.

    Attributes:
        fleet: the running simulated fleet (``fleet.labs[name].client_url`` reaches a vehicle).
        keys: the bus keys its mocap and cameras publish on.
        camera_error: why the cameras could not start ("" when they run or were not asked for).
    """

    fleet: SimFleet
    keys: tuple[str, ...]
    camera_error: str = ""


def serve_sim_fleet(
    lab_cfg: LabConfig,
    stop: threading.Event,
    *,
    base_port: int = 14540,
    host: str = "127.0.0.1",
    ready_after_s: float | None = None,
    shared_link: str | None = None,
    mocap: bool = True,
    camera: bool = True,
    on_event: Callable[[str, SimEvent], None] | None = None,
    on_ready: Callable[[SimFleetServed], None] | None = None,
) -> None:
    """Run a simulated fleet (the lab's ``[[vehicles]]``) until ``stop`` is set; blocks.

    Vehicle ``i`` (in config order) listens on ``udpin:host:base_port + i``; with
    ``shared_link = "udp"`` every vehicle is behind ``udpin:host:base_port`` instead (one port,
    one system id each), with ``"pty"`` behind one pseudo-terminal radio. One mocap system
    publishes every body under its vehicle's namespace; with ``camera`` each vehicle's camera
    publishes under its namespace too.

    Raises:
        EndpointError: a port is in use. BusError: the bus cannot be opened.
    """
    from flightkit.sim.fleet import SimFleet
    from flightkit.sim.publish import SimFleetPublishers
    from flightkit.sim.router import PTY

    n = len(lab_cfg.fleet())
    urls = [f"udpin:{host}:{base_port + i}" for i in range(n)]
    shared = {None: None, "udp": f"udpin:{host}:{base_port}", PTY: PTY}[shared_link]
    fleet = SimFleet(lab_cfg, ready_after_s=ready_after_s, urls=urls, shared_link=shared)
    if on_event is not None:
        for name, lab in fleet.labs.items():
            lab.events.append(_tagged(on_event, name))
    with fleet:

        def make(session: zenoh.Session, use_camera: bool) -> SimFleetPublishers:
            streams = camera_streams(lab_cfg) if use_camera else None
            return SimFleetPublishers(fleet, session, camera=use_camera, streams=streams, owns_session=True)

        def ready(keys: tuple[str, ...], camera_error: str) -> None:
            if on_ready is not None:
                on_ready(SimFleetServed(fleet, keys, camera_error))

        _publish_until_stopped(lab_cfg, stop, mocap or camera, camera, make, ready)


def _publish_until_stopped(
    lab_cfg: LabConfig,
    stop: threading.Event,
    publish: bool,
    camera: bool,
    make: Callable[[zenoh.Session, bool], SimPublishers],
    ready: Callable[[tuple[str, ...], str], None],
) -> None:
    """Publish (``make`` the publishers on a new session) until ``stop`` is set; without a camera
    when the camera cannot start (``ready`` is told why)."""
    from flightkit.bus.session import open_session
    from flightkit.errors import FlightkitError

    pubs = None
    camera_error = ""
    if publish:
        session = open_session(lab_cfg.bus)
        use_camera = camera and lab_cfg.camera.enabled
        try:
            pubs = make(session, use_camera)
        except FlightkitError as exc:  # the sim still runs without the camera
            camera_error = str(exc)
            pubs = make(session, False)
        pubs.start()
    try:
        ready(tuple(pubs.keys) if pubs is not None else (), camera_error)
        while not stop.wait(0.5):
            pass
    finally:
        if pubs is not None:
            pubs.stop()


def _tagged(on_event: Callable[[str, SimEvent], None], name: str) -> Callable[[SimEvent], None]:
    return lambda event: on_event(name, event)
