"""2D SLAM of one robot: each scan matched against a local map with the odometry's motion as
the first guess, keyframes in a pose graph, loop closures when the robot comes back, and the
occupancy grid drawn from the keyframes at their optimised poses.

Registration is small_gicp's GICP (``small_gicp.align``): the scan's echoes, and the map's, are
stood up as three rows of points 5 cm apart in z, so each wall is a vertical plane whose normal
lies in the floor's plane and GICP's plane-to-plane costs constrain x, y and yaw (flat points
give it two degenerate directions to choose between); the 6-DoF result is flattened back to
SE(2). Measured on the demo apartment's loop (5 % odometry scale error, 2 deg/m heading drift,
scan-to-map without loop closures, 120 s): point-to-point ICP 11 cm RMS, point-to-plane 7 mm,
GICP 0.15 mm. Points are thinned to one per 5 cm voxel: against 2 cm voxels this took 2.9 s
instead of 3.6 s of CPU for 60 s of a 10 Hz 360-beam laser, at 2.3 mm instead of 7.8 mm RMS
(``benchmarks/slam.py`` runs it). Two rows 5 cm apart were faster still (1.9 s) but lost the
way on a 5 Hz laser turning 0.3 rad between scans (7.6 cm RMS against 0.5 cm).

Nothing here knows ROS or Rerun: the host's feeder (:mod:`host_bridge.slam.feeder`) turns
messages into :class:`~host_bridge.slam.scan.Scan` and odometry poses and logs what comes back.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from host_bridge.slam.graph import PoseGraph
from host_bridge.slam.grid import DenseMap, TiledGrid
from host_bridge.slam.pose import (
    Pose2,
    between,
    compose,
    from_matrix,
    inverse,
    to_matrix,
    transform_points,
)
from host_bridge.slam.scan import Scan
from host_bridge.slam.settings import SlamSettings

FloatArray = npt.NDArray[np.float64]
_LAYERS = np.array([-0.05, 0.0, 0.05])
_DOWNSAMPLE = 0.05
_NEIGHBOURS = 10
_LOOP_WINDOW = 5
"""A loop candidate's submap: the keyframes this many before and after it."""
_JUMP_TURN = math.radians(45.0)
_LOOP_EVERY = 5
"""Keyframes after a loop closure before the next search: one closure per metre or so ties the
revisited stretch down; one per keyframe only costs optimisations."""
_REDRAW_SHIFT = 0.5
"""Cells a keyframe must move in an optimisation for the grid to be drawn again."""


def _stood_up(points: FloatArray) -> FloatArray:
    return np.concatenate([np.column_stack([points, np.full(len(points), z)]) for z in _LAYERS])


def _cloud(points: FloatArray) -> tuple[object, object]:
    """A small_gicp cloud (with covariances) and its k-d tree, of 2D points."""
    import small_gicp

    return small_gicp.preprocess_points(  # type: ignore[no-any-return]
        _stood_up(points), downsampling_resolution=_DOWNSAMPLE, num_neighbors=_NEIGHBOURS,
        num_threads=1,
    )


@dataclass(frozen=True, slots=True)
class Match:
    pose: Pose2
    matched: float
    """Fraction of the scan's points with a partner in the map."""


def _align(target: tuple[object, object], source: object, guess: Pose2, reach: float) -> Match:
    import small_gicp

    cloud, tree = target
    result = small_gicp.align(
        cloud, source, tree, init_T_target_source=to_matrix(guess), registration_type="GICP",
        max_correspondence_distance=reach, num_threads=1, max_iterations=30,
    )
    size = source.size()  # type: ignore[attr-defined]
    return Match(from_matrix(result.T_target_source), result.num_inliers / size if size else 0.0)


@dataclass(slots=True)
class Keyframe:
    scan: Scan
    pose: Pose2
    """In the map frame, as last optimised."""
    stamp_ns: int
    points: FloatArray
    """The scan's echoes in the base frame."""
    cloud: object = None
    """small_gicp cloud of ``points`` (as a loop closure's source), made when first needed."""


@dataclass(frozen=True, slots=True)
class Update:
    """What one scan did."""

    pose: Pose2
    """The base in the map frame."""
    matched: float | None
    """Fraction of echoes matched, None when the scan was not matched (the first one, or no
    map yet) or the match was refused (then the odometry's prediction is the pose)."""
    keyframe: bool
    closures: tuple[tuple[int, int], ...] = ()
    """Loop closures found with this scan: (older keyframe, newer keyframe)."""
    moved: bool = False
    """The pose graph moved keyframes: the map and trajectory were redrawn."""
    jumped: bool = False
    """The odometry jumped (a reset): a new segment started here."""
    seconds: float = 0.0


@dataclass(slots=True)
class _Anchor:
    """A scan's pose as the keyframe it was taken after, and where from it."""

    stamp_ns: int
    keyframe: int
    offset: Pose2


@dataclass(slots=True)
class Slam:
    settings: SlamSettings
    keyframes: list[Keyframe] = field(default_factory=list)
    segments: int = 0
    pose: Pose2 | None = None
    _grid: TiledGrid | None = None
    _graph: PoseGraph | None = None
    _anchors: list[_Anchor] = field(default_factory=list)
    _odom: Pose2 | None = None
    _velocity: Pose2 | None = None
    _local: tuple[object, object] | None = None
    _local_count: int = -1
    _last_closure: int = -_LOOP_EVERY
    _grid_stale: bool = False

    def __post_init__(self) -> None:
        self._grid = TiledGrid(self.settings.resolution)
        self._graph = PoseGraph()

    @property
    def grid(self) -> TiledGrid:
        assert self._grid is not None
        return self._grid

    @property
    def closures(self) -> int:
        assert self._graph is not None
        return self._graph.closures

    def add(self, scan: Scan, stamp_ns: int, odom: Pose2 | None) -> Update:
        """Take one scan (in the base frame) at ``stamp_ns`` with the odometry pose of the base
        then (None: scan matching alone, a constant-velocity guess)."""
        started = time.perf_counter()
        jumped = False
        if self.pose is None:
            start = odom if odom is not None else np.zeros(3)
            self.pose = start.copy()
            self._odom = odom
            self._add_keyframe(scan, stamp_ns, self.pose, None, True)
            return Update(self.pose, None, True, seconds=time.perf_counter() - started)
        step = None
        if odom is not None and self._odom is not None:
            step = between(self._odom, odom)
            if math.hypot(step[0], step[1]) > self.settings.odometry_jump or abs(step[2]) > _JUMP_TURN:
                step, jumped = None, True
                self.segments += 1
        elif odom is None and self._velocity is not None:
            step = self._velocity
        self._odom = odom
        guess = self.pose if step is None else compose(self.pose, step)
        points = scan.points
        match = self._match(points, guess)
        previous = self.pose
        self.pose = guess if match is None else match.pose
        self._velocity = between(previous, self.pose)
        last = self.keyframes[-1]
        since = between(last.pose, self.pose)
        update = Update(self.pose, None if match is None else match.matched, False, jumped=jumped)
        if (math.hypot(since[0], since[1]) >= self.settings.keyframe_distance
                or abs(since[2]) >= math.radians(self.settings.keyframe_angle) or jumped):
            closures = self._add_keyframe(scan, stamp_ns, self.pose, since, match is not None)
            update = Update(self.pose, update.matched, True, tuple(closures), bool(closures), jumped)
        else:
            self._anchors.append(_Anchor(stamp_ns, len(self.keyframes) - 1, since))
        return Update(update.pose, update.matched, update.keyframe, update.closures, update.moved,
                      update.jumped, time.perf_counter() - started)

    def _match(self, points: FloatArray, guess: Pose2) -> Match | None:
        if len(points) < self.settings.min_points:
            return None
        if self._local_count != len(self.keyframes):
            window = self.keyframes[-self.settings.local_keyframes :]
            self._local = _cloud(np.concatenate([transform_points(k.pose, k.points) for k in window]))
            self._local_count = len(self.keyframes)
        assert self._local is not None
        source, _ = _cloud(points)
        match = _align(self._local, source, guess, self.settings.max_correspondence)
        correction = between(guess, match.pose)
        limit = self.settings.max_correction
        if (match.matched < self.settings.min_matched or math.hypot(correction[0], correction[1]) > limit
                or abs(correction[2]) > math.radians(50.0 * limit)):
            return None
        return match

    def _add_keyframe(self, scan: Scan, stamp_ns: int, pose: Pose2, relative: Pose2 | None,
                      matched: bool) -> list[tuple[int, int]]:
        assert self._graph is not None
        keyframe = Keyframe(scan, pose.copy(), stamp_ns, scan.points)
        self.keyframes.append(keyframe)
        index = self._graph.add(pose, relative, matched)
        self._anchors.append(_Anchor(stamp_ns, index, np.zeros(3)))
        self.grid.add(scan, pose)
        if index - self._last_closure < _LOOP_EVERY:
            return []
        closures = self._close_loops(index)
        if closures:
            self._last_closure = index
            self._optimize()
        return closures

    def _close_loops(self, newest: int) -> list[tuple[int, int]]:
        """Match the newest keyframe against the map around the nearest old keyframe."""
        settings = self.settings
        current = self.keyframes[newest]
        if len(current.points) < settings.min_points:
            return []
        old = self.keyframes[: max(0, newest - settings.loop_min_separation)]
        if not old:
            return []
        positions = np.array([k.pose[:2] for k in old])
        distance = np.hypot(*(positions - current.pose[:2]).T)
        nearest = int(np.argmin(distance))
        if distance[nearest] > settings.loop_radius:
            return []
        anchor = old[nearest].pose
        window = self.keyframes[max(0, nearest - _LOOP_WINDOW) : nearest + _LOOP_WINDOW + 1]
        submap = _cloud(np.concatenate(
            [transform_points(between(anchor, k.pose), k.points) for k in window]))
        if current.cloud is None:
            current.cloud = _cloud(current.points)[0]
        guess = between(anchor, current.pose)
        # Coarse, then fine: the drift since the robot was last here may exceed the fine reach.
        coarse = _align(submap, current.cloud, guess, max(1.0, 3.0 * settings.max_correspondence))
        match = _align(submap, current.cloud, coarse.pose, settings.max_correspondence)
        if match.matched < settings.loop_min_matched:
            return []
        assert self._graph is not None
        self._graph.close_loop(nearest, newest, match.pose)
        return [(nearest, newest)]

    def _optimize(self) -> None:
        assert self._graph is not None
        assert self.pose is not None
        last = self.keyframes[-1]
        offset = between(last.pose, self.pose)
        shift = 0.0
        for keyframe, pose in zip(self.keyframes, self._graph.optimize(), strict=True):
            moved = between(keyframe.pose, pose)
            # A turn counts as the shift it makes 2 m away.
            shift = max(shift, math.hypot(moved[0], moved[1]), abs(moved[2]) * 2.0)
            keyframe.pose = pose
        self.pose = compose(self.keyframes[-1].pose, offset)
        self._local_count = -1
        # Redrawn when next asked for (occupancy), not at every closure: a long log closes
        # hundreds of loops, and redrawing thousands of keyframes each time would dominate.
        self._grid_stale |= shift >= _REDRAW_SHIFT * self.settings.resolution

    def map_to_odom(self) -> Pose2 | None:
        """The correction the host publishes: map -> odom such that map -> odom -> base is the
        SLAM pose (None before the first scan or without odometry)."""
        if self.pose is None or self._odom is None:
            return None
        return compose(self.pose, inverse(self._odom))

    def occupancy(self) -> DenseMap:
        """The map, drawn again from every keyframe first if loop closures moved them."""
        if self._grid_stale:
            self._grid = TiledGrid(self.settings.resolution, self.grid.odds)
            for keyframe in self.keyframes:
                self._grid.add(keyframe.scan, keyframe.pose)
            self._grid_stale = False
        return self.grid.dense()

    def trajectory(self) -> tuple[npt.NDArray[np.int64], FloatArray]:
        """Every scan's stamp and base pose in the map frame, with the keyframes' latest poses."""
        stamps = np.array([a.stamp_ns for a in self._anchors], dtype=np.int64)
        poses = np.array([compose(self.keyframes[a.keyframe].pose, a.offset) for a in self._anchors])
        return stamps, poses.reshape(-1, 3)
