"""Connection-string parsing (no sockets opened here; see tests/integration/test_link_mavlink.py)."""

from __future__ import annotations

import pytest

from flightkit.errors import EndpointError
from flightkit.link.endpoints import Endpoint, EndpointKind, parse_endpoint


@pytest.mark.parametrize(
    ("url", "kind", "host", "port"),
    [
        ("udpin:0.0.0.0:14540", EndpointKind.UDP_IN, "0.0.0.0", 14540),
        ("udp:127.0.0.1:14550", EndpointKind.UDP_IN, "127.0.0.1", 14550),
        ("udpin://:14540", EndpointKind.UDP_IN, "0.0.0.0", 14540),
        ("udpout:127.0.0.1:14540", EndpointKind.UDP_OUT, "127.0.0.1", 14540),
        ("udpout://192.168.1.20:14555", EndpointKind.UDP_OUT, "192.168.1.20", 14555),
        ("tcp:localhost:5760", EndpointKind.TCP_CLIENT, "localhost", 5760),
        ("tcpout://10.0.0.2:5760", EndpointKind.TCP_CLIENT, "10.0.0.2", 5760),
        ("tcpin:0.0.0.0:5760", EndpointKind.TCP_SERVER, "0.0.0.0", 5760),
        ("udpin:127.0.0.1:0", EndpointKind.UDP_IN, "127.0.0.1", 0),
        ("udpout:[::1]:14540", EndpointKind.UDP_OUT, "::1", 14540),
        ("  UDPOUT:127.0.0.1:14540 ", EndpointKind.UDP_OUT, "127.0.0.1", 14540),
    ],
)
def test_network_forms(url: str, kind: EndpointKind, host: str, port: int) -> None:
    ep = parse_endpoint(url)
    assert (ep.kind, ep.host, ep.port) == (kind, host, port)
    assert parse_endpoint(ep.url) == ep  # the canonical form parses back to the same endpoint


@pytest.mark.parametrize(
    ("url", "device", "baud"),
    [
        ("/dev/ttyACM0:57600", "/dev/ttyACM0", 57600),
        ("serial:/dev/ttyUSB0:921600", "/dev/ttyUSB0", 921600),
        ("serial:///dev/ttyUSB0:115200", "/dev/ttyUSB0", 115200),
        (
            "/dev/serial/by-id/usb-Holybro_Pixhawk6C-if00:921600",
            "/dev/serial/by-id/usb-Holybro_Pixhawk6C-if00",
            921600,
        ),
        ("/dev/ttyTHS1", "/dev/ttyTHS1", 230400),  # baud from link.baud
        ("COM3:57600", "COM3", 57600),
    ],
)
def test_serial_forms(url: str, device: str, baud: int) -> None:
    ep = parse_endpoint(url, default_baud=230400)
    assert (ep.kind, ep.device, ep.baud) == (EndpointKind.SERIAL, device, baud)
    assert parse_endpoint(ep.url) == ep


def test_mavsdk_urls() -> None:
    assert parse_endpoint("udp:0.0.0.0:14540").to_mavsdk_url() == "udpin://0.0.0.0:14540"
    assert parse_endpoint("udpout:127.0.0.1:14540").to_mavsdk_url() == "udpout://127.0.0.1:14540"
    assert parse_endpoint("tcp:127.0.0.1:5760").to_mavsdk_url() == "tcpout://127.0.0.1:5760"
    assert parse_endpoint("tcpin:0.0.0.0:5760").to_mavsdk_url() == "tcpin://0.0.0.0:5760"
    assert parse_endpoint("/dev/ttyACM0:57600").to_mavsdk_url() == "serial:///dev/ttyACM0:57600"
    assert Endpoint(EndpointKind.UDP_IN, "0.0.0.0", 14540).listens


@pytest.mark.parametrize(
    ("url", "says"),
    [
        ("", "empty connection string"),
        ("127.0.0.1:14540", "unknown scheme '127.0.0.1'"),
        ("http://127.0.0.1:14540", "unknown scheme 'http'"),
        ("udpout:127.0.0.1", "has no port"),
        ("udpout::14540", "has no host"),
        ("udpout:127.0.0.1:0", "out of range; use 1-65535"),
        ("udpin:0.0.0.0:70000", "out of range; use 0-65535"),
        ("udpout:127.0.0.1:fourteen", "is not a number"),
        ("tcp:no such host:5760", "is not an IP address or host name"),
        ("serial:ttyUSB0:57600", "is not a serial device"),
        ("/dev/ttyACM0:", "missing baud rate"),
        ("/dev/ttyACM0:300", "baud rate 300"),
        ("/dev/ttyACM0:9000000", "out of range"),
    ],
)
def test_malformed_strings_say_what_to_write(url: str, says: str) -> None:
    with pytest.raises(EndpointError) as info:
        parse_endpoint(url)
    message = str(info.value)
    assert says in message
    assert message.count("\n") == 0
    assert any(w in message for w in ("write", "use", "give")), message  # always says what to do


def test_a_udp_read_takes_the_queued_datagrams_of_one_sender() -> None:
    """One recv() returns every datagram already queued from one sender (one parse, one wake for a
    burst of telemetry); another sender's datagram waits for the next call, so replies still go
    to whoever sent."""
    import socket

    from flightkit.link.transports import open_transport

    transport = open_transport(parse_endpoint("udpin:127.0.0.1:0"))
    a, b = socket.socket(socket.AF_INET, socket.SOCK_DGRAM), socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        to = ("127.0.0.1", transport.local_port)
        for data in (b"a1", b"a2", b"a3"):
            a.sendto(data, to)
        b.sendto(b"b1", to)
        a.sendto(b"a4", to)
        assert transport.recv(1.0) == b"a1a2a3" and transport.last_sender == ("127.0.0.1", a.getsockname()[1])
        assert transport.recv(1.0) == b"b1" and transport.last_sender == ("127.0.0.1", b.getsockname()[1])
        assert transport.recv(1.0) == b"a4"
        assert transport.recv(0.01) == b""
    finally:
        a.close()
        b.close()
        transport.close()
