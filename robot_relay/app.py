"""``swanky-relay``'s wiring: options -> Zenoh session -> Relay -> file server -> one source.

cli.py turns the flags (over the ``--config`` file) into a :class:`RelayOptions` record and the
process's signals into a stop event; everything here reads records only. The source is a
:class:`~robot_relay.sources.base.Source` (a bag replayed, the live ROS graph); the relay
declares its publishers from the source's catalog and tells it when hosts listen. Closed in this
order: the source (ROS), the file server, the relay's declarations, the session.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

from robot_relay.config import DEFAULT_ALLOW, DEFAULT_DENY
from robot_relay.files import FileService, is_robot_description, serve_files
from robot_relay.policy import PolicyTable
from robot_relay.relay import Relay
from robot_relay.session import ZenohOptions, close_session, open_session
from robot_relay.sources.base import Source, topic_filter
from robot_relay.sources.take_loop import LATENCY_BUDGET_S
from robot_relay.wire import Catalog, RawMessage, TopicInfo, check_robot_name

log = logging.getLogger("swanky.relay")

POLL_S = 0.05
"""How often the main thread looks at a replay's source: it has ended when the bag has."""
LIVE_POLL_S = 0.5
"""How often it looks at a live source, which ends only when one of its threads failed: 20
wake-ups a second cost the idle relay 4 ms of CPU per second here (perf), a Pi's core more."""


@dataclass(frozen=True, slots=True)
class RelayOptions:
    """Everything ``swanky-relay`` was asked to do (cli.py reads it from the flags and the
    ``--config`` file)."""

    robot: str
    zenoh: ZenohOptions = field(default_factory=ZenohOptions)
    topics: tuple[str, ...] = DEFAULT_ALLOW
    """Globs of the topics to forward."""
    exclude: tuple[str, ...] = DEFAULT_DENY
    """Globs of the topics not to forward (a topic named exactly in ``topics`` goes anyway)."""
    policies: PolicyTable = field(default_factory=PolicyTable)
    bag: Path | None = None
    """Replay this bag instead of reading the live ROS graph."""
    rate: float = 1.0
    loop: bool = False
    wait_for_host: float | None = None
    """Replay: start once a host listens, giving up after this many seconds (None: never)."""
    hold: float = 0.0
    """Replay: afterwards keep serving latched topics, the catalog and files this long."""
    package_path: tuple[str, ...] = ()
    latency_budget: float = LATENCY_BUDGET_S
    """Live: the longest a message waits for the take loop's next turn, so that messages close
    together cost one wake-up (robot_relay/sources/take_loop.py); 0 forwards each at once."""


@dataclass
class RelayOutlet:
    """What sources push to: the file server learns each /robot_description's packages before
    the message is published, so a host that asks for a mesh right away is answered."""

    relay: Relay
    files: FileService

    def publish(self, raw: RawMessage) -> None:
        self.files.learn(raw)
        self.relay.publish(raw)

    def publish_run(
        self, info: TopicInfo, payloads: Sequence[bytes | memoryview], log_ns: Sequence[int]
    ) -> None:
        if is_robot_description(RawMessage(self.relay.robot, info.topic, info.msgtype, b"")):
            for data, stamp in zip(payloads, log_ns, strict=True):
                self.publish(RawMessage(self.relay.robot, info.topic, info.msgtype, data, log_ns=stamp))
            return
        self.relay.publish_run(info.topic, payloads, log_ns)

    def update_catalog(self, catalog: Catalog) -> None:
        self.relay.update_catalog(catalog)


def open_source(options: RelayOptions) -> Source:
    """The bag (opened) or the live graph the options name; RelayErrors say what is wrong."""
    accept = topic_filter(options.topics, options.exclude)
    if options.bag is not None:
        from robot_relay.sources.bag import BagSource

        bag: Source = BagSource(
            options.bag, options.robot, rate=options.rate, loop=options.loop, topics=accept
        ).open()
        return bag
    from robot_relay.sources.ros2 import RclpySource

    live: Source = RclpySource(options.robot, accept, options.latency_budget)
    return live


def run(options: RelayOptions, stop: threading.Event) -> int:
    """Relay until the source ends (a bag, then ``hold``) or ``stop`` is set; the exit code.
    RelayErrors are the caller's to print."""
    check_robot_name(options.robot)
    source = open_source(options)
    try:
        return relay_source(options, source, stop)
    finally:
        source.close()


def relay_source(options: RelayOptions, source: Source, stop: threading.Event) -> int:
    """:func:`run` with its source opened (tests give theirs); closes ``source`` too."""
    catalog = source.catalog()
    replay = options.bag is not None
    if replay and not catalog.topics:
        log.error("bag %s has no topics matching %s", options.bag, " ".join(options.topics))
        return 1
    with ExitStack() as closing:  # closes in reverse: the source, files, relay, session
        session = open_session(options.zenoh)
        closing.callback(close_session, session)
        relay = Relay(session, catalog, options.policies, demand=source,
                      source_drops=source.drop_counts)
        closing.callback(relay.close)
        files = serve_files(session, options.robot, options.package_path)
        closing.callback(files.close)
        # First to close: nothing is published while the relay undeclares.
        closing.callback(source.close)
        if replay:
            log.info("robot %s: %d topics from %s", options.robot, len(catalog.topics), options.bag)
            if not relay.wait_for_host(options.wait_for_host, stop):
                if stop.is_set():
                    log.info("robot %s: stopped before a host subscribed; nothing replayed",
                             options.robot)
                    return 0
                log.error("no host subscribed within %.1f s; nothing replayed", options.wait_for_host)
                return 1
        source.start(RelayOutlet(relay, files))
        poll = POLL_S if replay else LIVE_POLL_S
        while not stop.wait(poll) and not source.ended():
            pass
        if replay and stop.is_set():
            log.info("robot %s: replay stopped, %d messages sent", options.robot, relay.published)
        elif replay:
            log.info("robot %s: replay finished, %d messages sent", options.robot, relay.published)
            if options.hold > 0:
                log.info("robot %s: serving latched topics and files for %s s", options.robot,
                         options.hold)
                stop.wait(None if math.isinf(options.hold) else options.hold)
    if not replay:
        log.info("robot %s: stopped, %d messages sent", options.robot, relay.published)
    return 0
