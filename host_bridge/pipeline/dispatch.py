"""RawMessage runs -> taps -> decode -> convert -> sink, with the error policy and per-topic
counters (counters.py).

One path: a topic's run is handed to its converter whole (:class:`~host_bridge.core.contract.Run`:
messages decoded, or columns read, on demand); a run its converter fails on is converted again
message by message, so only a bad message is lost. A bad message never stops the host: it is
counted, warned about once per (robot, topic, error kind) and shown in Rerun under
``/_swanky/warnings``; ``strict`` (tests, ``--strict``) re-raises instead.

:class:`Conversion` is that core, with its slow lane (:class:`SlowLane`: the table's slow
converters, latest-only). The :class:`Dispatcher` is built around one, and so is the heavy
topics' process (offload.py). Everything the dispatcher converts for a robot is logged through
:meth:`Dispatcher.log`, which also keeps the robot's frames one tree and names its 3D view's
target frame (see frames.py).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import rerun as rr

from host_bridge.core.columns import Columns, columns_of_messages, read_columns
from host_bridge.core.contract import (
    TIMELINE_RECEIVE,
    WARNINGS_PATH,
    Converter,
    Int64Array,
    LogEntry,
    LogItem,
    PerMessage,
    Run,
)
from host_bridge.core.counters import TopicCounters, summary_table
from host_bridge.core.decode import Decoder
from host_bridge.core.frames import RobotFrames
from host_bridge.core.resources import ResourceResolver
from host_bridge.core.state import RobotState, TopicState
from host_bridge.errors import ConfigError, HostError, PartialConvertError, TypeChangeError
from host_bridge.inputs.base import (
    InputItem,
    InputProblem,
    MessageRun,
    RobotEvent,
    presence_items,
)
from host_bridge.outputs.sink import Sink
from host_bridge.table.config import HostConfig
from host_bridge.table.registry import Registry, default_registry
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


class _Payloads:
    """A run's payloads (``raws[start:stop]``) as its messages' source: decoded message by
    message with the decoder, or read as columns all at once."""

    __slots__ = ("_decoder", "_raws", "_start", "_stop")

    def __init__(self, raws: Sequence[RawMessage], decoder: Decoder, start: int = 0,
                 stop: int | None = None) -> None:
        self._raws = raws
        self._decoder = decoder
        self._start = start
        self._stop = len(raws) if stop is None else stop

    def __len__(self) -> int:
        return self._stop - self._start

    def decode(self, row: int) -> Any:
        return self._decoder.decode(self._raws[self._start + row])

    def columns(self) -> Columns:
        raws, start, stop = self._raws, self._start, self._stop
        first = raws[start]
        store = self._decoder.typestore_for(first.msgtype, first.definition)
        if isinstance(raws, MessageRun):
            payloads = raws.payloads if (start, stop) == (0, len(raws)) else raws.payloads[start:stop]
        else:
            payloads = [raws[row].data for row in range(start, stop)]
        # Any number of blocks: decoding the messages one by one would cost more.
        columns = read_columns(payloads, first.msgtype, store, max_blocks=len(payloads))
        if columns is not None:
            return columns
        # A payload columns refuse, which the decoder names; or a layout that is not columns
        # (nested sequences of differing lengths), which columns_of_messages names.
        return columns_of_messages([self.decode(row) for row in range(len(self))], first.topic)

    def part(self, row: int) -> _Payloads:
        return _Payloads(self._raws, self._decoder, self._start + row, self._start + row + 1)


def _arrivals(raws: Sequence[RawMessage]) -> tuple[Int64Array | None, Int64Array | None]:
    """The run's receive and log times, one array each (None: its messages lack that time)."""
    if isinstance(raws, MessageRun):
        return raws.receive_ns, raws.log_ns
    first = raws[0]
    receive = None if first.receive_ns is None else np.array([raw.receive_ns for raw in raws], np.int64)
    logged = None if first.log_ns is None else np.array([raw.log_ns for raw in raws], np.int64)
    return receive, logged


def _continues(run: Sequence[RawMessage], raw: RawMessage) -> bool:
    """Whether ``raw`` may join its topic's last ``run``: the same type and definition, and the
    same arrival timelines, as the messages of one :class:`~host_bridge.core.contract.Run` have."""
    first = run[0]
    return (
        raw.msgtype == first.msgtype
        and (raw.definition is first.definition or raw.definition == first.definition)
        and (raw.receive_ns is None) == (first.receive_ns is None)
        and (raw.log_ns is None) == (first.log_ns is None)
    )


LogEntries = Callable[[str, Sequence[LogEntry], Mapping[str, int]], None]
"""Logs a robot's entries (``times``: where items without times of their own go)."""


class Conversion:
    """Decode -> convert -> log for runs of one topic, with the error policy, the robots' state
    and the slow lane: the core the dispatcher is built around, and all the heavy topics'
    process runs (offload.py). Entries go to ``log``, warnings to ``sink``.

    The error policy: a message that does not decode or convert is counted as dropped, warned
    about once per (robot, topic, error kind) on its timelines and, ``strict``, re-raised; one
    that converts in part (PartialConvertError) has what converted logged and is warned about.
    """

    def __init__(
        self,
        sink: Sink,
        log: LogEntries,
        *,
        registry: Registry,
        decoder: Decoder,
        counters: dict[tuple[str, str], TopicCounters],
        strict: bool = False,
        resolver: ResourceResolver | None = None,
    ) -> None:
        self.sink = sink
        self.log = log
        self.registry = registry
        self.decoder = decoder
        self.counters = counters
        self.strict = strict
        # Finds mesh files for every robot (each robot's own relay for what is missing here).
        self._resolver = resolver or ResourceResolver.from_env()
        self._robots: dict[str, RobotState] = {}
        self._robots_lock = threading.Lock()
        self._warned: set[tuple[str, str, str]] = set()
        self._slow = SlowLane(self.attempt, self.registry.slow_converters())

    def robot_state(self, robot: str) -> RobotState:
        """The state ``robot``'s converters share. The slow lane converts for robots too."""
        state = self._robots.get(robot)  # a known robot's without the lock (dict reads are atomic)
        if state is not None:
            return state
        with self._robots_lock:
            state = self._robots.get(robot)
            if state is None:
                state = self._robots[robot] = RobotState(resolver=self._resolver.for_robot(robot))
            return state

    def warn(
        self, robot: str, topic: str, err: Exception, times: Mapping[str, int] | None = None
    ) -> None:
        """Report an error once per (robot, topic, kind); later ones are only counted.

        The warning goes on the bad message's timelines; without a message (an input or file
        problem) on the host's receive clock. A row without any time would be static, and each
        static warning would replace the one before it in the viewer.
        """
        self._warn(robot, topic, err, lambda: times or {TIMELINE_RECEIVE: time.time_ns()})

    def _warn(
        self, robot: str, topic: str, err: Exception, times: Callable[[], Mapping[str, int]]
    ) -> None:
        """:meth:`warn`, the warning's times asked for only when it is shown."""
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
        self.sink.log([LogItem(WARNINGS_PATH, (rr.TextLog(text, level=rr.TextLogLevel.WARN),))], times())

    def convert(self, raws: Sequence[RawMessage], topic: TopicBinding, counters: TopicCounters) -> None:
        """Decode, convert and log a run of one enabled topic (one type, one definition, the
        same arrival timelines: see :meth:`Dispatcher.dispatch`), counted in ``counters``. The
        newest message its converter took goes on to the row's slow converter, if it has one."""
        first = raws[0]
        converter = self.registry.get(first.msgtype, first.topic)
        receive_ns, log_ns = _arrivals(raws)
        run = Run(
            _Payloads(raws, self.decoder), robot=first.robot, topic=first.topic,
            entity_path=topic.entity_path, receive_ns=receive_ns, log_ns=log_ns,
            restamp=topic.restamp, topic_state=topic.state, robot_state=self.robot_state(first.robot),
        )
        started = time.perf_counter()
        parts = [run]
        if len(run) > 1 and isinstance(converter, PerMessage):
            # A converter written per message gets its messages one by one, decoded and timed
            # at once for the run (unless one does not decode: then each on its own).
            with contextlib.suppress(HostError):
                run.contexts()
            parts = run.split()
        taken = None
        for part in parts:
            taken = self.attempt(part, converter, counters, self.strict) or taken
        counters.convert_seconds += time.perf_counter() - started
        if taken is not None:
            self._slow.submit(first.msgtype, taken)

    def attempt(
        self, run: Run, converter: Converter, counters: TopicCounters | None, strict: bool
    ) -> Run | None:
        """Convert and log ``run`` under the error policy; when the converter fails on it, the
        run again message by message, so only a bad message is lost. The (last) run the
        converter took, None if none."""
        try:
            entries = converter(run)
        except PartialConvertError as err:
            # The run converted but for a part (the kinematics of a JointState run before the
            # robot model arrives; a long custom array): what did is logged, the rest warned of.
            self._failed(run, err, strict)
            entries = err.items
        except Exception as err:
            if len(run) > 1 and not strict:
                taken = None
                for one in run.split():
                    taken = self.attempt(one, converter, counters, strict) or taken
                return taken
            if counters is not None:
                counters.dropped += len(run)
            self._failed(run, err, strict)
            return None
        # Items without times of their own (a per-message converter's, of a message alone) go at
        # the timelines of the run's last message.
        times: Mapping[str, int] = {}
        for entry in entries:  # (a loop: any() of a generator costs a live message more)
            if isinstance(entry, LogItem) and entry.times is None and not entry.static:
                times = run.last_times()
                break
        self.log(run.robot, entries, times)
        if counters is not None:
            counters.converted += len(run)
        return run

    def _failed(self, run: Run, err: Exception, strict: bool) -> None:
        """Re-raise ``err`` (strict), or warn about it at the run's last message's timelines."""
        if strict:
            raise err
        self._warn(run.robot, run.topic, err, lambda: run.row_times(-1, run.stamp(-1)))

    def close(self, timeout: float = 30.0) -> None:
        """Let the slow lane finish what it holds (a saved .rrd then has the walls)."""
        self._slow.close(timeout)


class SlowLane:
    """One thread running the type table's slow converters (the walls of a map) on the newest
    message of each topic only: a map that changes faster than its walls can be computed
    skips intermediate versions. Its runs go through ``attempt`` (:meth:`Conversion.attempt`),
    never strict: its message was converted already, so its errors are only warned about."""

    def __init__(self, attempt: Callable[[Run, Converter, None, bool], Run | None],
                 converters: Mapping[str, Converter]) -> None:
        self._attempt = attempt
        self._converters = converters
        self._latest: dict[tuple[str, str], tuple[Converter, Run]] = {}
        self._cond = threading.Condition()
        self._busy = False
        self._closed = False
        self._thread: threading.Thread | None = None

    def submit(self, msgtype: str, run: Run) -> None:
        """The last message of ``run`` for ``msgtype``'s slow converter, if it has one."""
        converter = self._converters.get(msgtype)
        if converter is None:
            return
        last = run if len(run) == 1 else run.one(-1)
        with self._cond:
            self._latest[(run.robot, run.topic)] = (converter, last)
            if self._thread is None:
                self._thread = threading.Thread(target=self._work, name="slow-converters",
                                                daemon=True)
                self._thread.start()
            self._cond.notify()

    def _work(self) -> None:
        while True:
            with self._cond:
                while not self._latest and not self._closed:
                    self._cond.wait()
                if not self._latest:
                    return
                _, (converter, run) = self._latest.popitem()
                self._busy = True
            self._attempt(run, converter, None, False)
            with self._cond:
                self._busy = False
                self._cond.notify_all()

    def close(self, timeout: float) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
            self._cond.wait_for(lambda: not self._latest and not self._busy, timeout)


@dataclass(frozen=True, slots=True)
class _Frames:
    """A robot's frame tree, and the lock held from observing logged frames to logging the
    placements they call for (see :meth:`Dispatcher.log`)."""

    frames: RobotFrames
    placing: threading.Lock = field(default_factory=threading.Lock)


class Dispatcher:
    """Runs from the inputs -> the taps, then per topic: its settings and counters, and its
    conversion here (:class:`Conversion`) or in the heavy topics' process (``offload``);
    everything converted is logged with its robot's frame tree."""

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
        self._taps = tuple(taps)
        self.on_new_topic = on_new_topic
        self.registry = registry or default_registry()
        self.config = config or HostConfig.builtin(self.registry)
        self.counters: dict[tuple[str, str], TopicCounters] = {}
        self.conversion = Conversion(
            sink, self.log, registry=self.registry, decoder=decoder or Decoder(),
            counters=self.counters, strict=strict, resolver=resolver,
        )
        self._topics: dict[tuple[str, str], _TopicTypes] = {}
        # Taken when a topic's type changes: a robot's two threads may both carry the topic.
        self._retyping = threading.Lock()
        self._frames: dict[str, _Frames] = {}
        self._frames_lock = threading.Lock()
        self.offload: Offload | None = None
        """Where heavy topics are converted when not here (offload.py's process)."""

    @property
    def decoder(self) -> Decoder:
        return self.conversion.decoder

    @property
    def strict(self) -> bool:
        return self.conversion.strict

    def add_tap(self, tap: Tap) -> None:
        """``tap`` sees every run from now on, after the taps before it (add taps before the
        input starts: a run being dispatched meanwhile may miss it)."""
        self._taps = (*self._taps, tap)

    def robot_state(self, robot: str) -> RobotState:
        return self.conversion.robot_state(robot)

    def warn(
        self, robot: str, topic: str, err: Exception, times: Mapping[str, int] | None = None
    ) -> None:
        """:meth:`Conversion.warn`: once per (robot, topic, kind), later ones only counted."""
        self.conversion.warn(robot, topic, err, times)

    def _frames_of(self, robot: str) -> _Frames:
        # The slow lane's thread logs for robots too. A known robot's without the lock.
        found = self._frames.get(robot)
        if found is not None:
            return found
        with self._frames_lock:
            found = self._frames.get(robot)
            if found is None:
                found = self._frames[robot] = _Frames(RobotFrames(robot))
            return found

    def frames(self, robot: str) -> RobotFrames:
        return self._frames_of(robot).frames

    def log(self, robot: str, entries: Sequence[LogEntry], times: Mapping[str, int]) -> None:
        """Log ``robot``'s entries, then what its frames need now (placements, target).

        A robot's small topics, its heavy ones (inputs/queues.py) and the slow lane log from
        threads of their own. A frame placed at the robot's root shares its static entity with
        the frame's real transform and must never be written after it: entries are observed
        before they are logged, and those that call for placements are logged with them under
        the robot's lock, so a transform observed later is also logged later. Other entries
        (nearly all) are logged outside it: a small topic does not wait for a cloud's log."""
        known = self._frames_of(robot)
        with known.placing:
            updates = known.frames.observe(entries, self.conversion.robot_state(robot))
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
        known = self._frames_of(robot)
        with known.placing:
            updates = known.frames.note(relations, frames, self.robot_state(robot))
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
        messages are converted in runs of one type, definition and set of arrival timelines:
        the run's first message decides how all of it is decoded and converted."""
        for tap in self._taps:
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
            elif _continues(topic_runs[-1], raw):
                topic_runs[-1].append(raw)
            else:
                topic_runs.append([raw])
        for topic_runs in runs.values():
            for run in topic_runs:
                self._dispatch_run(run)

    def _dispatch_run(self, run: Sequence[RawMessage]) -> None:
        first = run[0]
        topic = self._topic(first.robot, first.topic, first.msgtype)
        counters = self.counters.get((first.robot, first.topic))
        if counters is None:
            counters = self.counters[(first.robot, first.topic)] = TopicCounters(first.msgtype)
        if isinstance(run, MessageRun):  # a bag's runs carry no wire sequence, bundles do
            counters.receive(len(run), run.sequence)
        elif first.sequence is not None or run[-1].sequence is not None:
            counters.receive(len(run), [raw.sequence for raw in run])
        else:
            counters.receive(len(run), None)
        if not topic.enabled:
            counters.skipped += len(run)
            return
        if self.offload is not None and self.offload.takes(first):
            self.offload.convert(run, topic, counters)
            return
        self.conversion.convert(run, topic, counters)

    def close(self, timeout: float = 30.0) -> None:
        """Let the slow lane and the heavy topics' process finish what they hold (a saved .rrd
        then has the walls), and name the frames no transform ever placed."""
        if self.offload is not None:
            self.offload.close()
        self.conversion.close(timeout)
        with self._frames_lock:
            robots = sorted(self._frames.items())
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
