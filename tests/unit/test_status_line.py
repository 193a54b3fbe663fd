"""The live status line of a flight (trajectories.status.Status)."""

import math

from trajectories.status import Status


def test_the_rate_and_error_read_dashes_until_known() -> None:
    early = Status(t_s=0.1, phase="takeoff", rate_hz=math.nan).line()
    assert "--- Hz" in early and "nan" not in early
    running = Status(t_s=12.0, phase="pattern", lap=1, laps=2, pos_m=(1.0, 0.0, 1.5), err_m=0.01, rate_hz=117.4).line()
    assert "117 Hz" in running and "lap 1/2" in running and "err  0.010 m" in running
