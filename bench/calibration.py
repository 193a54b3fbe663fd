"""Calibration benchmark: accuracy and run time of every estimate on simulated data with exact answers.

Parts (all on the simulated lab's calibration flights: a lab pattern flown while rocking the body
about three axes, ``flightkit.sim.calibration_flight``):

1. **Time offset and drift** across injected camera offsets (0-100 ms), drifts (0-200 ppm), mocap
   latencies (0-50 ms) and noise levels (VO rotation noise per frame, mocap noise), on the three
   lab patterns: error of the offset (ms) and drift (ppm), the reported 1-sigma, run time.
2. **Hand-eye** at the same noise levels: mount error (mm, deg), residuals, run time.
3. **Host clock offset** from NTP-style exchanges with queueing delays: offset and drift error.
4. **Latency compensation** (offline): the error of a pose ``latency`` old, and of the same pose
   predicted forward by ``latency`` at constant velocity, against the true pose now.
5. ``--vo``: the camera's motion from real VO (rgbd-pnp on rendered 320x240 frames) instead of
   the true motion plus noise, end to end.
6. **Latency compensation in flight** (``--flight``): the simulated lab flies the circle with
   0, 20 and 50 ms of mocap latency injected, without and with the runner's prediction
   (``[mocap] predict_latency_ms`` = the latency), side by side in one run: the *true* tracking
   error (the lab's ground truth against the reference, pattern phase) and the latency stages.

    .venv/bin/python bench/calibration.py            # parts 1-4 (~3 min on 2 shared cores)
    .venv/bin/python bench/calibration.py --quick    # circle only, fewer cases (~1 min)
    .venv/bin/python bench/calibration.py --vo       # and part 5 (~1-2 min more)
    .venv/bin/python bench/calibration.py --flight-only   # part 6 alone (~2 min at the default --speed 3)
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from flightkit.calibration import (  # noqa: E402
    Exchange,
    estimate_clock_offset,
    estimate_hand_eye,
    estimate_time_offset,
    predict_pose,
    transform_difference,
    velocity_from_poses,
)
from flightkit.datasets.trajectory import Trajectory  # noqa: E402
from flightkit.errors import CalibrationError  # noqa: E402
from flightkit.frames import Transform  # noqa: E402
from flightkit.sim.calibration_flight import calibration_motion, simulate_streams  # noqa: E402
from flightkit.sim.timing_errors import SimTimingErrors  # noqa: E402
from trajectories.patterns import Circle, Lawnmower, Rectangle  # noqa: E402

TRUE_MOUNT = Transform.from_xyz_euler_deg([0.085, -0.004, -0.017], "xz", [133.0, 91.5])
PATTERNS = {
    "circle": Circle(radius_m=1.0, period_s=20.0, laps=3, height_m=1.5),
    "rectangle": Rectangle([(-1, -1), (1, -1), (1, 1), (-1, 1)], 1.5, speed_m_s=0.3, turn_s=3.0),
    "lawnmower": Lawnmower((-1, -1), (2, 2), 0.5, 1.5, speed_m_s=0.3, turn_s=2.0),
}
# (label, VO rotation noise deg/frame, VO translation noise m/frame, mocap noise m, mocap noise deg)
NOISE = [
    ("none", 0.0, 0.0, 0.0, 0.0),
    ("low", 0.01, 0.0001, 0.0002, 0.01),
    ("mid", 0.03, 0.0003, 0.0005, 0.03),
]
TIMING = [(0.0, 0.0, 0.0), (0.05, 100.0, 0.02), (0.1, 200.0, 0.05), (0.02, -150.0, 0.0)]


def table(header: list[str], rows: list[list[str]]) -> None:
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(header)]
    print("| " + " | ".join(h.ljust(w) for h, w in zip(header, widths, strict=True)) + " |")
    print("|" + "|".join("-" * (w + 2) for w in widths) + "|")
    for r in rows:
        print("| " + " | ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)) + " |")
    print()


def part_time_and_hand_eye(patterns: list[str], noises: list[tuple], timings: list[tuple], duration_s: float) -> None:
    rows_t: list[list[str]] = []
    rows_h: list[list[str]] = []
    for name in patterns:
        for label, rot_deg, pos_m, mo_m, mo_deg in noises:
            for off, drift, lat in timings:
                err = SimTimingErrors(off, drift, lat)
                st = simulate_streams(
                    calibration_motion(PATTERNS[name]), duration_s, errors=err, T_body_camera=TRUE_MOUNT,
                    camera_noise_deg=rot_deg, camera_noise_m=pos_m, mocap_noise_m=mo_m,
                    mocap_noise_rad=math.radians(mo_deg), seed=7,
                )
                t0 = time.perf_counter()
                est = estimate_time_offset(st.mocap, st.camera)
                t_time = time.perf_counter() - t0
                want = err.expected_offset_s(est.ref_ns, st.start_ns)
                rows_t.append([
                    name, label, f"{off * 1e3:.0f}/{drift:.0f}/{lat * 1e3:.0f}",
                    f"{(est.offset_s - want) * 1e3:+.3f}", f"{est.offset_uncertainty_s * 1e3:.3f}",
                    f"{est.drift_ppm - drift:+.1f}", f"{est.drift_uncertainty_ppm:.1f}", f"{est.correlation:.4f}",
                    f"{t_time:.2f}",
                ])
                if (off, drift, lat) == timings[-1] or len(timings) == 1:
                    t0 = time.perf_counter()
                    he = estimate_hand_eye(st.mocap, st.camera, camera_to_body_ns=est.camera_to_mocap_ns)
                    t_he = time.perf_counter() - t0
                    dm, ddeg = transform_difference(he.T_body_camera, TRUE_MOUNT)
                    rows_h.append([
                        name, label, f"{dm * 1e3:.3f}", f"{ddeg:.4f}", f"{he.residual_m * 1e3:.2f}",
                        f"{he.residual_deg:.3f}", str(he.pairs), f"{he.axis_spread:.2f}", f"{t_he:.2f}",
                    ])
            print(f"  {name} / noise {label} done", file=sys.stderr)
    print(f"### Time offset and drift ({duration_s:.0f} s flights; errors are estimate minus truth)\n")
    table(["pattern", "noise", "offset/drift/latency (ms/ppm/ms)", "offset err ms", "1-sigma ms", "drift err ppm",
           "1-sigma ppm", "corr", "run s"], rows_t)
    print("### Hand-eye T_body_camera (timing errors of the last row above, aligned by the time estimate)\n")
    table(["pattern", "noise", "err mm", "err deg", "resid mm", "resid deg", "pairs", "axis spread", "run s"], rows_h)


def part_refusal() -> None:
    st = simulate_streams(calibration_motion(PATTERNS["circle"], rock_deg=(0, 0, 0), follow_yaw=False), 20.0,
                          T_body_camera=TRUE_MOUNT)
    print("### Pure translation (must refuse)\n")
    for what, fn in (("time", estimate_time_offset), ("hand-eye", estimate_hand_eye)):
        try:
            fn(st.mocap, st.camera)
            print(f"- {what}: NOT refused")
        except CalibrationError as exc:
            print(f"- {what}: refused: {str(exc)[:110]}...")
    print()


def part_clock() -> None:
    rows: list[list[str]] = []
    for wire_ms, queue_ms in ((0.2, 0.0), (0.2, 2.0), (1.0, 10.0)):
        rng = np.random.default_rng(1)
        offset_ns, drift = 3_250_000.0, 80.0
        ex = []
        for t0 in np.arange(0, 120e9, 50e6):
            up = wire_ms * 1e6 + (rng.exponential(queue_ms * 1e6) if queue_ms else 0.0)
            down = wire_ms * 1e6 + (rng.exponential(queue_ms * 1e6) if queue_ms else 0.0)
            t1 = (t0 + up) * (1 + drift * 1e-6) + offset_ns
            t2 = t1 + 100_000
            t3 = t0 + up + 100_000 / (1 + drift * 1e-6) + down
            ex.append(Exchange(int(t0), int(t1), int(t2), int(t3)))
        t = time.perf_counter()
        est = estimate_clock_offset(ex)
        run = time.perf_counter() - t
        naive = float(np.mean([e.offset_ns for e in ex]))
        rows.append([f"{wire_ms:g} + exp({queue_ms:g})", str(len(ex)),
                     f"{(est.offset_at_ns(60 * 10**9) - (offset_ns + drift * 60e3)) / 1e3:+.1f}",
                     f"{(naive - (offset_ns + drift * 60e3)) / 1e3:+.1f}", f"{est.drift_ppm - drift:+.2f}",
                     f"{est.uncertainty_ns / 1e3:.1f}", f"{run * 1e3:.1f}"])
    print("### Host clock offset (120 s of exchanges at 20 Hz, true offset 3.25 ms, drift 80 ppm)\n")
    table(["one-way delay ms", "exchanges", "offset err us (min-RTT fit)", "mean of all us", "drift err ppm",
           "bound us", "run ms"], rows)


def part_latency() -> None:
    rows: list[list[str]] = []
    truth = calibration_motion(PATTERNS["circle"])
    ts = np.arange(5.0, 55.0, 1 / 120)
    for lat_ms in (10.0, 30.0, 50.0):
        lat = lat_ms / 1e3
        stale, pred = [], []
        for t in ts:
            now = truth(t)
            old, older = truth(t - lat), truth(t - lat - 1 / 120)
            v, w = velocity_from_poses(older, old, 1 / 120)
            stale.append(transform_difference(old, now))
            pred.append(transform_difference(predict_pose(old, v, w, lat), now))
        s, p = np.array(stale), np.array(pred)
        rows.append([f"{lat_ms:.0f}", f"{np.sqrt(np.mean(s[:, 0] ** 2)) * 1e3:.2f}",
                     f"{np.sqrt(np.mean(p[:, 0] ** 2)) * 1e3:.2f}", f"{np.sqrt(np.mean(s[:, 1] ** 2)):.2f}",
                     f"{np.sqrt(np.mean(p[:, 1] ** 2)):.2f}"])
    print("### Latency compensation, offline (circle calibration flight, 120 Hz mocap, no noise)\n")
    table(["latency ms", "stale pose RMS mm", "predicted RMS mm", "stale RMS deg", "predicted RMS deg"], rows)


def part_vo(duration_s: float) -> None:
    from estimation.pipeline import run_vo
    from flightkit.config import CameraConfig
    from flightkit.sim.camera import SimCamera
    from flightkit.sim.sequence import SimSequence

    err = SimTimingErrors(0.06, 150.0, 0.025)
    truth = calibration_motion(PATTERNS["circle"], rock_deg=(12.0, 12.0, 15.0))
    st = simulate_streams(truth, duration_s, errors=err, T_body_camera=TRUE_MOUNT)
    cfg = CameraConfig(width_px=320, height_px=240, rate_hz=30.0)
    poses = [(int(t), truth((int(t) - st.start_ns) / 1e9)) for t in st.camera_truth_ns]
    seq = SimSequence(SimCamera.from_config(cfg), poses, TRUE_MOUNT, name="calibration", stereo=False)
    t0 = time.perf_counter()
    vo = run_vo(seq, "rgbd-pnp")
    t_vo = time.perf_counter() - t0
    cam = vo.trajectory("camera")
    stamps = np.array([err.camera_stamp_ns(int(t), st.start_ns) for t in cam.stamps_ns], dtype=np.int64)
    cam = Trajectory(stamps, cam.positions, cam.quats_wxyz, "vo")
    t0 = time.perf_counter()
    est = estimate_time_offset(st.mocap, cam)
    he = estimate_hand_eye(st.mocap, cam, camera_to_body_ns=est.camera_to_mocap_ns)
    t_cal = time.perf_counter() - t0
    want = err.expected_offset_s(est.ref_ns, st.start_ns)
    dm, ddeg = transform_difference(he.T_body_camera, TRUE_MOUNT)
    print(f"### End to end with VO (rgbd-pnp, 320x240, {duration_s:.0f} s circle, rocking 12-15 deg)\n")
    table(["offset err ms", "1-sigma ms", "drift err ppm", "mount err mm", "mount err deg", "resid mm",
           "resid deg", "VO s", "calibration s"],
          [[f"{(est.offset_s - want) * 1e3:+.3f}", f"{est.offset_uncertainty_s * 1e3:.3f}",
            f"{est.drift_ppm - 150.0:+.1f}", f"{dm * 1e3:.2f}", f"{ddeg:.3f}", f"{he.residual_m * 1e3:.2f}",
            f"{he.residual_deg:.3f}", f"{t_vo:.1f}", f"{t_cal:.2f}"]])


def _fly_circle(latency_ms: float, predict_ms: float, speed: float, period_s: float, log: Path) -> dict[str, float]:
    """One simulated circle flight; the true RMS/max tracking error of the pattern phase and the latency stages."""
    import asyncio
    import dataclasses

    from flightkit.apps.sim_session import SimSession, fly_plan_in_sim
    from flightkit.config import load_config
    from trajectories.flightlog import read_flight_log
    from trajectories.plan import load_plan

    root = Path(__file__).resolve().parents[1]
    plan = load_plan(root / "examples" / "circle.toml")
    plan = plan.with_changes(
        settings=dataclasses.replace(plan.settings, hold_before_s=1.0, hold_after_s=0.5, landed_timeout_s=60.0),
        pattern=dataclasses.replace(plan.pattern, laps=1, period_s=period_s),
    )
    cfg = load_config(table={"sim": {"mocap_latency_ms": latency_ms, "speed": speed},
                             "mocap": {"predict_latency_ms": predict_ms}})
    truth: list[tuple[int, tuple[float, float, float]]] = []

    async def sample(s: SimSession) -> None:  # the lab's ground truth on the clock's time_ns
        while True:
            t = s.lab.T_world_body().translation
            truth.append((s.clock.time_ns(), (float(t[0]), float(t[1]), float(t[2]))))
            await s.clock.sleep(0.02)

    async def go() -> Any:
        tasks: list[asyncio.Task[None]] = []
        try:
            return await fly_plan_in_sim(plan, cfg, log_path=log,
                                         on_session=lambda s: tasks.append(asyncio.ensure_future(sample(s))))
        finally:
            for t in tasks:
                t.cancel()

    summary = asyncio.run(go())
    data = read_flight_log(log)
    on = np.array([ph == "pattern" for ph in data["phase"]])
    stamps = np.array([t for t, _ in truth], dtype=np.float64)
    pos = np.array([p for _, p in truth])
    at = data["stamp_ns"][on]
    true_now = np.stack([np.interp(at, stamps, pos[:, k]) for k in range(3)], axis=1)
    ref = np.stack([data[f"ref_{a}_m"][on] for a in "xyz"], axis=1)
    err = np.linalg.norm(true_now - ref, axis=1)
    stages = summary.stage_latency_ms
    return {"rms_mm": float(np.sqrt(np.mean(err**2)) * 1e3), "max_mm": float(err.max() * 1e3),
            "seen_rms_mm": summary.phase("pattern").rms_error_m * 1e3,
            "capture_bus_ms": stages.get("capture->bus", (math.nan, math.nan))[0],
            "total_p99_ms": stages.get("capture->setpoint", (math.nan, math.nan))[1],
            "outcome": 1.0 if summary.outcome == "completed" else 0.0}


def part_flight(speed: float, period_s: float) -> None:
    import tempfile

    rows: list[list[str]] = []
    with tempfile.TemporaryDirectory() as tmp:
        for lat in (0.0, 20.0, 50.0):
            for pred in (0.0, lat) if lat else (0.0,):
                t0 = time.perf_counter()
                r = _fly_circle(lat, pred, speed, period_s, Path(tmp) / f"fly_{lat:.0f}_{pred:.0f}.csv")
                rows.append([f"{lat:.0f}", "on" if pred else "off", f"{r['rms_mm']:.1f}", f"{r['max_mm']:.1f}",
                             f"{r['seen_rms_mm']:.1f}", f"{r['capture_bus_ms']:.1f}", f"{r['total_p99_ms']:.1f}",
                             "completed" if r["outcome"] else "NOT completed", f"{time.perf_counter() - t0:.0f}"])
    print(f"### Latency compensation in flight (simulated lab, circle r 1 m, {period_s:g} s lap, "
          f"sim speed {speed:g}; true error = ground truth vs reference)\n")
    table(["latency ms", "prediction", "true RMS mm", "true max mm", "runner's RMS mm", "capture->bus p50 ms",
           "capture->setpoint p99 ms", "outcome", "wall s"], rows)


def main() -> None:
    ap = argparse.ArgumentParser(description="calibration benchmark on simulated flights with exact answers")
    ap.add_argument("--quick", action="store_true", help="circle only, fewer cases")
    ap.add_argument("--vo", action="store_true", help="also run the end-to-end VO case")
    ap.add_argument("--duration", type=float, default=60.0, help="flight length, s (default 60)")
    ap.add_argument("--flight", action="store_true", help="also run part 6 (latency compensation in flight)")
    ap.add_argument("--flight-only", action="store_true", help="run part 6 only")
    ap.add_argument("--speed", type=float, default=3.0, help="sim speed of part 6 (default 3)")
    ap.add_argument("--period", type=float, default=15.0, help="circle lap time of part 6, s (default 15)")
    args = ap.parse_args()
    if args.flight_only:
        part_flight(args.speed, args.period)
        return
    patterns = ["circle"] if args.quick else sorted(PATTERNS)
    timings = TIMING[1:2] if args.quick else TIMING
    part_time_and_hand_eye(patterns, NOISE, timings, args.duration)
    part_refusal()
    part_clock()
    part_latency()
    if args.vo:
        part_vo(min(args.duration, 30.0))
    if args.flight:
        part_flight(args.speed, args.period)


if __name__ == "__main__":
    main()
