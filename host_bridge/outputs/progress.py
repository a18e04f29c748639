"""A progress line on stderr while a bag converts offline: messages, topics, bag time, speed.

On a terminal the line redraws in place at most four times a second; otherwise (CI logs, a pipe)
a plain line is written every ``LOG_PERIOD_S`` seconds, so logs stay short. Its own renderer:
tqdm and rich draw one counter, while this line shows three (messages, topics, bag seconds).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Sequence
from typing import TextIO

from host_bridge.inputs.bag import BagExtent
from host_bridge.inputs.base import MessageRun
from robot_relay.wire import RawMessage

TTY_PERIOD_S = 0.25
LOG_PERIOD_S = 5.0


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
