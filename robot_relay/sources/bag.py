"""Raw replay of rosbag2 (sqlite3, MCAP, split, bare .mcap) and ROS 1 bags; nothing is decoded.

ROS 1 payloads are turned into CDR here with rosbags' ``ros1_to_cdr`` (a byte-level re-layout
driven by the bag's own definitions, not a decode into objects), so the wire always carries CDR
and the host has one decoding path. Like ``rosbags-convert``, it drops ``Header.seq`` (rosbags
expects the ROS 2 Header there); every other field keeps the bag's layout and names (CameraInfo
``D K R P``), and the definition sent along is generated from exactly those types.

Needs rosbags (``pip install swanky[relay,bag]``); the live ROS 2 source does not.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from robot_relay.errors import SourceError
from robot_relay.sources.qos import adapted_qos
from robot_relay.wire import (
    Catalog,
    MessageDefinition,
    QosProfile,
    RawMessage,
    TopicInfo,
    absolute_topic,
)

log = logging.getLogger("swanky.relay")

# Bags recorded without QoS metadata (ROS 1, old rosbag2) still have these latched in ROS.
CONVENTIONALLY_LATCHED = frozenset({"/tf_static", "/robot_description", "/map"})

TopicFilter = Callable[[str], bool]


def _all_topics(topic: str) -> bool:
    return True


def bag_paths(path: Path) -> list[Path]:
    """The paths AnyReader wants: a rosbag2 directory or .mcap/.db3 file, or ROS 1 .bag files."""
    if not path.exists():
        msg = f"bag {path} does not exist"
        raise SourceError(msg)
    if path.is_dir() and not (path / "metadata.yaml").exists():
        bags = sorted(path.glob("*.bag"))
        if bags:
            return bags
        msg = f"{path} is a directory without metadata.yaml and without .bag files: not a bag"
        raise SourceError(msg)
    return [path]


def _qos(connection: Any, topic: str) -> QosProfile:
    profiles = getattr(connection.ext, "offered_qos_profiles", None) or []
    if profiles:
        return adapted_qos([
            (p.reliability.name.lower(), p.durability.name.lower(), p.depth) for p in profiles
        ])
    if getattr(connection.ext, "latching", None) or topic in CONVENTIONALLY_LATCHED:
        return QosProfile(durability="transient_local", depth=1)
    return QosProfile()


def _definition(connection: Any) -> MessageDefinition | None:
    fmt = connection.msgdef.format.name
    if fmt == "MSG" and connection.msgdef.data:
        return MessageDefinition("ros2msg", connection.msgdef.data)
    if fmt == "IDL":
        return MessageDefinition("ros2idl", connection.msgdef.data)
    return None


def _ros1_conversion_store(bag_store: Any) -> Any:
    """The bag's own types, but with the ROS 2 Header, as ``ros1_to_cdr`` requires."""
    from rosbags.typesys import Stores, get_typestore

    types = dict(bag_store.fielddefs)
    humble = get_typestore(Stores.ROS2_HUMBLE)
    for name in ("std_msgs/msg/Header", "builtin_interfaces/msg/Time"):
        types[name] = humble.fielddefs[name]
    store = get_typestore(Stores.EMPTY)
    store.register(types)
    return store


class BagSource:
    """Yields a bag's messages as RawMessages in log-time order, optionally paced."""

    def __init__(
        self,
        path: Path,
        robot: str,
        *,
        rate: float = 0.0,
        loop: bool = False,
        topics: TopicFilter = _all_topics,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        self.paths = bag_paths(path)
        self.robot = robot
        self.rate = rate
        self.loop = loop
        self.topics = topics
        self._sleep = sleep
        self._stack = ExitStack()
        self._reader: Any = None
        self._ros1_store: Any = None
        self._warned: set[str] = set()

    def __enter__(self) -> BagSource:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        try:
            self._reader = self._stack.enter_context(
                AnyReader(self.paths, default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            )
        except Exception as err:
            msg = f"bag {self.paths[0]} cannot be opened: {err}"
            raise SourceError(msg) from err
        self.is_ros1 = not self._reader.is2
        self.connections = [c for c in self._reader.connections if self.topics(c.topic)]
        if self.is_ros1:
            self._ros1_store = _ros1_conversion_store(self._reader.typestore)
        self._infos = {
            c.id: TopicInfo(
                topic=absolute_topic(c.topic),
                msgtype=c.msgtype,
                definition=self._ros1_definition(c.msgtype) if self.is_ros1 else _definition(c),
                qos=_qos(c, absolute_topic(c.topic)),
            )
            for c in self.connections
        }
        return self

    def __exit__(self, *exc: object) -> None:
        self._stack.close()

    def catalog(self) -> Catalog:
        unique = {(i.topic, i.msgtype): i for i in self._infos.values()}
        return Catalog(robot=self.robot, source="bag", topics=tuple(unique.values()))

    def _ros1_definition(self, msgtype: str) -> MessageDefinition:
        return MessageDefinition("ros2msg", self._ros1_store.generate_msgdef(msgtype, ros_version=2)[0])

    def _cdr(self, raw: bytes, info: TopicInfo) -> bytes | memoryview | None:
        """CDR of a bag payload; None (warned once per topic) when a ROS 1 one is broken."""
        if not self.is_ros1:
            return raw
        try:
            return self._ros1_store.ros1_to_cdr(raw, info.msgtype)  # type: ignore[no-any-return]
        except Exception as err:
            if info.topic not in self._warned:
                self._warned.add(info.topic)
                log.warning(
                    "%s (%s): ROS 1 message does not convert to CDR, skipped: %s",
                    info.topic, info.msgtype, err,
                )
            return None

    def messages(self) -> Iterator[RawMessage]:
        """Every message once (or forever with ``loop``), paced by ``rate`` (0: no pacing)."""
        if not self.connections:
            return
        while True:
            started = time.monotonic()
            first_ns: int | None = None
            for connection, log_ns, raw in self._reader.messages(connections=self.connections):
                if first_ns is None:
                    first_ns = log_ns
                if self.rate > 0:
                    delay = (log_ns - first_ns) / 1e9 / self.rate - (time.monotonic() - started)
                    if delay > 0:
                        self._sleep(delay)
                info = self._infos[connection.id]
                data = self._cdr(raw, info)
                if data is None:
                    continue
                yield RawMessage(
                    robot=self.robot,
                    topic=info.topic,
                    msgtype=info.msgtype,
                    data=data,
                    definition=info.definition,
                    log_ns=log_ns,
                )
            if not self.loop:
                return
