"""Fleet benchmark: control cost and tracking as the fleet grows (1, 3, 5, 10 vehicles, one process).

Every vehicle flies one circle, evenly spaced around it, in real time. The simulated lab runs in
its own process (``flightkit sim`` with the fleet's ``[[vehicles]]``: an autopilot per vehicle on
its own UDP port, one mocap system publishing every body on the bus), standing in for the
hardware; this process holds what a lab's ground computer runs: one
:class:`~trajectories.fleet.Fleet` with a MAVLink link and a bus mocap subscription per vehicle,
at ``rate_hz`` each (the loop also wakes on every mocap sample). The one-vehicle run is the
baseline, in the same run.

Reported per fleet size:
- per vehicle, cycle p50/p99 as the loop thread's CPU time (the compute, without waits) and as
  wall time (including waits for the GIL while other vehicles' loops run);
- per vehicle, the loop's achieved rate (cycles per second of flight): median and slowest vehicle;
- CPU use in cores over the whole flight of this process (links, mocap subscriptions, loops), of
  the simulator's process (autopilots, mocap, router) and of everything else on the machine
  (``/proc/stat`` busy time less those two): a missed rate with ``other`` near zero and the two
  processes filling the cores is our cost, with ``other`` high it is the machine's load;
- the pattern start skew (spread of the vehicles' first pattern cycle, clock time);
- pattern RMS tracking error, worst vehicle and median.

Each size flies in every link set-up asked for (``--setups``), in the same run:

- ``ports``: one UDP port per vehicle and the autopilot's own pose streamed at 50 Hz (as before
  issue 16's shared link: one connection and reader thread per vehicle);
- ``ports-nopose``: the same without the pose streams (``link.pose_telemetry_hz = 0``; the runner
  flies on mocap and reads only heartbeat, landed state and battery);
- ``shared``: every vehicle behind one UDP port (``flightkit sim --shared-link udp``), one
  connection and one reader thread for the fleet, no pose streams.

``--threads`` prints where this process's CPU went, by thread (the main thread runs asyncio: the
control loops and the mocap delivery), for the largest size of each set-up. ``--profile N``
runs the main thread of those flights under cProfile and prints its N costliest functions (own
time; cProfile slows what it watches, so the figures of those rows are not comparable).

Goals (issue 16): 10 vehicles at 100 Hz within one core with every vehicle's cycle p99 under
2 ms of CPU; start skew under 20 ms; every vehicle's pattern RMS under 2 cm on the circle.

    .venv/bin/python bench/fleet.py                  # 1, 3, 5, 10 vehicles, 30 s lap, 3 set-ups
    .venv/bin/python bench/fleet.py --sizes 10 --period 15 --threads
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import io
import math
import os
import pstats
import resource
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench._host import busy_s, process_cpu_s  # noqa: E402
from flightkit.config import load_config  # noqa: E402
from trajectories.fleet_plan import FleetPlan, FleetResult, fly_fleet_plan, parse_fleet_plan  # noqa: E402

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def circle_plan(n: int, period_s: float, rate_hz: float) -> dict[str, object]:
    """``n`` vehicles evenly around one circle, big enough for 0.9 m between neighbours."""
    radius_m = max(1.0, 0.9 / (2.0 * math.sin(math.pi / n))) if n > 1 else 1.0
    return {
        "plan": {"name": f"fleet{n}", "takeoff_height_m": 1.2, "hold_before_s": 1.0, "hold_after_s": 1.0,
                 "rate_hz": rate_hz},
        "pattern": {"kind": "circle", "radius_m": radius_m, "period_s": period_s, "height_m": 1.2, "laps": 1},
        "fleet": {"min_separation_m": 0.6},
        "vehicles": {f"uav{i + 1}": {"phase_deg": 360.0 * i / n} for i in range(n)},
        "safety": {"geofence": {"min_m": [-4.0, -4.0, -0.5], "max_m": [4.0, 4.0, 2.5]}},
    }


def cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


_TICKS_PER_S = os.sysconf("SC_CLK_TCK")


def free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


SETUPS = {"ports": (False, 50.0), "ports-nopose": (False, -1.0), "shared": (True, -1.0)}
"""set-up -> (every vehicle behind one port, link.pose_telemetry_hz; -1: auto, none for a fleet)."""


def lab_files(fplan: FleetPlan, folder: Path, shared: bool, pose_hz: float) -> tuple[Path, Path, int]:
    """The simulator's lab config and ours: the same vehicles, standing under their start points,
    the simulator listening (MAVLink ports base.. or the one shared port, bus), us connecting."""
    base = free_port(socket.SOCK_DGRAM)
    while base + len(fplan.vehicles) > 65000:
        base = free_port(socket.SOCK_DGRAM)
    bus = free_port(socket.SOCK_STREAM)
    sim_lines = [f'[bus]\nlisten = ["tcp/127.0.0.1:{bus}"]\n']
    our_lines = [f'[bus]\nconnect = ["tcp/127.0.0.1:{bus}"]\n[link]\npose_telemetry_hz = {pose_hz}\n']
    for i, (name, pattern) in enumerate(fplan.build_patterns().items()):
        x, y, _ = pattern.reference(0.0).pos_m
        port = base if shared else base + i
        sim_lines.append(f'[[vehicles]]\nname = "{name}"\nsystem_id = {i + 1}\nstart_m = [{x:.4f}, {y:.4f}, 0.0]\n')
        our_lines.append(f'[[vehicles]]\nname = "{name}"\nsystem_id = {i + 1}\nurl = "udpout:127.0.0.1:{port}"\n')
    sim_cfg, our_cfg = folder / "sim.toml", folder / "ours.toml"
    sim_cfg.write_text("[camera]\nenabled = false\n" + "\n".join(sim_lines))
    our_cfg.write_text("\n".join(our_lines))
    return sim_cfg, our_cfg, base


def _short_name(name: str) -> str:
    """``mavlink-reader udpout:...`` -> ``mavlink-reader``; ``Thread-3 (run)`` -> ``Thread (run)``."""
    head, _, rest = name.partition(" ")
    head = head.rstrip("-_0123456789")
    return f"{head} {rest}" if rest.startswith("(") else head


def tasks_cpu_s() -> dict[int, tuple[str, float]]:
    """Every thread of this process (Python and native, e.g. Zenoh's): id -> (name, CPU seconds so far).
    Python threads go by their name without numbers, native ones by their OS name."""
    names = {t.native_id: _short_name(t.name) for t in threading.enumerate()}
    out = {}
    for entry in os.scandir("/proc/self/task"):
        try:
            with open(f"{entry.path}/stat") as f:
                comm, rest = f.read().split(" (", 1)[1].rsplit(")", 1)
        except OSError:
            continue
        fields = rest.split()
        tid = int(entry.name)
        out[tid] = (names.get(tid, comm.rstrip("-0123456789")), (int(fields[11]) + int(fields[12])) / _TICKS_PER_S)
    return out


@dataclass(frozen=True, slots=True)
class Cores:
    """CPU seconds over one flight: this process, the simulator's, the whole machine; wall seconds."""

    ours_s: float
    sim_s: float
    machine_s: float
    wall_s: float

    def cores(self, cpu_s: float) -> float:
        return cpu_s / self.wall_s if self.wall_s > 0 else math.nan

    @property
    def other_s(self) -> float:
        """What the rest of the machine used (other users' jobs), clamped at 0 (clock-tick rounding)."""
        return max(0.0, self.machine_s - self.ours_s - self.sim_s)


def run(
    n: int, period_s: float, rate_hz: float, setup: str, profile: cProfile.Profile | None = None
) -> tuple[FleetResult, Cores, dict[str, float]]:
    shared, pose_hz = SETUPS[setup]
    fplan = parse_fleet_plan(circle_plan(n, period_s, rate_hz), f"<bench fleet {n}>")
    with tempfile.TemporaryDirectory(prefix="bench-fleet-") as tmp:
        sim_cfg, our_cfg, base = lab_files(fplan, Path(tmp), shared, pose_hz)
        sim = subprocess.Popen(
            [str(Path(sys.executable).parent / "flightkit"), "sim", "--config", str(sim_cfg), "--ready-after", "0",
             "--no-camera", "--listen", f"udpin:127.0.0.1:{base}", *(["--shared-link", "udp"] if shared else [])],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
        )
        try:
            time.sleep(3.0)  # the simulator binds its ports and opens the bus
            lab = load_config(our_cfg)
            stop = threading.Event()
            seen: dict[int, tuple[str, float]] = {}

            def sample() -> None:  # threads end with the flight: keep each one's last reading
                while not stop.wait(0.25):
                    seen.update(tasks_cpu_s())

            start = tasks_cpu_s()
            sampler = threading.Thread(target=sample, name="bench-sampler", daemon=True)
            sampler.start()
            c0, w0, s0, m0 = cpu_s(), time.monotonic(), process_cpu_s(sim.pid), busy_s()
            if profile is not None:
                profile.enable()
            try:
                result = asyncio.run(fly_fleet_plan(fplan, lab, arm=True))
            finally:
                if profile is not None:
                    profile.disable()
            cores = Cores(cpu_s() - c0, process_cpu_s(sim.pid) - s0, busy_s() - m0, time.monotonic() - w0)
            seen.update(tasks_cpu_s())
            stop.set()
            sampler.join()
            threads: dict[str, float] = {}
            for tid, (name, secs) in seen.items():
                threads[name] = threads.get(name, 0.0) + secs - start.get(tid, (name, 0.0))[1]
            return result, cores, threads
        finally:
            sim.terminate()
            sim.wait(10)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[1, 3, 5, 10], help="fleet sizes to fly")
    ap.add_argument("--period", type=float, default=30.0, help="seconds per lap of the circle")
    ap.add_argument("--rate", type=float, default=100.0, help="control rate per vehicle, Hz")
    ap.add_argument("--setups", nargs="+", choices=list(SETUPS), default=list(SETUPS), help="link set-ups to fly")
    ap.add_argument("--threads", action="store_true", help="CPU by thread for the largest size of each set-up")
    ap.add_argument("--profile", type=int, default=0, metavar="N",
                    help="cProfile the main thread of the largest size's flights; print the N costliest functions")
    args = ap.parse_args()
    print(f"fleet benchmark: one circle, {args.period:g} s lap, {args.rate:g} Hz per vehicle, real time; "
          "the simulated lab in its own process")
    head = (f"{'setup':>12} {'vehicles':>8} {'outcome':>10} {'cpu p50 ms':>10} {'cpu p99 ms':>10} {'worst p99':>10} "
            f"{'wall p99 ms':>11} {'Hz p50':>6} {'Hz min':>6} {'cores':>6} {'sim':>5} {'other':>5} {'skew ms':>8} "
            f"{'RMS med mm':>10} "
            f"{'RMS max mm':>10} {'min sep m':>9}")
    print(head)
    breakdowns = {}
    profiles: dict[str, str] = {}
    for n in args.sizes:
        for setup in args.setups:
            largest = n == max(args.sizes)
            profile = cProfile.Profile() if args.profile and largest else None
            result, used, threads = run(n, args.period, args.rate, setup, profile)
            if largest:
                breakdowns[setup] = (threads, used.wall_s)
            if profile is not None:
                out = io.StringIO()
                pstats.Stats(profile, stream=out).sort_stats("tottime").print_stats(args.profile)
                profiles[setup] = out.getvalue()
            s = list(result.summaries.values())
            p50 = statistics.median(x.cycle_cpu_p50_ms for x in s)
            p99 = statistics.median(x.cycle_cpu_p99_ms for x in s)
            worst = max(x.cycle_cpu_p99_ms for x in s)
            wall99 = max(x.cycle_p99_ms for x in s)
            rates = [x.loop_rate_hz for x in s]
            rms = [x.phase("pattern").rms_error_m * 1e3 for x in s if any(p.name == "pattern" for p in x.phases)]
            skew = result.start_skew_s * 1e3
            print(f"{setup:>12} {n:>8} {result.outcome[:10]:>10} {p50:>10.3f} {p99:>10.3f} {worst:>10.3f} "
                  f"{wall99:>11.3f} {statistics.median(rates):>6.0f} {min(rates):>6.0f} "
                  f"{used.cores(used.ours_s):>6.2f} "
                  f"{used.cores(used.sim_s):>5.2f} {used.cores(used.other_s):>5.2f} {skew:>8.1f} "
                  f"{statistics.median(rms) if rms else math.nan:>10.1f} {max(rms) if rms else math.nan:>10.1f} "
                  f"{result.min_separation_m:>9.2f}", flush=True)
    print("goals: 10 vehicles within one core (cores <= 1.0), every p99 < 2 ms CPU, skew < 20 ms, RMS < 20 mm; "
          "Hz: loop rate per vehicle (median, slowest); cores: this process, sim: the simulator's, other: the rest "
          f"of the machine ({os.cpu_count()} cores)")
    if args.threads:
        for setup, (threads, wall) in breakdowns.items():
            ranked = sorted(threads.items(), key=lambda kv: -kv[1])[:8]
            top = ", ".join(f"{name} {secs / wall:.2f}" for name, secs in ranked if secs > 0)
            print(f"cores by thread, {setup}, {max(args.sizes)} vehicles: {top}")
    for setup, text in profiles.items():
        print(f"main thread under cProfile, {setup}, {max(args.sizes)} vehicles:")
        print("\n".join(line for line in text.splitlines() if line.strip())[:4000])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
