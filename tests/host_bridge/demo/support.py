"""Helpers the demo tests share: a run's messages decoded by topic, and stamps and poses read
from them."""

from __future__ import annotations

import math
from collections import defaultdict
from typing import Any

from host_bridge.demo import messages, robot

SHORT_S = 6.0
"""Seconds of the run every topic is checked on (the ``short`` fixture)."""

Messages = dict[str, list[tuple[int, Any]]]


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


def pose_at(odom: Messages, log_ns: int) -> robot.RobotState:
    pose = next(o.pose.pose for t, o in odom["/odom"] if t == log_ns)
    return state_at(pose.position.x, pose.position.y, yaw_of(pose.orientation))
