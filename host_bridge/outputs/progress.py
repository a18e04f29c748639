"""A progress line on stderr while a bag converts offline: messages, topics, bag time, speed.

On a terminal the line redraws in place at most four times a second; otherwise (CI logs, a pipe)
a plain line is written every ``LOG_PERIOD_S`` seconds, so logs stay short. Its own renderer:
tqdm and rich draw one counter, while this line shows three (messages, topics, bag seconds).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

from host_bridge.errors import InputError
from host_bridge.inputs.base import MessageRun
from robot_relay.errors import SourceError
from robot_relay.sources.bag import BagSource
from robot_relay.wire import RawMessage

TTY_PERIOD_S = 0.25
LOG_PERIOD_S = 5.0


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


def bag_extent(path: Path) -> BagExtent:
    """Opened the way the conversion opens it (the relay's bag source), so every bag that
    converts has a progress line too."""
    try:
        with BagSource(path, robot="") as source:
            return BagExtent(
                messages=source.message_count,
                topics=source.topic_count,
                start_ns=source.start_ns,
                end_ns=source.end_ns,
                types={info.topic: info.msgtype for info in source.catalog().topics},
            )
    except SourceError as err:
        raise InputError(str(err)) from err


def render_progress(
    extent: BagExtent, done: int, topics: int, log_ns: int | None, elapsed_s: float
) -> str:
    """``' 45% 3,700/8,197 msgs  3/4 topics  bag 43.8/97.4 s  2,310 msg/s'``."""
    percent = 100 * done // extent.messages if extent.messages else 100
    bag_done = 0.0 if log_ns is None else max(log_ns - extent.start_ns, 0) / 1e9
    speed = f"{done / elapsed_s:,.0f} msg/s" if elapsed_s > 0 else "- msg/s"
    return (
        f"{percent:3d}% {done:,}/{extent.messages:,} msgs  {topics}/{extent.topics} topics  "
        f"bag {bag_done:.1f}/{extent.duration_ns / 1e9:.1f} s  {speed}"
    )


class Progress:
    """A dispatcher tap that counts the runs going by and redraws the line."""

    def __init__(
        self,
        extent: BagExtent,
        stream: TextIO | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.extent = extent
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self.done = 0
        self._clock = clock
        self._topics: set[tuple[str, str]] = set()
        self._log_ns: int | None = None
        self._started = clock()
        self._period = TTY_PERIOD_S if self.tty else LOG_PERIOD_S
        self._next = self._started + self._period

    def line(self) -> str:
        return render_progress(
            self.extent, self.done, len(self._topics), self._log_ns, self._clock() - self._started
        )

    def __call__(self, batch: Sequence[RawMessage]) -> None:
        self.done += len(batch)
        if isinstance(batch, MessageRun):  # one topic: no RawMessage made per message
            self._topics.add((batch.robot, batch.topic))
        else:
            self._topics.update((raw.robot, raw.topic) for raw in batch)
        if batch and batch[-1].log_ns is not None:
            self._log_ns = batch[-1].log_ns
        now = self._clock()
        if now >= self._next:
            self._next = now + self._period
            self._write(self.line())

    def _write(self, text: str) -> None:
        if self.tty:
            self.stream.write(f"\r\x1b[K{text}")
        else:
            self.stream.write(f"{text}\n")
        self.stream.flush()

    def finish(self) -> None:
        self._write(self.line())
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()
