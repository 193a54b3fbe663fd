"""Latency statistics along the capture -> bus -> runner -> setpoint chain, and latency compensation.

A sample's life is a row of stamps on one time base (ns): captured, on the bus, used by the
flight runner, the setpoint that used it leaving. :func:`latency_stats` gives the p50/p99/max of
every stage and of the whole chain; :func:`predict_pose` moves a pose forward by a known
latency with constant linear and angular velocity (what the runner can do with a mocap pose
that is ``latency`` old), and :func:`velocity_from_poses` measures those velocities from two
consecutive poses.

Pure numpy/scipy.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from flightkit.errors import CalibrationError
from flightkit.frames import Transform

__all__ = [
    "LatencyStats",
    "StageStats",
    "StreamHealth",
    "latency_stats",
    "predict_pose",
    "stream_health",
    "velocity_from_poses",
]

DEFAULT_STAGES = ("capture", "bus", "runner", "setpoint")


@dataclass(frozen=True, slots=True)
class StageStats:
    """Ages over one stage, milliseconds.

    Attributes:
        name: ``"capture->bus"``, ..., or ``"capture->setpoint"`` for the whole chain.
        count: samples with both stamps.
        p50_ms, p99_ms, max_ms, mean_ms: statistics of the stage's duration.
    """

    name: str
    count: int
    p50_ms: float
    p99_ms: float
    max_ms: float
    mean_ms: float


@dataclass(frozen=True, slots=True)
class LatencyStats:
    """Every stage of the chain, then the whole chain (last)."""

    stages: tuple[StageStats, ...]

    @property
    def total(self) -> StageStats:
        return self.stages[-1]

    def table(self) -> list[tuple[str, str, str, str]]:
        """Rows (stage, p50 ms, p99 ms, max ms) for printing."""
        return [(s.name, f"{s.p50_ms:.1f}", f"{s.p99_ms:.1f}", f"{s.max_ms:.1f}") for s in self.stages]


def _stage(name: str, start: npt.NDArray[np.float64], stop: npt.NDArray[np.float64]) -> StageStats:
    ok = np.isfinite(start) & np.isfinite(stop)
    d = (stop[ok] - start[ok]) / 1e6
    if d.size == 0:
        return StageStats(name, 0, float("nan"), float("nan"), float("nan"), float("nan"))
    return StageStats(name, int(d.size), float(np.percentile(d, 50)), float(np.percentile(d, 99)),
                      float(d.max()), float(d.mean()))


def latency_stats(stamps_ns: Mapping[str, Sequence[float] | npt.ArrayLike],
                  stages: Sequence[str] = DEFAULT_STAGES) -> LatencyStats:
    """Per-stage and end-to-end latency of samples.

    Args:
        stamps_ns: stage name -> one stamp per sample (ns, same length; NaN where a sample did
            not reach that stage).
        stages: the order of the chain (names present in ``stamps_ns``).

    Raises:
        CalibrationError: fewer than two stages, a missing stage, or stamps of different lengths.
    """
    names = [s for s in stages if s in stamps_ns]
    if len(names) < 2:
        raise CalibrationError(
            f"latency needs stamps of at least two stages of {', '.join(stages)}; got {', '.join(stamps_ns) or 'none'}",
            "latency",
        )
    cols = {n: np.asarray(stamps_ns[n], dtype=np.float64) for n in names}
    sizes = {c.shape for c in cols.values()}
    if len(sizes) != 1:
        raise CalibrationError(f"stage stamps differ in length: {sizes}; give one stamp per sample per stage",
                               "latency")
    out = [_stage(f"{a}->{b}", cols[a], cols[b]) for a, b in zip(names[:-1], names[1:], strict=True)]
    out.append(_stage(f"{names[0]}->{names[-1]}", cols[names[0]], cols[names[-1]]))
    return LatencyStats(tuple(out))


def velocity_from_poses(
    T_a: Transform, T_b: Transform, dt_s: float  # noqa: N803
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """(world velocity m/s, body angular rate rad/s) between two poses ``dt_s`` apart (world ENU, body FLU).

    Raises:
        CalibrationError: ``dt_s`` not positive.
    """
    if not dt_s > 0:
        raise CalibrationError(f"poses {dt_s!r} s apart give no velocity; give increasing stamps", "latency")
    vel = (T_b.translation - T_a.translation) / dt_s
    omega = (T_a.rotation.inv() * T_b.rotation).as_rotvec() / dt_s
    return np.asarray(vel, dtype=np.float64), np.asarray(omega, dtype=np.float64)


def predict_pose(T_world_body: Transform, vel_world_m_s: npt.ArrayLike, omega_body_rad_s: npt.ArrayLike,  # noqa: N803
                 latency_s: float) -> Transform:
    """The pose ``latency_s`` later at constant world velocity and constant body rate."""
    v = np.asarray(vel_world_m_s, dtype=np.float64)
    w = np.asarray(omega_body_rad_s, dtype=np.float64)
    return Transform(T_world_body.rotation * Rotation.from_rotvec(w * latency_s),
                     T_world_body.translation + v * latency_s)


@dataclass(frozen=True, slots=True)
class StreamHealth:
    """Rate, age and jitter of a stream of stamps (e.g. the mocap poses before arming).

    Attributes:
        rate_hz: samples per second over the window.
        age_s: how old the newest sample is at ``now``.
        jitter_ms: p99 of ``|interval - median interval|``, milliseconds.
        samples: stamps in the window.
    """

    rate_hz: float
    age_s: float
    jitter_ms: float
    samples: int

    def problems(self, min_rate_hz: float, max_age_s: float, max_jitter_ms: float, what: str = "mocap") -> list[str]:
        """Each bound the stream breaks, one sentence naming the value and the bound; empty means go."""
        out: list[str] = []
        if self.rate_hz < min_rate_hz:
            out.append(f"{what} arrives at {self.rate_hz:.1f} Hz, below {min_rate_hz:g} Hz; check the mocap system's "
                       "rate and the link to it")
        if self.age_s > max_age_s:
            out.append(f"the newest {what} sample is {self.age_s * 1e3:.0f} ms old, above {max_age_s * 1e3:.0f} ms; "
                       "is the stream still flowing?")
        if self.jitter_ms > max_jitter_ms:
            out.append(f"{what} intervals jitter by {self.jitter_ms:.1f} ms (p99), above {max_jitter_ms:g} ms; "
                       "check for a congested link or a busy host")
        return out


def stream_health(stamps_ns: npt.ArrayLike, now_ns: int, window_s: float = 2.0) -> StreamHealth:
    """:class:`StreamHealth` of the stamps within ``window_s`` before ``now_ns`` (any order).

    Raises:
        CalibrationError: fewer than two stamps in the window.
    """
    st = np.sort(np.asarray(stamps_ns, dtype=np.int64))
    st = st[st >= now_ns - round(window_s * 1e9)]
    if st.size < 2:
        raise CalibrationError(
            f"{st.size} samples in the last {window_s:g} s: the stream is not flowing; check the source", "latency"
        )
    dt = np.diff(st).astype(np.float64) / 1e9
    span = float(st[-1] - st[0]) / 1e9
    jitter = np.abs(dt - float(np.median(dt)))
    return StreamHealth(
        rate_hz=(st.size - 1) / span if span > 0 else float("inf"),
        age_s=float(now_ns - int(st[-1])) / 1e9,
        jitter_ms=float(np.percentile(jitter, 99)) * 1e3,
        samples=int(st.size),
    )
