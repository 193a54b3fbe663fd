"""The safety supervisor: every fault, its action, severity order and preflight checks."""

from __future__ import annotations

import itertools
import math

import pytest

from flightkit.errors import ConfigError
from flightkit.link.base import BatteryState, FlightMode, Telemetry
from flightkit.settings import load_section
from trajectories.supervisor import (
    Action,
    FaultKind,
    Geofence,
    SafetyConfig,
    SupervisorInput,
    preflight_problems,
    supervise,
)

CFG = SafetyConfig(
    geofence=Geofence((-2.0, -2.0, -0.5), (2.0, 2.0, 2.5)), battery_min_pct=20.0, battery_min_v=13.0
)
GOOD_TEL = Telemetry(
    armed=True, mode=FlightMode.OFFBOARD, heartbeat_age_s=0.05, battery=BatteryState(15.5, 80.0)
)


def inp(**kw: object) -> SupervisorInput:
    base: dict[str, object] = dict(
        now_s=12.5,
        mocap_age_s=0.01,
        telemetry=GOOD_TEL,
        control_mode=FlightMode.OFFBOARD,
        pos_m=(0.0, 0.0, 1.0),
        ref_pos_m=(0.0, 0.0, 1.0),
        speed_m_s=0.2,
    )
    base.update(kw)
    return SupervisorInput(**base)  # type: ignore[arg-type]


def tel(**kw: object) -> Telemetry:
    d = dict(armed=True, mode=FlightMode.OFFBOARD, heartbeat_age_s=0.05, battery=BatteryState(15.5, 80.0))
    d.update(kw)
    return Telemetry(**d)  # type: ignore[arg-type]


def test_all_well_continues() -> None:
    d = supervise(CFG, inp())
    assert d.ok and d.action is Action.CONTINUE and d.faults == ()


@pytest.mark.parametrize(
    ("case", "kind", "action"),
    [
        (dict(mocap_age_s=0.25), FaultKind.MOCAP_STALE, Action.HOLD),
        (dict(mocap_age_s=math.inf), FaultKind.MOCAP_LOST, Action.LAND_AUTOPILOT),
        (dict(mocap_age_s=1.01), FaultKind.MOCAP_LOST, Action.LAND_AUTOPILOT),
        (dict(telemetry=tel(heartbeat_age_s=2.2)), FaultKind.HEARTBEAT_LOST, Action.STOP),
        (dict(telemetry=tel(mode=FlightMode.POSCTL)), FaultKind.PILOT_TAKEOVER, Action.RELEASE),
        (dict(telemetry=tel(armed=False)), FaultKind.DISARMED, Action.RELEASE),
        (dict(pos_m=(2.1, 0.0, 1.0)), FaultKind.GEOFENCE_POSITION, Action.ABORT),
        (dict(pos_m=(0.0, 0.0, 2.6)), FaultKind.GEOFENCE_POSITION, Action.ABORT),
        (dict(ref_pos_m=(0.0, -2.01, 1.0)), FaultKind.GEOFENCE_REFERENCE, Action.ABORT),
        (dict(speed_m_s=2.5), FaultKind.OVERSPEED, Action.ABORT),
        (dict(telemetry=tel(battery=BatteryState(15.0, 19.0))), FaultKind.BATTERY_LOW, Action.LAND),
        (dict(telemetry=tel(battery=BatteryState(12.9, math.nan))), FaultKind.BATTERY_LOW, Action.LAND),
        (dict(interrupted=True), FaultKind.INTERRUPTED, Action.LAND),
    ],
)
def test_each_fault_and_its_action(case: dict[str, object], kind: FaultKind, action: Action) -> None:
    d = supervise(CFG, inp(**case))
    assert d.action is action
    assert [f.kind for f in d.faults] == [kind]
    f = d.faults[0]
    assert f.time_s == 12.5 and f.action is action
    assert f.message and "\n" not in f.message
    assert f.to_dict()["kind"] == kind.value


def test_thresholds_are_strict_boundaries() -> None:
    assert supervise(CFG, inp(mocap_age_s=0.2)).ok
    assert supervise(CFG, inp(mocap_age_s=1.0)).action is Action.HOLD
    assert supervise(CFG, inp(telemetry=tel(heartbeat_age_s=2.0))).ok  # 1 Hz heartbeat, 1 s overdue
    assert supervise(CFG, inp(pos_m=(2.0, -2.0, 2.5))).ok  # on the fence is inside
    assert supervise(CFG, inp(telemetry=tel(battery=BatteryState(math.nan, math.nan)))).ok  # unknown battery


def test_before_control_no_takeover_or_disarm_checks() -> None:
    d = supervise(CFG, inp(control_mode=None, telemetry=tel(armed=False, mode=FlightMode.POSCTL)))
    assert d.ok


def test_heartbeat_loss_masks_stale_mode() -> None:
    d = supervise(CFG, inp(telemetry=tel(heartbeat_age_s=3.0, mode=FlightMode.POSCTL, armed=False)))
    assert [f.kind for f in d.faults] == [FaultKind.HEARTBEAT_LOST]


def test_disabled_checks() -> None:
    cfg = SafetyConfig(geofence=Geofence(enabled=False), battery_min_pct=0.0, battery_min_v=0.0)
    d = supervise(
        cfg,
        inp(
            pos_m=(100.0, 0.0, 1.0),
            ref_pos_m=(0.0, 100.0, 1.0),
            telemetry=tel(battery=BatteryState(1.0, 1.0)),
        ),
    )
    assert d.ok


# Severity: every combination of faults resolves to the most severe action, and reports all of them.
SINGLE = {
    FaultKind.MOCAP_STALE: dict(mocap_age_s=0.5),
    FaultKind.MOCAP_LOST: dict(mocap_age_s=5.0),
    FaultKind.HEARTBEAT_LOST: dict(hb=True),
    FaultKind.PILOT_TAKEOVER: dict(mode=FlightMode.POSCTL),
    FaultKind.GEOFENCE_POSITION: dict(pos_m=(5.0, 0.0, 1.0)),
    FaultKind.GEOFENCE_REFERENCE: dict(ref_pos_m=(5.0, 0.0, 1.0)),
    FaultKind.OVERSPEED: dict(speed_m_s=9.0),
    FaultKind.BATTERY_LOW: dict(batt=True),
    FaultKind.INTERRUPTED: dict(interrupted=True),
}
RANK = [
    FaultKind.HEARTBEAT_LOST,
    FaultKind.PILOT_TAKEOVER,
    FaultKind.MOCAP_LOST,
    FaultKind.BATTERY_LOW,
    FaultKind.INTERRUPTED,
    FaultKind.GEOFENCE_POSITION,
    FaultKind.GEOFENCE_REFERENCE,
    FaultKind.OVERSPEED,
    FaultKind.MOCAP_STALE,
]


def _combo_input(kinds: tuple[FaultKind, ...]) -> SupervisorInput:
    kw: dict[str, object] = {}
    t: dict[str, object] = {}
    for k in kinds:
        for key, val in SINGLE[k].items():
            if key == "hb":
                t["heartbeat_age_s"] = 3.0
            elif key == "mode":
                t["mode"] = val
            elif key == "batt":
                t["battery"] = BatteryState(15.0, 5.0)
            else:
                kw[key] = val
    return inp(telemetry=tel(**t), **kw)


COMBOS = [
    c
    for n in (2, 3)
    for c in itertools.combinations(SINGLE, n)
    if not {FaultKind.MOCAP_STALE, FaultKind.MOCAP_LOST} <= set(c)  # one mocap age cannot be both
]


@pytest.mark.parametrize("kinds", COMBOS)
def test_combinations_pick_most_severe(kinds: tuple[FaultKind, ...]) -> None:
    d = supervise(CFG, _combo_input(kinds))
    expected = set(kinds)
    if FaultKind.HEARTBEAT_LOST in expected:
        expected.discard(FaultKind.PILOT_TAKEOVER)  # the mode is stale without heartbeats
    assert {f.kind for f in d.faults} == expected
    assert d.action == max(f.action for f in d.faults)
    top = min(expected, key=RANK.index)
    assert d.action is next(f.action for f in d.faults if f.kind is top)


def test_preflight_names_visible_bodies() -> None:
    probs = preflight_problems(CFG, "uav1", ("cf2", "wand"), False, GOOD_TEL, None)
    assert len(probs) == 1 and "'uav1'" in probs[0] and "cf2, wand" in probs[0]
    assert "none" in preflight_problems(CFG, "uav1", (), False, GOOD_TEL, None)[0]
    assert "not tracked" in preflight_problems(CFG, "uav1", ("uav1",), False, GOOD_TEL, None)[0]
    assert preflight_problems(CFG, "uav1", ("uav1",), True, GOOD_TEL, (0.0, 0.0, 0.0)) == []
    bad = preflight_problems(
        CFG,
        "uav1",
        ("uav1",),
        True,
        tel(heartbeat_age_s=9.0, battery=BatteryState(12.0, 10.0)),
        (3.0, 0.0, 0.0),
    )
    assert len(bad) == 4  # heartbeat, battery %, battery V, geofence


def test_safety_config_validation() -> None:
    cfg = load_section(
        SafetyConfig, {"geofence": {"min_m": [-1, -1, 0], "max_m": [1, 1, 2]}}, path="p.toml", prefix="safety"
    )
    assert cfg.geofence.contains((0.5, 0.5, 1.0)) and not cfg.geofence.contains((1.5, 0.0, 1.0))
    with pytest.raises(ConfigError, match=r"p.toml: safety.geofence.min_m: x min 1.0 is not below max"):
        load_section(
            SafetyConfig,
            {"geofence": {"min_m": [1, -1, 0], "max_m": [1, 1, 2]}},
            path="p.toml",
            prefix="safety",
        )
    with pytest.raises(ConfigError, match="mocap_land_after_s"):
        load_section(
            SafetyConfig,
            {"mocap_hold_after_s": 0.5, "mocap_land_after_s": 0.4},
            path="p.toml",
            prefix="safety",
        )
    assert Geofence().contains((0.0, 0.0, 1.0), margin_m=0.5)
