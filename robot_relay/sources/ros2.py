"""Live ROS 2 source: rclpy raw subscriptions (``raw=True``: the CDR bytes, never decoded).

Every ``DISCOVERY_PERIOD_S`` the graph is read again (:meth:`Ros2Source.discover`): a topic with
at least one publisher that passes the allow/deny globs enters the catalog with the QoS adapted
to all its publishers (:func:`robot_relay.sources.qos.live_qos`: the ``ros2 bag record`` rule,
with a queue of at least 10, 50 for reliable streams) and the full definition of its type read
from the ament share directories (.msg, else .idl, as rosbag2 does), so custom packages decode on
a host without them. A topic whose last publisher leaves drops out; one whose type or policies
change, or whose publishers need a deeper queue, is subscribed again. Publishers merely coming
and going change nothing, so a latched topic's history is not delivered again (and what a new
subscription does re-deliver is recognised and dropped: :class:`_Delivered`).

Subscriptions follow demand: the Relay calls :meth:`Ros2Source.on_demand` from Zenoh's threads
when a host starts or stops listening, and the discovery thread applies it (create or destroy
the subscription), so the node is only touched by that thread and rclpy's executor. Latched
topics are always wanted (the Relay says so at once): their cache must be warm for late hosts.

Messages are taken without rclpy's executor, by a :class:`~robot_relay.sources.take_loop.TakeLoop`
(where the relay's CPU per message went, and what the loop saves, is in its docstring).

Loss the relay can see: with one publisher on a topic, a gap in the publication sequence numbers
rclpy gives with each message (Iron and later) counts as drops, reported in the relay's stats.

How this was checked: the source alone against fake nodes answering like rclpy's graph API
(tests/robot_relay/test_ros2_source.py), and :class:`RclpySource` in ``swanky-relay`` against
real rclpy nodes of ROS 2 Jazzy with Fast DDS, from the ros-jazzy PyPI wheels
(tests/integration/test_ros2_live.py). Humble's rclpy (message info without sequence numbers)
has not run here: the take loop uses only calls its source has too (rclpy's humble branch,
read for this); keep this adapter thin.
"""

from __future__ import annotations

import collections
import importlib
import logging
import os
import re
import threading
import time
from collections.abc import Callable, Hashable, Mapping, Sequence
from pathlib import Path
from typing import Any

from robot_relay.errors import SourceError
from robot_relay.heap import keep_freed_buffers
from robot_relay.sources.base import Outlet, SourceThread
from robot_relay.sources.qos import Offer, live_qos
from robot_relay.sources.take_loop import LATENCY_BUDGET_S, RawSubscription, TakeLoop
from robot_relay.wire import Catalog, MessageDefinition, RawMessage, TopicInfo

log = logging.getLogger("swanky.relay")

# A new topic is forwarded within this plus DDS's own matching of the new subscription (up to
# a second or two on a loaded robot); one graph read costs about a millisecond.
DISCOVERY_PERIOD_S = 1.0
# How many forwarded messages of a latched topic are remembered so that a new subscription's
# re-delivery of them is recognised. Depths do not tell: Fast DDS reports 0, and /rosout keeps
# 1000 lines per node (for 10 s); remembering one costs about 100 bytes.
REDELIVERY_WINDOW = 4096
_PRIMITIVES = frozenset({
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
    "uint32", "int64", "uint64", "string", "wstring",
})
_SEPARATOR = "=" * 80
_IDL_INCLUDE = re.compile(r'^#include\s+"([^"/]+/[^"/]+/[^"/]+)\.idl"', re.MULTILINE)

# rclpy's message info: source_timestamp, received_timestamp, and from Iron on
# publication_sequence_number, reception_sequence_number (None where the RMW has none).
MessageInfo = Mapping[str, Any]
Forward = Callable[[bytes, MessageInfo | None], None]
Subscribe = Callable[[TopicInfo, Forward], Any]
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


def _same_request(old: TopicInfo, new: TopicInfo) -> bool:
    """Whether ``old`` still serves ``new``'s publishers: same type and policies, deep enough."""
    return (old.msgtype, old.qos.reliability, old.qos.durability) == (
        new.msgtype, new.qos.reliability, new.qos.durability
    ) and old.qos.depth >= new.qos.depth


class _Delivered:
    """Identities of the messages of one transient-local topic forwarded lately, kept across its
    subscriptions: a new subscription receives every publisher's latched history again, and
    what the hosts (and the relay's cache) already have must not go out twice."""

    def __init__(self, msgtype: str, capacity: int) -> None:
        self.msgtype = msgtype
        self.capacity = capacity
        self._order: collections.deque[Hashable] = collections.deque()
        self._seen: set[Hashable] = set()

    def first_time(self, identity: Hashable) -> bool:
        if identity in self._seen:
            return False
        self._seen.add(identity)
        self._order.append(identity)
        while len(self._order) > self.capacity:
            self._seen.discard(self._order.popleft())
        return True


def message_identity(data: bytes, info: MessageInfo | None) -> Hashable:
    """The same for a message and its re-delivery: source time and the publisher's sequence
    number where the RMW gives them (Iron and later), else the bytes themselves (Humble)."""
    if info is not None and info.get("publication_sequence_number") is not None:
        return (info.get("source_timestamp"), info["publication_sequence_number"])
    return hash(data)


class _Forwarder:
    """The callback of one subscription: drops re-deliveries, counts publication sequence gaps
    (only while the topic has one publisher: the numbers are per publisher and the message info
    does not say which one sent), publishes the rest."""

    def __init__(self, source: Ros2Source, info: TopicInfo, publish: Publish) -> None:
        self.source = source
        self.info = info
        self.publish = publish
        self.delivered = source.delivered.get(info.topic)
        self.last_sequence: int | None = None

    def __call__(self, data: bytes, message_info: MessageInfo | None) -> None:
        if self.delivered is not None and not self.delivered.first_time(
            message_identity(data, message_info)
        ):
            return
        sequence = None if message_info is None else message_info.get("publication_sequence_number")
        if sequence is not None:
            if self.last_sequence is not None and sequence > self.last_sequence + 1 and (
                self.source.publisher_counts.get(self.info.topic) == 1
            ):
                self.source.count_drops(self.info.topic, sequence - self.last_sequence - 1)
            self.last_sequence = sequence
        info = self.info
        # When DDS received it (the system clock): the take loop may have held it for its budget.
        received = None if message_info is None else message_info.get("received_timestamp")
        self.publish(RawMessage(self.source.robot, info.topic, info.msgtype, data, info.definition,
                                receive_ns=received or None))


class Ros2Source:
    """The ROS graph seen through ``graph`` (an rclpy Node), as a catalog and demanded streams.

    ``subscribe(info, callback)`` creates a raw subscription (None if it cannot) whose messages go
    to ``callback(data, message_info)`` (rclpy's message info dict, or None where rclpy has none)
    and ``unsubscribe(handle)`` destroys one: injected, so everything but rclpy itself is testable.
    ``drops`` counts, per topic, messages the relay can tell it never received.
    """

    def __init__(
        self, graph: Any, robot: str, accept: Callable[[str], bool], share_dirs: Sequence[Path],
        *, subscribe: Subscribe, unsubscribe: Callable[[Any], object],
    ) -> None:
        self.graph = graph
        self.robot = robot
        self.accept = accept
        self.share_dirs = list(share_dirs)
        self._subscribe = subscribe
        self._unsubscribe = unsubscribe
        self.topics: dict[str, TopicInfo] = {}
        self.publisher_counts: dict[str, int] = {}
        self.delivered: dict[str, _Delivered] = {}
        self.subscriptions: dict[str, tuple[TopicInfo, Any]] = {}
        self.drops: dict[str, int] = {}
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

    def count_drops(self, topic: str, count: int) -> None:
        with self._lock:
            self.drops[topic] = self.drops.get(topic, 0) + count

    def drop_counts(self) -> dict[str, int]:
        with self._lock:
            return dict(self.drops)

    def discover(self) -> Catalog | None:
        """The graph's catalog now, or None when it is the same as at the previous call.

        A topic keeps its request while it still serves the publishers (same type and policies,
        deep enough): publishers coming and going re-subscribe nothing, and its depth never
        shrinks while it lives.
        """
        found: dict[str, TopicInfo] = {}
        counts: dict[str, int] = {}
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
            info = TopicInfo(topic, msgtype, definition, live_qos(offers))
            old = self.topics.get(topic)
            found[topic] = old if old is not None and _same_request(old, info) else info
            counts[topic] = len(offers)
        self.publisher_counts = counts
        if found == self.topics:
            return None
        for topic in self.topics.keys() - found.keys():
            log.info("%s vanished", topic)
        for topic, info in found.items():
            if self.topics.get(topic) != info:
                log.info("forwarding %s (%s, %s, %s, depth %d)", topic, info.msgtype,
                         info.qos.reliability, info.qos.durability, info.qos.depth)
        self.topics = found
        self._follow_deliveries()
        return Catalog(self.robot, "ros2", tuple(found[t] for t in sorted(found)))

    def _follow_deliveries(self) -> None:
        """One window per transient-local topic, as long as its type stays and it stays latched
        (the relay keeps its Zenoh publisher, and cache, just as long)."""
        for topic, info in self.topics.items():
            window = self.delivered.get(topic)
            if not info.latched:
                self.delivered.pop(topic, None)
            elif window is None or window.msgtype != info.msgtype:
                self.delivered[topic] = _Delivered(info.msgtype, max(info.qos.depth, REDELIVERY_WINDOW))
            else:
                window.capacity = max(info.qos.depth, REDELIVERY_WINDOW)
        for topic in self.delivered.keys() - self.topics.keys():
            del self.delivered[topic]

    def on_demand(self, topic: str, wanted: bool) -> None:
        """From the Relay (Zenoh's threads): remember, and wake the discovery thread."""
        with self._lock:
            self._demand[topic] = wanted
        self.wake.set()

    def apply_demand(self, publish: Publish) -> None:
        """Create or destroy subscriptions as demanded since the last call; a subscription whose
        topic changed (QoS, type) is made again, or dropped when the topic vanished."""
        outdated = {
            topic: topic in self.topics
            for topic, (info, _) in self.subscriptions.items()
            if self.topics.get(topic) != info
        }
        with self._lock:
            demand, self._demand = {**outdated, **self._demand}, {}
        for topic, wanted in demand.items():
            info = self.topics.get(topic) if wanted else None
            current = self.subscriptions.get(topic)
            if current is not None and current[0] == info:
                continue
            if current is not None:
                del self.subscriptions[topic]
                self._unsubscribe(current[1])
                log.info("%s: unsubscribed (%s)", topic, "changed" if info else "no host listens")
            if info is None:
                continue
            handle = self._subscribe(info, _Forwarder(self, info, publish))
            if handle is not None:
                self.subscriptions[topic] = (info, handle)
                log.info("%s: subscribed (%s, %s, depth %d)", topic, info.qos.reliability,
                         info.qos.durability, info.qos.depth)

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
            # Demand and a stop (:meth:`stop`) wake it at once.
            if not stop.is_set():
                self.wake.wait(max(next_discovery - time.monotonic(), 0.0))

    def stop(self, stop: threading.Event) -> None:
        """Set ``stop`` (the one :meth:`run` was given) and wake :meth:`run` to see it."""
        stop.set()
        self.wake.set()

    def close(self) -> None:
        for _, handle in self.subscriptions.values():
            self._unsubscribe(handle)
        self.subscriptions.clear()


def message_class(msgtype: str) -> Any:
    """The Python class of ``pkg/msg/Name`` (create_subscription needs it even in raw mode),
    imported as a ROS install provides it: ``pkg.msg.Name``, no rosidl_runtime_py needed."""
    package, interface, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{package}.{interface}"), name)


class RclpySource:
    """The live ROS 2 graph as the relay's :class:`~robot_relay.sources.base.Source`: a node
    ``swanky_relay`` whose raw subscriptions are taken on one thread by a
    :class:`~robot_relay.sources.take_loop.TakeLoop` while another reads the graph
    (:class:`Ros2Source`) and applies the hosts' demand, and rclpy's executor answers the node's
    own services (parameters) on a third. :meth:`close` destroys the subscriptions, the executor
    and the node, then shuts ROS down. rclpy's own signal handlers are not installed (they would
    shut ROS down under the running threads and end in tracebacks): the command's own handlers
    stop the app, which then closes this source."""

    def __init__(self, robot: str, accept: Callable[[str], bool],
                 latency_budget: float = LATENCY_BUDGET_S) -> None:
        try:
            import rclpy
            from rclpy.exceptions import NoTypeSupportImportedException
            from rclpy.executors import SingleThreadedExecutor
            from rclpy.impl.implementation_singleton import rclpy_implementation
            from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
            from rclpy.signals import SignalHandlerOptions
            from rclpy.type_support import check_is_valid_msg_type
            from rclpy.utilities import get_default_context
        except ImportError as err:
            msg = (f"rclpy is not importable ({err}): source ROS 2 (e.g. "
                   "/opt/ros/humble/setup.bash) or use --bag to replay a bag")
            raise SourceError(msg) from err
        self.robot = robot
        self._rclpy: Any = rclpy
        keep_freed_buffers()
        self._stop = threading.Event()
        self._threads: list[SourceThread] = []
        self._closed = False
        rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
        try:
            node = self._node = rclpy.create_node("swanky_relay")
        except BaseException:
            rclpy.shutdown()
            raise
        loop = self._loop = TakeLoop(rclpy_implementation, get_default_context().handle,
                                     latency_budget)

        def subscribe(info: TopicInfo, forward: Forward) -> RawSubscription | None:
            profile = QoSProfile(
                depth=info.qos.depth,
                reliability=ReliabilityPolicy.BEST_EFFORT if info.qos.reliability == "best_effort"
                else ReliabilityPolicy.RELIABLE,
                durability=DurabilityPolicy.TRANSIENT_LOCAL if info.latched
                else DurabilityPolicy.VOLATILE,
            )
            try:
                message_type = message_class(info.msgtype)
                check_is_valid_msg_type(message_type)  # imports its type support
            except (ImportError, AttributeError, ValueError, RuntimeError,
                    NoTypeSupportImportedException) as err:  # its package is not here
                log.error("%s: cannot subscribe, %s is not importable here: %s", info.topic,
                          info.msgtype, err)
                return None
            return loop.subscribe(node.handle, message_type, info, profile, forward)

        self.graph = Ros2Source(node, robot, accept, ament_share_dirs(), subscribe=subscribe,
                                unsubscribe=loop.remove)
        self._executor: Any = SingleThreadedExecutor()
        self._executor.add_node(node)

    def catalog(self) -> Catalog:
        """Nothing yet: topics arrive through the outlet as the graph is read."""
        return Catalog(self.robot, "ros2", ())

    def start(self, outlet: Outlet) -> None:
        def serve() -> None:  # returns once close() shut the executor down
            while not self._stop.is_set():
                self._executor.spin_once()

        self._threads = [
            SourceThread("rclpy-take", self._loop.run),
            SourceThread("rclpy-services", serve),
            SourceThread("ros2-graph", lambda: self.graph.run(
                outlet.update_catalog, outlet.publish, self._stop)),
        ]
        for thread in self._threads:
            thread.start()

    def ended(self) -> bool:
        """Never, unless a thread failed (raised here)."""
        return any(thread.ended() for thread in self._threads)

    def on_demand(self, topic: str, wanted: bool) -> None:
        self.graph.on_demand(topic, wanted)

    def drop_counts(self) -> Mapping[str, int]:
        return self.graph.drop_counts()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.graph.stop(self._stop)
        self._loop.stop()
        self._executor.shutdown()
        for thread in self._threads:
            thread.join()
        try:
            self.graph.close()
            self._loop.close()
            self._node.destroy_node()
        finally:
            self._rclpy.shutdown()
