"""Every example script runs against the simulator (fast settings) and does what it says."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
EXAMPLES = REPO / "examples"

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(180)]


def run_example(name: str, *args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "MPLBACKEND": "Agg", "PYTHONPATH": str(REPO)}
    return subprocess.run(
        [sys.executable, str(EXAMPLES / name), *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=170,
    )


def test_every_example_script_is_tested() -> None:
    tested = {"fly_circle.py", "fly_plan.py", "mocap_dropout.py"}
    assert {p.name for p in EXAMPLES.glob("*.py")} == tested


def test_fly_circle_script_api(tmp_path: Path) -> None:
    r = run_example(
        "fly_circle.py", "--speed", "5", "--laps", "1", "--period", "20", "--hold", "0.5", cwd=tmp_path
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert "flight 'circle': completed" in r.stdout
    m = re.search(r"circle: RMS ([\d.]+) mm, max ([\d.]+) mm, 360 deg flown", r.stdout)
    assert m, r.stdout
    # The example must fly the circle well; the tight tracking bounds live in test_fly_patterns.py.
    assert float(m.group(1)) < 40.0 and float(m.group(2)) < 120.0


def test_fly_plan_with_plot(tmp_path: Path) -> None:
    plan = tmp_path / "short.toml"
    text = (EXAMPLES / "rectangle.toml").read_text()
    text = text.replace("speed_m_s = 0.1", "speed_m_s = 0.3").replace("laps = 2", "laps = 1")
    text = text.replace("turn_s = 5.0", "turn_s = 1.0").replace("hold_before_s = 5.0", "hold_before_s = 0.5")
    # half the size (1 m x 0.5 m): the test is about the script and its plot, not the tracking
    text = text.replace("size_m = [2.0, 1.0]", "size_m = [1.0, 0.5]")
    assert "size_m = [1.0, 0.5]" in text
    plan.write_text(text.replace("hold_after_s = 5.0", "hold_after_s = 0.5"))
    r = run_example(
        "fly_plan.py", str(plan), "--speed", "5", "--log", str(tmp_path / "r.csv"), "--plot", cwd=tmp_path
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert "flight 'rectangle': completed" in r.stdout
    plots = [Path(line[6:]) for line in r.stdout.splitlines() if line.startswith("plot: ")]
    assert plots and all(p.is_file() and p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in plots)


def test_mocap_dropout_short_holds_long_lands(tmp_path: Path) -> None:
    short = run_example("mocap_dropout.py", "--dropout", "0.5", "--speed", "5", cwd=tmp_path)
    assert short.returncode == 0, short.stderr[-3000:]
    assert "held through the dropout" in short.stdout and "mocap_stale" in short.stdout
    assert "vehicle armed: False" in short.stdout
    long = run_example("mocap_dropout.py", "--dropout", "2.0", "--speed", "5", cwd=tmp_path)
    assert long.returncode == 0, long.stderr[-3000:]
    assert "the supervisor ended the flight: mocap_lost" in long.stdout
    assert "vehicle armed: False" in long.stdout
