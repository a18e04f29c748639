"""Sources -> Zenoh publishers, per schemas/wire.md. The relay never decodes a message.

Latched topics go through a zenoh-ext AdvancedPublisher with a cache, so a host that starts
late (or reconnects) still gets /tf_static, /robot_description and /map. Everything else uses a
plain publisher, whose matching status tells the relay whether any host listens.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterable
from typing import Any

import zenoh
from zenoh import ext

from robot_relay.wire import (
    Attachment,
    Catalog,
    RawMessage,
    TopicInfo,
    alive_key,
    catalog_key,
    cdr_encoding,
    check_robot_name,
    data_key,
)

log = logging.getLogger("swanky.relay")


class _TopicPublisher:
    def __init__(self, session: zenoh.Session, robot: str, info: TopicInfo) -> None:
        self.info = info
        self.key = data_key(robot, info.topic)
        self.sequence = 0
        encoding = zenoh.Encoding(cdr_encoding(info.msgtype))
        self.publisher: Any
        if info.latched:
            self.publisher = ext.declare_advanced_publisher(
                session,
                self.key,
                encoding=encoding,
                congestion_control=zenoh.CongestionControl.BLOCK,
                cache=ext.CacheConfig(max(info.qos.depth, 1)),
                publisher_detection=True,
            )
        else:
            self.publisher = session.declare_publisher(
                self.key,
                encoding=encoding,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )

    @property
    def matching(self) -> bool:
        """Whether some host listens; a cached latched topic is always worth publishing."""
        if self.info.latched:
            return True
        status = self.publisher.matching_status
        # zenoh-python returns a MatchingStatus object (its stub says bool).
        return bool(getattr(status, "matching", status))

    def put(self, raw: RawMessage, receive_ns: int) -> None:
        attachment = Attachment(self.sequence, receive_ns, raw.log_ns or 0)
        self.publisher.put(bytes(raw.data), attachment=attachment.pack())
        self.sequence = (self.sequence + 1) & 0xFFFFFFFF

    def undeclare(self) -> None:
        self.publisher.undeclare()


class Relay:
    """Publishes RawMessages of one robot; answers its catalog; holds its liveliness token."""

    def __init__(self, session: zenoh.Session, catalog: Catalog) -> None:
        self.session = session
        self.robot = check_robot_name(catalog.robot)
        self.catalog = catalog
        self._catalog_json = catalog.to_json()
        self._publishers: dict[str, _TopicPublisher] = {}
        self._lock = threading.Lock()
        for info in catalog.topics:
            self._publisher(info)
        self._queryable = session.declare_queryable(catalog_key(self.robot), self._answer_catalog)
        self._token = session.liveliness().declare_token(alive_key(self.robot))
        self.published = 0

    def _publisher(self, info: TopicInfo) -> _TopicPublisher:
        publisher = self._publishers.get(info.topic)
        if publisher is None:
            publisher = _TopicPublisher(self.session, self.robot, info)
            self._publishers[info.topic] = publisher
        return publisher

    def _answer_catalog(self, query: zenoh.Query) -> None:
        with self._lock:
            payload = self._catalog_json
        query.reply(catalog_key(self.robot), payload, encoding=zenoh.Encoding.APPLICATION_JSON)

    def update_catalog(self, catalog: Catalog) -> None:
        """New topics appeared (live source): publish them and answer the new catalog."""
        with self._lock:
            self.catalog = catalog
            self._catalog_json = catalog.to_json()
            for info in catalog.topics:
                self._publisher(info)

    def wait_for_host(self, timeout: float | None) -> bool:
        """Block until a host subscribes to any non-latched topic (or ``timeout`` passes)."""
        plain = [p for p in self._publishers.values() if not p.info.latched]
        if not plain:
            return True
        deadline = None if timeout is None else time.monotonic() + timeout
        while deadline is None or time.monotonic() < deadline:
            if any(p.matching for p in plain):
                return True
            time.sleep(0.05)
        return False

    def publish(self, raw: RawMessage) -> None:
        self._publishers[raw.topic].put(raw, time.time_ns())
        self.published += 1

    def publish_all(self, messages: Iterable[RawMessage], stop: threading.Event) -> None:
        for raw in messages:
            if stop.is_set():
                return
            self.publish(raw)

    def close(self) -> None:
        for publisher in self._publishers.values():
            publisher.undeclare()
        self._queryable.undeclare()
        self._token.undeclare()
