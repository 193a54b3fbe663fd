"""``flightkit demo``: a whole lab session on the simulated lab, end to end.

1. Start the simulated lab: a PX4-like (or ArduPilot-like) autopilot on a real UDP port,
   mocap published on the Zenoh bus in the lab's mocap frame, and the rendered camera
   (RGB + depth) published next to it, exactly as real drivers would.
2. Record every stream to MCAP while flying.
3. Fly the circle plan through the MAVLink link, on mocap read from the bus, behind the
   safety supervisor; print the summary and write plots.
4. Print ``capture info`` of the recording.
5. Run visual odometry on the recording and score it against the mocap ground truth.
6. Report the flight's poses to a mapping server over a pseudo-terminal pair (the serial/BLE
   protocol) and save the server's map.

``--short`` flies only take-off to 1.5 m, hold 5 s, land. ``--closed-loop`` flies the circle
with the autopilot fusing VO instead of mocap.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import time
from pathlib import Path
from typing import Any

__all__ = ["register", "run"]

_REPO_EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def register(sub: Any) -> None:
    p = sub.add_parser(
        "demo",
        help="fly, record, estimate and report on the simulated lab, end to end",
        description=__doc__.split("\n\n")[0] if __doc__ else None,
    )
    p.add_argument("--config", metavar="LAB.toml", help="lab config (default: examples/lab_sim.toml)")
    p.add_argument("--plan", metavar="PLAN.toml", help="flight plan (default: examples/circle.toml)")
    p.add_argument("--out", metavar="DIR", default="out/demo", help="where recordings, logs and plots go")
    p.add_argument("--speed", type=float, default=1.0, help="simulated seconds per wall second (default 1)")
    p.add_argument("--autopilot", choices=["px4", "ardupilot"], help="simulated firmware (default: config)")
    p.add_argument("--backend", choices=["pymavlink", "mavsdk"], help="MAVLink library (default: config)")
    p.add_argument("--short", action="store_true", help="only take off to 1.5 m, hold 5 s and land")
    p.add_argument("--closed-loop", action="store_true", help="fly the circle on VO fused by the autopilot")
    p.add_argument("--no-camera", action="store_true", help="skip the camera, recording of images and VO")
    p.add_argument("--method", default="rgbd-pnp", help="VO method for step 5 (default rgbd-pnp)")
    p.set_defaults(func=run)


def _say(step: str, text: str) -> None:
    print(f"[{step}] {text}", flush=True)


def _lab_config(args: argparse.Namespace) -> Any:
    from flightkit.config import Autopilot, LinkBackend, load_config

    path = Path(args.config) if args.config else _REPO_EXAMPLES / "lab_sim.toml"
    cfg = load_config(path) if path.is_file() else load_config()
    if args.autopilot:
        cfg = dataclasses.replace(cfg, vehicle=dataclasses.replace(cfg.vehicle, autopilot=Autopilot(args.autopilot)))
    if args.backend:
        cfg = dataclasses.replace(cfg, link=dataclasses.replace(cfg.link, backend=LinkBackend(args.backend)))
    # The demo renders at 320x240 by default so it keeps real time on a 2-core laptop.
    if not args.config:
        cfg = dataclasses.replace(cfg, camera=dataclasses.replace(cfg.camera, width_px=320, height_px=240))
    return dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, speed=args.speed))


def _plan(args: argparse.Namespace) -> Any:
    from trajectories.plan import load_plan

    return load_plan(Path(args.plan) if args.plan else _REPO_EXAMPLES / "circle.toml")


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = _lab_config(args)
    if args.closed_loop:
        from flightkit.cli.closed_loop import fly_closed_loop

        report = asyncio.run(fly_closed_loop(cfg, _plan(args), out, speed=args.speed))
        print(report.format())
        return 0 if report.ok else 1
    return asyncio.run(_demo(args, cfg, out))


async def _demo(args: argparse.Namespace, cfg: Any, out: Path) -> int:
    from flightkit.bus.keys import Keys
    from flightkit.bus.session import open_session
    from flightkit.clock import SimClock
    from flightkit.mocap import open_mocap
    from flightkit.sim.lab import SimLab
    from flightkit.sim.mocap_publisher import SimMocapPublisher

    clock = SimClock(args.speed)
    keys = Keys(cfg.vehicle.namespace)
    lab = SimLab(cfg, url="udpin:127.0.0.1:0", clock=clock)
    lab.start()
    cfg = dataclasses.replace(cfg, link=dataclasses.replace(cfg.link, url=lab.client_url))
    session = open_session(cfg.bus)
    camera = recorder = mocap_pub = None
    recording = out / "flight.mcap"
    try:
        _say(
            "1/6",
            f"simulated lab: {lab.personality.vehicle_name} on {lab.url} ({cfg.link.backend.value} link), "
            f"speed {args.speed:g}x",
        )
        from capture.session import start_recording

        # Record first, so the first camera frames already have mocap ground truth around them.
        recorder = start_recording(
            recording, session=session, topics=[keys.everything()], lab_cfg=cfg, allow_overwrite=True
        )
        mocap_pub = SimMocapPublisher(
            session, keys, cfg.mocap.body, truth=lambda: (clock.time_ns(), lab.T_world_body()), clock=clock,
            T_world_mocap=cfg.mocap.T_world_mocap.to_transform(), rate_hz=cfg.sim.mocap_rate_hz,
            noise_m=cfg.sim.mocap_noise_m,
        ).start()
        if not args.no_camera:
            from capture.config import CaptureConfig
            from capture.sources.sim import SimCameraPublisher

            camera = SimCameraPublisher(
                session, keys, lambda: (clock.time_ns(), lab.T_world_body()), cfg.camera, clock,
                capture_cfg=cfg.section("capture", CaptureConfig),
            ).start()
        cam_text = (
            "" if camera is None
            else f", camera {cfg.camera.width_px}x{cfg.camera.height_px} at {cfg.camera.rate_hz:g} Hz"
        )
        _say("2/6", f"bus: mocap on {mocap_pub.key} at {cfg.sim.mocap_rate_hz:g} Hz{cam_text}; recording {recording}")
        mocap = open_mocap(cfg.mocap, cfg.bus, keys, clock, session=session)
        summary = await _fly(args, cfg, mocap, clock, out)
    finally:
        if recorder is not None:
            rec_report = recorder.stop()
        if camera is not None:
            camera.stop()
        if mocap_pub is not None:
            mocap_pub.stop()
        session.close()
        lab.stop()
    print(summary.format_table())
    plots = _flight_plots(summary, out)
    for p in plots:
        _say("3/6", f"plot: {p}")
    if rec_report.error:
        _say("4/6", f"recording stopped early: {rec_report.error}")
    _print_capture_info(recording)
    if camera is not None:
        _run_vo(args, cfg, recording, out)
    else:
        _say("5/6", "visual odometry skipped (--no-camera)")
    map_png = _report_to_mapserver(recording, cfg, out)
    _say("6/6", f"mapping server map: {map_png}")
    ok = summary.outcome == "completed"
    _say("done", f"flight {summary.outcome}; everything is in {out}/")
    return 0 if ok else 1


async def _fly(args: argparse.Namespace, cfg: Any, mocap: Any, clock: Any, out: Path) -> Any:
    from trajectories.runner import Status, fly_plan

    if args.short:
        from trajectories.plan import parse_plan

        # Take off to 1.5 m, hold 5 s where it took off, land.
        plan = parse_plan(
            {
                "plan": {"name": "short", "takeoff_height_m": 1.5, "hold_before_s": 0.0, "hold_after_s": 0.0},
                "pattern": {"kind": "hold", "position_m": [0.0, 0.0, 1.5], "duration_s": 5.0},
            },
            "<demo --short>",
        )
    else:
        plan = _plan(args)
    _say("3/6", f"flying plan {plan.name!r} ({plan.build_pattern().duration_s:.0f} s pattern), arming from the script")
    last = {"t": 0.0, "phase": ""}

    def status(s: Status) -> None:
        now = time.monotonic()
        if now - last["t"] >= 2.0 or s.phase != last["phase"]:
            last["t"], last["phase"] = now, s.phase
            print(f"      {s.line()}", flush=True)

    (out / "flight_log.csv").unlink(missing_ok=True)  # the demo replaces its previous run
    async with mocap:
        return await fly_plan(
            plan, cfg, mocap=mocap, clock=clock, arm=True, log_path=out / "flight_log.csv", on_status=status
        )


def _flight_plots(summary: Any, out: Path) -> list[Path]:
    from trajectories.plots import plot_flight_log

    log_path = out / "flight_log.csv"
    if not log_path.is_file():
        return []
    return [Path(p) for p in plot_flight_log(log_path, out)]


def _print_capture_info(recording: Path) -> None:
    from flightkit.cli.capture import run_info

    _say("4/6", f"capture info {recording}")
    run_info(argparse.Namespace(recording=str(recording), gap_factor=3.0, json=False))


def _run_vo(args: argparse.Namespace, cfg: Any, recording: Path, out: Path) -> None:
    import numpy as np

    from estimation.evaluation import evaluate
    from estimation.pipeline import VoOptions, run_vo
    from estimation.plots import plot_evaluation
    from flightkit.cli.vo import print_report
    from flightkit.datasets import open_sequence, write_tum

    seq = open_sequence(
        recording, mocap_body=cfg.mocap.body, T_world_mocap=cfg.mocap.T_world_mocap.to_transform(),
        T_body_camera=cfg.camera.T_body_camera.to_transform(),
    )
    gt = seq.groundtruth()
    # Start at the first frame that has a mocap pose within 20 ms, so VO starts in the world frame,
    # and whose depth image is at least half within the depth range: on the ground the camera is a
    # few centimetres above the floor, below any depth camera's minimum range (0.2 m here).
    start = int(np.searchsorted(seq.stamps_ns(), gt.stamps_ns[0] - 20_000_000))
    skipped = start
    opts = VoOptions()
    for i, frame in enumerate(seq.frames(start), start):
        d = frame.depth_m
        if d is None or np.mean((d > opts.min_depth_m) & (d < opts.max_depth_m)) >= 0.5:
            start = i
            break
    if start > skipped:
        _say("5/6", f"VO starts at frame {start}, after take-off: the depth camera is below its "
                    f"{opts.min_depth_m:g} m minimum range on the ground")
    _say("5/6", f"visual odometry ({args.method}) on {len(seq) - start} frames of {recording.name}")
    result = run_vo(
        seq, args.method, options=opts, T_body_camera=cfg.camera.T_body_camera.to_transform(),
        init_from_groundtruth=True, start=start,
    )
    est = result.trajectory("camera")
    write_tum(out / "vo_camera.txt", est)
    write_tum(out / "gt_camera.txt", gt)
    report = evaluate(est, gt, alignment="none", delta=1, delta_unit="frames", max_diff_s=0.02)
    plots = plot_evaluation(report, out / "vo_plots")
    print_report(report, plots)
    print(f"      {len(result)} frames, {result.fps:.0f} frames/s of processing ({result.wall_s:.1f} s with decoding)")


def _report_to_mapserver(recording: Path, cfg: Any, out: Path) -> Path:
    from estimation.report.demo import report_trajectory_over_pty
    from estimation.report.reporter import read_mcap_samples
    from flightkit.bus.keys import Keys

    # The recorded mocap poses are in the mocap frame; the reporter works in the world frame.
    T_world_mocap = cfg.mocap.T_world_mocap.to_transform()
    topic = "/" + Keys(cfg.vehicle.namespace).mocap_pose(cfg.mocap.body)
    poses = [(s.stamp_ns, T_world_mocap @ s.T_world_body) for s in read_mcap_samples(recording, topic=topic)]
    _say("6/6", f"reporting {len(poses)} poses to a mapping server over a pty pair (115200 baud, COBS+CRC)")
    return report_trajectory_over_pty(poses, out / "mapserver")
