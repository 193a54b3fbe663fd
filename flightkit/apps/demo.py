"""The demo: a whole lab session on the simulated lab, end to end, as one function.

1. Start the simulated lab: a PX4-like (or ArduPilot-like) autopilot on a real UDP port, mocap
   published on the Zenoh bus in the lab's mocap frame, and the rendered camera (RGB + depth)
   published next to it, exactly as real drivers would.
2. Record every stream to MCAP while flying.
3. Fly the plan through the MAVLink link, on mocap read from the bus, behind the safety
   supervisor; write the flight log and plots.
4. Run visual odometry on the recording and score it against the mocap ground truth, both in
   the world frame as the recording places them (nothing here applies a calibration by hand).
5. Report the recorded poses to a mapping server over a pseudo-terminal pair (the serial/BLE
   protocol), in the world frame, and save the server's map.

``flightkit demo`` calls :func:`run_demo` and prints what it returns.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from estimation.evaluation import EvaluationReport, evaluate
from estimation.pipeline import VoOptions, VoResult, run_vo
from estimation.plots import plot_evaluation
from estimation.report.demo import report_trajectory_over_pty
from estimation.report.reporter import read_mcap_samples
from flightkit.bus.keys import Keys
from flightkit.clock import SimClock
from flightkit.config import LabConfig
from flightkit.datasets import open_sequence, write_tum
from flightkit.datasets.recording import McapSequence
from trajectories.flightlog import FlightSummary
from trajectories.fly import fly_plan
from trajectories.plan import Plan, parse_plan
from trajectories.status import Status

__all__ = ["DemoResult", "short_plan", "run_demo"]

logger = logging.getLogger(__name__)

Say = Callable[[str, str], None]
"""``say(step, text)``: one progress line of the demo."""


def short_plan() -> Plan:
    """Take off to 1.5 m, hold 5 s where it took off, land (``flightkit demo --short``)."""
    return parse_plan(
        {
            "plan": {"name": "short", "takeoff_height_m": 1.5, "hold_before_s": 0.0, "hold_after_s": 0.0},
            "pattern": {"kind": "hold", "position_m": [0.0, 0.0, 1.5], "duration_s": 5.0},
        },
        "<demo --short>",
    )


@dataclass
class DemoResult:
    """What the demo did and measured.

    Attributes:
        summary: the flight's summary.
        recording: the MCAP file written.
        recording_error: why the recording stopped early ("" when it did not).
        plots: flight plots written.
        vo: the VO run on the recording (None with ``camera=False``).
        vo_report: VO against the mocap ground truth, unaligned (both in the world frame).
        vo_plots: evaluation plots written.
        vo_start_frame: the first frame the VO ran on (after take-off).
        map_png: the mapping server's map.
        reported_poses: poses reported to the server.
    """

    summary: FlightSummary
    recording: Path
    recording_error: str = ""
    plots: list[Path] = field(default_factory=list)
    vo: VoResult | None = None
    vo_report: EvaluationReport | None = None
    vo_plots: list[Path] = field(default_factory=list)
    vo_start_frame: int = 0
    map_png: Path | None = None
    reported_poses: int = 0

    @property
    def ok(self) -> bool:
        return self.summary.outcome == "completed"


async def run_demo(
    cfg: LabConfig,
    plan: Plan,
    out: Path,
    *,
    camera: bool = True,
    method: str = "rgbd-pnp",
    say: Say | None = None,
    on_status: Callable[[Status], None] | None = None,
) -> DemoResult:
    """Fly ``plan`` in the simulated lab (at ``cfg.sim.speed``), record, run VO, report; blocks.

    Raises:
        LinkError, BusError, CaptureError: the set-up failed. EstimationError: the VO failed.
    """
    from capture.bus_recorder import start_recording
    from flightkit.apps.sim_lab import camera_streams
    from flightkit.bus.session import open_session
    from flightkit.mocap import open_mocap
    from flightkit.sim.lab import SimLab
    from flightkit.sim.publish import SimLabPublishers

    tell: Say = say or (lambda _step, _text: None)
    await asyncio.to_thread(out.mkdir, parents=True, exist_ok=True)
    clock = SimClock(cfg.sim.speed)
    keys = Keys(cfg.vehicle.namespace)
    lab = SimLab(cfg, url="udpin:127.0.0.1:0", clock=clock)
    lab.start()
    cfg = dataclasses.replace(cfg, link=dataclasses.replace(cfg.link, url=lab.client_url))
    session = open_session(cfg.bus)
    recording = out / "flight.mcap"
    recorder = pubs = None
    rec_error = ""
    try:
        tell(
            "1/6",
            f"simulated lab: {lab.personality.vehicle_name} on {lab.url} ({cfg.link.backend.value} link), "
            f"speed {cfg.sim.speed:g}x",
        )
        # Record first, so the first camera frames already have mocap ground truth around them.
        recorder = start_recording(
            recording, session=session, topics=[keys.everything()], lab_cfg=cfg, allow_overwrite=True
        )
        pubs = SimLabPublishers(lab, cfg, session, camera=camera, streams=camera_streams(cfg)).start()
        tell("2/6", f"bus: {', '.join(pubs.keys)}; recording {recording}")
        mocap = open_mocap(cfg.mocap, cfg.bus, keys, clock, session=session)
        duration_s = plan.build_pattern().duration_s
        tell("3/6", f"flying plan {plan.name!r} ({duration_s:.0f} s pattern), arming from the script")
        await asyncio.to_thread((out / "flight_log.csv").unlink, missing_ok=True)  # replaces the previous run
        async with mocap:
            summary = await fly_plan(
                plan, cfg, mocap=mocap, clock=clock, arm=True, log_path=out / "flight_log.csv", on_status=on_status
            )
    finally:
        if recorder is not None:
            rec_error = recorder.stop().error
        if pubs is not None:
            pubs.stop()
        session.close()
        lab.stop()
    result = DemoResult(summary, recording, rec_error)
    await asyncio.to_thread(_after_flight, result, cfg, out, camera, method, tell)
    return result


def _after_flight(result: DemoResult, cfg: LabConfig, out: Path, camera: bool, method: str, tell: Say) -> None:
    from capture.info import recording_info
    from trajectories.plots import plot_flight_log

    if result.summary.log_path:
        result.plots = [Path(p) for p in plot_flight_log(result.summary.log_path, out)]
    info = recording_info(result.recording)
    stopped = f"; stopped early: {result.recording_error}" if result.recording_error else ""
    tell(
        "4/6",
        f"recorded {result.recording}: {info.messages} messages on {len(info.streams)} topics, "
        f"{info.duration_s:.1f} s, {info.size_bytes / 1e6:.1f} MB{stopped}",
    )
    if camera:
        _run_vo(result, cfg, out, method, tell)
    else:
        tell("5/6", "visual odometry skipped (no camera)")
    topic = "/" + Keys(cfg.vehicle.namespace).mocap_pose(cfg.mocap.body)
    samples = read_mcap_samples(result.recording, topic=topic)  # world frame: the recording says where mocap is
    result.reported_poses = len(samples)
    tell("6/6", f"reporting {len(samples)} poses to a mapping server over a pty pair (115200 baud, COBS+CRC)")
    result.map_png = report_trajectory_over_pty(samples, out / "mapserver")


def _run_vo(result: DemoResult, cfg: LabConfig, out: Path, method: str, tell: Say) -> None:
    seq = open_sequence(result.recording, mocap_body=cfg.mocap.body)
    assert isinstance(seq, McapSequence)
    gt = seq.groundtruth()
    # Start at the first frame that has a mocap pose (so VO starts in the world frame: a frame in a
    # mocap gap has none, and VO would start at the origin) and whose depth image is at least half
    # within the depth range: on the ground the camera is a few centimetres above the floor, below
    # any depth camera's minimum range.
    start = int(np.searchsorted(seq.stamps_ns(), gt.stamps_ns[0] - 20_000_000))
    skipped = start
    opts = VoOptions()
    for i, frame in enumerate(seq.frames(start), start):
        if frame.T_world_camera is None:
            continue
        d = frame.depth_m
        if d is None or np.mean((d > opts.min_depth_m) & (d < opts.max_depth_m)) >= 0.5:
            start = i
            break
    if start > skipped:
        tell("5/6", f"VO starts at frame {start}, after take-off: the depth camera is below its "
                    f"{opts.min_depth_m:g} m minimum range on the ground")
    tell("5/6", f"visual odometry ({method}) on {len(seq) - start} frames of {result.recording.name}")
    vo = run_vo(seq, method, options=opts, T_body_camera=seq.T_body_camera, init_from_groundtruth=True, start=start)
    est = vo.trajectory("camera")
    write_tum(out / "vo_camera.txt", est)
    write_tum(out / "gt_camera.txt", gt)
    result.vo = vo
    result.vo_start_frame = start
    result.vo_report = evaluate(est, gt, alignment="none", delta=1, delta_unit="frames", max_diff_s=0.02)
    result.vo_plots = plot_evaluation(result.vo_report, out / "vo_plots")
