"""Swanky wire samples (schemas/wire.md) -> RawMessages, with definitions from each robot's
catalog.

A robot's samples wait (bounded) until its catalog has arrived: a ROS 1 bag replayed by a relay
carries CDR laid out after ROS 1 definitions (``Header.seq``), which the bundled ROS 2 types
would misread. The robots' data samples go through a Zenoh channel to a thread of the input's
that only parses and enqueues them (per robot, see queues.py); decoding happens on the host's
threads. Not a callback: Zenoh runs callbacks on its receiving threads, and a callback waits for
Python's GIL, which a busy host's threads hold, so Zenoh stopped reading the robots' links while
it waited and the robots' reliable publishers blocked: ``swanky-host --demo --robots 25
--no-slam --duration 30`` got 619 of each robot's 900 IMU messages by callback, 765 through the
channel (887 with ``--workers 2``, 557 by callback).

A relay's topic is of the type its catalog announces (the relay publishes nothing else): a sample
claiming another type waits for the relay's catalog as it is now (a live robot's node may have
retyped the topic) and is refused, counted and warned about if that does not announce its type
either, so a sender of garbage on a robot's keys cannot change how its topics are converted.

Receive times are the relay's clock; each robot's is measured against the PC's (clocks.py) and
its samples are delivered with their receive times on the PC's clock. A joining relay's samples
wait for that measurement too, bounded, as they wait for its catalog.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable

import numpy as np
import zenoh
from zenoh import ext

from host_bridge.core.columns import PackedPayloads
from host_bridge.core.shards import Shard
from host_bridge.errors import ConfigError, TypeMismatchError
from host_bridge.inputs.base import InputItem, InputProblem, MessageRun, RobotEvent
from host_bridge.inputs.clocks import RelayClocks
from host_bridge.inputs.queues import RobotQueues
from robot_relay.errors import WireError
from robot_relay.wire import (
    BUNDLE_ENTRY_SIZE,
    BUNDLE_HEAD_SIZE,
    Attachment,
    Catalog,
    RawMessage,
    TopicInfo,
    alive_selector,
    bundle_count,
    catalog_key,
    data_selector,
    decompress,
    parse_cdr_encoding,
    parse_data_key,
    parse_robot_key,
)

log = logging.getLogger("swanky.host")

CATALOG_TIMEOUT_S = 5.0
SAMPLE_CHANNEL_CAPACITY = 10_000
"""Samples received and not yet taken by the input's thread; a full channel holds Zenoh's
receiving back (what a slow callback did), so the relays' congestion control sees a host that is
behind."""
SAMPLES_PER_TURN = 256
"""A worker takes this many samples of one robot's channel at most before the next robot's."""
SAMPLES_PAUSE_S = (0.001, 0.016)
"""How long a worker's samples thread pauses when no channel holds a sample: the first pause,
doubled while none comes, up to the last."""
SAMPLES_JOIN_S = 10.0
"""How long closing waits for the samples received before to be taken."""
UNANNOUNCED_WAIT_S = 1.0
"""Samples of a robot no relay has announced yet (its liveliness token may come after its first
samples, or the samples are garbage) wait this long before its catalog is asked for: asked at
once, a query that no relay answers yet ends at once and its samples would go on with the
bundled types, while a relay starting meanwhile has the definitions."""
CATALOG_RETRY_S = 2.0
MAX_PENDING_PER_ROBOT = 2000


def check_robot_pattern(pattern: str) -> str:
    """``--robots``: one Zenoh key-expression chunk: a robot name (``tb3``), ``*`` (all), or a
    name with ``$*`` inside (``east-$*`` matches ``east-1``, ``east-tb3``). ``tb*`` and lists
    are not key expressions; a fleet split over hosts names its robots by group instead."""
    try:
        if "/" in pattern or not pattern:
            raise ValueError("a robot pattern is one non-empty chunk, without '/'")
        zenoh.KeyExpr(pattern)
    except Exception as err:
        msg = (
            f"--robots {pattern!r} is not a Zenoh key-expression chunk ({err}); use a name, "
            "'*', or '$*' inside a name (e.g. 'tb$*')"
        )
        raise ConfigError(msg) from err
    return pattern


def robot_matches(robot: str, pattern: str) -> bool:
    return bool(zenoh.KeyExpr(robot).intersects(zenoh.KeyExpr(pattern)))


def fetch_catalog(session: zenoh.Session, robot: str, timeout: float) -> Catalog | None:
    """``robot``'s catalog from its relay; None when no relay answered within ``timeout``
    seconds. A reply that is no catalog raises WireError naming the key."""
    key = catalog_key(robot)
    for reply in session.get(key, timeout=timeout):
        if reply.ok is not None:
            return Catalog.from_json(reply.ok.payload.to_bytes(), key)
    return None


def bundle_run(
    data: bytes, attachment: Attachment, key: str, *, robot: str, topic: str, msgtype: str
) -> MessageRun:
    """The messages of a relay's bundle (schemas/wire.md, Bundles) as a run, its payloads
    slices of ``data``; WireError naming ``key`` when the bundle does not hold together."""
    count = bundle_count(data, key)
    log_ns = np.frombuffer(data, "<i8", count, BUNDLE_HEAD_SIZE).astype(np.int64)
    sizes = np.frombuffer(data, "<u4", count, BUNDLE_HEAD_SIZE + 8 * count).astype(np.intp)
    first = BUNDLE_HEAD_SIZE + BUNDLE_ENTRY_SIZE * count
    ends = first + np.cumsum(sizes)
    if ends[-1] != len(data):
        msg = (
            f"bundle on {key!r}: its {count} payload sizes add up to {int(sizes.sum())} bytes "
            f"but {len(data) - first} follow them: a corrupt or cut-short sample"
        )
        raise WireError(msg)
    payloads = PackedPayloads((data,), np.zeros(count, np.intp), ends - sizes, ends)
    return MessageRun(
        robot, topic, msgtype, None, payloads,
        # 0: unknown, as a single message's source time; a run's times are all known or none.
        log_ns=log_ns if log_ns.all() else None,
        receive_ns=np.full(count, attachment.receive_ns, np.int64),
        sequence=(attachment.sequence + np.arange(count, dtype=np.int64)) & 0xFFFFFFFF,
    )


def _delivered(
    item: RawMessage | MessageRun, info: TopicInfo | None, offset_ns: int
) -> RawMessage | MessageRun:
    """``item`` with the definition its relay's catalog gives (``info``), if any, and its
    receive times on the PC's clock (``offset_ns``: the relay's clock minus the PC's); a
    RawMessage built directly, as this runs per sample on Zenoh's thread (2 us against
    dataclasses.replace's 3)."""
    definition = item.definition if info is None else info.definition
    if isinstance(item, MessageRun):
        receive_ns = None if item.receive_ns is None else item.receive_ns - offset_ns
        return dataclasses.replace(item, definition=definition, receive_ns=receive_ns)
    return RawMessage(
        robot=item.robot, topic=item.topic, msgtype=item.msgtype, data=item.data,
        definition=definition,
        receive_ns=None if item.receive_ns is None else item.receive_ns - offset_ns,
        log_ns=item.log_ns, sequence=item.sequence,
    )


class _RobotCatalog:
    """What the input knows of one robot's catalog: its topics, the samples waiting for it, the
    fetch under way; used under its ``lock``. A lock per robot, so one robot's catalog coming in
    (its waiting samples, up to :data:`MAX_PENDING_PER_ROBOT`, queued under its lock) holds up
    no other robot's samples. (It came with a thread per robot's channel, 25 of which queued on
    one lock for all: py-spy, 86 % of their samples waiting there; one thread takes them now.)"""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.topics: dict[str, TopicInfo] | None = None
        # Samples waiting for the robot's catalog: its first, or a newer one when a sample's
        # type is not the one the catalog in hand announces.
        self.pending: list[RawMessage | MessageRun] = []
        self.fetching = False
        self.last_fetch = 0.0
        # Relays that joined under this robot's name: a catalog asked for before the last one
        # joined is not its catalog (samples on its keys, garbage, had the host ask earlier).
        self.joins = 0
        self.dropped = 0
        """Samples that did not fit in ``pending``."""


class ZenohInput:
    """Subscribes to the data of the robots matched by ``robots`` (see
    :func:`check_robot_pattern`); a router then forwards only those robots' samples here.

    One worker of several (``shard``, core/shards.py) subscribes to each of its robots' data
    apart, once the robot's relay announces itself: a subscription to them all would bring every
    robot's samples into every worker, which is what they are there to share."""

    def __init__(
        self, session: zenoh.Session, robots: str = "*", queues: RobotQueues | None = None,
        shard: Shard | None = None,
    ) -> None:
        check_robot_pattern(robots)
        self.session = session
        self.shard = shard
        self.queues = queues or RobotQueues()
        self.refused: dict[tuple[str, str], int] = {}
        """Messages per (robot, topic) refused because they claimed another type than the
        robot's catalog announces for the topic."""
        self._robots: dict[str, _RobotCatalog] = {}
        self._lock = threading.Lock()
        """Guards the robots known (not their catalogs), the subscribers and the closing."""
        self._closed = threading.Event()
        self.clocks = RelayClocks(session, self._put)
        self._takers: list[threading.Thread] = []
        self._channels: list[zenoh.handlers.Handler[zenoh.Sample]] = []
        """A shard's robots' channels not yet undeclared and emptied."""
        self._subscribed: set[str] = set()
        """A shard's robots subscribed to."""
        if shard is None:
            self._subscribers = [self._subscribe(robots)]
            self._start_taker(self._take_samples, self._subscribers[0].handler, name=robots)
        else:
            self._subscribers = []
            self._start_taker(self._take_channels, name=shard.name)
        self._liveliness = session.liveliness().declare_subscriber(
            alive_selector(robots), self._on_alive, history=True
        )

    @property
    def dropped(self) -> int:
        """Samples dropped while they waited for their robot's catalog."""
        return sum(state.dropped for state in list(self._robots.values()))

    def _state(self, robot: str) -> _RobotCatalog:
        state = self._robots.get(robot)
        if state is None:
            with self._lock:
                state = self._robots.setdefault(robot, _RobotCatalog())
        return state

    def _subscribe(self, robots: str) -> ext.AdvancedSubscriber[zenoh.handlers.Handler[zenoh.Sample]]:
        """The data of ``robots``, through a channel a thread of this input's takes them from."""
        return ext.declare_advanced_subscriber(
            self.session,
            data_selector(robots),
            zenoh.handlers.FifoChannel(SAMPLE_CHANNEL_CAPACITY),
            history=ext.HistoryConfig(detect_late_publishers=True),
        )

    def _start_taker(self, take: Callable[..., None], *args: object, name: str) -> None:
        taker = threading.Thread(target=take, args=args, name=f"samples-{name}", daemon=True)
        taker.start()
        self._takers.append(taker)

    def _take_samples(self, samples: zenoh.handlers.Handler[zenoh.Sample]) -> None:
        """Hand the subscriber's samples on until it is undeclared (those received before are
        handed on first)."""
        while True:
            try:
                # Without letting go of the GIL while samples wait; blocking when none does.
                sample = samples.try_recv() or samples.recv()
            except zenoh.ZError:  # undeclared, and every sample taken
                return
            self._hand_on(sample)

    def _take_channels(self) -> None:
        """A worker's robots' channels (a subscriber each), taken in turn on this one thread,
        which pauses when none holds a sample, until the input closes and each is emptied. A
        thread per robot, woken for each sample, cost a worker 0.19-0.20 of a core at 25 demo
        robots over two workers; one thread taking the 25 robots' single channel in one process
        less than 0.03."""
        pause_s = SAMPLES_PAUSE_S[0]
        while True:
            with self._lock:
                channels = list(self._channels)
                if self._closed.is_set() and not channels:
                    return
            if sum(self._take_waiting(channel) for channel in channels):
                pause_s = SAMPLES_PAUSE_S[0]
            else:
                time.sleep(pause_s)
                pause_s = min(2 * pause_s, SAMPLES_PAUSE_S[1])

    def _take_waiting(self, channel: zenoh.handlers.Handler[zenoh.Sample]) -> int:
        """Hand on the samples waiting in ``channel``, up to :data:`SAMPLES_PER_TURN`; how many.
        A channel undeclared and emptied is forgotten."""
        for taken in range(SAMPLES_PER_TURN):
            try:
                sample = channel.try_recv()
            except zenoh.ZError:
                with self._lock:
                    self._channels.remove(channel)
                return taken
            if sample is None:
                return taken
            self._hand_on(sample)
        return SAMPLES_PER_TURN

    def _hand_on(self, sample: zenoh.Sample) -> None:
        try:
            self._on_sample(sample)
        except Exception:  # a bug on one sample must not stop the robots' data
            log.exception("a sample on %s could not be taken", sample.key_expr)

    def _subscribe_robot(self, robot: str) -> None:
        try:
            subscriber = self._subscribe(robot)
        except zenoh.ZError as err:  # the session closing meanwhile
            if not self._closed.is_set():
                self._put(InputProblem(robot, data_selector(robot), err))
            return
        with self._lock:
            if self._closed.is_set():
                subscriber.undeclare()
            else:
                self._subscribers.append(subscriber)
                self._channels.append(subscriber.handler)

    # -- zenoh callbacks (zenoh's threads) -------------------------------------------------

    def _on_alive(self, sample: zenoh.Sample) -> None:
        robot = parse_robot_key(str(sample.key_expr))
        joined = sample.kind == zenoh.SampleKind.PUT
        if self.shard is not None:
            if not self.shard.owns(robot):
                return  # another worker's
            with self._lock:
                subscribe = joined and robot not in self._subscribed
                self._subscribed.add(robot)
            if subscribe:  # not from Zenoh's callback, which declaring would wait on
                threading.Thread(target=self._subscribe_robot, args=(robot,),
                                 name=f"subscribe-{robot}", daemon=True).start()
        self.queues.put(RobotEvent(robot, joined, "swanky relay"))
        if not joined:
            self.clocks.unfollow(robot)
        else:
            state = self._state(robot)
            with state.lock:
                # A restarted relay may bring other topics or definitions: its samples wait
                # for the new catalog. (Not on leaving: its last samples may still arrive.)
                state.topics = None
                state.joins += 1
            self._fetch_catalog(robot, follow_clock=True)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            robot, topic = parse_data_key(key)
        except WireError as err:
            self._put(InputProblem("?", key, err))
            return
        try:
            attachment_bytes = sample.attachment
            if attachment_bytes is None:
                msg = f"sample on {key!r} has no attachment: not sent by a swanky relay"
                raise WireError(msg)
            attachment = Attachment.unpack(attachment_bytes.to_bytes(), key)
            msgtype = parse_cdr_encoding(str(sample.encoding), key)
            payload = decompress(sample.payload.to_bytes(), attachment.flags, key)
        except WireError as err:
            self._put(InputProblem(robot, topic, err))
            return
        self.clocks.check_arrival(robot, attachment.receive_ns)
        item: RawMessage | MessageRun
        if attachment.bundle:
            try:
                item = bundle_run(payload, attachment, key, robot=robot, topic=topic, msgtype=msgtype)
            except WireError as err:
                self._put(InputProblem(robot, topic, err))
                return
        else:
            item = RawMessage(
                robot=robot,
                topic=topic,
                msgtype=msgtype,
                data=payload,
                receive_ns=attachment.receive_ns,
                log_ns=attachment.source_ns or None,
                sequence=attachment.sequence,
            )
        self._route(item)

    # -- routing -----------------------------------------------------------------------------

    def _route(self, raw: RawMessage | MessageRun) -> None:
        fetch_after: float | None = None
        state = self._state(raw.robot)
        with state.lock:
            if state.topics is None:
                self._hold(state, raw)
                if not state.fetching:
                    fetch_after = 0.0 if state.joins else UNANNOUNCED_WAIT_S
            else:
                info = state.topics.get(raw.topic)
                wait = state.last_fetch + CATALOG_RETRY_S - time.monotonic()
                if info is not None and info.msgtype != raw.msgtype:
                    # The relay may have retyped the topic (its catalog follows the robot's
                    # graph): the sample waits for the catalog the relay has now, asked for at
                    # most every CATALOG_RETRY_S.
                    self._hold(state, raw)
                    if not state.fetching:
                        fetch_after = max(0.0, wait)
                else:
                    # Under the lock, as the catalog's waiting samples are queued: in order.
                    self._deliver(raw, info)
                    if info is None and wait < 0:
                        fetch_after = 0.0
        if fetch_after is not None:
            self._fetch_catalog(raw.robot, fetch_after)

    def _hold(self, state: _RobotCatalog, raw: RawMessage | MessageRun) -> None:
        """Keep ``raw`` until its robot's catalog comes (its lock held); counted in ``dropped``
        past :data:`MAX_PENDING_PER_ROBOT`."""
        if len(state.pending) < MAX_PENDING_PER_ROBOT:
            state.pending.append(raw)
        else:
            state.dropped += 1

    def _deliver(self, raw: RawMessage | MessageRun, info: TopicInfo | None) -> None:
        """Queue ``raw`` with the definition its robot's catalog gives its topic (its lock held) and
        its receive time on the PC's clock; a topic the catalog leaves out is decoded with the
        bundled types. The catalog's type is
        what the topic is: a sample claiming another type is refused, counted in ``refused``,
        and warned about (once per topic), so it cannot change how the topic's real messages
        are converted."""
        if info is None or info.msgtype == raw.msgtype:
            # A bundle's messages share the relay's receive time (the bundle's).
            receive_ns = raw.receive_ns[0] if isinstance(raw, MessageRun) and raw.receive_ns is not None \
                and len(raw.receive_ns) else raw.receive_ns
            offset = 0 if receive_ns is None else self.clocks.correction_ns(raw.robot, int(receive_ns))
            self._put(_delivered(raw, info, offset), info is not None and info.latched)
        else:
            key = (raw.robot, raw.topic)
            refused = self.refused.get(key, 0)
            self.refused[key] = refused + (len(raw) if isinstance(raw, MessageRun) else 1)
            if not refused:
                self._put(InputProblem(raw.robot, raw.topic, TypeMismatchError(
                    f"{raw.topic}: a sample claims type {raw.msgtype} but robot {raw.robot}'s "
                    f"relay announces {info.msgtype} for this topic ({catalog_key(raw.robot)}); "
                    "refused")))

    def _put(self, item: InputItem, latched: bool = False) -> None:
        self.queues.put(item, latched)

    def _fetch_catalog(self, robot: str, after: float = 0.0, *, follow_clock: bool = False) -> None:
        """Ask ``robot``'s relay for its catalog in ``after`` seconds, unless a fetch is under
        way; ``follow_clock`` (its relay joined): then measure its clock anew."""
        state = self._state(robot)
        with state.lock:
            fetching = state.fetching
            state.fetching = True
            if not fetching:
                state.last_fetch = time.monotonic() + after
        if fetching:
            if follow_clock:
                self.clocks.follow(robot)
            return
        threading.Thread(
            target=self._catalog_worker, args=(robot, after, follow_clock), name=f"catalog-{robot}",
            daemon=True,
        ).start()

    def _catalog_worker(self, robot: str, after: float, follow_clock: bool = False) -> None:
        if self._closed.wait(after):
            return
        state = self._state(robot)
        with state.lock:
            joins = state.joins
        key = catalog_key(robot)
        catalog: Catalog | None = None
        error: Exception | None = None
        try:
            catalog = fetch_catalog(self.session, robot, CATALOG_TIMEOUT_S)
        except WireError as err:
            error = err
        except Exception as err:  # session closed while asking
            if self._closed.is_set():
                return
            error = err
        if catalog is None and error is None:
            error = WireError(
                f"robot {robot} did not answer its catalog ({key}) within {CATALOG_TIMEOUT_S} s; "
                "decoding its topics with the bundled ROS 2 Humble types"
            )
        if follow_clock:
            # After the catalog's query, not beside it: a relay that has just joined answered
            # its catalog late (past CATALOG_TIMEOUT_S) in 2 of 5 runs when the clock's burst of
            # queries went out at the same time, in none of 4 without it.
            self.clocks.follow(robot)
        self.clocks.wait_ready(robot)
        with state.lock:
            state.fetching = False
            ask_again = state.joins != joins
            if not ask_again:
                if error is not None:
                    self._put(InputProblem(robot, key, error))
                known = dict(state.topics or {})
                if catalog is not None:
                    known.update({t.topic: t for t in catalog.topics})
                state.topics = known
                # Queued under the lock: a sample arriving meanwhile sees the catalog only after
                # them, and goes after them (else its sequence number came before older ones').
                for waiting in state.pending:
                    self._deliver(waiting, known.get(waiting.topic))
                state.pending = []
        if ask_again:
            self._fetch_catalog(robot)

    def close(self) -> None:
        with self._lock:
            self._closed.set()
            subscribers = list(self._subscribers)
        for subscriber in subscribers:
            subscriber.undeclare()
        for taker in list(self._takers):
            taker.join(SAMPLES_JOIN_S)
        self._liveliness.undeclare()
        self.clocks.close()
