"""The live status line of a flight: what the control loop (:mod:`trajectories.control_loop`)
tells ``on_status`` a few times a second.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from flightkit.frames import Vec3Tuple

__all__ = ["Status"]


@dataclass(frozen=True, slots=True)
class Status:
    """A snapshot for the live status line (given to ``on_status`` a few times a second).

    Attributes:
        t_s: flight time. phase: current phase. lap / laps: 1-based lap of the pattern.
        pos_m: measured position (world ENU). err_m: tracking error. rate_hz: control rate.
        action: supervisor action name. message: extra text (e.g. a countdown).
    """

    t_s: float
    phase: str
    lap: int = 0
    laps: int = 0
    pos_m: Vec3Tuple | None = None
    err_m: float = math.nan
    rate_hz: float = math.nan
    action: str = "CONTINUE"
    message: str = ""

    def line(self) -> str:
        p = (
            "(  ---,   ---,   ---)"
            if self.pos_m is None
            else "({:5.2f}, {:5.2f}, {:5.2f})".format(*self.pos_m)
        )
        lap = f"lap {self.lap}/{self.laps}" if self.laps else "       "
        extra = f"  {self.message}" if self.message else ""
        act = "" if self.action == "CONTINUE" else f"  [{self.action}]"
        return (
            f"t={self.t_s:7.2f}s  {self.phase:<10} {lap}  pos {p}  "
            f"err {'   ---' if math.isnan(self.err_m) else f'{self.err_m:6.3f}'} m  "
            f"{'  ---' if math.isnan(self.rate_hz) else f'{self.rate_hz:5.0f}'} Hz{act}{extra}"
        )
