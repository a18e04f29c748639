"""rmw_zenoh robots read directly, with no relay: their data keys and liveliness graph ->
RawMessages, like the swanky wire input (zenoh.py).

rmw_zenoh (Humble 0.1.x, Jazzy and later) publishes every ROS message as raw CDR (encapsulation
header included) on ``<domain>/<topic>/<dds type>/<type hash>``, with the type hash
``TypeHashNotSupported`` on Humble and ``RIHS01_<sha256>`` from Jazzy on. Its graph is a set of
liveliness tokens
``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<kind>/<enclave>/<namespace>/<node>`` followed,
for publishers (kind ``MP``), by ``/<topic>/<dds type>/<type hash>/<qos>``; names are mangled
(``/`` -> ``%``). The attachment holds the sequence number, the source timestamp and the
publisher gid.

A data key does not say which node sent it, so the robot comes from the graph: the first
namespace segment of the topic's publishers (``/tb3/scan`` from a node in ``/tb3`` is robot
``tb3``, topic ``/scan``); topics of nodes without a namespace belong to the robot named by
``--robot``. (A name per Zenoh session would split one robot in pieces: rmw_zenoh gives every
ROS process its own session, and the scan's frames would then never meet the TF tree.)
Definitions come from the host's bundled typestore; a Jazzy type hash picks the Jazzy
definition where it differs from Humble (``sensor_msgs/msg/Range``).
"""

from __future__ import annotations

import logging
import struct
import threading
import time
from collections import deque
from collections.abc import Collection
from dataclasses import dataclass

import zenoh
from zenoh import ext

from host_bridge.errors import GraphError, UnknownTypeError
from host_bridge.inputs.queues import InputProblem, QueueItem, RobotEvent, RobotQueues
from host_bridge.inputs.zenoh import check_robot_pattern, robot_matches
from robot_relay.wire import ROBOT_NAME_PATTERN, MessageDefinition, QosProfile, RawMessage

log = logging.getLogger("swanky.host")

ADMIN_SPACE = "@ros2_lv"
TYPE_HASH_NOT_SUPPORTED = "TypeHashNotSupported"
NODE = "NN"
PUBLISHER = "MP"
SOURCE = "rmw_zenoh"
# Samples that arrive before their publisher's liveliness token wait this long (and at most
# this many per key) for it; after that they go to the --robot robot.
WAIT_FOR_GRAPH_S = 2.0
MAX_WAITING_PER_KEY = 200

_I64 = struct.Struct("<q")
_GID_SIZE = 16


# -- pure parsing ------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class DataKey:
    domain: int
    topic: str
    msgtype: str
    type_hash: str | None  # None: Humble's TypeHashNotSupported


@dataclass(frozen=True, slots=True)
class GraphEntity:
    """One liveliness token: a node (``NN``) or an endpoint (``MP``, ``MS``, ``SS``, ``SC``)."""

    domain: int
    session: str
    node_id: str
    entity_id: str
    kind: str
    namespace: str
    node: str
    topic: str | None = None
    msgtype: str | None = None
    type_hash: str | None = None
    qos: QosProfile | None = None


@dataclass(frozen=True, slots=True)
class RmwAttachment:
    sequence: int
    source_ns: int
    gid: bytes


def demangle(name: str) -> str:
    """rmw_zenoh writes ``/`` as ``%`` inside one key chunk (``%tb3%scan`` -> ``/tb3/scan``)."""
    return name.replace("%", "/")


def ros_type(dds_type: str) -> str:
    """``sensor_msgs::msg::dds_::LaserScan_`` -> ``sensor_msgs/msg/LaserScan``."""
    parts = dds_type.split("::")
    if len(parts) != 4 or parts[2] != "dds_" or not parts[3].endswith("_") or len(parts[3]) < 2:
        msg = f"type {dds_type!r} is not an rmw_zenoh type name (<pkg>::msg::dds_::<Name>_)"
        raise GraphError(msg)
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


def _type_hash(text: str) -> str | None:
    return None if text == TYPE_HASH_NOT_SUPPORTED else text


def parse_data_key(key: str) -> DataKey:
    """``0/tb3/scan/sensor_msgs::msg::dds_::LaserScan_/RIHS01_...`` -> its parts."""
    parts = key.split("/")
    if len(parts) < 4 or not parts[0].isdigit():
        msg = f"key {key!r} is not an rmw_zenoh data key (<domain>/<topic>/<type>/<hash>)"
        raise GraphError(msg)
    try:
        msgtype = ros_type(parts[-2])
    except GraphError as err:
        msg = f"key {key!r}: {err}"
        raise GraphError(msg) from err
    return DataKey(int(parts[0]), "/" + "/".join(parts[1:-2]), msgtype, _type_hash(parts[-1]))


def parse_qos(text: str) -> QosProfile:
    """The reliability, durability and depth of an rmw_zenoh QoS chunk; empty fields are the
    rmw defaults (reliable, volatile, depth 10)."""
    fields = text.split(":")
    if len(fields) < 3:
        msg = f"QoS {text!r} is not an rmw_zenoh QoS string (<rel>:<dur>:<hist>,<depth>:...)"
        raise GraphError(msg)
    _, _, depth = fields[2].partition(",")
    try:
        return QosProfile(
            reliability="best_effort" if fields[0] == "2" else "reliable",
            durability="transient_local" if fields[1] == "1" else "volatile",
            depth=int(depth) if depth else 10,
        )
    except ValueError as err:
        msg = f"QoS {text!r}: history depth {depth!r} is not a number"
        raise GraphError(msg) from err


def parse_token(key: str) -> GraphEntity:
    """A liveliness token key -> the node or endpoint it announces."""
    parts = key.split("/")
    if len(parts) < 9 or parts[0] != ADMIN_SPACE or not parts[1].isdigit():
        msg = (
            f"liveliness token {key!r} is not an rmw_zenoh one ({ADMIN_SPACE}/<domain>/<zid>/"
            "<node id>/<entity id>/<kind>/<enclave>/<namespace>/<node>[/<topic>/<type>/<hash>/<qos>])"
        )
        raise GraphError(msg)
    entity = GraphEntity(
        domain=int(parts[1]), session=parts[2], node_id=parts[3], entity_id=parts[4],
        kind=parts[5], namespace=demangle(parts[7]), node=demangle(parts[8]),
    )
    if parts[5] == NODE:
        return entity
    if len(parts) < 13:
        msg = f"liveliness token {key!r} of a {parts[5]} lacks <topic>/<type>/<hash>/<qos>"
        raise GraphError(msg)
    try:
        msgtype = ros_type(parts[10])
        qos = parse_qos(parts[12])
    except GraphError as err:
        msg = f"liveliness token {key!r}: {err}"
        raise GraphError(msg) from err
    return GraphEntity(
        domain=entity.domain, session=entity.session, node_id=entity.node_id,
        entity_id=entity.entity_id, kind=entity.kind, namespace=entity.namespace,
        node=entity.node, topic=demangle(parts[9]), msgtype=msgtype,
        type_hash=_type_hash(parts[11]), qos=qos,
    )


def _varint(data: bytes, pos: int) -> tuple[int, int]:
    """zenoh-ext's LEB128 length prefix."""
    value = shift = 0
    while pos < len(data):
        byte = data[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return value, pos
        shift += 7
    raise IndexError("truncated length")


def parse_attachment(data: bytes, key: str) -> RmwAttachment:
    """The publisher attachment, in either form rmw_zenoh has used: zenoh-ext serialized
    ``"sequence_number", i64, "source_timestamp", i64, "source_gid", gid`` (rmw_zenoh Humble
    and Jazzy releases) or the same without the names (ros-z, zenoh-ros2-sdk). The gid is 16
    bytes, with or without its length prefix."""
    pos = 0

    def label(name: bytes) -> None:
        nonlocal pos
        length, start = _varint(data, pos)
        if data[start:start + length] != name:
            raise ValueError(f"expected {name.decode()!r}")
        pos = start + length

    def int64() -> int:
        nonlocal pos
        (value,) = _I64.unpack_from(data, pos)
        pos += _I64.size
        return int(value)

    keyed = data.startswith(b"\x0fsequence_number")
    try:
        if keyed:
            label(b"sequence_number")
        sequence = int64()
        if keyed:
            label(b"source_timestamp")
        source_ns = int64()
        if keyed:
            label(b"source_gid")
        if len(data) - pos != _GID_SIZE:
            length, pos = _varint(data, pos)
            if length != len(data) - pos:
                raise ValueError(f"gid of {length} bytes in {len(data) - pos}")
        gid = data[pos:]
    except (ValueError, IndexError, struct.error) as err:
        msg = f"attachment on {key!r} ({len(data)} bytes) is not an rmw_zenoh attachment: {err}"
        raise GraphError(msg) from err
    return RmwAttachment(sequence, source_ns, gid)


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


# -- definitions -------------------------------------------------------------------------------


class BundledDefinitions:
    """Which bundled definition a publisher's type hash names: Humble (plus schemas/msg),
    else Jazzy. ``None`` means "the decoder's own bundled Humble store"."""

    def __init__(self) -> None:
        self._answers: dict[tuple[str, str], tuple[MessageDefinition | None, str | None]] = {}
        self._lock = threading.Lock()

    def lookup(self, msgtype: str, type_hash: str | None) -> tuple[MessageDefinition | None, str | None]:
        """(definition to decode with, warning to show once or None)."""
        if type_hash is None:
            return None, None
        with self._lock:
            answer = self._answers.get((msgtype, type_hash))
            if answer is None:
                answer = self._answers[(msgtype, type_hash)] = self._match(msgtype, type_hash)
        return answer

    @staticmethod
    def _match(msgtype: str, type_hash: str) -> tuple[MessageDefinition | None, str | None]:
        from rosbags.typesys import Stores, get_typestore

        from host_bridge.decode import base_typestore

        humble = base_typestore()
        for index, store in enumerate((humble, get_typestore(Stores.ROS2_JAZZY))):
            if msgtype not in store.fielddefs:
                continue
            try:
                matches = store.hash_rihs01(msgtype) == type_hash
            except Exception:  # a definition rosbags cannot hash: not this one
                matches = False
            if matches:
                if index == 0:
                    return None, None
                return MessageDefinition("ros2msg", store.generate_msgdef(msgtype, ros_version=2)[0]), None
        if msgtype in humble.fielddefs:
            return None, (
                f"type hash {type_hash} of {msgtype} matches no bundled definition (Humble, "
                "Jazzy): decoding with the Humble one, which fails if the layouts differ"
            )
        return None, None  # unknown type: the decoder names it, once per topic


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
    key: DataKey
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
        self._entities: dict[str, GraphEntity] = {}
        self._nodes_per_robot: dict[str, int] = {}
        self._routes: dict[str, _Route] = {}
        self._waiting: dict[str, deque[_Waiting]] = {}
        self._gids: dict[tuple[str, str], set[bytes]] = {}
        self._warned: set[tuple[str, str]] = set()
        self._closed = False
        self._liveliness = session.liveliness().declare_subscriber(
            f"{ADMIN_SPACE}/{domain}/**", self._on_token, history=True
        )
        # Transient-local publishers (rmw_zenoh's AdvancedPublisher cache) answer the history
        # query, so a host that starts late still gets /tf_static and maps.
        self._subscriber = ext.declare_advanced_subscriber(
            session, f"{domain}/**", self._on_sample,
            history=ext.HistoryConfig(detect_late_publishers=True),
        )

    # -- graph ---------------------------------------------------------------------------------

    def _robot_of_node(self, entity: GraphEntity) -> str:
        return namespace_robot(entity.namespace) or self.root_robot

    def _on_token(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            entity = parse_token(key)
        except GraphError as err:
            self._problem("?", key, err)
            return
        if entity.kind not in (NODE, PUBLISHER):
            return
        event: RobotEvent | None = None
        flush: list[str] = []
        with self._lock:
            robot = self._robot_of_node(entity)
            if sample.kind == zenoh.SampleKind.PUT:
                if key in self._entities:
                    return
                self._entities[key] = entity
                if entity.kind == NODE:
                    count = self._nodes_per_robot.get(robot, 0)
                    self._nodes_per_robot[robot] = count + 1
                    if count == 0:
                        event = RobotEvent(robot, True, SOURCE)
            else:
                if self._entities.pop(key, None) is None:
                    return
                if entity.kind == NODE:
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
        for waiting_key in flush:
            self._flush(waiting_key, final=False)

    # -- data ----------------------------------------------------------------------------------

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        receive_ns = time.time_ns()
        try:
            data_key = parse_data_key(key)
            attachment = None if sample.attachment is None else parse_attachment(
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

    def _route(self, key: str, data_key: DataKey, final: bool) -> _Route | None:
        """Where samples of ``key`` go (lock held); None while the graph does not know yet."""
        route = self._routes.get(key)
        if route is not None:
            return route
        publishers = [
            e for e in self._entities.values()
            if e.kind == PUBLISHER and e.topic == data_key.topic and e.msgtype == data_key.msgtype
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

    # -- consumer side -------------------------------------------------------------------------

    def drain(self, max_items: int = 1024, wait: float = 0.05) -> list[QueueItem]:
        return self.queues.drain(max_items, wait)

    def close(self) -> None:
        with self._lock:
            self._closed = True
        self._subscriber.undeclare()
        self._liveliness.undeclare()
