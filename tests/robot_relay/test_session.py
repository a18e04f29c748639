"""ZenohOptions -> the zenoh configuration the relay and host open their sessions with."""

from __future__ import annotations

from pathlib import Path

import pytest

from robot_relay.errors import ConfigError
from robot_relay.session import ZenohOptions, priority_link_endpoints, zenoh_config


def test_options_become_zenoh_configuration_values() -> None:
    config = zenoh_config(ZenohOptions(
        mode="client", connect=("tcp/127.0.0.1:7447",), listen=("tcp/127.0.0.1:7448",),
        multicast_scouting=False, priority_links=True, cfg=("scouting/gossip/enabled:false",),
    ))
    assert {key: config.get_json(key) for key in (
        "mode", "connect/endpoints", "listen/endpoints", "scouting/multicast/enabled",
        "scouting/gossip/enabled", "timestamping/enabled", "transport/unicast/max_links",
    )} == {
        "mode": '"client"',
        "connect/endpoints": '["tcp/127.0.0.1:7447?prio=0-5","tcp/127.0.0.1:7447?prio=6-7"]',
        "listen/endpoints": '["tcp/127.0.0.1:7448"]',
        "scouting/multicast/enabled": "false",
        "scouting/gossip/enabled": "false",
        "timestamping/enabled": "true",  # zenoh-ext's AdvancedPublisher needs it
        "transport/unicast/max_links": "2",  # a listener accepts a peer's priority links
    }


@pytest.mark.parametrize(("endpoint", "links"), [
    ("tcp/pc:7447", ("tcp/pc:7447?prio=0-5", "tcp/pc:7447?prio=6-7")),
    ("tls/router.lab:7447#iface=wlan0",
     ("tls/router.lab:7447?prio=0-5#iface=wlan0", "tls/router.lab:7447?prio=6-7#iface=wlan0")),
    ("tcp/pc:7447?rel=1", ("tcp/pc:7447?rel=1;prio=0-5", "tcp/pc:7447?rel=1;prio=6-7")),
    ("tcp/pc:7447?prio=1-7", ("tcp/pc:7447?prio=1-7",)),  # the user's own ranges
    ("udp/pc:7447", ("udp/pc:7447",)),  # datagrams do not queue behind each other
    ("quic/pc:7447", ("quic/pc:7447",)),
])
def test_stream_endpoints_become_a_priority_and_a_bulk_link(
    endpoint: str, links: tuple[str, ...]
) -> None:
    assert priority_link_endpoints(endpoint) == links


def test_by_default_endpoints_stay_one_link_and_peers_links_are_accepted() -> None:
    config = zenoh_config(ZenohOptions(connect=("tcp/pc:7447",)))
    assert config.get_json("connect/endpoints") == '["tcp/pc:7447"]'
    assert config.get_json("transport/unicast/max_links") == "2"


def test_max_links_of_the_zenoh_config_file_is_kept_when_higher(tmp_path: Path) -> None:
    file = tmp_path / "zenoh.json5"
    file.write_text("{transport: {unicast: {max_links: 4}}}")
    config = zenoh_config(ZenohOptions(config_file=str(file), listen=("tcp/0.0.0.0:7447",)))
    assert config.get_json("transport/unicast/max_links") == "4"
    assert config.get_json("listen/endpoints") == '["tcp/0.0.0.0:7447"]'


def test_cfg_sets_max_links_last() -> None:
    config = zenoh_config(ZenohOptions(cfg=("transport/unicast/max_links:3",)))
    assert config.get_json("transport/unicast/max_links") == "3"


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
