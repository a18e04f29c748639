"""Host-side SLAM live: real rclpy publishers (a TurtleBot's drivers: /scan, drifting /odom,
/tf_static) -> swanky-relay -> Zenoh -> swanky-host --slam, on loopback. The map grows while the
robot drives, and the host's trajectory follows the truth while the robot's odometry drifts."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest

from tests.host_bridge.slam.robot_logs import LaserLog, simulate
from tests.integration.procs import command, free_port, running
from tests.integration.robot_bags import Lines
from tests.integration.test_ros2_live import ros_environment, stop
from tests.rrd import entity_rows

pytestmark = [
    pytest.mark.integration,
    pytest.mark.skipif(
        not all(__import__("importlib").util.find_spec(name) for name in ("rclpy", "gtsam")),
        reason="needs rclpy ([ros-test]: CPython 3.11 on x86-64 Linux) and gtsam ([slam])",
    ),
]

__all__ = ["ros_environment"]  # the fixture, shared with the other live ROS tests
SECONDS = 40.0
ROBOT = "tb3"


def test_the_map_grows_while_a_real_ros_robot_drives_and_the_trajectory_follows_the_truth(
    ros_environment: None, tmp_path: Path,
) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    out = tmp_path / "live.rrd"
    maps = tmp_path / "maps"
    relay_cmd = command("robot_relay.cli", "--robot", ROBOT, "-l", endpoint, "--no-multicast-scouting")
    host_cmd = command("host_bridge.cli", "-e", endpoint, "--no-multicast-scouting", "--no-rmw-zenoh",
                       "--slam", "--save-map", str(maps), "--save", str(out))
    with running(relay_cmd) as relay, running(host_cmd) as host:
        relay_lines, host_lines = Lines(relay), Lines(host)
        with running(command("tests.integration.ros_robot", "laser", str(SECONDS))) as robot:
            robot_lines = Lines(robot)
            robot_lines.wait_for("ros_laser_robot: done", timeout=SECONDS + 60)
            robot.wait(timeout=30)
        host_lines.wait_for(f"robot {ROBOT} joined", timeout=5)
        stopped = stop(host, host_lines)
        stop(relay, relay_lines)
    assert stopped.returncode == 0, stopped.stderr[-3000:]
    rows = entity_rows(out)
    grids = rows[f"/{ROBOT}/slam/map"]
    known = [sum(1 for cell in row["GridMap:data"][0] if cell != 255) for row in grids]
    # A map every second of robot time, each knowing more of the apartment than the first.
    assert len(grids) >= SECONDS / 2
    assert known[-1] > 2 * known[0]  # measured: 7,260 cells known after the first scan, 18,004 at the end
    assert sum(b > a for a, b in itertools.pairwise(known)) > len(known) / 2
    # The saved trajectory against the truth at the scans that were mapped.
    truth = {s.stamp_ns: s.truth for s in simulate(LaserLog(seconds=SECONDS)).scans}
    tum = np.loadtxt(maps / ROBOT / "trajectory.tum")
    assert len(tum) > 0.8 * len(truth)
    stamps = [round(t * 1e9 / 1e6) * 1_000_000 for t in tum[:, 0]]
    expected = np.array([truth[s][:2] for s in stamps])
    error = np.hypot(*(tum[:, 1:3] - expected).T)
    assert math.sqrt(float(np.mean(error**2))) < 0.05
    assert len(rows[f"/{ROBOT}/slam/map_to_odom"]) == len(tum)
