"""Camera-to-mocap time offset and clock drift, from the rotation rates both see.

The camera (through VO) and the mocap body see the same rotation; their rate magnitudes
``|omega|`` do not depend on the camera mount or on either world frame, so they match once the
camera's stamps are moved onto the mocap's time base. The model, for one physical instant::

    t_camera - t_mocap = offset_s + drift_ppm * 1e-6 * (t_mocap - ref)

(``offset_s > 0``: the camera's stamps are late; ``drift_ppm > 0``: the camera clock runs fast).
A mocap system that stamps on arrival adds its latency to ``t_mocap``, so what is measured is
the camera's offset *minus* the mocap's latency, which is what aligning the two streams needs.

Estimation, in :func:`estimate_time_offset`:

1. the mocap orientation is smoothed (a zero-phase moving average about one camera frame long),
   slerped, and its mean rate taken over intervals as long as the camera's rate intervals
   (``rate_interval_s``, whole frames) on a 0.5 ms grid, so both rate series are averaged alike;
2. coarse: the lag maximising the correlation of the two ``|omega|`` series within
   ``max_offset_s``;
3. per time window: a scan around it, then Brent's method on the exact objective (the mocap
   rate over each camera interval shifted by the lag), giving a sub-millisecond offset and its
   uncertainty from the curvature of the objective;
4. a line through the windows' offsets: the offset at ``ref`` and the drift;
5. offset and drift refined together on every interval (Gauss-Newton from the line), with
   their 1-sigma from the Jacobian (overlapping intervals counted once); the offset's is at
   least the windows' curvature one.

It refuses (:class:`~flightkit.errors.CalibrationError`) when the rotation rate varies too little
to tell one lag from another, or when no lag correlates clearly.

Pure numpy/scipy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.optimize import minimize_scalar
from scipy.spatial.transform import Rotation, Slerp

from flightkit.calibration.rates import TimedOrientations, interval_rates, rotations_of
from flightkit.errors import CalibrationError

__all__ = ["TimeOffsetEstimate", "estimate_time_offset"]

_GRID_S = 0.0005
_NS = 1_000_000_000


@dataclass(frozen=True, slots=True)
class TimeOffsetEstimate:
    """The camera clock against the mocap clock (see the module docstring for the model).

    Attributes:
        offset_s: camera stamp minus mocap stamp of the same instant, at ``ref_ns`` (mocap time).
        offset_uncertainty_s: one standard deviation of ``offset_s``.
        drift_ppm: how much faster the camera clock runs, parts per million (0 when not estimated).
        drift_uncertainty_ppm: one standard deviation (0 when not estimated).
        drift_estimated: whether the recording was long enough for windows to give a drift.
        ref_ns: the mocap time ``offset_s`` refers to (the middle of the overlap).
        correlation: Pearson correlation of the two ``|omega|`` series once aligned (1 = identical).
        excitation_rad_s: standard deviation of the mocap body's ``|omega|`` over the overlap.
        windows: per window, (centre in s from ``ref_ns``, offset in s, its uncertainty in s).
        pairs: camera intervals used.
        outliers: camera intervals left out because no lag explains their rate (VO glitches).
    """

    offset_s: float
    offset_uncertainty_s: float
    drift_ppm: float
    drift_uncertainty_ppm: float
    drift_estimated: bool
    ref_ns: int
    correlation: float
    excitation_rad_s: float
    windows: tuple[tuple[float, float, float], ...]
    pairs: int
    outliers: int = 0

    def offset_at_s(self, t_mocap_ns: int) -> float:
        """Camera minus mocap stamp at mocap time ``t_mocap_ns``, seconds."""
        return self.offset_s + self.drift_ppm * 1e-6 * (t_mocap_ns - self.ref_ns) / _NS

    def camera_to_mocap_ns(self, stamps_ns: npt.ArrayLike) -> npt.NDArray[np.int64]:
        """Camera stamps moved onto the mocap time base (int64 ns)."""
        t_c = np.asarray(stamps_ns, dtype=np.int64)
        k = self.drift_ppm * 1e-6
        rel = (t_c - self.ref_ns).astype(np.float64) - self.offset_s * _NS
        return np.asarray(self.ref_ns + np.round(rel / (1.0 + k)).astype(np.int64), dtype=np.int64)


def _smoothed(rots: Rotation, half: int) -> Rotation:
    """A zero-phase moving average of an orientation track over ``2 * half + 1`` samples (in the
    tangent space of each sample), so white mocap noise does not make the objective jagged."""
    n = len(rots)
    if half < 1 or n < 2 * half + 1:
        return rots
    acc = np.zeros((n, 3))
    cnt = np.zeros(n)
    for j in range(-half, half + 1):
        lo, hi = max(0, -j), min(n, n - j)
        idx = np.arange(lo, hi)
        acc[idx] += (rots[idx].inv() * rots[idx + j]).as_rotvec()
        cnt[idx] += 1
    return rots * Rotation.from_rotvec(acc / cnt[:, None])


def _mean_rate_series(
    slerp: Slerp, m0: float, m1: float, interval_s: float
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    half = 0.5 * interval_s
    grid = np.arange(m0 + half, m1 - half, _GRID_S)
    w = np.linalg.norm(interval_rates(slerp, grid - half, grid + half), axis=1)
    return grid, np.asarray(w, dtype=np.float64)


def _joint(
    slerp: Slerp,
    a: npt.NDArray[np.float64],
    b: npt.NDArray[np.float64],
    w_c: npt.NDArray[np.float64],
    t_rel: npt.NDArray[np.float64],
    offset_s: float,
    drift_ppm: float,
    overlap: int,
) -> tuple[float, float, float, float]:
    """Offset and drift fitted together on every interval (Gauss-Newton, central differences
    wide enough to step over the slerp's knots); returns them with their 1-sigma."""
    x = np.array([offset_s * 1e3, drift_ppm])  # ms, ppm: both of order 1-100
    steps = np.array([0.2, 5.0])

    def resid(p: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        d = p[0] * 1e-3 + p[1] * 1e-6 * t_rel
        return np.asarray(w_c - np.linalg.norm(interval_rates(slerp, a - d, b - d), axis=1), dtype=np.float64)

    J = np.zeros((a.size, 2))  # noqa: N806
    for _ in range(8):
        r0 = resid(x)
        for i in range(2):
            e = np.zeros(2)
            e[i] = steps[i]
            J[:, i] = (resid(x + e) - resid(x - e)) / (2 * steps[i])
        dx, *_ = np.linalg.lstsq(J, -r0, rcond=None)
        x = x + dx
        if abs(dx[0]) < 1e-4 and abs(dx[1]) < 1e-2:
            break
    r = resid(x)
    s2 = float(r @ r) / max(1, r.size - 2)
    cov = s2 * overlap * np.linalg.inv(J.T @ J)
    return float(x[0]) * 1e-3, float(x[1]), math.sqrt(float(cov[0, 0])) * 1e-3, math.sqrt(float(cov[1, 1]))


def _corr(a: npt.NDArray[np.float64], b: npt.NDArray[np.float64]) -> float:
    a = a - a.mean()
    b = b - b.mean()
    den = math.sqrt(float(a @ a) * float(b @ b))
    return float(a @ b) / den if den > 0 else 0.0


def estimate_time_offset(
    mocap: TimedOrientations,
    camera: TimedOrientations,
    *,
    max_offset_s: float = 0.5,
    window_s: float = 10.0,
    min_excitation_deg_s: float = 5.0,
    fit_drift: bool = True,
    rate_interval_s: float = 0.1,
    refine_jointly: bool = True,
) -> TimeOffsetEstimate:
    """Estimate the camera's time offset (and drift) against the mocap from rotation rates.

    Args:
        mocap: the mocap body's orientations (any world frame), stamps in mocap time.
        camera: the camera's orientations (e.g. VO, any world frame), stamps in camera time.
        max_offset_s: the largest offset searched, either sign.
        window_s: the length of the windows whose offsets give the drift.
        min_excitation_deg_s: the smallest standard deviation of the body's ``|omega|`` accepted.
        fit_drift: fit a drift (needs at least three windows, else it is reported as 0).
        rate_interval_s: rates are mean rates over this long (whole camera frames, at least
            one): longer averages out noise of VO and mocap, shorter keeps fast motion.
        refine_jointly: after the line through the windows, fit offset and drift together on
            every interval (more precise than the windows' line).

    Returns:
        The estimate. Runs in well under a second for minutes of data.

    Raises:
        CalibrationError: too few samples, no overlap, too little rotation, or no clear correlation.
    """
    cam_st = np.asarray(camera.stamps_ns, dtype=np.int64)
    mo_st = np.asarray(mocap.stamps_ns, dtype=np.int64)
    if cam_st.size < 10 or mo_st.size < 10:
        raise CalibrationError(
            f"{cam_st.size} camera and {mo_st.size} mocap orientations are too few to align; record longer",
            "time offset",
        )
    origin = int(mo_st[0])
    t_m, r_m = rotations_of(mocap, origin)
    t_c, r_c = rotations_of(camera, origin)
    frame_s_est = float(np.median(np.diff(t_c)))
    mocap_dt = float(np.median(np.diff(t_m)))
    slerp = Slerp(t_m, _smoothed(r_m, round(0.5 * frame_s_est / mocap_dt)))
    frame_s = float(np.median(np.diff(t_c)))
    k = max(1, round(rate_interval_s / frame_s))
    dt_c = t_c[k:] - t_c[:-k]
    interval = k * frame_s
    ok = np.abs(dt_c - interval) <= 0.25 * frame_s
    a, b = t_c[:-k][ok], t_c[k:][ok]
    w_c_all = np.linalg.norm((r_c[:-k].inv() * r_c[k:]).as_rotvec(), axis=1)
    w_c = w_c_all[ok] / (b - a)
    # camera intervals whose mocap counterpart exists for every lag searched
    inside = (a - max_offset_s >= t_m[0] + interval) & (b + max_offset_s <= t_m[-1] - interval)
    a, b, w_c = a[inside], b[inside], w_c[inside]
    if a.size < 10:
        raise CalibrationError(
            f"the camera and mocap overlap in only {a.size} usable camera intervals (searching +-{max_offset_s:g} s); "
            "check that both streams cover the same flight, or lower max_offset_s",
            "time offset",
        )
    grid, w_grid = _mean_rate_series(slerp, float(t_m[0]), float(t_m[-1]), interval)
    mid = 0.5 * (a + b)

    excitation = float(np.std(np.interp(mid, grid, w_grid)))
    if math.degrees(excitation) < min_excitation_deg_s:
        raise CalibrationError(
            f"too little rotation to tell: the body's rotation rate varies by {math.degrees(excitation):.2f} deg/s "
            f"(standard deviation) over the recording, below {min_excitation_deg_s:g} deg/s; "
            "rotate the body about at least two axes (roll, pitch and yaw swings of 20-40 degrees, "
            "changing speed) while the camera sees texture",
            "time offset",
        )

    # 2. coarse: correlation over every lag of the grid
    lags = np.arange(-max_offset_s, max_offset_s + _GRID_S / 2, _GRID_S)
    scores = np.empty(lags.size)
    for i, d in enumerate(lags):
        scores[i] = _corr(w_c, np.interp(mid - d, grid, w_grid))
    best = int(np.argmax(scores))
    d0 = float(lags[best])
    if scores[best] < 0.5:
        raise CalibrationError(
            f"no lag within +-{max_offset_s:g} s makes the camera's and the body's rotation rates agree "
            f"(best correlation {scores[best]:.2f} at {d0 * 1e3:.1f} ms); check that the camera is rigidly on "
            "that body, that VO tracked the flight, or search a larger max_offset_s",
            "time offset",
        )

    # intervals the aligned body rate cannot explain (a VO glitch) are left out
    r = w_c - np.interp(mid - d0, grid, w_grid)
    mad = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    good = np.abs(r - np.median(r)) <= max(6.0 * mad, 0.02)
    outliers = int(a.size - good.sum())
    a, b, w_c, mid = a[good], b[good], w_c[good], mid[good]

    # 3. windows: scan around d0, then Brent on the exact interval objective
    t_ref = 0.5 * (mid[0] + mid[-1])
    duration = float(mid[-1] - mid[0])
    n_win = max(1, int(duration // window_s))
    if fit_drift and n_win < 3 and duration / 3.0 >= 3.0:
        n_win = 3
    edges = np.linspace(mid[0], mid[-1] + 1e-9, n_win + 1)
    span_s = 0.03 if n_win > 1 else 0.005
    windows: list[tuple[float, float, float]] = []
    for k in range(n_win):
        sel = (mid >= edges[k]) & (mid < edges[k + 1])
        if sel.sum() < 10:
            continue
        wa, wb, wc = a[sel], b[sel], w_c[sel]
        if math.degrees(float(np.std(wc))) < 0.5 * min_excitation_deg_s:
            continue  # a quiet window says nothing about the lag
        local = np.arange(d0 - span_s, d0 + span_s + _GRID_S / 2, _GRID_S)
        sse = [float(np.mean((wc - np.interp(0.5 * (wa + wb) - d, grid, w_grid)) ** 2)) for d in local]
        dk = float(local[int(np.argmin(sse))])

        def objective(d: float, wa: npt.NDArray[np.float64] = wa, wb: npt.NDArray[np.float64] = wb,
                      wc: npt.NDArray[np.float64] = wc) -> float:
            w_m = np.linalg.norm(interval_rates(slerp, wa - d, wb - d), axis=1)
            return float(np.mean((wc - w_m) ** 2))

        res = minimize_scalar(objective, bounds=(dk - 2 * _GRID_S, dk + 2 * _GRID_S), method="bounded",
                              options={"xatol": 1e-7})
        d_k = float(res.x)
        f0 = float(res.fun)
        h = 5e-4
        curv = (objective(d_k + h) - 2 * f0 + objective(d_k - h)) / (h * h)
        n = int(sel.sum())
        s2 = f0 * n / max(1, n - 1)
        # overlapping rate intervals (k frames each) share their noise: n / k independent residuals
        sigma = math.sqrt(2.0 * s2 * k / (n * curv)) if curv > 0 else math.inf
        windows.append((float(np.mean(0.5 * (wa + wb)) - t_ref), d_k, sigma))
    if not windows:
        raise CalibrationError(
            "too little rotation to tell: no part of the recording has enough rotation to align; "
            "rotate the body about at least two axes while the camera sees texture",
            "time offset",
        )

    # 4. a line through the windows
    tc = np.array([w[0] for w in windows])
    dk_arr = np.array([w[1] for w in windows])
    sig = np.array([w[2] for w in windows])
    curv_sigma = float(1.0 / math.sqrt(float(np.sum(1.0 / np.maximum(sig, 1e-9) ** 2))))
    drift_ok = fit_drift and len(windows) >= 3
    if drift_ok:
        X = np.stack([np.ones_like(tc), tc], axis=1)  # noqa: N806
        coef, *_ = np.linalg.lstsq(X, dk_arr, rcond=None)
        resid = dk_arr - X @ coef
        dof = max(1, len(windows) - 2)
        cov = float(resid @ resid) / dof * np.linalg.inv(X.T @ X)
        offset, slope = float(coef[0]), float(coef[1])
        off_sigma = max(math.sqrt(float(cov[0, 0])), curv_sigma)
        drift_sigma = math.sqrt(float(cov[1, 1])) * 1e6
        # the windows' own precision bounds the slope's too
        spread = float(np.sum((tc - tc.mean()) ** 2))
        drift_sigma = max(drift_sigma, curv_sigma * math.sqrt(len(windows) / spread) * 1e6 if spread > 0 else 0.0)
        drift_ppm = slope * 1e6
    else:
        w = 1.0 / np.maximum(sig, 1e-9) ** 2
        offset = float(np.sum(w * dk_arr) / np.sum(w))
        off_sigma = max(curv_sigma, float(np.std(dk_arr)) / math.sqrt(len(windows)))
        drift_ppm = drift_sigma = 0.0
    if drift_ok and refine_jointly:
        offset, drift_ppm, off_sigma_j, drift_sigma_j = _joint(slerp, a, b, w_c, mid - t_ref, offset, drift_ppm, k)
        off_sigma = max(off_sigma_j, curv_sigma)
        drift_sigma = drift_sigma_j
    # the aligned correlation (drift applied)
    shift = offset + drift_ppm * 1e-6 * (mid - t_ref)
    corr = _corr(w_c, np.interp(mid - shift, grid, w_grid))
    return TimeOffsetEstimate(
        offset_s=offset,
        offset_uncertainty_s=off_sigma,
        drift_ppm=drift_ppm,
        drift_uncertainty_ppm=drift_sigma,
        drift_estimated=drift_ok,
        ref_ns=origin + round(t_ref * _NS),
        correlation=corr,
        excitation_rad_s=excitation,
        windows=tuple(windows),
        pairs=int(a.size),
        outliers=outliers,
    )
