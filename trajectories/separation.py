"""Separation between the vehicles of a fleet: measured, predicted, and of a plan's references.

Pure functions over positions in the world frame (ENU, metres). The fleet supervisor
(:class:`trajectories.fleet.Fleet`) calls :func:`closest_approach` on every check, and
:func:`plan_separation` before take-off to refuse a plan whose references come too close.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping
from dataclasses import dataclass

from flightkit.errors import ConfigError
from flightkit.frames import Vec3Tuple
from flightkit.settings import setting
from trajectories.base import Pattern

__all__ = ["Approach", "FleetSafety", "closest_approach", "plan_separation"]


@dataclass(frozen=True, slots=True)
class FleetSafety:
    """The ``[fleet]`` table of a fleet plan: the fleet supervisor's limits and policy."""

    min_separation_m: float = setting(0.6, min=0.05, max=20.0, help="least distance between any two vehicles")
    lookahead_s: float = setting(1.0, min=0.0, max=10.0, help="how far ahead separation is predicted")
    check_rate_hz: float = setting(20.0, min=1.0, max=200.0, help="how often separation is checked")
    on_vehicle_fault: str = setting("land", help="what the others do when one vehicle faults: land or continue")

    @staticmethod
    def _check(obj: FleetSafety, path: str, key: str) -> None:
        if obj.on_vehicle_fault not in ("land", "continue"):
            raise ConfigError(
                path,
                f"{key}.on_vehicle_fault" if key else "on_vehicle_fault",
                f"unknown policy {obj.on_vehicle_fault!r}",
                "use 'land' (the others hold, then land) or 'continue'",
                obj.on_vehicle_fault,
            )


@dataclass(frozen=True, slots=True)
class Approach:
    """The closest pair of vehicles: who, how far apart now and at the look-ahead."""

    pair: tuple[str, str]
    distance_m: float
    predicted_m: float

    @property
    def closest_m(self) -> float:
        return min(self.distance_m, self.predicted_m)


def closest_approach(
    positions_m: Mapping[str, Vec3Tuple], velocities_m_s: Mapping[str, Vec3Tuple], lookahead_s: float
) -> Approach | None:
    """The pair of vehicles closest now or ``lookahead_s`` ahead (constant velocity; the
    minimum over the look-ahead, not only its end). None with fewer than two vehicles."""
    best: Approach | None = None
    for a, b in itertools.combinations(sorted(positions_m), 2):
        pa, pb = positions_m[a], positions_m[b]
        va = velocities_m_s.get(a, (0.0, 0.0, 0.0))
        vb = velocities_m_s.get(b, (0.0, 0.0, 0.0))
        d = [pb[i] - pa[i] for i in range(3)]
        v = [vb[i] - va[i] for i in range(3)]
        now = math.sqrt(sum(x * x for x in d))
        vv = sum(x * x for x in v)
        # time of the closest approach within [0, lookahead_s]
        t = 0.0 if vv == 0.0 else min(max(-sum(d[i] * v[i] for i in range(3)) / vv, 0.0), lookahead_s)
        ahead = math.sqrt(sum((d[i] + v[i] * t) ** 2 for i in range(3)))
        cand = Approach((a, b), now, ahead)
        if best is None or cand.closest_m < best.closest_m:
            best = cand
    return best


def plan_separation(patterns: Mapping[str, Pattern], step_s: float = 0.05) -> tuple[float, float, tuple[str, str]]:
    """The least distance between any two vehicles' references when all patterns start together:
    (distance m, pattern time s, the pair). Patterns that end earlier stay at their end."""
    names = sorted(patterns)
    if len(names) < 2:
        return math.inf, 0.0, ("", "")
    duration_s = max(p.duration_s for p in patterns.values())
    n = max(2, int(duration_s / step_s) + 1)
    best = (math.inf, 0.0, ("", ""))
    for i in range(n + 1):
        t = duration_s * i / n
        pos = {k: patterns[k].reference(min(t, patterns[k].duration_s)).pos_m for k in names}
        for a, b in itertools.combinations(names, 2):
            d = math.dist(pos[a], pos[b])
            if d < best[0]:
                best = (d, t, (a, b))
    return best
