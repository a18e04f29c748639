"""Sources -> Zenoh publishers, per schemas/wire.md. The relay never decodes a message.

Latched topics go through a zenoh-ext AdvancedPublisher with a cache, so a host that starts
late (or reconnects) still gets /tf_static, /robot_description and /map. Everything else uses a
plain publisher.

Demand: each plain publisher's matching listener tells the source (``on_demand(topic, wanted)``)
when the first host starts and the last one stops listening, so the rclpy source holds a ROS
subscription only while someone listens. Latched topics are always wanted: their cache must be
warm before a late host asks.

Clock: every wall-clock time the relay sends (a message's receive time, its stats report's time,
its answers to clock queries) comes from one function, ``clock`` (``time.time_ns`` unless a test
gives another), so a host that measures the relay's clock over the clock query (schemas/wire.md,
Clock) measures the clock of its receive times, and a test can shift it.

Policy (robot_relay.policy) sets each publisher's Zenoh priority and congestion control, the
optional lz4/zstd compression of its payloads and a keep-latest rate cap. A capped message that
arrives inside its period waits in the topic's limiter and one flusher thread sends it when the
period ends. Checking only when the next message arrives would hold the last message of a burst
until the topic speaks again, which may be never (a robot that stops stops publishing its pose);
one thread per relay instead of a timer per message keeps it to one wake-up per waiting message.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from typing import Any, Protocol

import zenoh
from zenoh import ext

from robot_relay.errors import ConfigError, RelayError
from robot_relay.policy import Policy, PolicyTable, RateLimiter
from robot_relay.session import shared_memory_pool
from robot_relay.stats import RelayStatsPublisher
from robot_relay.wire import (
    BUNDLE_ENTRY_SIZE,
    COMPRESSION_FLAGS,
    COMPRESSION_PACKAGES,
    FLAG_BUNDLE,
    Catalog,
    ClockReading,
    RawMessage,
    TopicInfo,
    alive_key,
    catalog_key,
    cdr_encoding,
    check_robot_name,
    clock_key,
    compressor,
    data_key,
    pack_attachment,
    pack_bundle,
)

log = logging.getLogger("swanky.relay")

_CONGESTION = {"drop": zenoh.CongestionControl.DROP, "block": zenoh.CongestionControl.BLOCK}
STOP_POLL_S = 0.05
"""How often :meth:`Relay.wait_for_host` looks at its stop event."""


class DemandListener(Protocol):
    """A source that subscribes to a ROS topic only while a host listens to it."""

    def on_demand(self, topic: str, wanted: bool) -> None: ...


def _compressor(policy: Policy, topic: str) -> Callable[[bytes], bytes] | None:
    if policy.compression == "none":
        return None
    try:
        return compressor(policy.compression)
    except ImportError as err:
        package = COMPRESSION_PACKAGES[policy.compression]
        msg = (
            f"{topic}: compression {policy.compression!r} needs the Python package {package!r}, "
            "which is not installed: pip install 'swanky[compression]' (or set compression: none)"
        )
        raise ConfigError(msg) from err


# A bundle of a topic that drops under congestion stays under Zenoh's default 64 KiB batch, so
# it is never fragmented: Zenoh may drop a fragmented message whole when its fragments wait
# (max_wait_before_drop_fragments, 50 ms: a 1 MB one over a slow link, eclipse-zenoh/zenoh#2258).
# A blocking topic's may be larger: the host converts each bundle (with what waits behind it) as
# one run, and a run's conversion costs Rerun calls, not its length (benchmarks/live_capacity.py's
# unpaced replay: the host's converting thread 0.23 s of CPU instead of 0.28; 1.7x the messages
# per second when the Imu there, which drops, was allowed 1 MB bundles too).
# Larger messages go alone (bundling saves a sample's overhead, which a large payload dwarfs).
MAX_BUNDLE_BYTES = 60_000
MAX_BLOCKING_BUNDLE_BYTES = 1_000_000
MAX_BUNDLE_MESSAGES = 4096


def bundle_bounds(
    payloads: Sequence[bytes | memoryview], max_bytes: int = MAX_BUNDLE_BYTES
) -> Iterator[int]:
    """Where the bundles of a run end: each at most MAX_BUNDLE_MESSAGES messages and
    ``max_bytes`` of payload, a larger payload on its own; in the run's order."""
    size = count = 0
    for index, payload in enumerate(payloads):
        length = len(payload) + BUNDLE_ENTRY_SIZE
        if count and (size + length > max_bytes or count == MAX_BUNDLE_MESSAGES):
            yield index
            size = count = 0
        size += length
        count += 1
    if count:
        yield len(payloads)


class _TopicPublisher:
    def __init__(
        self, session: zenoh.Session, robot: str, info: TopicInfo, policy: Policy,
        on_sent: Callable[[int, int], None],
    ) -> None:
        self.robot = robot
        self.info = info
        self.policy = policy
        self.key = data_key(robot, info.topic)
        self.sequence = 0
        self._on_sent = on_sent
        # Held while sending and while undeclaring: the take loop may still hold this publisher
        # when a catalog refresh undeclares it, and zenoh's Python publisher raises "Already
        # borrowed" if put and undeclare overlap ("Undeclared publisher" if put comes after).
        self._lock = threading.Lock()
        self._undeclared = False
        self._compress = _compressor(policy, info.topic)
        self._flag = COMPRESSION_FLAGS.get(policy.compression, 0)
        self._bundle_bytes = MAX_BUNDLE_BYTES if policy.congestion == "drop" else MAX_BLOCKING_BUNDLE_BYTES
        self.limiter: RateLimiter[tuple[RawMessage, int]] | None = (
            RateLimiter(policy.max_rate) if policy.max_rate else None
        )
        self._listener: Any = None
        # Not for latched topics: their cached samples would hold the pool's buffers.
        self._shared_memory = None if info.latched else shared_memory_pool(session)
        options: dict[str, Any] = {
            "encoding": zenoh.Encoding(cdr_encoding(info.msgtype)),
            "priority": getattr(zenoh.Priority, policy.priority.upper()),
            "congestion_control": _CONGESTION[policy.congestion],
            # Not express: zenoh batches what queues up while its link is busy. Express (one
            # write per message) cost 27-32 us of CPU per 3 KB message at full rate instead of
            # 3-4, and gained no latency at 200 Hz 3 KB or 30 Hz 1 MB (p50 0.3 ms and 1.8-2.0
            # ms either way on loopback; measured beside benchmarks/relay_throughput.py).
        }
        self.publisher: Any
        if info.latched:
            # Miss detection makes its samples carry (publisher id, sequence number), which the
            # host's AdvancedSubscriber orders per publisher, as it does the plain ones (_put).
            self.publisher = ext.declare_advanced_publisher(
                session, self.key, cache=ext.CacheConfig(max(info.qos.depth, 1)),
                publisher_detection=True,
                sample_miss_detection=ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=None),
                **options,
            )
        else:
            self.publisher = session.declare_publisher(self.key, **options)
        # The source info of each plain sample (_put); read once, as Zenoh makes it anew per read.
        self._publisher_id = None if info.latched else self.publisher.id

    @property
    def matching(self) -> bool:
        """Whether some host listens; a cached latched topic is always worth publishing."""
        if self.info.latched:
            return True
        status = self.publisher.matching_status
        # zenoh-python returns a MatchingStatus object (its stub says bool).
        return bool(getattr(status, "matching", status))

    def watch_demand(self, callback: Callable[[bool], None]) -> None:
        """``callback(listening)`` now and whenever that changes (plain publishers only)."""
        self._listener = self.publisher.declare_matching_listener(
            lambda status: callback(bool(status.matching))
        )
        # The listener reports changes only: a host that was already there counts too.
        callback(self.matching)

    def offer(self, raw: RawMessage, receive_ns: int, now: float | None = None) -> float | None:
        """Send ``raw`` or let it wait for its rate-cap period (``now``: time.monotonic(), read
        here if not given); returns when to flush, if due."""
        with self._lock:
            if self.limiter is None:
                self._put(raw, receive_ns)
                return None
            ready = self.limiter.offer((raw, receive_ns), time.monotonic() if now is None else now)
            if ready is not None:
                self._put(*ready)
            return self.limiter.due_at

    def flush(self, now: float, force: bool = False) -> float | None:
        """Send the waiting message if its period has ended (or ``force``); the next due time."""
        with self._lock:
            if self.limiter is None:
                return None
            item = self.limiter.take_any() if force else self.limiter.take_due(now)
            if item is not None:
                self._put(*item)
            return self.limiter.due_at

    def _put(self, raw: RawMessage, receive_ns: int) -> None:
        if self._undeclared:  # the topic left the catalog while this message was on its way
            return
        payload, flags = bytes(raw.data), 0
        if self._compress is not None:
            packed = self._compress(payload)
            # Per sample, so incompressible payloads (JPEG, noise) go as they are.
            if len(packed) < len(payload):
                payload, flags = packed, self._flag
        attachment = pack_attachment(self.sequence, receive_ns, raw.log_ns or 0, flags)
        # Plain samples carry the source info an AdvancedPublisher's would. Without it the
        # host's AdvancedSubscriber orders every sample of this session by timestamp and drops
        # any older than the last it delivered, i.e. every sample a higher-priority topic
        # overtook (a JointState sent just before a TF).
        if self._publisher_id is None:  # latched: AdvancedPublisher.put sets its own
            self.publisher.put(payload, attachment=attachment)
        else:
            source_info = zenoh.SourceInfo(self._publisher_id, self.sequence)
            shared = None if self._shared_memory is None else self._shared_memory.copy(payload)
            self.publisher.put(payload if shared is None else shared,
                               attachment=attachment, source_info=source_info)
        self.sequence = (self.sequence + 1) & 0xFFFFFFFF
        self._on_sent(1, len(payload))

    @property
    def bundles(self) -> bool:
        """Whether a run of this topic goes as bundles: not when latched (the cache keeps
        ``depth`` samples, each must be one message) nor rate-capped (one message per period)."""
        return not self.info.latched and self.limiter is None

    def offer_run(
        self, payloads: Sequence[bytes | memoryview], log_ns: Sequence[int], receive_ns: int,
        now: float,
    ) -> float | None:
        """Send a run of messages, as bundles where the topic allows (:attr:`bundles`), each
        message alone otherwise; returns when to flush, as :meth:`offer`."""
        if not self.bundles:
            due = None
            for data, stamp in zip(payloads, log_ns, strict=True):
                raw = RawMessage(self.robot, self.info.topic, self.info.msgtype, data, log_ns=stamp)
                due = self.offer(raw, receive_ns, now)
            return due
        with self._lock:
            begin = 0
            for end in bundle_bounds(payloads, self._bundle_bytes):
                if end - begin == 1:
                    raw = RawMessage(self.robot, self.info.topic, self.info.msgtype,
                                     payloads[begin], log_ns=log_ns[begin])
                    self._put(raw, receive_ns)
                else:
                    self._put_bundle(payloads[begin:end], log_ns[begin:end], receive_ns)
                begin = end
        return None

    def _put_bundle(
        self, payloads: Sequence[bytes | memoryview], log_ns: Sequence[int], receive_ns: int
    ) -> None:
        if self._undeclared:
            return
        payload, flags = pack_bundle(payloads, log_ns), FLAG_BUNDLE
        if self._compress is not None:
            packed = self._compress(payload)
            if len(packed) < len(payload):
                payload, flags = packed, flags | self._flag
        attachment = pack_attachment(self.sequence, receive_ns, 0, flags)
        assert self._publisher_id is not None  # a latched topic's messages go alone (bundles)
        source_info = zenoh.SourceInfo(self._publisher_id, self.sequence)
        self.publisher.put(payload, attachment=attachment, source_info=source_info)
        self.sequence = (self.sequence + len(payloads)) & 0xFFFFFFFF
        self._on_sent(len(payloads), len(payload))

    def undeclare(self) -> None:
        self.flush(time.monotonic(), force=True)  # the newest message is never lost
        if self._listener is not None:
            self._listener.undeclare()
        with self._lock:
            self._undeclared = True
            self.publisher.undeclare()


class _Flusher:
    """One thread sending rate-capped messages when their period ends."""

    def __init__(self) -> None:
        self._due: dict[_TopicPublisher, float] = {}
        self._wake = threading.Condition()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="relay-flush", daemon=True)
        self._thread.start()

    def schedule(self, publisher: _TopicPublisher, at: float | None) -> None:
        if at is None:
            return
        with self._wake:
            if at < self._due.get(publisher, float("inf")):
                self._due[publisher] = at
                self._wake.notify()

    def _run(self) -> None:
        while True:
            with self._wake:
                ready: list[_TopicPublisher] = []
                while not self._closed and not ready:
                    now = time.monotonic()
                    ready = [p for p, at in self._due.items() if at <= now]
                    if not ready:
                        self._wake.wait(min(self._due.values()) - now if self._due else None)
                if self._closed:
                    return
                for publisher in ready:
                    del self._due[publisher]
            for publisher in ready:
                self.schedule(publisher, publisher.flush(time.monotonic()))

    def close(self) -> None:
        with self._wake:
            self._closed = True
            self._wake.notify()
        self._thread.join(timeout=5.0)


class Relay:
    """Publishes RawMessages of one robot; answers its catalog and clock queries; holds its
    liveliness token.

    ``demand`` (a live source) hears when a host starts or stops listening to each topic;
    ``source_drops`` gives the messages per topic the source saw lost before the relay, for
    the stats report; ``clock`` is the relay's wall clock (ns since the Unix epoch).
    """

    def __init__(
        self, session: zenoh.Session, catalog: Catalog, policies: PolicyTable | None = None,
        demand: DemandListener | None = None,
        source_drops: Callable[[], Mapping[str, int]] | None = None,
        *,
        clock: Callable[[], int] = time.time_ns,
    ) -> None:
        self.session = session
        self.clock = clock
        self.robot = check_robot_name(catalog.robot)
        self.catalog = catalog
        self.policies = policies or PolicyTable()
        self._demand = demand
        self._catalog_json = catalog.to_json()
        self._publishers: dict[str, _TopicPublisher] = {}
        self._wanted: dict[str, bool] = {}
        self._failed: dict[str, TopicInfo] = {}
        # Reentrant: zenoh may report a matching status on the declaring thread.
        self._lock = threading.RLock()
        # Notified when a host starts listening to a topic (wait_for_host).
        self._demand_changed = threading.Condition(self._lock)
        self.published = 0
        self.published_bytes = 0
        self._flusher = _Flusher()
        for info in catalog.topics:
            self._add(info)
        self._queryable = session.declare_queryable(catalog_key(self.robot), self._answer_catalog)
        self._clock_queryable = session.declare_queryable(clock_key(self.robot), self._answer_clock)
        self._token = session.liveliness().declare_token(alive_key(self.robot))
        self._stats = RelayStatsPublisher(
            session, self.robot, lambda: (self.published, self.published_bytes), source_drops,
            clock=clock,
        )

    def _count_sent(self, messages: int, size: int) -> None:
        with self._lock:
            self.published += messages
            self.published_bytes += size

    def _add(self, info: TopicInfo) -> None:
        policy = self.policies.resolve(info.topic, info.msgtype, info.qos)
        publisher = _TopicPublisher(self.session, self.robot, info, policy, self._count_sent)
        with self._lock:
            self._publishers[info.topic] = publisher
        log.debug("%s: %s", info.topic, policy)
        if info.latched:
            self._set_wanted(publisher, True)
        else:
            publisher.watch_demand(lambda listening: self._set_wanted(publisher, listening))

    def _set_wanted(self, publisher: _TopicPublisher, wanted: bool) -> None:
        topic = publisher.info.topic
        with self._lock:
            if self._publishers.get(topic) is not publisher or self._wanted.get(topic, False) == wanted:
                return
            self._wanted[topic] = wanted
            self._demand_changed.notify_all()
        if self._demand is not None:
            self._demand.on_demand(topic, wanted)

    def _answer_catalog(self, query: zenoh.Query) -> None:
        with self._lock:
            payload = self._catalog_json
        query.reply(catalog_key(self.robot), payload, encoding=zenoh.Encoding.APPLICATION_JSON)

    def _answer_clock(self, query: zenoh.Query) -> None:
        received_ns = self.clock()
        # The reply's time is read last: the host takes what happened in between as the relay's.
        reading = ClockReading(received_ns, self.clock())
        query.reply(clock_key(self.robot), reading.pack(),
                    encoding=zenoh.Encoding.APPLICATION_OCTET_STREAM)

    def _still_fits(self, publisher: _TopicPublisher, info: TopicInfo | None) -> bool:
        """Whether ``publisher`` can go on publishing ``info``: same type, latched or not, same
        policy. A depth or (latched) reliability change keeps it, and with it a latched topic's
        cache: a new publisher would send the cached history to the hosts once more."""
        return info is not None and (info.msgtype, info.latched) == (
            publisher.info.msgtype, publisher.info.latched
        ) and self.policies.resolve(info.topic, info.msgtype, info.qos) == publisher.policy

    def update_catalog(self, catalog: Catalog) -> None:
        """The live graph changed: publish new topics, drop vanished ones, re-declare topics
        whose type, durability or policy changed, and answer the new catalog.

        A topic that cannot be published (its compression is not installed) is reported once
        and left out; the others go on.
        """
        infos = {info.topic: info for info in catalog.topics}
        with self._lock:
            self.catalog = catalog
            self._catalog_json = catalog.to_json()
            stale = []
            for topic, publisher in self._publishers.items():
                if self._still_fits(publisher, infos.get(topic)):
                    publisher.info = infos[topic]
                else:
                    stale.append(publisher)
            for publisher in stale:
                del self._publishers[publisher.info.topic]
            unwanted = [p.info.topic for p in stale if self._wanted.pop(p.info.topic, False)]
        # Outside the lock: undeclaring waits for running matching callbacks, which take it.
        for publisher in stale:
            publisher.undeclare()
        if self._demand is not None:
            for topic in unwanted:
                self._demand.on_demand(topic, False)
        for info in catalog.topics:
            if info.topic in self._publishers or self._failed.get(info.topic) == info:
                continue
            try:
                self._add(info)
            except RelayError as err:
                self._failed[info.topic] = info
                log.error("%s is not forwarded: %s", info.topic, err)

    def wait_for_host(self, timeout: float | None, stop: threading.Event | None = None) -> bool:
        """Block until a host subscribes to any non-latched topic (True), or ``timeout`` passes
        or ``stop`` is set (False). Woken by the publishers' matching listeners, so a replay
        starts as soon as a host listens, and every STOP_POLL_S to look at ``stop``: a
        condition cannot also wait on an event, and a stop signal must not wait for a host."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._demand_changed:
            while not self._host_listening():
                left = STOP_POLL_S if deadline is None else deadline - time.monotonic()
                if left <= 0 or (stop is not None and stop.is_set()):
                    return False
                self._demand_changed.wait(min(left, STOP_POLL_S))
            return True

    def _host_listening(self) -> bool:
        plain = [p.info.topic for p in self._publishers.values() if not p.info.latched]
        return not plain or any(self._wanted.get(topic, False) for topic in plain)

    def publish(self, raw: RawMessage) -> None:
        publisher = self._publishers.get(raw.topic)
        if publisher is None:  # the topic vanished from the live graph meanwhile
            return
        now = self.clock()
        # A live source's receive time (DDS's, on the system clock; its take loop may have held
        # the message for its latency budget) moved onto this relay's clock.
        receive_ns = now if raw.receive_ns is None else now - max(0, time.time_ns() - raw.receive_ns)
        due = publisher.offer(raw, receive_ns)
        if due is not None:
            self._flusher.schedule(publisher, due)

    def publish_run(self, topic: str, payloads: Sequence[bytes | memoryview], log_ns: Sequence[int]) -> None:
        """Publish a run of ``topic``'s messages that are all due now (a replay that is behind,
        or not paced): bundled into fewer samples where the topic allows, each message's wire
        sequence number and source time kept (schemas/wire.md, Bundles)."""
        publisher = self._publishers.get(topic)
        if publisher is None:
            return
        due = publisher.offer_run(payloads, log_ns, self.clock(), time.monotonic())
        self._flusher.schedule(publisher, due)

    def publish_all(self, messages: Iterable[RawMessage], stop: threading.Event) -> None:
        for raw in messages:
            if stop.is_set():
                return
            self.publish(raw)

    def close(self) -> None:
        self._stats.close()
        self._flusher.close()
        for publisher in self._publishers.values():
            publisher.undeclare()
        self._queryable.undeclare()
        self._clock_queryable.undeclare()
        self._token.undeclare()
