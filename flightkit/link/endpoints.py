"""MAVLink connection strings: parsing, validation, and the byte transports behind them.

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
:attr:`Transport.local_port`), which is what tests use.

A transport moves raw bytes; framing and signing are pymavlink's job in
:mod:`flightkit.link.mavlink`. Transports are used from one reader thread (``recv``) and
any number of writer threads (``send`` is serialised by the caller).
"""

from __future__ import annotations

import enum
import errno
import ipaddress
import logging
import re
import select
import socket
from dataclasses import dataclass
from typing import Protocol

from flightkit.errors import EndpointError

__all__ = [
    "Endpoint",
    "EndpointKind",
    "Transport",
    "open_transport",
    "parse_endpoint",
]

logger = logging.getLogger(__name__)

_EXAMPLES = "udpin:0.0.0.0:14540, udpout:127.0.0.1:14540, tcp:127.0.0.1:5760, tcpin:0.0.0.0:5760 or /dev/ttyACM0:57600"
_MAX_DATAGRAM = 65535
_UDP_RCVBUF_BYTES = 1 << 20  # room for a fleet's telemetry while the reader waits for the GIL
_DRAIN_DATAGRAMS = 64  # datagrams one recv() returns at most (one parse, one wake for the batch)


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


# --------------------------------------------------------------------------- transports


class Transport(Protocol):
    """A byte pipe to the autopilot."""

    @property
    def description(self) -> str:
        """Human-readable endpoint, for messages."""
        ...

    @property
    def local_port(self) -> int:
        """The local UDP/TCP port (0 for serial)."""
        ...

    def recv(self, timeout_s: float) -> bytes:
        """Wait up to ``timeout_s`` (wall time) for bytes; b"" if none arrived.

        Raises:
            EndpointError: the transport is dead (serial device gone, TCP connection closed).
        """
        ...

    @property
    def last_sender(self) -> tuple[str, int] | None:
        """Address of the newest datagram's sender (UDP); None for TCP and serial."""
        ...

    def pin_peer(self, addr: tuple[str, int]) -> None:
        """Send to ``addr`` from now on (UDP listeners); a no-op elsewhere."""
        ...

    def send(self, data: bytes) -> None:
        """Send bytes now; drops them if there is nobody to send to yet."""
        ...

    def close(self) -> None: ...


def open_transport(endpoint: Endpoint, connect_timeout_s: float = 5.0) -> Transport:
    """Open the transport for ``endpoint``.

    Blocks for at most ``connect_timeout_s`` (TCP client connect only).

    Raises:
        EndpointError: the port is in use, the address is not local, the device is missing,
            or a TCP connection is refused.
    """
    if endpoint.kind is EndpointKind.UDP_IN:
        return _UdpIn(endpoint)
    if endpoint.kind is EndpointKind.UDP_OUT:
        return _UdpOut(endpoint)
    if endpoint.kind is EndpointKind.TCP_CLIENT:
        return _TcpClient(endpoint, connect_timeout_s)
    if endpoint.kind is EndpointKind.TCP_SERVER:
        return _TcpServer(endpoint)
    return _Serial(endpoint)


def _bind_error(endpoint: Endpoint, exc: OSError) -> EndpointError:
    if exc.errno == errno.EADDRINUSE:
        return EndpointError(
            f"port {endpoint.port} of {endpoint.url} is already in use (another GCS, MAVProxy or flightkit?); "
            "close that program or choose another port in link.url"
        )
    if exc.errno == errno.EADDRNOTAVAIL:
        return EndpointError(
            f"{endpoint.host} in {endpoint.url} is not an address of this machine; listen on 0.0.0.0 or a local address"
        )
    if exc.errno == errno.EACCES:
        return EndpointError(f"no permission to open port {endpoint.port} of {endpoint.url}; use a port above 1023")
    return EndpointError(f"cannot open {endpoint.url}: {exc.strerror}; check link.url")


def _resolve(endpoint: Endpoint, kind: socket.SocketKind) -> tuple[int, tuple[str, int]]:
    try:
        infos = socket.getaddrinfo(endpoint.host, endpoint.port, type=kind)
    except socket.gaierror as exc:
        raise EndpointError(
            f"cannot resolve host {endpoint.host!r} of {endpoint.url} ({exc.strerror}); "
            "use an IP address or a known name"
        ) from exc
    family, _, _, _, addr = infos[0]
    return family, (str(addr[0]), int(addr[1]))


def _udp_socket(family: int) -> socket.socket:
    sock = socket.socket(family, socket.SOCK_DGRAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, _UDP_RCVBUF_BYTES)
    except OSError:  # the OS caps it; the default still works
        pass
    return sock


def _recv_batch(sock: socket.socket, timeout_s: float) -> tuple[bytes, tuple[str, int] | None]:
    """Wait up to ``timeout_s`` for a datagram, then take those already queued from the same sender.

    Returns (their bytes joined, the sender), or (b"", None) when none arrived.
    """
    if not _wait_readable(sock, timeout_s):
        return b"", None
    chunks: list[bytes] = []
    sender: tuple[str, int] | None = None
    for _ in range(_DRAIN_DATAGRAMS):
        try:  # the first datagram is waiting; later ones only if already queued (peeked first)
            data, addr = sock.recvfrom(_MAX_DATAGRAM, (socket.MSG_PEEK | socket.MSG_DONTWAIT) if chunks else 0)
        except OSError:  # none queued, or e.g. ICMP port unreachable on Linux: nobody listens yet
            break
        addr_t = (str(addr[0]), int(addr[1]))
        if chunks:
            if addr_t != sender:
                break  # another sender's datagram stays queued for the next call
            sock.recv(_MAX_DATAGRAM, socket.MSG_DONTWAIT)
        chunks.append(data)
        sender = addr_t
    return b"".join(chunks), sender


def _wait_readable(sock: socket.socket, timeout_s: float) -> bool:
    try:
        ready, _, _ = select.select([sock], [], [], max(0.0, timeout_s))
    except (OSError, ValueError):
        return False
    return bool(ready)


class _UdpIn:
    """Listen on a local UDP port; replies go to the peer set by the link (or the last sender)."""

    def __init__(self, endpoint: Endpoint) -> None:
        self._endpoint = endpoint
        family, addr = _resolve(endpoint, socket.SOCK_DGRAM)
        self._sock = _udp_socket(family)
        try:
            self._sock.bind(addr)
        except OSError as exc:
            self._sock.close()
            raise _bind_error(endpoint, exc) from exc
        self._peer: tuple[str, int] | None = None
        self._pinned = False
        self.last_sender: tuple[str, int] | None = None

    @property
    def description(self) -> str:
        return self._endpoint.url

    @property
    def local_port(self) -> int:
        return int(self._sock.getsockname()[1])

    def pin_peer(self, addr: tuple[str, int]) -> None:
        """Send to ``addr`` from now on (the link calls this once it has found the autopilot)."""
        self._peer = addr
        self._pinned = True

    def recv(self, timeout_s: float) -> bytes:
        data, sender = _recv_batch(self._sock, timeout_s)
        if sender is not None:
            self.last_sender = sender
            if not self._pinned:
                self._peer = sender
        return data

    def send(self, data: bytes) -> None:
        if self._peer is None:
            return
        try:
            self._sock.sendto(data, self._peer)
        except OSError as exc:
            logger.debug("udp send to %s failed: %s", self._peer, exc)

    def close(self) -> None:
        self._sock.close()


class _UdpOut:
    """Send to a remote UDP port from an ephemeral local port; accept replies from anyone."""

    def __init__(self, endpoint: Endpoint) -> None:
        self._endpoint = endpoint
        family, self._addr = _resolve(endpoint, socket.SOCK_DGRAM)
        self._sock = _udp_socket(family)
        self._sock.bind(("::" if family == socket.AF_INET6 else "0.0.0.0", 0))
        self.last_sender: tuple[str, int] | None = None

    @property
    def description(self) -> str:
        return self._endpoint.url

    @property
    def local_port(self) -> int:
        return int(self._sock.getsockname()[1])

    def pin_peer(self, addr: tuple[str, int]) -> None:
        """No-op: an outgoing UDP link always sends to its configured address."""

    def recv(self, timeout_s: float) -> bytes:
        data, sender = _recv_batch(self._sock, timeout_s)
        if sender is not None:
            self.last_sender = sender
        return data

    def send(self, data: bytes) -> None:
        try:
            self._sock.sendto(data, self._addr)
        except OSError as exc:
            logger.debug("udp send to %s failed: %s", self._addr, exc)

    def close(self) -> None:
        self._sock.close()


class _TcpClient:
    last_sender: tuple[str, int] | None = None

    def __init__(self, endpoint: Endpoint, connect_timeout_s: float) -> None:
        self._endpoint = endpoint
        family, addr = _resolve(endpoint, socket.SOCK_STREAM)
        self._sock = socket.socket(family, socket.SOCK_STREAM)
        self._sock.settimeout(connect_timeout_s)
        try:
            self._sock.connect(addr)
        except OSError as exc:
            self._sock.close()
            what = "refused the connection" if isinstance(exc, ConnectionRefusedError) else f"is unreachable ({exc})"
            raise EndpointError(
                f"{endpoint.url} {what}; is the autopilot/simulator running and listening on TCP port {endpoint.port}?"
            ) from exc
        self._sock.settimeout(None)
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._closed = False

    @property
    def description(self) -> str:
        return self._endpoint.url

    @property
    def local_port(self) -> int:
        return int(self._sock.getsockname()[1])

    def pin_peer(self, addr: tuple[str, int]) -> None:
        """No-op for TCP."""

    def recv(self, timeout_s: float) -> bytes:
        if self._closed or not _wait_readable(self._sock, timeout_s):
            return b""
        try:
            data = self._sock.recv(_MAX_DATAGRAM)
        except OSError:
            data = b""
        if not data:
            self._closed = True
            raise EndpointError(f"{self._endpoint.url}: the autopilot closed the TCP connection")
        return data

    def send(self, data: bytes) -> None:
        if self._closed:
            return
        try:
            self._sock.sendall(data)
        except OSError as exc:
            logger.debug("tcp send failed: %s", exc)

    def close(self) -> None:
        self._closed = True
        self._sock.close()


class _TcpServer:
    """Listen for one TCP client at a time; a new client replaces the old one."""

    last_sender: tuple[str, int] | None = None

    def __init__(self, endpoint: Endpoint) -> None:
        self._endpoint = endpoint
        family, addr = _resolve(endpoint, socket.SOCK_STREAM)
        self._listener = socket.socket(family, socket.SOCK_STREAM)
        try:
            self._listener.bind(addr)
            self._listener.listen(1)
        except OSError as exc:
            self._listener.close()
            raise _bind_error(endpoint, exc) from exc
        self._client: socket.socket | None = None

    @property
    def description(self) -> str:
        return self._endpoint.url

    @property
    def local_port(self) -> int:
        return int(self._listener.getsockname()[1])

    def pin_peer(self, addr: tuple[str, int]) -> None:
        """No-op for TCP."""

    def recv(self, timeout_s: float) -> bytes:
        socks = [self._listener] + ([self._client] if self._client is not None else [])
        try:
            ready, _, _ = select.select(socks, [], [], max(0.0, timeout_s))
        except (OSError, ValueError):
            return b""
        if self._listener in ready:
            try:
                client, addr = self._listener.accept()
            except OSError:
                return b""
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            if self._client is not None:
                self._client.close()
            logger.info("%s: client connected from %s:%s", self._endpoint.url, addr[0], addr[1])
            self._client = client
            return b""
        if self._client is not None and self._client in ready:
            try:
                data = self._client.recv(_MAX_DATAGRAM)
            except OSError:
                data = b""
            if not data:
                self._client.close()
                self._client = None
            return data
        return b""

    def send(self, data: bytes) -> None:
        client = self._client
        if client is None:
            return
        try:
            client.sendall(data)
        except OSError as exc:
            logger.debug("tcp send failed: %s", exc)

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
        self._listener.close()


class _Serial:
    last_sender: tuple[str, int] | None = None

    def __init__(self, endpoint: Endpoint) -> None:
        import serial  # pyserial; only needed for serial links

        self._endpoint = endpoint
        try:
            self._port = serial.Serial(endpoint.device, endpoint.baud, timeout=0, write_timeout=1.0, exclusive=True)
        except serial.SerialException as exc:
            cause = exc.__cause__ or exc.__context__
            errno_ = getattr(exc, "errno", None) or getattr(cause, "errno", None)
            if errno_ == errno.ENOENT:
                fix = "check the cable and the device name (ls /dev/serial/by-id/)"
                problem = "does not exist"
            elif errno_ == errno.EACCES:
                fix = "add yourself to the 'dialout' group and log in again"
                problem = "is not accessible (permission denied)"
            elif errno_ in (errno.EBUSY, errno.EAGAIN):
                fix = "close the other program (MAVProxy, QGroundControl, ModemManager) that holds it"
                problem = "is in use by another program"
            else:
                fix = "check the device name, cable and permissions"
                problem = f"cannot be opened ({exc})"
            raise EndpointError(f"serial device {endpoint.device} {problem}; {fix}") from exc
        self._serial_exception = serial.SerialException

    @property
    def description(self) -> str:
        return self._endpoint.url

    @property
    def local_port(self) -> int:
        return 0

    def pin_peer(self, addr: tuple[str, int]) -> None:
        """No-op for serial."""

    def recv(self, timeout_s: float) -> bytes:
        try:
            fd = self._port.fileno()
            ready, _, _ = select.select([fd], [], [], max(0.0, timeout_s))
            if not ready:
                return b""
            return bytes(self._port.read(max(1, self._port.in_waiting)))
        except (OSError, ValueError, self._serial_exception) as exc:
            raise EndpointError(f"serial device {self._endpoint.device} stopped answering ({exc})") from exc

    def send(self, data: bytes) -> None:
        try:
            self._port.write(data)
        except (OSError, self._serial_exception) as exc:
            logger.debug("serial write failed: %s", exc)

    def close(self) -> None:
        self._port.close()
