"""The clock offset between two hosts from request/response exchanges (NTP's arithmetic).

One exchange: the local host sends at ``t0`` (its clock), the remote receives at ``t1`` and answers
at ``t2`` (its clock), the answer arrives at ``t3`` (local clock). Then::

    offset = ((t1 - t0) + (t2 - t3)) / 2      remote clock minus local clock
    rtt    = (t3 - t0) - (t2 - t1)            time on the wire, both ways

The offset is exact when both ways take equally long; its error is at most ``rtt / 2``. Queues
make some exchanges slow and lopsided, so :func:`estimate_clock_offset` keeps, in each time
window, the exchanges with the smallest round trip (NTP's clock filter), then fits a line
through them: the offset at the reference time and the drift of the remote clock in ppm.
:class:`ClockSync` does the same continuously, for a bus that exchanges stamps all the time.

Pure numpy.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from flightkit.errors import CalibrationError

__all__ = [
    "CLOCK_OFFSETS_RECORD",
    "ClockOffsetEstimate",
    "ClockSync",
    "Exchange",
    "estimate_clock_offset",
    "offsets_from_metadata",
    "offsets_to_metadata",
]

CLOCK_OFFSETS_RECORD = "clock_offsets"
"""Recording metadata record: ``local_host`` (the recorder's host, whose clock stamps ``log_time``)
and one JSON :class:`ClockOffsetEstimate` per other host on the bus."""

_NS = 1_000_000_000


@dataclass(frozen=True, slots=True)
class Exchange:
    """One request/response: ``t0``/``t3`` on the local clock, ``t1``/``t2`` on the remote's, ns."""

    t0_ns: int
    t1_ns: int
    t2_ns: int
    t3_ns: int

    @property
    def offset_ns(self) -> float:
        """Remote minus local clock, ns (exact for a symmetric path)."""
        return ((self.t1_ns - self.t0_ns) + (self.t2_ns - self.t3_ns)) / 2.0

    @property
    def rtt_ns(self) -> int:
        """Round trip on the wire (the remote's processing time taken out), ns."""
        return (self.t3_ns - self.t0_ns) - (self.t2_ns - self.t1_ns)


@dataclass(frozen=True, slots=True)
class ClockOffsetEstimate:
    """Remote clock against local clock: ``remote - local = offset + drift * (local - ref)``.

    Attributes:
        offset_ns: remote minus local clock at ``ref_ns``, ns.
        drift_ppm: how much faster the remote clock runs, ppm (0 when not estimated).
        ref_ns: local time the offset refers to.
        rtt_min_ns: the smallest round trip seen, ns.
        uncertainty_ns: a bound on the offset's error: half the round trip of the exchanges kept
            (the median), plus the scatter of the fit.
        exchanges: exchanges given; kept: exchanges used after the min-RTT filter.
    """

    offset_ns: float
    drift_ppm: float
    ref_ns: int
    rtt_min_ns: int
    uncertainty_ns: float
    exchanges: int
    kept: int

    def remote_to_local_ns(self, remote_ns: int) -> int:
        """A remote stamp on the local clock."""
        k = self.drift_ppm * 1e-6
        return self.ref_ns + round((remote_ns - self.ref_ns - self.offset_ns) / (1.0 + k))

    def offset_at_ns(self, local_ns: int) -> float:
        """Remote minus local clock at local time ``local_ns``, ns."""
        return self.offset_ns + self.drift_ppm * 1e-6 * (local_ns - self.ref_ns)


def estimate_clock_offset(
    exchanges: list[Exchange] | tuple[Exchange, ...],
    *,
    window_s: float = 10.0,
    keep_fraction: float = 0.2,
    fit_drift: bool = True,
) -> ClockOffsetEstimate:
    """Offset (and drift) of a remote clock from exchanges (see the module docstring).

    Args:
        exchanges: at least one; in any order.
        window_s: the exchanges are filtered per window of this length (local time).
        keep_fraction: the share of each window's exchanges kept, smallest round trip first
            (at least one per window).
        fit_drift: fit a drift when the kept exchanges span at least two windows.

    Raises:
        CalibrationError: no exchange, or one whose stamps run backwards (rtt < 0).
    """
    if not exchanges:
        raise CalibrationError("no clock exchange to estimate an offset from; exchange stamps first", "clock offset")
    t0 = np.array([e.t0_ns for e in exchanges], dtype=np.int64)
    off = np.array([e.offset_ns for e in exchanges], dtype=np.float64)
    rtt = np.array([e.rtt_ns for e in exchanges], dtype=np.int64)
    if np.any(rtt < 0):
        bad = exchanges[int(np.argmin(rtt))]
        raise CalibrationError(
            f"an exchange has a negative round trip ({bad.rtt_ns} ns: {bad}); the stamps are swapped or taken "
            "from different clocks",
            "clock offset",
        )
    origin = int(t0.min())
    t_s = (t0 - origin).astype(np.float64) / _NS
    n_win = max(1, math.ceil((t_s.max() + 1e-9) / window_s))
    keep: list[int] = []
    for k in range(n_win):
        idx = np.flatnonzero((t_s >= k * window_s) & (t_s < (k + 1) * window_s + (1e-9 if k == n_win - 1 else 0)))
        if idx.size == 0:
            continue
        m = max(1, int(round(keep_fraction * idx.size)))
        keep.extend(idx[np.argsort(rtt[idx], kind="stable")[:m]].tolist())
    sel = np.array(sorted(keep))
    ts, os_ = t_s[sel], off[sel]
    ref_s = float(ts.mean())
    span = float(ts.max() - ts.min())
    if fit_drift and sel.size >= 3 and span >= window_s:
        X = np.stack([np.ones_like(ts), ts - ref_s], axis=1)  # noqa: N806
        coef, *_ = np.linalg.lstsq(X, os_, rcond=None)
        offset, slope = float(coef[0]), float(coef[1]) / _NS
        scatter = float(np.std(os_ - X @ coef))
    else:
        offset, slope = float(np.median(os_)), 0.0
        scatter = float(np.std(os_))
    return ClockOffsetEstimate(
        offset_ns=offset,
        drift_ppm=slope * 1e6,
        ref_ns=origin + round(ref_s * _NS),
        rtt_min_ns=int(rtt.min()),
        uncertainty_ns=float(np.median(rtt[sel])) / 2.0 + scatter,
        exchanges=len(exchanges),
        kept=int(sel.size),
    )


class ClockSync:
    """A running estimate from a stream of exchanges (keeps the last ``horizon_s`` of local time).

    Args:
        horizon_s: how much history the estimate uses.
        window_s, keep_fraction: see :func:`estimate_clock_offset`.
    """

    def __init__(self, horizon_s: float = 60.0, window_s: float = 10.0, keep_fraction: float = 0.2) -> None:
        self.horizon_s = horizon_s
        self.window_s = window_s
        self.keep_fraction = keep_fraction
        self._ex: deque[Exchange] = deque()

    def add(self, exchange: Exchange) -> None:
        """Add one exchange (old ones beyond the horizon are forgotten)."""
        self._ex.append(exchange)
        while self._ex and exchange.t0_ns - self._ex[0].t0_ns > self.horizon_s * _NS:
            self._ex.popleft()

    def estimate(self) -> ClockOffsetEstimate:
        """The estimate over the history.

        Raises:
            CalibrationError: no exchange yet.
        """
        return estimate_clock_offset(tuple(self._ex), window_s=self.window_s, keep_fraction=self.keep_fraction)

    def offsets(self) -> npt.NDArray[np.float64]:
        """Every offset in the history, ns (for plots)."""
        return np.array([e.offset_ns for e in self._ex], dtype=np.float64)


def offsets_to_metadata(local_host: str, estimates: Mapping[str, ClockOffsetEstimate]) -> dict[str, str]:
    """The :data:`CLOCK_OFFSETS_RECORD` record: ``local_host`` and host -> JSON estimate."""
    out = {"local_host": local_host}
    out.update({host: json.dumps(dataclasses.asdict(est), sort_keys=True) for host, est in estimates.items()})
    return out


def offsets_from_metadata(record: Mapping[str, str]) -> dict[str, ClockOffsetEstimate]:
    """The inverse of :func:`offsets_to_metadata` (host -> estimate; ``local_host`` left out).

    Raises:
        CalibrationError: a malformed entry.
    """
    out: dict[str, ClockOffsetEstimate] = {}
    for host, text in record.items():
        if host == "local_host":
            continue
        try:
            out[host] = ClockOffsetEstimate(**json.loads(text))
        except (TypeError, ValueError) as exc:
            raise CalibrationError(f"the clock offset of host {host!r} is malformed ({exc})", "clock offset") from exc
    return out
