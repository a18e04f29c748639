"""Link and pipeline health as Rerun data, so a plot shows whether the Wi-Fi or the PC is the
bottleneck.

Once per second of each robot's receive time (live: the relay's, on the PC's clock, see
inputs/clocks.py; the bag's log time when ``--stats`` is asked for an offline conversion), for
every topic of that robot:

- ``/_stats/<robot><topic>/rate_hz``: messages that reached the host, per second;
- ``.../bandwidth_kbps``: their CDR bytes (after wire decompression), kbit/s;
- ``.../drops``: messages lost between the relay and the host (wire sequence gaps) in the
  period, less the host's own ``host_drops`` (they leave gaps too, but are counted once, there);
- ``.../host_drops`` (live): messages the host itself dropped in the period because it converts
  the robot's messages slower than they arrive (a full queue, a heavy topic's message replaced
  by a newer one while behind: inputs/queues.py), also for topics with nothing else to show;
  what is dropped after the last closed period is logged when the host stops, at the end of the
  period it falls in, so the series sums to the host's drop summary;
- ``.../latency_ms``: mean host wall clock when the message reached the pipeline (before it is
  decoded and converted) minus the relay's receive time (live only);
- ``.../convert_ms``: mean host decode + conversion time per message;
- ``/_stats/<robot>/host/convert_load_percent``: host time spent converting this robot's
  messages, in % of the period;
- ``/_stats/<robot>/relay/cpu_percent`` (% of one core), ``sent_hz``, ``sent_kbps``: the
  relay's own report (``swanky/<robot>/stats``), to compare what was sent with what arrived;
- ``/_stats/<robot><topic>/ros_drops``: messages the relay saw lost between the ROS publisher
  and itself (publication sequence gaps) since its previous report, for topics with any;
- ``/_stats/<robot>/clock/offset_ms``, ``uncertainty_ms`` (live): the relay's clock minus the
  PC's, and how far the truth may lie from it, at each measurement (inputs/clocks.py).

The two drop counts, 0 nearly always, are logged where they change and every QUIET_PERIODS
else (:class:`QuietZeros`); the rows of a period are made as one batch (``scalar_rows``): with
25 robots of 15 topics, 1,600 rows a second instead of 2,275, for 40-65 ms of the host's CPU a
second instead of 110-130 (benchmarks/RESULTS.md, issue 24's fleet of 25).

Not from this tap, on the host's wall clock (thinning.py): ``/_stats/host/viewer_lag_ms``, how far
behind the viewers are, and ``/_stats/<robot><topic>/viewer_thinned``, the heavy messages they
were not sent, each second.

Latency compares two clocks: the relay's receive times come corrected by the measured offset
(inputs/zenoh.py), so latency is right within the offset's uncertainty whether or not robot and
PC are synchronised; a relay that does not answer the clock query is not corrected, and its
clock's offset shows as a constant shift of every topic's latency (negative when the robot's
clock is ahead). The relay's reports are put on the PC's clock the same way. Congestion shows
as latency that grows with bandwidth, together with drops or ``sent_hz`` above ``rate_hz``. A
saturated PC shows as ``convert_load_percent`` near 100 instead.
Latency includes the time a sample waited in the host's input queue.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, TypeVar

import numpy as np
import numpy.typing as npt
import rerun as rr

from host_bridge.core.columns import PackedPayloads
from host_bridge.core.contract import (
    STATS_ROOT,
    TIMELINE_LOG,
    TIMELINE_RECEIVE,
    ColumnsItem,
    LogEntry,
    LogItem,
    scalar_rows,
)
from host_bridge.core.counters import TopicCounters, sequence_gap, sequence_gaps
from host_bridge.inputs.base import MessageRun
from host_bridge.inputs.clocks import ClockEstimate, RelayClocks
from robot_relay.errors import WireError
from robot_relay.wire import RawMessage, RelayReport, parse_robot_key, stats_selector

if TYPE_CHECKING:
    import zenoh

    from host_bridge.outputs.sink import Sink

log = logging.getLogger("swanky.host")

PERIOD_NS = 1_000_000_000
# After a silence longer than this many periods, log one empty period and skip the rest.
MAX_EMPTY_PERIODS = 10

ConvertTotals = Callable[[str, str], tuple[int, float]]
HostDropped = Callable[[str], Mapping[str, int]]
"""A robot's messages the host's queue dropped so far, per topic, as counted when the batch being
observed left the queue (:meth:`~host_bridge.inputs.queues.RobotQueues.dropped_when_taken`)."""


def no_convert_totals(robot: str, topic: str) -> tuple[int, float]:
    return 0, 0.0


@dataclass(frozen=True, slots=True)
class TopicStats:
    """One topic over one period ending at ``end_ns`` on ``timeline``."""

    robot: str
    topic: str
    timeline: str
    end_ns: int
    rate_hz: float
    bandwidth_kbps: float
    drops: int
    host_drops: int | None
    """None: no host queue (a bag)."""
    latency_ms: float | None
    convert_ms: float | None
    convert_seconds: float


@dataclass(slots=True)
class _TopicWindow:
    count: int = 0
    bytes: int = 0
    drops: int = 0
    latency_ns: int = 0
    latency_count: int = 0
    last_sequence: int | None = None
    # The topic's host drops as of the last batch it was in; those since then left gaps in this
    # batch (unless older than the topic's first message seen) and are not the link's drops.
    host_dropped_seen: int = 0
    converted_before: int = 0
    convert_seconds_before: float = 0.0


@dataclass(slots=True)
class _RobotWindow:
    timeline: str
    end_ns: int
    topics: dict[str, _TopicWindow] = field(default_factory=dict)
    # Host drops per topic up to the last closed period.
    host_dropped_closed: Mapping[str, int] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class HostDrops:
    """Host drops of a topic after its last closed period, when the host stops."""

    robot: str
    topic: str
    timeline: str
    end_ns: int
    count: int


Time = TypeVar("Time", int, "npt.NDArray[np.int64]")


def _arrival(receive_ns: Time | None, log_ns: Time | None) -> tuple[Time, str] | None:
    """When a message (or each of a run's) counts, and on which timeline: the relay's receive
    time live, the log time of a bag; None without either."""
    if receive_ns is not None:
        return receive_ns, TIMELINE_RECEIVE
    if log_ns is not None:
        return log_ns, TIMELINE_LOG
    return None


class StatsTracker:
    """Per-robot one-second windows over RawMessages; pure (times come in, numbers go out)."""

    def __init__(
        self,
        period_ns: int = PERIOD_NS,
        convert_totals: ConvertTotals = no_convert_totals,
        host_dropped: HostDropped | None = None,
    ) -> None:
        self.period_ns = period_ns
        self.convert_totals = convert_totals
        self.host_dropped = host_dropped
        self._robots: dict[str, _RobotWindow] = {}
        # Per (robot, topic): host drops not yet set against a sequence gap of the current batch.
        self._unmatched: dict[tuple[str, str], int] = {}

    def observe_batch(self, batch: Sequence[RawMessage], host_ns: int) -> list[TopicStats]:
        """:meth:`observe` a batch the host's queue handed over at once (a robot's worker took
        it); host drops not found in its gaps were of messages older than any seen. A run
        (a relay's bundles, a bag's window) is observed with arrays, a period at a time."""
        self._unmatched.clear()
        if isinstance(batch, MessageRun):
            return self._observe_run(batch, host_ns)
        closed: list[TopicStats] = []
        for raw in batch:
            closed += self.observe(raw, host_ns)
        return closed

    def observe(self, raw: RawMessage, host_ns: int) -> list[TopicStats]:
        """Count ``raw``, handed to the host pipeline at ``host_ns``; return the periods it closed."""
        arrival = _arrival(raw.receive_ns, raw.log_ns)
        if arrival is None:
            return []
        closed, window = self._window(raw.robot, raw.topic, *arrival)
        window.count += 1
        window.bytes += len(raw.data)
        if raw.sequence is not None:
            gap = sequence_gap(window.last_sequence, raw.sequence)
            window.drops += gap - self._dropped_by_host(raw.robot, raw.topic, window, gap)
            window.last_sequence = raw.sequence
        if raw.receive_ns is not None:
            window.latency_ns += host_ns - raw.receive_ns
            window.latency_count += 1
        return closed

    def _observe_run(self, run: MessageRun, host_ns: int) -> list[TopicStats]:
        """:meth:`observe` of every message of ``run``, each period's part of it at once."""
        arrival = _arrival(run.receive_ns, run.log_ns)
        if arrival is None:
            return []
        times, timeline = arrival
        payloads = run.payloads
        sizes = (payloads.ends - payloads.starts if isinstance(payloads, PackedPayloads)
                 else np.fromiter(map(len, payloads), np.int64, len(payloads)))
        closed: list[TopicStats] = []
        begin = 0
        while begin < len(run):
            closed_now, window = self._window(run.robot, run.topic, int(times[begin]), timeline)
            closed += closed_now
            later = np.flatnonzero(times[begin:] >= self._robots[run.robot].end_ns)
            end = begin + int(later[0]) if len(later) else len(run)
            window.count += end - begin
            window.bytes += int(sizes[begin:end].sum())
            if run.sequence is not None:
                part = run.sequence[begin:end]
                gap = sequence_gaps(window.last_sequence, part)
                window.drops += gap - self._dropped_by_host(run.robot, run.topic, window, gap)
                window.last_sequence = int(part[-1])
            if run.receive_ns is not None:
                window.latency_ns += int((host_ns - run.receive_ns[begin:end]).sum())
                window.latency_count += end - begin
            begin = end
        return closed

    def _window(self, name: str, topic: str, at: int, timeline: str) -> tuple[list[TopicStats], _TopicWindow]:
        """The periods a message at ``at`` closes, and its topic's window of the period it is in."""
        robot = self._robots.get(name)
        if robot is None:
            robot = self._robots[name] = _RobotWindow(timeline, self._period_end(at))
        closed: list[TopicStats] = []
        while at >= robot.end_ns:
            closed += self._close(name, robot)
            if at >= robot.end_ns + MAX_EMPTY_PERIODS * self.period_ns:
                closed += self._close(name, robot)  # one empty period shows the silence
                robot.end_ns = self._period_end(at)
        window = robot.topics.get(topic)
        if window is None:
            window = robot.topics[topic] = self._new_window(name, topic)
        return closed, window

    def _new_window(self, robot: str, topic: str) -> _TopicWindow:
        converted, seconds = self.convert_totals(robot, topic)
        return _TopicWindow(converted_before=converted, convert_seconds_before=seconds)

    def _dropped_by_host(self, robot: str, topic: str, window: _TopicWindow, gap: int) -> int:
        """How much of the sequence ``gap`` the host's own queue dropped."""
        if self.host_dropped is None:
            return 0
        key = (robot, topic)
        unmatched = self._unmatched.get(key)
        if unmatched is None:  # the topic's first message in this batch
            dropped = self.host_dropped(robot).get(topic, 0)
            unmatched, window.host_dropped_seen = dropped - window.host_dropped_seen, dropped
        matched = min(unmatched, gap)
        self._unmatched[key] = unmatched - matched
        return matched

    def _period_end(self, at: int) -> int:
        return (at // self.period_ns + 1) * self.period_ns

    def _close(self, name: str, robot: _RobotWindow) -> list[TopicStats]:
        seconds = self.period_ns / 1e9
        closed = []
        host_dropped = None if self.host_dropped is None else self.host_dropped(name)
        for topic in sorted((host_dropped or {}).keys() - robot.topics.keys()):
            robot.topics[topic] = self._new_window(name, topic)  # dropped, none converted yet
        for topic, window in robot.topics.items():
            converted, convert_seconds = self.convert_totals(name, topic)
            new_converted = converted - window.converted_before
            spent = convert_seconds - window.convert_seconds_before
            closed.append(TopicStats(
                robot=name,
                topic=topic,
                timeline=robot.timeline,
                end_ns=robot.end_ns,
                rate_hz=window.count / seconds,
                bandwidth_kbps=window.bytes * 8 / 1000 / seconds,
                drops=window.drops,
                host_drops=None if host_dropped is None
                else host_dropped.get(topic, 0) - robot.host_dropped_closed.get(topic, 0),
                latency_ms=window.latency_ns / window.latency_count / 1e6
                if window.latency_count else None,
                convert_ms=spent * 1000 / new_converted if new_converted else None,
                convert_seconds=spent,
            ))
            robot.topics[topic] = _TopicWindow(
                last_sequence=window.last_sequence,
                host_dropped_seen=window.host_dropped_seen,
                converted_before=converted,
                convert_seconds_before=convert_seconds,
            )
        if host_dropped is not None:
            robot.host_dropped_closed = host_dropped
        robot.end_ns += self.period_ns
        return closed

    def host_drops_at_stop(self) -> list[HostDrops]:
        """The host drops after each robot's last closed period, on its open period's end, so
        that ``host_drops`` sums to what the host dropped (call once the queues are drained)."""
        if self.host_dropped is None:
            return []
        found = []
        for name, robot in self._robots.items():
            dropped = self.host_dropped(name)
            for topic, count in sorted(dropped.items()):
                new = count - robot.host_dropped_closed.get(topic, 0)
                if new:
                    found.append(HostDrops(name, topic, robot.timeline, robot.end_ns, new))
            robot.host_dropped_closed = dropped
        return found


QUIET_PERIODS = 10
"""A drop count that stays 0 is logged every this many periods (besides where a run of drops
begins and ends, :class:`QuietZeros`)."""
QUIET_COUNTS = ("drops", "host_drops")
"""The series that are 0 nearly always: two of every topic's six, a third of ``/_stats``'s rows
(25 robots of 15 topics: 750 of 2,275 a second)."""


@dataclass(slots=True)
class _QuietSeries:
    timeline: str
    logged_ns: int
    """The end of the last period logged."""
    last_ns: int
    last_value: float


class QuietZeros:
    """Which periods of a count that is mostly 0 to log: every one that is not 0, the 0 that
    ends a run of them and the (skipped) 0 before one, the first period and one every
    ``every`` periods. A plot draws the same lines (Rerun joins two zeros with a flat line, as
    it does the zeros between them), and a run of drops starts and ends where it did; the
    periods skipped at the end are logged by :meth:`skipped` when the host stops."""

    def __init__(self, every: int = QUIET_PERIODS, period_ns: int = PERIOD_NS) -> None:
        self.every_ns = every * period_ns
        self._series: dict[str, _QuietSeries] = {}

    def rows(self, path: str, timeline: str, end_ns: int, value: float) -> list[tuple[int, float]]:
        """The rows of ``path`` to log now, (end of period, value), for its period ending at
        ``end_ns``."""
        series = self._series.get(path)
        if series is None:
            self._series[path] = _QuietSeries(timeline, end_ns, end_ns, value)
            return [(end_ns, value)]
        rows = []
        if value or series.last_value or end_ns - series.logged_ns >= self.every_ns:
            if value and series.logged_ns != series.last_ns:
                rows.append((series.last_ns, 0.0))  # the run of drops begins after this one
            rows.append((end_ns, value))
            series.logged_ns = end_ns
        series.last_ns, series.last_value = end_ns, value
        return rows

    def skipped(self) -> list[tuple[str, str, int]]:
        """Each series whose last period was a 0 not logged: (path, timeline, its end)."""
        return [(path, series.timeline, series.last_ns) for path, series in self._series.items()
                if series.logged_ns != series.last_ns]


def topic_stats_items(
    stats: Sequence[TopicStats], period_ns: int = PERIOD_NS, quiet: QuietZeros | None = None,
) -> list[ColumnsItem]:
    """Scalars per topic and metric, plus each robot's host conversion load per period; with
    ``quiet``, of the drop counts only the rows it picks (:data:`QUIET_COUNTS`)."""
    rows: list[tuple[str, Mapping[str, int], float]] = []
    load: dict[tuple[str, str, int], float] = {}
    for s in stats:
        times = {s.timeline: s.end_ns}
        root = f"{STATS_ROOT}/{s.robot}{s.topic}"
        values: dict[str, float | None] = {
            "rate_hz": s.rate_hz,
            "bandwidth_kbps": s.bandwidth_kbps,
            "drops": float(s.drops),
            "host_drops": None if s.host_drops is None else float(s.host_drops),
            "latency_ms": s.latency_ms,
            "convert_ms": s.convert_ms,
        }
        for name, value in values.items():
            if value is None:
                continue
            path = f"{root}/{name}"
            if quiet is None or name not in QUIET_COUNTS:
                rows.append((path, times, value))
            else:
                rows += [(path, {s.timeline: at}, kept)
                         for at, kept in quiet.rows(path, s.timeline, s.end_ns, value)]
        if s.timeline == TIMELINE_RECEIVE:  # a wall-clock share; meaningless on bag time
            key = (s.robot, s.timeline, s.end_ns)
            load[key] = load.get(key, 0.0) + s.convert_seconds
    rows += [
        (f"{STATS_ROOT}/{robot}/host/convert_load_percent", {timeline: end_ns},
         seconds * 1e9 / period_ns * 100)
        for (robot, timeline, end_ns), seconds in load.items()
    ]
    return scalar_rows(rows)


def clock_items(robot: str, estimate: ClockEstimate) -> list[LogItem]:
    """A relay clock's measured offset and its uncertainty, at the PC's time of measurement."""
    root = f"{STATS_ROOT}/{robot}/clock"
    times = {TIMELINE_RECEIVE: estimate.at_ns}
    return [
        LogItem(f"{root}/offset_ms", (rr.Scalars(estimate.offset_ns / 1e6),), times=times),
        LogItem(f"{root}/uncertainty_ms", (rr.Scalars(estimate.uncertainty_ns / 1e6),), times=times),
    ]


class RelayRates:
    """Turns a relay's cumulative reports into rates between consecutive reports."""

    def __init__(self) -> None:
        self._last: dict[str, RelayReport] = {}

    def items(self, report: RelayReport) -> list[LogItem]:
        root = f"{STATS_ROOT}/{report.robot}/relay"
        times = {TIMELINE_RECEIVE: report.time_ns}
        items = [LogItem(f"{root}/cpu_percent", (rr.Scalars(report.cpu_percent),), times=times)]
        last = self._last.get(report.robot)
        self._last[report.robot] = report
        for topic, dropped in sorted(report.drops.items()):
            before = 0 if last is None else last.drops.get(topic, 0)
            if dropped >= before:  # smaller: the relay restarted; its counts began again
                items.append(LogItem(f"{STATS_ROOT}/{report.robot}{topic}/ros_drops",
                                     (rr.Scalars(float(dropped - before)),), times=times))
        if last is not None and report.time_ns > last.time_ns and report.messages >= last.messages:
            seconds = (report.time_ns - last.time_ns) / 1e9
            sent_hz = (report.messages - last.messages) / seconds
            sent_kbps = (report.payload_bytes - last.payload_bytes) * 8 / 1000 / seconds
            items += [
                LogItem(f"{root}/sent_hz", (rr.Scalars(sent_hz),), times=times),
                LogItem(f"{root}/sent_kbps", (rr.Scalars(sent_kbps),), times=times),
            ]
        return items


HELD_S = 5.0
"""How many seconds of ``/_stats`` rows a host holds and logs at once while its viewers take data
in slowly (:meth:`host_bridge.pipeline.thinning.ViewerThinning.stats_hold_s`)."""


class HeldRows:
    """``/_stats`` rows held while ``hold_s()`` says so, then logged at once. Rows of an entity
    logged together go to the viewer as one chunk, and a viewer takes chunks in at a cost each,
    whatever their rows: logged every second, ``/_stats`` was one chunk per series per second,
    as many as every other entity together (10 demo robots: 1,049 series; a saving viewer's
    file held 16,264 of their chunks against 5,918 of the robots' data, /tmp/chunks10.sh)."""

    def __init__(self, hold_s: Callable[[], float]) -> None:
        self._hold_s = hold_s
        self._items: list[LogEntry] = []
        self._since: float | None = None

    def release(self, items: list[LogEntry], now: float) -> list[LogEntry]:
        """What to log now, ``items`` included, or nothing while they are held."""
        if items:
            self._items += items
            if self._since is None:
                self._since = now
        if self._since is None or now - self._since < self._hold_s():
            return []
        return self.rest()

    def rest(self) -> list[LogEntry]:
        """Everything held."""
        released, self._items, self._since = self._items, [], None
        return released


class StatsTap:
    """Dispatcher tap logging ``/_stats``; with a Zenoh session it also logs the relays' reports,
    with ``clocks`` their clocks' offsets (and puts the reports' times on the PC's clock);
    ``hold_s``: how long to hold its rows before logging them (:class:`HeldRows`)."""

    def __init__(
        self,
        sink: Sink,
        counters: Mapping[tuple[str, str], TopicCounters],
        *,
        session: zenoh.Session | None = None,
        robots: str = "*",
        owns: Callable[[str], bool] | None = None,
        host_dropped: HostDropped | None = None,
        clock: Callable[[], int] = time.time_ns,
        clocks: RelayClocks | None = None,
        hold_s: Callable[[], float] = lambda: 0.0,
    ) -> None:
        self.sink = sink
        self._held = HeldRows(hold_s)
        self.tracker = StatsTracker(convert_totals=self._convert_totals, host_dropped=host_dropped)
        self._counters = counters
        self._clock = clock
        self._rates = RelayRates()
        self._reports: collections.deque[RelayReport] = collections.deque(maxlen=1000)
        self._clocks = clocks
        self._owns = owns
        """Whose relay reports this host logs (one worker of several: its shard's)."""
        self._estimates: collections.deque[tuple[str, ClockEstimate]] = collections.deque(maxlen=1000)
        self._quiet = QuietZeros(period_ns=self.tracker.period_ns)
        if clocks is not None:
            clocks.watch(lambda robot, estimate: self._estimates.append((robot, estimate)))
        # Live robots are dispatched from one thread each; windows and rates are shared state.
        self._lock = threading.Lock()
        self._subscriber = (
            None if session is None
            else session.declare_subscriber(stats_selector(robots), self._on_report)
        )

    def _convert_totals(self, robot: str, topic: str) -> tuple[int, float]:
        counters = self._counters.get((robot, topic))
        return (0, 0.0) if counters is None else (counters.converted, counters.convert_seconds)

    def _on_report(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            report = RelayReport.from_json(sample.payload.to_bytes(), key)
            if report.robot != parse_robot_key(key):
                msg = f"relay stats on {key!r} name robot {report.robot!r}"
                raise WireError(msg)
        except WireError as err:
            log.debug("%s", err)
            return
        if self._owns is not None and not self._owns(report.robot):
            return
        if self._clocks is not None:
            offset = self._clocks.correction_ns(report.robot, report.time_ns)
            report = dataclasses.replace(report, time_ns=report.time_ns - offset)
        self._reports.append(report)  # zenoh's thread; logged on the host's thread

    def __call__(self, batch: Sequence[RawMessage]) -> None:
        host_ns = self._clock()
        with self._lock:
            closed = self.tracker.observe_batch(batch, host_ns)
            items = self._held.release(
                [*topic_stats_items(closed, self.tracker.period_ns, self._quiet),
                 *self._received_items()],
                host_ns / 1e9)
        if items:
            self.sink.log(items, {})

    def _received_items(self) -> list[LogItem]:
        """What came from the relays meanwhile, their reports and clocks (lock held)."""
        items: list[LogItem] = []
        while self._reports:
            items += self._rates.items(self._reports.popleft())
        while self._estimates:
            items += clock_items(*self._estimates.popleft())
        return items

    def close(self) -> None:
        """Stop taking the relays' reports; log the rows held, the reports still waiting, the
        clock estimates since the last run, the drop counts' zeros skipped at the end
        (:class:`QuietZeros`) and the host drops of the periods still open (the input is closed
        first, so its queues are drained)."""
        if self._subscriber is not None:
            self._subscriber.undeclare()
            self._subscriber = None
        with self._lock:
            items: list[LogEntry] = [*self._held.rest(), *self._received_items(), *scalar_rows(
                [(path, {timeline: end_ns}, 0.0) for path, timeline, end_ns in self._quiet.skipped()]
                + [(f"{STATS_ROOT}/{d.robot}{d.topic}/host_drops", {d.timeline: d.end_ns}, float(d.count))
                   for d in self.tracker.host_drops_at_stop()]
            )]
        if items:
            self.sink.log(items, {})
