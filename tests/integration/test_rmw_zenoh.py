"""An rmw_zenoh robot with no relay: zenoh-ros2-sdk publishes through a Zenoh router on
loopback, swanky-host (connected to the router, rmw_zenoh input on by default) logs it."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from tests.integration import rmw_publisher as robot
from tests.integration.procs import command, free_port, running
from tests.integration.router import router_command, wait_for_port
from tests.rrd import entity_rows

pytestmark = pytest.mark.integration


def test_host_logs_an_rmw_zenoh_robot_without_relay(tmp_path: Path) -> None:
    port = free_port()
    out = tmp_path / "rmw.rrd"
    host = command("host_bridge.cli", "-e", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting",
                   "--robot", "base", "--save", str(out), "--until-idle", "4", "--duration", "90")
    with running(router_command(port)):
        wait_for_port(port)
        with running(command("tests.integration.rmw_publisher", str(port))) as publisher, \
                running(host) as host_proc:
            assert publisher.wait(timeout=90) == 0, publisher.stderr.read() if publisher.stderr else ""
            assert host_proc.wait(timeout=90) == 0, host_proc.stderr.read() if host_proc.stderr else ""
    rows = entity_rows(out)

    # /pupper/scan from a node in /pupper: robot "pupper", topic /scan (Humble key form).
    scans = rows["/pupper/scan"]
    assert [r["ros_time"] for r in scans] == [
        (robot.STAMP_SEC + i) * 10**9 for i in range(robot.COUNT)
    ]
    for i, row in enumerate(scans):
        ranges = np.asarray(robot.SCAN_RANGES) + i
        angles = np.arange(len(ranges)) * robot.ANGLE_INCREMENT
        expected = np.stack([ranges * np.cos(angles), ranges * np.sin(angles), 0 * ranges], axis=1)
        np.testing.assert_allclose(np.asarray(row["Points3D:positions"]), expected, atol=1e-5)
        assert row["CoordinateFrame:frame"] == ["pupper/laser"]
        # log_time is the publisher's source timestamp (attachment), received just after.
        assert 0 <= row["receive_time"] - row["log_time"] < 10 * 10**9

    # /tf from the same node (Jazzy key form): robot "pupper", frames prefixed.
    transforms = rows["/pupper/tf"]
    assert len(transforms) == robot.COUNT
    for i, row in enumerate(transforms):
        assert row["ros_time"] == (robot.STAMP_SEC + i) * 10**9
        assert row["Transform3D:parent_frame"] == ["pupper/odom"]
        assert row["Transform3D:child_frame"] == ["pupper/base_link"]
        x, y, z = robot.TRANSLATION
        np.testing.assert_allclose(row["Transform3D:translation"][0], [x + i, y, z])
        np.testing.assert_allclose(
            row["Transform3D:quaternion"][0],
            [0.0, 0.0, math.sin(robot.YAW / 2), math.cos(robot.YAW / 2)], atol=1e-7,
        )

    # A node without namespace belongs to the --robot robot.
    assert [r["Scalars:scalars"] for r in rows["/base/voltage"]] == [
        [12.0 + i] for i in range(robot.COUNT)
    ]
    # Both robots came and went (liveliness), as lines of /_swanky/robots.
    lines = sorted(r["TextLog:text"][0] for r in rows["/_swanky/robots"])
    assert lines == [
        "robot base joined (rmw_zenoh)", "robot base left (rmw_zenoh)",
        "robot pupper joined (rmw_zenoh)", "robot pupper left (rmw_zenoh)",
    ]
