"""Helpers the demo tests share: a run's messages decoded by topic, and stamps, true poses and
odometry read from them."""

from __future__ import annotations

import math
from collections import defaultdict
from typing import Any

import numpy as np
from numpy.typing import NDArray

from host_bridge.demo import messages, robot

SHORT_S = 6.0
"""Seconds of the run every topic is checked on (the ``short`` fixture)."""
LAP_S = 65.0
"""Seconds of the run the motion topics are checked on (the ``lap`` fixture): the robot is
back at its start after about 59 s."""

Messages = dict[str, list[tuple[int, Any]]]


def xyz(v: Any) -> tuple[float, float, float]:
    return (v.x, v.y, v.z)


def yaw_of(q: Any) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def log_stamp_ns(log: Any) -> int:
    """rcl_interfaces/Log has its stamp at the top, not in a header."""
    return int(log.stamp.sec) * 1_000_000_000 + int(log.stamp.nanosec)


def decode_run(**kwargs: Any) -> Messages:
    store = messages.typestore()
    by_topic: Messages = defaultdict(list)
    for m in messages.simulate(**kwargs):
        by_topic[m.topic].append((m.log_ns, store.deserialize_cdr(m.data, m.msgtype)))
    return by_topic


def state_at(x: float, y: float, yaw: float) -> robot.RobotState:
    return robot.RobotState(x, y, yaw, 0.0, 0.0, (0.0, 0.0))


def _pose(message: Any) -> Any:
    """The geometry_msgs/Pose of a PoseStamped or of an Odometry."""
    return message.pose.pose if hasattr(message.pose, "pose") else message.pose


def true_state_at(run: Messages, log_ns: int) -> robot.RobotState:
    """The true pose published at ``log_ns`` (/ground_truth/pose), as the sensors saw it."""
    pose = next(_pose(m) for t, m in run[messages.GROUND_TRUTH_POSE_TOPIC] if t == log_ns)
    return state_at(pose.position.x, pose.position.y, yaw_of(pose.orientation))


def track(run: Messages, topic: str) -> NDArray[np.float64]:
    """(x, y, yaw) of every pose of ``topic`` (/odom or /ground_truth/pose), shape (N, 3)."""
    poses = [_pose(m) for _, m in run[topic]]
    return np.array([(p.position.x, p.position.y, yaw_of(p.orientation)) for p in poses])
