"""What every pattern gives: a :class:`Reference` at time t, and the building blocks of patterns.

A pattern is a pure, closed-form function of time. It knows its duration and lap count, and
its yaw is *continuous* (unwrapped): a vehicle flying two laps of a circle looking inward sees
the reference yaw grow by 4 pi, never jump at +-pi. Wrapping happens only where a yaw is sent.

All positions and velocities are in the world frame (ENU, z up), metres and m/s; yaw is the
heading counter-clockwise from world x, radians.

Piecewise patterns (rectangle, lawnmower, waypoints, take-off, land, hold) are sequences of
:class:`Segment` values: a straight move with a trapezoidal speed profile (speed ramps within an
acceleration limit instead of jumping), or a turn in place with a smooth yaw profile.
"""

from __future__ import annotations

import bisect
import dataclasses
import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from flightkit.errors import PlanError
from flightkit.frames import Vec3Tuple

__all__ = [
    "Move",
    "Pattern",
    "PiecewisePattern",
    "Reference",
    "Segment",
    "Turn",
    "YawMode",
    "chain",
    "heading_rad",
    "trapezoid",
    "trapezoid_duration_s",
    "unwrap_next",
    "with_acceleration",
]



class YawMode(enum.Enum):
    """How a pattern points the vehicle.

    ``INWARD``/``OUTWARD``: at / away from the pattern's centre (perpendicular to the side for
    polygons); ``TRAVEL``: along the direction of travel (the tangent on a circle); ``FIXED``:
    a constant heading.
    """

    INWARD = "inward"
    OUTWARD = "outward"
    TRAVEL = "travel"
    FIXED = "fixed"

    @classmethod
    def _missing_(cls, value: object) -> YawMode | None:
        return cls.TRAVEL if value == "tangent" else None


@dataclass(frozen=True, slots=True)
class Reference:
    """Where the vehicle should be at one instant.

    Attributes:
        t_s: pattern time this reference is for (seconds since the pattern started).
        pos_m: position, world ENU, metres.
        vel_m_s: velocity, world ENU, m/s (the time derivative of ``pos_m``).
        yaw_rad: heading, continuous over laps (not wrapped).
        yaw_rate_rad_s: time derivative of ``yaw_rad``.
        lap: zero-based lap index.
        done: True once ``t_s`` is at or past the pattern's duration.
        accel_m_s2: time derivative of ``vel_m_s``; patterns leave it zero and
            :func:`with_acceleration` fills it in where it is needed.
    """

    t_s: float
    pos_m: Vec3Tuple
    vel_m_s: Vec3Tuple
    yaw_rad: float
    yaw_rate_rad_s: float = 0.0
    lap: int = 0
    done: bool = False
    accel_m_s2: Vec3Tuple = (0.0, 0.0, 0.0)


@runtime_checkable
class Pattern(Protocol):
    """A closed-form reference trajectory.

    Attributes:
        name: short kind name ("circle", "rectangle", ...).
        laps: number of laps (1 for patterns without laps).
        lap_duration_s: seconds per lap.
        duration_s: total seconds; ``reference(t)`` for ``t >= duration_s`` is the final pose at rest.
    """

    @property
    def name(self) -> str: ...

    @property
    def laps(self) -> int: ...

    @property
    def lap_duration_s(self) -> float: ...

    @property
    def duration_s(self) -> float: ...

    def reference(self, t_s: float) -> Reference:
        """The reference at pattern time ``t_s`` (clamped to [0, duration_s]); pure, returns immediately."""
        ...


def with_acceleration(pattern: Pattern, ref: Reference, step_s: float = 0.01) -> Reference:
    """``ref`` (from ``pattern.reference(ref.t_s)``) with its acceleration: the velocity's central
    difference over ``step_s`` either side (one-sided at the pattern's start)."""
    t0 = max(0.0, ref.t_s - step_s)
    t1 = ref.t_s + step_s
    v0 = pattern.reference(t0).vel_m_s
    v1 = pattern.reference(t1).vel_m_s
    span = t1 - t0
    acc = ((v1[0] - v0[0]) / span, (v1[1] - v0[1]) / span, (v1[2] - v0[2]) / span)
    return dataclasses.replace(ref, accel_m_s2=acc)


def heading_rad(p0: Sequence[float], p1: Sequence[float]) -> float:
    """Horizontal heading (ENU, counter-clockwise from x) of the direction p0 -> p1."""
    return math.atan2(p1[1] - p0[1], p1[0] - p0[0])


def trapezoid_duration_s(distance_m: float, speed_m_s: float, accel_m_s2: float) -> float:
    """Time to cover ``distance_m`` from rest to rest with a speed and acceleration limit."""
    if distance_m <= 0.0:
        return 0.0
    if math.isinf(accel_m_s2):
        return distance_m / speed_m_s
    d_ramp = speed_m_s * speed_m_s / accel_m_s2  # distance of both ramps at full speed
    if distance_m >= d_ramp:
        return distance_m / speed_m_s + speed_m_s / accel_m_s2
    return 2.0 * math.sqrt(distance_m / accel_m_s2)


def trapezoid(t_s: float, distance_m: float, speed_m_s: float, accel_m_s2: float) -> tuple[float, float]:
    """Distance and speed at time ``t_s`` of a rest-to-rest trapezoidal (or triangular) profile.

    Returns:
        (s_m, v_m_s), with s clamped to [0, distance_m] outside the profile.
    """
    if distance_m <= 0.0 or t_s <= 0.0:
        return 0.0, 0.0
    if math.isinf(accel_m_s2):
        total = distance_m / speed_m_s
        if t_s >= total:
            return distance_m, 0.0
        return speed_m_s * t_s, speed_m_s
    v_peak = min(speed_m_s, math.sqrt(distance_m * accel_m_s2))
    t_ramp = v_peak / accel_m_s2
    d_ramp = 0.5 * v_peak * t_ramp
    t_cruise = (distance_m - 2.0 * d_ramp) / v_peak
    total = 2.0 * t_ramp + t_cruise
    if t_s >= total:
        return distance_m, 0.0
    if t_s < t_ramp:
        return 0.5 * accel_m_s2 * t_s * t_s, accel_m_s2 * t_s
    if t_s < t_ramp + t_cruise:
        return d_ramp + v_peak * (t_s - t_ramp), v_peak
    tr = total - t_s
    return distance_m - 0.5 * accel_m_s2 * tr * tr, accel_m_s2 * tr


class Segment(Protocol):
    """One piece of a piecewise pattern, with its own local time tau in [0, duration_s]."""

    @property
    def duration_s(self) -> float: ...

    @property
    def start_yaw_rad(self) -> float: ...

    @property
    def end_yaw_rad(self) -> float: ...

    def at(self, tau_s: float) -> tuple[Vec3Tuple, Vec3Tuple, float, float]:
        """(pos, vel, yaw, yaw_rate) at local time ``tau_s``."""
        ...


@dataclass(frozen=True, slots=True)
class Move:
    """A straight move from rest to rest at a constant yaw, speed ramped within ``accel_m_s2``."""

    start_m: Vec3Tuple
    end_m: Vec3Tuple
    speed_m_s: float
    accel_m_s2: float
    yaw_rad: float

    @property
    def length_m(self) -> float:
        return math.dist(self.start_m, self.end_m)

    @property
    def duration_s(self) -> float:
        return trapezoid_duration_s(self.length_m, self.speed_m_s, self.accel_m_s2)

    @property
    def start_yaw_rad(self) -> float:
        return self.yaw_rad

    @property
    def end_yaw_rad(self) -> float:
        return self.yaw_rad

    def at(self, tau_s: float) -> tuple[Vec3Tuple, Vec3Tuple, float, float]:
        length = self.length_m
        if length <= 0.0:
            return self.start_m, (0.0, 0.0, 0.0), self.yaw_rad, 0.0
        s, v = trapezoid(tau_s, length, self.speed_m_s, self.accel_m_s2)
        a, b = self.start_m, self.end_m
        u = ((b[0] - a[0]) / length, (b[1] - a[1]) / length, (b[2] - a[2]) / length)
        pos = (a[0] + u[0] * s, a[1] + u[1] * s, a[2] + u[2] * s)
        return pos, (u[0] * v, u[1] * v, u[2] * v), self.yaw_rad, 0.0


@dataclass(frozen=True, slots=True)
class Turn:
    """Turn in place (or hold, when the yaws are equal) over ``duration``.

    The yaw follows a cosine profile, so the yaw rate starts and ends at zero and peaks at
    ``pi/2 * delta / duration`` in the middle.
    """

    pos_m: Vec3Tuple
    from_yaw_rad: float
    to_yaw_rad: float
    turn_duration_s: float

    @property
    def duration_s(self) -> float:
        return self.turn_duration_s

    @property
    def start_yaw_rad(self) -> float:
        return self.from_yaw_rad

    @property
    def end_yaw_rad(self) -> float:
        return self.to_yaw_rad

    def at(self, tau_s: float) -> tuple[Vec3Tuple, Vec3Tuple, float, float]:
        d = self.to_yaw_rad - self.from_yaw_rad
        T = self.turn_duration_s
        if T <= 0.0 or d == 0.0:
            return self.pos_m, (0.0, 0.0, 0.0), self.to_yaw_rad if tau_s > 0 else self.from_yaw_rad, 0.0
        x = min(max(tau_s / T, 0.0), 1.0)
        yaw = self.from_yaw_rad + d * 0.5 * (1.0 - math.cos(math.pi * x))
        rate = d * 0.5 * math.pi / T * math.sin(math.pi * x) if 0.0 < x < 1.0 else 0.0
        return self.pos_m, (0.0, 0.0, 0.0), yaw, rate


class PiecewisePattern:
    """A pattern made of segments forming one lap, repeated ``laps`` times.

    Consecutive segments must join (the end of one is the start of the next, in position and
    yaw); a multi-lap pattern must close (the lap ends where it started, with a yaw equal to the
    start yaw plus a whole number of turns). The yaw keeps accumulating over laps, so it stays
    continuous.

    Raises:
        PlanError: when the segments do not join, or a multi-lap pattern does not close.
    """

    def __init__(self, name: str, segments: Sequence[Segment], laps: int = 1) -> None:
        if laps < 1:
            raise PlanError(
                f"laps must be at least 1, got {laps}",
                "give laps >= 1",
                pattern=name,
                key="laps",
                value=laps,
            )
        segs = [s for s in segments if s.duration_s > 0.0]
        if not segs:
            raise PlanError(
                "the pattern has no motion (all segments are empty)",
                "give it a size, a speed or a duration",
                pattern=name,
                key="segments",
            )
        self._name = name
        self._laps = int(laps)
        self._segments = segs
        starts: list[float] = []
        t = 0.0
        for i, seg in enumerate(segs):
            starts.append(t)
            t += seg.duration_s
            if i + 1 < len(segs):
                _check_join(name, seg, segs[i + 1])
        self._starts = starts
        self._lap_s = t
        first_pos = segs[0].at(0.0)[0]
        last_pos, _, last_yaw, _ = segs[-1].at(segs[-1].duration_s)
        self._lap_yaw_delta = last_yaw - segs[0].start_yaw_rad
        if laps > 1:
            gap = math.dist(first_pos, last_pos)
            turns = self._lap_yaw_delta / (2.0 * math.pi)
            if gap > 1e-6 or abs(turns - round(turns)) > 1e-6:
                raise PlanError(
                    f"a lap ends {gap:.3f} m and {math.degrees(self._lap_yaw_delta):.1f} deg "
                    f"away from where it starts, so it cannot be repeated {laps} times",
                    "use laps = 1",
                    pattern=name,
                    key="laps",
                    value=laps,
                )

    @property
    def name(self) -> str:
        return self._name

    @property
    def laps(self) -> int:
        return self._laps

    @property
    def lap_duration_s(self) -> float:
        return self._lap_s

    @property
    def duration_s(self) -> float:
        return self._lap_s * self._laps

    @property
    def segments(self) -> tuple[Segment, ...]:
        return tuple(self._segments)

    def reference(self, t_s: float) -> Reference:
        done = t_s >= self.duration_s
        t = min(max(t_s, 0.0), self.duration_s)
        lap = min(int(t // self._lap_s), self._laps - 1)
        tau = t - lap * self._lap_s
        i = max(0, bisect.bisect_right(self._starts, tau) - 1)
        seg = self._segments[i]
        pos, vel, yaw, rate = seg.at(tau - self._starts[i])
        if done:
            vel, rate = (0.0, 0.0, 0.0), 0.0
        return Reference(t, pos, vel, yaw + lap * self._lap_yaw_delta, rate, lap, done)


def _check_join(name: str, a: Segment, b: Segment) -> None:
    pa, _, ya, _ = a.at(a.duration_s)
    pb, _, yb, _ = b.at(0.0)
    if math.dist(pa, pb) > 1e-6 or abs(ya - yb) > 1e-6:
        raise PlanError(
            f"segments do not join at {pa} / {pb} (internal error)",
            "report this as a bug in the pattern",
            pattern=name,
            key="segments",
        )


def chain(
    points: Sequence[Vec3Tuple],
    yaws_rad: Sequence[float],
    speed_m_s: float,
    accel_m_s2: float,
    turn_s: float,
) -> list[Segment]:
    """Moves through ``points`` with yaw ``yaws_rad[i]`` on leg i, turning in place between legs.

    A turn between two legs takes ``turn_s`` (or no time when the yaw does not change).
    ``yaws_rad`` has one entry per leg and must already be continuous (unwrapped); a final
    entry beyond the legs, if given, adds a last turn at the final point.
    """
    legs = len(points) - 1
    segs: list[Segment] = []
    for i in range(legs):
        if i > 0 and yaws_rad[i] != yaws_rad[i - 1]:
            segs.append(Turn(points[i], yaws_rad[i - 1], yaws_rad[i], turn_s))
        segs.append(Move(points[i], points[i + 1], speed_m_s, accel_m_s2, yaws_rad[i]))
    if len(yaws_rad) > legs and legs > 0 and yaws_rad[legs] != yaws_rad[legs - 1]:
        segs.append(Turn(points[legs], yaws_rad[legs - 1], yaws_rad[legs], turn_s))
    return segs


def unwrap_next(prev_rad: float, angle_rad: float) -> float:
    """``angle_rad`` shifted by whole turns to be within pi of ``prev_rad``."""
    return prev_rad + math.remainder(angle_rad - prev_rad, 2.0 * math.pi)
