"""Offline input: a bag straight into the host pipeline, no Zenoh, in runs for batching.

It reuses the relay's raw bag source, so a bag converted here and one replayed through a relay
give the host the same RawMessages (same CDR, same definitions, same log times). A rosbag2 in
MCAP or sqlite3 storage is read in bulk by the relay's bulk readers, :mod:`robot_relay.sources.mcap`
and :mod:`robot_relay.sources.sqlite`, instead (the same messages in the same order, payloads
sliced out of whole chunks or of a batch of rows) and handed on as one
:class:`~host_bridge.inputs.base.MessageRun` per topic, with no record per message; a file they
do not take is read by the source. The bag is opened once: what it holds (:class:`BagExtent`, for
the progress line) and its messages come from the same opened source.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from host_bridge.core.columns import PackedPayloads
from host_bridge.errors import InputError
from host_bridge.inputs.bag_opener import RUN_BYTES, BagOpener, open_bag
from host_bridge.inputs.base import Deliver, MessageRun
from host_bridge.inputs.rows_ahead import read_ahead
from robot_relay.errors import SourceError
from robot_relay.sources.bag import BagSource
from robot_relay.sources.mcap import TopicRun
from robot_relay.wire import RawMessage

RUN_MESSAGES = 32768
"""Messages read before they go on as runs: big runs amortise what each run costs (a
send_columns call per plotted series, the frames' bookkeeping), up to RUN_BYTES of payload."""
DELIVERY_SECONDS = 0.25
"""About how long converting one delivery may take: the host stops (Ctrl-C, SIGTERM) after the
delivery under way, and a whole run of a slow type is seconds (24,000 LaserScans: 2.5-5 s)."""
FIRST_DELIVERY = 256
"""Messages of a topic delivered first, to time what one of them takes."""


@dataclass(frozen=True, slots=True)
class BagExtent:
    """What a whole bag holds, from its index or metadata (nothing is read)."""

    messages: int
    topics: int
    start_ns: int
    end_ns: int
    types: Mapping[str, str] = field(default_factory=dict)
    """Each topic's type (host-side SLAM asks whether the bag holds odometry)."""

    @property
    def duration_ns(self) -> int:
        return max(self.end_ns - self.start_ns, 0)

    @classmethod
    def of(cls, source: BagSource) -> BagExtent:
        """The extent of an opened bag."""
        return cls(
            messages=source.message_count,
            topics=source.topic_count,
            start_ns=source.start_ns,
            end_ns=source.end_ns,
            types={info.topic: info.msgtype for info in source.catalog().topics},
        )


def bag_runs(
    path: Path, robot: str, run_size: int = RUN_MESSAGES, run_bytes: int = RUN_BYTES,
    stop: threading.Event | None = None,
) -> Iterator[Sequence[RawMessage]]:
    """:func:`source_runs` of the bag at ``path``, opened and closed here."""
    source = open_bag(path, robot)
    try:
        yield from source_runs(source, run_size, run_bytes, stop)
    finally:
        source.close()


def source_runs(
    source: BagSource, run_size: int = RUN_MESSAGES, run_bytes: int = RUN_BYTES,
    stop: threading.Event | None = None,
) -> Iterator[Sequence[RawMessage]]:
    """The opened bag's messages, every topic's in log-time order, in windows of at most
    ``run_size`` messages and about ``run_bytes`` bytes of payload (at least one message). An
    indexed MCAP or a sqlite3 bag gives each window as one :class:`MessageRun` per topic (the run
    holding the window's last message last; see
    :meth:`~robot_relay.sources.mcap.McapFile.windows`); another bag gives each window as one list
    of RawMessages in log-time order, read message by message, so it ends early, as the last
    window, once ``stop`` is set."""
    try:
        files = source.bulk_files()
        if files is None:
            messages = source.messages()
            while window := _window(messages, run_size, run_bytes, stop):
                yield window
                if stop is not None and stop.is_set():
                    return
            return
        source.log_undefined()
        for index in range(len(files)):
            read_ahead(source, index + 1, run_bytes)  # the next file's rows, while this converts
            opened = files[index]
            try:
                for runs in opened.windows(run_size, run_bytes):
                    yield from (message_run(source.robot, run) for run in runs)
            finally:
                opened.close()
    except SourceError as err:
        raise InputError(str(err)) from err


def _window(
    messages: Iterator[RawMessage], size: int, payload_bytes: int, stop: threading.Event | None
) -> list[RawMessage]:
    window: list[RawMessage] = []
    total = 0
    for raw in messages:
        window.append(raw)
        total += len(raw.data)
        if len(window) >= size or total >= payload_bytes or (stop is not None and stop.is_set()):
            break
    return window


def message_run(robot: str, run: TopicRun) -> MessageRun:
    """The bulk reader's run of one topic as the host's run, its payloads left in its buffers."""
    return MessageRun(robot, run.info.topic, run.info.msgtype, run.info.definition,
                      PackedPayloads(run.buffers, run.sources, run.starts, run.ends), run.log_ns)


class BagInput:
    """The :class:`~host_bridge.inputs.base.Input` of ``--bag``: the bag's runs, read and
    delivered on a thread of its own until its end or :meth:`close` (after the current run).

    The bag is opened once, by :meth:`extent` or else by the reading thread: opening an MCAP bag
    parses every channel's QoS (rosbags), 8-64 ms for nav2_turtlebot.mcap's four; a bag recorded
    with ``--compression-mode file`` starts its decompression, a sqlite3 one's tables are read. With
    ``opener`` (the bag at ``path`` opening on its thread since before the app was imported,
    cli.py) the bag is taken from it instead."""

    def __init__(self, path: Path, robot: str, opener: BagOpener | None = None) -> None:
        self.path = path
        self.robot = robot
        self._opener = opener
        self.finished = threading.Event()
        """Set by the reading thread once it is done (:meth:`ended`): the app waits on it."""
        self.last_activity = time.monotonic()
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._source: BagSource | None = None

    def extent(self) -> BagExtent:
        """What the bag holds (an InputError when it cannot be opened); call it before
        :meth:`start`, which then reads the bag opened here."""
        return BagExtent.of(self._opened())

    def _opened(self) -> BagSource:
        if self._source is None:
            self._source = (open_bag(self.path, self.robot) if self._opener is None
                            else self._opener.take())
        return self._source

    def start(self, deliver: Deliver) -> None:
        self._thread = threading.Thread(
            target=self._read, args=(deliver,), name="bag-input", daemon=True
        )
        self._thread.start()

    def _read(self, deliver: Deliver) -> None:
        deliveries = _TimedDeliveries()
        try:
            for run in source_runs(self._opened(), stop=self._closing):
                for part in deliveries.parts(run):
                    self.last_activity = time.monotonic()
                    started = time.perf_counter()
                    deliver([part] if isinstance(part, MessageRun) else part)
                    deliveries.took(part, time.perf_counter() - started)
                    if self._closing.is_set():
                        return
        except BaseException as err:  # raised on the app's thread by ended()
            self._error = err
        finally:
            self.finished.set()

    def ended(self) -> bool:
        if self._error is not None:
            raise self._error
        return self.finished.is_set()

    def close(self) -> None:
        self._closing.set()
        if self._thread is not None:
            self._thread.join()
        if self._source is not None:
            self._source.close()


class _TimedDeliveries:
    """Splits the bag's runs into deliveries of about DELIVERY_SECONDS each, from what the last
    delivery of the same topic took a message (a window of several topics, from a bag other than
    an indexed MCAP, counts as one topic): a fast, columnar topic still goes on in whole runs."""

    def __init__(self) -> None:
        self._seconds_per_message: dict[str | None, float] = {}

    def parts(self, run: Sequence[RawMessage]) -> Iterator[Sequence[RawMessage]]:
        start = 0
        while start < len(run):
            stop = start + self._size(_topic(run))
            yield run.part(start, stop) if isinstance(run, MessageRun) else run[start:stop]
            start = stop

    def took(self, part: Sequence[RawMessage], seconds: float) -> None:
        self._seconds_per_message[_topic(part)] = seconds / len(part)

    def _size(self, topic: str | None) -> int:
        seconds = self._seconds_per_message.get(topic)
        if seconds is None:
            return FIRST_DELIVERY
        return max(1, int(DELIVERY_SECONDS / max(seconds, 1e-9)))


def _topic(run: Sequence[RawMessage]) -> str | None:
    return run.topic if isinstance(run, MessageRun) else None
