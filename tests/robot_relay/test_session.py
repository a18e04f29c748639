"""ZenohOptions -> the zenoh configuration the relay and host open their sessions with."""

from __future__ import annotations

import pytest

from robot_relay.errors import ConfigError
from robot_relay.session import ZenohOptions, zenoh_config


def test_options_become_zenoh_configuration_values() -> None:
    config = zenoh_config(ZenohOptions(
        mode="client", connect=("tcp/127.0.0.1:7447",), listen=("tcp/127.0.0.1:7448",),
        multicast_scouting=False, cfg=("scouting/gossip/enabled:false",),
    ))
    assert {key: config.get_json(key) for key in (
        "mode", "connect/endpoints", "listen/endpoints", "scouting/multicast/enabled",
        "scouting/gossip/enabled", "timestamping/enabled",
    )} == {
        "mode": '"client"',
        "connect/endpoints": '["tcp/127.0.0.1:7447"]',
        "listen/endpoints": '["tcp/127.0.0.1:7448"]',
        "scouting/multicast/enabled": "false",
        "scouting/gossip/enabled": "false",
        "timestamping/enabled": "true",  # zenoh-ext's AdvancedPublisher needs it
    }


def test_cfg_items_apply_last_over_the_flags() -> None:
    config = zenoh_config(ZenohOptions(mode="client", cfg=('mode:"peer"',)))
    assert config.get_json("mode") == '"peer"'


@pytest.mark.parametrize(("options", "message"), [
    (ZenohOptions(cfg=("nocolon",)), "--cfg 'nocolon': expected KEY:JSON5, e.g. 'mode:\"client\"'"),
    (ZenohOptions(cfg=("no/such/key:1",)), "zenoh configuration key 'no/such/key' = 1: "),
    (ZenohOptions(mode="bogus"), "zenoh configuration key 'mode' = \"bogus\": "),
    (ZenohOptions(config_file="/nonexistent/zenoh.json5"),
     "zenoh config file /nonexistent/zenoh.json5: "),
])
def test_a_bad_option_is_named(options: ZenohOptions, message: str) -> None:
    with pytest.raises(ConfigError) as raised:
        zenoh_config(options)
    assert str(raised.value).startswith(message)
