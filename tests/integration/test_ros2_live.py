"""``swanky-relay`` against a real ROS 2 graph: rclpy and Fast DDS (ROS 2 Jazzy, the ros-jazzy PyPI
wheels of the ``[ros-test]`` extra) on loopback, through Zenoh to ``swanky-host``, read back
from the .rrd.

One run is shared by the module (about 30 s): the nodes of ``tests/integration/ros_robot.py``
publish like a small robot; the relay starts after /robot_description was published; a first
host starts once the relay holds the latched topics. During the run the relay is stopped
(SIGSTOP) five times for 0.3 s, then a node appears with a new topic and ten more nodes that log
(so /rosout gains publishers and is subscribed again) and leaves. The first host is stopped with
SIGTERM, a second host runs (a restart: the latched topics again, once), then the relay is
stopped with SIGTERM. The tests assert on what that run left behind.

By default images and clouds drop under congestion (a stale frame is worth nothing on a weak
link): the burst after each stall filled Zenoh's queue and lost frames on the loaded 2-core CI
machine. The relay here gets the config a user who wants every frame writes
(:data:`EVERY_FRAME`), and the test asserts that nothing is then lost.

The processes get what sourcing ROS sets (``AMENT_PREFIX_PATH`` = this venv, where the wheels
put the share directories), a private ``ROS_DOMAIN_ID`` and localhost-only discovery.
"""

from __future__ import annotations

import collections
import importlib.util
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray
from rerun.chunk import RrdReader

from robot_relay.wire import Catalog, catalog_key
from tests.integration import ros_robot
from tests.integration.procs import command, free_port, open_loopback, running
from tests.integration.robot_bags import Lines
from tests.rrd import entity_rows

pytestmark = [
    pytest.mark.integration,
    pytest.mark.skipif(
        importlib.util.find_spec("rclpy") is None,
        reason="rclpy is not installed: pip install -e '.[ros-test]' (the ros-jazzy wheels exist "
        "for CPython 3.11 on x86-64 Linux only)",
    ),
]

ROBOT = "tb"
STALLS = 5
STALL_S = 0.3
LATE_SECONDS = 4.0
Rows = dict[str, list[dict[str, Any]]]
EXPECTED_TOPICS = frozenset({"/scan", "/odom", "/camera/image_raw", "/points", "/arm/joint_states",
                             "/status", "/robot_description"})
EVERY_FRAME = """\
policy:
  /camera/image_raw: {congestion: block}
  /points: {congestion: block}
"""


@dataclass
class Proc:
    """What a stopped process left: exit code and stderr."""

    returncode: int | None = None
    stderr: str = ""


@dataclass
class LiveRun:
    directory: Path
    catalog: Catalog | None = None
    relay: Proc = field(default_factory=Proc)
    hosts: list[Proc] = field(default_factory=list)
    robot: str = ""
    stalls_ns: list[tuple[int, int]] = field(default_factory=list)
    late_first_ns: int = 0

    def rrd(self, run: int) -> Path:
        return self.directory / f"host{run}.rrd"


@pytest.fixture(scope="module")
def ros_environment(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """What sourcing ROS sets, for every process this module starts."""
    with pytest.MonkeyPatch.context() as env:
        env.setenv("AMENT_PREFIX_PATH", sys.prefix)
        env.setenv("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
        env.setenv("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))
        env.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        env.setenv("ROS_LOG_DIR", str(tmp_path_factory.mktemp("ros_log")))
        yield


def stop(proc: subprocess.Popen[str], lines: Lines, timeout: float = 30) -> Proc:
    proc.send_signal(signal.SIGTERM)
    proc.wait(timeout=timeout)
    time.sleep(0.2)  # the reader thread takes the last lines
    return Proc(proc.returncode, lines.text)


def query_catalog(endpoint: str) -> Catalog:
    session = open_loopback("-e", endpoint)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            for reply in session.get(catalog_key(ROBOT), timeout=5.0):
                if reply.ok is not None:
                    catalog = Catalog.from_json(reply.ok.payload.to_bytes(), catalog_key(ROBOT))
                    # Every node's topics discovered (the camera is a process of its own).
                    if {t.topic for t in catalog.topics} >= EXPECTED_TOPICS:
                        return catalog
            time.sleep(0.5)
    finally:
        session.close()
    raise AssertionError(f"no catalog with {sorted(EXPECTED_TOPICS)} from the relay within 60 s")


def host_command(endpoint: str, save: Path) -> list[str]:
    return command("host_bridge.cli", "-e", endpoint, "--no-multicast-scouting", "--no-rmw-zenoh",
                   "--save", str(save))


@pytest.fixture(scope="module")
def live(ros_environment: None, tmp_path_factory: pytest.TempPathFactory) -> LiveRun:
    run = LiveRun(tmp_path_factory.mktemp("ros2_live"))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = run.directory / "relay.yaml"
    config.write_text(EVERY_FRAME)
    relay_cmd = command("robot_relay.cli", "--robot", ROBOT, "--config", str(config), "-l", endpoint,
                        "--no-multicast-scouting")
    with running(command("tests.integration.ros_robot", "robot")) as robot, \
            running(command("tests.integration.ros_robot", "camera")) as camera:
        robot_lines, camera_lines = Lines(robot), Lines(camera)
        robot_lines.wait_for("ros_robot: publishing", timeout=60)
        camera_lines.wait_for("ros_robot: publishing", timeout=60)
        with running(relay_cmd) as relay:
            relay_lines = Lines(relay)
            relay_lines.wait_for("/robot_description: subscribed", timeout=60)
            run.catalog = query_catalog(endpoint)
            with running(host_command(endpoint, run.rrd(1))) as host:
                host_lines = Lines(host)
                relay_lines.wait_for("/odom: subscribed", timeout=60)
                time.sleep(1.0)
                for _ in range(STALLS):
                    started = time.time_ns()
                    relay.send_signal(signal.SIGSTOP)
                    time.sleep(STALL_S)
                    relay.send_signal(signal.SIGCONT)
                    run.stalls_ns.append((started, time.time_ns()))
                    time.sleep(0.5)
                with running(command("tests.integration.ros_robot", "late", str(LATE_SECONDS))) as late:
                    late_lines = Lines(late)
                    first = late_lines.wait_for("late first publish at", timeout=60)
                    run.late_first_ns = int(first.split()[-1])
                    late.wait(timeout=60)
                relay_lines.wait_for("/late_chatter vanished", timeout=20)
                time.sleep(1.0)
                run.hosts.append(stop(host, host_lines))
            with running(host_command(endpoint, run.rrd(2))) as host:
                host_lines = Lines(host)
                host_lines.wait_for(f"robot {ROBOT} joined", timeout=60)
                time.sleep(4.0)
                run.hosts.append(stop(host, host_lines))
            run.relay = stop(relay, relay_lines)
        for proc in (robot, camera):
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=30)
        run.robot = robot_lines.text + camera_lines.text
    return run


def _rows(live: LiveRun, run: int, entity: str) -> list[dict[str, Any]]:
    rows = entity_rows(live.rrd(run), entity)
    stderr = live.hosts[run - 1].stderr[-3000:]
    assert entity in rows, f"{entity} missing from host{run}.rrd; host stderr:\n{stderr}"
    return rows[entity]


def _index(ros_time: int, hz: int) -> int:
    index, rest = divmod(ros_time - ros_robot.T0_NS, 1_000_000_000 // hz)
    assert rest == 0, ros_time
    return index


def _contiguous(indices: list[int], what: str) -> None:
    assert indices == list(range(indices[0], indices[0] + len(indices))), (
        f"{what}: missing {sorted(set(range(indices[0], indices[-1] + 1)) - set(indices))}"
    )


def _arrays(path: Path, entity: str, column: str) -> list[tuple[int, NDArray[Any]]]:
    """(ros_time, flat values) of every row of a big list column, without Python lists."""
    found = []
    for chunk in RrdReader(path).stream():
        if chunk.entity_path != entity:
            continue
        batch = chunk.to_record_batch()
        times = batch.column("ros_time").cast("int64").to_pylist()
        values = batch.column(column)
        for row, at in enumerate(times):
            cell = values[row].values  # the row's one instance
            while hasattr(cell, "flatten"):
                cell = cell.flatten()
            found.append((at, cell.to_numpy(zero_copy_only=False)))
    return sorted(found, key=lambda item: item[0])


def test_qos_chosen_per_topic(live: LiveRun) -> None:
    assert live.catalog is not None
    qos = {t.topic: (t.qos.reliability, t.qos.durability, t.qos.depth) for t in live.catalog.topics}
    # Fast DDS reports depth 0 for every publisher: the queues get the floors, 100 for streams
    # (they ride out the relay's stalls and its latency budget), 10 for latched topics.
    assert qos["/scan"] == ("best_effort", "volatile", 100)
    assert qos["/odom"] == ("reliable", "volatile", 100)
    assert qos["/camera/image_raw"] == ("reliable", "volatile", 100)
    assert qos["/points"] == ("reliable", "volatile", 100)
    assert qos["/arm/joint_states"] == ("reliable", "volatile", 100)
    # A reliable and a best-effort publisher: best effort reaches both.
    assert qos["/status"] == ("best_effort", "volatile", 100)
    assert qos["/robot_description"] == ("reliable", "transient_local", 10)
    assert qos["/rosout"][:2] == ("reliable", "transient_local")
    assert "/parameter_events" not in qos  # as ros2 bag record would not need it
    types = {t.topic: t.msgtype for t in live.catalog.topics}
    assert types["/arm/joint_states"] == "sensor_msgs/msg/JointState"
    definition = next(t.definition for t in live.catalog.topics if t.topic == "/odom")
    assert definition is not None
    assert "MSG: geometry_msgs/PoseWithCovariance" in definition.text  # from the wheels' share dirs


def test_reliable_odometry_and_joints_arrive_complete_with_exact_values(live: LiveRun) -> None:
    odom = [row for row in _rows(live, 1, f"/{ROBOT}/odom") if not row["static"]]
    indices = [_index(row["ros_time"], ros_robot.ODOM_HZ) for row in odom]
    _contiguous(indices, "/odom")
    assert len(indices) >= 5 * ros_robot.ODOM_HZ
    for index, row in zip(indices, odom, strict=True):
        x, y, yaw = ros_robot.odom_values(index)
        assert row["Transform3D:translation"][0] == pytest.approx([x, y, 0.0], abs=1e-6)
        assert row["Transform3D:quaternion"][0] == pytest.approx(
            [0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)], abs=1e-6)
    joints = _rows(live, 1, f"/{ROBOT}/arm/joint_states/{ros_robot.JOINT}/position")
    indices = [_index(row["ros_time"], ros_robot.JOINT_HZ) for row in joints]
    _contiguous(indices, "/arm/joint_states")
    assert len(indices) >= 5 * ros_robot.JOINT_HZ
    assert [row["Scalars:scalars"][0] for row in joints] == pytest.approx(
        [ros_robot.joint_position(i) for i in indices], abs=1e-12)


def test_images_and_clouds_arrive_complete_and_byte_exact(live: LiveRun) -> None:
    images = _arrays(live.rrd(1), f"/{ROBOT}/camera/image_raw", "Image:buffer")
    indices = [_index(at, ros_robot.IMAGE_HZ) for at, _ in images]
    _contiguous(indices, "/camera/image_raw")
    assert len(indices) >= 5 * ros_robot.IMAGE_HZ
    for index, (_, pixels) in zip(indices, images, strict=True):
        np.testing.assert_array_equal(pixels, ros_robot.image_pixels(index))
    clouds = _arrays(live.rrd(1), f"/{ROBOT}/points", "Points3D:positions")
    indices = [_index(at, ros_robot.CLOUD_HZ) for at, _ in clouds]
    _contiguous(indices, "/points")
    assert len(indices) >= 5 * ros_robot.CLOUD_HZ
    grid = ros_robot.cloud_points()
    for index, (_, flat) in zip(indices, clouds, strict=True):
        expected = grid.copy()
        expected[0, 0] = ros_robot.first_point_x(index)
        np.testing.assert_array_equal(flat.reshape(-1, 3), expected)


def test_stalled_relay_loses_no_reliable_message(live: LiveRun) -> None:
    """Five SIGSTOPs of 0.3 s: nine odometry messages (more on a loaded machine) each time wait
    in the relay's queue."""
    odom = [row for row in _rows(live, 1, f"/{ROBOT}/odom") if not row["static"]]
    received = [row["receive_time"] for row in odom]
    assert min(received) < live.stalls_ns[0][0]
    assert max(received) > live.stalls_ns[-1][1]
    # Every stall left a hole in the relay's receive times, and nothing is missing around it
    # (contiguous indices: test_reliable_odometry_and_joints_arrive_complete_with_exact_values).
    gaps = np.diff(np.asarray(sorted(received)))
    assert int((gaps > 0.25e9).sum()) >= STALLS
    drops = entity_rows(live.rrd(1), f"/_stats/{ROBOT}/odom/ros_drops")
    assert all(row["Scalars:scalars"] == [0.0] for row in drops.get(f"/_stats/{ROBOT}/odom/ros_drops", []))
    assert "Traceback" not in live.relay.stderr


def test_topic_appearing_mid_run_is_forwarded_within_3_s_and_its_end_noticed(live: LiveRun) -> None:
    late = _rows(live, 1, f"/{ROBOT}/late_chatter")
    first = min(row["receive_time"] for row in late)
    assert 0 < first - live.late_first_ns < 3_000_000_000
    _contiguous([int(row["TextLog:text"][0].removeprefix("late ")) for row in late], "/late_chatter")
    assert "/late_chatter vanished" in live.relay.stderr


def test_rosout_lines_arrive_once_although_rosout_was_subscribed_again(live: LiveRun) -> None:
    # Sixteen nodes publish /rosout once the late ones start: the topic needs a deeper queue,
    # so the relay subscribes again and the latched history comes again; none of it goes out.
    assert "/rosout: unsubscribed (changed)" in live.relay.stderr
    texts = [row["TextLog:text"][0] for row in _rows(live, 1, f"/{ROBOT}/rosout")]
    counts = collections.Counter(texts)
    assert counts["[robot] robot up"] == 1
    helpers = [f"[late_helper_{k}] late helper {k} up" for k in range(ros_robot.LATE_NODES)]
    assert all(counts[line] == 1 for line in helpers), counts
    assert max(counts.values()) == 1, counts


def test_late_and_restarted_hosts_get_the_latched_topics_once(live: LiveRun) -> None:
    for run in (1, 2):
        for link, half_sizes in (("base_link", [0.15, 0.1, 0.05]), ("arm_link", [0.025, 0.025, 0.1])):
            (visual,) = _rows(live, run, f"/{ROBOT}/robot_model/{link}/visual_0")
            assert visual["Boxes3D:half_sizes"][0] == pytest.approx(half_sizes)
        # /rosout is latched too; the relay's cache holds its last 10 lines, each once.
        logs = collections.Counter(row["TextLog:text"][0] for row in _rows(live, run, f"/{ROBOT}/rosout"))
        assert max(logs.values()) == 1, logs
        assert len(logs) >= 10, logs
        assert _rows(live, run, f"/{ROBOT}/odom")


def test_sigterm_stops_relay_and_hosts_cleanly(live: LiveRun) -> None:
    for name, proc in [("relay", live.relay)] + [(f"host {i + 1}", h) for i, h in enumerate(live.hosts)]:
        assert proc.returncode == 0, f"{name}: exit {proc.returncode}\n{proc.stderr[-3000:]}"
        assert "Traceback" not in proc.stderr, f"{name}:\n{proc.stderr[-3000:]}"
    assert "SIGTERM: stopping" in live.relay.stderr
    assert f"robot {ROBOT}: stopped" in live.relay.stderr
    assert "published odom" in live.robot
    assert "published image" in live.robot


def test_relay_stats_count_no_reliable_drops(live: LiveRun) -> None:
    assert len(_rows(live, 1, f"/_stats/{ROBOT}/relay/cpu_percent")) >= 3
    for topic in ("odom", "camera/image_raw", "points", "arm/joint_states", "status"):
        entity = f"/_stats/{ROBOT}/{topic}/ros_drops"
        drops = entity_rows(live.rrd(1), entity).get(entity, [])
        # /status: two publishers, whose sequence numbers cannot be told apart: never counted.
        assert sum(row["Scalars:scalars"][0] for row in drops) == 0, topic


def test_sigint_stops_the_relay_cleanly_and_a_second_signal_at_once(ros_environment: None) -> None:
    relay_cmd = command("robot_relay.cli", "--robot", ROBOT, "-l", f"tcp/127.0.0.1:{free_port()}",
                        "--no-multicast-scouting")
    with running(relay_cmd) as relay:
        lines = Lines(relay)
        lines.wait_for("/rosout: subscribed", timeout=60)  # its own node's log
        relay.send_signal(signal.SIGINT)
        assert relay.wait(timeout=30) == 0, lines.text
    time.sleep(0.2)
    assert "SIGINT: stopping" in lines.text
    assert "Traceback" not in lines.text
    with running(relay_cmd) as relay:
        lines = Lines(relay)
        lines.wait_for("/rosout: subscribed", timeout=60)
        # Both arrive together when it resumes: the first starts the stop, the second ends it.
        relay.send_signal(signal.SIGSTOP)
        relay.send_signal(signal.SIGINT)
        relay.send_signal(signal.SIGTERM)
        relay.send_signal(signal.SIGCONT)
        assert relay.wait(timeout=30) == 128 + signal.SIGTERM, lines.text
    time.sleep(0.2)
    assert "SIGTERM again, exiting at once" in lines.text
