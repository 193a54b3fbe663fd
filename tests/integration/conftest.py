"""Fixtures of the simulated autopilot's wire tests (tests/integration/test_sim_autopilot*.py): a lab
at accelerated time with the streams a pure-Python client can drain, and raw GCS clients closed
after the test."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import replace
from typing import Any

import pytest

from flightkit.clock import ONE_PROCESS_WALL_STEP_S, SimClock
from flightkit.sim.autopilot import AutopilotOptions
from flightkit.sim.lab import SimLab
from tests.integration.sim_gcs import QUIET_STREAMS, SPEED, Client


@pytest.fixture
def make_lab() -> Iterator[Callable[..., SimLab]]:
    labs: list[SimLab] = []

    def make(autopilot: str = "px4", speed: float = SPEED, **kw: Any) -> SimLab:
        kw.setdefault("ready_after_s", 0.0)
        # a pure-Python client in the same process cannot drain every default stream at 10x speed
        opts = kw.pop("options", AutopilotOptions())
        kw["options"] = replace(opts, stream_rates_hz={**QUIET_STREAMS, **opts.stream_rates_hz})
        kw.setdefault("url", "udpin:127.0.0.1:0")
        # the test's client shares the lab's process and clock: stall-limited (docs/sim.md "Time")
        lab = SimLab(autopilot=autopilot, clock=SimClock(speed, max_wall_step_s=ONE_PROCESS_WALL_STEP_S), **kw)
        lab.start()
        labs.append(lab)
        return lab

    yield make
    for lab in labs:
        lab.stop()


@pytest.fixture
def clients() -> Iterator[list[Client]]:
    made: list[Client] = []
    yield made
    for c in made:
        c.close()
