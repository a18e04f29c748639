"""Robot models over the wire: meshes fetched from the robot's relay, two TurtleBots side by side.

Two relay processes (tb1, tb2) replay bags with the same burger URDF and frame names but their
own wheel angles and odometry, and serve the meshes (``--package-path``); one host, with no
package path and no ROS environment, records both. One run serves every test here.
"""

from __future__ import annotations

from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh

from host_bridge.cli import main as host_main
from tests.integration.procs import command, free_port, running
from tests.integration.robot_bags import (
    PACKAGE,
    START_NS,
    WHEELS,
    Entry,
    Lines,
    burger_urdf,
    joint_state,
    package_dir,
    string,
    tf_message,
    transform,
    write_bag,
)
from tests.rrd import entity_rows

pytestmark = pytest.mark.integration

ROBOTS = ("tb1", "tb2")
STEPS = 10
STEP_NS = 100_000_000
MISSING_URI = f"package://{PACKAGE}/meshes/missing.stl"
# An extra link whose mesh the relay does not have: it must cost that visual and nothing else.
EXTRA_LINK = f"""
  <joint name="extra_joint" type="fixed">
    <parent link="base_link"/><child link="extra_link"/><origin xyz="0 0 0.3" rpy="0 0 0"/>
  </joint>
  <link name="extra_link">
    <visual><geometry><mesh filename="{MISSING_URI}"/></geometry></visual>
  </link>
</robot>"""
MESHES = {
    "base_link": "meshes/bases/burger_base.stl",
    "wheel_left_link": "meshes/wheels/left_tire.stl",
    "wheel_right_link": "meshes/wheels/right_tire.stl",
    "base_scan": "meshes/sensors/lds.stl",
}


def wheel_angles(robot: str, step: int) -> tuple[float, float]:
    if robot == "tb1":
        return 0.1 * step, -0.05 * step
    return 0.2 + 0.3 * step, 0.25 * step


def odom_x(robot: str, step: int) -> float:
    return 0.02 * step if robot == "tb1" else -0.5 - 0.03 * step


def robot_bag(path: Path, urdf: str, robot: str) -> Path:
    entries = [Entry("/robot_description", "std_msgs/msg/String", 0, string(urdf), 1)]
    for step in range(STEPS):
        offset = 500_000_000 + step * STEP_NS
        entries.append(Entry("/joint_states", "sensor_msgs/msg/JointState", offset,
                             joint_state(START_NS + offset, wheel_angles(robot, step))))
        odom = transform(START_NS + offset, "odom", "base_footprint", (odom_x(robot, step), 0.0, 0.0))
        entries.append(Entry("/tf", "tf2_msgs/msg/TFMessage", offset, tf_message(odom)))
    return write_bag(path, entries)


@dataclass(frozen=True, slots=True)
class Run:
    rows: dict[str, list[dict[str, Any]]]
    package: Path
    relay_logs: dict[str, str]


@pytest.fixture(scope="module")
def run(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Run:
    tmp = tmp_path_factory.mktemp("robot_model_live")
    package = package_dir(shared_data)
    urdf = burger_urdf(shared_data).replace("</robot>", EXTRA_LINK)
    ports = {robot: free_port() for robot in ROBOTS}
    out = tmp / "two_robots.rrd"
    with ExitStack() as stack, pytest.MonkeyPatch.context() as env:
        # The host must not find the meshes itself.
        for variable in ("ROS_PACKAGE_PATH", "AMENT_PREFIX_PATH"):
            env.delenv(variable, raising=False)
        logs = {}
        for robot in ROBOTS:
            bag = robot_bag(tmp / f"{robot}_bag", urdf, robot)
            relay = stack.enter_context(running(command(
                "robot_relay.cli", "--robot", robot, "--bag", str(bag), "--rate", "1",
                "--package-path", f"{PACKAGE}={package}", "--wait-for-host", "60", "--hold", "inf",
                "-l", f"tcp/127.0.0.1:{ports[robot]}", "--no-multicast-scouting",
            )))
            logs[robot] = Lines(relay)
        for lines in logs.values():
            lines.wait_for("topics from", timeout=60)
        endpoints = [arg for robot in ROBOTS for arg in ("-e", f"tcp/127.0.0.1:{ports[robot]}")]
        assert host_main([*endpoints, "--no-multicast-scouting", "--save", str(out),
                          "--until-idle", "3", "--duration", "60"]) == 0
        for lines in logs.values():
            lines.wait_for("replay finished", timeout=30)
    return Run(entity_rows(out), package, {robot: lines.text for robot, lines in logs.items()})


def test_every_mesh_comes_from_the_robot_vertex_for_vertex(run: Run) -> None:
    for robot in ROBOTS:
        for link, relpath in MESHES.items():
            rows = run.rows[f"/{robot}/robot_model/{link}/visual_0"]
            assert rows[0]["static"]
            assert rows[0]["CoordinateFrame:frame"] == [f"{robot}/{link}"]
            stl = trimesh.load_mesh(run.package / relpath)
            expected = np.asarray(stl.vertices, np.float64) * 0.001  # the URDF's scale
            logged = np.asarray(rows[0]["Mesh3D:vertex_positions"], np.float64)
            assert logged.shape == expected.shape
            np.testing.assert_allclose(logged, expected, rtol=0, atol=1e-7)
            assert len(rows[0]["Mesh3D:triangle_indices"]) == len(stl.faces)
        model = f"/{robot}/robot_model/"
        visuals = {path for path in run.rows if path.startswith(model) and "/visual_" in path}
        assert visuals == {f"/{robot}/robot_model/{link}/visual_0" for link in MESHES}


def test_a_refused_file_is_one_warning_naming_robot_and_uri(run: Run) -> None:
    warnings = [
        text
        for row in run.rows["/_swanky/warnings"]
        for text in row.get("TextLog:text") or []
        if MISSING_URI in text
    ]
    for robot in ROBOTS:
        mine = [text for text in warnings if text.startswith(f"[{robot}] /robot_description")]
        assert len(mine) == 1, warnings
        assert f"robot {robot} refused {MISSING_URI} (not_found:" in mine[0]
        assert "link 'extra_link'" in mine[0]
        assert f"/{robot}/robot_model/extra_link/visual_0" not in run.rows


def quaternion_product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ])


def wheel_angle(quaternion: list[float]) -> float:
    """Angle about the wheel axis: the burger's wheel joints have rpy (-1.57 0 0), axis z."""
    origin = np.array([np.sin(-1.57 / 2), 0.0, 0.0, np.cos(-1.57 / 2)])
    conjugate = origin * np.array([-1.0, -1.0, -1.0, 1.0])
    x, y, z, w = quaternion_product(conjugate, np.asarray(quaternion, np.float64))
    assert abs(x) < 1e-6
    assert abs(y) < 1e-6
    return float(2.0 * np.arctan2(z, w))


def test_two_robots_keep_their_own_joints_and_odometry(run: Run) -> None:
    for robot in ROBOTS:
        stamps = [START_NS + 500_000_000 + step * STEP_NS for step in range(STEPS)]
        for index, joint in enumerate(WHEELS):
            rows = run.rows[f"/{robot}/robot_model/joints/{joint}"]
            moving = [row for row in rows if not row["static"]]
            assert [row["ros_time"] for row in moving] == stamps
            assert moving[0]["Transform3D:child_frame"] == [f"{robot}/{joint.replace('joint', 'link')}"]
            assert moving[0]["Transform3D:parent_frame"] == [f"{robot}/base_link"]
            angles = [wheel_angle(row["Transform3D:quaternion"][0]) for row in moving]
            expected = [wheel_angles(robot, step)[index] for step in range(STEPS)]
            np.testing.assert_allclose(angles, expected, atol=1e-5)
        odom = run.rows[f"/{robot}/tf"]
        assert [row["Transform3D:child_frame"] for row in odom] == [[f"{robot}/base_footprint"]] * STEPS
        assert [row["Transform3D:parent_frame"][0] for row in odom] == [f"{robot}/odom"] * STEPS
        xs = [row["Transform3D:translation"][0][0] for row in odom]
        np.testing.assert_allclose(xs, [odom_x(robot, step) for step in range(STEPS)], atol=1e-6)
    # Neither relay was asked for the other's files or refused a request it could serve.
    for robot in ROBOTS:
        assert "Traceback" not in run.relay_logs[robot]
