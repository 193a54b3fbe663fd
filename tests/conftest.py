"""Shared test options and fixtures."""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

# One BLAS thread, as the `flightkit` command sets for itself (flightkit/cli/main.py): set before
# any test module imports numpy. Measured: the renderer's (76800 x 3) @ (3 x 3) product took 5-16
# ms with OpenBLAS's two threads on this busy 2-core machine and 0.3 ms with one; same results.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")



def _private_bus_port() -> int:
    """A free TCP port below Linux's ephemeral range (so no session's own ephemeral listener takes
    it between tests), picked from the process id so two test runs on one machine differ."""
    for k in range(200):
        port = 20000 + (os.getpid() + 37 * k) % 12000
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise OSError("no free TCP port for the test run's bus between 20000 and 32000")


# The test run's own bus: every embedded-default Zenoh session of the tests and of the commands
# they start meets on this port instead of 7447, so tests never join a lab's bus on this machine,
# nor another test run's (flightkit/bus/session.py, FLIGHTKIT_BUS_PORT). A port given in the
# environment is kept; one picked by another process is not: each pytest-xdist worker inherits the
# controller's pick and takes a port of its own, so two workers' tests never share a bus.
_BUS_PORT_PICKED_BY = "FLIGHTKIT_TEST_BUS_PORT_PICKED_BY"
if "FLIGHTKIT_BUS_PORT" not in os.environ or os.environ.get(_BUS_PORT_PICKED_BY, str(os.getpid())) != str(
    os.getpid()
):
    os.environ["FLIGHTKIT_BUS_PORT"] = str(_private_bus_port())
    os.environ[_BUS_PORT_PICKED_BY] = str(os.getpid())

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--hardware", action="store_true", default=False, help="run tests that need real hardware")


# Test modules whose simulated time follows the wall clock (a SimClock at a speed-up, a flight in
# a subprocess) or whose waits are bounded in wall time. Under pytest-xdist (`make test` runs two
# workers, --dist loadgroup) they all run one after another in one worker, at normal CPU priority:
# two accelerated flights at once on a 2-core machine starve each other's control loop (measured:
# 40 Hz instead of 100). tests/unit/test_paced_group.py checks that no such module is left out.
PACED_MODULES = frozenset({
    "tests/integration/test_bus.py",
    "tests/integration/test_capture_cli.py",
    "tests/integration/test_capture_readout.py",
    "tests/integration/test_capture_sources.py",
    "tests/integration/test_clock_exchange.py",
    "tests/integration/test_closed_loop.py",
    "tests/integration/test_demo.py",
    "tests/integration/test_examples.py",
    "tests/integration/test_fleet.py",
    "tests/integration/test_fleet_shared_link.py",
    "tests/integration/test_fly_faults.py",
    "tests/integration/test_fly_latency.py",
    "tests/integration/test_fly_on_autopilot_estimate.py",
    "tests/integration/test_fly_patterns.py",
    "tests/integration/test_link_mavlink.py",
    "tests/integration/test_link_mavsdk.py",
    "tests/integration/test_link_mavsdk_tcp.py",
    "tests/integration/test_mocap.py",
    "tests/integration/test_mocap_simulated.py",
    "tests/integration/test_preflight_failsafe.py",
    "tests/integration/test_report_pty.py",
    "tests/integration/test_sim_autopilot.py",
    "tests/integration/test_sim_autopilot_flight.py",
    "tests/integration/test_sim_stepper.py",
    "tests/unit/test_clock.py",
})
PACED_GROUP = "paced"


def _is_paced(item: pytest.Item) -> bool:
    return item.path.relative_to(REPO_ROOT).as_posix() in PACED_MODULES


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if config.getoption("--hardware"):
        return
    skip = pytest.mark.skip(reason="needs real hardware; run with --hardware")
    for item in items:
        if "hardware" in item.keywords:
            item.add_marker(skip)


@pytest.hookimpl(optionalhook=True)  # a hook of pytest-xdist: without it, unused
def pytest_xdist_make_scheduler(config: pytest.Config, log: object) -> object:
    """Under ``--dist loadgroup``, the paced modules form one work unit (one worker runs them in
    turn); every other test is a unit of its own. Grouped here by the test's file, in the
    controller: pytest-xdist 3.8's own ``xdist_group`` mark renames the test's node id, which pytest
    9 no longer allows, and is silently ignored."""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadGroupScheduling

    class PacedGroupScheduling(LoadGroupScheduling):
        def _split_scope(self, nodeid: str) -> str:
            if nodeid.split("::", 1)[0] in PACED_MODULES:
                return PACED_GROUP
            return super()._split_scope(nodeid)

    return PacedGroupScheduling(config, log)  # type: ignore[arg-type]


_first_test_seen = False


def pytest_runtest_setup(item: pytest.Item) -> None:
    """In a pytest-xdist worker whose first test is not a paced one (so the paced group went to the
    other worker), lower this worker's CPU priority: its tests do not depend on wall time, and on a
    loaded machine the paced worker's flights then get the CPU they need first."""
    global _first_test_seen
    if _first_test_seen:
        return
    _first_test_seen = True
    if os.environ.get("PYTEST_XDIST_WORKER") and item.config.getvalue("loadgroup") and not _is_paced(item):
        os.nice(10)


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def shared_data() -> Path:
    """The team's real recorded sequences (../shared/data), read in place."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not found at {SHARED_DATA}")
    return SHARED_DATA


def wait(predicate: Callable[[], object], timeout_s: float, what: str) -> None:
    """Poll ``predicate`` until it is true; AssertionError naming ``what`` after ``timeout_s`` (wall)."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.001)


@pytest.fixture
def sessions() -> Iterator[tuple[object, object]]:
    """Two Zenoh sessions joined on a private loopback port: (listener, connector)."""
    from flightkit.bus.session import open_session
    from flightkit.config import BusConfig

    port = free_tcp_port()
    a = open_session(BusConfig(listen=(f"tcp/127.0.0.1:{port}",)))
    b = open_session(BusConfig(connect=(f"tcp/127.0.0.1:{port}",)))
    try:
        yield a, b
    finally:
        b.close()
        a.close()
