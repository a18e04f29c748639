"""``swanky-host --bag BAG --slam --save-map DIR --save X.rrd`` on laser logs as robots record
them: what the viewer gets, the files nav2 and evo read, and each bad input named once."""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest
import yaml

from host_bridge.cli import main as host_main
from host_bridge.demo.world import distance_to_walls
from host_bridge.slam.pose import yaw_of
from tests.host_bridge.slam.robot_logs import LaserLog, Run, simulate, write_bag, write_ros1_bag
from tests.rrd import entity_rows

pytest.importorskip("gtsam", reason="host-side SLAM needs the [slam] extra (gtsam, small-gicp)")


def map_bag(run: Run, tmp_path: Path, *extra: str) -> tuple[Path, dict[str, list[dict[str, Any]]]]:
    bag = write_bag(run, tmp_path / "bag")
    out = tmp_path / "out.rrd"
    maps = tmp_path / "maps"
    assert host_main(["--bag", str(bag), "--robot", "r", "--slam", "--save-map", str(maps),
                      "--save", str(out), *extra]) == 0
    return maps / "r", entity_rows(out)


def read_pgm(path: Path) -> npt.NDArray[np.uint8]:
    """A binary PGM as map_server reads it (magic, width height, maxval, one byte a pixel)."""
    data = path.read_bytes()
    fields: list[bytes] = []
    at = 0
    while len(fields) < 4:
        while data[at : at + 1].isspace():
            at += 1
        if data[at : at + 1] == b"#":
            at = data.index(b"\n", at) + 1
            continue
        end = at
        while not data[end : end + 1].isspace():
            end += 1
        fields.append(data[at:end])
        at = end
    magic, width, height, maxval = fields[0], int(fields[1]), int(fields[2]), int(fields[3])
    assert (magic, maxval) == (b"P5", 255)
    body = data[at + 1 :]
    assert len(body) == width * height
    return np.frombuffer(body, np.uint8).reshape(height, width)


def read_tum(path: Path) -> npt.NDArray[np.float64]:
    rows = [line.split() for line in path.read_text().splitlines()]
    assert all(len(row) == 8 for row in rows)
    return np.array(rows, dtype=np.float64)


def test_a_drifting_robot_log_becomes_a_map_server_map_a_tum_trajectory_and_the_viewers_map(
    tmp_path: Path,
) -> None:
    run = simulate(LaserLog(seconds=90.0, range_noise=0.01))
    saved, rows = map_bag(run, tmp_path)

    meta = yaml.safe_load((saved / "map.yaml").read_text())
    assert set(meta) == {"image", "mode", "resolution", "origin", "negate", "occupied_thresh", "free_thresh"}
    assert (meta["image"], meta["mode"], meta["resolution"]) == ("map.pgm", "trinary", 0.05)
    assert (meta["negate"], meta["occupied_thresh"], meta["free_thresh"]) == (0, 0.65, 0.25)
    assert len(meta["origin"]) == 3
    assert meta["origin"][2] == 0
    pixels = read_pgm(saved / meta["image"])
    assert set(np.unique(pixels).tolist()) == {0, 205, 254}
    # Row 0 of the image is the top of the map (largest y), as map_server reads it.
    rows_, cols = np.nonzero(pixels == 0)
    height = pixels.shape[0]
    walls = np.column_stack([meta["origin"][0] + (cols + 0.5) * 0.05,
                             meta["origin"][1] + (height - rows_ - 0.5) * 0.05])
    assert len(walls) > 300
    assert distance_to_walls(walls).max() < 0.1
    free_rows, free_cols = np.nonzero(pixels == 254)
    free = np.column_stack([meta["origin"][0] + (free_cols + 0.5) * 0.05,
                            meta["origin"][1] + (height - free_rows - 0.5) * 0.05])
    assert np.all((free > [-0.05, -0.05]) & (free < [8.05, 6.05]))  # inside the apartment

    tum = read_tum(saved / "trajectory.tum")
    scans = run.scans
    assert len(tum) == len(scans) == 450
    stamps = np.array([s.stamp_ns for s in scans]) / 1e9
    assert np.allclose(tum[:, 0], stamps, atol=1e-9, rtol=0)
    truth = np.array([s.truth for s in scans])
    error = np.hypot(tum[:, 1] - truth[:, 0], tum[:, 2] - truth[:, 1])
    assert np.sqrt(np.mean(error**2)) < 0.05
    assert np.allclose(np.linalg.norm(tum[:, 4:8], axis=1), 1.0)
    yaw = np.array([yaw_of(q) for q in tum[:, 4:8]])
    assert np.max(np.abs(np.angle(np.exp(1j * (yaw - truth[:, 2]))))) < math.radians(2.0)

    # The viewer: map in the host's map frame, the correction at every scan, stats, closures.
    grids = rows["/r/slam/map"]
    assert grids[-1]["CoordinateFrame:frame"] == ["r/map"]
    corrections = rows["/r/slam/map_to_odom"]
    assert len(corrections) == 450
    assert {(c["Transform3D:parent_frame"][0], c["Transform3D:child_frame"][0]) for c in corrections} == {
        ("r/map", "r/odom")}
    # map -> odom undoes the drift: applied to the last odometry pose it gives the truth.
    last = corrections[-1]
    tx, ty, _ = last["Transform3D:translation"][0]
    turn = yaw_of(last["Transform3D:quaternion"][0])
    ox, oy, _ = scans[-1].odom
    c, s = math.cos(turn), math.sin(turn)
    corrected = (tx + c * ox - s * oy, ty + s * ox + c * oy)
    assert math.dist(corrected, truth[-1, :2]) < 0.05
    assert math.dist(scans[-1].odom[:2], truth[-1, :2]) > 0.5
    assert rows["/_stats/r/slam/closures"][-1]["Scalars:scalars"][0] >= 1
    assert rows["/r/slam/loop_closures"]
    assert len(rows["/_stats/r/slam/scan_ms"]) == 450
    assert np.median([r["Scalars:scalars"][0] for r in rows["/_stats/r/slam/matched_fraction"]]) > 0.9
    assert rows["/r/slam/map/walls"][-1]["Mesh3D:vertex_positions"]
    trail = rows["/r/slam/trajectory"][-1]["LineStrips3D:strips"][0]
    assert len(trail) == 450


def test_bad_laser_and_odometry_input_is_named_once_each_and_costs_only_itself(
    tmp_path: Path, caplog: pytest.LogCaptureFixture,
) -> None:
    run = simulate(LaserLog(seconds=70.0, range_noise=0.01, no_return="range_max", dropout=0.05,
                            odom_reset_at=35.0, sparse_scan_at=10.0, stale_scan_at=20.0))
    with caplog.at_level(logging.WARNING, logger="swanky.host"):
        saved, _ = map_bag(run, tmp_path)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    sparse = [w for w in warnings if "5 valid ranges of 360" in w]
    stale = [w for w in warnings if "not after the last mapped one" in w]
    jump = [w for w in warnings if "odometry jumped" in w]
    assert len(sparse) == len(stale) == len(jump) == 1
    assert all(w.startswith("[r] /scan: ") for w in sparse + stale)
    assert jump[0].startswith("[r] /odom: ")
    tum = read_tum(saved / "trajectory.tum")
    scans = run.scans
    assert len(tum) == len(scans)  # the sparse and the stale scan only were left out
    truth = np.array([s.truth for s in scans])
    error = np.hypot(tum[:, 1] - truth[:, 0], tum[:, 2] - truth[:, 1])
    assert np.sqrt(np.mean(error**2)) < 0.05  # the reset cost nothing: the map was kept


def test_a_log_without_odometry_or_laser_transform_is_mapped_by_scan_matching_with_one_warning_each(
    tmp_path: Path, caplog: pytest.LogCaptureFixture,
) -> None:
    run = simulate(LaserLog(seconds=30.0, odom=False, laser_mount=False))
    with caplog.at_level(logging.WARNING, logger="swanky.host"):
        saved, _ = map_bag(run, tmp_path)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert [w for w in warnings if "no odometry" in w] == [
        "[r] /scan: no odometry (/odom (nav_msgs/Odometry) or odom -> base on /tf); mapping with "
        "scan matching alone (further NoOdometryErrors on this topic are counted, not shown)"]
    # Without odometry nothing names the base: the laser is what moves (no transform needed).
    assert len(read_tum(saved / "trajectory.tum")) == len(run.scans)


@pytest.mark.parametrize("compression", ["bz2", "lz4"])
def test_a_ros1_log_with_odometry_and_the_laser_mount_on_tf_only(tmp_path: Path, compression: str) -> None:
    """What SLAM datasets' bags hold: /scan and /tf (odom -> base at 30 Hz, the laser's mount
    repeated beside it), no /odom, no /tf_static, compressed chunks."""
    run = simulate(LaserLog(seconds=40.0, range_noise=0.01, odom_on_tf=True, mount_on_tf=True))
    bag = write_ros1_bag(run, tmp_path / "log.bag", compression)
    maps = tmp_path / "maps"
    assert host_main(["--bag", str(bag), "--robot", "r", "--save-map", str(maps),
                      "--save", str(tmp_path / "out.rrd"), "--strict"]) == 0
    tum = read_tum(maps / "r" / "trajectory.tum")
    truth = np.array([s.truth for s in run.scans])
    assert len(tum) == len(truth)
    error = np.hypot(tum[:, 1] - truth[:, 0], tum[:, 2] - truth[:, 1])
    assert np.sqrt(np.mean(error**2)) < 0.05


def test_a_robot_with_its_own_map_frame_keeps_it_and_the_hosts_map_hangs_below_odom(tmp_path: Path) -> None:
    run = simulate(LaserLog(seconds=10.0, robot_map=True))
    _, rows = map_bag(run, tmp_path)
    corrections = rows["/r/slam/map_to_odom"]
    assert {(c["Transform3D:parent_frame"][0], c["Transform3D:child_frame"][0]) for c in corrections} == {
        ("r/odom", "r/slam_map")}
    assert rows["/r/slam/map"][-1]["CoordinateFrame:frame"] == ["r/slam_map"]
    # The robot's own map -> odom is untouched: one parent per frame, one tree.
    assert rows["/r/tf_static/odom"][-1]["Transform3D:parent_frame"] == ["r/map"]
    # The first pose is the odometry's, so odom -> slam_map starts as the identity.
    assert corrections[0]["Transform3D:translation"][0] == pytest.approx([0.0, 0.0, 0.0], abs=1e-6)


def test_the_real_hokuyo_log_without_odometry_is_mapped_consistently(
    shared_data: Path, tmp_path: Path,
) -> None:
    """CCNY's Hokuyo log (360 scans, no odometry, no TF): every scan placed by scan matching
    lands on the walls of the final map, which the same scans drawn without motion do not."""
    bag = shared_data / "hokuyo_scan_ccny" / "laser_scan_matcher_demo.bag"
    maps = tmp_path / "maps"
    assert host_main(["--bag", str(bag), "--robot", "r", "--slam", "--save-map", str(maps),
                      "--save", str(tmp_path / "out.rrd")]) == 0
    tum = read_tum(maps / "r" / "trajectory.tum")
    assert len(tum) == 360
    meta = yaml.safe_load((maps / "r" / "map.yaml").read_text())
    pixels = read_pgm(maps / "r" / "map.pgm")
    from rosbags.highlevel import AnyReader

    from host_bridge.slam.scan import scan_from_msg

    with AnyReader([bag]) as reader:
        msgs = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()]
    occupied = np.zeros_like(pixels, bool)
    occupied[pixels == 0] = True
    # One cell of slack: a wall's echo falls in the cell or its neighbour.
    near = occupied | np.roll(occupied, 1, 0) | np.roll(occupied, -1, 0) | np.roll(occupied, 1, 1) | np.roll(
        occupied, -1, 1)

    def on_walls(poses: npt.NDArray[np.float64]) -> float:
        hits = total = 0
        for msg, (x, y, yaw) in zip(msgs, poses, strict=True):
            points = scan_from_msg(msg).points
            c, s = math.cos(yaw), math.sin(yaw)
            world = points @ np.array([[c, s], [-s, c]]) + [x, y]
            col = np.floor((world[:, 0] - meta["origin"][0]) / 0.05).astype(int)
            row = pixels.shape[0] - 1 - np.floor((world[:, 1] - meta["origin"][1]) / 0.05).astype(int)
            inside = (row >= 0) & (row < pixels.shape[0]) & (col >= 0) & (col < pixels.shape[1])
            hits += int(near[row[inside], col[inside]].sum())
            total += len(points)
        return hits / total

    yaws = np.array([yaw_of(q) for q in tum[:, 4:8]])
    slam = on_walls(np.column_stack([tum[:, 1], tum[:, 2], yaws]))
    unmoved = on_walls(np.zeros((360, 3)))
    assert slam > 0.9
    assert unmoved < slam - 0.1
