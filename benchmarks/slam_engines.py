"""Issue 21's comparison of 2D SLAM engines, measured on the same scans: ours
(:class:`host_bridge.slam.engine.Slam`: small_gicp GICP against the latest keyframes with the
odometry's motion as the guess, a GTSAM ISAM2 pose graph with loop closures; also without loop
closures and without odometry), KISS-ICP (the scans as 3D points with z = 0, as its authors
suggest in PRBonn/kiss-icp#37; its own constant-velocity guess, or the odometry's increment put
in its place), KISS-SLAM (KISS-ICP, MapClosures' loop detection and its own pose graph, the
same points), and odometry alone, the floor.

The logs:

* the demo apartment's robot (``tests/host_bridge/slam/robot_logs.py``: true poses known,
  odometry 5 % long and turning 2 deg/m, 1 cm of range noise): a TurtleBot laser (360 beams,
  3.5 m, 10 Hz) for 100 s, 1.6 laps, so the robot comes back and a loop can be closed; and a
  Hokuyo UTM-30LX-like laser (1080 beams over 270 deg, 30 m, 40 Hz) for 30 s, half a lap;
* CCNY's real Hokuyo log (``../shared/data/hokuyo_scan_ccny`` beside the repo: 360 scans of
  681 beams, 5.6 m, 35.8 s) with no odometry and no truth: the engines that need odometry are
  left out, the floor ("odometry alone") is every scan drawn where the first was, and accuracy
  can only be judged by consistency.

Columns: "ATE" the RMS position error against the truth (each trajectory placed at the true
first pose, as ``tests/host_bridge/slam/test_engine.py`` does; no fitted alignment), "worst" its
largest; each map is judged the same way, every scan drawn into the host's 5 cm occupancy grid
(``host_bridge.slam.grid``) at the engine's pose for it: "walls" the mean distance of the
echoes so placed to the apartment's true walls, "occupied" the cells above 65 % (the same walls
drawn blurred take more cells), "on walls" the fraction of echoes in or next to an occupied cell
of that map (the real Hokuyo log's test); "start-end" how far the trajectory ends from its
start, "from ours" the RMS distance of its positions from ours'; "ms/scan" CPU
(``time.process_time``: every thread, the engine's calls alone, one thread asked of each
library); "RSS +MB" the growth of peak RSS from just before the engine's library is imported
(one process per engine and log); "loops" the closures made. Above the tables: the installed
size of each library with every dependency, and the part a host with ``[host]`` lacks.

Needs packages outside the project's extras (KISS-SLAM pins numpy below 2.3 and pulls Open3D, so
a venv of its own: benchmarks/README.md); engines whose packages are missing are named and
skipped. Opt-in: ``python -m benchmarks slam_engines`` or ``python benchmarks/slam_engines.py``.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import importlib.util
import itertools
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

OPT_IN = True
BUDGET_SECONDS = 900
CASE_TIMEOUT_S = 300.0
NO_LOOPS = 10**9
"""``loop_min_separation`` that no keyframe count reaches: the loop search never has candidates."""
KISS_SLAM_SPLIT_M = 3.0
"""KISS-SLAM's local maps end every this many metres (its default, 100 m, is made for cars: the
apartment's loop is 13 m)."""
FloatArray = npt.NDArray[np.float64]
ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: tests/ for the simulated robot's logs
    sys.path.insert(0, str(ROOT))
HOKUYO_BAG = ROOT.parent / "shared" / "data" / "hokuyo_scan_ccny" / "laser_scan_matcher_demo.bag"
"""Beside the repo, as the tests find it (tests/conftest.py)."""


@dataclass(frozen=True, slots=True)
class LaserData:
    """One log's scans as every engine is fed them, with odometry and truth where known."""

    ranges: npt.NDArray[np.float32]
    """(scans, beams)."""
    stamps_ns: npt.NDArray[np.int64]
    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float
    mount: FloatArray
    """The laser on the base (x, y, yaw)."""
    odom: FloatArray | None
    truth: FloatArray | None

    def save(self, path: Path) -> None:
        arrays: dict[str, npt.NDArray[Any]] = {
            "ranges": self.ranges, "stamps_ns": self.stamps_ns, "mount": self.mount,
            "geometry": np.array([self.angle_min, self.angle_increment, self.range_min, self.range_max])}
        arrays |= {k: v for k, v in (("odom", self.odom), ("truth", self.truth)) if v is not None}
        np.savez(path, **arrays)  # type: ignore[arg-type]

    @classmethod
    def load(cls, path: Path) -> LaserData:
        with np.load(path) as saved:
            angle_min, increment, range_min, range_max = (float(v) for v in saved["geometry"])
            return cls(saved["ranges"], saved["stamps_ns"], angle_min, increment, range_min, range_max,
                       saved["mount"], saved.get("odom"), saved.get("truth"))


@dataclass(frozen=True, slots=True)
class Log:
    name: str
    describe: str
    make: Callable[[], LaserData]


def simulated(**laser: Any) -> Callable[[], LaserData]:
    def make() -> LaserData:
        from tests.host_bridge.slam.robot_logs import LASER_XY, LaserLog, simulate

        run = simulate(LaserLog(range_noise=0.01, **laser))
        scans = [s for s in run.scans if s.ranges is not None]
        return LaserData(np.array([s.ranges for s in scans]), np.array([s.stamp_ns for s in scans]),
                         run.angle_min, run.angle_increment, run.log.range_min, run.log.range_max,
                         np.array([*LASER_XY, 0.0]), np.array([s.odom for s in scans]),
                         np.array([s.truth for s in scans]))

    return make


def hokuyo() -> LaserData:
    from rosbags.highlevel import AnyReader

    with AnyReader([HOKUYO_BAG]) as reader:
        msgs: list[tuple[int, Any]] = [
            (stamp, reader.deserialize(raw, c.msgtype)) for c, stamp, raw in reader.messages()]
    first = msgs[0][1]
    return LaserData(np.array([m.ranges for _, m in msgs], np.float32), np.array([s for s, _ in msgs]),
                     float(first.angle_min), float(first.angle_increment), float(first.range_min),
                     float(first.range_max), np.zeros(3), None, None)


LOGS = (
    Log("loop-360", "apartment, 360 beams 3.5 m 10 Hz, 100 s (1.6 laps: a loop)",
        simulated(seconds=100.0, scan_hz=10.0)),
    Log("half-1080", "apartment, 1080 beams 270 deg 30 m 40 Hz, 30 s (half a lap)",
        simulated(seconds=30.0, scan_hz=40.0, beams=1080, fov_deg=270.0, range_max=30.0)),
    Log("ccny-hokuyo", "CCNY's real Hokuyo log, 681 beams 5.6 m 10 Hz, 36 s, no odometry or truth",
        hokuyo),
)


@dataclass(frozen=True, slots=True)
class Inputs:
    """What the engines take, made before any clock starts."""

    data: LaserData
    scans: list[Any]
    """host_bridge.slam.scan.Scan per scan, in the base frame."""
    points: list[FloatArray]
    """The echoes as (n, 3) points, z = 0, in the base frame."""
    steps: list[FloatArray | None]
    """The odometry's motion since the previous scan (None for the first, or without odometry)."""
    max_range: float
    """What the engines are told of the laser's reach (ours: its ``max_range`` setting too)."""
    kiss_voxel: float | None = None
    """KISS-ICP's voxel in metres (None: its own rule, max_range / 100)."""


def inputs_of(data: LaserData, kiss_voxel: float | None = None) -> Inputs:
    from host_bridge.slam.pose import between, to_matrix
    from host_bridge.slam.scan import scan_from_ranges
    from host_bridge.slam.settings import SlamSettings

    limit = SlamSettings().max_range
    max_range = data.range_max if limit is None else min(data.range_max, limit)
    mount = to_matrix(data.mount)
    scans = [scan_from_ranges(r, data.angle_min, data.angle_increment, data.range_min, data.range_max,
                              max_range=max_range).moved(mount) for r in data.ranges]
    points = [np.column_stack([s.points, np.zeros(len(s.points))]) for s in scans]
    steps: list[FloatArray | None] = [None] * len(scans)
    if data.odom is not None:
        steps[1:] = [between(a, b) for a, b in itertools.pairwise(data.odom)]
    return Inputs(data, scans, points, steps, max_range, kiss_voxel)


@dataclass(frozen=True, slots=True)
class Mapped:
    poses: FloatArray
    """(scans, 3): the base at each scan, in the engine's own frame."""
    closures: int | None = None


Runner = Callable[[], Mapped]


def odometry_alone(inputs: Inputs) -> Runner:
    def run() -> Mapped:
        odom = inputs.data.odom
        return Mapped(np.zeros((len(inputs.scans), 3)) if odom is None else odom.copy())

    return run


def ours(odometry: bool, loops: bool) -> Callable[[Inputs], Runner]:
    def setup(inputs: Inputs) -> Runner:
        from host_bridge.slam.engine import Slam
        from host_bridge.slam.settings import SlamSettings

        # Loaded here, not in the first scan's add: the import counts in RSS, not in CPU.
        importlib.import_module("gtsam")
        importlib.import_module("small_gicp")
        settings = SlamSettings(enabled=True)
        if not loops:
            settings = dataclasses.replace(settings, loop_min_separation=NO_LOOPS)
        odom = inputs.data.odom

        def run() -> Mapped:
            slam = Slam(settings)
            for i, (scan, stamp) in enumerate(zip(inputs.scans, inputs.data.stamps_ns, strict=True)):
                slam.add(scan, int(stamp), odom[i] if odometry and odom is not None else None)
            return Mapped(slam.trajectory()[1], slam.closures)

        return run

    return setup


def kiss_odometry_config(inputs: Inputs) -> dict[str, Any]:
    """KISS-ICP's defaults for this laser: its voxel is max_range / 100 (``load_config``; or
    ``--kiss-voxel``); no minimum range (its default, 0, kept: a 5 m one is the suggestion for
    cars); no deskewing (the scans carry no per-point times); one thread."""
    config = importlib.import_module("kiss_icp.config.config")
    return {
        "data": config.DataConfig(max_range=inputs.max_range, min_range=0.0, deskew=False),
        "registration": config.RegistrationConfig(max_num_threads=1),
        "mapping": config.MappingConfig(
            voxel_size=inputs.max_range / 100.0 if inputs.kiss_voxel is None else inputs.kiss_voxel),
    }


def kiss_icp(odometry: bool) -> Callable[[Inputs], Runner]:
    def setup(inputs: Inputs) -> Runner:
        from host_bridge.slam.pose import from_matrix, to_matrix

        kiss = importlib.import_module("kiss_icp.kiss_icp")
        parser = importlib.import_module("kiss_icp.config.parser")
        config = parser.KISSConfig(**kiss_odometry_config(inputs))
        no_times = np.empty(0)

        def run() -> Mapped:
            icp = kiss.KissICP(config)
            poses = []
            for points, step in zip(inputs.points, inputs.steps, strict=True):
                if odometry and step is not None:
                    # Its prediction is last_pose @ last_delta: the odometry's increment instead
                    # of the last scan's motion.
                    icp.last_delta = to_matrix(step)
                icp.register_frame(points, no_times)
                poses.append(from_matrix(icp.last_pose))
            return Mapped(np.array(poses))

        return run

    return setup


def kiss_slam(inputs: Inputs) -> Runner:
    """KISS-SLAM scaled down to rooms: a local map every :data:`KISS_SLAM_SPLIT_M`, its voxels
    the odometry's, MapClosures' density maps at 5 cm (its default 0.5 m is 16 x 12 pixels for
    the whole apartment). MapClosures found no closure candidate on the apartment's loop at
    density maps of 5, 10 or 50 cm, 3 or 6 m local maps, 50 or 100 bits of Hamming distance, 3
    or 5 inliers: it looks for features in a bird's-eye density image, which a single plane of
    points gives it little of."""
    from host_bridge.slam.pose import from_matrix

    config_module = importlib.import_module("kiss_slam.config.config")
    closures_config = importlib.import_module("map_closures.config.config")
    slam_module = importlib.import_module("kiss_slam.slam")
    odometry = kiss_odometry_config(inputs)
    config = config_module.KissSLAMConfig(
        odometry=config_module.KissOdometryConfig(
            preprocessing=odometry["data"], registration=odometry["registration"],
            mapping=odometry["mapping"]),
        local_mapper=config_module.LocalMapperConfig(
            splitting_distance=KISS_SLAM_SPLIT_M, voxel_size=odometry["mapping"].voxel_size),
        loop_closer=config_module.LoopCloserConfig(
            detector=closures_config.MapClosuresConfig(density_map_resolution=0.05)),
    )
    no_times = np.empty(0)

    def run() -> Mapped:
        slam = slam_module.KissSLAM(config)
        for points in inputs.points:
            slam.process_scan(points, no_times)
        # What its pipeline does after the last scan (kiss_slam.pipeline.SlamPipeline._run_pipeline).
        slam.generate_new_node()
        slam.local_map_graph.erase_last_local_map()
        poses, _ = slam.fine_grained_optimization()
        return Mapped(np.array([from_matrix(p) for p in poses]), len(slam.closures))

    return run


@dataclass(frozen=True, slots=True)
class Engine:
    name: str
    setup: Callable[[Inputs], Runner]
    odometry: bool
    """Needs the log's odometry (left out on a log without)."""
    modules: tuple[str, ...] = ()
    distributions: tuple[str, ...] = ()
    """What to install: named when missing, and weighed."""


def our_engine(name: str, odometry: bool, loops: bool) -> Engine:
    return Engine(name, ours(odometry, loops), odometry, ("small_gicp", "gtsam"), ("small-gicp", "gtsam"))


ENGINES = (
    Engine("odometry alone", odometry_alone, False),
    our_engine("ours", odometry=True, loops=True),
    our_engine("ours, no loops", odometry=True, loops=False),
    our_engine("ours, scan only", odometry=False, loops=True),
    our_engine("ours, scan, no loops", odometry=False, loops=False),
    Engine("kiss-icp + odom", kiss_icp(odometry=True), True, ("kiss_icp",), ("kiss-icp",)),
    Engine("kiss-icp", kiss_icp(odometry=False), False, ("kiss_icp",), ("kiss-icp",)),
    Engine("kiss-slam", kiss_slam, False, ("kiss_slam", "map_closures", "open3d"), ("kiss-slam",)),
)


def status_mb(key: str) -> float:
    """``VmRSS`` (now) or ``VmHWM`` (peak) of this process. Not ``ru_maxrss``: Linux carries the
    forking parent's peak over the exec into it."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(f"{key}:"):
            return int(line.split()[1]) / 1024
    msg = f"/proc/self/status has no {key}"
    raise RuntimeError(msg)


def run_case(data_path: Path, engine_name: str, kiss_voxel: float | None) -> dict[str, Any]:
    """One engine on one log, in a process of its own (so its peak RSS is its own)."""
    engine = next(e for e in ENGINES if e.name == engine_name)
    inputs = inputs_of(LaserData.load(data_path), kiss_voxel)
    before = status_mb("VmRSS")
    run = engine.setup(inputs)
    started = time.process_time()
    mapped = run()
    cpu = time.process_time() - started
    peak = status_mb("VmHWM")
    return {"poses": mapped.poses.tolist(), "closures": mapped.closures, "cpu_s": cpu,
            "rss_growth_mb": peak - before}


def measured(data_path: Path, engine: Engine, kiss_voxel: float | None) -> dict[str, Any] | str:
    """The case's figures, or why there are none."""
    with tempfile.TemporaryDirectory(prefix="slam-engine-") as tmp:
        out = Path(tmp) / "case.json"
        command = [sys.executable, str(Path(__file__).resolve()), "--case", str(data_path), engine.name,
                   str(out)]
        if kiss_voxel is not None:
            command += ["--kiss-voxel", str(kiss_voxel)]
        try:
            done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True,
                                  timeout=CASE_TIMEOUT_S, check=False)
        except subprocess.TimeoutExpired:
            return f"stopped after {CASE_TIMEOUT_S:.0f} s"
        if done.returncode != 0 or not out.exists():
            last = (done.stderr.strip().splitlines() or ["no output"])[-1]
            return f"failed (exit {done.returncode}): {last[:160]}"
        return json.loads(out.read_text())  # type: ignore[no-any-return]


# Installed size


def _name(distribution: str) -> str:
    return re.sub(r"[-_.]+", "-", distribution).lower()


def _requirements(distribution: str, extras: Iterable[str]) -> list[tuple[str, tuple[str, ...]]]:
    """The distributions ``distribution`` (with ``extras``) requires in this environment."""
    from packaging.requirements import Requirement

    found = []
    for text in metadata.requires(distribution) or []:
        requirement = Requirement(text)
        wanted = requirement.marker is None or any(
            requirement.marker.evaluate({"extra": extra}) for extra in ("", *extras))
        if wanted:
            found.append((requirement.name, tuple(requirement.extras)))
    return found


def dependency_closure(roots: Iterable[tuple[str, tuple[str, ...]]]) -> set[str]:
    """Every installed distribution the roots need, themselves included."""
    seen: set[tuple[str, tuple[str, ...]]] = set()
    names: set[str] = set()
    todo = list(roots)
    while todo:
        name, extras = todo.pop()
        if (_name(name), extras) in seen:
            continue
        seen.add((_name(name), extras))
        try:
            metadata.distribution(name)
        except metadata.PackageNotFoundError:
            continue
        names.add(_name(name))
        todo.extend(_requirements(name, extras))
    return names


def installed_mb(name: str) -> float:
    files = metadata.distribution(name).files or []
    return sum(path.stat().st_size for f in files if (path := Path(str(f.locate()))).is_file()) / 1e6


def install_weight(distributions: tuple[str, ...]) -> tuple[float, float] | None:
    """MB installed by the distributions with their dependencies, and the part of it that
    swanky's ``[host]`` extra does not install anyway (None: not installed here)."""
    if not distributions:
        return (0.0, 0.0)
    try:
        for name in distributions:
            metadata.distribution(name)
    except metadata.PackageNotFoundError:
        return None
    needed = dependency_closure((name, ()) for name in distributions)
    host = dependency_closure(_requirements("swanky", ("host",)))
    return (sum(installed_mb(n) for n in needed), sum(installed_mb(n) for n in needed - host))


# Judging the maps


@dataclass(frozen=True, slots=True)
class Figures:
    ate_cm: float | None
    worst_cm: float | None
    true_walls_cm: float | None
    occupied: int
    on_walls: float
    start_end_m: float
    from_ours_cm: float | None
    """RMS distance between this trajectory's positions and ours' (the first of ours that ran)."""
    ms_per_scan: float
    rss_growth_mb: float
    closures: int | None


def placed(poses: FloatArray, start: FloatArray) -> FloatArray:
    """The trajectory moved so that its first pose is ``start``."""
    from host_bridge.slam.pose import between, compose

    first = poses[0]
    return np.array([compose(start, between(first, p)) for p in poses])


def map_figures(inputs: Inputs, poses: FloatArray) -> tuple[int, float, float | None]:
    """Occupied cells, the fraction of echoes on them, and (truth known) the echoes' mean
    distance to the true walls."""
    from host_bridge.demo.world import distance_to_walls
    from host_bridge.slam.grid import TiledGrid
    from host_bridge.slam.pose import transform_points
    from host_bridge.slam.settings import SlamSettings

    resolution = SlamSettings().resolution
    grid = TiledGrid(resolution)
    for scan, pose in zip(inputs.scans, poses, strict=True):
        grid.add(scan, pose)
    dense = grid.dense()
    occupied = dense.cells > 65
    near = occupied.copy()
    for axis in (0, 1):
        for shift in (1, -1):
            near |= np.roll(occupied, shift, axis)
    hits = total = 0
    distances = []
    for scan, pose in zip(inputs.scans, poses, strict=True):
        world = transform_points(pose, scan.points)
        col = np.floor((world[:, 0] - dense.origin[0]) / resolution).astype(int)
        row = np.floor((world[:, 1] - dense.origin[1]) / resolution).astype(int)
        inside = (row >= 0) & (row < near.shape[0]) & (col >= 0) & (col < near.shape[1])
        hits += int(near[row[inside], col[inside]].sum())
        total += len(world)
        if inputs.data.truth is not None:
            distances.append(distance_to_walls(world))
    walls = float(np.mean(np.concatenate(distances))) if distances else None
    return int(occupied.sum()), hits / max(total, 1), walls


def start_of(inputs: Inputs) -> FloatArray:
    """Where every trajectory is placed to begin: the truth's first pose, else the origin."""
    truth = inputs.data.truth
    return truth[0] if truth is not None else np.zeros(3)


def figures(inputs: Inputs, found: dict[str, Any], ours_poses: FloatArray | None) -> Figures:
    """``ours_poses``: ours' trajectory, placed (None: this is ours, or ours did not run)."""
    truth = inputs.data.truth
    poses = placed(np.array(found["poses"]), start_of(inputs))
    ate = worst = None
    if truth is not None:
        error = np.hypot(*(poses[:, :2] - truth[:, :2]).T)
        ate, worst = float(np.sqrt(np.mean(error**2))) * 100, float(error.max()) * 100
    occupied, on_walls, walls = map_figures(inputs, poses)
    from_ours = None
    if ours_poses is not None:
        from_ours = float(np.sqrt(np.mean(np.sum((poses[:, :2] - ours_poses[:, :2]) ** 2, axis=1)))) * 100
    return Figures(ate, worst, None if walls is None else walls * 100, occupied, on_walls,
                   float(np.hypot(*(poses[-1, :2] - poses[0, :2]))), from_ours,
                   found["cpu_s"] / len(poses) * 1e3, found["rss_growth_mb"], found["closures"])


def _cell(value: float | None, width: int, digits: int = 0) -> str:
    """``value`` right-aligned in ``width`` with ``digits`` decimals, or a dash as wide."""
    return "-".rjust(width) if value is None else f"{value:{width}.{digits}f}"


def table(rows: list[tuple[Engine, Figures | str]]) -> list[str]:
    lines = [f"  {'engine':<20} {'ATE cm':>7} {'worst':>6} {'walls cm':>8} {'occupied':>8} "
             f"{'on walls':>8} {'start-end':>9} {'from ours':>9} {'ms/scan':>7} {'RSS +MB':>7} {'loops':>5}"]
    for engine, found in rows:
        if isinstance(found, str):
            lines.append(f"  {engine.name:<20} {found}")
            continue
        lines.append(
            f"  {engine.name:<20} {_cell(found.ate_cm, 7, 2)} {_cell(found.worst_cm, 6, 1)} "
            f"{_cell(found.true_walls_cm, 8, 2)} {found.occupied:8d} {found.on_walls:8.3f} "
            f"{found.start_end_m:8.2f}m {_cell(found.from_ours_cm, 9, 2)} {found.ms_per_scan:7.2f} "
            f"{found.rss_growth_mb:7.0f} {_cell(found.closures, 5)}")
    return lines


def verdict(rows: list[tuple[Engine, Figures | str]], mine_name: str, scan_only: bool) -> str | None:
    """``mine_name`` against the best alternative engine (``scan_only``: of those not given the
    odometry): accuracy first (the ATE where the truth is known, else the echoes on walls), and
    the CPU. None when either did not run."""
    done = [(e, f) for e, f in rows if isinstance(f, Figures)]
    ours_rows = [(e, f) for e, f in done if e.name == mine_name]
    others = [(e, f) for e, f in done if not e.name.startswith("ours") and e.name != "odometry alone"
              and not (scan_only and e.odometry)]
    if not ours_rows or not others:
        return None

    def score(figures: Figures) -> float:
        return figures.ate_cm if figures.ate_cm is not None else -figures.on_walls

    mine_engine, mine = ours_rows[0]
    best_engine, best = min(others, key=lambda row: score(row[1]))
    if mine.ate_cm is not None and best.ate_cm is not None:
        accuracy = (f"ATE {mine.ate_cm:.2f} cm vs {best.ate_cm:.2f} cm "
                    f"(the alternative's error is {best.ate_cm / mine.ate_cm:.1f}x ours)")
    else:
        accuracy = f"echoes on walls {mine.on_walls:.3f} vs {best.on_walls:.3f}"
    return (f"  {mine_engine.name} vs the best alternative, {best_engine.name}: {accuracy}; CPU "
            f"{mine.ms_per_scan:.2f} vs {best.ms_per_scan:.2f} ms/scan (ratio ours/alternative "
            f"{mine.ms_per_scan / best.ms_per_scan:.2f})")


def missing(engine: Engine) -> list[str]:
    return [m for m in engine.modules if importlib.util.find_spec(m) is None]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--case", nargs=3, metavar=("DATA", "ENGINE", "OUT"), help=argparse.SUPPRESS)
    parser.add_argument("--logs", nargs="*", default=[log.name for log in LOGS],
                        choices=[log.name for log in LOGS], help="the logs to map (default: all)")
    parser.add_argument("--kiss-voxel", type=float, default=None, metavar="METRES",
                        help="KISS-ICP's and KISS-SLAM's voxel (default: theirs, max range / 100)")
    args = parser.parse_args()
    if args.case:
        data, name, out = args.case
        Path(out).write_text(json.dumps(run_case(Path(data), name, args.kiss_voxel)))
        return
    print(f"load average (1, 5, 15 min) at the start: {' '.join(f'{v:.2f}' for v in os.getloadavg())}",
          flush=True)
    print("installed size, MB, with every dependency (in brackets: what [host] does not install already)")
    for distributions in dict.fromkeys(e.distributions for e in ENGINES if e.distributions):
        weight = install_weight(distributions)
        shown = "not installed" if weight is None else f"{weight[0]:7.1f} ({weight[1]:6.1f})"
        print(f"  {' + '.join(distributions):<20} {shown}")
        users = [e for e in ENGINES if e.distributions == distributions]
        if absent := sorted({m for e in users for m in missing(e)}):
            print(f"    skipped: {', '.join(e.name for e in users)} ({', '.join(absent)} not importable; "
                  f"pip install {' '.join(distributions)})")
    with tempfile.TemporaryDirectory(prefix="slam-engines-") as tmp:
        for log in LOGS:
            if log.name not in args.logs:
                continue
            if log.make is hokuyo and not HOKUYO_BAG.exists():
                print(f"{log.name}: {HOKUYO_BAG} not found, skipped")
                continue
            data = log.make()
            path = Path(tmp) / f"{log.name}.npz"
            data.save(path)
            inputs = inputs_of(data, args.kiss_voxel)
            truly = ("" if data.truth is None else
                     f", ending {np.hypot(*(data.truth[-1, :2] - data.truth[0, :2])):.2f} m from its start")
            print(f"{log.name}: {log.describe}; {len(data.ranges)} scans{truly}", flush=True)
            rows: list[tuple[Engine, Figures | str]] = []
            ours_poses: FloatArray | None = None
            print(table(rows)[0], flush=True)
            for engine in ENGINES:
                if missing(engine) or (engine.odometry and data.odom is None):
                    continue
                found = measured(path, engine, args.kiss_voxel)
                if isinstance(found, str):
                    rows.append((engine, found))
                else:
                    rows.append((engine, figures(inputs, found, ours_poses)))
                    if ours_poses is None and engine.name.startswith("ours"):
                        ours_poses = placed(np.array(found["poses"]), start_of(inputs))
                print(table(rows[-1:])[-1], flush=True)
            judged = [verdict(rows, "ours", False), verdict(rows, "ours, scan only", True)]
            print("\n".join(line for line in judged if line) or "  no alternative engine ran",
                  flush=True)
    print(f"load average at the end: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
