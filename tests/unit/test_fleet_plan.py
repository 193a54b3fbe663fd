"""Fleet plans: the examples parse, share the pattern out as they say, and crowded plans are refused."""

import math
from pathlib import Path

import pytest

from flightkit.errors import ConfigError, PlanError
from flightkit.settings import load_toml
from trajectories.fleet_plan import is_fleet_plan, load_fleet_plan, parse_fleet_plan

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def test_three_on_a_circle_start_120_degrees_apart() -> None:
    fp = load_fleet_plan(EXAMPLES / "fleet_circle.toml")
    assert is_fleet_plan(load_toml(EXAMPLES / "fleet_circle.toml"))
    assert not is_fleet_plan(load_toml(EXAMPLES / "circle.toml"))
    pats = fp.build_patterns()
    starts = {n: p.reference(0.0).pos_m for n, p in pats.items()}
    angles = {n: math.degrees(math.atan2(s[1], s[0])) % 360.0 for n, s in starts.items()}
    assert angles == pytest.approx({"uav1": 180.0, "uav2": 300.0, "uav3": 60.0})
    assert fp.fleet.min_separation_m == 0.6 and fp.fleet.on_vehicle_fault == "land"
    fp.check_separation()  # 1.73 m apart all the way round


def test_formation_keeps_its_offsets_all_the_way() -> None:
    fp = load_fleet_plan(EXAMPLES / "fleet_formation.toml")
    pats = fp.build_patterns()
    for t in (0.0, 3.3, 7.1, pats["leader"].duration_s):
        lead = pats["leader"].reference(t).pos_m
        left = pats["left"].reference(t).pos_m
        assert (left[0] - lead[0], left[1] - lead[1], left[2] - lead[2]) == pytest.approx((0.0, 0.9, 0.0))
    assert pats["left"].duration_s == pats["leader"].duration_s


def test_lawnmower_strips_cover_the_area_once() -> None:
    fp = load_fleet_plan(EXAMPLES / "fleet_lawnmower.toml")
    pats = fp.build_patterns()
    times = [i * 0.5 for i in range(200)]
    ys = {n: sorted({round(p.reference(t).pos_m[1], 3) for t in times}) for n, p in pats.items()}
    # two 2 x 1 m strips, one below y = 0 and one above it
    assert max(ys["uav1"]) <= 0.0 + 1e-9 and min(ys["uav1"]) >= -1.0 - 1e-9
    assert min(ys["uav2"]) >= 0.0 - 1e-9 and max(ys["uav2"]) <= 1.0 + 1e-9


def base_table() -> dict[str, object]:
    return {
        "plan": {"name": "t"},
        "pattern": {"kind": "circle", "radius_m": 1.0, "period_s": 20.0, "height_m": 1.0},
        "vehicles": {"a": {}, "b": {"phase_deg": 20.0}},
    }


def test_crowded_references_are_refused_before_flight() -> None:
    fp = parse_fleet_plan(base_table(), "crowded.toml")
    with pytest.raises(PlanError, match=r"crowded.toml: the references of a and b come 0.3. m close"):
        fp.check_separation()


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"fleet": {"split": "rings"}}, "unknown split"),
        ({"fleet": {"on_vehicle_fault": "panic"}}, "on_vehicle_fault"),
        ({"vehicles": {}}, "names its vehicles"),
        ({"pattern": {"kind": "hold", "position_m": [0, 0, 1]}, "vehicles": {"a": {"phase_deg": 90.0}}}, "circle"),
        ({"fleet": {"split": "strips"}}, "lawnmower"),
    ],
)
def test_bad_fleet_plans_name_the_key(change: dict[str, object], match: str) -> None:
    table = {**base_table(), **change}
    with pytest.raises(ConfigError, match=match):
        parse_fleet_plan(table, "bad.toml")
