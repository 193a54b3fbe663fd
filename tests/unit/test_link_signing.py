"""MAVLink 2 signing: key parsing, timestamps, and sign/verify between two codecs (no sockets)."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from flightkit.errors import ConfigError, LinkError
from flightkit.link.signing import (
    SIGNING_EPOCH_NS,
    SigningSettings,
    apply_signing,
    parse_signing_key,
    setup_signing_message,
    signing_timestamp,
)

KEY_HEX = "00112233445566778899aabbccddeeff" * 2
NOW_NS = 1_700_000_000_000_000_000


def test_key_parsing() -> None:
    assert parse_signing_key("") is None
    assert parse_signing_key(KEY_HEX) == bytes.fromhex(KEY_HEX)
    with pytest.raises(ConfigError, match="link.signing_key_hex: not a hex string; give 64 hex digits"):
        parse_signing_key("zz" * 32, source="lab.toml")
    with pytest.raises(ConfigError, match=r"lab.toml: link.signing_key_hex: 8 hex digits \(4 bytes\)"):
        parse_signing_key("deadbeef", source="lab.toml")


def test_settings_hide_the_key() -> None:
    s = SigningSettings(bytes(32), link_id=7)
    assert "00" not in repr(s) and "link_id=7" in repr(s)
    with pytest.raises(LinkError, match="32 bytes, got 16"):
        SigningSettings(bytes(16))
    with pytest.raises(LinkError, match="link_id must be 0-255, got 256"):
        SigningSettings(bytes(32), link_id=256)


def test_timestamp_units() -> None:
    assert signing_timestamp(SIGNING_EPOCH_NS) == 0
    assert signing_timestamp(SIGNING_EPOCH_NS + 1_000_000_000) == 100_000  # 10 us units


def _codec(key: bytes | None) -> mavlink2.MAVLink:
    mav = mavlink2.MAVLink(None, 1, 1)
    mav.robust_parsing = True
    if key is not None:
        apply_signing(mav, SigningSettings(key, 1), NOW_NS)
    return mav


def _deliver(sender: mavlink2.MAVLink, receiver: mavlink2.MAVLink) -> str:
    msg = mavlink2.MAVLink_heartbeat_message(2, 12, 0, 0, 4, 3)
    buf = bytes(msg.pack(sender))
    if sender.signing.sign_outgoing:
        sender.signing.timestamp += 1
    out = receiver.parse_buffer(buf) or []
    return out[0].get_type() if out else "nothing"


def test_signed_packets_verify_and_others_are_rejected() -> None:
    key = bytes.fromhex(KEY_HEX)
    receiver = _codec(key)
    assert _deliver(_codec(key), receiver) == "HEARTBEAT"
    assert _deliver(_codec(None), _codec(key)) == "BAD_DATA"  # unsigned
    assert _deliver(_codec(bytes(32)), _codec(key)) == "BAD_DATA"  # wrong key


def test_setup_signing_message_carries_the_key() -> None:
    settings = SigningSettings(bytes(range(32)), link_id=2)
    msg = setup_signing_message(mavlink2, settings, 1, 1, NOW_NS)
    assert list(msg.secret_key) == list(range(32))
    assert msg.initial_timestamp == signing_timestamp(NOW_NS)
