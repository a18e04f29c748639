"""A robot's usual traffic as a rosbag2, for the bad-link, crash and slow-consumer tests.

Latched: /tf_static from three broadcasters (one transform each, three transient-local
publishers), /robot_description (a small URDF of primitives, no meshes) and /map. Reliable:
/odom at 30 Hz. Best effort: /scan at 10 Hz and /camera/image_raw (rgb8) at 15 Hz. Every
message says which one it is, so a test reading the .rrd back knows exactly what arrived:
odometry ``i`` is at x = i / 1000 m with header stamp ``START_NS + i * ODOM_PERIOD_NS``, scan
``i`` has every range ``1 + i / 100`` m, image ``i`` is filled with the byte ``i % 251``.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import Writer

from tests.integration.robot_bags import (
    START_NS,
    STORE,
    header,
    latched_qos,
    occupancy_grid,
    string,
    tf_message,
    transform,
)

ODOM_HZ, SCAN_HZ, IMAGE_HZ = 30, 10, 15
ODOM_PERIOD_NS = 1_000_000_000 // ODOM_HZ
SCAN_PERIOD_NS = 1_000_000_000 // SCAN_HZ
IMAGE_PERIOD_NS = 1_000_000_000 // IMAGE_HZ
SCAN_POINTS = 360
MAP_SIZE = 100

# (parent, child, translation): one per /tf_static broadcaster.
BROADCASTERS = (
    ("base_footprint", "base_link", (0.0, 0.0, 0.01)),
    ("base_link", "base_scan", (-0.032, 0.0, 0.172)),
    ("base_link", "camera_link", (0.05, 0.0, 0.2)),
)
URDF = """<?xml version="1.0"?>
<robot name="traffic_bot">
  <link name="base_footprint"/>
  <link name="base_link"><visual><geometry><box size="0.2 0.2 0.1"/></geometry></visual></link>
  <joint name="base_joint" type="fixed">
    <parent link="base_footprint"/><child link="base_link"/><origin xyz="0 0 0.01"/>
  </joint>
</robot>
"""


def _qos(reliability: QosReliability, depth: int) -> list[Qos]:
    zero = QosTime(0, 0)
    return [Qos(QosHistory.KEEP_LAST, depth, reliability, QosDurability.VOLATILE, zero, zero,
                QosLiveliness.AUTOMATIC, zero, False)]


def odom_x(index: int) -> float:
    return index / 1000


def scan_range(index: int) -> float:
    return 1 + index / 100


def image_fill(index: int) -> int:
    return index % 251


def odom_index(ros_time: int) -> int:
    return round((ros_time - START_NS) / ODOM_PERIOD_NS)


def image_index(ros_time: int) -> int:
    return round((ros_time - START_NS) / IMAGE_PERIOD_NS)


def map_cells() -> np.ndarray[Any, np.dtype[np.int8]]:
    """A room: walls (100) round free space (0), one unknown (-1) corner."""
    cells = np.zeros((MAP_SIZE, MAP_SIZE), np.int8)
    cells[[0, -1], :] = 100
    cells[:, [0, -1]] = 100
    cells[:10, :10] = -1
    return cells


def odometry(index: int) -> Any:
    types = STORE.types
    ns = START_NS + index * ODOM_PERIOD_NS
    pose = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=odom_x(index), y=0.0, z=0.0),
        orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
    )
    vector = types["geometry_msgs/msg/Vector3"]
    twist = types["geometry_msgs/msg/Twist"](linear=vector(x=0.03, y=0.0, z=0.0),
                                              angular=vector(x=0.0, y=0.0, z=0.0))
    return types["nav_msgs/msg/Odometry"](
        header=header(ns, "odom"), child_frame_id="base_footprint",
        pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
    )


def laser_scan(index: int) -> Any:
    return STORE.types["sensor_msgs/msg/LaserScan"](
        header=header(START_NS + index * SCAN_PERIOD_NS, "base_scan"),
        angle_min=-np.pi, angle_max=np.pi, angle_increment=2 * np.pi / SCAN_POINTS,
        time_increment=0.0, scan_time=0.1, range_min=0.1, range_max=30.0,
        ranges=np.full(SCAN_POINTS, scan_range(index), np.float32),
        intensities=np.zeros(0, np.float32),
    )


def image(index: int, width: int, height: int) -> Any:
    return STORE.types["sensor_msgs/msg/Image"](
        header=header(START_NS + index * IMAGE_PERIOD_NS, "camera_link"),
        height=height, width=width, encoding="rgb8", is_bigendian=0, step=width * 3,
        data=np.full(width * height * 3, image_fill(index), np.uint8),
    )


@dataclass(frozen=True, slots=True)
class Traffic:
    """What a bag holds: ``seconds`` of data from odometry message ``first_odom`` on (a second
    bag continues the first one's stamps); images of ``image_size`` (0 x 0: no camera)."""

    seconds: float
    image_size: tuple[int, int] = (320, 240)
    first_odom: int = 0
    latched: bool = True
    scans: bool = True

    def odom(self) -> range:
        return range(self.first_odom, self.first_odom + int(self.seconds * ODOM_HZ))

    def scan_indices(self) -> range:
        first = self.first_odom * SCAN_HZ // ODOM_HZ
        return range(first, first + int(self.seconds * SCAN_HZ)) if self.scans else range(0)

    def image_indices(self) -> range:
        if self.image_size == (0, 0):
            return range(0)
        first = self.first_odom * IMAGE_HZ // ODOM_HZ
        return range(first, first + int(self.seconds * IMAGE_HZ))


def _entries(traffic: Traffic) -> Iterator[tuple[str, int, Any]]:
    """(topic, log time, message) in log-time order within each topic."""
    start = START_NS + traffic.first_odom * ODOM_PERIOD_NS
    if traffic.latched:
        yield "/robot_description", start, string(URDF)
        for n, (parent, child, xyz) in enumerate(BROADCASTERS):
            yield "/tf_static", start + n, tf_message(transform(start, parent, child, xyz))
        grid = occupancy_grid(start, MAP_SIZE, MAP_SIZE, 0.05, np.flipud(map_cells()).ravel().tolist())
        yield "/map", start + 10, grid
    for i in traffic.odom():
        yield "/odom", START_NS + i * ODOM_PERIOD_NS, odometry(i)
    for i in traffic.scan_indices():
        yield "/scan", START_NS + i * SCAN_PERIOD_NS, laser_scan(i)
    width, height = traffic.image_size
    for i in traffic.image_indices():
        yield "/camera/image_raw", START_NS + i * IMAGE_PERIOD_NS, image(i, width, height)


TYPES = {
    "/robot_description": "std_msgs/msg/String",
    "/tf_static": "tf2_msgs/msg/TFMessage",
    "/map": "nav_msgs/msg/OccupancyGrid",
    "/odom": "nav_msgs/msg/Odometry",
    "/scan": "sensor_msgs/msg/LaserScan",
    "/camera/image_raw": "sensor_msgs/msg/Image",
}
QOS = {
    "/robot_description": latched_qos(1),
    "/tf_static": latched_qos(len(BROADCASTERS)),
    "/map": latched_qos(1),
    "/odom": _qos(QosReliability.RELIABLE, 10),
    "/scan": _qos(QosReliability.BEST_EFFORT, 5),
    "/camera/image_raw": _qos(QosReliability.BEST_EFFORT, 5),
}


def write_traffic_bag(path: Path, traffic: Traffic) -> Path:
    """The rosbag2 (sqlite3) of ``traffic``, with the QoS ``ros2 bag record`` stores."""
    entries = sorted(_entries(traffic), key=lambda entry: entry[1])
    with Writer(path, version=9) as writer:
        connections = {
            topic: writer.add_connection(topic, TYPES[topic], typestore=STORE,
                                         offered_qos_profiles=QOS[topic])
            for topic in dict.fromkeys(topic for topic, _, _ in entries)
        }
        for topic, log_ns, msg in entries:
            writer.write(connections[topic], log_ns, bytes(STORE.serialize_cdr(msg, TYPES[topic])))
    return path
