"""The relay's own health, published once a second on ``swanky/<robot>/stats`` (schemas/wire.md).

CPU comes from ``os.times()`` (user + system time of this process, every thread) against
``time.monotonic()``: no psutil on the robot. 100 % is one full core, so the value lies in
``[0, 100 * cores]``. Counts are cumulative (messages, bytes, and per topic the drops a live
source saw before the relay), so a lost report loses nothing; the host turns consecutive
reports into rates.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable, Mapping

import zenoh

from robot_relay.wire import RelayReport, stats_key

log = logging.getLogger("swanky.relay")

REPORT_PERIOD_S = 1.0


def process_cpu_seconds() -> float:
    times = os.times()
    return times.user + times.system


class CpuMeter:
    """Process CPU use since the previous reading, in percent of one core."""

    def __init__(
        self,
        cpu_seconds: Callable[[], float] = process_cpu_seconds,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._cpu_seconds = cpu_seconds
        self._clock = clock
        self._last = (clock(), cpu_seconds())

    def percent(self) -> float:
        now, cpu = self._clock(), self._cpu_seconds()
        (then, cpu_then), self._last = self._last, (now, cpu)
        elapsed = now - then
        return max(0.0, (cpu - cpu_then) / elapsed * 100) if elapsed > 0 else 0.0


class RelayStatsPublisher:
    """A thread putting one RelayReport per period; ``counts`` gives (messages, bytes) sent,
    ``drops`` the source's cumulative drops per topic, ``clock`` the relay's wall clock (ns)."""

    def __init__(
        self,
        session: zenoh.Session,
        robot: str,
        counts: Callable[[], tuple[int, int]],
        drops: Callable[[], Mapping[str, int]] | None = None,
        period_s: float = REPORT_PERIOD_S,
        *,
        clock: Callable[[], int] = time.time_ns,
    ) -> None:
        self.robot = robot
        self._clock = clock
        self._counts = counts
        self._drops = drops or dict
        self._period_s = period_s
        self._meter = CpuMeter()
        self._publisher = session.declare_publisher(
            stats_key(robot), encoding=zenoh.Encoding.APPLICATION_JSON
        )
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="relay-stats", daemon=True)
        self._thread.start()

    def report(self) -> RelayReport:
        messages, sent = self._counts()
        return RelayReport(
            self.robot, self._clock(), self._meter.percent(), messages, sent, self._drops()
        )

    def _run(self) -> None:
        while not self._stop.wait(self._period_s):
            try:
                self._publisher.put(self.report().to_json())
            except Exception as err:  # the session is closing; stats are best effort
                log.debug("relay stats not sent: %s", err)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        self._publisher.undeclare()
