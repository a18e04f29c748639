"""The swanky wire input (host_bridge/inputs/zenoh.py): robot patterns."""

from __future__ import annotations

import pytest

from host_bridge.inputs.zenoh import check_robot_pattern, robot_matches


def test_robot_patterns() -> None:
    assert check_robot_pattern("east-$*") == "east-$*"
    with pytest.raises(Exception, match=r"tb\$\*"):
        check_robot_pattern("tb*")
    with pytest.raises(Exception, match="one non-empty chunk"):
        check_robot_pattern("a/b")
    assert robot_matches("east-a", "east-$*")
    assert not robot_matches("west-c", "east-$*")
    assert robot_matches("tb3", "*")
