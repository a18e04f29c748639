"""Latched topics reach hosts that start after they were sent, and again after a host restart.

One relay replays a bag of /robot_description, two /tf_static messages from two publishers
(different child frames) and a /map, then keeps serving them (``--hold``). Two host runs, both
started after the replay ended, must each get both static transforms, the model (meshes
fetched from the relay) and the map.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from host_bridge.cli import main as host_main
from tests.integration.procs import command, free_port, running
from tests.integration.robot_bags import (
    PACKAGE,
    START_NS,
    Entry,
    Lines,
    burger_urdf,
    occupancy_grid,
    package_dir,
    string,
    tf_message,
    transform,
    write_bag,
)
from tests.rrd import entity_rows

pytestmark = pytest.mark.integration

ROBOT = "tb"
# (parent, child, translation, yaw) per /tf_static publisher. The second repeats the URDF's
# fixed joint base_footprint -> base_link (z 0.010), as robot_state_publisher would.
CAMERA = ("base_link", "camera_link", (0.05, 0.0, 0.2), 0.5)
BASE = ("base_footprint", "base_link", (0.0, 0.0, 0.010), 0.0)
LASER_MOUNT = ("base_scan", "laser_mount", (0.0, 0.01, 0.03), -1.0)
MAP_CELLS = [0, 100, -1, 50, 0, 0, 100, 100, -1, -1, 0, 25]


def latched_bag(path: Path, urdf: str) -> Path:
    first = tf_message(transform(START_NS, *CAMERA[:3], yaw=CAMERA[3]))
    second = tf_message(
        transform(START_NS, *BASE[:3], yaw=BASE[3]),
        transform(START_NS, *LASER_MOUNT[:3], yaw=LASER_MOUNT[3]),
    )
    grid = occupancy_grid(START_NS, width=4, height=3, resolution=0.5, cells=MAP_CELLS)
    return write_bag(path, [
        Entry("/robot_description", "std_msgs/msg/String", 0, string(urdf), 1),
        Entry("/tf_static", "tf2_msgs/msg/TFMessage", 100_000_000, first, 2),
        Entry("/tf_static", "tf2_msgs/msg/TFMessage", 200_000_000, second, 2),
        Entry("/map", "nav_msgs/msg/OccupancyGrid", 300_000_000, grid, 1),
    ])


def static_transform(rows: dict[str, list[dict[str, Any]]], child: str) -> tuple[Any, ...]:
    """The relation into ``child``; a URDF fixed joint may have written the same entity too,
    and every static write there must agree. A frame the host placed at the robot's root while
    no transform had reached it yet (frames.py: parent ``tf#/<robot>``, no translation) sits on
    that entity too, so that the transform replaces it: it must come before the transform."""
    statics = [row for row in rows[f"/{ROBOT}/tf_static/{child}"] if row["static"]]
    relations = [row for row in statics if row["Transform3D:parent_frame"] != [f"tf#/{ROBOT}"]]
    assert relations, statics
    assert statics[-1] is relations[-1], statics  # the viewer keeps the last
    (value,) = {
        (
            row["Transform3D:parent_frame"][0],
            row["Transform3D:child_frame"][0],
            tuple(row["Transform3D:translation"][0]),
            tuple(row["Transform3D:quaternion"][0]),
        )
        for row in relations
    }
    return value


def check_recording(rows: dict[str, list[dict[str, Any]]], package: Path) -> None:
    for parent, child, xyz, yaw in (CAMERA, BASE, LASER_MOUNT):
        logged_parent, logged_child, translation, quaternion = static_transform(rows, child)
        assert (logged_parent, logged_child) == (f"{ROBOT}/{parent}", f"{ROBOT}/{child}")
        np.testing.assert_allclose(translation, xyz, atol=1e-7)
        np.testing.assert_allclose(quaternion, [0, 0, np.sin(yaw / 2), np.cos(yaw / 2)], atol=1e-7)
    model = f"/{ROBOT}/robot_model/"
    visuals = sorted(path for path in rows if path.startswith(model) and "/visual_" in path)
    assert visuals == [f"/{ROBOT}/robot_model/{link}/visual_0"
                       for link in ("base_link", "base_scan", "wheel_left_link", "wheel_right_link")]
    base = rows[f"/{ROBOT}/robot_model/base_link/visual_0"][0]
    assert len(base["Mesh3D:vertex_positions"]) > 1000  # the burger base STL, from the relay
    assert (package / "meshes" / "bases" / "burger_base.stl").is_file()
    (grid,) = rows[f"/{ROBOT}/map"]
    assert grid["ros_time"] == START_NS
    assert grid["CoordinateFrame:frame"] == [f"{ROBOT}/map"]
    assert grid["GridMap:cell_size"] == [0.5]
    assert grid["GridMap:translation"] == [[-1.0, -2.0, 0.0]]
    assert (grid["GridMap:format"][0]["width"], grid["GridMap:format"][0]["height"]) == (4, 3)
    # ROS grid row 0 is the bottom, an image's the top; unknown (-1) is 255.
    cells = np.flipud(np.asarray(MAP_CELLS, np.int8).reshape(3, 4)).astype(np.uint8)
    assert grid["GridMap:data"] == [cells.ravel().tolist()]
    assert "/_swanky/warnings" not in rows, rows.get("/_swanky/warnings")
    # The URDF's fixed joint base_footprint -> base_link is on /tf_static too: whichever came
    # first, the relation sits on that one entity (Rerun wants one entity per relation).
    assert not any("/robot_model/joints/" in path for path in rows)
    assert static_transform(rows, "base_link")[:3] == (f"{ROBOT}/base_footprint", f"{ROBOT}/base_link",
                                                        pytest.approx(BASE[2]))


def test_late_hosts_get_static_transforms_model_and_map(shared_data: Path, tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    for variable in ("ROS_PACKAGE_PATH", "AMENT_PREFIX_PATH"):
        monkeypatch.delenv(variable, raising=False)
    package = package_dir(shared_data)
    bag = latched_bag(tmp_path / "latched_bag", burger_urdf(shared_data))
    port = free_port()
    relay = command("robot_relay.cli", "--robot", ROBOT, "--bag", str(bag), "--rate", "0",
                    "--hold", "inf", "--package-path", f"{PACKAGE}={package}",
                    "-l", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting")
    with running(relay) as relay_proc:
        lines = Lines(relay_proc)
        lines.wait_for("serving latched topics", timeout=60)  # everything was sent before any host
        for run in ("first", "restarted"):
            out = tmp_path / f"{run}.rrd"
            assert host_main(["-e", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting",
                              "--save", str(out), "--until-idle", "3", "--duration", "40"]) == 0
            check_recording(entity_rows(out), package)
        assert relay_proc.poll() is None, lines.text
