"""Plans: the example TOML files load, build the lab's patterns, and errors name file and key."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from flightkit.errors import ConfigError
from trajectories.base import YawMode
from trajectories.controller import OutputFrame
from trajectories.plan import CircleSpec, LawnmowerSpec, RectangleSpec, load_plan, parse_plan

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def test_circle_example_is_the_lab_circle() -> None:
    plan = load_plan(EXAMPLES / "circle.toml")
    assert isinstance(plan.pattern, CircleSpec)
    pat = plan.build_pattern()
    assert pat.laps == 2
    r0 = pat.reference(0.0)
    assert r0.pos_m == pytest.approx((-1.0, 0.0, 1.5))
    assert r0.yaw_rad == pytest.approx(0.0)  # looking inward from (-1, 0)
    assert pat.lap_duration_s == pytest.approx(40.0, abs=0.5)
    assert plan.controller.max_horizontal_m_s == 1.0 and plan.controller.max_vertical_m_s == 0.4
    assert plan.controller.output_frame is OutputFrame.BODY


def test_rectangle_example() -> None:
    plan = load_plan(EXAMPLES / "rectangle.toml")
    assert isinstance(plan.pattern, RectangleSpec)
    pat = plan.build_pattern()
    assert pat.laps == 2
    xs = [pat.reference(t).pos_m[0] for t in range(0, int(pat.duration_s))]
    ys = [pat.reference(t).pos_m[1] for t in range(0, int(pat.duration_s))]
    assert max(xs) - min(xs) == pytest.approx(2.0) and max(ys) - min(ys) == pytest.approx(1.0)
    assert pat.lap_duration_s == pytest.approx(60.0 + 2.0 + 20.0)  # sides, ramps, four 5 s turns


def test_lawnmower_example() -> None:
    plan = load_plan(EXAMPLES / "lawnmower.toml")
    assert isinstance(plan.pattern, LawnmowerSpec)
    assert plan.pattern.yaw is YawMode.TRAVEL
    pat = plan.build_pattern()
    assert pat.reference(0.0).pos_m == pytest.approx((-1.0, -0.5, 1.5))


def test_defaults_and_tangent_alias() -> None:
    plan = parse_plan({"pattern": {"kind": "circle", "speed_m_s": 0.5, "yaw": "tangent", "direction": "cw"}})
    assert plan.settings.takeoff_height_m == 1.5
    pat = plan.build_pattern()
    r = pat.reference(1.0)
    assert math.remainder(r.yaw_rad - math.atan2(r.vel_m_s[1], r.vel_m_s[0]), 2 * math.pi) == pytest.approx(
        0.0
    )


@pytest.mark.parametrize(
    ("table", "match"),
    [
        ({}, r"p.toml: pattern: missing \[pattern\]"),
        ({"pattern": {"kind": "spiral"}}, r"pattern.kind: 'spiral' is not a pattern kind"),
        (
            {"pattern": {"kind": "circle", "period_s": 10, "radius_m": -1}},
            r"pattern.radius_m: -1.0 is out of range",
        ),
        ({"pattern": {"kind": "circle", "period_s": 10, "radius": 1}}, r"pattern.radius: unknown key"),
        ({"pattern": {"kind": "circle"}}, r"pattern.period_s: give exactly one"),
        ({"pattern": {"kind": "circle", "period_s": 10, "direction": "left"}}, r"pattern.direction"),
        ({"pattern": {"kind": "circle", "period_s": 10}, "plan": {"rate_hz": 1}}, r"plan.rate_hz: 1"),
        ({"pattern": {"kind": "circle", "period_s": 10}, "controler": {}}, r"controler: unknown section"),
        ({"pattern": {"kind": "lawnmower", "yaw": "inward"}}, r"pattern.yaw: 'inward' is not allowed"),
        ({"pattern": {"kind": "waypoints", "points_m": [[0, 0, 1]]}}, r"pattern.points_m: needs 2"),
        (
            {"pattern": {"kind": "rectangle", "corners_m": [[0, 0], [0, 0], [1, 1]]}},
            r"p.toml: pattern.corners_m: corners 0 and 1 coincide",
        ),
    ],
)
def test_errors_name_file_and_key(table: dict[str, object], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        parse_plan(table, "p.toml")


def test_missing_file_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="file not found"):
        load_plan(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[pattern\n")
    with pytest.raises(ConfigError, match="invalid TOML"):
        load_plan(bad)


def test_a_safety_key_set_from_the_command_line_survives_the_labs_safety_table(tmp_path: Path) -> None:
    from flightkit.config import load_config

    lab_toml = tmp_path / "lab.toml"
    lab_toml.write_text("[safety]\nmax_speed_m_s = 1.5\nallow_hover_on_companion_loss = false\n")
    lab = load_config(lab_toml)
    plan = load_plan(Path(__file__).resolve().parents[2] / "examples" / "circle.toml")
    assert not plan.with_lab_defaults(lab).safety.allow_hover_on_companion_loss
    merged = plan.with_safety(allow_hover_on_companion_loss=True).with_lab_defaults(lab)
    assert merged.safety.allow_hover_on_companion_loss
    assert merged.safety.max_speed_m_s == 1.5  # the lab's other keys still apply


def test_reference_headroom_is_a_plan_setting_within_its_bounds() -> None:
    plan = parse_plan({"plan": {"reference_headroom": 1.0}, "pattern": {"kind": "circle", "period_s": 20.0}})
    assert plan.settings.reference_headroom == 1.0
    assert parse_plan({"pattern": {"kind": "circle", "period_s": 20.0}}).settings.reference_headroom == 0.8
    with pytest.raises(ConfigError, match="reference_headroom"):
        parse_plan({"plan": {"reference_headroom": 0.3}, "pattern": {"kind": "circle", "period_s": 20.0}})
