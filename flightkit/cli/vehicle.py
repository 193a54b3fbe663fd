"""``flightkit vehicle``: talk to an autopilot without flying.

``flightkit vehicle status --connect udpin:0.0.0.0:14540`` waits for the autopilot's
heartbeat, collects a moment of telemetry and prints who it is, what state it is in and what
it would do if flightkit stopped (its failsafe parameters, as the preflight reads them;
``--json`` for scripts). It never arms or commands anything.
"""

from __future__ import annotations

import argparse
import math
import sys
from typing import Any

__all__ = ["register", "run"]


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser("vehicle", help="inspect a connected autopilot (no flying)")
    sub = parser.add_subparsers(dest="vehicle_command", metavar="ACTION")
    status = sub.add_parser(
        "status",
        help="print heartbeat, autopilot, mode, armed, position and battery",
        description="Connect, wait for the autopilot's HEARTBEAT, and print its state.",
    )
    status.add_argument(
        "--connect", metavar="URL", help="MAVLink connection string (default: link.url of --config)"
    )
    status.add_argument("--config", metavar="TOML", help="lab config file (link and vehicle sections)")
    status.add_argument(
        "--timeout", type=float, metavar="S", help="seconds to wait for the heartbeat (default 5)"
    )
    status.add_argument(
        "--listen",
        type=float,
        default=1.5,
        metavar="S",
        help="seconds of telemetry to collect after it (default 1.5)",
    )
    status.add_argument("--json", action="store_true", help="print one JSON object")
    status.set_defaults(func=run)
    parser.set_defaults(func=lambda args: _usage(parser))


def _usage(parser: argparse.ArgumentParser) -> int:
    parser.print_help(sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    import asyncio
    import dataclasses

    from flightkit.config import load_config
    from flightkit.errors import EndpointError
    from flightkit.link.endpoints import parse_endpoint

    cfg = load_config(args.config) if args.config else load_config()
    link_cfg = cfg.link
    if args.connect:
        link_cfg = dataclasses.replace(link_cfg, url=args.connect)
    if args.timeout is not None:
        if not (math.isfinite(args.timeout) and args.timeout > 0):
            print(
                f"flightkit: error: --timeout must be a positive number of seconds, got {args.timeout}",
                file=sys.stderr,
            )
            return 2
        link_cfg = dataclasses.replace(link_cfg, heartbeat_timeout_s=args.timeout)
    try:
        parse_endpoint(link_cfg.url, link_cfg.baud)
    except EndpointError as exc:
        print(f"flightkit: error: {exc}", file=sys.stderr)
        return 2
    report = asyncio.run(_status(link_cfg, cfg.vehicle.autopilot, max(0.0, args.listen)))
    if args.json:
        import json

        print(json.dumps(report, indent=2, allow_nan=False, default=str))
    else:
        _print_report(report)
    return 0


async def _status(link_cfg: Any, autopilot: Any, listen_s: float) -> dict[str, Any]:
    from flightkit.clock import WallClock
    from flightkit.link.base import read_companion_loss
    from flightkit.link.mavlink import MavlinkLink

    clock = WallClock()
    async with MavlinkLink(link_cfg, autopilot, clock) as link:
        info = link.info
        try:
            await link.wait_for(
                lambda t: not math.isnan(t.pos_local_enu_m[0]) and not math.isnan(t.battery.voltage_v),
                listen_s,
                "telemetry",
            )
        except Exception:  # noqa: BLE001 - partial telemetry is still worth printing
            pass
        await clock.sleep(min(0.3, listen_s))  # let a firmware version or a status text trail in
        info = link.info
        tel = link.telemetry
        stats = link.stats
        companion_loss = await read_companion_loss(link)

        def num(x: float, digits: int = 3) -> float | None:
            return None if math.isnan(x) or math.isinf(x) else round(x, digits)

        return {
            "endpoint": link.endpoint.url,
            "system_id": info.system_id,
            "component_id": info.component_id,
            "autopilot": info.autopilot.value,
            "vehicle_type": info.vehicle_type,
            "firmware_version": info.firmware_version or None,
            "heartbeat_age_s": num(tel.heartbeat_age_s),
            "mode": tel.mode.value,
            "custom_mode": tel.custom_mode,
            "armed": tel.armed,
            "landed_state": tel.landed_state.name,
            "position_enu_m": None
            if math.isnan(tel.pos_local_enu_m[0])
            else [num(x) for x in tel.pos_local_enu_m],
            "yaw_enu_deg": num(math.degrees(tel.yaw_local_rad), 1),
            "battery_voltage_v": num(tel.battery.voltage_v, 2),
            "battery_remaining_pct": num(tel.battery.remaining_pct, 0),
            "statustext": list(link.statustext[-5:]),
            "packets_received": stats.packets_received,
            "packets_rejected": stats.packets_rejected,
            "companion_loss": companion_loss.summary,
            "hovers_on_companion_loss": companion_loss.hovers,
        }


def _print_report(r: dict[str, Any]) -> None:
    def show(value: Any, unit: str = "") -> str:
        if value is None:
            return "-"
        if isinstance(value, list):
            return "[" + ", ".join(f"{v:.2f}" for v in value) + "]" + unit
        return f"{value}{unit}"

    rows = [
        ("endpoint", r["endpoint"]),
        (
            "heartbeat",
            f"system {r['system_id']} component {r['component_id']}, age {show(r['heartbeat_age_s'], ' s')}",
        ),
        (
            "autopilot",
            f"{r['autopilot']} {r['firmware_version'] or ''}".strip() + f" (MAV_TYPE {r['vehicle_type']})",
        ),
        ("mode", f"{r['mode']} (custom_mode {r['custom_mode']})"),
        ("armed", "yes" if r["armed"] else "no"),
        ("landed", r["landed_state"]),
        ("position", show(r["position_enu_m"], " m ENU") + f", yaw {show(r['yaw_enu_deg'], ' deg')}"),
        ("battery", f"{show(r['battery_voltage_v'], ' V')}, {show(r['battery_remaining_pct'], ' %')}"),
        ("failsafe", r["companion_loss"] + (" (fly refuses to arm)" if r["hovers_on_companion_loss"] else "")),
    ]
    width = max(len(k) for k, _ in rows)
    for key, value in rows:
        print(f"{key:<{width}}  {value}")
    for line in r["statustext"]:
        print(f"{'text':<{width}}  {line}")
