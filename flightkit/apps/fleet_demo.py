"""The fleet demo: three simulated vehicles fly one circle together and are recorded.

1. Start a simulated fleet: three autopilots (each on its own UDP port), one mocap system
   tracking every body, a camera per vehicle, all published on the bus under each vehicle's
   namespace, the vehicles standing under their start points on the circle.
2. Record every vehicle's streams into one MCAP file.
3. Fly ``examples/fleet_circle.toml`` (120 degrees apart, synchronised start, separation
   watched) over real MAVLink.
4. Read the recording back grouped by vehicle and export one TUM RGB-D folder per vehicle.

``flightkit demo --fleet`` calls :func:`run_fleet_demo` and prints what it returns.
"""

from __future__ import annotations

import asyncio
import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from capture.export import ExportReport
from flightkit.config import LabConfig
from trajectories.fleet_plan import FleetPlan, FleetResult
from trajectories.status import Status

__all__ = ["FleetDemoResult", "run_fleet_demo"]

Say = Callable[[str, str], None]


@dataclass
class FleetDemoResult:
    """What the fleet demo did: the flight, the recording and the per-vehicle exports."""

    flight: FleetResult
    recording: Path
    recording_error: str = ""
    exports: dict[str, ExportReport] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.flight.outcome == "completed" and not self.recording_error


async def run_fleet_demo(
    cfg: LabConfig,
    fplan: FleetPlan,
    out: Path,
    *,
    say: Say | None = None,
    on_status: Callable[[str, Status], None] | None = None,
) -> FleetDemoResult:
    """Fly ``fplan`` with a simulated fleet (at ``cfg.sim.speed``), recording it; blocks.

    Raises:
        PlanError: the plan's references come too close. LinkError, BusError, CaptureError: set-up.
    """
    from capture.bus_recorder import start_recording
    from capture.export import export_vehicles
    from capture.info import recording_info
    from flightkit.apps.fleet import sim_fleet_config
    from flightkit.apps.sim_lab import camera_streams
    from flightkit.bus.session import open_session
    from flightkit.sim.fleet import SimFleet
    from flightkit.sim.mocap import SimMocapSource
    from flightkit.sim.publish import SimFleetPublishers
    from trajectories.fleet_plan import fly_fleet_plan

    tell: Say = say or (lambda _step, _text: None)
    fplan.check_separation()
    await asyncio.to_thread(out.mkdir, parents=True, exist_ok=True)
    for name in fplan.vehicles:  # the demo replaces its previous run
        await asyncio.to_thread((out / f"{fplan.name}-{name}.csv").unlink, missing_ok=True)
    cfg = sim_fleet_config(fplan, cfg)
    sim = SimFleet(cfg, ready_after_s=0.0).start()
    session = open_session(cfg.bus)
    recording = out / "fleet.mcap"
    recorder = pubs = None
    try:
        tell("1/4", f"simulated fleet: {', '.join(f'{n} on {lab.url}' for n, lab in sim.labs.items())}, "
                    f"speed {cfg.sim.speed:g}x")
        recorder = start_recording(recording, session=session, lab_cfg=cfg, allow_overwrite=True)
        pubs = SimFleetPublishers(sim, session, camera=cfg.camera.enabled, streams=camera_streams(cfg)).start()
        tell("2/4", f"recording {', '.join(recorder.topics)} to {recording}")
        tell("3/4", f"flying {fplan.name!r}: {len(fplan.vehicles)} vehicles, started together, "
                    f"min separation {fplan.fleet.min_separation_m:g} m")
        mocap = SimMocapSource(system=sim.mocap, T_world_mocap=cfg.mocap.T_world_mocap.to_transform())
        async with mocap:
            flight = await fly_fleet_plan(
                fplan, sim.client_config(), clock=sim.clock, mocap=mocap, arm=True, log_dir=out,
                on_status=on_status,
            )
    finally:
        rec_report = recorder.stop() if recorder is not None else None
        rec_error = rec_report.error if rec_report is not None else ""
        if pubs is not None:
            pubs.stop()
        session.close()
        sim.stop()
    result = FleetDemoResult(flight, recording, rec_error)
    info = await asyncio.to_thread(recording_info, recording)
    groups = info.by_vehicle()
    lost = f"; the recorder dropped {rec_report.dropped} under load" if rec_report and rec_report.dropped else ""
    tell("4/4", f"recorded {info.messages} messages, {info.duration_s:.1f} s: "
                + ", ".join(f"{v} {sum(s.count for s in streams)}" for v, streams in groups.items()) + lost)
    if cfg.camera.enabled:
        result.exports = await asyncio.to_thread(export_vehicles, recording, out / "tum", "tum", allow_overwrite=True)
        for v, rep in result.exports.items():
            tell("4/4", f"{v}: {rep.summary()}")
    return result


def fleet_demo_config(cfg: LabConfig, speed: float) -> LabConfig:
    """The lab for the fleet demo: small cameras (three render in real time on two cores)."""
    cam = dataclasses.replace(cfg.camera, width_px=160, height_px=120)
    return dataclasses.replace(cfg, camera=cam, sim=dataclasses.replace(cfg.sim, speed=speed))
