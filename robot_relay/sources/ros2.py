"""Live ROS 2 source: rclpy raw subscriptions (``raw=True``: the CDR bytes, never decoded).

How this was checked: rclpy cannot be installed on the development machine (no ROS 2), so
:func:`run_ros2_relay` has NOT run against a live ROS graph here. What is tested for real is the
pure part it relies on: :func:`message_definition` (the full ros2msg text built from the ament
share directories, checked against rosbags' parser on a fake share tree) and
:func:`adapted_qos` (the ``ros2 bag record`` QoS rule). Everything after the subscription callback
is the same Relay that the bag-replay and rmw_zenoh tests exercise. Keep this adapter thin.
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from robot_relay.wire import Catalog, MessageDefinition, QosProfile, RawMessage, TopicInfo

log = logging.getLogger("swanky.relay")

DISCOVERY_PERIOD_S = 2.0
_PRIMITIVES = frozenset({
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
    "uint32", "int64", "uint64", "string", "wstring",
})
_SEPARATOR = "=" * 80


def ament_share_dirs(environ: dict[str, str] | None = None) -> list[Path]:
    env = os.environ if environ is None else environ
    prefixes = env.get("AMENT_PREFIX_PATH", "")
    return [Path(p) / "share" for p in prefixes.split(os.pathsep) if p]


def _field_types(text: str, package: str) -> list[str]:
    """Full names (``pkg/Name``) of the message types a .msg text uses."""
    used = []
    for line in text.splitlines():
        parts = line.split("#", 1)[0].split()
        if len(parts) < 2 or "=" in parts[1]:  # blank, comment, or a constant
            continue
        base = re.sub(r"<=\d+$", "", re.sub(r"\[[^\]]*\]$", "", parts[0]))
        if base in _PRIMITIVES:
            continue
        if base == "Header":
            used.append("std_msgs/Header")
        elif "/" in base:
            used.append(base.replace("/msg/", "/"))
        else:
            used.append(f"{package}/{base}")
    return used


def message_definition(msgtype: str, share_dirs: Sequence[Path]) -> MessageDefinition | None:
    """The MCAP-style ros2msg text of ``pkg/msg/Name`` and every type it uses, or None."""

    def read(name: str) -> str | None:
        package, _, type_name = name.partition("/")
        for share in share_dirs:
            path = share / package / "msg" / f"{type_name}.msg"
            if path.is_file():
                return path.read_text(encoding="utf-8")
        return None

    root = msgtype.replace("/msg/", "/")
    root_text = read(root)
    if root_text is None:
        return None
    blocks: list[str] = [root_text]
    seen = {root}
    queue = _field_types(root_text, root.split("/")[0])
    while queue:
        name = queue.pop(0)
        if name in seen:
            continue
        seen.add(name)
        text = read(name)
        if text is None:
            return None
        blocks.append(f"{_SEPARATOR}\nMSG: {name}\n{text}")
        queue.extend(_field_types(text, name.split("/")[0]))
    return MessageDefinition("ros2msg", "\n".join(blocks))


def adapted_qos(publishers: Sequence[tuple[str, str, int]]) -> QosProfile:
    """QoS matching the (reliability, durability, depth) of every publisher, like rosbag2:
    best effort when any publisher is, transient-local only when all are."""
    if not publishers:
        return QosProfile()
    best_effort = any(r == "best_effort" for r, _, _ in publishers)
    latched = all(d == "transient_local" for _, d, _ in publishers)
    depth = max(*(d for _, _, d in publishers), 1)
    return QosProfile(
        reliability="best_effort" if best_effort else "reliable",
        durability="transient_local" if latched else "volatile",
        depth=depth,
    )


def run_ros2_relay(
    args: argparse.Namespace, stop: threading.Event, accept: Callable[[str], bool]
) -> int:
    try:
        import rclpy
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    except ImportError:
        log.error("rclpy is not importable: source ROS 2 (e.g. /opt/ros/humble/setup.bash) "
                  "or use --bag to replay a bag")
        return 2
    from robot_relay.relay import Relay
    from robot_relay.session import open_session

    rclpy.init()
    node = rclpy.create_node("swanky_relay")
    session = open_session(args)
    shares = ament_share_dirs()
    topics: dict[str, TopicInfo] = {}
    relay = Relay(session, Catalog(args.robot, "ros2", ()))
    subscriptions: list[Any] = []

    def subscribe(topic: str, msgtype: str) -> None:
        infos = node.get_publishers_info_by_topic(topic)
        qos = adapted_qos([
            (
                "best_effort" if i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
                else "reliable",
                "transient_local" if i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
                else "volatile",
                int(i.qos_profile.depth),
            )
            for i in infos
        ])
        info = TopicInfo(topic, msgtype, message_definition(msgtype, shares), qos)
        topics[topic] = info
        relay.update_catalog(Catalog(args.robot, "ros2", tuple(topics.values())))
        profile = QoSProfile(
            depth=qos.depth,
            reliability=ReliabilityPolicy.BEST_EFFORT if qos.reliability == "best_effort"
            else ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if info.latched
            else DurabilityPolicy.VOLATILE,
        )

        def on_message(data: bytes) -> None:
            relay.publish(RawMessage(args.robot, topic, msgtype, data))

        message_class = _message_class(msgtype)
        subscriptions.append(
            node.create_subscription(message_class, topic, on_message, profile, raw=True)
        )
        log.info("forwarding %s (%s, %s)", topic, msgtype, qos.durability)

    spinner = threading.Thread(target=rclpy.spin, args=(node,), daemon=True)
    spinner.start()
    try:
        while not stop.is_set():
            for topic, types in node.get_topic_names_and_types():
                if topic not in topics and len(types) == 1 and accept(topic):
                    subscribe(topic, types[0])
            stop.wait(DISCOVERY_PERIOD_S)
    finally:
        relay.close()
        node.destroy_node()
        rclpy.shutdown()
        session.close()
    return 0


def _message_class(msgtype: str) -> Any:
    """The rclpy message class (needed by create_subscription even in raw mode)."""
    from rosidl_runtime_py.utilities import get_message

    return get_message(msgtype)
