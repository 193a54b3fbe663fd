"""Per-sample latency stages in the flight log and summary, and the runner's latency prediction,
on the simulated lab with a known mocap latency injected. The mocap runs at 30 Hz, so the same
flight shows that a slow stream above the default preflight bound (20 Hz) is flown on
(tests/integration/test_fly_faults.py refuses one below a raised bound)."""

from __future__ import annotations

import asyncio
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from flightkit.apps.sim_session import fly_plan_in_sim
from flightkit.config import load_config
from trajectories.flightlog import read_flight_log
from trajectories.plan import load_plan

REPO = Path(__file__).resolve().parents[2]


def quick_circle():
    plan = load_plan(REPO / "examples" / "circle.toml")
    return plan.with_changes(
        settings=dataclasses.replace(plan.settings, hold_before_s=0.5, hold_after_s=0.0, landed_timeout_s=60.0),
        pattern=dataclasses.replace(plan.pattern, laps=1, period_s=10.0),
    )


def test_a_flight_logs_and_prints_its_latency_stages_with_a_20_ms_mocap(tmp_path: Path) -> None:
    cfg = load_config(
        table={"sim": {"mocap_latency_ms": 20.0, "mocap_rate_hz": 30.0}, "mocap": {"predict_latency_ms": 20.0}}
    )
    log = tmp_path / "flight.csv"
    summary = asyncio.run(fly_plan_in_sim(quick_circle(), cfg, speed=5.0, log_path=log))
    table = summary.format_table()
    assert summary.outcome == "completed", table  # the 30 Hz stream passed the preflight's 20 Hz bound
    assert 0.0 < summary.latency_p50_ms <= summary.latency_p99_ms, table
    assert "mocap sample to setpoint: p50" in table
    stages = summary.stage_latency_ms
    # the simulated system stamps capture time; its poses reach the runner 20 ms later (in-process: no bus)
    assert stages["capture->bus"][0] == pytest.approx(20.0, abs=1.0), table
    assert stages["bus->runner"] == (0.0, 0.0), table
    assert 0.0 < stages["runner->setpoint"][0] <= stages["runner->setpoint"][1], table
    assert stages["capture->setpoint"][0] >= 20.0, table
    assert "latency per stage, p50 / p99 ms: capture->bus 20." in table
    data = read_flight_log(log)
    pattern = np.array([ph == "pattern" for ph in data["phase"]])
    assert np.median(data["capture_to_bus_s"][pattern]) == pytest.approx(0.020, abs=0.001)
    # a setpoint follows its pose; in the same simulated instant when the clock holds for a late
    # sleeper on a loaded host (flightkit.clock.SimClock), so zero is a valid sample, never negative
    runner_to_setpoint = data["runner_to_setpoint_s"][pattern]
    assert np.all(np.isfinite(runner_to_setpoint) & (runner_to_setpoint >= 0.0))
    assert np.median(runner_to_setpoint) > 0.0
    assert summary.to_dict()["stage_latency_ms"]["capture->bus"]["p50"] == pytest.approx(20.0, abs=1.0)
