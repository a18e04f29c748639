"""Small rosbag2 files of a TurtleBot3 burger for the live robot-model and latched-topic tests.

Latched topics carry the QoS ``ros2 bag record`` stores for a transient-local publisher, one
profile per publisher, so the relay treats them as ROS would.
"""

from __future__ import annotations

import math
import subprocess
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

STORE = get_typestore(Stores.ROS2_HUMBLE)
PACKAGE = "turtlebot3_description"
START_NS = 1_700_000_000 * 10**9
WHEELS = ("wheel_left_joint", "wheel_right_joint")


def package_dir(shared_data: Path) -> Path:
    """The package directory (with package.xml) inside the shared data set."""
    return shared_data / PACKAGE / PACKAGE


def burger_urdf(shared_data: Path) -> str:
    return (package_dir(shared_data) / "urdf" / "turtlebot3_burger.urdf").read_text(encoding="utf-8")


def latched_qos(publishers: int = 1) -> list[Qos]:
    zero = QosTime(0, 0)
    profile = Qos(
        QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
        zero, zero, QosLiveliness.AUTOMATIC, zero, False,
    )
    return [profile] * publishers


def stamp(ns: int) -> Any:
    return STORE.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)


def header(ns: int, frame: str) -> Any:
    return STORE.types["std_msgs/msg/Header"](stamp=stamp(ns), frame_id=frame)


def transform(ns: int, parent: str, child: str, xyz: Sequence[float], yaw: float = 0.0) -> Any:
    types = STORE.types
    return types["geometry_msgs/msg/TransformStamped"](
        header=header(ns, parent),
        child_frame_id=child,
        transform=types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](x=xyz[0], y=xyz[1], z=xyz[2]),
            rotation=types["geometry_msgs/msg/Quaternion"](
                x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)
            ),
        ),
    )


def tf_message(*transforms: Any) -> Any:
    return STORE.types["tf2_msgs/msg/TFMessage"](transforms=list(transforms))


def string(text: str) -> Any:
    return STORE.types["std_msgs/msg/String"](data=text)


def joint_state(ns: int, positions: Sequence[float]) -> Any:
    return STORE.types["sensor_msgs/msg/JointState"](
        header=header(ns, ""),
        name=list(WHEELS),
        position=np.asarray(positions, np.float64),
        velocity=np.zeros(0),
        effort=np.zeros(0),
    )


def occupancy_grid(ns: int, width: int, height: int, resolution: float, cells: Sequence[int]) -> Any:
    types = STORE.types
    pose = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=-1.0, y=-2.0, z=0.0),
        orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
    )
    info = types["nav_msgs/msg/MapMetaData"](
        map_load_time=stamp(ns), resolution=resolution, width=width, height=height, origin=pose
    )
    return types["nav_msgs/msg/OccupancyGrid"](
        header=header(ns, "map"), info=info, data=np.asarray(cells, np.int8)
    )


def laser_scan(ns: int, ranges: int) -> Any:
    """A 240-degree scan of ``ranges`` readings, a wall 2 m away (a Hokuyo's shape)."""
    return STORE.types["sensor_msgs/msg/LaserScan"](
        header=header(ns, "laser"), angle_min=-2.09, angle_max=2.09,
        angle_increment=4.18 / (ranges - 1), time_increment=0.0, scan_time=0.1, range_min=0.02,
        range_max=5.6, ranges=np.full(ranges, 2.0, np.float32), intensities=np.zeros(0, np.float32),
    )


def write_copies(
    path: Path, topic: str, msgtype: str, msg: Any, *, count: int, period_ns: int,
    storage: StoragePlugin = StoragePlugin.MCAP, compression: CompressionMode = CompressionMode.NONE,
) -> Path:
    """A rosbag2 of ``count`` copies of ``msg``, ``period_ns`` apart: serialized once, so a bag
    that takes the host seconds to convert is written in about one."""
    data = bytes(STORE.serialize_cdr(msg, msgtype))
    writer = Writer(path, version=9, storage_plugin=storage)
    writer.set_compression(compression, CompressionFormat.ZSTD)
    with writer:
        connection = writer.add_connection(topic, msgtype, typestore=STORE)
        for i in range(count):
            writer.write(connection, START_NS + i * period_ns, data)
    return path


@dataclass(frozen=True, slots=True)
class Entry:
    """One message to write: topic, type, log time (ns after START_NS), message, publishers."""

    topic: str
    msgtype: str
    offset_ns: int
    msg: Any
    latched_publishers: int = 0


def write_bag(path: Path, entries: Sequence[Entry]) -> Path:
    """A rosbag2 (sqlite3) of ``entries``; a topic is latched when its entries say so."""
    with Writer(path, version=9) as writer:
        connections: dict[str, Any] = {}
        for entry in entries:
            if entry.topic not in connections:
                qos = latched_qos(entry.latched_publishers) if entry.latched_publishers else ()
                connections[entry.topic] = writer.add_connection(
                    entry.topic, entry.msgtype, typestore=STORE, offered_qos_profiles=qos
                )
        for entry in sorted(entries, key=lambda e: e.offset_ns):
            data = bytes(STORE.serialize_cdr(entry.msg, entry.msgtype))
            writer.write(connections[entry.topic], START_NS + entry.offset_ns, data)
    return path


class Lines:
    """Collects a process's stderr lines on a thread, so a test can wait for one without
    blocking on the pipe (and the process never blocks on a full pipe)."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.lines: list[str] = []
        assert proc.stderr is not None
        self._thread = threading.Thread(target=self._read, args=(proc.stderr,), daemon=True)
        self._thread.start()

    def _read(self, stream: IO[str]) -> None:
        for line in stream:
            self.lines.append(line)

    def wait_for(self, text: str, timeout: float) -> str:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for line in list(self.lines):
                if text in line:
                    return line
            time.sleep(0.05)
        got = "".join(self.lines)
        raise AssertionError(f"no line with {text!r} within {timeout} s; stderr so far:\n{got}")

    @property
    def text(self) -> str:
        return "".join(self.lines)

    def all_text(self, timeout: float = 10.0) -> str:
        """Every line, once the process has ended and its stderr closed (the reader took the
        last lines after ``wait()`` returned)."""
        self._thread.join(timeout)
        return self.text
