"""The architecture's import rules, checked on the source (ARCHITECTURE.md "Layers").

::

    flightkit/cli        parses, calls the composition layer (and the core)
    flightkit/apps       the composition layer: wires capabilities and the simulated lab together
    trajectories  capture  estimation          none imports another, or the simulated lab
    flightkit core: link mocap bus datasets sim frames config clock errors ...
"""

from __future__ import annotations

import ast
import re
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
    "flightkit/bus/cdr.py",
    "flightkit/bus/msg_base.py",
    "flightkit/bus/pose_msgs.py",
    "flightkit/bus/image_msgs.py",
    "flightkit/bus/msgs.py",
    "flightkit/link/endpoints.py",
    "trajectories/base.py",
    "trajectories/circle.py",
    "trajectories/rectangle.py",
    "trajectories/lawnmower.py",
    "trajectories/hold.py",
    "trajectories/waypoints.py",
    "trajectories/takeoff.py",
    "trajectories/patterns.py",
    "trajectories/controller.py",
    "trajectories/supervisor.py",
    "trajectories/status.py",
    "flightkit/calibration/rates.py",
    "flightkit/calibration/time_offset.py",
    "flightkit/calibration/hand_eye.py",
    "flightkit/calibration/board.py",
    "flightkit/calibration/clock_sync.py",
    "flightkit/calibration/latency.py",
    "flightkit/calibration/result.py",
    "estimation/motion.py",
    "estimation/rigid.py",
    "estimation/pnp.py",
    "estimation/p3p.py",
    "estimation/essential.py",
    "estimation/evaluation.py",
    "estimation/report/protocol.py",
    "estimation/report/link_session.py",
    "estimation/report/events.py",
    "estimation/report/endpoints.py",
)


def imported_modules(path: Path) -> set[str]:
    """Every absolute module name ``path`` imports (``import a.b`` and ``from a.b import c`` give ``a.b``)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    mods: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            mods.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            mods.add(node.module)
    return mods


def imported_roots(path: Path) -> set[str]:
    return {m.split(".")[0] for m in imported_modules(path)}


def under(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def py_files(folder: str) -> list[Path]:
    return sorted((ROOT / folder).rglob("*.py"))


ABOVE_CORE = ("cli", "apps")  # flightkit/cli and the composition layer flightkit/apps


@pytest.mark.parametrize(
    "path",
    [
        p
        for p in py_files("flightkit")
        if not set(ABOVE_CORE) & set(p.relative_to(ROOT).parts) and p.name != "__main__.py"  # python -m flightkit
    ],
)
def test_core_never_imports_capabilities_or_the_layers_above(path: Path) -> None:
    bad = sorted(imported_roots(path) & set(CAPABILITIES)) + sorted(
        m for m in imported_modules(path) if under(m, "flightkit.apps") or under(m, "flightkit.cli")
    )
    assert not bad, f"{path.relative_to(ROOT)} imports {bad}; only flightkit/apps may wire capabilities"


@pytest.mark.parametrize("path", py_files("flightkit/cli"), ids=lambda p: p.name)
def test_cli_imports_only_the_composition_layer_and_the_core(path: Path) -> None:
    bad = sorted(imported_roots(path) & set(CAPABILITIES))
    assert not bad, f"{path.relative_to(ROOT)} imports {bad}; call a function of flightkit/apps instead"


@pytest.mark.parametrize("package", CAPABILITIES)
def test_capabilities_do_not_import_each_other(package: str) -> None:
    others = set(CAPABILITIES) - {package}
    offenders = {str(p.relative_to(ROOT)): sorted(imported_roots(p) & others) for p in py_files(package)}
    offenders = {k: v for k, v in offenders.items() if v}
    assert not offenders, f"capability packages import each other: {offenders}"


@pytest.mark.parametrize("package", CAPABILITIES)
def test_capabilities_do_not_import_the_simulated_lab_or_the_layers_above(package: str) -> None:
    offenders = {
        str(p.relative_to(ROOT)): sorted(
            m for m in imported_modules(p)
            if under(m, "flightkit.sim") or under(m, "flightkit.apps") or under(m, "flightkit.cli")
        )
        for p in py_files(package)
    }
    offenders = {k: v for k, v in offenders.items() if v}
    assert not offenders, f"capabilities must not import the simulated lab or flightkit/apps: {offenders}"


ALL_CODE = [p for folder in ("flightkit", *CAPABILITIES) for p in py_files(folder)]


def test_mcap_files_are_read_and_written_only_in_flightkit_datasets() -> None:
    offenders = sorted(
        str(p.relative_to(ROOT))
        for p in ALL_CODE
        if imported_roots(p) & {"mcap", "mcap_ros2"} and "flightkit/datasets" not in str(p.relative_to(ROOT))
    )
    assert not offenders, f"read recordings through flightkit.datasets.mcap_reader, not on your own: {offenders}"


# Hand-made ENU<->NED conversions: swapping x and y with z negated, or a heading as pi/2 minus another.
_HAND_FRAME = re.compile(
    r"\[1\],\s*-?[\w.]+\[0\],\s*-\s*[\w.]+\[2\]"  # (v[1], v[0], -v[2])
    r"|pi\s*/\s*2(\.0)?\s*-\s*[\w(]"  # pi / 2 - yaw
)


@pytest.mark.parametrize("path", [p for p in ALL_CODE if p.name != "frames.py"], ids=lambda p: str(p.relative_to(ROOT)))
def test_no_enu_ned_conversion_by_hand_outside_frames(path: Path) -> None:
    hits = [
        f"{path.relative_to(ROOT)}:{i}: {line.strip()}"
        for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if _HAND_FRAME.search(line)
    ]
    assert not hits, "convert frames with flightkit.frames (enu_to_ned, yaw_enu_to_ned, ...):\n" + "\n".join(hits)


def test_the_frame_check_catches_hand_conversions() -> None:
    assert _HAND_FRAME.search("return np.array([v[1], v[0], -v[2]])")
    assert _HAND_FRAME.search("yaw = wrap_angle_rad(math.pi / 2.0 - msg.yaw)")
    assert not _HAND_FRAME.search("yaw = yaw_ned_to_enu(msg.yaw)")


@pytest.mark.parametrize("module", PURE_MODULES)
def test_pure_logic_imports_no_io_library(module: str) -> None:
    path = ROOT / module
    assert path.is_file(), f"{module} listed as pure logic but missing"
    bad = imported_roots(path) & set(IO_LIBRARIES)
    assert not bad, f"{module} is pure logic but imports {sorted(bad)}"
