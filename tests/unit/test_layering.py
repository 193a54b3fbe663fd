"""The architecture's import rules, checked on the source (ARCHITECTURE.md "Layers")."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
CAPABILITIES = ("trajectories", "capture", "estimation")
IO_LIBRARIES = ("pymavlink", "mavsdk", "serial", "zenoh", "mcap", "mcap_ros2", "motioncapture", "pyrealsense2")

# Pure logic: numpy/scipy/stdlib (and cv2 for vision math) only, never an IO library.
PURE_MODULES = (
    "flightkit/frames.py",
    "flightkit/clock.py",
    "flightkit/config.py",
    "flightkit/errors.py",
    "trajectories/base.py",
    "trajectories/circle.py",
    "trajectories/rectangle.py",
    "trajectories/lawnmower.py",
    "trajectories/hold.py",
    "trajectories/waypoints.py",
    "trajectories/takeoff.py",
    "trajectories/land.py",
    "trajectories/patterns.py",
    "trajectories/controller.py",
    "trajectories/supervisor.py",
    "estimation/motion.py",
    "estimation/evaluation.py",
    "estimation/report/protocol.py",
    "estimation/report/session.py",
)


def imported_roots(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    roots: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            roots.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            roots.add(node.module.split(".")[0])
    return roots


def py_files(folder: str) -> list[Path]:
    return sorted((ROOT / folder).rglob("*.py"))


ABOVE_CORE = ("cli", "apps")  # flightkit/cli and the composition layer flightkit/apps


@pytest.mark.parametrize(
    "path", [p for p in py_files("flightkit") if not set(ABOVE_CORE) & set(p.relative_to(ROOT).parts)]
)
def test_core_never_imports_capabilities(path: Path) -> None:
    bad = imported_roots(path) & set(CAPABILITIES)
    assert not bad, f"{path.relative_to(ROOT)} imports {sorted(bad)}; only flightkit/apps (and the CLI) may"


@pytest.mark.parametrize("package", CAPABILITIES)
def test_capabilities_do_not_import_each_other(package: str) -> None:
    others = set(CAPABILITIES) - {package}
    offenders = {str(p.relative_to(ROOT)): sorted(imported_roots(p) & others) for p in py_files(package)}
    offenders = {k: v for k, v in offenders.items() if v}
    assert not offenders, f"capability packages import each other: {offenders}"


@pytest.mark.parametrize("module", PURE_MODULES)
def test_pure_logic_imports_no_io_library(module: str) -> None:
    path = ROOT / module
    assert path.is_file(), f"{module} listed as pure logic but missing"
    bad = imported_roots(path) & set(IO_LIBRARIES)
    assert not bad, f"{module} is pure logic but imports {sorted(bad)}"
