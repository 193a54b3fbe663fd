"""``flightkit demo``: a whole lab session on the simulated lab, end to end.

Flies, records, runs visual odometry on the recording and reports the flight to a mapping
server (see :mod:`flightkit.apps.demo`). ``--short`` flies only take-off to 1.5 m, hold 5 s,
land. ``--closed-loop`` flies the circle with the autopilot fusing VO instead of mocap
(:mod:`flightkit.apps.closed_loop`).
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
        description="Fly a plan on the simulated lab, record every stream, run visual odometry on the "
        "recording and report the poses to a mapping server over a pty pair.",
    )
    p.add_argument("--config", metavar="LAB.toml", help="lab config (default: examples/lab_sim.toml)")
    p.add_argument("--plan", metavar="PLAN.toml", help="flight plan (default: examples/circle.toml)")
    p.add_argument("--out", metavar="DIR", default="out/demo", help="where recordings, logs and plots go")
    p.add_argument("--speed", type=float, default=1.0, help="simulated seconds per wall second (default 1)")
    p.add_argument("--autopilot", choices=["px4", "ardupilot"], help="simulated firmware (default: config)")
    p.add_argument("--backend", choices=["pymavlink", "mavsdk"], help="MAVLink library (default: config)")
    p.add_argument("--short", action="store_true", help="only take off to 1.5 m, hold 5 s and land")
    p.add_argument("--closed-loop", action="store_true", help="fly the circle on VO fused by the autopilot")
    p.add_argument(
        "--fleet", action="store_true", help="three vehicles on one circle, recorded (examples/fleet_circle.toml)"
    )
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


def run(args: argparse.Namespace) -> int:
    from flightkit.apps.demo import run_demo, short_plan
    from flightkit.apps.flight import load_plan

    out = Path(args.out)
    if args.fleet:
        return _run_fleet(args, out)
    cfg = _lab_config(args)
    plan = short_plan() if args.short else load_plan(Path(args.plan) if args.plan else _REPO_EXAMPLES / "circle.toml")
    if args.closed_loop:
        from flightkit.apps.closed_loop import fly_closed_loop

        report = asyncio.run(fly_closed_loop(cfg, plan, out, speed=args.speed))
        print(report.format())
        return 0 if report.ok else 1
    last_t, last_phase = 0.0, ""

    def status(s: Any) -> None:
        nonlocal last_t, last_phase
        now = time.monotonic()
        if now - last_t >= 2.0 or s.phase != last_phase:
            last_t, last_phase = now, s.phase
            print(f"      {s.line()}", flush=True)

    result = asyncio.run(
        run_demo(cfg, plan, out, camera=not args.no_camera, method=args.method, say=_say, on_status=status)
    )
    from flightkit.cli.capture import print_info

    print(result.summary.format_table())
    for p in result.plots:
        print(f"      plot: {p}")
    print(f"      capture info {result.recording}")
    print_info(result.recording)
    if result.vo is not None and result.vo_report is not None:
        from flightkit.cli.vo import print_report

        print_report(result.vo_report, result.vo_plots)
        vo = result.vo
        print(f"      {len(vo)} frames, {vo.fps:.0f} frames/s of processing ({vo.wall_s:.1f} s with decoding)")
    _say("6/6", f"mapping server map: {result.map_png}")
    _say("done", f"flight {result.summary.outcome}; everything is in {out}/")
    return 0 if result.ok else 1


def _run_fleet(args: argparse.Namespace, out: Path) -> int:
    from flightkit.apps.fleet import load_fleet_plan
    from flightkit.apps.fleet_demo import fleet_demo_config, run_fleet_demo
    from flightkit.config import load_config

    path = Path(args.config) if args.config else _REPO_EXAMPLES / "lab_sim.toml"
    cfg = fleet_demo_config(load_config(path) if path.is_file() else load_config(), args.speed)
    fplan = load_fleet_plan(Path(args.plan) if args.plan else _REPO_EXAMPLES / "fleet_circle.toml")
    last: dict[str, float] = {}

    def status(name: str, s: Any) -> None:
        now = time.monotonic()
        if now - last.get(name, 0.0) >= 2.0:
            last[name] = now
            print(f"      {name:>5} {s.line()}", flush=True)

    result = asyncio.run(run_fleet_demo(cfg, fplan, out, say=_say, on_status=status))
    print(result.flight.format_table())
    if result.recording_error:
        _say("4/4", f"recording stopped early: {result.recording_error}")
    _say("done", f"fleet {result.flight.outcome}; everything is in {out}/")
    return 0 if result.ok else 1
