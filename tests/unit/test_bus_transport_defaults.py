"""flightkit's Zenoh transport defaults: applied to every config, unless the user's file sets the key."""

from __future__ import annotations

import json
from pathlib import Path

from flightkit.bus.session import DROP_WAIT_US, build_zenoh_config
from flightkit.config import BusConfig

WAIT_KEY = "transport/link/tx/queue/congestion_control/drop/wait_before_drop"
QUEUE_KEY = "transport/link/tx/queue/size/data"


def value(conf: object, key: str) -> object:
    return json.loads(conf.get_json(key))  # type: ignore[attr-defined]


def test_defaults_raise_the_drop_wait_and_the_data_queue() -> None:
    conf = build_zenoh_config(BusConfig())
    assert value(conf, WAIT_KEY) == DROP_WAIT_US == 20_000
    assert value(conf, QUEUE_KEY) == 16
    # Shorter than one frame period of a 30 Hz camera: a congested link still drops.
    assert DROP_WAIT_US < 1e6 / 30


def test_a_user_file_that_sets_the_keys_wins(tmp_path: Path) -> None:
    f = tmp_path / "zenoh.json5"
    f.write_text(
        "{ transport: { link: { tx: { queue: { size: { data: 4 },"
        " congestion_control: { drop: { wait_before_drop: 3000 } } } } } } }"
    )
    conf = build_zenoh_config(BusConfig(zenoh_config_file=str(f)))
    assert value(conf, WAIT_KEY) == 3000
    assert value(conf, QUEUE_KEY) == 4


def test_a_user_file_that_is_silent_gets_the_defaults(tmp_path: Path) -> None:
    f = tmp_path / "zenoh.json5"
    f.write_text('{ scouting: { multicast: { enabled: false } } }')
    conf = build_zenoh_config(BusConfig(zenoh_config_file=str(f)))
    assert value(conf, WAIT_KEY) == DROP_WAIT_US
    assert value(conf, QUEUE_KEY) == 16
