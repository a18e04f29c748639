"""Live ROS 2 source: rclpy raw subscriptions (``raw=True``: the CDR bytes, never decoded).

Every ``DISCOVERY_PERIOD_S`` the graph is read again (:meth:`Ros2Source.discover`): a topic with
at least one publisher that passes the allow/deny globs enters the catalog with the QoS adapted
to all its publishers (:func:`robot_relay.sources.qos.adapted_qos`, the ``ros2 bag record``
rule) and the full definition of its type read from the ament share directories (.msg, else
.idl, as rosbag2 does), so custom packages decode on a host without them. A topic whose last
publisher leaves drops out; one whose type or publishers' QoS changes is re-declared.

Subscriptions follow demand: the Relay calls :meth:`Ros2Source.on_demand` from Zenoh's threads
when a host starts or stops listening, and the discovery thread applies it (create or destroy
the subscription), so the node is only touched by that thread and rclpy's executor. Latched
topics are always wanted (the Relay says so at once): their cache must be warm for late hosts.

How this was checked -- honestly. rclpy cannot be installed on the development machine (no ROS
2, no apt ROS repository), so :func:`run_ros2_relay`, the only function that imports rclpy, has
NOT run against a live ROS graph here. What runs for real in the tests:

- :class:`Ros2Source` (discovery, vanished and changed topics, QoS adaptation, demand-driven
  subscribe/unsubscribe, the message callback) against a fake node that answers
  ``get_topic_names_and_types`` / ``get_publishers_info_by_topic`` the way rclpy documents them
  (``TopicEndpointInfo.qos_profile`` with ``ReliabilityPolicy`` / ``DurabilityPolicy`` enums),
  both alone and behind a real Relay and a real Zenoh subscriber on loopback;
- :func:`message_definition` on fake share trees (.msg with relative, nested, bounded and
  Header fields; an .idl-only package), its output parsed back by rosbags.

Not checked here: rclpy's exact enum names (``.name`` of the policies, lower-cased), that
``create_subscription(..., raw=True)`` hands the callback ``bytes``, the QoS profile built in
:func:`run_ros2_relay`, and rclpy's thread safety when subscriptions are created while
``rclpy.spin`` runs in another thread. Keep this adapter thin.
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from robot_relay.sources.qos import Offer, adapted_qos
from robot_relay.wire import Catalog, MessageDefinition, RawMessage, TopicInfo

log = logging.getLogger("swanky.relay")

DISCOVERY_PERIOD_S = 2.0
_PRIMITIVES = frozenset({
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
    "uint32", "int64", "uint64", "string", "wstring",
})
_SEPARATOR = "=" * 80
_IDL_INCLUDE = re.compile(r'^#include\s+"([^"/]+/[^"/]+/[^"/]+)\.idl"', re.MULTILINE)

Subscribe = Callable[[TopicInfo, Callable[[bytes], None]], Any]
Publish = Callable[[RawMessage], None]


def ament_share_dirs(environ: dict[str, str] | None = None) -> list[Path]:
    env = os.environ if environ is None else environ
    prefixes = env.get("AMENT_PREFIX_PATH", "")
    return [Path(p) / "share" for p in prefixes.split(os.pathsep) if p]


def _read_interface(name: str, suffix: str, share_dirs: Sequence[Path]) -> str | None:
    """Text of ``pkg/msg/Name`` + ``suffix`` from the first share dir holding it."""
    package, interface, type_name = name.split("/")
    for share in share_dirs:
        path = share / package / interface / f"{type_name}{suffix}"
        if path.is_file():
            return path.read_text(encoding="utf-8")
    return None


def _field_types(text: str, package: str) -> list[str]:
    """Full names (``pkg/msg/Name``) of the message types a .msg text uses."""
    used = []
    for line in text.splitlines():
        parts = line.split("#", 1)[0].split()
        if len(parts) < 2 or "=" in "".join(parts[1:]):  # blank, comment, or a constant
            continue
        base = re.sub(r"<=\d+$", "", re.sub(r"\[[^\]]*\]$", "", parts[0]))
        if base in _PRIMITIVES:
            continue
        if base == "Header":
            used.append("std_msgs/msg/Header")
        elif "/" in base:
            pkg, _, type_name = base.rpartition("/")
            used.append(f"{pkg.split('/')[0]}/msg/{type_name}")
        else:
            used.append(f"{package}/msg/{base}")
    return used


def _closure(root: str, read: Callable[[str], str | None],
             uses: Callable[[str, str], list[str]]) -> list[tuple[str, str]] | None:
    """(name, text) of ``root`` and every type it uses, root first; None if one is missing."""
    found: list[tuple[str, str]] = []
    seen: set[str] = set()
    queue = [root]
    while queue:
        name = queue.pop(0)
        if name in seen:
            continue
        seen.add(name)
        text = read(name)
        if text is None:
            return None
        found.append((name, text))
        queue.extend(uses(name, text))
    return found


def message_definition(msgtype: str, share_dirs: Sequence[Path]) -> MessageDefinition | None:
    """The definition rosbag2 would store for ``pkg/msg/Name``: ros2msg text of the type and
    every type it uses from the .msg files, else ros2idl from the .idl files (packages written
    in IDL); None when neither is complete (e.g. action types, or a package not installed)."""
    if msgtype.count("/") != 2:
        return None
    msgs = _closure(
        msgtype,
        lambda name: _read_interface(name, ".msg", share_dirs),
        lambda name, text: _field_types(text, name.split("/")[0]),
    )
    if msgs is not None:
        blocks = [msgs[0][1]] + [
            f"{_SEPARATOR}\nMSG: {name.replace('/msg/', '/')}\n{text}" for name, text in msgs[1:]
        ]
        return MessageDefinition("ros2msg", "\n".join(blocks))
    idls = _closure(
        msgtype,
        lambda name: _read_interface(name, ".idl", share_dirs),
        lambda name, text: _IDL_INCLUDE.findall(text),
    )
    if idls is not None:
        return MessageDefinition(
            "ros2idl", "\n".join(f"{_SEPARATOR}\nIDL: {name}\n{text}" for name, text in idls)
        )
    return None


def publisher_offer(endpoint: Any) -> Offer:
    """(reliability, durability, depth) of an rclpy ``TopicEndpointInfo``."""
    qos = endpoint.qos_profile
    return (qos.reliability.name.lower(), qos.durability.name.lower(), int(qos.depth))


class Ros2Source:
    """The ROS graph seen through ``graph`` (an rclpy Node), as a catalog and demanded streams.

    ``subscribe(info, callback)`` creates a raw subscription (None if it cannot) and
    ``unsubscribe(handle)`` destroys one: injected, so everything but rclpy itself is testable.
    """

    def __init__(
        self, graph: Any, robot: str, accept: Callable[[str], bool], share_dirs: Sequence[Path],
        *, subscribe: Subscribe, unsubscribe: Callable[[Any], None],
    ) -> None:
        self.graph = graph
        self.robot = robot
        self.accept = accept
        self.share_dirs = list(share_dirs)
        self._subscribe = subscribe
        self._unsubscribe = unsubscribe
        self.topics: dict[str, TopicInfo] = {}
        self.subscriptions: dict[str, tuple[TopicInfo, Any]] = {}
        self.wake = threading.Event()
        self._demand: dict[str, bool] = {}
        self._lock = threading.Lock()
        self._definitions: dict[str, MessageDefinition | None] = {}
        self._warned: set[str] = set()

    def _warn_once(self, topic: str, message: str, *args: object) -> None:
        if topic not in self._warned:
            self._warned.add(topic)
            log.warning(message, topic, *args)

    def _definition(self, msgtype: str) -> MessageDefinition | None:
        if msgtype not in self._definitions:
            self._definitions[msgtype] = message_definition(msgtype, self.share_dirs)
        return self._definitions[msgtype]

    def discover(self) -> Catalog | None:
        """The graph's catalog now, or None when it is the same as at the previous call."""
        found: dict[str, TopicInfo] = {}
        for topic, types in self.graph.get_topic_names_and_types():
            if not self.accept(topic):
                continue
            if len(types) != 1:
                self._warn_once(topic, "%s has several types (%s): not forwarded", ", ".join(types))
                continue
            offers = [publisher_offer(e) for e in self.graph.get_publishers_info_by_topic(topic)]
            if not offers:  # only subscribers: nothing to forward yet
                continue
            msgtype = types[0]
            definition = self._definition(msgtype)
            if definition is None:
                self._warn_once(topic, "%s: no definition of %s in AMENT_PREFIX_PATH; hosts decode "
                                "it with their bundled types only", msgtype)
            found[topic] = TopicInfo(topic, msgtype, definition, adapted_qos(offers))
        if found == self.topics:
            return None
        for topic in self.topics.keys() - found.keys():
            log.info("%s vanished", topic)
        for topic, info in found.items():
            if self.topics.get(topic) != info:
                log.info("forwarding %s (%s, %s, %s)", topic, info.msgtype, info.qos.reliability,
                         info.qos.durability)
        self.topics = found
        return Catalog(self.robot, "ros2", tuple(found[t] for t in sorted(found)))

    def on_demand(self, topic: str, wanted: bool) -> None:
        """From the Relay (Zenoh's threads): remember, and wake the discovery thread."""
        with self._lock:
            self._demand[topic] = wanted
        self.wake.set()

    def apply_demand(self, publish: Publish) -> None:
        """Create or destroy subscriptions as demanded since the last call."""
        with self._lock:
            demand, self._demand = self._demand, {}
        for topic, wanted in demand.items():
            info = self.topics.get(topic) if wanted else None
            current = self.subscriptions.get(topic)
            if current is not None and current[0] == info:
                continue
            if current is not None:
                del self.subscriptions[topic]
                self._unsubscribe(current[1])
                log.info("%s: no host listens, unsubscribed", topic)
            if info is None:
                continue
            handle = self._subscribe(info, self._forwarder(info, publish))
            if handle is not None:
                self.subscriptions[topic] = (info, handle)
                log.info("%s: a host listens, subscribed", topic)

    def _forwarder(self, info: TopicInfo, publish: Publish) -> Callable[[bytes], None]:
        def forward(data: bytes) -> None:
            publish(RawMessage(self.robot, info.topic, info.msgtype, data, info.definition))

        return forward

    def run(self, update_catalog: Callable[[Catalog], None], publish: Publish,
            stop: threading.Event, period: float = DISCOVERY_PERIOD_S) -> None:
        """Discover every ``period`` and apply demand as it comes, until ``stop``."""
        next_discovery = time.monotonic()
        while not stop.is_set():
            if time.monotonic() >= next_discovery:
                catalog = self.discover()
                if catalog is not None:
                    update_catalog(catalog)
                next_discovery = time.monotonic() + period
            self.wake.clear()
            self.apply_demand(publish)
            # Short waits so a stop (signal) is seen quickly; demand wakes it at once.
            self.wake.wait(min(max(next_discovery - time.monotonic(), 0.0), 0.2))

    def close(self) -> None:
        for _, handle in self.subscriptions.values():
            self._unsubscribe(handle)
        self.subscriptions.clear()


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
    from robot_relay.files import serve_files
    from robot_relay.relay import Relay
    from robot_relay.session import open_session

    rclpy.init()
    node = rclpy.create_node("swanky_relay")

    def subscribe(info: TopicInfo, callback: Callable[[bytes], None]) -> Any:
        profile = QoSProfile(
            depth=info.qos.depth,
            reliability=ReliabilityPolicy.BEST_EFFORT if info.qos.reliability == "best_effort"
            else ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if info.latched
            else DurabilityPolicy.VOLATILE,
        )
        try:
            message_class = _message_class(info.msgtype)
        except Exception as err:  # the type's package is not installed beside the relay
            log.error("%s: cannot subscribe, %s is not importable here: %s", info.topic,
                      info.msgtype, err)
            return None
        return node.create_subscription(message_class, info.topic, callback, profile, raw=True)

    source = Ros2Source(node, args.robot, accept, ament_share_dirs(), subscribe=subscribe,
                        unsubscribe=node.destroy_subscription)
    session = open_session(args)
    relay = Relay(session, Catalog(args.robot, "ros2", ()), args.policies, demand=source)
    files = serve_files(session, args.robot, args.package_path)

    def forward(raw: RawMessage) -> None:
        files.learn(raw)
        relay.publish(raw)

    spinner = threading.Thread(target=rclpy.spin, args=(node,), daemon=True)
    spinner.start()
    try:
        source.run(relay.update_catalog, forward, stop)
    finally:
        source.close()
        files.close()
        relay.close()
        node.destroy_node()
        rclpy.shutdown()
        session.close()
    return 0


def _message_class(msgtype: str) -> Any:
    """The rclpy message class (needed by create_subscription even in raw mode)."""
    from rosidl_runtime_py.utilities import get_message

    return get_message(msgtype)
