"""The SLAM engine against the truth: the demo apartment's walls and the robot's true poses,
with odometry drifting as real wheel odometry does and lasers misbehaving as real ones do."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import pytest

from host_bridge.demo.world import distance_to_walls
from host_bridge.slam.engine import Slam
from host_bridge.slam.pose import compose, pose2, to_matrix
from host_bridge.slam.scan import scan_from_ranges
from host_bridge.slam.settings import SlamSettings
from tests.host_bridge.slam.robot_logs import LASER_XY, LaserLog, Run, simulate

pytest.importorskip("gtsam", reason="host-side SLAM needs the [slam] extra (gtsam, small-gicp)")

MOUNT = to_matrix(pose2(*LASER_XY, 0.0))


def map_run(run: Run, odometry: bool = True) -> tuple[Slam, npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Feed every scan of ``run`` to SLAM; its trajectory, and the true poses of the scans."""
    slam = Slam(SlamSettings(enabled=True))
    log = run.log
    truths = []
    for sample in run.scans:
        assert sample.ranges is not None
        scan = scan_from_ranges(sample.ranges, 0.0, 2 * math.pi / log.beams, log.range_min,
                                log.range_max).moved(MOUNT)
        slam.add(scan, sample.stamp_ns, sample.odom if odometry else None)
        truths.append(sample.truth)
    return slam, slam.trajectory()[1], np.array(truths)


def rms(poses: npt.NDArray[np.float64], truths: npt.NDArray[np.float64]) -> float:
    return float(np.sqrt(np.mean(np.sum((poses[:, :2] - truths[:, :2]) ** 2, axis=1))))


def occupied_points(slam: Slam) -> npt.NDArray[np.float64]:
    """Centres of the cells the map calls occupied (above map_saver's 65 %)."""
    dense = slam.occupancy()
    rows, cols = np.nonzero(dense.cells > 65)
    return np.column_stack([dense.origin[0] + (cols + 0.5) * dense.resolution,
                            dense.origin[1] + (rows + 0.5) * dense.resolution])


def test_a_drifting_loop_is_mapped_within_5_cm_of_the_truth_with_walls_where_they_are() -> None:
    # 5 % scale error and 2 deg/m heading drift, 1 cm of range noise, 1.6 laps of the loop.
    run = simulate(LaserLog(seconds=100.0, range_noise=0.01))
    slam, poses, truths = map_run(run)
    odometry = np.array([s.odom for s in run.scans])
    assert len(poses) == len(run.scans) == 500
    assert rms(poses, truths) < 0.05
    assert rms(odometry, truths) > 0.5  # what the robot's own odometry would have drawn
    assert slam.closures >= 1
    walls = occupied_points(slam)
    assert len(walls) > 400
    # Every occupied cell's centre within two cells of a true wall; nearly all within one.
    near = distance_to_walls(walls)
    assert near.max() < 0.1
    assert np.mean(near < 0.05) > 0.95


def test_the_same_loop_mapped_from_odometry_alone_misses_the_walls() -> None:
    """The baseline the host replaces: the same scans drawn where odometry puts them."""
    run = simulate(LaserLog(seconds=100.0))
    slam = Slam(SlamSettings(enabled=True))
    from host_bridge.slam.grid import TiledGrid

    grid = TiledGrid(slam.settings.resolution)
    for sample in run.scans:
        assert sample.ranges is not None
        grid.add(scan_from_ranges(sample.ranges, 0.0, 2 * math.pi / 360, 0.12, 3.5).moved(MOUNT), sample.odom)
    dense = grid.dense()
    rows, cols = np.nonzero(dense.cells > 65)
    points = np.column_stack([dense.origin[0] + (cols + 0.5) * 0.05, dense.origin[1] + (rows + 0.5) * 0.05])
    assert np.mean(distance_to_walls(points) < 0.05) < 0.5


@pytest.mark.parametrize("no_return", ["inf", "range_max", "zero"])
def test_no_return_readings_dropouts_and_noise_map_the_same_walls(no_return: str) -> None:
    run = simulate(LaserLog(seconds=40.0, range_noise=0.01, dropout=0.1, no_return=no_return))
    slam, poses, truths = map_run(run)
    assert rms(poses, truths) < 0.05
    near = distance_to_walls(occupied_points(slam))
    # A no-return reading is never an obstacle: nothing occupied off the walls.
    assert near.max() < 0.1


def test_no_return_is_free_space_up_to_range_max_and_no_obstacle() -> None:
    """One scan in open space (no wall within range): free up to range_max, nothing occupied."""
    slam = Slam(SlamSettings(enabled=True, min_points=1))
    ranges = np.full(360, 3.5, np.float32)  # range_max: no echo anywhere ...
    ranges[0] = 1.0  # ... but straight ahead
    scan = scan_from_ranges(ranges, 0.0, 2 * math.pi / 360, 0.12, 3.5)
    slam.add(scan, 0, None)
    dense = slam.occupancy()

    def cell(x: float, y: float) -> int:
        col = math.floor((x - dense.origin[0]) / dense.resolution)
        row = math.floor((y - dense.origin[1]) / dense.resolution)
        return int(dense.cells[row, col])

    assert cell(1.01, 0.01) > 65  # the echo
    assert 0 <= cell(0.0, 3.3) < 50  # free up to range_max across the no-echo beams
    assert 0 <= cell(-3.3, 0.0) < 50
    assert cell(0.0, 3.7) == -1  # unknown beyond
    assert (dense.cells > 65).sum() == 1


def test_an_odometry_reset_starts_a_segment_and_keeps_the_map() -> None:
    run = simulate(LaserLog(seconds=90.0, range_noise=0.01, odom_reset_at=40.0))
    slam, poses, truths = map_run(run)
    assert slam.segments == 1
    assert rms(poses, truths) < 0.05
    assert distance_to_walls(occupied_points(slam)).max() < 0.1


def test_scan_matching_alone_follows_the_loop() -> None:
    """Without odometry the map frame is where the first scan was taken; the constant-velocity
    guess drifts more between loop closures (11 cm at most here) than odometry's does."""
    run = simulate(LaserLog(seconds=70.0, range_noise=0.01))
    _, poses, truths = map_run(run, odometry=False)
    start = truths[0]
    placed = np.array([compose(start, pose) for pose in poses])
    assert rms(placed, truths) < 0.1
    assert np.hypot(*(placed[-1, :2] - truths[-1, :2])) < 0.03


def test_tiles_follow_the_area_seen_not_its_extent() -> None:
    """Two places 150 m apart (a 200 m x 200 m site at 5 cm would be 16 M cells dense)."""
    slam = Slam(SlamSettings(enabled=True, min_points=1))
    grid = slam.grid
    scan = scan_from_ranges(np.full(360, 3.0, np.float32), 0.0, 2 * math.pi / 360, 0.12, 3.5)
    grid.add(scan, pose2(0.0, 0.0, 0.0))
    grid.add(scan, pose2(150.0, 150.0, 0.0))
    assert grid.tile_count <= 2 * 16  # a 7 m square of 3.2 m tiles, twice
    assert grid.nbytes <= 2 * 16 * 64 * 64 * 2
