"""Laser logs of the kinds real robots produce, made from the demo apartment whose walls and
true poses are known: a TurtleBot-like 360-beam laser on a robot driving the apartment's loop,
wheel odometry with a scale error and a heading drift, and what real logs do besides (no-return
readings as +inf, 0 or range_max, dropouts, range noise, odometry that resets), written as a
rosbag2 with rosbags' Writer the way ``ros2 bag record`` stores the topics."""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from host_bridge.demo.robot import TICK_HZ, trajectory
from host_bridge.demo.world import WALLS, cast_rays
from host_bridge.slam.pose import Pose2, between, compose, pose2, quaternion_of

START_NS = 1_700_000_000_000_000_000
LASER_XY = (-0.032, 0.0)
"""The laser on base_footprint (x, y), a TurtleBot 3's, at 0.17 m height."""
LASER_Z = 0.17


@dataclass(frozen=True, slots=True)
class LaserLog:
    """How the simulated robot's laser and odometry misbehave."""

    seconds: float = 120.0
    scan_hz: float = 5.0
    beams: int = 360
    fov_deg: float = 360.0
    """The beams span this much, centred ahead (a Hokuyo UTM-30LX: 1080 beams over 270 deg)."""
    range_min: float = 0.12
    range_max: float = 3.5
    range_noise: float = 0.0
    no_return: str = "inf"
    """How a beam without echo reads: ``inf``, ``range_max`` or ``zero``."""
    dropout: float = 0.0
    """Fraction of beams reading NaN."""
    odom_scale_error: float = 0.05
    odom_heading_drift_deg_per_m: float = 2.0
    odom_reset_at: float | None = None
    """Seconds into the run at which odometry restarts from zero (a robot restart)."""
    odom: bool = True
    laser_mount: bool = True
    """Whether /tf_static places the laser (base_footprint -> base_scan)."""
    odom_on_tf: bool = False
    """Odometry as odom -> base_footprint on /tf (what SLAM datasets' bags carry), not /odom."""
    mount_on_tf: bool = False
    """The laser's mount repeated on /tf with every odometry tick, as ROS 1 logs have it."""
    robot_map: bool = False
    """Whether /tf_static gives odom a parent, map (as a robot running its own SLAM would)."""
    sparse_scan_at: float | None = None
    """Seconds into the run of one extra scan with only 5 valid ranges (the rest NaN)."""
    stale_scan_at: float | None = None
    """Seconds into the run at which the first scan is sent again, stamped as it was."""
    seed: int = 7
    route_offset: float = 0.0


@dataclass(slots=True)
class Sample:
    stamp_ns: int
    truth: Pose2
    odom: Pose2
    ranges: npt.NDArray[np.float32] | None = None


@dataclass(slots=True)
class Run:
    log: LaserLog
    ticks: list[Sample] = field(default_factory=list)
    """The odometry's (30 Hz)."""
    scans: list[Sample] = field(default_factory=list)

    @property
    def angle_min(self) -> float:
        return 0.0 if self.log.fov_deg >= 360.0 else -math.radians(self.log.fov_deg) / 2.0

    @property
    def angle_increment(self) -> float:
        return math.radians(self.log.fov_deg) / (self.log.beams if self.log.fov_deg >= 360.0
                                                  else self.log.beams - 1)


def _between_ticks(run: Run, stamp: int) -> tuple[Pose2, Pose2]:
    """Truth and odometry at ``stamp``, interpolated between the ticks around it."""
    period = 1_000_000_000 / TICK_HZ
    index = min(int((stamp - START_NS) // period), len(run.ticks) - 2)
    a, b = run.ticks[index], run.ticks[index + 1]
    fraction = (stamp - a.stamp_ns) / (b.stamp_ns - a.stamp_ns)
    return (compose(a.truth, between(a.truth, b.truth) * fraction),
            compose(a.odom, between(a.odom, b.odom) * fraction))


def simulate(log: LaserLog) -> Run:
    """The odometry at every tick (30 Hz) with the truth, and the scans at ``scan_hz``."""
    rng = np.random.default_rng(log.seed)
    run = Run(log)
    angles = run.angle_min + np.arange(log.beams) * run.angle_increment
    odom: Pose2 | None = None
    previous: Pose2 | None = None
    for tick, state in enumerate(trajectory(log.seconds, log.route_offset)):
        truth = pose2(state.x, state.y, state.yaw)
        if odom is None or previous is None:
            odom = truth.copy()
        else:
            step = between(previous, truth)
            travelled = math.hypot(step[0], step[1])
            odom = compose(odom, pose2(
                step[0] * (1 + log.odom_scale_error), step[1] * (1 + log.odom_scale_error),
                step[2] + math.radians(log.odom_heading_drift_deg_per_m) * travelled))
        stamp = START_NS + tick * 1_000_000_000 // TICK_HZ
        if log.odom_reset_at is not None and tick == round(log.odom_reset_at * TICK_HZ):
            odom = np.zeros(3)
        previous = truth
        run.ticks.append(Sample(stamp, truth, odom.copy()))
    last = run.ticks[-2].stamp_ns
    for index in range(int((last - START_NS) / 1e9 * log.scan_hz) + 1):
        stamp = START_NS + round(index * 1e9 / log.scan_hz)
        truth, odom = _between_ticks(run, stamp)
        origin = compose(truth, pose2(*LASER_XY, 0.0))[:2]
        ranges = cast_rays(origin, truth[2], angles, WALLS, log.range_max)
        if log.range_noise:
            ranges = ranges + rng.normal(0.0, log.range_noise, ranges.shape)
        ranges[ranges < log.range_min] = -np.inf
        if log.no_return == "range_max":
            ranges[~np.isfinite(ranges) & (ranges > 0)] = log.range_max
        elif log.no_return == "zero":
            ranges[~np.isfinite(ranges) & (ranges > 0)] = 0.0
        if log.dropout:
            ranges[rng.random(ranges.shape) < log.dropout] = np.nan
        run.scans.append(Sample(stamp, truth, odom, ranges.astype(np.float32)))
    return run


def timeline(run: Run) -> list[Sample]:
    """Odometry ticks and scans in the order a robot publishes them (odometry first on a tie)."""
    return sorted([*run.ticks, *run.scans], key=lambda sample: (sample.stamp_ns, sample.ranges is not None))


def messages(run: Run, store: Typestore | None = None) -> Iterator[tuple[str, str, int, Any]]:
    """The run's messages in time order (``store``: ROS 2 Humble's types, or ROS 1's)."""
    store = store or get_typestore(Stores.ROS2_HUMBLE)
    t = store.types
    log = run.log
    ros1 = any(name == "seq" for name, _ in store.fielddefs["std_msgs/msg/Header"][1])

    def header(stamp: int, frame: str) -> Any:
        sec, nanosec = divmod(stamp, 1_000_000_000)
        time = t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
        if ros1:
            return t["std_msgs/msg/Header"](seq=0, stamp=time, frame_id=frame)
        return t["std_msgs/msg/Header"](stamp=time, frame_id=frame)

    def transform(stamp: int, parent: str, child: str, xyz: tuple[float, float, float],
                  yaw: float) -> Any:
        x, y, z, w = quaternion_of(yaw)
        return t["geometry_msgs/msg/TransformStamped"](
            header=header(stamp, parent), child_frame_id=child,
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](x=xyz[0], y=xyz[1], z=xyz[2]),
                rotation=t["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)))

    def scan(stamp: int, ranges: npt.NDArray[np.float32]) -> Any:
        return t["sensor_msgs/msg/LaserScan"](
            header=header(stamp, "base_scan"), angle_min=run.angle_min,
            angle_max=run.angle_min + (log.beams - 1) * run.angle_increment,
            angle_increment=run.angle_increment, time_increment=0.0,
            scan_time=1.0 / log.scan_hz, range_min=log.range_min, range_max=log.range_max,
            ranges=ranges, intensities=np.zeros(0, np.float32))

    first = run.ticks[0].stamp_ns
    statics = []
    if log.laser_mount and not log.mount_on_tf:
        statics.append(transform(first, "base_footprint", "base_scan", (*LASER_XY, LASER_Z), 0.0))
    if log.robot_map:
        statics.append(transform(first, "map", "odom", (1.0, 0.0, 0.0), 0.0))
    if statics:
        yield "/tf_static", "tf2_msgs/msg/TFMessage", first, t["tf2_msgs/msg/TFMessage"](transforms=statics)
    covariance = np.zeros(36)
    scans = run.scans
    def due(at: float | None, sample: Sample) -> bool:
        """The odometry tick at ``at`` seconds into the run."""
        if at is None or sample.ranges is not None:
            return False
        return abs((sample.stamp_ns - first) / 1e9 - at) < 0.5 / TICK_HZ

    for sample in timeline(run):
        if due(log.sparse_scan_at, sample):
            sparse = np.full(log.beams, np.nan, np.float32)
            sparse[:5] = 1.0
            yield "/scan", "sensor_msgs/msg/LaserScan", sample.stamp_ns + 1, scan(sample.stamp_ns + 1, sparse)
        if due(log.stale_scan_at, sample):
            stale = scans[0]
            assert stale.ranges is not None
            yield "/scan", "sensor_msgs/msg/LaserScan", sample.stamp_ns, scan(stale.stamp_ns, stale.ranges)
        if log.odom and sample.ranges is None and (log.odom_on_tf or log.mount_on_tf):
            moving = []
            if log.odom_on_tf:
                x, y, yaw = (float(v) for v in sample.odom)
                moving.append(transform(sample.stamp_ns, "odom", "base_footprint", (x, y, 0.0), yaw))
            if log.mount_on_tf:
                mount = (*LASER_XY, LASER_Z)
                moving.append(transform(sample.stamp_ns, "base_footprint", "base_scan", mount, 0.0))
            tf = t["tf2_msgs/msg/TFMessage"](transforms=moving)
            yield "/tf", "tf2_msgs/msg/TFMessage", sample.stamp_ns, tf
        if log.odom and sample.ranges is None and not log.odom_on_tf:
            x, y, yaw = sample.odom
            qx, qy, qz, qw = quaternion_of(float(yaw))
            pose = t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
                orientation=t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw))
            zero = t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
            yield "/odom", "nav_msgs/msg/Odometry", sample.stamp_ns, t["nav_msgs/msg/Odometry"](
                header=header(sample.stamp_ns, "odom"), child_frame_id="base_footprint",
                pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=covariance),
                twist=t["geometry_msgs/msg/TwistWithCovariance"](
                    twist=t["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=covariance))
        if sample.ranges is not None:
            yield "/scan", "sensor_msgs/msg/LaserScan", sample.stamp_ns, scan(sample.stamp_ns, sample.ranges)


def write_ros1_bag(run: Run, path: Path, compression: str | None = None) -> Path:
    """The run as a ROS 1 bag (``compression``: None, "bz2" or "lz4" chunks)."""
    store = get_typestore(Stores.ROS1_NOETIC)
    # ROS 1's tf2_msgs/TFMessage, which rosbags' Noetic store leaves out.
    tf = "geometry_msgs/TransformStamped[] transforms"
    store.register(get_types_from_msg(tf, "tf2_msgs/msg/TFMessage"))
    connections: dict[str, Any] = {}
    writer = Ros1Writer(path)
    if compression is not None:
        writer.set_compression(Ros1Writer.CompressionFormat[compression.upper()])
    with writer:
        for topic, msgtype, stamp, msg in messages(run, store):
            connection = connections.get(topic)
            if connection is None:
                connection = connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(connection, stamp, store.serialize_ros1(msg, msgtype))
    return path


def write_bag(run: Run, path: Path, storage: StoragePlugin = StoragePlugin.MCAP) -> Path:
    """The run as a rosbag2 (MCAP by default) at ``path``."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    connections: dict[str, Any] = {}
    with Writer(path, version=9, storage_plugin=storage) as writer:
        for topic, msgtype, stamp, msg in messages(run):
            connection = connections.get(topic)
            if connection is None:
                connection = connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(connection, stamp, store.serialize_cdr(msg, msgtype))
    return path
