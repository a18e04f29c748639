"""RawMessage runs -> decode -> convert -> sink, with the error policy and per-topic counters.

A bad message never stops the host: decoding and conversion errors are caught per message,
warned about once per (robot, topic, error kind), counted, and shown in Rerun under
``/_swanky/warnings``. ``strict`` (tests, ``--strict``) re-raises instead.

Everything converted for a robot is logged through :meth:`Dispatcher.log`, which also keeps the
robot's frames one tree and names its 3D view's target frame (see frames.py).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
import rerun as rr

from host_bridge.columns import read_columns
from host_bridge.config import HostConfig
from host_bridge.contract import (
    TIMELINE_LOG,
    TIMELINE_RECEIVE,
    TIMELINE_ROS,
    WARNINGS_PATH,
    ConvertContext,
    ConverterSpec,
    LogEntry,
    LogItem,
    RunContext,
)
from host_bridge.counters import TopicCounters, sequence_gap, sequence_gaps, summary_table
from host_bridge.decode import Decoder
from host_bridge.errors import ConfigError, HostError, PartialConvertError, TypeChangeError
from host_bridge.frames import RobotFrames
from host_bridge.inputs.base import (
    InputItem,
    InputProblem,
    MessageRun,
    RobotEvent,
    presence_items,
)
from host_bridge.registry import Registry, default_registry
from host_bridge.resources import ResourceResolver
from host_bridge.sink import Sink
from host_bridge.state import RobotState, TopicState
from robot_relay.wire import RawMessage

log = logging.getLogger("swanky.host")

# Sees every run before decoding (the MCAP recorder, the stats); must not raise on good data.
# Live robots dispatch from one thread each, so a tap must be thread-safe.
Tap = Callable[[Sequence[RawMessage]], None]
# Told of each enabled topic when its first message arrives and when its type changes: (robot,
# topic, type, entity path).
TopicListener = Callable[[str, str, str, str], None]


class Offload(Protocol):
    """Converts some topics' runs elsewhere, counting them in their counters (offload.py)."""

    def takes(self, raw: RawMessage) -> bool: ...
    def convert(self, run: Sequence[RawMessage], topic: TopicBinding, counters: TopicCounters) -> None: ...
    def close(self) -> None: ...


@dataclass(frozen=True, slots=True)
class TopicBinding:
    """A topic bound to one type of message (see ``Dispatcher._bind``): how its messages of that
    type are converted, from the host configuration (``config.TopicConfig``): where they are
    logged, their options' state, whether they are converted at all, and whether ros_time is
    their arrival time."""

    msgtype: str
    entity_path: str
    state: TopicState
    enabled: bool = True
    restamp: bool = False


MAX_TYPES_PER_TOPIC = 8
"""Types a topic's settings are kept for: a topic that switches back to a type it had (a sender
of garbage between a robot's real messages) finds its converters' state (a video decoder, a
trail) as it left it; beyond these, the least recently used type's is forgotten, so a stream of
made-up type names costs no memory."""


@dataclass(slots=True)
class _TopicTypes:
    """A topic's settings per type of message it came with."""

    current: TopicBinding
    """The type of its last message."""
    earlier: dict[str, TopicBinding] = field(default_factory=dict)
    """Its other types, least recently used first."""


@dataclass(frozen=True, slots=True)
class _RobotConversion:
    """What the host keeps per robot: the state its converters share, and its frame tree."""

    state: RobotState
    frames: RobotFrames
    # Held from observing logged frames to logging the placements they call for (see log).
    placing: threading.Lock = field(default_factory=threading.Lock)


Arrivals = tuple[npt.NDArray[np.int64] | None, npt.NDArray[np.int64] | None]


def run_arrivals(run: Sequence[RawMessage]) -> Arrivals | None:
    """The run's receive and log times, one array each (None: no message has that time); None
    when some messages have a time and others not, which columns cannot say."""
    if isinstance(run, MessageRun):
        return run.receive_ns, run.log_ns
    found = []
    for values in ([raw.receive_ns for raw in run], [raw.log_ns for raw in run]):
        missing = values.count(None)
        if 0 < missing < len(values):
            return None
        found.append(None if missing else np.array(values, dtype=np.int64))
    return found[0], found[1]


def message_times(msg: Any, raw: RawMessage, *, restamp: bool = False) -> dict[str, int]:
    """The message's timelines; ``restamp`` makes ros_time the receive (else log) time, for
    robots whose clock is off or whose stamps are zero."""
    times: dict[str, int] = {}
    header = getattr(msg, "header", None)
    stamp = getattr(header, "stamp", None)
    arrival = raw.receive_ns if raw.receive_ns is not None else raw.log_ns
    if restamp and arrival is not None:
        times[TIMELINE_ROS] = arrival
    elif stamp is not None:
        ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
        if ns:
            times[TIMELINE_ROS] = ns
    if raw.receive_ns is not None:
        times[TIMELINE_RECEIVE] = raw.receive_ns
    if raw.log_ns is not None:
        times[TIMELINE_LOG] = raw.log_ns
    return times


class Dispatcher:
    def __init__(
        self,
        sink: Sink,
        *,
        registry: Registry | None = None,
        decoder: Decoder | None = None,
        config: HostConfig | None = None,
        strict: bool = False,
        resolver: ResourceResolver | None = None,
        taps: Sequence[Tap] = (),
        on_new_topic: TopicListener | None = None,
    ) -> None:
        self.sink = sink
        self.taps = list(taps)
        self.on_new_topic = on_new_topic
        self.registry = registry or default_registry()
        self.decoder = decoder or Decoder()
        self.config = config or HostConfig.builtin(self.registry)
        self.strict = strict
        self.counters: dict[tuple[str, str], TopicCounters] = {}
        self._topics: dict[tuple[str, str], _TopicTypes] = {}
        # Taken when a topic's type changes: a robot's two threads may both carry the topic.
        self._retyping = threading.Lock()
        # Finds mesh files for every robot (each robot's own relay for what is missing here).
        self._resolver = resolver or ResourceResolver.from_env()
        self._robots: dict[str, _RobotConversion] = {}
        self._robots_lock = threading.Lock()
        self._warned: set[tuple[str, str, str]] = set()
        self._slow = _SlowWorker(self, self.registry.slow_converters())
        self.offload: Offload | None = None
        """Where heavy topics are converted when not here (offload.py's process)."""

    def _robot(self, robot: str) -> _RobotConversion:
        # The slow converters' thread logs for robots too.
        with self._robots_lock:
            found = self._robots.get(robot)
            if found is None:
                state = RobotState(resolver=self._resolver.for_robot(robot))
                found = self._robots[robot] = _RobotConversion(state, RobotFrames(robot))
            return found

    def robot_state(self, robot: str) -> RobotState:
        return self._robot(robot).state

    def frames(self, robot: str) -> RobotFrames:
        return self._robot(robot).frames

    def log(self, robot: str, entries: Sequence[LogEntry], times: Mapping[str, int]) -> None:
        """Log ``robot``'s entries, then what its frames need now (placements, target).

        A robot's small topics, its heavy ones (inputs/queues.py) and the slow converters log
        from threads of their own. A frame placed at the robot's root shares its static entity
        with the frame's real transform and must never be written after it: entries are observed
        before they are logged, and those that call for placements are logged with them under
        the robot's lock, so a transform observed later is also logged later. Other entries
        (nearly all) are logged outside it: a small topic does not wait for a cloud's log."""
        known = self._robot(robot)
        with known.placing:
            updates = known.frames.observe(entries, known.state)
            if updates:
                self.sink.log(entries, times)
                self.sink.log(updates, times)
                return
        self.sink.log(entries, times)

    def log_frames(
        self, robot: str, relations: Iterable[tuple[str, str]], frames: Iterable[str]
    ) -> None:
        """Note the frames that ``robot``'s entries logged elsewhere named (offload.py), and log
        the placements and target they call for."""
        known = self._robot(robot)
        with known.placing:
            updates = known.frames.note(relations, frames, known.state)
            if updates:
                self.sink.log(updates, {})

    def _topic(self, robot: str, name: str, msgtype: str) -> TopicBinding:
        """The settings ``robot``'s topic ``name`` converts a message of ``msgtype`` with."""
        found = self._topics.get((robot, name))
        if found is not None and found.current.msgtype == msgtype:
            return found.current
        return self._bind(robot, name, msgtype)

    def _bind(self, robot: str, name: str, msgtype: str) -> TopicBinding:
        """Bind a topic to ``msgtype``: its first message, or one of another type than its last
        (a node moved from Twist to TwistStamped; a sender of garbage). Settings belong to the
        type, so a message of one type never has a later one of another converted with its
        options or state (a LaserScan with a PointCloud2's). A change is warned about once per
        topic, naming both types, and counted in its warnings; the layout follows it."""
        key = (robot, name)
        created = None
        with self._retyping:
            found = self._topics.get(key)
            before = None if found is None else found.current
            if before is not None and before.msgtype == msgtype:
                return before
            topic = None if found is None else found.earlier.pop(msgtype, None)
            if topic is None:
                created = self.config.resolve(robot, name, msgtype)
                topic = TopicBinding(msgtype, created.entity_path, TopicState(created.options),
                                      created.enabled, created.restamp)
            if found is None:
                self._topics[key] = _TopicTypes(topic)
            else:
                found.earlier[found.current.msgtype] = found.current
                if len(found.earlier) >= MAX_TYPES_PER_TOPIC:
                    del found.earlier[next(iter(found.earlier))]
                found.current = topic
                counters = self.counters.get(key)
                if counters is not None:
                    counters.msgtype = msgtype
        if before is not None:
            self.warn(robot, name, TypeChangeError(
                f"{name}: type changed from {before.msgtype} to {msgtype}; each message is "
                "converted as its own type, with that type's options"))
        if topic.enabled and self.on_new_topic is not None:
            self.on_new_topic(robot, name, msgtype, topic.entity_path)
        if created is not None and created.problems:
            err = ConfigError("\n".join(created.problems) + " (ignored for this topic)")
            if self.strict:
                raise err
            self.warn(robot, name, err)
        return topic

    def warn(
        self, robot: str, topic: str, err: Exception, times: Mapping[str, int] | None = None
    ) -> None:
        """Report an error once per (robot, topic, kind); later ones are only counted.

        The warning goes on the bad message's timelines; without a message (an input or file
        problem) on the host's receive clock. A row without any time would be static, and each
        static warning would replace the one before it in the viewer.
        """
        counters = self.counters.get((robot, topic))
        if counters is not None:
            counters.warnings += 1
        kind = type(err).__name__
        if (robot, topic, kind) in self._warned:
            return
        self._warned.add((robot, topic, kind))
        problem = str(err)
        # Converters name the topic themselves (their errors also end --strict runs).
        if not problem.startswith(f"{topic}: "):
            problem = f"{topic}: {problem}"
        text = f"[{robot}] {problem} (further {kind}s on this topic are counted, not shown)"
        log.warning("%s", text)
        self.sink.log(
            [LogItem(WARNINGS_PATH, (rr.TextLog(text, level=rr.TextLogLevel.WARN),))],
            times or {TIMELINE_RECEIVE: time.time_ns()},
        )

    def _count(self, run: Sequence[RawMessage], first: RawMessage) -> TopicCounters:
        """Counts a run of one topic as received, with the wire sequence gaps within it."""
        key = (first.robot, first.topic)
        counters = self.counters.get(key)
        if counters is None:
            counters = self.counters[key] = TopicCounters(first.msgtype)
        counters.received += len(run)
        if isinstance(run, MessageRun):  # a bag's runs carry no wire sequence, bundles do
            if run.sequence is not None:
                counters.sequence_gaps += sequence_gaps(counters.last_sequence, run.sequence)
                counters.last_sequence = int(run.sequence[-1])
        elif first.sequence is not None or run[-1].sequence is not None:
            for raw in run:
                if raw.sequence is not None:
                    counters.sequence_gaps += sequence_gap(counters.last_sequence, raw.sequence)
                    counters.last_sequence = raw.sequence
        return counters

    def take(self, items: Sequence[InputItem]) -> None:
        """A run from an input (inputs/base.py): problems warned about, robots joining or
        leaving logged under /_swanky/robots, messages dispatched."""
        batch: list[RawMessage] = []
        for item in items:
            if isinstance(item, MessageRun):
                if batch:  # the messages before it first: a topic's order is kept
                    self.dispatch(batch)
                    batch = []
                self.dispatch(item)
            elif isinstance(item, InputProblem):
                self.warn(item.robot, item.topic, item.error)
            elif isinstance(item, RobotEvent):
                log.info("%s", item.text)
                self.sink.log(presence_items(item, time.time_ns()), {})
            else:
                batch.append(item)
        if batch:
            self.dispatch(batch)

    def dispatch(self, batch: Sequence[RawMessage]) -> None:
        """Convert and log a run of messages; messages of one topic keep their order. A topic's
        messages are converted in runs of one type: the run's first message decides how all of
        it is decoded and converted."""
        for tap in self.taps:
            tap(batch)
        if isinstance(batch, MessageRun):
            if len(batch):
                self._dispatch_run(batch)
            return
        runs: dict[tuple[str, str], list[list[RawMessage]]] = {}
        for raw in batch:
            topic_runs = runs.get((raw.robot, raw.topic))
            if topic_runs is None:
                runs[(raw.robot, raw.topic)] = [[raw]]
            elif topic_runs[-1][0].msgtype == raw.msgtype:
                topic_runs[-1].append(raw)
            else:
                topic_runs.append([raw])
        for topic_runs in runs.values():
            for run in topic_runs:
                self._dispatch_run(run)

    def _dispatch_run(self, run: Sequence[RawMessage]) -> None:
        first = run[0]
        topic = self._topic(first.robot, first.topic, first.msgtype)
        counters = self._count(run, first)
        if not topic.enabled:
            counters.skipped += len(run)
            return
        if self.offload is not None and self.offload.takes(first):
            self.offload.convert(run, topic, counters)
            return
        self.convert_run(run, topic, counters)

    def convert_run(self, run: Sequence[RawMessage], topic: TopicBinding, counters: TopicCounters) -> None:
        """Decode, convert and log a run of one enabled topic, counted in ``counters``."""
        first = run[0]
        spec = self.registry.get(first.msgtype, first.topic)
        if spec.convert_columns is not None and self._convert_columns(run, topic, spec, counters):
            return
        robot_state = self.robot_state(first.robot)
        decoded: list[tuple[Any, ConvertContext, RawMessage]] = []
        for raw in run:
            try:
                msg = self.decoder.decode(raw)
            except HostError as err:
                counters.dropped += 1
                if self.strict:
                    raise
                self.warn(raw.robot, raw.topic, err, message_times(None, raw))
                continue
            ctx = ConvertContext(
                robot=raw.robot,
                topic=raw.topic,
                entity_path=topic.entity_path,
                times=message_times(msg, raw, restamp=topic.restamp),
                topic_state=topic.state,
                robot_state=robot_state,
                restamp=topic.restamp,
            )
            decoded.append((msg, ctx, raw))
        if decoded:
            self._convert(decoded)

    def _convert_columns(
        self, run: Sequence[RawMessage], topic: TopicBinding, spec: ConverterSpec, counters: TopicCounters
    ) -> bool:
        """Convert the run through its columns, no Python per message; False when the run needs
        the message path: columns refuse it (a payload rosbags would refuse: that path names it
        and converts the others), its arrival times or definitions differ between messages, or
        the converter declines or fails on the run as a whole."""
        assert spec.convert_columns is not None
        first = run[0]
        definition = first.definition
        if not isinstance(run, MessageRun) and any(
            raw.definition is not definition and raw.definition != definition for raw in run
        ):
            return False
        arrivals = run_arrivals(run)
        if arrivals is None:
            return False
        receive_ns, log_ns = arrivals
        try:
            store = self.decoder.typestore_for(first.msgtype, definition)
        except HostError:
            return False  # the message path warns about the type
        started = time.perf_counter()
        # Any number of blocks: the message path would read its messages as columns anyway.
        payloads = run.payloads if isinstance(run, MessageRun) else [raw.data for raw in run]
        columns = read_columns(payloads, first.msgtype, store, max_blocks=len(run))
        if columns is None:
            return False
        ctx = RunContext(
            robot=first.robot,
            topic=first.topic,
            entity_path=topic.entity_path,
            size=len(run),
            receive_ns=receive_ns,
            log_ns=log_ns,
            restamp=topic.restamp,
            topic_state=topic.state,
            robot_state=self.robot_state(first.robot),
        )
        try:
            entries = spec.convert_columns(columns, ctx)
        except PartialConvertError as err:
            if self.strict:
                raise
            # As for a run of messages (see _convert): log what converted, warn once.
            entries = err.items
            self.warn(first.robot, first.topic, err, ctx.last_times())
        except Exception:
            if self.strict:
                raise
            return False  # message by message, so only a bad message is lost
        if entries is None:
            return False
        self.log(first.robot, entries, ctx.last_times())
        counters.converted += len(run)
        counters.convert_seconds += time.perf_counter() - started
        return True

    def _convert(self, decoded: list[tuple[Any, ConvertContext, RawMessage]]) -> None:
        msgtype = decoded[0][2].msgtype
        spec = self.registry.get(msgtype, decoded[0][2].topic)
        counters = self.counters[(decoded[0][2].robot, decoded[0][2].topic)]
        started = time.perf_counter()
        # The newest message its fast converter took; the slow converters (walls) get only that
        # one, so a message the fast path rejected is neither re-warned nor drawn as walls.
        accepted: tuple[Any, ConvertContext, RawMessage] | None = None
        if not spec.message_by_message and len(decoded) > 1:
            robot, topic = decoded[0][2].robot, decoded[0][2].topic
            entries: list[LogEntry] | None = None
            try:
                entries = spec.convert_run([d[0] for d in decoded], [d[1] for d in decoded])
            except PartialConvertError as err:
                if self.strict:
                    raise
                # The run converted but for a part (the kinematics of a JointState run before
                # the robot model arrives; a long custom array): log what did convert and warn
                # once for the run, instead of converting it again message by message.
                entries = err.items
                self.warn(robot, topic, err, decoded[-1][1].times)
            except Exception:
                if self.strict:
                    raise
                # Fall through: convert one by one so only the bad message is lost.
            if entries is not None:
                self.log(robot, entries, decoded[0][1].times)
                counters.converted += len(decoded)
                accepted = decoded[-1]
        if accepted is None:
            for msg, ctx, raw in decoded:
                try:
                    entries = spec.convert(msg, ctx)
                except PartialConvertError as err:
                    if self.strict:
                        raise
                    self.log(raw.robot, err.items, ctx.times)
                    self.warn(raw.robot, raw.topic, err, ctx.times)
                    counters.converted += 1
                    continue
                except Exception as err:
                    counters.dropped += 1
                    if self.strict:
                        raise
                    self.warn(raw.robot, raw.topic, err, ctx.times)
                    continue
                self.log(raw.robot, entries, ctx.times)
                counters.converted += 1
                accepted = (msg, ctx, raw)
        counters.convert_seconds += time.perf_counter() - started
        if accepted is not None:
            self._slow.submit(msgtype, *accepted)

    def close(self, timeout: float = 30.0) -> None:
        """Let the slow worker and the heavy topics' process finish what they hold (a saved .rrd
        then has the walls), and name the frames no transform ever placed."""
        if self.offload is not None:
            self.offload.close()
        self._slow.close(timeout)
        with self._robots_lock:
            robots = sorted(self._robots.items())
        for robot, known in robots:
            unplaced = known.frames.unplaced()
            if unplaced:
                log.info(
                    "[%s] no transform places frames %s; they are drawn at the robot's root /%s",
                    robot, ", ".join(unplaced), robot,
                )

    def summary(self) -> str:
        """A table of every topic seen (counters.summary_table)."""
        return summary_table(self.counters)


class _SlowWorker:
    """One thread running slow converters on the latest message of each topic only: a map
    that changes faster than its walls can be computed skips intermediate versions."""

    def __init__(self, dispatcher: Dispatcher, specs: Mapping[str, Any]) -> None:
        self._dispatcher = dispatcher
        self._specs = specs
        self._latest: dict[tuple[str, str], tuple[Any, Any, ConvertContext, RawMessage]] = {}
        self._cond = threading.Condition()
        self._busy = False
        self._closed = False
        self._thread: threading.Thread | None = None

    def submit(self, msgtype: str, msg: Any, ctx: ConvertContext, raw: RawMessage) -> None:
        spec = self._specs.get(msgtype)
        if spec is None:
            return
        with self._cond:
            self._latest[(raw.robot, raw.topic)] = (spec, msg, ctx, raw)
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="slow-converters",
                                                daemon=True)
                self._thread.start()
            self._cond.notify()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._latest and not self._closed:
                    self._cond.wait()
                if not self._latest:
                    return
                _, (spec, msg, ctx, raw) = self._latest.popitem()
                self._busy = True
            try:
                self._dispatcher.log(raw.robot, spec.convert(msg, ctx), ctx.times)
            except PartialConvertError as err:
                self._dispatcher.log(raw.robot, err.items, ctx.times)
                self._dispatcher.warn(raw.robot, raw.topic, err, ctx.times)
            except Exception as err:
                self._dispatcher.warn(raw.robot, raw.topic, err, ctx.times)
            with self._cond:
                self._busy = False
                self._cond.notify_all()

    def close(self, timeout: float) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
            self._cond.wait_for(lambda: not self._latest and not self._busy, timeout)
