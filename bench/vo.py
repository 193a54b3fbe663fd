"""Benchmark of the visual odometry methods against the lab's original pipeline, one core.

For every real sequence in ``../shared/data`` (KITTI 06 stereo, 7-Scenes RGB-D, the two
TUM fr1/xyz pairs, EuRoC V1_01 at rest) and every method that the sequence's sensors allow,
and for the synthetic sequences of the three lab patterns (``sim_circle``, ``sim_rectangle``,
``sim_lawnmower``: the simulated camera flown along them with exact ground truth, rendered
natively at each size before timing, see ``bench/_synthetic.py``), at 320x240 and 640x480, prints:

* frames/s of processing (images already decoded and resized; best of ``--rounds`` runs),
  from wall time ("fps") and from the thread's CPU time ("cpu fps": what one dedicated
  core does; on a shared machine the wall figure includes time the core spent on other
  processes), and the mean per-stage wall milliseconds (track, motion, keyframe, ba);
* the speed against the baseline as the median of paired ratios: each of ``--rounds`` rounds
  runs baseline-pnp once and then every method once, on the same frames, and each method's
  frames per CPU second is divided by the baseline's of the same round. On this shared 2-core
  machine one run's speed moves by +-25 % with the load from minute to minute; a ratio of two
  runs made seconds apart moves far less, and the median of several is the figure to quote
  (the spread, min-max, is printed beside it);
* accuracy against ground truth: ATE (SE(3)-aligned RMSE; none for 2-frame pairs), RPE
  (delta 1 frame, RMSE), the lab's relative (per step) and absolute (accumulated) errors
  (mean translation and rotation);
* methods whose model does not hold on a sequence (``UNSUITED``: flow on the forward-driving
  KITTI car) are named with the reason instead of a meaningless number;
* the lab's baseline (SIFT + brute force + solvePnP iterative / essential matrix, every
  frame, on the depth images where there are any; on the synthetic sequences also on the
  stereo pair, ``baseline-pnp@stereo``, the like-for-like comparison for ``stereo``) side by
  side, and the speed ratio to the baseline on the same sensor.

The process is pinned to one CPU and OpenCV/BLAS to one thread.

The real sequences are decoded and resized frame by frame between the timed calls (the decoding
is not counted, but it runs on the same core between two frames and evicts the VO's working set
from the caches: 7-Scenes at 320x240, rgbd-pnp ran 20-30 % more frames per CPU second on the
same frames held in memory). ``--preload`` decodes and resizes every frame before the timed runs,
as the synthetic sequences are rendered before them, for the figure of the processing alone;
the trajectories are the same bit for bit.

Run: .venv/bin/python bench/vo.py [--sizes 320x240,640x480] [--rounds 3] [--no-baseline]
     [--ba 4] [--only kitti06,sim_circle] [--no-synthetic] [--json out.json] [--unsuited]
     [--preload] [--cpu N]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
from collections.abc import Iterator  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # `bench._synthetic` when run as a script

from bench._synthetic import METHODS as SYNTHETIC_METHODS  # noqa: E402
from bench._synthetic import SYNTHETIC, prerendered  # noqa: E402
from estimation.baseline import run_baseline  # noqa: E402
from estimation.evaluation import Alignment, ape, lab_errors, rpe  # noqa: E402
from estimation.pipeline import Method, VoOptions, VoResult, _resize_intrinsics, run_vo, warm_up  # noqa: E402
from flightkit.datasets.base import Frame  # noqa: E402
from flightkit.datasets.registry import open_sequence  # noqa: E402

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

SEQUENCES = {
    "kitti06": ("kitti06_stereo", ["stereo", "flow", "flow@stereo"]),
    "7scenes": ("sevenscenes_tsdf50", ["rgbd-pnp", "rgbd-essential", "rgbd-kabsch", "flow"]),
    "tum_case1": ("tum_fr1xyz_pairs/case_1", ["rgbd-pnp", "rgbd-essential", "rgbd-kabsch", "flow"]),
    "tum_case2": ("tum_fr1xyz_pairs/case_2", ["rgbd-pnp", "rgbd-essential", "rgbd-kabsch", "flow"]),
    "euroc_static": ("euroc_v101_static", ["stereo", "flow", "flow@stereo"]),
}

UNSUITED: dict[tuple[str, str], str] = {
    ("kitti06", "flow"): (
        "wrong tool: a forward-driving car, not a camera above the ground (one altitude depth for "
        "all points) moving little between frames (1.2 m per frame at 10 Hz); use stereo"
    ),
    ("kitti06", "flow@stereo"): (
        "wrong tool: at 1.2 m per frame every frame is a new flow reference, so flow is frame-to-frame "
        "motion on sparse stereo without a map (ATE 0.13 m at 320x240 with the reprojection polish, 1.2 m "
        "without); use stereo"
    ),
}
"""(sequence, method) pairs not run by default: the method's model does not hold there, so its
number would mean nothing (``--unsuited`` runs them anyway; docs/estimation.md, "Methods and when to use them")."""


class Preloaded:
    """A real sequence decoded and resized into memory once (``--preload``): the frames hold
    the images at ``size`` (grey with INTER_AREA, depth in metres with INTER_NEAREST, as
    ``estimation.pipeline.FramePreparer`` resizes them), so the timed runs do no decoding."""

    def __init__(self, seq: Any, size: tuple[int, int]) -> None:
        self._seq = seq
        intr, di = seq.intrinsics, seq.depth_intrinsics
        native = size == (intr.width, intr.height)
        self.intrinsics = intr if native else _resize_intrinsics(intr, size)
        self.depth_intrinsics = di if (native or di is None) else _resize_intrinsics(di, size)
        self.baseline_m = seq.baseline_m
        self.name = seq.name
        self._frames: list[Frame] = []
        for f in seq.frames():
            gray, right, depth = f.gray, f.right_gray, f.depth_m
            if not native:
                gray = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
                right = None if right is None else cv2.resize(right, size, interpolation=cv2.INTER_AREA)
                depth = None if depth is None else cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST)
            self._frames.append(Frame(f.index, f.stamp_ns, gray, None, right, depth, 1.0, f.T_world_camera))

    def __len__(self) -> int:
        return len(self._frames)

    def frames(self, start: int = 0, stop: int | None = None, step: int = 1) -> Iterator[Frame]:
        yield from self._frames[start:stop:step]

    def __getattr__(self, name: str) -> Any:  # groundtruth(), has_groundtruth(), ...
        return getattr(self._seq, name)


def errors(res: VoResult, seq: object) -> dict[str, float]:
    gt = seq.groundtruth()  # type: ignore[attr-defined]
    est = res.trajectory("camera")
    out: dict[str, float] = {}
    alignment = Alignment.SE3 if len(est) >= 3 else Alignment.NONE
    a = ape(est, gt, alignment)
    out["ate_m"] = a.translation.rmse
    r = rpe(est, gt, 1.0, "frames", alignment)
    out["rpe_m"] = r.translation.rmse
    out["rpe_deg"] = math.degrees(r.rotation.rmse)
    lab = lab_errors(est, gt)
    out["lab_rel_m"] = lab.relative_translation.mean
    out["lab_rel_deg"] = math.degrees(lab.relative_rotation.mean)
    out["lab_abs_m"] = lab.absolute_translation.mean
    out["lab_abs_deg"] = math.degrees(lab.absolute_rotation.mean)
    return out


def best(results: list[VoResult]) -> VoResult:
    """The run with the most frames per CPU second (the trajectories of all runs are the same)."""
    return max(results, key=lambda r: r.fps_cpu)


def paired(ours: list[VoResult], base: list[VoResult]) -> list[float]:
    """Speed ratios to the baseline, round by round (each round ran both on the same frames)."""
    return [o.fps_cpu / b.fps_cpu for o, b in zip(ours, base, strict=True)]


def stage_line(res: VoResult) -> str:
    ms = {k: float(np.mean(v)) for k, v in res.stage_ms.items()}
    return " ".join(f"{k} {ms[k]:5.2f}" for k in ("track", "motion", "keyframe", "ba", "total"))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="320x240,640x480")
    ap.add_argument(
        "--rounds",
        type=int,
        default=3,
        help="rounds of (baseline-pnp, then every method) per sequence and size; speed = median paired ratio",
    )
    ap.add_argument("--no-baseline", action="store_true")
    ap.add_argument("--ba", type=int, default=0, help="also run with local BA over N keyframes")
    ap.add_argument("--only", help="comma-separated sequence keys")
    ap.add_argument("--no-synthetic", action="store_true", help="skip the synthetic lab-pattern sequences")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--unsuited", action="store_true", help="also run the methods marked unsuited (UNSUITED)")
    ap.add_argument("--preload", action="store_true", help="decode and resize the real sequences before the timed runs")
    ap.add_argument("--cpu", type=int, help="the CPU to pin the process to (default: the last one)")
    args = ap.parse_args()

    cv2.setNumThreads(1)
    if hasattr(os, "sched_setaffinity"):
        cpus = sorted(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpus[-1] if args.cpu is None else args.cpu})
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    keys = args.only.split(",") if args.only else list(SEQUENCES) + ([] if args.no_synthetic else list(SYNTHETIC))
    rows: list[dict[str, object]] = []
    # Untimed: the first VO run in a process loads the compiled kernels (~0.4 s,
    # estimation/_kernels.py), a start-up cost, not a per-frame one.
    for m in Method:
        warm_up(m)
    print(f"data: {DATA}; OpenCV {cv2.__version__}, threads {cv2.getNumThreads()}, one CPU")
    hdr = (
        f"{'sequence':13} {'size':8} {'method':16} {'fps':>7} {'cpu fps':>7} {'ATE m':>8} {'RPE m':>8} "
        f"{'RPE deg':>8} {'rel m':>8} {'rel deg':>8} {'abs m':>8} {'abs deg':>8}  stages ms"
    )
    for key in keys:
        if key in SYNTHETIC:
            methods = SYNTHETIC_METHODS
            seq = None
        else:
            folder, methods = SEQUENCES[key]
            seq = open_sequence(DATA / folder)
            print(f"\n== {key}: {seq.name}, {len(seq)} frames, {seq.intrinsics.width}x{seq.intrinsics.height}")
            print(hdr)
        for size in sizes:
            if key in SYNTHETIC:
                # Rendered natively at this size, every frame in memory before the timed runs.
                seq = prerendered(SYNTHETIC[key], size)
                print(
                    f"\n== {key} at {size[0]}x{size[1]}: {len(seq)} frames at 15 Hz, rendered in "
                    f"{seq.render_s:.1f} s ({1e3 * seq.render_s / len(seq):.0f} ms per frame with stereo)"
                )
                print(hdr)
            assert seq is not None
            if args.preload and key not in SYNTHETIC:
                seq = Preloaded(seq if not isinstance(seq, Preloaded) else seq._seq, size)
                print(f"   ({key} at {size[0]}x{size[1]}: {len(seq)} frames decoded and resized before timing)")
            # What runs: (label, method, options); "flow@stereo" is flow with per-point stereo
            # depth instead of the altitude.
            plan: list[tuple[str, str, VoOptions]] = []
            for label in methods:
                if (key, label) in UNSUITED and not args.unsuited:
                    print(f"{key:13} {size[0]}x{size[1]:<4} {label:16} not run: {UNSUITED[(key, label)]}")
                    rows.append(
                        {
                            "sequence": key,
                            "size": f"{size[0]}x{size[1]}",
                            "method": label,
                            "unsuited": UNSUITED[(key, label)],
                        }
                    )
                    continue
                m, _, variant = label.partition("@")
                plan.append((label, m, VoOptions(flow_depth="stereo") if variant == "stereo" else VoOptions()))

            # Rounds: the baseline, then every method, on the same frames; speeds are compared
            # within a round (see the module docstring). Each method is compared with the lab's
            # pipeline on the same sensor: on the synthetic sequences, which carry both, the
            # stereo methods with the baseline on the stereo pair ("baseline-pnp@stereo"), the
            # others with the baseline on the depth images (its best input).
            def base_for(label: str, key: str = key) -> str:
                on_stereo = label == "stereo" or label.endswith("@stereo")
                return "baseline-pnp@stereo" if key in SYNTHETIC and on_stereo else "baseline-pnp"

            timed: dict[str, list[VoResult]] = {label: [] for label, _, _ in plan}
            bases = [] if args.no_baseline else sorted({base_for(label) for label, _, _ in plan} | {"baseline-pnp"})
            base_rounds: dict[str, list[VoResult]] = {b: [] for b in bases}
            for _ in range(max(1, args.rounds)):
                for b in bases:
                    sensor = "stereo" if b.endswith("@stereo") else "auto"
                    base_rounds[b].append(
                        run_baseline(seq, "pnp", size=size, init_from_groundtruth=True, sensor=sensor)
                    )
                for label, m, opts in plan:
                    timed[label].append(run_vo(seq, m, options=opts, size=size, init_from_groundtruth=True))
            runs: list[tuple[str, VoResult, list[float]]] = []
            for label, m, opts in plan:
                ratios = paired(timed[label], base_rounds[base_for(label)]) if bases else []
                runs.append((label, best(timed[label]), ratios))
                if args.ba and Method(m) is not Method.FLOW:
                    o2 = replace(opts, ba_window=args.ba)
                    res_ba = run_vo(seq, m, options=o2, size=size, init_from_groundtruth=True)
                    runs.append((f"{m}+ba{args.ba}", res_ba, []))
            if bases:
                runs += [(b, best(base_rounds[b]), []) for b in bases]
                # The essential-matrix baseline once: no ratio uses it.
                res_e = run_baseline(seq, "essential", size=size, init_from_groundtruth=True)
                runs.append(("baseline-essential", res_e, []))
            for name, res, ratios in runs:
                err = errors(res, seq)
                print(
                    f"{key:13} {size[0]}x{size[1]:<4} {name:16} {res.fps:7.1f} {res.fps_cpu:7.1f} "
                    f"{err['ate_m']:8.4f} {err['rpe_m']:8.4f} {err['rpe_deg']:8.3f} {err['lab_rel_m']:8.4f} "
                    f"{err['lab_rel_deg']:8.3f} {err['lab_abs_m']:8.4f} {err['lab_abs_deg']:8.3f}  "
                    f"{stage_line(res)}"
                )
                row: dict[str, object] = {
                    "sequence": key,
                    "size": f"{size[0]}x{size[1]}",
                    "method": name,
                    "fps": res.fps,
                    "fps_cpu": res.fps_cpu,
                    "preloaded": bool(args.preload and key not in SYNTHETIC),
                    **err,
                }
                row["stage_ms"] = {k: float(np.mean(v)) for k, v in res.stage_ms.items()}
                row["quality_counts"] = np.bincount(res.quality, minlength=5).tolist()
                if ratios:
                    row["speedup_baseline"] = base_for(name)
                    row["speedup_paired"] = ratios
                    row["speedup_median"] = float(np.median(ratios))
                rows.append(row)
            for b in bases:
                ours = [(n, q) for n, _, q in runs if q and base_for(n) == b]
                if not ours:
                    continue
                base_fps = ", ".join(f"{r.fps_cpu:.1f}" for r in base_rounds[b])
                print(
                    f"{'':13} speed vs {b} ({base_fps} cpu fps in {len(base_rounds[b])} rounds), "
                    "median of the paired ratios (min-max):"
                )
                print(
                    f"{'':13}   " + ", ".join(f"{n} {np.median(q):.1f}x ({min(q):.1f}-{max(q):.1f})" for n, q in ours)
                )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
        print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
