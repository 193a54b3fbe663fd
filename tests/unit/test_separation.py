"""Separation of a fleet's vehicles: measured, predicted at constant velocity, and of a plan."""

import math

import pytest

from flightkit.config import load_config
from flightkit.errors import ConfigError
from trajectories.circle import Circle
from trajectories.separation import FleetSafety, closest_approach, plan_separation


def test_closest_pair_now_and_ahead() -> None:
    pos = {"a": (0.0, 0.0, 1.0), "b": (2.0, 0.0, 1.0), "c": (0.0, 5.0, 1.0)}
    # b flies at a at 1 m/s: 2 m apart now, 1 m a second ahead, 0 m two seconds ahead
    vel = {"b": (-1.0, 0.0, 0.0)}
    a = closest_approach(pos, vel, lookahead_s=1.0)
    assert a is not None and a.pair == ("a", "b")
    assert a.distance_m == pytest.approx(2.0) and a.predicted_m == pytest.approx(1.0)
    assert a.closest_m == pytest.approx(1.0)
    # moving apart: the prediction never comes closer than now
    away = closest_approach(pos, {"b": (1.0, 0.0, 0.0)}, lookahead_s=1.0)
    assert away is not None and away.predicted_m == pytest.approx(2.0)
    # passing by: the minimum inside the look-ahead, not at its end
    by = closest_approach({"a": (0.0, 0.0, 0.0), "b": (1.0, -1.0, 0.0)}, {"b": (0.0, 2.0, 0.0)}, 2.0)
    assert by is not None and by.predicted_m == pytest.approx(1.0)
    assert closest_approach({"a": (0.0, 0.0, 0.0)}, {}, 1.0) is None


def test_plan_separation_finds_the_closest_moment() -> None:
    base = Circle(radius_m=1.0, height_m=1.0, period_s=10.0)
    same_way = {"a": base, "b": Circle(radius_m=1.0, height_m=1.0, period_s=10.0, start_angle_rad=0.0)}
    d, _, pair = plan_separation(same_way)
    assert pair == ("a", "b") and d == pytest.approx(2.0, abs=1e-6)  # opposite sides all the way
    other_way = Circle(radius_m=1.0, height_m=1.0, period_s=10.0, clockwise=True, start_angle_rad=0.0)
    crossing = {"a": base, "b": other_way}
    d, t, _ = plan_separation(crossing)
    assert d < 0.05 and t > 1.0  # opposite starts, opposite ways: they meet a quarter lap on
    assert plan_separation({"a": base})[0] == math.inf


def test_fleet_safety_policy_is_checked() -> None:
    from flightkit.settings import load_section

    with pytest.raises(ConfigError, match="on_vehicle_fault"):
        load_section(FleetSafety, {"on_vehicle_fault": "panic"}, prefix="fleet")


def test_lab_config_lists_vehicles() -> None:
    cfg = load_config(
        table={
            "link": {"url": "udpout:10.0.0.2:14550"},
            "vehicles": [
                {"name": "uav1", "system_id": 1},
                {"name": "uav2", "system_id": 2, "autopilot": "ardupilot", "body": "cf2"},
                {"name": "uav3", "url": "udpout:10.0.0.3:14550", "geofence_min_m": [-1, -1, 0],
                 "geofence_max_m": [1, 1, 2]},
            ],
        }
    )
    fleet = cfg.fleet()
    assert [c.vehicle.namespace for c in fleet] == ["uav1", "uav2", "uav3"]
    assert [c.mocap.body for c in fleet] == ["uav1", "cf2", "uav3"]
    assert [c.link.system_id for c in fleet] == [1, 2, 0]
    assert fleet[1].vehicle.autopilot.value == "ardupilot" and fleet[0].vehicle.autopilot.value == "px4"
    assert fleet[0].link.url == "udpout:10.0.0.2:14550" and fleet[2].link.url == "udpout:10.0.0.3:14550"
    assert load_config().fleet()[0].vehicle.namespace == "uav1"  # one-vehicle configs unchanged


@pytest.mark.parametrize(
    ("vehicles", "match"),
    [
        ([{"name": "a"}, {"name": "a", "system_id": 2}], "same name 'a'"),
        ([{"name": "a", "body": "x"}, {"name": "b", "body": "x"}], "same body 'x'"),
        ([{"name": "a", "url": "udpin:0.0.0.0:1"}, {"name": "b", "url": "udpin:0.0.0.0:1"}], "same link"),
        ([{"name": "a", "autopilot": "inav"}], "unknown autopilot"),
        ([{"system_id": 3}], "missing vehicle name"),
        ([{"name": "a", "geofence_min_m": [0, 0, 0]}], "needs both corners"),
    ],
)
def test_bad_fleet_configs_are_refused(vehicles: list[dict[str, object]], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        load_config(table={"vehicles": vehicles})
