"""The rmw_zenoh input's robot naming: a topic's robot from its publishers' namespaces."""

from __future__ import annotations

from host_bridge.inputs.rmw_zenoh import namespace_robot, resolve_robot


def test_robot_from_namespace() -> None:
    assert namespace_robot("/") is None
    assert namespace_robot("/tb3") == "tb3"
    assert namespace_robot("/tb3/front") == "tb3"
    # Inside its namespace the prefix goes; /tf of a namespaced node stays /tf on that robot.
    assert resolve_robot("/tb3/scan", {"tb3"}, "robot") == ("tb3", "/scan")
    assert resolve_robot("/tf", {"tb3"}, "robot") == ("tb3", "/tf")
    # No namespace, or several robots on one topic: the --robot robot.
    assert resolve_robot("/scan", {None}, "pupper") == ("pupper", "/scan")
    assert resolve_robot("/tf", {"tb3", "tb4"}, "robot") == ("robot", "/tf")
    assert resolve_robot("/tb3/scan", {"tb3", None}, "robot") == ("tb3", "/scan")
