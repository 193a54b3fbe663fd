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
# nor another test run's (flightkit/bus/session.py, FLIGHTKIT_BUS_PORT).
os.environ.setdefault("FLIGHTKIT_BUS_PORT", str(_private_bus_port()))

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--hardware", action="store_true", default=False, help="run tests that need real hardware")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if config.getoption("--hardware"):
        return
    skip = pytest.mark.skip(reason="needs real hardware; run with --hardware")
    for item in items:
        if "hardware" in item.keywords:
            item.add_marker(skip)


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
