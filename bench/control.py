"""Control-loop benchmark: compute time, sample-to-wire latency, loop jitter and tracking error.

Two parts, both against the in-process simulated lab over real UDP:

1. **Timing** (wall time, ``SimClock(speed=1)``): take off and hold with the simulated mocap at
   100 Hz and at 200 Hz. A UDP sniffer sits between the link and the simulated autopilot and
   timestamps every SET_POSITION_TARGET_LOCAL_NED as it passes; each one is matched to the mocap
   sample the runner had when it computed that setpoint, whose publication time the mocap
   source's hook recorded. Reported: control-cycle compute time p50/p99 (the runner's own
   measurement: pose, reference, supervisor, controller, send), sample-to-wire latency p50/p99,
   loop period jitter. Each rate runs twice: setpoints sent at once (``send_now``) and, as the
   baseline, only by the link's 100 Hz stream thread.
2. **Tracking** (``SimClock(speed=5)``): the three example plans, feed-forward controller vs
   the lab's P-only law (``feedforward = false``), side by side: RMS and max error of the
   pattern phase (after take-off, the hold and the move to the start).

Goals: cycle p99 < 1 ms, latency p99 < 3 ms, circle RMS >= 5x lower with feed-forward,
every pattern within 0.05 m max with feed-forward.

    .venv/bin/python bench/control.py            # full example plans (~5 min on 2 cores)
    .venv/bin/python bench/control.py --quick    # one lap each, faster sides (~2 min)
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import logging
import math
import select
import socket
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink2

from flightkit.clock import SimClock
from flightkit.config import LabConfig
from flightkit.link.base import VelocitySetpoint
from flightkit.link.mavlink import encode_velocity_setpoint
from trajectories.flightlog import read_flight_log
from trajectories.plan import Plan, load_plan
from trajectories.runner import FlightRunner
from trajectories.simulated import fly_plan_in_sim, sim_session

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
SPM = mavlink2.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED


# ---------------------------------------------------------------------------- the sniffer


class Sniffer:
    """A UDP relay between the link and the simulated autopilot that timestamps setpoints.

    The link connects to :attr:`port`; datagrams go on to ``target`` and replies come back.
    Every SET_POSITION_TARGET_LOCAL_NED from the link is recorded as (perf_counter_ns at
    receipt, fields) before it is forwarded.
    """

    def __init__(self, target: tuple[str, int]) -> None:
        self.target = target
        self.front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.front.bind(("127.0.0.1", 0))
        self.back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.back.bind(("127.0.0.1", 0))
        self.port = self.front.getsockname()[1]
        self.client: tuple[str, int] | None = None
        self.setpoints: list[tuple[int, tuple[float, ...]]] = []
        self._mav = mavlink2.MAVLink(None)
        self._mav.robust_parsing = True
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sniffer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self.front, self.back], [], [], 0.1)
            for sock in ready:
                data, addr = sock.recvfrom(65535)
                t_ns = time.perf_counter_ns()
                if sock is self.front:
                    self.client = addr
                    self.back.sendto(data, self.target)
                    for msg in self._mav.parse_buffer(data) or []:
                        if msg.get_msgId() == SPM:
                            self.setpoints.append(
                                (t_ns, (msg.vx, msg.vy, msg.vz, msg.yaw, msg.yaw_rate, msg.coordinate_frame))
                            )
                elif self.client is not None:
                    self.front.sendto(data, self.client)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.front.close()
        self.back.close()


def _key(sp: VelocitySetpoint) -> tuple[float, ...]:
    f = encode_velocity_setpoint(sp)
    v = np.array([f.vx, f.vy, f.vz, f.yaw, f.yaw_rate], dtype=np.float32)
    return (*(float(x) for x in v), float(f.coordinate_frame))


def _wire_key(fields: tuple[float, ...]) -> tuple[float, ...]:
    v = np.array(fields[:5], dtype=np.float32)
    return (*(float(x) for x in v), float(fields[5]))


class Tap:
    """Delegates to the link; remembers which mocap sample each setpoint was computed from."""

    def __init__(self, link: Any, mocap: Any, body: str, send_now: bool) -> None:
        self._link, self._mocap, self._body, self._send_now = link, mocap, body, send_now
        self.set: list[tuple[tuple[float, ...], int]] = []
        self.called_s: list[float] = []

    def __getattr__(self, name: str) -> Any:
        return getattr(self._link, name)

    def set_velocity(self, setpoint: VelocitySetpoint, *, send_now: bool = False) -> None:
        self.called_s.append(time.perf_counter())
        pose = self._mocap.latest(self._body)
        self.set.append((_key(setpoint), pose.seq if pose is not None else -1))
        self._link.set_velocity(setpoint, send_now=send_now and self._send_now)


def match_latencies(
    tap: Tap, wire: list[tuple[int, tuple[float, ...]]], published: dict[int, int]
) -> list[float]:
    """Sample-to-wire latency (ms) of each setpoint's first appearance on the wire, in order."""
    pending: deque[tuple[tuple[float, ...], int]] = deque(tap.set)
    out: list[float] = []
    last: tuple[float, ...] | None = None
    for t_ns, fields in wire:
        k = _wire_key(fields)
        if k == last:
            continue  # a re-send by the stream
        for _ in range(min(len(pending), 50)):
            key, seq = pending.popleft()
            if key == k:
                if seq in published:
                    out.append((t_ns - published[seq]) / 1e6)
                last = k
                break
    return out


def pct(values: list[float] | np.ndarray, q: float) -> float:
    return float(np.percentile(values, q)) if len(values) else math.nan


# ---------------------------------------------------------------------------- part 1: timing


@dataclasses.dataclass
class Timing:
    rate_hz: float
    send_now: bool
    cycle_p50_ms: float
    cycle_p99_ms: float
    lat_p50_ms: float
    lat_p99_ms: float
    matched: int
    period_std_ms: float
    period_p99_ms: float


async def timing_run(rate_hz: float, send_now: bool, hold_s: float, tmp: Path) -> Timing:
    cfg = LabConfig()
    async with sim_session(cfg, autopilot="px4", clock=SimClock(1.0), mocap_rate_hz=rate_hz) as s:
        # re-route the link through the sniffer: a second link on the relay's port
        sniff = Sniffer(s.lab.autopilot.bound_address)
        from flightkit.link import open_link

        link_cfg = dataclasses.replace(s.config.link, url=f"udpout:127.0.0.1:{sniff.port}", source_system=250)
        published: dict[int, int] = {}
        s.mocap.hooks.append(lambda p: published.__setitem__(p.seq, time.perf_counter_ns()))
        try:
            async with open_link(link_cfg, s.config.vehicle.autopilot, s.clock) as link:
                tap = Tap(link, s.mocap, s.config.mocap.body, send_now)
                runner = FlightRunner(
                    tap,
                    s.mocap,
                    body=s.config.mocap.body,  # type: ignore[arg-type]
                    autopilot=s.config.vehicle.autopilot,
                    clock=s.clock,
                )
                try:
                    await runner.preflight()
                    await runner.start(arm=True)
                    await runner.takeoff(1.0, 0.5)
                    tap.set.clear()
                    tap.called_s.clear()
                    sniff.setpoints.clear()
                    t0 = len(runner._cycle_s)
                    await runner.hold(hold_s)
                    cycles = sorted(runner._cycle_s[t0:])
                    n_set = len(tap.set)
                    await runner.land()
                finally:
                    await runner.close()
        finally:
            sniff.close()
    tap.set = tap.set[:n_set]
    lat = match_latencies(tap, sniff.setpoints, published)
    # loop period: time between control cycles (each sends one setpoint), against the mocap period
    periods_ms = np.diff(np.array(tap.called_s[:n_set])) * 1e3
    nominal = 1000.0 / rate_hz
    return Timing(
        rate_hz,
        send_now,
        pct(cycles, 50) * 1e3,
        pct(cycles, 99) * 1e3,
        pct(lat, 50),
        pct(lat, 99),
        len(lat),
        float(np.std(periods_ms - nominal)) if len(periods_ms) else math.nan,
        pct(np.abs(periods_ms - nominal), 99),
    )


# ---------------------------------------------------------------------------- part 2: tracking


def bench_plan(name: str, quick: bool) -> Plan:
    plan = load_plan(EXAMPLES / f"{name}.toml")
    plan = plan.with_changes(settings=dataclasses.replace(plan.settings, hold_before_s=1.0, hold_after_s=1.0))
    if quick:
        pat = dataclasses.replace(plan.pattern, laps=1)
        if name != "circle":
            pat = dataclasses.replace(pat, speed_m_s=0.25, turn_s=2.0)
        plan = plan.with_changes(pattern=pat)
    return plan


async def tracking_run(
    plan: Plan, feedforward: bool, speed: float, autopilot: str, tmp: Path
) -> dict[str, float]:
    plan = plan.with_changes(controller=dataclasses.replace(plan.controller, feedforward=feedforward))
    log = tmp / f"{plan.name}-{autopilot}-{'ff' if feedforward else 'p'}-{time.time_ns()}.csv"
    summary = await fly_plan_in_sim(plan, autopilot=autopilot, speed=speed, log_path=log)
    try:
        pat = summary.phase("pattern")
    except KeyError:  # a fault ended the flight before the pattern: say so, do not crash the table
        faults = ", ".join(f.kind.value for f in summary.faults)
        law = "FF" if feedforward else "P"
        print(f"  {plan.name} ({law}): {summary.outcome} before the pattern ({faults})")
        return {"rms": math.nan, "max": math.nan, "max_after_2s": math.nan, "outcome": False, "faults": 1}
    data = read_flight_log(log)
    sel = (data["phase"] == "pattern") & (data["action"] == "CONTINUE")
    err = data["err_m"][sel]
    t = data["t_s"][sel]
    # the same figures without the first 2 s of the pattern (the hand-over from the move to the start)
    late = err[t > t[0] + 2.0] if len(t) else err
    return {
        "rms": pat.rms_error_m,
        "max": pat.max_error_m,
        "max_after_2s": float(np.max(late)) if len(late) else math.nan,
        "outcome": summary.outcome == "completed",
        "faults": len(summary.faults),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description="control-loop benchmark against the simulated lab")
    ap.add_argument("--quick", action="store_true", help="one lap each, faster sides")
    ap.add_argument("--speed", type=float, default=5.0, help="sim speed of the tracking runs")
    ap.add_argument("--hold", type=float, default=8.0, help="seconds of hold measured per timing run")
    ap.add_argument("--autopilot", default="px4", choices=["px4", "ardupilot"])
    ap.add_argument("--skip-timing", action="store_true")
    ap.add_argument("--skip-tracking", action="store_true")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    tmp = Path("/tmp/flightkit-bench-control")
    tmp.mkdir(exist_ok=True)

    if not args.skip_timing:
        print("timing (wall time, SimClock speed 1, PX4 personality, pymavlink, hover)")
        print(
            f"{'mocap':>6} {'send':>9} {'cycle p50':>10} {'cycle p99':>10} {'lat p50':>8} {'lat p99':>8} "
            f"{'n':>5} {'jitter sd':>9} {'jitter p99':>10}"
        )
        for rate in (100.0, 200.0):
            for send_now in (True, False):
                r = asyncio.run(timing_run(rate, send_now, args.hold, tmp))
                print(
                    f"{rate:>4.0f}Hz {'now' if send_now else 'stream':>9} {r.cycle_p50_ms:>8.3f}ms "
                    f"{r.cycle_p99_ms:>8.3f}ms {r.lat_p50_ms:>6.2f}ms {r.lat_p99_ms:>6.2f}ms {r.matched:>5} "
                    f"{r.period_std_ms:>7.3f}ms {r.period_p99_ms:>8.3f}ms",
                    flush=True,
                )
        print()

    if not args.skip_tracking:
        print(
            f"tracking, pattern phase ({args.autopilot}, pymavlink, sim speed {args.speed:g}, "
            f"{'quick' if args.quick else 'full example plans'})"
        )
        print(
            f"{'pattern':<10} {'FF rms':>8} {'FF max':>8} {'FF max>2s':>9} "
            f"{'P rms':>8} {'P max':>8} {'ratio':>6}"
        )
        for name in ("circle", "rectangle", "lawnmower"):
            plan = bench_plan(name, args.quick)
            ff = asyncio.run(tracking_run(plan, True, args.speed, args.autopilot, tmp))
            p = asyncio.run(tracking_run(plan, False, args.speed, args.autopilot, tmp))
            print(
                f"{name:<10} {ff['rms'] * 1e3:>6.1f}mm {ff['max'] * 1e3:>6.1f}mm "
                f"{ff['max_after_2s'] * 1e3:>7.1f}mm "
                f"{p['rms'] * 1e3:>6.1f}mm {p['max'] * 1e3:>6.1f}mm {p['rms'] / ff['rms']:>5.1f}x"
                + ("" if ff["outcome"] and p["outcome"] else "  (a flight did not complete)"),
                flush=True,
            )


if __name__ == "__main__":
    main()
