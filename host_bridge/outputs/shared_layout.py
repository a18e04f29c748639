"""One layout for hosts that share a viewer: each host lays out every robot of the fleet.

Hosts of one fleet given the same ``--recording-id`` fill one recording in the viewer they share,
but a viewer shows one layout, the last one sent, and each host's layout named only its own
robots (benchmarks/fleet.py --router: the layout shown alternated between the hosts' halves).
So each host tells the others over Zenoh the topics it lays out (robot, topic, type, entity
path: :class:`~host_bridge.outputs.blueprint.TopicEntry`), and lays out theirs beside its own:
every host sends the same layout, whichever comes last.

Keys: ``swanky/@layout/<recording id>/<Zenoh id of the host>``; each host puts its topics there
when they change and answers a query there (a host that starts later asks ``.../*``), and puts
them again when it first hears from another host: that host's query may have gone out before it
could reach this one (``.ci/run`` once saw a late host's layout miss the first host's). ``@layout``
is a verbatim chunk: no robot's ``swanky/*/...`` subscription or query matches it. A peer's
topics stay in the layout after the peer stopped, as its data stays in the recording.
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Iterable
from typing import TYPE_CHECKING
from urllib.parse import quote

import zenoh

from host_bridge.outputs.blueprint import TopicEntry
from robot_relay.wire import PREFIX

if TYPE_CHECKING:
    from host_bridge.outputs.blueprint import BlueprintFollower

log = logging.getLogger("swanky.host")

LAYOUT_CHUNK = "@layout"


def layout_prefix(recording_id: str) -> str:
    """The key space of one recording's hosts (the id quoted: it may hold '/', '*', '?')."""
    return f"{PREFIX}/{LAYOUT_CHUNK}/{quote(recording_id, safe='')}"


def encode_topics(topics: Iterable[TopicEntry]) -> bytes:
    return json.dumps([[t.robot, t.topic, t.msgtype, t.entity_path] for t in sorted(topics)]).encode()


NO_TOPICS = encode_topics(())


def decode_topics(payload: bytes) -> frozenset[TopicEntry]:
    """A peer's topics; ValueError when the payload is not a list of four strings each."""
    try:
        rows = json.loads(payload)
    except ValueError as err:  # JSONDecodeError, UnicodeDecodeError
        msg = f"not JSON ({err})"
        raise ValueError(msg) from err
    if not isinstance(rows, list) or not all(
        isinstance(row, list) and len(row) == 4 and all(isinstance(part, str) for part in row)
        for row in rows
    ):
        msg = "not a list of [robot, topic, type, entity path]"
        raise ValueError(msg)
    return frozenset(TopicEntry(*row) for row in rows)


class SharedLayout:
    """Shares ``follower``'s topics with the other hosts of ``recording_id`` on ``session`` and
    hands it theirs (:meth:`BlueprintFollower.peer_topics`)."""

    def __init__(self, session: zenoh.Session, recording_id: str, follower: BlueprintFollower) -> None:
        prefix = layout_prefix(recording_id)
        self._own_key = f"{prefix}/{session.zid()}"
        self._follower = follower
        self._own = NO_TOPICS
        self._peers: set[str] = set()
        # Zenoh's callbacks and the follower's thread put while close() may undeclare: zenoh's
        # Python publisher raises "Already borrowed" when the two overlap (a .ci/run did).
        self._publishing = threading.Lock()
        self._closed = False
        # Remote only: a put made in _on_sample (Zenoh's callback thread) that went to this
        # session's own subscriber waited for room in that subscriber's queue, which only that
        # thread empties; with many hosts' layouts queued it waited for ever.
        self._publisher = session.declare_publisher(
            self._own_key, allowed_destination=zenoh.Locality.REMOTE)
        self._queryable = session.declare_queryable(self._own_key, self._on_query)
        self._subscriber = session.declare_subscriber(f"{prefix}/*", self._on_sample)
        follower.on_own_topics = self._publish
        session.get(f"{prefix}/*", self._on_reply)  # the hosts already there

    def _publish(self, topics: frozenset[TopicEntry]) -> None:
        self._own = encode_topics(topics)
        self._put_own()

    def _put_own(self) -> None:
        with self._publishing:
            if not self._closed:
                self._publisher.put(self._own)

    def _on_query(self, query: zenoh.Query) -> None:
        query.reply(self._own_key, self._own)

    def _on_reply(self, reply: zenoh.Reply) -> None:
        if reply.ok is not None:
            self._on_sample(reply.ok)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        if key == self._own_key:
            return
        try:
            topics = decode_topics(sample.payload.to_bytes())
        except ValueError as err:
            log.warning("layout shared at %s: ignored, %s", key, err)
            return
        met = key not in self._peers
        self._peers.add(key)
        self._follower.peer_topics(key, topics)
        if met and self._own != NO_TOPICS:
            self._put_own()

    def close(self) -> None:
        self._follower.on_own_topics = None
        self._subscriber.undeclare()
        self._queryable.undeclare()
        with self._publishing:
            self._closed = True
            self._publisher.undeclare()
