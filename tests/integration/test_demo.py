"""``swanky-host --demo --duration 20 --save demo.rrd``, headless, as a real process: the simulated
robot through relay -> Zenoh on loopback -> host, then every topic it publishes read back from
the .rrd with plausible values.

One demo run is shared by every test of this module (it takes the demo's 20 s plus the bag):
to check another output of the same run (e.g. ``--record-mcap``), add its flag to
:func:`demo_command` and a test reading ``demo.directory``.
"""

from __future__ import annotations

import itertools
import math
import os
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from host_bridge.demo.messages import (
    GROUND_TRUTH_POSE_TOPIC,
    GROUND_TRUTH_WALLS_TOPIC,
    GROUND_TRUTH_WALLS_Z,
    STEP_TIMER_TOPIC,
    TOPICS,
    simulate,
    tick_stamp_ns,
)
from host_bridge.demo.robot import BASE_LINK_Z, SCAN_XYZ, WHEEL_RADIUS, odometry_track
from host_bridge.demo.run import demo_bag_seconds
from host_bridge.demo.sensors import DEPTH_MAX, camera_matrix
from host_bridge.demo.world import BOUNDS, WALLS, distance_to_walls
from tests.integration.procs import command, rerun_binary, running
from tests.rrd import entity_rows, verify

pytestmark = pytest.mark.integration

DEMO_SECONDS = 20
# Writing the bag, zenoh start-up and the final flush come on top of the demo's own 20 s; a
# loaded 2-core CI machine needs some slack.
TIMEOUT_S = 150
ROBOT = "sim"

Rows = dict[str, list[dict[str, Any]]]


@dataclass(frozen=True)
class DemoRun:
    directory: Path
    returncode: int
    stdout: str
    stderr: str
    elapsed_s: float
    rows: Rows

    def entity(self, path: str) -> list[dict[str, Any]]:
        assert path in self.rows, f"{path} missing from demo.rrd; stderr:\n{self.stderr[-3000:]}"
        return self.rows[path]


def demo_command(directory: Path) -> list[str]:
    """The shared demo run; every output it writes goes into ``directory``."""
    return command(
        "host_bridge.cli", "--demo", "--duration", str(DEMO_SECONDS),
        "--save", str(directory / "demo.rrd"), "--record-mcap", str(directory / "demo.mcap"),
        "--save-map", str(directory / "maps"),
    )


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> DemoRun:
    directory = tmp_path_factory.mktemp("demo")
    started = time.monotonic()
    with running(demo_command(directory)) as proc:
        stdout, stderr = proc.communicate(timeout=TIMEOUT_S)
    elapsed = time.monotonic() - started
    rrd = directory / "demo.rrd"
    rows = entity_rows(rrd) if rrd.exists() else {}
    return DemoRun(directory, proc.returncode, stdout, stderr, elapsed, rows)


def test_demo_ends_by_itself_with_a_summary(demo: DemoRun) -> None:
    assert demo.returncode == 0, demo.stderr[-3000:]
    assert DEMO_SECONDS <= demo.elapsed_s < TIMEOUT_S
    assert f"robot {ROBOT} joined" in demo.stderr
    summary = {line.split()[1]: line.split() for line in demo.stderr.splitlines()
               if line.startswith(f"{ROBOT} ")}
    assert set(summary) == {spec.topic for spec in TOPICS}


def test_demo_saves_one_file_rerun_accepts(demo: DemoRun) -> None:
    """20 s is shorter than --save-split: demo.rrd itself, with its footer."""
    assert sorted(path.name for path in demo.directory.glob("*.rrd")) == ["demo.rrd"]
    verify(demo.directory / "demo.rrd")


def _scalars(rows: list[dict[str, Any]]) -> NDArray[np.float64]:
    return np.array([r["Scalars:scalars"][0] for r in rows if r.get("Scalars:scalars")])


def _quaternion_rotate(q: list[float], v: NDArray[np.float64]) -> NDArray[np.float64]:
    x, y, z, w = q
    u = np.array([x, y, z])
    return (  # type: ignore[no-any-return]
        v * (w * w - u @ u) + 2.0 * np.outer(v @ u, u) + 2.0 * w * np.cross(u, v)
    )


def _true_poses(demo: DemoRun) -> dict[int, dict[str, Any]]:
    """The /ground_truth/pose rows by ros_time."""
    return {r["ros_time"]: r for r in demo.entity(f"/{ROBOT}{GROUND_TRUTH_POSE_TOPIC}")
            if r.get("Transform3D:translation")}


def test_scan_points_lie_on_the_apartment_walls(demo: DemoRun) -> None:
    """Seen from the true pose (the drifting odometry would smear them: the host's SLAM's job)."""
    scans = [r for r in demo.entity(f"/{ROBOT}/scan") if r.get("Points3D:positions")]
    assert len(scans) >= 3 * DEMO_SECONDS // 2  # 5 Hz; the machine may drop some
    assert scans[0]["CoordinateFrame:frame"] == [f"{ROBOT}/base_scan"]
    body = _true_poses(demo)
    offset = np.add(SCAN_XYZ, (0.0, 0.0, BASE_LINK_Z))
    checked = 0
    for scan in scans:
        pose = body.get(scan["ros_time"])
        if pose is None:  # its /tf sample was dropped on the way
            continue
        local = np.asarray(scan["Points3D:positions"], np.float64) + offset
        world = _quaternion_rotate(pose["Transform3D:quaternion"][0], local)
        world += pose["Transform3D:translation"][0]
        x0, y0, x1, y1 = BOUNDS
        assert np.all((world[:, 0] > x0 - 0.01) & (world[:, 0] < x1 + 0.01))
        assert np.all((world[:, 1] > y0 - 0.01) & (world[:, 1] < y1 + 0.01))
        assert distance_to_walls(world[:, :2]).max() < 0.01
        checked += 1
    assert checked >= len(scans) // 2


def test_camera_image_depth_and_cloud(demo: DemoRun) -> None:
    (pinhole, *_) = demo.entity(f"/{ROBOT}/camera")
    k = np.asarray(pinhole["Pinhole:image_from_camera"][0]).reshape(3, 3).T  # column-major
    np.testing.assert_allclose(k, camera_matrix())
    assert pinhole["Pinhole:resolution"] == [[160.0, 120.0]]
    assert pinhole["Pinhole:parent_frame"] == [f"{ROBOT}/camera_optical_frame"]

    images = [r for r in demo.entity(f"/{ROBOT}/camera/image_raw") if r.get("Image:buffer")]
    assert len(images) >= 2 * DEMO_SECONDS
    fmt = images[0]["Image:format"][0]
    assert (fmt["width"], fmt["height"]) == (160, 120)
    pixels = np.asarray(images[-1]["Image:buffer"][0], np.uint8).reshape(120, 160, 3)
    assert len(np.unique(pixels.reshape(-1, 3), axis=0)) > 20  # a rendered view, not a fill

    depths = [r for r in demo.entity(f"/{ROBOT}/camera/depth/image_raw")
              if r.get("DepthImage:buffer")]
    assert len(depths) >= 2 * DEMO_SECONDS
    assert depths[0]["DepthImage:meter"] == [1000.0]
    for row in depths[::10]:
        mm = np.asarray(row["DepthImage:buffer"][0], np.uint8).view("<u2").reshape(120, 160)
        assert mm.min() >= 200  # the floor just below the lens
        assert mm.max() <= DEPTH_MAX * 1000
        # the sky is a ceiling, the horizon a wall: the middle row is the farthest
        assert mm[59].mean() > mm[-1].mean()

    clouds = [r for r in demo.entity(f"/{ROBOT}/camera/depth/points")
              if r.get("Points3D:positions")]
    assert len(clouds) >= 2 * DEMO_SECONDS
    assert clouds[0]["CoordinateFrame:frame"] == [f"{ROBOT}/camera_optical_frame"]
    points = np.asarray(clouds[-1]["Points3D:positions"], np.float64)
    assert points.shape == (30 * 40, 3)
    assert np.all((points[:, 2] > 0.2) & (points[:, 2] <= DEPTH_MAX))
    assert len(clouds[-1]["Points3D:colors"]) == len(points)


def test_no_map_from_the_robot_and_the_ground_truth_beside_its_drifting_odometry(
    demo: DemoRun,
) -> None:
    assert not any(path.startswith(f"/{ROBOT}/map") for path in demo.rows)
    (walls,) = [r for r in demo.entity(f"/{ROBOT}{GROUND_TRUTH_WALLS_TOPIC}/walls/0")
                if r.get("LineStrips3D:strips")]
    assert walls["Transform3D:parent_frame"] == [f"{ROBOT}/map"]
    strips = np.asarray(walls["LineStrips3D:strips"], np.float64)
    np.testing.assert_allclose(strips[:, :, :2], WALLS, atol=1e-6)
    np.testing.assert_allclose(strips[:, :, 2], GROUND_TRUTH_WALLS_Z, atol=1e-6)

    truth = _true_poses(demo)
    assert len(truth) >= 15 * DEMO_SECONDS  # 30 Hz; the machine may drop some
    assert {r["Transform3D:parent_frame"][0] for r in truth.values()} == {f"{ROBOT}/map"}
    odom = {r["ros_time"]: r for r in demo.entity(f"/{ROBOT}/tf")
            if r.get("Transform3D:child_frame") == [f"{ROBOT}/base_footprint"]}
    assert {r["Transform3D:parent_frame"][0] for r in odom.values()} == {f"{ROBOT}/odom"}
    # Both are odometry_track's, at the tick of their stamp; the odometry drifts away.
    track = list(odometry_track(demo_bag_seconds(DEMO_SECONDS)))
    tick_of = {tick_stamp_ns(tick): tick for tick in range(len(track))}
    compared = 0
    for stamp in sorted(truth.keys() & odom.keys()):
        state, pose = track[tick_of[stamp]]
        np.testing.assert_allclose(
            truth[stamp]["Transform3D:translation"][0], (state.x, state.y, 0.0), atol=1e-6)
        np.testing.assert_allclose(
            odom[stamp]["Transform3D:translation"][0], (pose.x, pose.y, 0.0), atol=1e-6)
        compared += 1
    assert compared >= 15 * DEMO_SECONDS
    last = max(truth.keys() & odom.keys())
    apart = np.subtract(odom[last]["Transform3D:translation"][0][:2],
                        truth[last]["Transform3D:translation"][0][:2])
    assert np.hypot(*apart) > 0.1  # 0.1 m after 8 s of driving, 0.34 m after 20 s


def test_the_host_maps_the_apartment_from_the_drifting_odometry(demo: DemoRun) -> None:
    """--demo runs host-side SLAM: its map's walls stand on the true walls and its trajectory
    on the true track, while the robot's own odometry drifts away from both."""
    grid = demo.entity(f"/{ROBOT}/slam/map")[-1]
    assert grid["CoordinateFrame:frame"] == [f"{ROBOT}/map"]
    width, height = grid["GridMap:format"][0]["width"], grid["GridMap:format"][0]["height"]
    cells = np.frombuffer(bytes(grid["GridMap:data"][0]), np.uint8).reshape(height, width)[::-1]
    resolution = grid["GridMap:cell_size"][0]
    x0, y0, _ = grid["GridMap:translation"][0]
    rows, cols = np.nonzero((cells > 65) & (cells <= 100))
    walls = np.column_stack([x0 + (cols + 0.5) * resolution, y0 + (rows + 0.5) * resolution])
    assert len(walls) > 100
    assert distance_to_walls(walls).max() < 0.1
    tum = np.loadtxt(demo.directory / "maps" / ROBOT / "trajectory.tum")
    track = list(odometry_track(demo_bag_seconds(DEMO_SECONDS)))
    tick_of = {tick_stamp_ns(tick): tick for tick in range(len(track))}
    ticks = [tick_of[round(stamp * 1e3) * 1_000_000] for stamp in tum[:, 0]]
    truth = np.array([(track[i][0].x, track[i][0].y) for i in ticks])
    odometry = np.array([(track[i][1].x, track[i][1].y) for i in ticks])
    assert len(tum) >= DEMO_SECONDS * 4  # 5 Hz scans, a few left at the start
    assert np.sqrt(np.mean(np.sum((tum[:, 1:3] - truth) ** 2, axis=1))) < 0.05
    assert np.hypot(*(odometry[-1] - truth[-1])) > 0.2


def test_robot_model_and_frames(demo: DemoRun) -> None:
    visuals = [p for p in demo.rows if p.startswith(f"/{ROBOT}/robot_model/")]
    links = {p.split("/")[3] for p in visuals}
    assert links >= {"base_link", "wheel_left_link", "wheel_right_link", "caster_back_link",
                     "base_scan", "camera_link"}
    (wheel,) = demo.entity(f"/{ROBOT}/robot_model/wheel_left_link/visual_0")
    assert wheel["Cylinders3D:radii"] == [pytest.approx(WHEEL_RADIUS)]
    statics = {p.rsplit("/", 1)[1] for p in demo.rows if p.startswith(f"/{ROBOT}/tf_static/")}
    # /tf_static's own relations and the roots placed at the robot's root (map, which only the
    # ground truth names; odom, which no transform names as a child until the host's SLAM
    # places it; the model's root base_footprint until /tf arrives), so the 3D view reaches
    # every frame from the first row; and the URDF's movable joints at zero (the wheels) when
    # the model is converted before /tf first moves them: the demo's topics arrive in either
    # order (the model on the robot's small-topic thread, as /tf), so those two rows may or
    # may not be there.
    wheels_at_zero = {"wheel_left_link", "wheel_right_link"}
    assert statics - wheels_at_zero == {
        "odom", "base_link", "caster_back_link", "imu_link", "base_scan", "camera_link",
        "camera_optical_frame", "map", "base_footprint"}
    assert statics & wheels_at_zero in (set(), wheels_at_zero)
    # The camera's first image may be converted (on the heavy thread) before /tf_static (on the
    # small one): its frame is then placed at the robot's root first, and /tf_static's relation
    # written after it on the same static entity, the row the viewer keeps (core/frames.py).
    *placed, optical = demo.entity(f"/{ROBOT}/tf_static/camera_optical_frame")
    assert [row["Transform3D:parent_frame"] for row in placed] in ([], [[f"tf#/{ROBOT}"]])
    assert optical["Transform3D:quaternion"][0] == pytest.approx([-0.5, 0.5, -0.5, 0.5])
    wheels = {r["Transform3D:child_frame"][0] for r in demo.entity(f"/{ROBOT}/tf")}
    assert wheels == {f"{ROBOT}/base_footprint", f"{ROBOT}/wheel_left_link",
                      f"{ROBOT}/wheel_right_link"}
    angles = _scalars(demo.entity(f"/{ROBOT}/joint_states/wheel_left_joint/position"))
    assert np.all(np.diff(angles) >= 0.0)  # always rolling forward
    assert angles[-1] > 2 * math.pi  # at least a turn in 20 s


def test_imu_battery_timer_and_logs(demo: DemoRun) -> None:
    accel = [r["Scalars:scalars"] for r in demo.entity(f"/{ROBOT}/imu/linear_acceleration")
             if r.get("Scalars:scalars")]
    assert len(accel) >= 10 * DEMO_SECONDS
    np.testing.assert_allclose(np.asarray(accel)[:, 2], 9.80665, rtol=1e-6)

    battery = _scalars(demo.entity(f"/{ROBOT}/battery_state/percentage"))
    assert len(battery) >= DEMO_SECONDS // 2
    assert np.all((battery > 0.9) & (battery <= 0.97 + 1e-6))
    assert np.all(np.diff(battery) < 0.0)
    voltage = _scalars(demo.entity(f"/{ROBOT}/battery_state/voltage"))
    assert np.all((voltage > 10.5) & (voltage < 12.6))

    timer = _scalars(demo.entity(f"/{ROBOT}{STEP_TIMER_TOPIC}"))
    assert len(timer) >= 10 * DEMO_SECONDS
    assert np.all((timer > 0.5) & (timer < 8.0))

    logs = [(r["TextLog:level"][0], r["TextLog:text"][0]) for r in demo.entity(f"/{ROBOT}/rosout")]
    assert logs[0] == ("INFO", "[swanky_bot.driver] driving the apartment loop from (2.00, 1.70), "
                               "next waypoint 1 at (6.0, 1.7)")
    assert logs[1][0] == "WARN"
    assert "camera: no calibration file found" in logs[1][1]


def test_recorded_mcap_holds_the_bytes_the_robot_sent(demo: DemoRun) -> None:
    """--record-mcap: every message the host received, byte for byte as the simulator made it."""
    from collections import Counter

    from mcap.reader import make_reader

    assert demo.returncode == 0, demo.stderr[-3000:]
    with (demo.directory / "demo.mcap").open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        records = [(c.topic, m) for _, c, m in reader.iter_messages(log_time_order=False)]
    assert summary is not None
    schemas = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    assert schemas == {spec.topic: spec.msgtype for spec in TOPICS}  # one robot: ROS names
    received = {line.split()[1]: int(line.split()[3]) for line in demo.stderr.splitlines()
                if line.startswith(f"{ROBOT} ")}
    assert Counter(topic for topic, _ in records) == received
    # The simulation is a pure function of time, except the measured step time.
    sent = {(m.topic, m.log_ns): m.data for m in simulate(demo_bag_seconds(DEMO_SECONDS))
            if m.topic != STEP_TIMER_TOPIC}
    checked = [(topic, m) for topic, m in records if topic != STEP_TIMER_TOPIC]
    assert len(checked) >= 10 * DEMO_SECONDS
    for topic, message in checked:
        assert message.data == sent[topic, message.publish_time], topic
        assert message.log_time > message.publish_time  # relay receive (now) after the sim time


def test_fleet_demo_keeps_each_robot_apart(tmp_path: Path) -> None:
    """``--demo --robots 2``: two simulated robots, each through its own relay, in one host;
    each has its own entity root, frames and position along the route, and its own channels in
    the recorded MCAP (``/sim/scan``, ``/sim2/scan``: a reader that goes by channel names, as
    ``ros2 bag play`` and ``rerun mcap convert`` do, keeps them apart)."""
    out = tmp_path / "fleet.rrd"
    mcap = tmp_path / "fleet.mcap"
    with running(command("host_bridge.cli", "--demo", "--robots", "2", "--duration", "4",
                         "--save", str(out), "--no-stats", "--record-mcap", str(mcap))) as proc:
        _, stderr = proc.communicate(timeout=TIMEOUT_S)
    assert proc.returncode == 0, stderr[-3000:]
    check_fleet_recording(mcap, ("sim", "sim2"), tmp_path / "imported.rrd")
    rows = entity_rows(out)
    starts = {}
    for robot in ("sim", "sim2"):
        assert f"robot {robot} joined" in stderr
        odom = [row for row in rows[f"/{robot}/tf"]
                if row["Transform3D:child_frame"] == [f"{robot}/base_footprint"]]
        assert odom, f"no odometry transform for {robot}"
        assert {row["Transform3D:parent_frame"][0] for row in odom} == {f"{robot}/odom"}
        starts[robot] = np.asarray(odom[0]["Transform3D:translation"][0])
        assert rows[f"/{robot}/scan"]
    assert not any(path.startswith("/sim3") for path in rows)
    # Spread along the loop: the two robots do not start on top of each other.
    assert np.linalg.norm(starts["sim"] - starts["sim2"]) > 0.5


def check_fleet_recording(mcap: Path, robots: tuple[str, ...], imported: Path) -> None:
    """Every channel is ``/<robot><topic>``, each robot has all the demo's topics, and Rerun's
    own MCAP importer puts each robot's messages under its own entity root, none merged."""
    from mcap.reader import make_reader

    with mcap.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    assert summary.statistics is not None
    channels = {(c.metadata["swanky.robot"], c.metadata["swanky.topic"]): c.topic
                for c in summary.channels.values()}
    assert channels == {(robot, spec.topic): f"/{robot}{spec.topic}"
                        for robot in robots for spec in TOPICS}
    counted = {summary.channels[channel].topic: count
               for channel, count in summary.statistics.channel_message_counts.items()}
    assert all(counted[f"/{robot}/scan"] >= 1 for robot in robots), counted
    subprocess.run([str(rerun_binary()), "mcap", "convert", str(mcap), "-o", str(imported)], check=True,
                   capture_output=True, timeout=120)
    rows = entity_rows(imported)
    for robot in robots:  # each scan once, under its robot's root
        assert sum(not row["static"] for row in rows[f"/{robot}/scan"]) == counted[f"/{robot}/scan"]
    assert "/scan" not in rows


@pytest.mark.filterwarnings("ignore:RRD file has no footer")  # the viewer's own file
def test_workers_split_a_fleet_demo_over_processes_into_one_recording(tmp_path: Path) -> None:
    """``--demo --robots 4 --workers 2`` into a viewer and files: each robot converted by the
    one worker its name gives (core/shards.py), in that worker's file, every IMU message of the
    run; the viewer gets one recording of all four robots, each worker's viewer lag apart, and
    both files lay out all four robots (the workers share their layout)."""
    from host_bridge.core.shards import Shard
    from tests.integration.procs import saving_viewer
    from tests.integration.test_fleet import recording_id
    from tests.rrd import saved_views

    robots = ("sim", "sim2", "sim3", "sim4")
    seconds = 6
    viewed = tmp_path / "viewer.rrd"
    with saving_viewer(viewed) as (url, _), running(command(
            "host_bridge.cli", "--demo", "--robots", "4", "--workers", "2", "--duration", str(seconds),
            "--no-slam", "--save", str(tmp_path / "fleet.rrd"), "--rerun-addr", url)) as proc:
        _, stderr = proc.communicate(timeout=TIMEOUT_S)
    assert proc.returncode == 0, stderr[-3000:]
    assert "2 workers (pids " in stderr
    files = {index: tmp_path / f"fleet-worker{index}.rrd" for index in (0, 1)}
    assert sorted(path.name for path in tmp_path.glob("fleet*.rrd")) == sorted(p.name for p in files.values())
    verify(*files.values())
    assert len({recording_id(path) for path in [*files.values(), viewed]}) == 1
    for index, path in files.items():
        rows = entity_rows(path)
        owned = [robot for robot in robots if Shard(index, 2).owns(robot)]
        assert owned, "crc32 gives each worker some of sim..sim4"
        assert {p.split("/")[1] for p in rows if not p.startswith("/_")} == set(owned), path.name
        for robot in owned:
            assert f"swanky.host (worker{index}): INFO: robot {robot} joined" in stderr
            # 30 Hz for the run's seconds, less the relays' start: none lost between them.
            imu = [row for row in rows[f"/{robot}/imu/linear_acceleration"] if not row["static"]]
            assert len(imu) >= 30 * (seconds - 2), (robot, len(imu))
            stamps = [row["ros_time"] for row in imu]
            assert stamps == sorted(set(stamps))
            assert max(b - a for a, b in itertools.pairwise(stamps)) < 1.5e9 / 30, robot  # none lost
        assert {view["name"] for view in saved_views(path) if view.get("class") == "3D"} >= {
            f"{robot} 3D" for robot in robots}, path.name
    shown = entity_rows(viewed)
    assert {p.split("/")[1] for p in shown if not p.startswith("/_")} == set(robots)
    assert {f"/_stats/host/worker{index}/viewer_lag_ms" for index in (0, 1)} <= set(shown)


def test_a_worker_that_dies_is_named_and_the_other_goes_on(tmp_path: Path) -> None:
    """One of two workers killed mid-run (a host that vanishes): the command names it and whose
    robots it converted as it dies, the other worker's robots are converted to the end into a
    complete file, and the exit code says something failed."""
    import re
    import signal as signals

    from host_bridge.core.shards import Shard
    from tests.integration.robot_bags import Lines

    seconds = 10
    with running(command("host_bridge.cli", "--demo", "--robots", "4", "--workers", "2",
                         "--duration", str(seconds), "--no-slam", "--no-stats",
                         "--save", str(tmp_path / "fleet.rrd"))) as proc:
        lines = Lines(proc)
        started = lines.wait_for("2 workers (pids ", timeout=TIMEOUT_S)
        match = re.search(r"pids (\d+), (\d+)\)", started)
        assert match is not None, started
        doomed = int(match.group(2))
        for index in (0, 1):
            lines.wait_for(f"swanky.host (worker{index}): INFO: robot ", timeout=60)
        # The demo's relays start once every robot's host subscribed: killed after, not before.
        time.sleep(3)
        os.kill(doomed, signals.SIGKILL)
        said = lines.wait_for("worker1 (pid", timeout=10)
        assert proc.wait(timeout=TIMEOUT_S) == 1
    assert said.strip() == (
        f"swanky-host: worker1 (pid {doomed}) was killed by signal 9: its robots are no longer "
        "converted (those whose name's crc32 % 2 is 1); the other workers go on")
    survivor = tmp_path / "fleet-worker0.rrd"
    verify(survivor)
    rows = entity_rows(survivor)
    for robot in (robot for robot in ("sim", "sim2", "sim3", "sim4") if Shard(0, 2).owns(robot)):
        imu = [row for row in rows[f"/{robot}/imu/linear_acceleration"] if not row["static"]]
        assert len(imu) >= 30 * (seconds - 4), (robot, len(imu))  # to the end, past the kill
