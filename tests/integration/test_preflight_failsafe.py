"""The preflight reads the autopilot's own failsafe parameters and refuses to arm a vehicle that
would hover armed until its battery runs out if flightkit stopped (override: [safety]
allow_hover_on_companion_loss). Real UDP MAVLink to the simulated autopilots, which serve the
firmware defaults (``[sim.autopilot_params]`` sets them; the simulated lab's own set-up makes
ArduCopter land on GCS loss, as docs/hardware.md recommends)."""

from __future__ import annotations

import asyncio
import dataclasses
import json
from pathlib import Path

import pytest

from flightkit.apps.sim_session import SimSession, sim_session
from flightkit.cli.main import main
from flightkit.clock import ONE_PROCESS_WALL_STEP_S, SimClock
from flightkit.config import LabConfig, LinkBackend
from flightkit.errors import SafetyAbort
from flightkit.sim.lab import SimLab
from trajectories.runner import FlightRunner
from trajectories.supervisor import SafetyConfig

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(60)]

SPEED = 5.0
APM_FACTORY = {"FS_GCS_ENABLE": 0.0}  # ArduCopter 4.7 as shipped (the lab set-up lands instead)
PX4_HOVER = {"COM_OBL_RC_ACT": 5.0, "COM_RCL_EXCEPT": 2.0}  # Hold on offboard loss, RC loss ignored in Hold
# the mocap-stream bounds are another check (test_fly_faults); off here, so a loaded machine's
# stalls cannot refuse for a reason other than the one under test
QUIET_MOCAP_CHECKS = SafetyConfig(
    preflight_mocap_min_rate_hz=0.0, preflight_mocap_max_age_s=0.0, preflight_mocap_max_jitter_ms=0.0
)


def lab(params: dict[str, float], backend: str = "pymavlink") -> LabConfig:
    cfg = LabConfig()
    return dataclasses.replace(
        cfg,
        sim=dataclasses.replace(cfg.sim, autopilot_params=params),
        link=dataclasses.replace(cfg.link, backend=LinkBackend(backend)),
    )


async def preflight_and_arm(s: SimSession, allow: bool = False) -> str:
    """Preflight and arm with the script (SafetyAbort when refused); returns the one-line verdict."""
    runner = FlightRunner(
        s.link,
        s.mocap,
        body=s.config.mocap.body,
        clock=s.clock,
        safety=dataclasses.replace(QUIET_MOCAP_CHECKS, allow_hover_on_companion_loss=allow),
    )
    try:
        try:
            await runner.preflight()
        finally:
            verdict = runner.summary.companion_loss
        await runner.start(arm=True)
        assert s.lab.autopilot.armed
        await s.link.disarm()
    finally:
        await runner.close()
    return verdict


@pytest.mark.parametrize(
    ("autopilot", "params", "refusal"),
    [
        ("ardupilot", APM_FACTORY, r"GCS failsafe is off \(FS_GCS_ENABLE = 0\); set FS_GCS_ENABLE = 5"),
        ("ardupilot", {"MAV_GCS_SYSID": 254.0}, r"watches the heartbeat of system MAV_GCS_SYSID = 254"),
        ("px4", PX4_HOVER, r"Hold mode \(COM_OBL_RC_ACT = 5\) and RC loss is ignored in Hold"),
    ],
)
def test_a_vehicle_that_would_hover_on_companion_loss_is_refused_unless_allowed(
    autopilot: str, params: dict[str, float], refusal: str
) -> None:
    async def go() -> None:
        async with sim_session(lab(params), autopilot=autopilot, speed=SPEED) as s:
            with pytest.raises(SafetyAbort, match=refusal) as info:
                await preflight_and_arm(s)
            assert info.value.reason == "preflight"
            assert "allow_hover_on_companion_loss = true" in str(info.value)
            assert not s.lab.autopilot.armed
            verdict = await preflight_and_arm(s, allow=True)
            assert "hovers armed" in verdict and "until the battery runs out" in verdict

    asyncio.run(go())


@pytest.mark.parametrize(
    ("autopilot", "params", "says"),
    [
        (
            "ardupilot",
            {},
            "if flightkit stops: ArduCopter keeps the last velocity 3 s (GUID_TIMEOUT), brakes, and 5 s "
            "(FS_GCS_TIMEOUT) after flightkit's last heartbeat its GCS failsafe lands (FS_GCS_ENABLE = 5)",
        ),
        (
            "px4",
            {},
            "if flightkit stops: PX4 switches after 1 s (COM_OF_LOSS_T) to Position mode (COM_OBL_RC_ACT = 0): "
            "an RC pilot flies it; without RC the RC-loss failsafe switches to Return (NAV_RCL_ACT = 2)",
        ),
        ("px4", {"COM_OBL_RC_ACT": 4.0}, "to Land mode (COM_OBL_RC_ACT = 4) and lands"),
    ],
)
def test_a_vehicle_that_lands_on_companion_loss_arms_and_says_so(
    autopilot: str, params: dict[str, float], says: str
) -> None:
    async def go() -> None:
        async with sim_session(lab(params), autopilot=autopilot, speed=SPEED) as s:
            assert says in await preflight_and_arm(s)

    asyncio.run(go())


@pytest.mark.parametrize(("autopilot", "params"), [("ardupilot", APM_FACTORY), ("px4", PX4_HOVER)])
def test_mavsdk_reads_the_failsafe_parameters_too(autopilot: str, params: dict[str, float]) -> None:
    async def go() -> None:
        async with sim_session(lab(params, "mavsdk"), autopilot=autopilot, speed=1.0) as s:
            with pytest.raises(SafetyAbort, match="allow_hover_on_companion_loss") as info:
                await preflight_and_arm(s)
            assert not s.lab.autopilot.armed
            # every parameter was read (integers decoded, PX4's bytewise ones too)
            assert "could not be read" not in str(info.value)

    asyncio.run(go())


def test_flightkit_fly_refuses_factory_arducopter_and_the_flag_overrides(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    lab_toml = tmp_path / "lab.toml"
    lab_toml.write_text('[vehicle]\nautopilot = "ardupilot"\n\n[sim.autopilot_params]\nFS_GCS_ENABLE = 0\n')
    plan = tmp_path / "hop.toml"
    plan.write_text(
        '[plan]\nname = "hop"\ntakeoff_height_m = 0.5\nhold_before_s = 0.0\nhold_after_s = 0.0\n\n'
        '[pattern]\nkind = "hold"\nposition_m = [0.0, 0.0, 0.5]\nduration_s = 0.5\n\n'
        "[safety]\npreflight_mocap_min_rate_hz = 0.0\npreflight_mocap_max_age_s = 0.0\n"
        "preflight_mocap_max_jitter_ms = 0.0\n"
    )
    argv = ["fly", str(plan), "--sim", "--config", str(lab_toml), "--speed", "5", "--log", "", "--json"]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "preflight failed: ArduCopter's GCS failsafe is off (FS_GCS_ENABLE = 0)" in err
    assert "--allow-hover-on-companion-loss" in err
    assert main([*argv, "--allow-hover-on-companion-loss"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["outcome"] == "completed"
    assert "hovers armed in GUIDED until the battery runs out (FS_GCS_ENABLE = 0)" in summary["companion_loss"]


def test_vehicle_status_says_what_the_vehicle_does_if_flightkit_stops(capsys: pytest.CaptureFixture[str]) -> None:
    clock = SimClock(1.0, max_wall_step_s=ONE_PROCESS_WALL_STEP_S)
    url = "udpin:127.0.0.1:0"
    with SimLab(lab(APM_FACTORY), autopilot="ardupilot", url=url, clock=clock, ready_after_s=0.0) as sim:
        assert main(["vehicle", "status", "--connect", sim.client_url, "--listen", "0.5"]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("failsafe "))
    assert "if flightkit stops: ArduCopter keeps the last velocity 3 s (GUID_TIMEOUT)" in line
    assert line.endswith("(FS_GCS_ENABLE = 0) (fly refuses to arm)")
