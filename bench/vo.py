"""Benchmark of the visual odometry methods against plain OpenCV pipelines, at native resolution, one core.

For every real sequence in ``../shared/data`` (KITTI 06 stereo 1226x370, TUM fr1/rpy RGB-D
640x480, 7-Scenes RGB-D, the two TUM fr1/xyz pairs, EuRoC V1_01 at rest), at the camera's own
resolution unless ``--sizes`` asks for others, runs side by side in the same process:

* every flightkit method the sequence's sensors allow (``estimation.pipeline.run_vo``);
* the plain pipelines of ``estimation.baselines`` with their fixed parameters: ``plain-stereo``
  (StereoSGBM of the previous pair + GFTT + KLT + solvePnPRansac) on stereo sequences,
  ``plain-rgbd`` (ORB + depth + solvePnPRansac) on RGB-D ones. These are the bar (issue 15);
* the lab's SIFT pipeline (``estimation.lab_sift``, ``baseline-pnp``), the historical reference.

Per run it prints:

* ``cpu fps``: frames per CPU second of the VO thread (images decoded before each frame's
  timer starts), the median of ``--rounds`` runs, and ``best``, the fastest of them (other
  processes only ever add time, so the fastest run is the least disturbed one). The rounds are
  interleaved: each round runs every row of a sequence, in alternating order, so a change in
  the machine's load falls on all rows alike. The process is pinned to one CPU and OpenCV/BLAS
  to one thread;
* ``ATE``: RMSE of the positions after SE(3) alignment, and after Sim(3) alignment with its scale;
* ``RPE``: RMSE of the 1-frame relative translation (mm) and rotation (deg);
* ``rot``: RMSE of the absolute rotation error (deg) after SE(3) alignment, and with only the
  first pose aligned (``rot0``: the estimate started at the first ground-truth pose), which
  is the meaningful figure on a nearly straight path (the SE(3) alignment of a line leaves
  its roll free);
* ``drift``: the end-point position error with the first pose aligned, in % of the
  ground-truth path length;
* the quality counts (estimated / predicted / fallback frames) and keyframes.

``--spread N`` reruns every row without an ``@variant`` (``--ba`` rows included) on N copies of the
sequence whose exposure is jittered by an amount no eye would see (gains log-normal, 0.5 % rms,
seeds 0..N-1) and prints the mean and standard deviation of its errors: on these short sequences
a single run is one draw (KITTI's SE3 ATE moves by +-20 % between such copies, for ours and for
plain), so a comparison of two methods is read on the means, against the spreads.

``--synthetic`` adds the three lab patterns (the simulated camera, exact ground truth, rendered
before timing at each size: ``bench/_synthetic.py``).

``--features 450,600`` adds ``stereo#N`` rows with N corners per keyframe.

``--replay forward,reverse,every2,exposure`` runs every sequence also played backwards (rows
mirrored for a rolling-shutter camera), at half the frame rate, and with the exposure changing
from frame to frame (gains log-normal, 15 % rms, seed 0) (``flightkit.datasets.replay``): the
same real data with motion and lighting nothing was tuned on.

Run: .venv/bin/python bench/vo.py [--only kitti06,tum_rpy] [--sizes native,640x480] [--rounds 1]
     [--no-sift] [--ba 4] [--features 450,600] [--replay forward,reverse,every2,exposure] [--spread 6]
     [--synthetic]
     [--json out.json] [--cpu N]
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
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # `bench._synthetic` when run as a script

from bench._host import pin_one_cpu  # noqa: E402
from bench._synthetic import METHODS as SYNTHETIC_METHODS  # noqa: E402
from bench._synthetic import SYNTHETIC, prerendered  # noqa: E402
from estimation.baselines import run_plain  # noqa: E402
from estimation.evaluation import Alignment, ape, lab_errors, rpe  # noqa: E402
from estimation.lab_sift import run_baseline  # noqa: E402
from estimation.pipeline import (  # noqa: E402
    FlowOptions,
    Method,
    PnpOptions,
    Quality,
    VoOptions,
    VoResult,
    run_vo,
    warm_up,
)
from flightkit.datasets.registry import open_sequence  # noqa: E402
from flightkit.datasets.replay import (  # noqa: E402
    exposure_sequence,
    lognormal_gains,
    reversed_sequence,
    strided_sequence,
)

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

RGBD = [
    "rgbd-pnp",
    "rgbd-essential",
    "rgbd-kabsch",
    "rgbd-kabsch@weigh",
    "rgbd-kabsch@revisit",
    "rgbd-kabsch@fixedexp",
    "flow",
    "rgbd-pnp@global",
    "rgbd-essential@global",
    "rgbd-kabsch@global",
]
STEREO = [
    "stereo",
    "stereo@lk",
    "stereo@row",
    "stereo@exact",
    "stereo@ransac",
    "stereo@drop",
    "stereo@far",
    "stereo@offset",
    "stereo@fixedexp",
]
SEQUENCES: dict[str, tuple[str, list[str], str]] = {
    # key: (folder, flightkit methods, plain baseline)
    "kitti06": ("kitti06_stereo", STEREO + ["flow"], "plain-stereo"),
    "tum_rpy": ("tum_fr1rpy_000_199", RGBD, "plain-rgbd"),
    "7scenes": ("sevenscenes_tsdf50", RGBD, "plain-rgbd"),
    "tum_case1": ("tum_fr1xyz_pairs/case_1", RGBD, "plain-rgbd"),
    "tum_case2": ("tum_fr1xyz_pairs/case_2", RGBD, "plain-rgbd"),
    "euroc_static": ("euroc_v101_static", STEREO + ["flow@stereo"], "plain-stereo"),
}


VARIANTS: dict[str, VoOptions] = {
    "": VoOptions(),
    "stereo": VoOptions(estimator=FlowOptions(depth="stereo")),  # flow with per-point stereo depth
    "drop": VoOptions(far_points="drop", stereo_offset=False),  # stereo before the eleventh pass
    "offset": VoOptions(far_points="drop"),  # stereo: far points dropped, the disparity offset estimated online
    "far": VoOptions(stereo_offset=False),  # stereo: far points weighted, no disparity offset
    "global": VoOptions(readout_s=0.0),  # the rows read as exposed at once (before the fourteenth pass)
    "fixedexp": VoOptions(exposure_compensation=False),  # exposure changes not undone (before the eighteenth pass)
    "revisit": VoOptions(revisit_keyframes=30),  # RGB-D returning to kept keyframes the camera sees again
    "weigh": VoOptions(point_uncertainty=True),  # RGB-D: the polish weighs each point by its keyframe depth's noise
    "exact": VoOptions(point_uncertainty=False),  # stereo: the polish takes the keyframe points as exact
    "ransac": VoOptions(estimator=PnpOptions(prior_gate_px=0.0)),  # stereo before the speed pass: RANSAC every step
    "lk": VoOptions(stereo_matcher="lk"),  # stereo: new points' disparity by LK alone (before the twelfth pass)
    "row": VoOptions(stereo_matcher="row"),  # stereo: new points' disparity by the row search alone
}
"""Row-name suffixes (``method@variant``) and their options."""

REPLAYS: dict[str, Any] = {
    "forward": lambda seq: seq,
    "reverse": reversed_sequence,
    "every2": lambda seq: strided_sequence(seq, 2),
    "exposure": lambda seq: exposure_sequence(seq, lognormal_gains(len(seq))),
}
"""``--replay`` names and how each replays a sequence."""

SPREAD_GAIN_RMS = 0.005
"""``--spread``: the exposure jitter of each copy (log-normal gains, rms of their logarithm)."""


def metrics(res: VoResult, gt: Any) -> dict[str, float]:
    """ATE (SE3, Sim3 and its scale), RPE, rotation errors and end-point drift of a run that
    started at the first ground-truth pose (``init_from_groundtruth=True``)."""
    est = res.trajectory("camera")
    nan = float("nan")
    out: dict[str, float] = dict.fromkeys(("ate_m", "ate_sim3_m", "sim3_scale", "rot_deg"), nan)
    if len(est) >= 3:
        a = ape(est, gt, Alignment.SE3)
        s = ape(est, gt, Alignment.SIM3)
        out.update(
            ate_m=a.translation.rmse,
            ate_sim3_m=s.translation.rmse,
            sim3_scale=s.alignment.scale,
            rot_deg=math.degrees(a.rotation.rmse),
        )
    r = rpe(est, gt, 1.0, "frames", Alignment.NONE)
    out["rpe_mm"] = 1e3 * r.translation.rmse
    out["rpe_deg"] = math.degrees(r.rotation.rmse)
    lab = lab_errors(est, gt)
    out["rot0_deg"] = math.degrees(float(np.sqrt(np.mean(lab.absolute_rotation_rad**2))))
    path = gt.path_length_m() if len(gt) == len(est) else _matched_path(est, gt)
    out["drift_pct"] = 100.0 * float(lab.absolute_translation_m[-1]) / path if path > 0 else nan
    return out


def _matched_path(est: Any, gt: Any) -> float:
    """Path length of the ground truth over the estimate's time span."""
    t0, t1 = est.stamps_ns[0], est.stamps_ns[-1]
    keep = (gt.stamps_ns >= t0 - 10_000_000) & (gt.stamps_ns <= t1 + 10_000_000)
    p = gt.positions[keep]
    return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1))) if len(p) > 1 else 0.0


def quality_line(res: VoResult) -> str:
    q = np.bincount(res.quality.astype(int), minlength=len(Quality))
    est = int(q[Quality.GOOD] + q[Quality.WEAK])
    return f"est {est} pred {int(q[Quality.PREDICTED])} fb {int(q[Quality.FALLBACK])} kf {int(res.keyframe.sum())}"


HEADER = (
    f"{'sequence':12} {'size':9} {'method':16} {'cpu fps':>7} {'best':>6} {'ATE m':>7} {'Sim3 m':>7} {'scale':>6} "
    f"{'RPE mm':>7} {'RPE deg':>7} {'rot deg':>7} {'rot0 deg':>8} {'drift %':>7}  frames"
)


def fmt(key: str, size: str, name: str, fps: float, best: float, e: dict[str, float], q: str) -> str:
    return (
        f"{key:12} {size:9} {name:16} {fps:7.1f} {best:6.1f} "
        f"{e['ate_m']:7.4f} {e['ate_sim3_m']:7.4f} {e['sim3_scale']:6.3f} "
        f"{e['rpe_mm']:7.2f} {e['rpe_deg']:7.3f} {e['rot_deg']:7.3f} {e['rot0_deg']:8.3f} {e['drift_pct']:7.2f}  {q}"
    )


def spread_rows(
    seq: Any, plan: list[tuple[str, str, Any]], size: tuple[int, int], n: int, gt: Any
) -> list[dict[str, Any]]:
    """``--spread``: every default row of ``plan`` on ``n`` exposure-jittered copies of ``seq``;
    prints the mean and standard deviation of ATE, Sim3 ATE and RPE, returns them as JSON rows."""
    copies = [exposure_sequence(seq, lognormal_gains(len(seq), SPREAD_GAIN_RMS, seed)) for seed in range(n)]
    print(f"-- over {n} copies, exposure jittered {100 * SPREAD_GAIN_RMS:.1f} % rms: mean +- sd")
    out: list[dict[str, Any]] = []
    for name, what, opts in plan:
        if "@" in name or "#" in name or what == "sift":
            continue
        errs = [metrics(run_one(c, what, opts, size), gt) for c in copies]
        stats = {k: (float(np.mean([e[k] for e in errs])), float(np.std([e[k] for e in errs]))) for k in errs[0]}
        (a, sa), (b, sb), (r, sr) = stats["ate_m"], stats["ate_sim3_m"], stats["rpe_mm"]
        print(
            f"{'':12} {'':9} {name:16} ATE {a:.4f} +- {sa:.4f}  Sim3 {b:.4f} +- {sb:.4f}  RPE mm {r:.2f} +- {sr:.2f}",
            flush=True,
        )
        means = {f"{k}_mean": v[0] for k, v in stats.items()}
        sds = {f"{k}_sd": v[1] for k, v in stats.items()}
        out.append({"method": name, "copies": n, "gain_rms": SPREAD_GAIN_RMS, **means, **sds})
    return out


def run_one(seq: Any, what: str, opts: VoOptions | None, size: tuple[int, int]) -> VoResult:
    """One run started at the first ground-truth pose: a flightkit method, a plain baseline or the SIFT pipeline."""
    if what == "sift":
        return run_baseline(seq, "pnp", size=size, init_from_groundtruth=True)
    if what.startswith("plain-"):
        return run_plain(seq, what, size=size, init_from_groundtruth=True)
    return run_vo(seq, what, options=opts, size=size, init_from_groundtruth=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="native", help="comma-separated WIDTHxHEIGHT or 'native' (default)")
    ap.add_argument(
        "--rounds", type=int, default=1, help="interleaved runs per method; the speed is their median (and best)"
    )
    ap.add_argument("--no-sift", action="store_true", help="skip the lab's SIFT pipeline (slow at native size)")
    ap.add_argument("--ba", type=int, default=0, help="also run with local BA over N keyframes")
    ap.add_argument(
        "--features", default="", help="comma-separated corner budgets: also run the stereo rows with each"
    )
    ap.add_argument(
        "--replay", default="forward", help=f"comma-separated replays of each sequence: {', '.join(REPLAYS)}"
    )
    ap.add_argument(
        "--spread", type=int, default=0, help="also run the default rows on N copies with the exposure jittered"
    )
    ap.add_argument("--only", help="comma-separated sequence keys")
    ap.add_argument("--synthetic", action="store_true", help="add the synthetic lab-pattern sequences")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--cpu", type=int, help="the CPU to pin the process to (default: the last one)")
    args = ap.parse_args()

    cv2.setNumThreads(1)
    pin_one_cpu(args.cpu)
    keys = args.only.split(",") if args.only else list(SEQUENCES) + (list(SYNTHETIC) if args.synthetic else [])
    replays = args.replay.split(",")
    unknown = [r for r in replays if r not in REPLAYS]
    if unknown:
        ap.error(f"unknown replay {', '.join(unknown)}; use {', '.join(REPLAYS)}")
    rows: list[dict[str, object]] = []
    for m in Method:  # untimed: load the compiled kernels (estimation/_kernels.py)
        warm_up(m)
    print(f"data: {DATA}; OpenCV {cv2.__version__}, threads {cv2.getNumThreads()}, one CPU")
    for key in keys:
        for size_s, replay in ((s, r) for s in args.sizes.split(",") for r in replays):
            if key in SYNTHETIC:
                size = (320, 240) if size_s == "native" else tuple(int(v) for v in size_s.split("x"))
                seq: Any = prerendered(SYNTHETIC[key], size)
                methods, plain = SYNTHETIC_METHODS, ["plain-stereo", "plain-rgbd"]
            else:
                folder, methods, base = SEQUENCES[key]
                seq = open_sequence(DATA / folder)
                plain = [base]
                native = (seq.intrinsics.width, seq.intrinsics.height)
                size = native if size_s == "native" else tuple(int(v) for v in size_s.split("x"))
            if replay != "forward" and len(seq) < 4:
                continue  # a frame pair: nothing to replay
            seq = REPLAYS[replay](seq)
            label = f"{size[0]}x{size[1]}"
            print(f"\n== {key}: {seq.name}, {len(seq)} frames at {label}")
            print(HEADER)
            gt = seq.groundtruth()
            plan: list[tuple[str, str, Any]] = []  # (row name, what to run, method or options)
            for name in methods:
                m, _, variant = name.partition("@")
                opts = VARIANTS[variant]
                plan.append((name, m, opts))
                if args.ba and Method(m) is not Method.FLOW and not variant:
                    plan.append((f"{m}+ba{args.ba}", m, replace(opts, ba_window=args.ba)))
                if m == "stereo" and not variant:
                    for n in (int(v) for v in args.features.split(",") if v):
                        plan.append((f"{name}#{n}", m, replace(opts, max_features=n)))
            plan += [(b, b, None) for b in plain]
            if not args.no_sift:
                plan.append(("sift-pnp (lab)", "sift", None))
            runs: dict[str, list[VoResult]] = {name: [] for name, _, _ in plan}
            for r in range(max(1, args.rounds)):
                for name, what, opts in plan if r % 2 == 0 else plan[::-1]:
                    runs[name].append(run_one(seq, what, opts, size))
            for name, _, _ in plan:
                res = runs[name][0]
                fps = float(np.median([x.fps_cpu for x in runs[name]]))
                best = max(x.fps_cpu for x in runs[name])
                e = metrics(res, gt)
                print(fmt(key, label, name, fps, best, e, quality_line(res)), flush=True)
                stage = {k: float(np.mean(v)) for k, v in res.stage_ms.items()}
                rows.append(
                    {
                        "sequence": key,
                        "size": label,
                        "replay": replay,
                        "method": name,
                        "fps_cpu": fps,
                        "fps_cpu_best": best,
                        **e,
                        "stage_ms": stage,
                        "quality_counts": np.bincount(res.quality.astype(int), minlength=len(Quality)).tolist(),
                        "keyframes": int(res.keyframe.sum()),
                    }
                )
            if args.spread > 0 and len(seq) >= 4:
                for row in spread_rows(seq, plan, size, args.spread, gt):
                    rows.append({"sequence": key, "size": label, "replay": replay, "spread": True, **row})
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
        print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
