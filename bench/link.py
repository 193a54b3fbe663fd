"""Benchmark the pymavlink link: setpoint stream timing, command latency, simulator speed.

Run: ``.venv/bin/python bench/link.py [--seconds 3] [--commands 40]``

1. Setpoint stream at 50, 100 and 200 Hz on wall time, measured on the *receiving* side: a
   plain UDP socket playing autopilot, in a process of its own, timestamps every
   SET_POSITION_TARGET_LOCAL_NED. The period error is computed from the kernel's receive
   timestamps (SO_TIMESTAMPNS: when the datagram reached the socket, i.e. what an autopilot's
   UART/UDP driver sees) and, for comparison, from when the receiving process woke up to read
   it (which adds the receiver's own scheduling delay). Baselines in the same run: a naive loop
   that sleeps one period after each send (relative sleeps), which is what most scripts do,
   and a bare absolute-deadline sleep loop without I/O (the machine's scheduling floor).
2. Command round trip: MAV_CMD_COMPONENT_ARM_DISARM -> COMMAND_ACK through MavlinkLink
   against the simulated autopilot on wall time (arm and disarm alternate).
3. Real-time factor of the simulated autopilot at SimClock(speed=10): simulated seconds
   of vehicle dynamics per wall second.
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import socket
import statistics
import struct
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench._host import StealMeter  # noqa: E402
from flightkit.clock import SimClock, WallClock  # noqa: E402
from flightkit.config import Autopilot, LinkConfig  # noqa: E402
from flightkit.link.base import VelocitySetpoint  # noqa: E402
from flightkit.link.mavlink import MavlinkLink  # noqa: E402
from flightkit.sim.autopilot import AutopilotOptions, SimAutopilot  # noqa: E402
from flightkit.sim.personality import personality_for  # noqa: E402

SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux; the cmsg type SCM_TIMESTAMPNS is the same
_TIMESPEC = struct.Struct("@qq")  # struct timespec on 64-bit Linux


def _receiver_process(port_out: Any, cmd_in: Any) -> None:
    """Child process: answer with autopilot heartbeats and timestamp arriving setpoints."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.05)
    sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    port_out.send(sock.getsockname()[1])
    rx = mavlink2.MAVLink(None, 1, 1)
    rx.robust_parsing = True
    tx = mavlink2.MAVLink(None, 1, 1)
    arrivals: list[tuple[int, int]] = []  # (kernel receive time, process wake-up time), ns
    peer = None
    next_hb = 0.0
    while True:
        if cmd_in.poll():
            cmd = cmd_in.recv()
            if cmd == "clear":
                arrivals.clear()
            elif cmd == "get":
                port_out.send(list(arrivals))
            else:
                break
        try:
            data, ancillary, _, peer = sock.recvmsg(2048, socket.CMSG_SPACE(_TIMESPEC.size))
            t_app = time.time_ns()
            t_kernel = t_app
            for level, kind, cdata in ancillary:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                    sec, nsec = _TIMESPEC.unpack(cdata[: _TIMESPEC.size])
                    t_kernel = sec * 1_000_000_000 + nsec
            for m in rx.parse_buffer(data) or []:
                if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED":
                    arrivals.append((t_kernel, t_app))
        except TimeoutError:
            pass
        now = time.monotonic()
        if now >= next_hb and peer is not None:
            next_hb = now + 0.2
            sock.sendto(bytes(mavlink2.MAVLink_heartbeat_message(2, 12, 1, 0, 4, 3).pack(tx)), peer)
    sock.close()


class FakeReceiver:
    """A UDP autopilot stand-in in its own process (so it does not share our GIL)."""

    def __init__(self) -> None:
        self._data_parent, data_child = mp.Pipe()
        self._cmd_parent, cmd_child = mp.Pipe()
        self._proc = mp.Process(target=_receiver_process, args=(data_child, cmd_child), daemon=True)
        self._proc.start()
        self.port = int(self._data_parent.recv())

    def clear(self) -> None:
        self._cmd_parent.send("clear")

    def arrivals_ns(self) -> list[tuple[int, int]]:
        """(kernel receive time, receiver wake-up time) of each setpoint, ns."""
        self._cmd_parent.send("get")
        return list(self._data_parent.recv())

    def close(self) -> None:
        self._cmd_parent.send("stop")
        self._proc.join(5.0)


def period_stats(arrivals_ns: list[int], rate_hz: float) -> dict[str, float]:
    t = np.asarray(arrivals_ns, dtype=np.float64) / 1e9
    periods = np.diff(t)
    err_ms = np.abs(periods - 1.0 / rate_hz) * 1e3
    span = t[-1] - t[0]
    return {
        "rate_hz": (len(t) - 1) / span,
        "p50_ms": float(np.percentile(err_ms, 50)),
        "p99_ms": float(np.percentile(err_ms, 99)),
        "max_ms": float(err_ms.max()),
    }


def wire_stats(arrivals: list[tuple[int, int]], rate_hz: float) -> dict[str, float]:
    """Period statistics from the kernel stamps, plus the p99 seen by the woken receiver."""
    out = period_stats([k for k, _ in arrivals], rate_hz)
    out["app_p99_ms"] = period_stats([a for _, a in arrivals], rate_hz)["p99_ms"]
    return out


async def bench_link_stream(rate_hz: float, seconds: float) -> dict[str, float]:
    recv = FakeReceiver()
    link = MavlinkLink(
        LinkConfig(url=f"udpout:127.0.0.1:{recv.port}", setpoint_timeout_s=10.0), Autopilot.PX4
    )
    try:
        async with link:
            await link.start_setpoint_stream(rate_hz)
            await asyncio.sleep(0.3)
            recv.clear()
            end = time.monotonic() + seconds
            while time.monotonic() < end:  # a caller feeding at 20 Hz, as a controller would
                link.set_velocity(VelocitySetpoint((0.1, 0.0, 0.0)))
                await asyncio.sleep(0.05)
            arrivals = recv.arrivals_ns()
    finally:
        recv.close()
    return wire_stats(arrivals, rate_hz)


def bench_naive_stream(rate_hz: float, seconds: float) -> dict[str, float]:
    """Baseline: send, then time.sleep(period) (relative sleeps), from one thread."""
    recv = FakeReceiver()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    mav = mavlink2.MAVLink(None, 255, 191)
    period = 1.0 / rate_hz
    try:
        end = time.monotonic() + seconds + 0.3
        started = time.monotonic()
        while time.monotonic() < end:
            msg = mavlink2.MAVLink_set_position_target_local_ned_message(
                0, 1, 1, 1, 1479, 0, 0, 0, 0.1, 0, 0, 0, 0, 0, 0, 0
            )
            sock.sendto(bytes(msg.pack(mav)), ("127.0.0.1", recv.port))
            if time.monotonic() - started < 0.3:
                recv.clear()
            time.sleep(period)
        arrivals = recv.arrivals_ns()
    finally:
        sock.close()
        recv.close()
    return wire_stats(arrivals, rate_hz)


def bench_sleep_floor(rate_hz: float, seconds: float) -> dict[str, float]:
    """Reference: a bare absolute-deadline sleep loop (no I/O); the machine's scheduling floor."""
    period = 1.0 / rate_hz
    stamps: list[int] = []
    nxt = time.perf_counter()
    end = nxt + seconds
    while nxt < end:
        nxt += period
        time.sleep(max(0.0, nxt - time.perf_counter()))
        stamps.append(time.perf_counter_ns())
    return period_stats(stamps, rate_hz)


async def bench_commands(n: int) -> dict[str, float]:
    clock = WallClock()
    opts = AutopilotOptions(url="udpin:127.0.0.1:0", ready_after_s=0.0)
    sim = SimAutopilot(personality_for(Autopilot.ARDUPILOT), clock=clock, options=opts)
    sim.start()
    latencies_ms: list[float] = []
    try:
        async with MavlinkLink(LinkConfig(url=sim.client_url), Autopilot.ARDUPILOT, clock) as link:
            await asyncio.sleep(1.0)  # let the stream requests settle
            for i in range(n):
                t0 = time.perf_counter()
                result = await link.command_long(mavlink2.MAV_CMD_COMPONENT_ARM_DISARM, (float((i + 1) % 2),))
                latencies_ms.append((time.perf_counter() - t0) * 1e3)
                assert result == 0, result
                await link.wait_for(lambda t, armed=bool((i + 1) % 2): t.armed == armed, 2.0, "armed state")
    finally:
        sim.stop()
    return {
        "p50_ms": statistics.median(latencies_ms),
        "p99_ms": float(np.percentile(latencies_ms, 99)),
        "max_ms": max(latencies_ms),
    }


def bench_sim_rtf(speed: float, seconds: float) -> float:
    clock = SimClock(speed)
    opts = AutopilotOptions(url="udpin:127.0.0.1:0", ready_after_s=0.0)
    sim = SimAutopilot(personality_for(Autopilot.PX4), clock=clock, options=opts)
    sim.start()
    try:
        time.sleep(0.2)
        s0, w0 = sim.truth().time_s, time.monotonic()
        time.sleep(seconds)
        s1, w1 = sim.truth().time_s, time.monotonic()
    finally:
        sim.stop()
    return (s1 - s0) / (w1 - w0)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=3.0, help="seconds per stream measurement")
    parser.add_argument("--commands", type=int, default=40, help="commands for the latency measurement")
    parser.add_argument("--rates", type=float, nargs="+", default=[50.0, 100.0, 200.0], help="stream rates (Hz)")
    parser.add_argument("--stream-only", action="store_true", help="skip the command and real-time-factor parts")
    args = parser.parse_args()

    print("setpoint stream over UDP loopback, period error = |period - 1/rate| from kernel receive stamps;")
    print("'woken p99' is the same from when the receiving process woke up (adds its scheduling delay);")
    print("'steal ms': CPU time the hypervisor took from this VM during the row (bench/_host.py)")
    print(
        f"{'sender':<28}{'target Hz':>10}{'achieved Hz':>13}{'p50 ms':>9}{'p99 ms':>9}{'max ms':>9}"
        f"{'woken p99':>11}{'steal ms':>11}"
    )
    for rate in args.rates:
        runs = (
            ("MavlinkLink (deadlines)", lambda r=rate: asyncio.run(bench_link_stream(r, args.seconds))),
            ("naive sleep(period)", lambda r=rate: bench_naive_stream(r, args.seconds)),
            ("bare sleep loop (floor)", lambda r=rate: bench_sleep_floor(r, args.seconds)),
        )
        for name, fn in runs:
            with StealMeter() as stolen:
                r = fn()
            woken = f"{r['app_p99_ms']:>11.3f}" if "app_p99_ms" in r else f"{'-':>11}"
            print(
                f"{name:<28}{rate:>10.0f}{r['rate_hz']:>13.2f}{r['p50_ms']:>9.3f}{r['p99_ms']:>9.3f}{r['max_ms']:>9.3f}"
                + woken
                + f"{stolen.ms:>11.0f}",
                flush=True,
            )
    print()
    if args.stream_only:
        return 0
    c = asyncio.run(bench_commands(args.commands))
    print(f"COMMAND_LONG arm/disarm -> COMMAND_ACK vs simulated ArduPilot, n={args.commands}")
    print(f"  p50 {c['p50_ms']:.2f} ms   p99 {c['p99_ms']:.2f} ms   max {c['max_ms']:.2f} ms")
    print()
    for speed in (10.0, 50.0):
        rtf = bench_sim_rtf(speed, min(args.seconds, 2.0))
        print(f"simulated autopilot at SimClock(speed={speed:g}): real-time factor {rtf:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
