"""MAVLink connection strings: parsing and validation (the byte transports behind them:
:mod:`flightkit.link.transports`).

Accepted forms (the ``//`` after the scheme is optional, so MAVSDK-style URLs work too)::

    udpin:0.0.0.0:14540      listen for UDP on a local port (reply to whoever talks to us)
    udp:0.0.0.0:14540        the same (pymavlink/MAVProxy convention: ``udp:`` listens)
    udpout:127.0.0.1:14540   send UDP to a remote port (from an ephemeral local port)
    tcp:127.0.0.1:5760       TCP client (``tcpout:`` is accepted as a synonym)
    tcpin:0.0.0.0:5760       TCP server, one client at a time
    serial:/dev/ttyUSB0:921600
    /dev/ttyACM0:57600       a device path, optionally with its baud rate
    /dev/ttyACM0             baud rate from ``link.baud``
    COM3:57600               Windows serial port

Listening endpoints accept port 0 (the OS picks a free port; read it back from
:attr:`flightkit.link.transports.Transport.local_port`), which is what tests use.
"""

from __future__ import annotations

import enum
import ipaddress
import re
from dataclasses import dataclass

from flightkit.errors import EndpointError

__all__ = [
    "Endpoint",
    "EndpointKind",
    "parse_endpoint",
]

_EXAMPLES = "udpin:0.0.0.0:14540, udpout:127.0.0.1:14540, tcp:127.0.0.1:5760, tcpin:0.0.0.0:5760 or /dev/ttyACM0:57600"


class EndpointKind(enum.Enum):
    UDP_IN = "udpin"
    UDP_OUT = "udpout"
    TCP_CLIENT = "tcp"
    TCP_SERVER = "tcpin"
    SERIAL = "serial"


@dataclass(frozen=True, slots=True)
class Endpoint:
    """A parsed connection string.

    Attributes:
        kind: transport kind.
        host: IP address or host name (network kinds; "" for serial).
        port: UDP/TCP port (0 for serial; 0 on a listening kind = any free port).
        device: serial device path ("" for network kinds).
        baud: serial baud rate (0 for network kinds).
    """

    kind: EndpointKind
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 0

    @property
    def url(self) -> str:
        """Canonical connection string, e.g. ``udpin:0.0.0.0:14540``."""
        if self.kind is EndpointKind.SERIAL:
            return f"serial:{self.device}:{self.baud}"
        return f"{self.kind.value}:{self.host}:{self.port}"

    @property
    def listens(self) -> bool:
        return self.kind in (EndpointKind.UDP_IN, EndpointKind.TCP_SERVER)

    def to_mavsdk_url(self) -> str:
        """The same endpoint as a MAVSDK connection URL (``udpin://``, ``tcpout://``, ``serial://``)."""
        if self.kind is EndpointKind.SERIAL:
            return f"serial://{self.device}:{self.baud}"
        scheme = {
            EndpointKind.UDP_IN: "udpin",
            EndpointKind.UDP_OUT: "udpout",
            EndpointKind.TCP_CLIENT: "tcpout",
            EndpointKind.TCP_SERVER: "tcpin",
        }[self.kind]
        return f"{scheme}://{self.host}:{self.port}"

    def __str__(self) -> str:
        return self.url


_SCHEMES = {
    "udpin": EndpointKind.UDP_IN,
    "udp": EndpointKind.UDP_IN,
    "udpout": EndpointKind.UDP_OUT,
    "tcp": EndpointKind.TCP_CLIENT,
    "tcpout": EndpointKind.TCP_CLIENT,
    "tcpin": EndpointKind.TCP_SERVER,
    "serial": EndpointKind.SERIAL,
}
_HOSTNAME_RE = re.compile(
    r"^(?=.{1,253}$)[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?(\.[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$"
)
_SERIAL_DEVICE_RE = re.compile(r"^(/dev/[^\s:]+|COM\d+|\\\\\.\\COM\d+)$", re.IGNORECASE)
_BAUD_MIN, _BAUD_MAX = 1200, 4_000_000


def parse_endpoint(url: str, default_baud: int = 57600) -> Endpoint:
    """Parse and validate a MAVLink connection string (forms in the module docstring).

    Args:
        url: the connection string (``link.url``).
        default_baud: baud rate for a serial device given without one (``link.baud``).

    Raises:
        EndpointError: the string is malformed; the message says what to write instead.
    """
    text = url.strip()
    if not text:
        raise EndpointError(f"empty connection string; write one like {_EXAMPLES}")
    if _looks_like_serial(text):
        return _parse_serial(url, text, default_baud)
    scheme, sep, rest = text.partition(":")
    if not sep:
        raise EndpointError(f"connection string {url!r} has no scheme; write one like {_EXAMPLES}")
    kind = _SCHEMES.get(scheme.lower())
    if kind is None:
        known = ", ".join(f"{s}:" for s in _SCHEMES)
        raise EndpointError(
            f"unknown scheme {scheme!r} in connection string {url!r}; use one of {known} (e.g. {_EXAMPLES})"
        )
    rest = rest.removeprefix("//")
    if kind is EndpointKind.SERIAL:
        return _parse_serial(url, rest, default_baud)
    host, sep, port_text = rest.rpartition(":")
    if not sep:
        raise EndpointError(
            f"connection string {url!r} has no port; write {scheme}:HOST:PORT, e.g. {scheme}:127.0.0.1:14540"
        )
    host = host.strip("[]")
    if kind in (EndpointKind.UDP_IN, EndpointKind.TCP_SERVER) and host == "":
        host = "0.0.0.0"  # MAVSDK's "udpin://:14540"
    if not host:
        raise EndpointError(
            f"connection string {url!r} has no host; write {scheme}:HOST:PORT, e.g. {scheme}:127.0.0.1:14540"
        )
    if not _valid_host(host):
        raise EndpointError(
            f"{host!r} in {url!r} is not an IP address or host name; write e.g. {scheme}:127.0.0.1:14540"
        )
    try:
        port = int(port_text)
    except ValueError:
        raise EndpointError(
            f"port {port_text!r} in {url!r} is not a number; write e.g. {scheme}:{host}:14540"
        ) from None
    low = 0 if kind in (EndpointKind.UDP_IN, EndpointKind.TCP_SERVER) else 1
    if not low <= port <= 65535:
        raise EndpointError(f"port {port} in {url!r} is out of range; use {low}-65535")
    return Endpoint(kind, host=host, port=port)


def _looks_like_serial(text: str) -> bool:
    return text.startswith("/dev/") or re.match(r"^(COM\d+|\\\\\.\\COM\d+)(:|$)", text, re.IGNORECASE) is not None


def _parse_serial(url: str, rest: str, default_baud: int) -> Endpoint:
    device, baud_text = rest, ""
    m = re.match(r"^(.*?):(\d*)$", rest)
    if m and _SERIAL_DEVICE_RE.match(m.group(1)):
        device, baud_text = m.group(1), m.group(2)
    if not _SERIAL_DEVICE_RE.match(device):
        raise EndpointError(
            f"{device!r} in {url!r} is not a serial device; write serial:/dev/ttyUSB0:921600 or /dev/ttyACM0:57600"
        )
    if baud_text:
        baud = int(baud_text)
    elif m and m.group(2) == "" and rest.endswith(":"):
        raise EndpointError(f"missing baud rate after ':' in {url!r}; write e.g. {device}:57600")
    else:
        baud = default_baud
    if not _BAUD_MIN <= baud <= _BAUD_MAX:
        raise EndpointError(
            f"baud rate {baud} in {url!r} is out of range; use {_BAUD_MIN}-{_BAUD_MAX} (e.g. 57600, 921600)"
        )
    return Endpoint(EndpointKind.SERIAL, device=device, baud=baud)


def _valid_host(host: str) -> bool:
    try:
        ipaddress.ip_address(host)
        return True
    except ValueError:
        return _HOSTNAME_RE.match(host) is not None
