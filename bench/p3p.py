"""Benchmark of the compiled P3P RANSAC (``estimation.p3p.pnp_ransac``) beside OpenCV's
``solvePnPRansac`` with its iterative kernel (as ``estimation.pnp.pnp`` calls it by default) and
with its AP3P kernel, on the PnP RANSAC calls of real runs, one core.

Every ``solvePnPRansac`` call of an ``rgbd-pnp`` run on TUM fr1/rpy and 7-Scenes and of a
``stereo`` run on KITTI 06 (native resolution, started at the first ground-truth pose) is
recorded; then the three run on the recorded calls, interleaved (the order rotates each round),
``--rounds`` times. Prints per sequence: the calls, the median point count, ms per call of each
(CPU time, median of the rounds), OpenCV's over ours, how many calls give the iterative kernel's
inlier set exactly and the mean size of ours minus the iterative kernel's (and the same for
OpenCV's AP3P kernel, for scale); then the same for the whole ``pnp()`` (the
RANSAC, Levenberg-Marquardt on its inliers and the inliers re-selected: ``ransac_kernel="p3p"``
against None) with the largest pose difference (mm, degrees) between the two.

Run: .venv/bin/python bench/p3p.py [--only tum_rpy,7scenes,kitti06] [--rounds 5] [--cpu N]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench._host import pin_one_cpu  # noqa: E402
from estimation.motion import make_T, rotation_angle_rad  # noqa: E402
from estimation.p3p import pnp_ransac  # noqa: E402
from estimation.pipeline import run_vo, warm_up  # noqa: E402
from estimation.pnp import pnp  # noqa: E402
from flightkit.datasets.registry import open_sequence  # noqa: E402

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SEQUENCES = {
    "tum_rpy": ("tum_fr1rpy_000_199", "rgbd-pnp"),
    "7scenes": ("sevenscenes_tsdf50", "rgbd-pnp"),
    "kitti06": ("kitti06_stereo", "stereo"),
}


@dataclass(frozen=True, slots=True)
class Call:
    """One recorded ``solvePnPRansac`` call."""

    points_ref: np.ndarray  # (N, 3) m
    pts_px: np.ndarray  # (N, 2)
    K: np.ndarray
    rvec0: np.ndarray | None  # the extrinsic guess, if one was used
    tvec0: np.ndarray | None
    iters: int
    threshold_px: float
    confidence: float
    flags: int


def record(folder: str, method: str) -> list[Call]:
    """The PnP RANSAC calls of one run (the run itself uses OpenCV's, as by default)."""
    calls: list[Call] = []
    original = cv2.solvePnPRansac

    def recorder(obj: Any, img: Any, K: Any, dist: Any, **kw: Any) -> Any:
        guess = bool(kw.get("useExtrinsicGuess", False))
        calls.append(
            Call(
                np.array(obj, dtype=np.float64).reshape(-1, 3),
                np.array(img, dtype=np.float64).reshape(-1, 2),
                np.array(K, dtype=np.float64),
                np.array(kw["rvec"], dtype=np.float64) if guess else None,
                np.array(kw["tvec"], dtype=np.float64) if guess else None,
                int(kw.get("iterationsCount", 100)),
                float(kw.get("reprojectionError", 8.0)),
                float(kw.get("confidence", 0.99)),
                int(kw.get("flags", cv2.SOLVEPNP_ITERATIVE)),
            )
        )
        return original(obj, img, K, dist, **kw)

    cv2.solvePnPRansac = recorder
    try:
        run_vo(open_sequence(DATA / folder), method, init_from_groundtruth=True)
    finally:
        cv2.solvePnPRansac = original
    return calls


def opencv(c: Call, flags: int, guess: tuple[np.ndarray, np.ndarray] | None) -> Any:
    """``solvePnPRansac`` on a recorded call with ``flags`` (and the call's guess, copied fresh)."""
    r0, t0 = guess if guess is not None else (None, None)
    return cv2.solvePnPRansac(
        c.points_ref,
        c.pts_px,
        c.K,
        None,
        rvec=r0,
        tvec=t0,
        useExtrinsicGuess=guess is not None,
        iterationsCount=c.iters,
        reprojectionError=c.threshold_px,
        confidence=c.confidence,
        flags=flags,
    )


def mask_of(n: int, inl: Any) -> np.ndarray:
    m = np.zeros(n, dtype=bool)
    if inl is not None:
        m[np.asarray(inl).ravel()] = True
    return m


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", default=",".join(SEQUENCES), help="comma-separated sequence keys")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--cpu", type=int, help="the CPU to pin the process to (default: the last one)")
    args = ap.parse_args()
    pin_one_cpu(args.cpu)
    cv2.setNumThreads(1)
    warm_up("rgbd-pnp")
    pnp_ransac(np.eye(4, 3), np.ones((4, 2)), np.eye(3))  # compiled (or loaded) before timing
    print(f"OpenCV {cv2.__version__}, one thread, one CPU; median of {args.rounds} interleaved rounds")
    print(
        f"{'sequence':9} {'calls':>5} {'pts':>4} {'ours ms':>7} {'iter ms':>7} {'ap3p ms':>7} {'iter/':>5} "
        f"{'ap3p/':>5} {'same inliers':>12} {'d size':>6} {'(ap3p:':>6} {'same':>4} {'d size)':>7} | "
        f"{'pnp(): same':>11} {'d size':>6} {'max dt mm':>9} {'max dR deg':>10}"
    )
    for key in args.only.split(","):
        folder, method = SEQUENCES[key]
        calls = record(folder, method)
        if not calls:
            print(f"{key:9} {0:5d}  (no RANSAC call: the prediction explained every frame)")
            continue
        others = sum(c.flags != cv2.SOLVEPNP_ITERATIVE for c in calls)
        kernels = ("ours", "iter", "ap3p")
        t: dict[str, list[float]] = {k: [] for k in kernels}
        got: dict[str, list[Any]] = {}
        for r in range(args.rounds):
            # Fresh copies of the guesses (OpenCV writes its result into them), made before timing.
            guesses = [None if c.rvec0 is None or c.tvec0 is None else (c.rvec0.copy(), c.tvec0.copy()) for c in calls]
            for k in kernels[r % 3 :] + kernels[: r % 3]:
                clock = time.thread_time()
                if k == "ours":
                    out = [
                        pnp_ransac(c.points_ref, c.pts_px, c.K, c.threshold_px, c.confidence, c.iters) for c in calls
                    ]
                elif k == "iter":
                    out = [opencv(c, cv2.SOLVEPNP_ITERATIVE, g) for c, g in zip(calls, guesses, strict=True)]
                else:
                    out = [opencv(c, cv2.SOLVEPNP_AP3P, None) for c in calls]
                t[k].append(time.thread_time() - clock)
                got.setdefault(k, out)
        ms = {k: 1e3 * float(np.median(v)) / len(calls) for k, v in t.items()}
        same, dsize, same_ap3p, dsize_ap3p = 0, [], 0, []
        for c, o, i, a3 in zip(calls, got["ours"], got["iter"], got["ap3p"], strict=True):
            n = len(c.points_ref)
            m_ours = o[3] if o[0] else np.zeros(n, dtype=bool)
            m_iter = mask_of(n, i[3]) if i[0] else np.zeros(n, dtype=bool)
            m_ap3p = mask_of(n, a3[3]) if a3[0] else np.zeros(n, dtype=bool)
            same += bool(np.array_equal(m_ours, m_iter))
            dsize.append(int(m_ours.sum()) - int(m_iter.sum()))
            same_ap3p += bool(np.array_equal(m_ap3p, m_iter))
            dsize_ap3p.append(int(m_ap3p.sum()) - int(m_iter.sum()))
        # The whole pnp() (as estimation.estimators calls it: iterative, refine) with either RANSAC.
        same_f, dsize_f, dt, dR = 0, [], 0.0, 0.0
        for c in calls:
            guess_T = None
            if c.rvec0 is not None and c.tvec0 is not None:
                guess_T = make_T(cv2.Rodrigues(c.rvec0)[0], c.tvec0.ravel())
            kw: dict[str, Any] = dict(
                method="iterative",
                reproj_px=c.threshold_px,
                max_iters=c.iters,
                confidence=c.confidence,
                min_inliers=6,
                guess_T_cur_ref=guess_T,
            )
            a = pnp(c.points_ref, c.pts_px, c.K, ransac_kernel=None, **kw)
            b = pnp(c.points_ref, c.pts_px, c.K, ransac_kernel="p3p", **kw)
            same_f += bool(np.array_equal(a.inliers, b.inliers) and a.ok == b.ok)
            dsize_f.append(b.n_inliers - a.n_inliers)
            if a.ok and b.ok:
                dt = max(dt, 1e3 * float(np.linalg.norm(a.t - b.t)))
                dR = max(dR, float(np.degrees(rotation_angle_rad(a.R.T @ b.R))))
        npts = float(np.median([len(c.points_ref) for c in calls]))
        label = f"{len(calls):5d}" + (f" ({others} not iterative)" if others else "")
        print(
            f"{key:9} {label} {npts:4.0f} {ms['ours']:7.3f} {ms['iter']:7.3f} {ms['ap3p']:7.3f} "
            f"{ms['iter'] / ms['ours']:5.1f} {ms['ap3p'] / ms['ours']:5.1f} {same:5d} of {len(calls):4d} "
            f"{np.mean(dsize):+6.2f} {same_ap3p:11d} {np.mean(dsize_ap3p):+7.2f} | {same_f:4d} of {len(calls):4d} "
            f"{np.mean(dsize_f):+6.2f} {dt:9.3f} {dR:10.4f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
