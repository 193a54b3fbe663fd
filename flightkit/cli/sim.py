"""``flightkit sim``: run the simulated lab (autopilot on a UDP port, vehicle, mocap) until Ctrl-C."""

from __future__ import annotations

import argparse
import math
from typing import Any

__all__ = ["register", "run"]


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "sim",
        help="run the simulated lab: a PX4- or ArduPilot-like autopilot on a real UDP port",
        description=(
            "Run a simulated vehicle and its autopilot speaking MAVLink 2 over UDP, like PX4 or "
            "ArduPilot SITL. By default it listens on udpin:127.0.0.1:14540 and answers every client "
            "that sends to it (connect with udpout:127.0.0.1:14540, or MAVSDK udpout://127.0.0.1:14540)."
        ),
    )
    p.add_argument(
        "--autopilot", choices=["px4", "ardupilot"], help="firmware personality (default: from config)"
    )
    where = p.add_mutually_exclusive_group()
    where.add_argument(
        "--listen", metavar="URL", help="udpin:HOST:PORT to listen on (default udpin:127.0.0.1:14540)"
    )
    where.add_argument(
        "--connect", metavar="URL", help="udpout:HOST:PORT of a listening client (as PX4 SITL does)"
    )
    p.add_argument(
        "--speed", type=float, help="simulated seconds per wall second (default: config sim.speed)"
    )
    p.add_argument("--config", metavar="LAB.toml", help="lab config file")
    p.add_argument(
        "--ready-after",
        type=float,
        default=2.0,
        metavar="S",
        help="seconds until the estimator is ready and arming is allowed (default 2)",
    )
    p.add_argument(
        "--heading-offset-deg",
        type=float,
        default=0.0,
        help="rotation of the autopilot's local frame (its north) about the lab's z axis",
    )
    p.add_argument(
        "--signing-key", metavar="HEX", help="MAVLink 2 signing key, 64 hex digits (default: config)"
    )
    p.add_argument(
        "--vehicles", type=int, metavar="N",
        help="a fleet of N vehicles uav1..uavN, on ports 14540.. (or the config's [[vehicles]])",
    )
    p.add_argument(
        "--shared-link", choices=["udp", "pty"],
        help="with --vehicles: every vehicle behind one link, each with its own system id: one UDP port "
        "(the --listen port, default 14540) as a router gives, or one pseudo-terminal as a telemetry radio",
    )
    p.add_argument("--no-mocap", action="store_true", help="do not publish simulated mocap on the bus")
    p.add_argument(
        "--no-camera", action="store_true", help="do not publish the simulated camera streams on the bus"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import dataclasses
    import threading

    from flightkit.apps.sim_lab import SimLabServed, serve_sim_lab
    from flightkit.config import load_config
    from flightkit.errors import ConfigError
    from flightkit.sim.autopilot import AutopilotOptions
    from flightkit.sim.lab import SimEvent

    config = load_config(args.config) if args.config else load_config()
    speed = args.speed if args.speed is not None else config.sim.speed
    if not (speed > 0 and math.isfinite(speed)):
        raise ConfigError(
            "<command line>", "--speed", f"{speed!r} is not a positive number", "give e.g. --speed 5"
        )
    config = dataclasses.replace(config, sim=dataclasses.replace(config.sim, speed=float(speed)))
    url = args.connect or args.listen or "udpin:127.0.0.1:14540"
    key_hex = args.signing_key if args.signing_key is not None else config.link.signing_key_hex
    key: bytes | None = None
    if key_hex:
        try:
            key = bytes.fromhex(key_hex)
        except ValueError:
            key = b""
        if len(key) != 32:
            raise ConfigError("<command line>", "signing key", "is not 64 hex digits", "give 32 bytes as hex")
    options = AutopilotOptions(
        url=url,
        ready_after_s=args.ready_after,
        heading_offset_rad=math.radians(args.heading_offset_deg),
        signing_key=key,
    )

    if args.vehicles is not None or config.vehicles:
        return _run_fleet(args, config)
    if args.shared_link:
        from flightkit.errors import ConfigError

        raise ConfigError("<command line>", "--shared-link", "one vehicle has no link to share",
                          "add --vehicles N (or a config with [[vehicles]])", args.shared_link)

    def show(event: SimEvent) -> None:
        if event.kind in ("param",):
            return
        print(f"[t={event.stamp_s:8.2f} s] {event.kind}: {event.detail}", flush=True)

    def ready(served: SimLabServed) -> None:
        lab = served.lab
        print(f"flightkit sim: {lab.personality.vehicle_name}, {lab.clock!r}")
        if url.startswith("udpout"):
            print(f"  MAVLink: sending to {url.split(':', 1)[1].lstrip('/')} from local port {lab.port}")
        else:
            print(
                f"  MAVLink: listening on {lab.url}; connect with {lab.client_url} "
                f"(MAVSDK: udpout://{lab.client_url.split(':', 1)[1]})"
            )
        if key is not None:
            print("  MAVLink 2 signing: on (unsigned messages are ignored)")
        if served.keys:
            print(f"  bus: mocap (PoseStamped in the mocap frame) and camera on {', '.join(served.keys)}")
        if served.camera_error:
            print(f"  camera: not published ({served.camera_error})")
        print("  Ctrl-C to stop")

    stop = threading.Event()
    try:
        serve_sim_lab(
            config,
            options,
            stop,
            autopilot=args.autopilot,
            mocap=not args.no_mocap,
            camera=not args.no_camera,
            on_event=show,
            on_ready=ready,
        )
    except KeyboardInterrupt:
        print("flightkit sim: stopping")
    return 0


def _run_fleet(args: argparse.Namespace, config: Any) -> int:
    import threading

    from flightkit.apps.sim_lab import SimFleetServed, serve_sim_fleet
    from flightkit.errors import ConfigError
    from flightkit.sim.fleet import fleet_lab_config
    from flightkit.sim.lab import SimEvent

    if args.connect or args.signing_key or args.heading_offset_deg:
        raise ConfigError(
            "<command line>", "--vehicles", "a fleet takes neither --connect, --signing-key nor --heading-offset-deg",
            "run one vehicle with those, or a fleet without them",
        )
    if args.vehicles is not None:
        config = fleet_lab_config(config, args.vehicles)
    base_port = 14540
    host = "127.0.0.1"
    if args.listen:
        host, _, port = args.listen.split(":", 1)[1].rpartition(":")
        base_port = int(port)

    def show(name: str, event: SimEvent) -> None:
        if event.kind != "param":
            print(f"[t={event.stamp_s:8.2f} s] {name}: {event.kind}: {event.detail}", flush=True)

    def ready(served: SimFleetServed) -> None:
        fleet = served.fleet
        print(f"flightkit sim: a fleet of {len(fleet.labs)}, {fleet.clock!r}")
        for name, lab in fleet.labs.items():
            print(f"  {name}: {lab.personality.vehicle_name}, mocap body {fleet.body_of(name)!r}, "
                  f"system id {fleet.system_ids[name]}, "
                  f"connect with {fleet.client_url(name)}")
        if served.keys:
            print(f"  bus: {', '.join(served.keys)}")
        if served.camera_error:
            print(f"  cameras: not published ({served.camera_error})")
        print("  Ctrl-C to stop")

    stop = threading.Event()
    try:
        serve_sim_fleet(
            config, stop, base_port=base_port, host=host or "127.0.0.1", ready_after_s=args.ready_after,
            shared_link=args.shared_link, mocap=not args.no_mocap, camera=not args.no_camera, on_event=show,
            on_ready=ready,
        )
    except KeyboardInterrupt:
        print("flightkit sim: stopping")
    return 0
