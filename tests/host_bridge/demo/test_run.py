"""``--demo --robots N``: the fleet's names, the live filter that admits them, and clear errors."""

from __future__ import annotations

import re

import pytest

from host_bridge.cli import host_options, parse_args
from host_bridge.demo.run import configure_demo, demo_robot_names
from host_bridge.errors import ConfigError
from host_bridge.inputs.zenoh import robot_matches


def test_robot_count_names_the_fleet() -> None:
    assert demo_robot_names("*") == ["sim"]  # --robots left at its live default
    assert demo_robot_names("1") == ["sim"]
    assert demo_robot_names("3") == ["sim", "sim2", "sim3"]
    assert demo_robot_names("25")[-2:] == ["sim24", "sim25"]  # the fleet on one PC


@pytest.mark.parametrize("value", ["abc", "0", "-2", "26", "2.5", "tb$*"])
def test_robots_must_be_a_count_with_demo(value: str) -> None:
    with pytest.raises(ConfigError, match=rf"--robots '{re.escape(value)}'.*number of simulated robots"):
        demo_robot_names(value)


def test_configure_demo_listens_on_loopback_for_its_own_robots() -> None:
    options = host_options(
        parse_args(["--demo", "--robots", "3", "--save", "x.rrd", "-l", "tcp/127.0.0.1:7447"])
    )
    demo = configure_demo(options.robots)
    zenoh = demo.host_zenoh(options.zenoh)
    assert list(demo.robots) == ["sim", "sim2", "sim3"]
    assert all(robot_matches(name, demo.robot_filter) for name in demo.robots)
    assert not robot_matches("tb3", demo.robot_filter)
    assert zenoh.listen[0] == "tcp/127.0.0.1:7447"
    assert zenoh.listen[1] == demo.endpoint
    assert demo.endpoint.startswith("tcp/127.0.0.1:")
    assert not zenoh.multicast_scouting
