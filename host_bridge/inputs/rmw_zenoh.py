"""rmw_zenoh robots read directly, with no relay: their data keys and liveliness graph ->
RawMessages, like the swanky wire input (zenoh.py). The key, token and attachment formats are
parsed in ``robot_relay/wire.py`` (its rmw_zenoh section).

A data key does not say which node sent it, so the robot comes from the graph: the first
namespace segment of the topic's publishers (``/tb3/scan`` from a node in ``/tb3`` is robot
``tb3``, topic ``/scan``); topics of nodes without a namespace belong to the robot named by
``--robot``. (A name per Zenoh session would split one robot in pieces: rmw_zenoh gives every
ROS process its own session, and the scan's frames would then never meet the TF tree.)
Definitions come from the host's bundled typestore; a Jazzy type hash picks the Jazzy
definition where it differs from Humble (``sensor_msgs/msg/Range``; see
``schemas.BundledDefinitions``).

Times: with no relay there is no clock to measure (inputs/clocks.py). ``receive_time`` is the
host's own arrival time, on the PC's clock like every corrected relay's; ``latency_ms`` is then
only the host's queue wait, not the link's; ``log_time`` (the publisher's source timestamp) and
``ros_time`` (header stamps) stay on the robot's clock.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Collection
from dataclasses import dataclass

import zenoh
from zenoh import ext

from host_bridge.core.schemas import BundledDefinitions
from host_bridge.errors import GraphError, UnknownTypeError
from host_bridge.inputs.base import InputProblem, RobotEvent
from host_bridge.inputs.queues import RobotQueues
from host_bridge.inputs.rmw_keys import (
    RMW_NODE,
    RMW_PUBLISHER,
    RmwAttachment,
    RmwDataKey,
    RmwGraphEntity,
    parse_rmw_attachment,
    parse_rmw_data_key,
    parse_rmw_token,
    rmw_data_selector,
    rmw_liveliness_selector,
)
from host_bridge.inputs.zenoh import check_robot_pattern, robot_matches
from robot_relay.wire import ROBOT_NAME_PATTERN, MessageDefinition, RawMessage

log = logging.getLogger("swanky.host")

SOURCE = "rmw_zenoh"
# Samples that arrive before their publisher's liveliness token wait this long (and at most
# this many per key) for it; after that they go to the --robot robot.
WAIT_FOR_GRAPH_S = 2.0
MAX_WAITING_PER_KEY = 200


# -- robot of a topic, from its publishers' namespaces --------------------------------------


def namespace_robot(namespace: str) -> str | None:
    """First segment of a node namespace as a robot name; None for the root namespace."""
    first = namespace.strip("/").split("/", 1)[0]
    if not first:
        return None
    return "".join(c if ROBOT_NAME_PATTERN.match(c) else "_" for c in first)


def resolve_robot(topic: str, namespaces: Collection[str | None], root_robot: str) -> tuple[str, str]:
    """(robot, topic within the robot) of a topic published from nodes in ``namespaces``
    (their :func:`namespace_robot`). A topic inside its publishers' namespace loses that prefix;
    a topic outside it (``/tf`` from a node in ``/tb3``) belongs to that namespace's robot when
    all its publishers share one; anything else is the ``root_robot``'s."""
    first, _, rest = topic.lstrip("/").partition("/")
    if first in namespaces and rest:
        return first, "/" + rest
    named = {namespace for namespace in namespaces if namespace is not None}
    if len(named) == 1 and None not in namespaces:
        return named.pop(), topic
    return root_robot, topic


# -- the input ---------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _Route:
    robot: str
    topic: str
    definition: MessageDefinition | None
    latched: bool
    accepted: bool


@dataclass(frozen=True, slots=True)
class _Waiting:
    key: RmwDataKey
    payload: bytes
    attachment: RmwAttachment | None
    receive_ns: int


class RmwZenohInput:
    """Subscribes to ``<domain>/**`` and the ``@ros2_lv/<domain>/**`` graph; puts RawMessages of
    the robots matched by ``robots`` (see zenoh.check_robot_pattern) into ``queues``."""

    def __init__(
        self,
        session: zenoh.Session,
        domain: int = 0,
        robots: str = "*",
        root_robot: str = "robot",
        queues: RobotQueues | None = None,
    ) -> None:
        self.queues = queues or RobotQueues()
        self.root_robot = root_robot
        self._robots = check_robot_pattern(robots)
        self._definitions = BundledDefinitions()
        self._lock = threading.Lock()
        self._entities: dict[str, RmwGraphEntity] = {}
        self._nodes_per_robot: dict[str, int] = {}
        self._routes: dict[str, _Route] = {}
        self._waiting: dict[str, deque[_Waiting]] = {}
        self._gids: dict[tuple[str, str], set[bytes]] = {}
        self._warned: set[tuple[str, str]] = set()
        self._closed = False
        self._liveliness = session.liveliness().declare_subscriber(
            rmw_liveliness_selector(domain), self._on_token, history=True
        )
        # Transient-local publishers (rmw_zenoh's AdvancedPublisher cache) answer the history
        # query, so a host that starts late still gets /tf_static and maps.
        self._subscriber = ext.declare_advanced_subscriber(
            session, rmw_data_selector(domain), self._on_sample,
            history=ext.HistoryConfig(detect_late_publishers=True),
        )

    # -- graph ---------------------------------------------------------------------------------

    def _robot_of_node(self, entity: RmwGraphEntity) -> str:
        return namespace_robot(entity.namespace) or self.root_robot

    def _on_token(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            entity = parse_rmw_token(key)
        except GraphError as err:
            self._problem("?", key, err)
            return
        if entity.kind not in (RMW_NODE, RMW_PUBLISHER):
            return
        event: RobotEvent | None = None
        flush: list[str] = []
        with self._lock:
            robot = self._robot_of_node(entity)
            if sample.kind == zenoh.SampleKind.PUT:
                if key in self._entities:
                    return
                self._entities[key] = entity
                if entity.kind == RMW_NODE:
                    count = self._nodes_per_robot.get(robot, 0)
                    self._nodes_per_robot[robot] = count + 1
                    if count == 0:
                        event = RobotEvent(robot, True, SOURCE)
            else:
                if self._entities.pop(key, None) is None:
                    return
                if entity.kind == RMW_NODE:
                    count = self._nodes_per_robot.get(robot, 1) - 1
                    self._nodes_per_robot[robot] = count
                    if count == 0:
                        event = RobotEvent(robot, False, SOURCE)
                        self._gids = {k: v for k, v in self._gids.items() if k[0] != robot}
            # Who publishes what changed: routes are worked out again from the new graph.
            self._routes.clear()
            flush = list(self._waiting)
        if event is not None and robot_matches(event.robot, self._robots):
            self.queues.put(event)
            if event.joined:
                log.info("robot %s (rmw_zenoh) has no relay whose clock the host can measure: its "
                         "receive_time is this PC's arrival time, its latency_ms the host's own "
                         "wait only; ros_time and log_time stay on the robot's clock", event.robot)
        for waiting_key in flush:
            self._flush(waiting_key, final=False)

    # -- data ----------------------------------------------------------------------------------

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        receive_ns = time.time_ns()
        try:
            data_key = parse_rmw_data_key(key)
            attachment = None if sample.attachment is None else parse_rmw_attachment(
                sample.attachment.to_bytes(), key
            )
        except GraphError as err:
            self._problem("?", key, err)
            return
        waiting = _Waiting(data_key, sample.payload.to_bytes(), attachment, receive_ns)
        # Outside the lock: the first Jazzy hash of a type builds the bundled typestores.
        self._definitions.lookup(data_key.msgtype, data_key.type_hash)
        with self._lock:
            route = self._route(key, data_key, final=False)
            if route is None:
                queue = self._waiting.get(key)
                if queue is None:
                    queue = self._waiting[key] = deque(maxlen=MAX_WAITING_PER_KEY)
                    timer = threading.Timer(WAIT_FOR_GRAPH_S, self._flush, args=(key, True))
                    timer.daemon = True
                    timer.start()
                queue.append(waiting)
                return
        self._emit(route, waiting)

    def _route(self, key: str, data_key: RmwDataKey, final: bool) -> _Route | None:
        """Where samples of ``key`` go (lock held); None while the graph does not know yet."""
        route = self._routes.get(key)
        if route is not None:
            return route
        publishers = [
            e for e in self._entities.values()
            if e.kind == RMW_PUBLISHER and e.topic == data_key.topic and e.msgtype == data_key.msgtype
        ]
        namespaces: set[str | None] = {namespace_robot(e.namespace) for e in publishers}
        if not publishers:
            known = {namespace_robot(e.namespace) for e in self._entities.values()}
            first = data_key.topic.lstrip("/").split("/", 1)[0]
            if first in known:
                namespaces = {first}
            elif not final:
                return None
        robot, topic = resolve_robot(data_key.topic, namespaces, self.root_robot)
        definition, warning = self._definitions.lookup(data_key.msgtype, data_key.type_hash)
        route = _Route(
            robot=robot, topic=topic, definition=definition,
            latched=any(e.qos is not None and e.qos.durability == "transient_local"
                        for e in publishers),
            accepted=robot_matches(robot, self._robots),
        )
        self._routes[key] = route
        if warning is not None and route.accepted and (robot, topic) not in self._warned:
            self._warned.add((robot, topic))
            self.queues.put(InputProblem(robot, topic, UnknownTypeError(warning)))
        return route

    def _flush(self, key: str, final: bool) -> None:
        """Send the samples that waited for the graph, once it knows their publisher (or, when
        ``final``, to the --robot robot)."""
        with self._lock:
            queue = self._waiting.get(key)
            if not queue or self._closed:
                return
            route = self._route(key, queue[0].key, final)
            if route is None:
                return
            del self._waiting[key]
        for waiting in queue:
            self._emit(route, waiting)

    def _emit(self, route: _Route, waiting: _Waiting) -> None:
        if not route.accepted:
            return
        sequence: int | None = None
        source_ns: int | None = None
        if waiting.attachment is not None:
            source_ns = waiting.attachment.source_ns or None
            with self._lock:
                gids = self._gids.setdefault((route.robot, route.topic), set())
                gids.add(waiting.attachment.gid)
                # Sequence numbers are per publisher: with several, gaps would be invented.
                if len(gids) == 1:
                    sequence = waiting.attachment.sequence
        raw = RawMessage(
            robot=route.robot, topic=route.topic, msgtype=waiting.key.msgtype,
            data=waiting.payload, definition=route.definition, receive_ns=waiting.receive_ns,
            log_ns=source_ns, sequence=sequence,
        )
        self.queues.put(raw, route.latched)

    def _problem(self, robot: str, key: str, err: Exception) -> None:
        with self._lock:
            if (robot, key) in self._warned:
                return
            self._warned.add((robot, key))
        self.queues.put(InputProblem(robot, key, err))

    def close(self) -> None:
        with self._lock:
            self._closed = True
        self._subscriber.undeclare()
        self._liveliness.undeclare()
