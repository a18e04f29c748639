"""SLAM in the host: a dispatcher tap that hands each robot's scans, odometry and transforms to
a thread of that robot's own, which runs :class:`~host_bridge.slam.engine.Slam` and logs what it
finds through the dispatcher.

The tap only sorts and queues raw messages (no decoding), so a robot's small topics, and every
other robot, never wait for its SLAM. A live robot whose SLAM falls behind loses its oldest
queued scans (counted, warned once); a bag (``lossless``) waits for SLAM instead, so every scan
of a bag is mapped and two conversions of one bag give one map.

What is logged for robot ``R`` (frames ``R/<id>``):

* ``/R/slam/map`` the occupancy grid (drawn as ``/map`` is, with the walls meshed from it at
  ``/R/slam/map/walls``), every ``map_period`` seconds of robot time and at the end;
* ``/R/slam/map_to_odom`` the transform ``R/map -> R/odom`` at every scan, so the model, scans
  and clouds stand in the map;
* ``/R/slam/trajectory`` the base's corrected path and ``/R/slam/loop_closures`` a segment per
  closure between the two poses it ties;
* ``/_stats/R/slam/{scan_ms,matched_fraction,closures}`` per scan.

Odometry: the ``odometry`` topic (nav_msgs/Odometry), else the ``odom_frame -> base`` transforms
of /tf; a scan waits for the odometry of its stamp (interpolated between two samples) until
odometry newer than it arrives, half a second of robot time live. The laser's pose on the base
comes from /tf_static, else the robot model's fixed joints.
"""

from __future__ import annotations

import bisect
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from fnmatch import fnmatchcase
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
import rerun as rr

from host_bridge.converters._common import frame_components, stamp_ns
from host_bridge.converters.occupancy import grid_items
from host_bridge.converters.segments import TileCache
from host_bridge.converters.walls import grid_wall_items
from host_bridge.core.contract import (
    STATS_ROOT,
    TIMELINE_LOG,
    TIMELINE_RECEIVE,
    TIMELINE_ROS,
    LogEntry,
    LogItem,
)
from host_bridge.core.decode import Decoder
from host_bridge.core.options import GridOptions
from host_bridge.core.state import Grid, RobotState
from host_bridge.errors import (
    HostError,
    NoLaserTransformError,
    NoOdometryError,
    OdometryJumpError,
    SlamBehindError,
    SlamError,
    SparseScanError,
    StampBackwardsError,
)
from host_bridge.slam.engine import Slam, Update
from host_bridge.slam.files import TRAJECTORY, write_map, write_trajectory
from host_bridge.slam.pose import Pose2, between, compose, inverse, pose2, quaternion_of, yaw_of
from host_bridge.slam.scan import Scan, finite_scan_geometry, scan_from_msg
from host_bridge.slam.settings import NO_ODOMETRY, ODOMETRY_FROM_TF, SlamSettings
from robot_relay.wire import RawMessage

log = logging.getLogger("swanky.host")


class Host(Protocol):
    """What SLAM uses of the host's dispatcher (dispatch.py): its decoder, its warnings (once
    per robot, topic and kind), logging with the robot's frame tree, the robot's state."""

    @property
    def decoder(self) -> Decoder: ...
    def warn(
        self, robot: str, topic: str, err: Exception, times: Mapping[str, int] | None = None
    ) -> None: ...
    def log(self, robot: str, entries: Sequence[LogEntry], times: Mapping[str, int]) -> None: ...
    def robot_state(self, robot: str) -> RobotState: ...

LASER_SCAN = "sensor_msgs/msg/LaserScan"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
BASE_FRAMES = ("base_footprint", "base_link")
SLAM_MAP_FRAME = "slam_map"
"""The host's map frame when the robot's own TF already gives odom a parent."""
LIVE_SCAN_BACKLOG = 4
"""Live: scans queued beyond this many are dropped, the oldest first (only the newest matter)."""
LOSSLESS_BACKLOG = 20000
"""A bag: the tap waits while this many messages are queued (SLAM runs behind the reader)."""
ODOMETRY_WAIT_NS = 500_000_000
"""Live: how long (robot time) a scan waits for the odometry of its stamp."""
ODOMETRY_REACH_NS = 500_000_000
"""How far past its last sample odometry is taken as still valid."""
NO_ODOMETRY_AFTER_NS = 2_000_000_000
"""Live: scans without any odometry for this long mean scan matching alone."""
ODOMETRY_KEPT = 100_000
"""Odometry samples kept while no scan is mapped (an hour of 30 Hz odometry is 108,000): a bag
may bring minutes of odometry before the scans of the same minutes."""
LIVE_CLOSE_S = 5.0
"""A live host stopping maps what its robots' SLAM still holds for this long at most."""
CLOSE_POLL_S = 0.1
MAP_COST_FACTOR = 4.0
"""A map is drawn again no sooner than this many times what drawing the last one took."""


def frame_of(robot: str, frame_id: str) -> str:
    return f"{robot}/{frame_id.strip('/')}"


class OdometryTrack:
    """Odometry poses by stamp, the last minute of them, interpolated at scan stamps."""

    def __init__(self) -> None:
        self.stamps: list[int] = []
        self.poses: list[Pose2] = []

    def __bool__(self) -> bool:
        return bool(self.stamps)

    @property
    def newest(self) -> int:
        return self.stamps[-1]

    def add(self, stamp: int, pose: Pose2) -> None:
        at = bisect.bisect_right(self.stamps, stamp)
        if at and self.stamps[at - 1] == stamp:
            return
        self.stamps.insert(at, stamp)
        self.poses.insert(at, pose)
        if len(self.stamps) > 2 * ODOMETRY_KEPT:  # a robot whose scans stopped coming
            del self.stamps[:ODOMETRY_KEPT], self.poses[:ODOMETRY_KEPT]

    def forget_before(self, stamp: int) -> None:
        """Drop the samples no scan at or after ``stamp`` needs (one before it stays)."""
        keep = max(bisect.bisect_left(self.stamps, stamp) - 1, 0)
        if keep > ODOMETRY_KEPT // 100:  # in batches: a list's front is dear to cut
            del self.stamps[:keep], self.poses[:keep]

    def at(self, stamp: int) -> Pose2 | None:
        """The pose at ``stamp``: between the samples around it, the nearest sample within
        :data:`ODOMETRY_REACH_NS` outside them, else None."""
        if not self.stamps:
            return None
        at = bisect.bisect_left(self.stamps, stamp)
        if at < len(self.stamps) and self.stamps[at] == stamp:
            return self.poses[at]
        if at == 0 or at == len(self.stamps):
            nearest = 0 if at == 0 else -1
            return self.poses[nearest] if abs(self.stamps[nearest] - stamp) <= ODOMETRY_REACH_NS else None
        t0, t1 = self.stamps[at - 1], self.stamps[at]
        fraction = (stamp - t0) / (t1 - t0)
        step = between(self.poses[at - 1], self.poses[at])
        return compose(self.poses[at - 1], step * fraction)


@dataclass(slots=True)
class _Frames:
    """A robot's transforms other than odometry (child -> parent, 4x4, the latest of each), from
    /tf_static and /tf."""

    parents: dict[str, tuple[str, npt.NDArray[np.float64]]] = field(default_factory=dict)

    def add(self, parent: str, child: str, translation: Any, rotation: Any) -> None:
        matrix = np.eye(4)
        x, y, z, w = (float(v) for v in (rotation.x, rotation.y, rotation.z, rotation.w))
        if not any((x, y, z, w)):
            w = 1.0
        norm = math.sqrt(x * x + y * y + z * z + w * w)
        x, y, z, w = x / norm, y / norm, z / norm, w / norm
        matrix[:3, :3] = [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
        matrix[:3, 3] = [float(translation.x), float(translation.y), float(translation.z)]
        self.parents[child.strip("/")] = (parent.strip("/"), matrix)

    def chain(self, base: str, frame: str, model: Any) -> npt.NDArray[np.float64] | None:
        """base -> frame through the transforms seen, else the model's fixed joints; None if no path."""
        matrix = np.eye(4)
        current = frame
        for _ in range(64):
            if current == base:
                return matrix
            step = self.parents.get(current) or _model_parent(model, current)
            if step is None:
                return None
            parent, relative = step
            matrix = relative @ matrix
            current = parent
        return None


def _model_parent(model: Any, child: str) -> tuple[str, npt.NDArray[np.float64]] | None:
    if model is None:
        return None
    for joint in model.joints.values():
        if joint.child.strip("/") == child and joint.type == "fixed":
            matrix = np.eye(4)
            matrix[:3, :3] = joint.rotation
            matrix[:3, 3] = joint.translation
            return joint.parent.strip("/"), matrix
    return None


@dataclass(slots=True)
class _PendingScan:
    raw: RawMessage
    scan: Scan
    stamp: int
    frame_id: str


class RobotSlam:
    """One robot's SLAM thread (see the module docstring)."""

    def __init__(self, robot: str, settings: SlamSettings, dispatcher: Host, *,
                 lossless: bool, expect_odometry: bool | None = None) -> None:
        self.robot = robot
        self.settings = settings
        self._dispatcher = dispatcher
        self._lossless = lossless
        # A bag says up front whether it holds odometry; live, it shows by arriving.
        self._expect_odometry = expect_odometry
        self.slam = Slam(settings)
        self._queue: deque[tuple[str, RawMessage]] = deque()
        self._queued_scans = 0
        self._cond = threading.Condition()
        self._closing = False
        self._abandon = False
        self._thread = threading.Thread(target=self._run, name=f"slam-{robot}", daemon=True)
        self._odometry = OdometryTrack()
        self._tf_odometry = OdometryTrack()
        self._frames = _Frames()
        self._pending: deque[_PendingScan] = deque()
        self._scan_topic: str | None = None
        self._base_frame = settings.base_frame
        self._last_stamp: int | None = None
        self._first_scan_stamp: int | None = None
        self._last_map_stamp: int | None = None
        self._last_map_wall = 0.0
        self._last_map_cost = 0.0
        self._closures: list[tuple[int, int]] = []
        self._walls = TileCache()
        self._warned_scan_only = False
        # A parent of odom in the robot's own TF (its SLAM or AMCL): the host's map is then
        # named SLAM_MAP_FRAME and hangs below odom, so the frames stay one tree.
        self._robot_map: str | None = None
        self.dropped = 0
        self._thread.start()

    # -- the tap's side ----------------------------------------------------------------------

    def put(self, kind: str, run: Sequence[RawMessage]) -> None:
        with self._cond:
            if self._lossless:
                self._cond.wait_for(lambda: len(self._queue) < LOSSLESS_BACKLOG or self._closing
                                    or self._abandon)
            for raw in run:
                self._queue.append((kind, raw))
            if kind == LASER_SCAN:
                self._queued_scans += len(run)
                if not self._lossless and self._queued_scans > LIVE_SCAN_BACKLOG:
                    self._drop_oldest_scans()
            self._cond.notify_all()

    def _drop_oldest_scans(self) -> None:
        excess = self._queued_scans - LIVE_SCAN_BACKLOG
        kept: deque[tuple[str, RawMessage]] = deque()
        topic = ""
        for kind, raw in self._queue:
            if kind == LASER_SCAN and excess:
                excess -= 1
                self.dropped += 1
                topic = raw.topic
                continue
            kept.append((kind, raw))
        self._queue = kept
        self._queued_scans = LIVE_SCAN_BACKLOG
        self._warn(topic, "SLAM falls behind this robot's scans; the oldest queued scans are skipped",
                   SlamBehindError)

    def close(self, stop: threading.Event, deadline: float | None) -> None:
        """Map what is queued, log the final map, and stop; what is still queued at the
        ``deadline`` (``time.monotonic``) or once ``stop`` is set is left unmapped, said once."""
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        while self._thread.is_alive():
            self._thread.join(CLOSE_POLL_S)
            late = deadline is not None and time.monotonic() > deadline
            if not self._abandon and (stop.is_set() or late):
                with self._cond:
                    left = len(self._pending) + sum(kind == LASER_SCAN for kind, _ in self._queue)
                    self._abandon = True
                    self._cond.notify_all()
                log.warning("[%s] SLAM stopped with %d scans not mapped", self.robot, left)

    # -- the thread ---------------------------------------------------------------------------

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: bool(self._queue) or self._closing)
                items = list(self._queue)
                self._queue.clear()
                self._queued_scans = 0
                closing = self._closing
                self._cond.notify_all()
            for kind, raw in items:
                try:
                    self._take(kind, raw)
                except Exception as err:  # one bad message costs itself only
                    self._dispatcher.warn(self.robot, raw.topic, err)
            self._map_ready(final=closing and not self._queue)
            if closing:
                with self._cond:
                    if not self._queue or self._abandon:
                        break
        self._log_map(final=True)

    def _take(self, kind: str, raw: RawMessage) -> None:
        msg = self._dispatcher.decoder.decode(raw)
        if kind == LASER_SCAN:
            self._take_scan(raw, msg)
        elif kind == ODOMETRY:
            stamp = stamp_ns(msg.header.stamp)
            pose = msg.pose.pose
            if self._base_frame is None and msg.child_frame_id:
                self._base_frame = msg.child_frame_id.strip("/")
            self._odometry.add(stamp, pose2(float(pose.position.x), float(pose.position.y),
                                            yaw_of([pose.orientation.x, pose.orientation.y,
                                                    pose.orientation.z, pose.orientation.w])))
        else:  # TFMessage
            static = raw.topic.endswith("tf_static")
            for transform in msg.transforms:
                parent = transform.header.frame_id.strip("/")
                child = transform.child_frame_id.strip("/")
                t, q = transform.transform.translation, transform.transform.rotation
                if child == self.settings.odom_frame and self._robot_map is None and self.slam.pose is None:
                    self._robot_map = parent  # the robot's own SLAM or localisation places odom
                if not static and parent == self.settings.odom_frame and child == self._odom_child(child):
                    self._tf_odometry.add(stamp_ns(transform.header.stamp), pose2(
                        float(t.x), float(t.y), yaw_of([q.x, q.y, q.z, q.w])))
                else:  # ROS 1 logs repeat their fixed transforms (the laser's mount) on /tf
                    self._frames.add(parent, child, t, q)

    def _odom_child(self, child: str) -> str | None:
        if self._base_frame is None and child in BASE_FRAMES:
            self._base_frame = child
        return self._base_frame

    def _take_scan(self, raw: RawMessage, msg: Any) -> None:
        if self._scan_topic is None:
            self._scan_topic = raw.topic
        elif raw.topic != self._scan_topic:
            return  # one scan topic per robot: the first that matched
        problem = finite_scan_geometry(msg)
        if problem is not None:
            raise SlamError(f"{raw.topic}: {problem}; the scan is not mapped")
        stamp = stamp_ns(msg.header.stamp) or (raw.log_ns or raw.receive_ns or 0)
        scan = scan_from_msg(msg, self.settings.max_range)
        if len(scan.points) < self.settings.min_points:
            text = (f"{raw.topic}: {len(scan.points)} valid ranges of {scan.beams} (fewer than "
                    f"min_points {self.settings.min_points}); the scan is not mapped")
            raise SparseScanError(text)
        if self._first_scan_stamp is None:
            self._first_scan_stamp = stamp
        self._pending.append(_PendingScan(raw, scan, stamp, msg.header.frame_id.strip("/")))

    def _odometry_source(self) -> OdometryTrack | None:
        mode = self.settings.odometry
        if mode == NO_ODOMETRY:
            return None
        if mode == ODOMETRY_FROM_TF:
            return self._tf_odometry
        return self._odometry if self._odometry else self._tf_odometry

    def _map_ready(self, final: bool) -> None:
        """Map the pending scans whose odometry has come (or will not come)."""
        while self._pending and not self._abandon:
            pending = self._pending[0]
            track = self._odometry_source()
            newest_scan = self._pending[-1].stamp
            if track is None or (not track and self._scan_only(newest_scan, final)):
                odom = None
            elif (track and pending.stamp <= track.newest) or final or (
                    not self._lossless and newest_scan - pending.stamp > ODOMETRY_WAIT_NS):
                odom = track.at(pending.stamp)
            else:
                return  # its odometry is on the way
            self._pending.popleft()
            try:
                self._map(pending, odom, track)
            except Exception as err:
                self._dispatcher.warn(self.robot, pending.raw.topic, err)

    def _scan_only(self, newest_scan: int, final: bool) -> bool:
        if self._lossless and self._expect_odometry is not None:
            no_odometry = not self._expect_odometry
        else:
            assert self._first_scan_stamp is not None
            no_odometry = final or newest_scan - self._first_scan_stamp > NO_ODOMETRY_AFTER_NS
        if no_odometry and not self._warned_scan_only:
            self._warned_scan_only = True
            source = ("odom_frame -> base transforms on /tf" if self.settings.odometry == ODOMETRY_FROM_TF
                      else f"{self.settings.odometry} (nav_msgs/Odometry) or {self.settings.odom_frame} "
                      "-> base on /tf")
            self._warn(self._scan_topic or self.settings.scan,
                       f"no odometry ({source}); mapping with scan matching alone", NoOdometryError)
        return no_odometry

    def _laser_mount(self, pending: _PendingScan) -> npt.NDArray[np.float64]:
        base = self._base_frame
        if base is None or pending.frame_id in ("", base):
            return np.eye(4)
        model = self._dispatcher.robot_state(self.robot).model
        mount = self._frames.chain(base, pending.frame_id, model)
        if mount is None:
            self._warn(pending.raw.topic, f"no transform from {base} to the laser frame "
                       f"{pending.frame_id!r} (/tf_static or the robot model); taking the laser "
                       "to be at the base", NoLaserTransformError)
            return np.eye(4)
        return mount

    def _map(self, pending: _PendingScan, odom: Pose2 | None, track: OdometryTrack | None) -> None:
        if self._last_stamp is not None and pending.stamp <= self._last_stamp:
            raise StampBackwardsError(
                f"{pending.raw.topic}: scan stamped {pending.stamp / 1e9:.3f} s, not after the last "
                f"mapped one ({self._last_stamp / 1e9:.3f} s); the scan is not mapped")
        if odom is None and track:
            raise SlamError(f"{pending.raw.topic}: no odometry within "
                              f"{ODOMETRY_REACH_NS / 1e9:g} s of the scan at {pending.stamp / 1e9:.3f} s; "
                              "the scan is not mapped")
        scan = pending.scan.moved(self._laser_mount(pending))
        update = self.slam.add(scan, pending.stamp, odom)
        self._last_stamp = pending.stamp
        if track is not None:
            track.forget_before(pending.stamp)
        if update.jumped:
            self._warn(self.settings.odometry, "odometry jumped (a reset or a robot restart): a new "
                       "trajectory segment starts, the map is kept", OdometryJumpError)
        self._closures.extend(update.closures)
        times = self._times(pending)
        self._dispatcher.log(self.robot, self._scan_items(update, times), times)
        due = (update.closures or self._last_map_stamp is None
               or pending.stamp - self._last_map_stamp >= self.settings.map_period * 1e9)
        # A big map costs: at most a fifth of this thread's time goes to drawing it.
        affordable = time.monotonic() - self._last_map_wall >= MAP_COST_FACTOR * self._last_map_cost
        if update.keyframe and due and affordable:
            self._log_map(final=False, times=times)

    def _times(self, pending: _PendingScan) -> dict[str, int]:
        times = {TIMELINE_ROS: pending.stamp}
        if pending.raw.receive_ns is not None:
            times[TIMELINE_RECEIVE] = pending.raw.receive_ns
        if pending.raw.log_ns is not None:
            times[TIMELINE_LOG] = pending.raw.log_ns
        return times

    # -- what is logged -----------------------------------------------------------------------

    @property
    def _map_frame(self) -> str:
        return self.settings.map_frame if self._robot_map is None else SLAM_MAP_FRAME

    @property
    def _root(self) -> str:
        return f"/{self.robot}/slam"

    def _frame(self, frame_id: str) -> str:
        return frame_of(self.robot, frame_id)

    def _scan_items(self, update: Update, times: Mapping[str, int]) -> list[LogEntry]:
        items: list[LogEntry] = []
        correction = self.slam.map_to_odom()
        if correction is not None:
            parent, child = self._frame(self._map_frame), self._frame(self.settings.odom_frame)
            if self._robot_map is not None:  # the robot's own map owns odom: hang ours below it
                correction, parent, child = inverse(correction), child, parent
            items.append(LogItem(f"{self._root}/map_to_odom", (rr.Transform3D(
                translation=[correction[0], correction[1], 0.0],
                quaternion=rr.Quaternion(xyzw=quaternion_of(float(correction[2]))),
                parent_frame=parent, child_frame=child,
            ),)))
        stats = f"{STATS_ROOT}/{self.robot}/slam"
        items.append(LogItem(f"{stats}/scan_ms", (rr.Scalars(update.seconds * 1e3),)))
        if update.matched is not None:
            items.append(LogItem(f"{stats}/matched_fraction", (rr.Scalars(update.matched),)))
        items.append(LogItem(f"{stats}/closures", (rr.Scalars(self.slam.closures),)))
        if update.closures:
            items.append(self._closure_item())
        return items

    def _closure_item(self) -> LogItem:
        keyframes = self.slam.keyframes
        strips = [[[*keyframes[a].pose[:2], 0.05], [*keyframes[b].pose[:2], 0.05]]
                  for a, b in self._closures]
        return LogItem(f"{self._root}/loop_closures", (
            *frame_components(self._frame(self._map_frame)),
            rr.LineStrips3D(strips, colors=[255, 120, 0], radii=0.01),
        ))

    def _log_map(self, final: bool, times: Mapping[str, int] | None = None) -> None:
        if self.slam.pose is None:
            return
        started = time.monotonic()
        if times is None:
            last = self._last_stamp or 0
            times = {TIMELINE_ROS: last}
        dense = self.slam.occupancy()
        grid = Grid(
            topic=f"{self._root}/map", entity_path=f"{self._root}/map",
            frame=self._frame(self._map_frame), cells=dense.cells,
            resolution=dense.resolution,
            translation=np.array([dense.origin[0], dense.origin[1], 0.0]),
            quaternion=np.array([0.0, 0.0, 0.0, 1.0]), options=GridOptions(),
        )
        items: list[LogEntry] = [*grid_items(grid)]
        stamps, poses = self.slam.trajectory()
        if len(poses) > 1:
            items.append(LogItem(f"{self._root}/trajectory", (
                *frame_components(self._frame(self._map_frame)),
                rr.LineStrips3D([np.column_stack([poses[:, :2], np.full(len(poses), 0.02)])],
                                colors=[0, 170, 255], radii=0.015),
            )))
        try:
            items.extend(grid_wall_items(grid, self._dispatcher.robot_state(self.robot), self._walls))
        except HostError as err:
            self._dispatcher.warn(self.robot, grid.topic, err, times)
        self._dispatcher.log(self.robot, items, times)
        self._last_map_stamp = self._last_stamp
        self._last_map_wall = time.monotonic()
        self._last_map_cost = self._last_map_wall - started
        if final:
            log.info("[%s] SLAM: %d scans mapped, %d keyframes, %d loop closures, %d segments",
                     self.robot, len(stamps), len(self.slam.keyframes), self.slam.closures,
                     self.slam.segments + 1)

    def save(self, directory: Path) -> None:
        """``--save-map``: the map and the trajectory of this robot under ``directory``."""
        if self.slam.pose is None:
            log.warning("[%s] SLAM mapped no scan; no map saved", self.robot)
            return
        write_map(directory, self.slam.occupancy())
        stamps, poses = self.slam.trajectory()
        write_trajectory(directory / TRAJECTORY, stamps, poses)

    def _warn(self, topic: str, text: str, kind: type[SlamError]) -> None:
        self._dispatcher.warn(self.robot, topic, kind(f"{topic}: {text}"))


class SlamTap:
    """The dispatcher tap feeding every robot's :class:`RobotSlam` (made on its first scan)."""

    def __init__(self, dispatcher: Host, settings: Callable[[str], SlamSettings], *,
                 lossless: bool, stop: threading.Event | None = None, save_map: Path | None = None,
                 bag_types: Mapping[str, str] | None = None) -> None:
        self._dispatcher = dispatcher
        self._stop = stop or threading.Event()
        self._settings = settings
        self._lossless = lossless
        self._save_map = save_map
        self._bag_types = bag_types
        self._robots: dict[str, RobotSlam | None] = {}
        self._lock = threading.Lock()
        self._closed = False

    def robots(self) -> dict[str, RobotSlam]:
        with self._lock:
            return {name: robot for name, robot in self._robots.items() if robot is not None}

    def __call__(self, batch: Sequence[RawMessage]) -> None:
        if not len(batch):
            return
        first = batch[0]
        if all(raw.robot == first.robot and raw.topic == first.topic for raw in batch[1:]):
            self._take(first, batch)
            return
        runs: dict[tuple[str, str], list[RawMessage]] = {}
        for raw in batch:
            if raw.msgtype in (LASER_SCAN, ODOMETRY, TF_MESSAGE):
                runs.setdefault((raw.robot, raw.topic), []).append(raw)
        for run in runs.values():
            self._take(run[0], run)

    def _take(self, first: RawMessage, run: Sequence[RawMessage]) -> None:
        kind = first.msgtype
        if kind not in (LASER_SCAN, ODOMETRY, TF_MESSAGE):
            return
        robot = self._robot(first.robot)
        if robot is None:
            return
        settings = robot.settings
        wanted = (
            (kind == LASER_SCAN and fnmatchcase(first.topic, settings.scan))
            or (kind == ODOMETRY and first.topic == settings.odometry)
            or (kind == TF_MESSAGE and first.topic.rsplit("/", 1)[-1] in ("tf", "tf_static"))
        )
        if wanted:
            robot.put(kind, run)

    def _robot(self, name: str) -> RobotSlam | None:
        with self._lock:
            if name in self._robots:
                return self._robots[name]
            settings = self._settings(name)
            robot = None
            if settings.enabled:
                expect = None
                if self._bag_types is not None:
                    expect = settings.odometry != NO_ODOMETRY and any(
                        (t == ODOMETRY and topic == settings.odometry) or t == TF_MESSAGE
                        for topic, t in self._bag_types.items())
                robot = RobotSlam(name, settings, self._dispatcher, lossless=self._lossless,
                                  expect_odometry=expect)
            self._robots[name] = robot
            return robot

    def close(self) -> None:
        """Map what is queued (a bag: all of it, unless ``stop`` is set meanwhile; live: for
        :data:`LIVE_CLOSE_S` at most), log each robot's final map, write ``--save-map`` files
        (once)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        deadline = None if self._lossless else time.monotonic() + LIVE_CLOSE_S
        for name, robot in sorted(self.robots().items()):
            robot.close(self._stop, deadline)
            if self._save_map is not None:
                robot.save(self._save_map / name)
