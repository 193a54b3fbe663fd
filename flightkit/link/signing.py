"""MAVLink 2 message signing.

With signing on, every packet we send carries a 13-byte signature block (link id, a
48-bit timestamp in units of 10 microseconds since 2015-01-01 00:00 UTC, and the first
6 bytes of SHA-256 over key + packet), and every packet we receive must carry a valid
signature made with the same 32-byte key; unsigned packets and packets signed with another
key are dropped. pymavlink implements the cryptography; this module turns config into
that state and builds the SETUP_SIGNING message that provisions a key on an autopilot.

The key lives in config as 64 hex digits (``link.signing_key_hex``). Generate one with
``python -c "import secrets; print(secrets.token_hex(32))"``; see ``docs/hardware.md``
for putting it on the vehicle.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from flightkit.errors import ConfigError, LinkError

if TYPE_CHECKING:
    from flightkit.link.mavlink.encoding import MavlinkMessage

__all__ = [
    "SIGNING_EPOCH_NS",
    "SigningSettings",
    "apply_signing",
    "parse_signing_key",
    "setup_signing_message",
    "signing_timestamp",
]

logger = logging.getLogger(__name__)

SIGNING_EPOCH_NS = 1_420_070_400_000_000_000  # 2015-01-01T00:00:00Z
_KEY_LEN = 32


@dataclass(frozen=True, slots=True, repr=False)
class SigningSettings:
    """Signing state for one link.

    Attributes:
        key: the 32-byte secret key.
        link_id: our link id (0-255), part of every signature; pick distinct ids for
            several links of one system.
    """

    key: bytes
    link_id: int = 1

    def __post_init__(self) -> None:
        if len(self.key) != _KEY_LEN:
            raise LinkError(
                f"a MAVLink signing key has {_KEY_LEN} bytes, got {len(self.key)}; "
                "decode link.signing_key_hex (64 hex digits) with parse_signing_key"
            )
        if not 0 <= self.link_id <= 255:
            raise LinkError(
                f"signing link_id must be 0-255, got {self.link_id}; pick a distinct id in that range per link",
            )

    def __repr__(self) -> str:  # never print the key
        return f"SigningSettings(key=<{len(self.key)} bytes>, link_id={self.link_id})"


def parse_signing_key(
    key_hex: str, *, source: str = "<config>", key: str = "link.signing_key_hex"
) -> bytes | None:
    """Decode ``link.signing_key_hex``: None when empty (signing off), else 32 bytes.

    Raises:
        ConfigError: not 64 hex digits.
    """
    text = key_hex.strip()
    if not text:
        return None
    try:
        raw = bytes.fromhex(text)
    except ValueError:
        raise ConfigError(
            source,
            key,
            "not a hex string",
            "give 64 hex digits, e.g. from: python -c 'import secrets; print(secrets.token_hex(32))'",
        ) from None
    if len(raw) != _KEY_LEN:
        raise ConfigError(
            source,
            key,
            f"{len(text)} hex digits ({len(raw)} bytes)",
            f"give exactly {2 * _KEY_LEN} hex digits ({_KEY_LEN} bytes)",
        )
    return raw


def signing_timestamp(time_ns: int) -> int:
    """MAVLink signing timestamp (10 us units since 2015-01-01) for a Unix time in ns."""
    return max(0, (int(time_ns) - SIGNING_EPOCH_NS) // 10_000)


def apply_signing(mav: Any, settings: SigningSettings, time_ns: int) -> None:
    """Turn signing on for a pymavlink ``MAVLink`` object.

    Outgoing packets are signed; incoming packets are accepted only with a valid signature
    from ``settings.key`` (no unsigned exceptions).
    """
    mav.signing.secret_key = settings.key
    mav.signing.link_id = settings.link_id
    mav.signing.timestamp = signing_timestamp(time_ns)
    mav.signing.sign_outgoing = True
    mav.signing.allow_unsigned_callback = None


def setup_signing_message(
    mavlink_module: Any, settings: SigningSettings, target_system: int, target_component: int, time_ns: int
) -> MavlinkMessage:
    """A SETUP_SIGNING message that installs ``settings.key`` on the autopilot.

    Send it once over a trusted link (USB) before turning signing on; the autopilot stores
    the key (ArduPilot persists it; PX4 stores it in its key file).
    """
    msg: MavlinkMessage = mavlink_module.MAVLink_setup_signing_message(
        target_system, target_component, list(settings.key), signing_timestamp(time_ns)
    )
    return msg
