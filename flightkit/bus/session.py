"""Opening Zenoh sessions from :class:`~flightkit.config.BusConfig`.

Three set-ups, picked by config alone:

* **Embedded default** (``mode = "peer"``, no ``listen``/``connect``): processes on one
  machine find each other with no configuration and no multicast. Every session first tries
  to listen on the well-known loopback endpoint ``tcp/127.0.0.1:<well_known_port>``; when
  another flightkit process holds it, the session connects there instead and listens on an
  ephemeral loopback port of its own. Zenoh's gossip then meshes all peers, so they keep
  talking when the first one exits, and the next process to start takes the well-known
  port over (the others reconnect to it).
* **Explicit endpoints** (``listen``/``connect`` given, any mode): e.g. a router on the
  ground station (``mode = "router"``, ``listen = ["tcp/0.0.0.0:7447"]``) and vehicles as
  clients or peers connecting to it.
* **TLS and access control**: ``tls/`` endpoints with ``tls_root_ca``/``tls_cert``/
  ``tls_key``, and any other Zenoh setting (ACL rules, QoS, ...) from
  ``zenoh_config_file``, which is loaded first; the BusConfig fields are applied on top.

Multicast scouting is off unless ``multicast_scouting = true``.

The environment variable ``FLIGHTKIT_BUS_PORT`` replaces the default well-known port (7447)
for every session of the process and its children; a config that names another port keeps
it. The test suite sets it, so a test run never joins a lab's bus on the same machine, nor
another test run's.

Transport tuning (applied unless a ``zenoh_config_file`` sets the key itself): a best-effort
publisher (images) waits up to :data:`DROP_WAIT_US` for room in the transmit queue before
Zenoh drops the sample, instead of Zenoh's 1 ms, and the data priority gets a deeper queue.
With 1 ms, a scheduler stall of the sending thread on a loaded host (they reach several ms
on small VMs and single-board computers) dropped camera frames at 30 Hz with the link idle;
20 ms is still shorter than a frame period at 30 Hz, so a truly congested link keeps
dropping instead of slowing the camera loop (docs/bus.md).
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import Any

import zenoh

from flightkit.config import BusConfig, BusMode
from flightkit.errors import BusError

__all__ = ["build_zenoh_config", "bus_session", "open_session", "session_locators"]

logger = logging.getLogger(__name__)

_OPEN_ATTEMPTS = 4
_CONNECT_TIMEOUT_MS = 2000

DROP_WAIT_US = 20_000
"""How long a best-effort sample waits for the transmit queue before it is dropped (us)."""

# key -> (Zenoh's own default, flightkit's default)
_TRANSPORT_DEFAULTS: dict[str, tuple[Any, Any]] = {
    "transport/link/tx/queue/congestion_control/drop/wait_before_drop": (1000, DROP_WAIT_US),
    "transport/link/tx/queue/size/data": (2, 16),
}


PORT_ENV = "FLIGHTKIT_BUS_PORT"
"""Environment variable: replaces the default ``well_known_port`` (see the module docstring)."""


def well_known_port(cfg: BusConfig) -> int:
    """``cfg``'s well-known loopback port, or ``$FLIGHTKIT_BUS_PORT`` when ``cfg`` keeps the default.

    Raises:
        BusError: when the variable is set but is not a port number.
    """
    default = BusConfig().well_known_port
    text = os.environ.get(PORT_ENV, "").strip()
    if cfg.well_known_port != default or not text:
        return cfg.well_known_port
    if not text.isdigit() or not 1 <= int(text) <= 65535:
        raise BusError(f"{PORT_ENV}={text!r} is not a TCP port: set it to a number from 1 to 65535, or unset it")
    return int(text)


def _loopback(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def _insert(conf: zenoh.Config, key: str, value: Any, source: str) -> None:
    try:
        conf.insert_json5(key, json.dumps(value))
    except zenoh.ZError as exc:
        raise BusError(f"Zenoh rejected {key} = {value!r} from {source}: {exc}; fix that value") from exc


def _check_endpoints(endpoints: Sequence[str], key: str) -> None:
    for ep in endpoints:
        proto, sep, rest = ep.partition("/")
        if not sep or not proto or not rest:
            raise BusError(
                f"bus.{key} endpoint {ep!r} is not a Zenoh locator; write it as 'tcp/<host>:<port>' "
                "(or udp/, tls/, quic/, unixsock-stream/)"
            )


def _check_file(path: str, key: str) -> None:
    if path and not os.path.isfile(path):
        raise BusError(f"bus.{key} file {path!r} does not exist; give the path of the PEM file")


def build_zenoh_config(
    cfg: BusConfig, *, listen: Sequence[str] | None = None, connect: Sequence[str] | None = None
) -> zenoh.Config:
    """The :class:`zenoh.Config` for ``cfg``; ``listen``/``connect`` override the config's endpoints.

    The Zenoh JSON5 file ``cfg.zenoh_config_file`` (if any) is the starting point; mode,
    endpoints (when non-empty), multicast scouting and TLS files from ``cfg`` are set on top.

    Raises:
        BusError: for an unreadable config file, a malformed endpoint or a missing PEM file.
    """
    if cfg.zenoh_config_file:
        try:
            conf = zenoh.Config.from_file(cfg.zenoh_config_file)
        except (zenoh.ZError, OSError, ValueError) as exc:
            raise BusError(
                f"cannot load Zenoh config file {cfg.zenoh_config_file!r}: {exc}; check the path and its JSON5"
            ) from exc
        source = cfg.zenoh_config_file
    else:
        conf = zenoh.Config()
        source = "bus config"
    listen = tuple(cfg.listen if listen is None else listen)
    connect = tuple(cfg.connect if connect is None else connect)
    _check_endpoints(listen, "listen")
    _check_endpoints(connect, "connect")
    _insert(conf, "mode", cfg.mode.value, source)
    for key, (zenoh_default, ours) in _TRANSPORT_DEFAULTS.items():
        if json.loads(conf.get_json(key)) == zenoh_default:  # not set by the user's file
            _insert(conf, key, ours, "flightkit's transport defaults")
    if listen:
        _insert(conf, "listen/endpoints", list(listen), source)
    if connect:
        _insert(conf, "connect/endpoints", list(connect), source)
    _insert(conf, "scouting/multicast/enabled", bool(cfg.multicast_scouting), source)
    uses_tls = any(ep.startswith("tls/") for ep in (*listen, *connect))
    for key, path in (("tls_root_ca", cfg.tls_root_ca), ("tls_cert", cfg.tls_cert), ("tls_key", cfg.tls_key)):
        _check_file(path, key)
    if uses_tls and not cfg.tls_root_ca and not cfg.zenoh_config_file:
        raise BusError("tls/ endpoints need bus.tls_root_ca (the CA's PEM file); set it in the bus config")
    if cfg.tls_root_ca:
        _insert(conf, "transport/link/tls/root_ca_certificate", cfg.tls_root_ca, source)
    if cfg.tls_cert and cfg.tls_key:
        _insert(conf, "transport/link/tls/listen_certificate", cfg.tls_cert, source)
        _insert(conf, "transport/link/tls/listen_private_key", cfg.tls_key, source)
        _insert(conf, "transport/link/tls/connect_certificate", cfg.tls_cert, source)
        _insert(conf, "transport/link/tls/connect_private_key", cfg.tls_key, source)
        _insert(conf, "transport/link/tls/enable_mtls", True, source)
    elif bool(cfg.tls_cert) != bool(cfg.tls_key):
        raise BusError("bus.tls_cert and bus.tls_key go together; give both PEM files or neither")
    return conf


def _open(conf: zenoh.Config, what: str) -> zenoh.Session:
    try:
        return zenoh.open(conf)
    except zenoh.ZError as exc:
        raise BusError(f"cannot open the Zenoh session ({what}): {exc}") from exc


def _uses_embedded_default(cfg: BusConfig) -> bool:
    if cfg.mode is not BusMode.PEER or cfg.listen or cfg.connect:
        return False
    if cfg.zenoh_config_file:
        # A user file that names endpoints is an explicit set-up.
        conf = build_zenoh_config(cfg)
        for key in ("listen/endpoints", "connect/endpoints"):
            if json.loads(conf.get_json(key)):
                return False
    return True


def open_session(cfg: BusConfig | None = None) -> zenoh.Session:
    """Open a Zenoh session for ``cfg`` (defaults: the embedded loopback peer).

    The session is a context manager (``with open_session(cfg) as s:``) and must be closed.
    Blocks for at most a few seconds (the connect timeout of the embedded default).

    Raises:
        BusError: on a bad endpoint, a port in use, an unreadable config file, or when the
            embedded default can neither listen on nor connect to the well-known port.
    """
    cfg = cfg or BusConfig()
    if not _uses_embedded_default(cfg):
        if cfg.mode is BusMode.CLIENT and not cfg.connect:
            connect: tuple[str, ...] | None = (_loopback(well_known_port(cfg)),)
        else:
            connect = None
        listen: tuple[str, ...] | None = None
        if cfg.mode is BusMode.ROUTER and not cfg.listen:
            listen = (f"tcp/0.0.0.0:{well_known_port(cfg)}",)
        conf = build_zenoh_config(cfg, listen=listen, connect=connect)
        what = f"{cfg.mode.value}, listen {list(listen or cfg.listen)}, connect {list(connect or cfg.connect)}"
        s = _open(conf, what)
        logger.info("bus session %s opened (%s)", s.zid(), what)
        return s

    well_known = _loopback(well_known_port(cfg))
    last: Exception | None = None
    for attempt in range(_OPEN_ATTEMPTS):
        # 1. Be the first: listen on the well-known port.
        conf = build_zenoh_config(cfg, listen=(well_known,), connect=())
        try:
            s = zenoh.open(conf)
            logger.info("bus session %s listens on %s (first flightkit process here)", s.zid(), well_known)
            return s
        except zenoh.ZError as exc:
            last = exc
            logger.debug("well-known %s taken (%s); connecting to it", well_known, exc)
        # 2. Someone holds it: connect to them and listen on an ephemeral loopback port.
        conf = build_zenoh_config(cfg, listen=(_loopback(0),), connect=(well_known,))
        _insert(conf, "connect/timeout_ms", _CONNECT_TIMEOUT_MS, "embedded default")
        _insert(conf, "connect/exit_on_failure", True, "embedded default")
        try:
            s = zenoh.open(conf)
            logger.info("bus session %s joined the peer on %s", s.zid(), well_known)
            return s
        except zenoh.ZError as exc:  # the holder went away between our two tries
            last = exc
            logger.debug("attempt %d: cannot connect to %s (%s)", attempt + 1, well_known, exc)
    raise BusError(
        f"cannot listen on or connect to {well_known} (last error: {last}); another program may hold that port: "
        "set bus.well_known_port to a free port, or give bus.listen/bus.connect explicitly"
    )


@contextmanager
def bus_session(cfg: BusConfig | None = None) -> Iterator[zenoh.Session]:
    """``with bus_session(cfg) as s:`` -- :func:`open_session` that always closes."""
    s = open_session(cfg)
    try:
        yield s
    finally:
        s.close()


def session_locators(s: zenoh.Session) -> list[str]:
    """Source and destination locators of the session's current links (for diagnostics)."""
    return [f"{link.src} -> {link.dst}" for link in s.info.links()]
