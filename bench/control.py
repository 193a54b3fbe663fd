"""Control-loop benchmark: compute time, sample-to-wire latency, loop jitter and tracking error.

Two parts, both against the in-process simulated lab over real UDP:

1. **Timing** (wall time): take off and hold with the simulated mocap at 100 Hz and at 200 Hz.
   The simulator (``flightkit sim``: autopilot on UDP, mocap on the bus) runs in its own
   process, standing in for the hardware; this process holds what a companion computer runs:
   the link, the bus mocap source and the flight runner. A UDP sniffer, in a third process,
   sits between the link and the autopilot and timestamps every SET_POSITION_TARGET_LOCAL_NED
   as it passes; each one is matched to the mocap sample the runner had when it computed that
   setpoint, and its latency counts from the moment that sample reached this process (both
   CLOCK_MONOTONIC). Reported: control-cycle time p50/p99 (the runner's own measurement: pose,
   reference, supervisor, controller, send), as wall time and as the loop thread's CPU time
   (the compute alone, without waits for the GIL, the scheduler or the hypervisor; the
   "steal ms" column shows how much the hypervisor took), sample-to-wire latency p50/p99,
   loop period jitter. Each rate runs twice: setpoints sent at once (``send_now``) and, as the
   baseline, only by the link's 100 Hz stream thread.
2. **Tracking** (``SimClock(speed=5)``): the three example plans, two controllers side by side
   (``--compare``): by default today's velocity feed-forward vs position + velocity +
   acceleration targets (``setpoint = "pva"``); ``--compare velocity P`` gives the old table
   (feed-forward vs the lab's P-only law). Per flight: take-off and goto RMS, and the pattern
   phase's RMS, max, and max after its first 2 s.

Goals: cycle p99 < 1 ms, latency p99 < 3 ms, circle RMS >= 5x lower with feed-forward than
P-only; with pva on the simulated ArduPilot (``--autopilot ardupilot``): pattern RMS < 8 mm
and max after 2 s < 30 mm, take-off and goto RMS < 30 mm (issue 19; docs/benchmarks.md).

    .venv/bin/python bench/control.py            # full example plans (~5 min on 2 cores)
    .venv/bin/python bench/control.py --quick    # one lap each, faster sides (~2 min)
    .venv/bin/python bench/control.py --skip-timing --one-lap --autopilot ardupilot
    .venv/bin/python bench/control.py --like-for-like    # part 3 only (~6 min at 5x on a quiet host)

3. **Like for like** (``--like-for-like``): the simulated ArduPilot flown as the real ArduCopter run
   of issue 19 was (the runner of then: references up to the controller's limits, vertical limit
   0.3 m/s; mocap = the autopilot's own estimate republished at 100 Hz) and as today's runner and
   the band test fly it (sim truth as mocap), each row beside the real figures (docs/sim.md).
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import json
import logging
import math
import select
import socket
import struct
import subprocess
import sys
import time
from collections import deque
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink2

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # `bench._host` when run as a script

from bench._host import StealMeter  # noqa: E402
from flightkit.apps.sim_session import fly_plan_in_sim  # noqa: E402
from flightkit.errors import FlightkitError  # noqa: E402
from flightkit.link.base import VelocitySetpoint  # noqa: E402
from flightkit.link.mavlink import encode_velocity_setpoint  # noqa: E402
from trajectories.controller import OutputFrame, SetpointKind  # noqa: E402
from trajectories.flightlog import read_flight_log  # noqa: E402
from trajectories.plan import Plan, load_plan  # noqa: E402
from trajectories.runner import FlightRunner  # noqa: E402

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
SPM = mavlink2.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux; the cmsg type SCM_TIMESTAMPNS is the same
_TIMESPEC = struct.Struct("@qq")  # struct timespec on 64-bit Linux


# ---------------------------------------------------------------------------- the sniffer process


def sniffer_role(target_port: int) -> int:
    """A UDP relay between the link and the simulated autopilot, in a process of its own, that
    timestamps each SET_POSITION_TARGET_LOCAL_NED from the link with the kernel's receive time
    (SO_TIMESTAMPNS: when it was on the wire, not when this process woke up), expressed on
    CLOCK_MONOTONIC like ``time.monotonic`` in every process. Prints its port, relays until
    stdin closes, then prints one JSON list ``[[t_ns, vx, vy, vz, yaw, yaw_rate, frame], ...]``."""
    target = ("127.0.0.1", target_port)
    front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    front.bind(("127.0.0.1", 0))
    front.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    back.bind(("127.0.0.1", 0))
    mav = mavlink2.MAVLink(None)
    mav.robust_parsing = True
    client: tuple[str, int] | None = None
    seen: list[tuple[int, tuple[float, ...]]] = []
    print(front.getsockname()[1], flush=True)
    while True:
        ready, _, _ = select.select([front, back, sys.stdin], [], [])
        if sys.stdin in ready and not sys.stdin.readline():
            break
        if front in ready:
            data, ancillary, _, client = front.recvmsg(65535, socket.CMSG_SPACE(_TIMESPEC.size))
            back.sendto(data, target)
            # the kernel's receive stamp (CLOCK_REALTIME) on the CLOCK_MONOTONIC time line
            t_ns = time.monotonic_ns()
            for level, kind, cdata in ancillary:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                    sec, nsec = _TIMESPEC.unpack(cdata[: _TIMESPEC.size])
                    t_ns = sec * 1_000_000_000 + nsec - (time.time_ns() - time.monotonic_ns())
            for msg in mav.parse_buffer(data) or []:
                if msg.get_msgId() == SPM:
                    seen.append((t_ns, (msg.vx, msg.vy, msg.vz, msg.yaw, msg.yaw_rate, msg.coordinate_frame)))
        if back in ready:
            data = back.recv(65535)
            if client is not None:
                front.sendto(data, client)
    print(json.dumps([[t, *f] for t, f in seen]), flush=True)
    return 0


def _key(sp: VelocitySetpoint) -> tuple[float, ...]:
    f = encode_velocity_setpoint(sp)
    v = np.array([f.vx, f.vy, f.vz, f.yaw, f.yaw_rate], dtype=np.float32)
    return (*(float(x) for x in v), float(f.coordinate_frame))


def _wire_key(fields: Sequence[float]) -> tuple[float, ...]:
    v = np.array(fields[:5], dtype=np.float32)
    return (*(float(x) for x in v), float(fields[5]))


class Tap:
    """Delegates to the link; remembers which mocap sample (and when it was received) each
    setpoint was computed from."""

    def __init__(self, link: Any, mocap: Any, body: str, send_now: bool) -> None:
        self._link, self._mocap, self._body, self._send_now = link, mocap, body, send_now
        self.set: list[tuple[tuple[float, ...], float]] = []  # (setpoint key, sample received_s)
        self.called_s: list[float] = []

    def __getattr__(self, name: str) -> Any:
        return getattr(self._link, name)

    def set_velocity(self, setpoint: VelocitySetpoint, *, send_now: bool = False) -> None:
        self.called_s.append(time.monotonic())
        pose = self._mocap.latest(self._body)
        self.set.append((_key(setpoint), pose.received_s if pose is not None else math.nan))
        self._link.set_velocity(setpoint, send_now=send_now and self._send_now)


def match_latencies(tap: Tap, wire: Sequence[Sequence[float]]) -> list[float]:
    """Sample-received-to-wire latency (ms) of each setpoint's first appearance on the wire."""
    pending: deque[tuple[tuple[float, ...], float]] = deque(tap.set)
    out: list[float] = []
    last: tuple[float, ...] | None = None
    for t_ns, *fields in wire:
        k = _wire_key(fields)
        if k == last:
            continue  # a re-send by the stream
        for _ in range(min(len(pending), 50)):
            key, received_s = pending.popleft()
            if key == k:
                if math.isfinite(received_s):
                    out.append((t_ns / 1e9 - received_s) * 1e3)
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
    cpu_p50_ms: float
    cpu_p99_ms: float
    lat_p50_ms: float
    lat_p99_ms: float
    matched: int
    period_std_ms: float
    period_p99_ms: float


def _free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as sk:
        sk.bind(("127.0.0.1", 0))
        return int(sk.getsockname()[1])


LAB_TOML = """
[vehicle]
namespace = "uav1"
autopilot = "px4"
[link]
url = "udpout:127.0.0.1:{link_port}"
setpoint_rate_hz = 100
source_system = 250
[mocap]
source = "bus"
body = "uav1"
[bus]
{bus_role} = ["tcp/127.0.0.1:{bus_port}"]
[sim]
speed = 1.0
mocap_rate_hz = {rate_hz}
"""


async def _hover(
    cfg: Any, send_now: bool, hold_s: float
) -> tuple[Tap, tuple[list[float], list[float]], int]:
    """Take off, hold ``hold_s`` and land; the hold's (wall, CPU) seconds per cycle."""
    from flightkit.clock import WallClock
    from flightkit.link import open_link
    from trajectories.fly import open_lab_mocap

    clock = WallClock()
    async with open_link(cfg.link, cfg.vehicle.autopilot, clock) as link, open_lab_mocap(cfg, clock) as mocap:
        tap = Tap(link, mocap, cfg.mocap.body, send_now)
        runner = FlightRunner(tap, mocap, body=cfg.mocap.body, clock=clock)
        try:
            await runner.preflight()
            await runner.start(arm=True)
            await runner.takeoff(1.0, 0.5)
            tap.set.clear()
            tap.called_s.clear()
            t0 = len(runner.loop.cycle_s)
            await runner.hold(hold_s)
            cycles = (runner.loop.cycle_s[t0:], runner.loop.cycle_cpu_s[t0:])
            n_set = len(tap.set)
            await runner.land()
        finally:
            await runner.close()
    return tap, cycles, n_set


def timing_run(rate_hz: float, send_now: bool, hold_s: float, tmp: Path) -> Timing:
    """One hover on wall time with the simulator (autopilot + mocap on the bus, standing in for
    the hardware) and the sniffer in processes of their own; the link, the bus mocap source and
    the runner in this one, as on a companion computer."""
    from flightkit.config import load_config

    sim_port, bus_port = _free_port(socket.SOCK_DGRAM), _free_port(socket.SOCK_STREAM)
    sim_toml = tmp / f"sim-{rate_hz:g}.toml"
    sim_toml.write_text(LAB_TOML.format(link_port=0, bus_role="listen", bus_port=bus_port, rate_hz=rate_hz))
    with (tmp / "sim.log").open("w") as sim_log:
        sim = subprocess.Popen(
            [sys.executable, "-m", "flightkit", "sim", "--config", str(sim_toml), "--listen",
             f"udpin:127.0.0.1:{sim_port}", "--no-camera", "--ready-after", "0"],
            stdout=sim_log, stderr=sim_log,
        )
    sniff = subprocess.Popen(
        [sys.executable, __file__, "--role", "sniffer", "--target", str(sim_port)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )
    try:
        assert sniff.stdout is not None and sniff.stdin is not None
        sniff_port = int(sniff.stdout.readline())
        ctl_toml = tmp / f"ctl-{rate_hz:g}.toml"
        ctl_toml.write_text(
            LAB_TOML.format(link_port=sniff_port, bus_role="connect", bus_port=bus_port, rate_hz=rate_hz)
        )
        tap, cycles, n_set = asyncio.run(_hover(load_config(ctl_toml), send_now, hold_s))
        sniff.stdin.close()
        wire = json.loads(sniff.stdout.readline())
    finally:
        for proc in (sniff, sim):
            if proc.poll() is None:
                proc.terminate()
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
    tap.set = tap.set[:n_set]
    wire_after = [w for w in wire if w[0] / 1e9 >= tap.called_s[0]] if tap.called_s else wire
    lat = match_latencies(tap, wire_after)
    # loop period: time between control cycles (each sends one setpoint), against the mocap period
    periods_ms = np.diff(np.array(tap.called_s[:n_set])) * 1e3
    nominal = 1000.0 / rate_hz
    return Timing(
        rate_hz,
        send_now,
        pct(cycles[0], 50) * 1e3,
        pct(cycles[0], 99) * 1e3,
        pct(cycles[1], 50) * 1e3,
        pct(cycles[1], 99) * 1e3,
        pct(lat, 50),
        pct(lat, 99),
        len(lat),
        float(np.std(periods_ms - nominal)) if len(periods_ms) else math.nan,
        pct(np.abs(periods_ms - nominal), 99),
    )


# ---------------------------------------------------------------------------- part 2: tracking


def bench_plan(name: str, quick: bool, one_lap: bool = False) -> Plan:
    plan = load_plan(EXAMPLES / f"{name}.toml")
    plan = plan.with_changes(settings=dataclasses.replace(plan.settings, hold_before_s=1.0, hold_after_s=1.0))
    if quick or one_lap:
        plan = plan.with_changes(pattern=dataclasses.replace(plan.pattern, laps=1))
    if quick and name != "circle":
        plan = plan.with_changes(pattern=dataclasses.replace(plan.pattern, speed_m_s=0.25, turn_s=2.0))
    return plan


# The controllers compared: the lab's P-only law, today's velocity feed-forward (the baseline),
# and position + velocity + acceleration targets (in the autopilot's local frame).
CONTROLLERS: dict[str, dict[str, Any]] = {
    "P": {"feedforward": False},
    "velocity": {"feedforward": True},
    "pva": {"feedforward": True, "output_frame": OutputFrame.LOCAL_NED, "setpoint": SetpointKind.PVA},
}


async def tracking_run(
    plan: Plan, controller: str, speed: float, autopilot: str, tmp: Path, mocap_from_autopilot_hz: float = 0.0
) -> dict[str, Any]:
    """Fly ``plan`` with one of :data:`CONTROLLERS`; the phase figures (NaN when a fault ended it early)."""
    plan = plan.with_changes(controller=dataclasses.replace(plan.controller, **CONTROLLERS[controller]))
    log = tmp / f"{plan.name}-{autopilot}-{controller}-{time.time_ns()}.csv"
    summary = await fly_plan_in_sim(
        plan, autopilot=autopilot, speed=speed, log_path=log, mocap_from_autopilot_hz=mocap_from_autopilot_hz
    )
    nan = {k: math.nan for k in ("rms", "max", "max_after_2s", "takeoff_rms", "goto_rms", "land_rms")}
    try:
        pat = summary.phase("pattern")
    except KeyError:  # a fault ended the flight before the pattern: say so, do not crash the table
        faults = ", ".join(f.kind.value for f in summary.faults)
        print(f"  {plan.name} ({controller}): {summary.outcome} before the pattern ({faults})")
        return {**nan, "outcome": False, "faults": 1, "fault_kinds": faults}
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
        "takeoff_rms": summary.phase("takeoff").rms_error_m,
        "takeoff_max": summary.phase("takeoff").max_error_m,
        "goto_rms": summary.phase("goto").rms_error_m,
        "goto_max": summary.phase("goto").max_error_m,
        "land_rms": summary.phase("land").rms_error_m if "land" in [p.name for p in summary.phases] else math.nan,
        "outcome": summary.outcome == "completed",
        "faults": len(summary.faults),
        "fault_kinds": ", ".join(sorted({f.kind.value for f in summary.faults})),
    }


# ------------------------------------------------------------- part 3: like for like with the real run

# Real ArduCopter 4.7.0-dev SITL flown by the runner as it was then (issue 19, ../shared/FACTS.md):
# per plan, (low, high) of each figure in metres; the take-off, goto and landing ranges span the plans.
REAL_ARDUCOPTER: dict[str, dict[str, tuple[float, float]]] = {
    name: {
        "takeoff_rms": (0.060, 0.070),
        "takeoff_max": (0.109, 0.131),
        "goto_rms": (0.066, 0.069),
        "goto_max": (0.111, 0.125),
        "rms": (pat_rms, pat_rms),
        "max_after_2s": (pat_max, pat_max),
        "land_rms": (0.051, 0.052),
    }
    for name, pat_rms, pat_max in (("circle", 0.015, 0.023), ("rectangle", 0.014, 0.045), ("lawnmower", 0.013, 0.046))
}
# The runner of the real run: its take-off, transit and landing references ran up to the controller's
# limits, the vertical one 0.3 m/s (today: 80 % of 0.4 m/s).
RUNNER_THEN = {"reference_headroom": 1.0, "max_vertical_m_s": 0.3}
LIKE_COLUMNS = ("takeoff_rms", "takeoff_max", "goto_rms", "goto_max", "rms", "max_after_2s", "land_rms")


def runner_then(plan: Plan) -> Plan:
    """``plan`` flown as the real run's runner flew it (:data:`RUNNER_THEN`)."""
    return plan.with_changes(
        settings=dataclasses.replace(plan.settings, reference_headroom=RUNNER_THEN["reference_headroom"]),
        controller=dataclasses.replace(plan.controller, max_vertical_m_s=RUNNER_THEN["max_vertical_m_s"]),
    )


def like_for_like(speed: float, tmp: Path, plans: Sequence[str], one_lap: bool) -> None:
    """The real run's figures beside the simulated ArduPilot flown by that runner and today's, each on the
    autopilot's own estimate republished at 100 Hz (as the real run's mocap was) and on the sim's truth.
    The example plans are flown as they are, as the real run flew them (``one_lap``: one lap, 1 s holds)."""
    size = "one lap, 1 s holds" if one_lap else "the example plans as they are"
    print(f"like for like with real ArduCopter (pymavlink, velocity setpoints, sim speed {speed:g}, {size}), mm")
    print(f"{'plan':<10} {'runner / mocap':<16} " + " ".join(f"{c:>12}" for c in LIKE_COLUMNS))
    for name in plans:
        real = REAL_ARDUCOPTER[name]
        cells = [f"{lo * 1e3:.0f}" if lo == hi else f"{lo * 1e3:.0f}-{hi * 1e3:.0f}" for lo, hi in real.values()]
        print(f"{name:<10} {'real ArduCopter':<16} " + " ".join(f"{c:>12}" for c in cells), flush=True)
        for runner in ("then", "today"):
            plan = bench_plan(name, quick=False, one_lap=True) if one_lap else load_plan(EXAMPLES / f"{name}.toml")
            plan = runner_then(plan) if runner == "then" else plan
            for mocap, hz in (("estimate", 100.0), ("truth", 0.0)):
                try:
                    r = asyncio.run(tracking_run(plan, "velocity", speed, "ardupilot", tmp, mocap_from_autopilot_hz=hz))
                except FlightkitError as exc:  # a host stall can cost a command its ACK: say so, go on
                    r = {"outcome": False, "faults": 1, "error": str(exc)}
                row = " ".join(f"{r.get(c, math.nan) * 1e3:>12.0f}" for c in LIKE_COLUMNS)
                note = "" if r["outcome"] else f"  (did not complete: {r.get('error', r.get('fault_kinds', ''))})"
                print(f"{'':<10} {runner + ' / ' + mocap:<16} {row}{note}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description="control-loop benchmark against the simulated lab")
    ap.add_argument("--quick", action="store_true", help="one lap each, faster sides")
    ap.add_argument("--one-lap", action="store_true", help="one lap each at the plans' own speeds")
    ap.add_argument(
        "--compare",
        nargs=2,
        default=["velocity", "pva"],
        choices=sorted(CONTROLLERS),
        metavar=("BASELINE", "CANDIDATE"),
        help="the two controllers flown side by side (default: velocity pva; the old table: velocity P)",
    )
    ap.add_argument("--speed", type=float, default=5.0, help="sim speed of the tracking runs")
    ap.add_argument("--hold", type=float, default=8.0, help="seconds of hold measured per timing run")
    ap.add_argument("--autopilot", default="px4", choices=["px4", "ardupilot"])
    ap.add_argument("--skip-timing", action="store_true")
    ap.add_argument("--skip-tracking", action="store_true")
    ap.add_argument(
        "--like-for-like",
        action="store_true",
        help="only the ArduPilot flights beside the real run's figures: then/today's runner x estimate/truth mocap",
    )
    ap.add_argument("--plans", default="circle,rectangle,lawnmower", help="plans for --like-for-like")
    ap.add_argument("--role", choices=("main", "sniffer"), default="main", help=argparse.SUPPRESS)
    ap.add_argument("--target", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.role == "sniffer":
        sys.exit(sniffer_role(args.target))
    logging.basicConfig(level=logging.ERROR)
    tmp = Path("/tmp/flightkit-bench-control")
    tmp.mkdir(exist_ok=True)
    if args.like_for_like:
        like_for_like(args.speed, tmp, args.plans.split(","), args.one_lap)
        return

    if not args.skip_timing:
        print("timing (wall time; simulator and sniffer in their own processes; PX4 personality, pymavlink, hover)")
        print(
            f"{'mocap':>6} {'send':>9} {'cycle p50':>10} {'cycle p99':>10} {'cpu p50':>8} {'cpu p99':>8} "
            f"{'lat p50':>8} {'lat p99':>8} "
            f"{'n':>5} {'jitter sd':>9} {'jitter p99':>10} {'steal ms':>8}"
        )
        for rate in (100.0, 200.0):
            for send_now in (True, False):
                with StealMeter() as stolen:
                    r = timing_run(rate, send_now, args.hold, tmp)
                print(
                    f"{rate:>4.0f}Hz {'now' if send_now else 'stream':>9} {r.cycle_p50_ms:>8.3f}ms "
                    f"{r.cycle_p99_ms:>8.3f}ms {r.cpu_p50_ms:>6.3f}ms {r.cpu_p99_ms:>6.3f}ms "
                    f"{r.lat_p50_ms:>6.2f}ms {r.lat_p99_ms:>6.2f}ms {r.matched:>5} "
                    f"{r.period_std_ms:>7.3f}ms {r.period_p99_ms:>8.3f}ms {stolen.ms:>8.0f}",
                    flush=True,
                )
        print()

    if not args.skip_tracking:
        base, cand = args.compare
        size = "quick" if args.quick else ("one lap" if args.one_lap else "full example plans")
        print(f"tracking ({args.autopilot}, pymavlink, sim speed {args.speed:g}, {size}): {cand} vs {base}")
        print(
            f"{'pattern':<10} {'':>9} {'tkoff rms':>9} {'goto rms':>9} {'pat rms':>8} {'pat max':>8} {'max>2s':>8}"
        )
        for name in ("circle", "rectangle", "lawnmower"):
            plan = bench_plan(name, args.quick, args.one_lap)
            rows = {law: asyncio.run(tracking_run(plan, law, args.speed, args.autopilot, tmp)) for law in (cand, base)}
            for law, r in rows.items():
                print(
                    f"{name if law == cand else '':<10} {law:>9} {r['takeoff_rms'] * 1e3:>7.1f}mm "
                    f"{r['goto_rms'] * 1e3:>7.1f}mm {r['rms'] * 1e3:>6.1f}mm {r['max'] * 1e3:>6.1f}mm "
                    f"{r['max_after_2s'] * 1e3:>6.1f}mm"
                    + ("" if r["outcome"] else "  (did not complete)")
                    + (f"  ({r['faults']} fault(s), stale holds included)" if r["faults"] else ""),
                    flush=True,
                )
            print(f"{'':<10} {'ratio':>9} {rows[base]['rms'] / rows[cand]['rms']:>37.1f}x pattern RMS", flush=True)


if __name__ == "__main__":
    main()
