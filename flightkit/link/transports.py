"""The byte transports behind MAVLink connection strings (:mod:`flightkit.link.endpoints`):
UDP in and out, TCP client and server, serial.

A transport moves raw bytes; framing and signing are pymavlink's job in
:mod:`flightkit.link.mavlink`. Transports are used from one reader thread (``recv``) and
any number of writer threads (``send`` is serialised by the caller).
"""

from __future__ import annotations

import errno
import logging
import select
import socket
from typing import Protocol

from flightkit.errors import EndpointError
from flightkit.link.endpoints import Endpoint, EndpointKind

__all__ = [
    "Transport",
    "open_transport",
]

logger = logging.getLogger(__name__)

_MAX_DATAGRAM = 65535
_UDP_RCVBUF_BYTES = 1 << 20  # room for a fleet's telemetry while the reader waits for the GIL
_DRAIN_DATAGRAMS = 64  # datagrams one recv() returns at most (one parse, one wake for the batch)


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
