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
- this process's CPU use in cores over the whole flight (links, mocap subscriptions, loops);
- the pattern start skew (spread of the vehicles' first pattern cycle, clock time);
- pattern RMS tracking error, worst vehicle and median.

Goals (issue 16): 10 vehicles at 100 Hz within one core with every vehicle's cycle p99 under
2 ms of CPU; start skew under 20 ms; every vehicle's pattern RMS under 2 cm on the circle.

    .venv/bin/python bench/fleet.py                  # 1, 3, 5, 10 vehicles, 30 s lap (~5 min)
    .venv/bin/python bench/fleet.py --sizes 1 3 --period 20
"""

from __future__ import annotations

import argparse
import asyncio
import math
import os
import resource
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

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


def free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def lab_files(fplan: FleetPlan, folder: Path) -> tuple[Path, Path, int]:
    """The simulator's lab config and ours: the same vehicles, standing under their start points,
    the simulator listening (MAVLink ports base.., bus), us connecting."""
    base = free_port(socket.SOCK_DGRAM)
    while base + len(fplan.vehicles) > 65000:
        base = free_port(socket.SOCK_DGRAM)
    bus = free_port(socket.SOCK_STREAM)
    sim_lines = [f'[bus]\nlisten = ["tcp/127.0.0.1:{bus}"]\n']
    our_lines = [f'[bus]\nconnect = ["tcp/127.0.0.1:{bus}"]\n']
    for i, (name, pattern) in enumerate(fplan.build_patterns().items()):
        x, y, _ = pattern.reference(0.0).pos_m
        sim_lines.append(f'[[vehicles]]\nname = "{name}"\nstart_m = [{x:.4f}, {y:.4f}, 0.0]\n')
        our_lines.append(f'[[vehicles]]\nname = "{name}"\nurl = "udpout:127.0.0.1:{base + i}"\n')
    sim_cfg, our_cfg = folder / "sim.toml", folder / "ours.toml"
    sim_cfg.write_text("[camera]\nenabled = false\n" + "\n".join(sim_lines))
    our_cfg.write_text("\n".join(our_lines))
    return sim_cfg, our_cfg, base


def run(n: int, period_s: float, rate_hz: float) -> tuple[FleetResult, float, float]:
    fplan = parse_fleet_plan(circle_plan(n, period_s, rate_hz), f"<bench fleet {n}>")
    with tempfile.TemporaryDirectory(prefix="bench-fleet-") as tmp:
        sim_cfg, our_cfg, base = lab_files(fplan, Path(tmp))
        sim = subprocess.Popen(
            [str(Path(sys.executable).parent / "flightkit"), "sim", "--config", str(sim_cfg), "--ready-after", "0",
             "--no-camera", "--listen", f"udpin:127.0.0.1:{base}"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
        )
        try:
            time.sleep(3.0)  # the simulator binds its ports and opens the bus
            lab = load_config(our_cfg)
            c0, w0 = cpu_s(), time.monotonic()
            result = asyncio.run(fly_fleet_plan(fplan, lab, arm=True))
            return result, cpu_s() - c0, time.monotonic() - w0
        finally:
            sim.terminate()
            sim.wait(10)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[1, 3, 5, 10], help="fleet sizes to fly")
    ap.add_argument("--period", type=float, default=30.0, help="seconds per lap of the circle")
    ap.add_argument("--rate", type=float, default=100.0, help="control rate per vehicle, Hz")
    args = ap.parse_args()
    print(f"fleet benchmark: one circle, {args.period:g} s lap, {args.rate:g} Hz per vehicle, real time; "
          "the simulated lab in its own process")
    head = (f"{'vehicles':>8} {'outcome':>10} {'cpu p50 ms':>10} {'cpu p99 ms':>10} {'worst p99':>10} "
            f"{'wall p99 ms':>11} {'loop Hz':>8} {'cores':>6} {'skew ms':>8} {'RMS med mm':>10} "
            f"{'RMS max mm':>10} {'min sep m':>9}")
    print(head)
    rows = []
    for n in args.sizes:
        result, cpu, wall = run(n, args.period, args.rate)
        s = list(result.summaries.values())
        p50 = statistics.median(x.cycle_cpu_p50_ms for x in s)
        p99 = statistics.median(x.cycle_cpu_p99_ms for x in s)
        worst = max(x.cycle_cpu_p99_ms for x in s)
        wall99 = max(x.cycle_p99_ms for x in s)
        rate = statistics.median(x.loop_rate_hz for x in s)
        rms = [x.phase("pattern").rms_error_m * 1e3 for x in s if any(p.name == "pattern" for p in x.phases)]
        cores = cpu / wall if wall > 0 else math.nan
        skew = result.start_skew_s * 1e3
        row = (f"{n:>8} {result.outcome[:10]:>10} {p50:>10.3f} {p99:>10.3f} {worst:>10.3f} {wall99:>11.3f} "
               f"{rate:>8.0f} {cores:>6.2f} {skew:>8.1f} {statistics.median(rms) if rms else math.nan:>10.1f} "
               f"{max(rms) if rms else math.nan:>10.1f} {result.min_separation_m:>9.2f}")
        rows.append(row)
        print(row, flush=True)
    print("goals: 10 vehicles within one core (cores <= 1.0), every p99 < 2 ms CPU, skew < 20 ms, RMS < 20 mm")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
