"""Every test module that runs simulated time at a speed-up of the wall clock is in conftest's
paced group, so pytest-xdist never runs two of them at once (tests/conftest.py, PACED_MODULES)."""

import re

from tests.conftest import PACED_MODULES, REPO_ROOT

# What starts wall-paced simulated time in a test: a SimClock, the simulated lab or fleet, a flight
# in the simulator, or a command or example script run with --speed.
PACING = re.compile(
    r"SimClock\(|SimLab\(|SimFleet\(|sim_session\(|sim_fleet_session\(|fly_plan_in_sim\(|fly_closed_loop\(|"
    r"\"--speed\"|\[\"demo\""
)


def paced_by_their_source() -> set[str]:
    found = set()
    for path in sorted((REPO_ROOT / "tests").rglob("test_*.py")):
        if PACING.search(path.read_text(encoding="utf-8")):
            found.add(path.relative_to(REPO_ROOT).as_posix())
    return found


def test_every_wall_paced_module_is_in_the_paced_group() -> None:
    missing = paced_by_their_source() - PACED_MODULES
    assert not missing, f"add these to PACED_MODULES in tests/conftest.py: {sorted(missing)}"


def test_the_paced_group_names_existing_modules() -> None:
    gone = [m for m in PACED_MODULES if not (REPO_ROOT / m).is_file()]
    assert not gone, f"PACED_MODULES in tests/conftest.py names modules that no longer exist: {gone}"


def test_the_scan_finds_the_flights() -> None:
    found = paced_by_their_source()
    assert {"tests/integration/test_fly_patterns.py", "tests/integration/test_demo.py",
            "tests/integration/test_examples.py", "tests/unit/test_clock.py"} <= found
    assert "tests/unit/test_paced_group.py" not in found
