"""What a viewer that falls behind is sent (issue 24): fewer heavy messages, and the same rows
in fewer chunks.

A viewer drawing with software GL takes in less than a few robots send: the demo's robot fell
minutes behind in the native viewer, seconds in the web viewer. How far behind it is, is
measured (viewer_lag.py: the round trip of a flush into the viewer). While that round trip is
over :data:`BEHIND_S`, every :data:`BACK_OFF_EVERY_S` :class:`Pace` doubles

* the interval at which each heavy topic (the type table's ``Lane.HEAVY`` rows: images, clouds,
  whole maps) goes to it, latest-only, per robot and topic (from :data:`FIRST_INTERVAL_S` up to
  :data:`MAX_INTERVAL_S`): its newest message once the interval since the last one sent has
  passed, none in between;
* when the viewers themselves are slow to answer (not this host slow to send), the period of
  the flushes that batch their rows (``ViewerLag.period``, up to ``LONGEST_PERIOD_S``): Rerun's
  viewer takes in a bounded number of chunks per frame it draws, so a topic's rows of a longer
  period in one chunk lose nothing and cost it less;

and once they are under :data:`CAUGHT_UP_S` both shrink by :data:`RECOVERY` every
:data:`CONTROL_EVERY_S`, until heavy topics go in full again: the rate the viewer takes is found
by trying, as TCP finds a link's. A topic slower than the interval is never thinned.

Never thinned: small topics (scans, TF, IMU, odometry), a grid's patches (they must follow their
grid), static data, and the ``--save`` file: a heavy message the viewers are not sent is still
converted and logged to the file (``RerunSink.saved_only``). Without a file it is not converted
at all (that is where a host on the viewer's PC gets its CPU back); when a converter process
logs the heavy topics (offload.py: a viewer is then the one destination), it is not sent there.

The user is told: a warning per robot and topic the first time it is thinned (stderr and
``/_swanky/warnings``), naming the rate the viewer gets; a line each time the viewer caught up,
with what it was not sent; ``/_stats/host/viewer_lag_ms`` (each second, the most it was behind:
round trip plus period; ``/_stats/host/<name>/viewer_lag_ms`` with ``--host-name``) and
``/_stats/<robot><topic>/viewer_thinned`` (messages not sent to it in that second); the counts
when the host stops.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import rerun as rr

from host_bridge.core.contract import STATS_ROOT, TIMELINE_RECEIVE, WARNINGS_PATH, LogItem
from host_bridge.inputs.queues import TypeLanes
from host_bridge.outputs.stats import HELD_S
from host_bridge.outputs.viewer_lag import LONGEST_PERIOD_S, SHORTEST_PERIOD_S
from host_bridge.table.registry import Lane

if TYPE_CHECKING:
    from host_bridge.core.counters import TopicCounters
    from host_bridge.outputs.sink import RerunSink
    from host_bridge.outputs.viewer_lag import ViewerLag
    from host_bridge.pipeline.dispatch import Dispatcher, Offload, TopicBinding
    from robot_relay.wire import RawMessage

log = logging.getLogger("swanky.host")

LAG_PATH = f"{STATS_ROOT}/host/viewer_lag_ms"
"""Where a host logs how far behind its viewers are; ``/_stats/host/<name>/viewer_lag_ms`` for a
host given ``--host-name`` (hosts of one fleet sharing a viewer, each its own series)."""


def lag_path(host_name: str | None) -> str:
    return LAG_PATH if host_name is None else f"{STATS_ROOT}/host/{host_name}/viewer_lag_ms"

BEHIND_S = 0.5
"""A flush's round trip over this: the viewers are sent less."""
CAUGHT_UP_S = 0.25
"""A flush's round trip under this: they are sent more again."""
CONTROL_EVERY_S = 0.25
BACK_OFF_EVERY_S = 1.0
"""Pace backs off at most this often: a viewer needs a moment to show it is sent less."""
FIRST_INTERVAL_S = 0.25
MAX_INTERVAL_S = 4.0
RECOVERY = 0.85
"""Each CONTROL_EVERY_S the viewers keep up, period and interval are multiplied by this (the
rate up by 90 % each second: from one message in 4 s to 30 Hz in 7.5 s)."""
LAST_INTERVAL_S = 1 / 30
"""Below this interval thinning ends: no camera is faster."""
STATS_EVERY_S = 1.0


class Pace:
    """How much the viewers are sent, from the round trips of flushes into them: the period of
    the flushes that batch their rows, and the interval between a heavy topic's messages (0:
    every one)."""

    def __init__(self) -> None:
        self.period = SHORTEST_PERIOD_S
        self.interval = 0.0
        self._backed_off_at: float | None = None

    def update(self, now: float, round_trip: float, answers: float) -> bool:
        """Back off or recover from a flush's ``round_trip`` (the heavy topics' interval) and
        the viewers' ``answers``, their part of it (the period: batching helps only a viewer
        slow to take chunks in, not a host slow to send them); True when thinning just ended."""
        rested = self._backed_off_at is None or now - self._backed_off_at >= BACK_OFF_EVERY_S
        if round_trip > BEHIND_S and rested:
            self._backed_off_at = now
            self.interval = min(MAX_INTERVAL_S, max(FIRST_INTERVAL_S, self.interval * 2))
            if answers > BEHIND_S:
                self.period = min(LONGEST_PERIOD_S, self.period * 2)
        if answers < CAUGHT_UP_S:
            self.period = max(SHORTEST_PERIOD_S, self.period * RECOVERY)
        if round_trip < CAUGHT_UP_S and self.interval:
            self.interval *= RECOVERY
            if self.interval < LAST_INTERVAL_S:
                self.interval = 0.0
                return True
        return False


@dataclass(slots=True)
class _Topic:
    sent_at: float | None = None
    thinned: int = 0
    """In all."""
    thinned_in_second: int = 0
    thinned_in_episode: int = 0
    """Since thinning began; 0 until this topic is thinned."""


class ViewerThinning:
    """Routes each run of the heavy lane: to the viewers (through ``inner``, the converter
    process, when there is one) when its topic's turn has come, else to the ``--save`` file
    only, or nowhere. Holds the dispatcher's ``offload`` place (dispatch.Offload), ``inner``
    behind it; a thread applies :class:`Pace` and logs the ``/_stats`` series."""

    def __init__(
        self, dispatcher: Dispatcher, sink: RerunSink, lag: ViewerLag,
        inner: Offload | None = None, *, stats: bool = True, path: str = LAG_PATH,
        clock: Callable[[], float] = time.monotonic, wall_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        """``stats``: log the ``/_stats`` series (not with ``--no-stats``), the lag at ``path``."""
        self._dispatcher = dispatcher
        self._sink = sink
        self._lag = lag
        self._inner = inner
        self._stats = stats
        self._path = path
        self._clock = clock
        self._wall_ns = wall_ns
        self._lanes = TypeLanes(dispatcher.registry)
        self._lock = threading.Lock()
        self._topics: dict[tuple[str, str], _Topic] = {}
        self.pace = Pace()
        self._began_at: float | None = None
        self._most_behind = 0.0
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._run, name="viewer-thinning", daemon=True)
        self._thread.start()

    # -- the dispatcher's side (each robot's heavy thread) ----------------------------------

    def takes(self, raw: RawMessage) -> bool:
        return self._lanes(raw) is Lane.HEAVY or (self._inner is not None and self._inner.takes(raw))

    def convert(self, run: Sequence[RawMessage], topic: TopicBinding, counters: TopicCounters) -> None:
        first = run[0]
        if self._lanes(first) is Lane.HEAVY and not self._admits(first.robot, first.topic, len(run)):
            if self._sink.saving:
                with self._sink.saved_only():
                    self._dispatcher.conversion.convert(run, topic, counters)
            return
        if self._inner is not None and self._inner.takes(first):
            self._inner.convert(run, topic, counters)
        else:
            self._dispatcher.conversion.convert(run, topic, counters)

    def _admits(self, robot: str, topic: str, count: int) -> bool:
        """Whether a run of ``count`` messages of ``robot``'s heavy ``topic`` goes to the
        viewers: always when they keep up, else when its last one went an interval ago."""
        now = self._clock()
        with self._lock:
            state = self._topics.setdefault((robot, topic), _Topic())
            interval = self.pace.interval
            if not interval or state.sent_at is None or now - state.sent_at >= interval:
                state.sent_at = now
                return True
            first = not state.thinned
            state.thinned += count
            state.thinned_in_second += count
            state.thinned_in_episode += count
            if self._began_at is None:
                self._began_at = now
        if first:
            self._warn(robot, topic, interval)
        return False

    def _warn(self, robot: str, topic: str, interval: float) -> None:
        text = (
            f"[{robot}] {topic}: the Rerun viewer {self._lag.names} is {self._lag.seconds:.1f} s "
            f"behind: it gets the newest message of this topic at most every {interval:.2g} s "
            f"({1 / interval:.2g} Hz) until it catches up"
            + ("; the --save file gets every one" if self._sink.saving else "")
            + f" (each time: {STATS_ROOT}/{robot}{topic}/viewer_thinned)"
        )
        log.warning("%s", text)
        self._sink.log([LogItem(WARNINGS_PATH, (rr.TextLog(text, level=rr.TextLogLevel.WARN),))],
                       {TIMELINE_RECEIVE: self._wall_ns()})

    def stats_hold_s(self) -> float:
        """How long ``/_stats`` rows are held before they are logged (stats.HeldRows): HELD_S
        from the first back-off (heavy topics thinned, or the flushes batched longer) until the
        viewers caught up. ``/_stats`` are a third of what 10 demo robots send a viewer (chunks
        in ``rerun rrd stats`` of what a saving viewer got: 15,347 of 34,474), so they wait
        first, before the plots of the robots' own data are batched longer."""
        behind = self.pace.interval > 0 or self.pace.period > SHORTEST_PERIOD_S
        return HELD_S if behind else 0.0

    # -- the control loop -------------------------------------------------------------------

    def _run(self) -> None:
        stats_due = self._clock() + STATS_EVERY_S
        while not self._stopping.wait(CONTROL_EVERY_S):
            now = self._clock()
            self._most_behind = max(self._most_behind, self._lag.seconds)
            with self._lock:
                ended = self.pace.update(now, self._lag.round_trip, self._lag.answers)
                self._lag.period = self.pace.period
                if ended:
                    self._end_episode(now)
            if now >= stats_due:
                stats_due = now + STATS_EVERY_S
                self._log_stats()

    def _end_episode(self, now: float) -> None:
        """Thinning ended (the lock held): say which topics were thinned, how much."""
        thinned = sorted((key, state.thinned_in_episode) for key, state in self._topics.items()
                         if state.thinned_in_episode)
        began, self._began_at = self._began_at, None
        if thinned:
            log.info(
                "the Rerun viewer %s caught up: heavy topics go to it in full again (over %.0f s "
                "it was not sent %s)", self._lag.names, now - (now if began is None else began),
                ", ".join(f"[{robot}] {topic} {count}" for (robot, topic), count in thinned))
        for state in self._topics.values():
            state.thinned_in_episode = 0

    def _log_stats(self) -> None:
        behind, self._most_behind = self._most_behind, 0.0
        log.debug("viewer lag: %.0f ms at most in the last second; flush period %.2f s, heavy "
                  "interval %.2f s", behind * 1000, self.pace.period, self.pace.interval)
        times = {TIMELINE_RECEIVE: self._wall_ns()}
        items = [LogItem(self._path, (rr.Scalars(behind * 1000),), times=times)]
        with self._lock:
            for (robot, topic), state in sorted(self._topics.items()):
                if state.thinned_in_episode or state.thinned_in_second:
                    items.append(LogItem(f"{STATS_ROOT}/{robot}{topic}/viewer_thinned",
                                         (rr.Scalars(float(state.thinned_in_second)),), times=times))
                    state.thinned_in_second = 0
        if self._stats:
            self._sink.log(items, {})

    # -- closing ----------------------------------------------------------------------------

    def thinned(self) -> dict[tuple[str, str], int]:
        """Heavy messages not sent to the viewers, per (robot, topic), in all."""
        with self._lock:
            return {key: state.thinned for key, state in self._topics.items() if state.thinned}

    def close(self) -> None:
        """Stop pacing; the inner offload finishes what it holds; tell what the viewers were
        not sent."""
        self._stopping.set()
        self._thread.join()
        self._most_behind = max(self._most_behind, self._lag.seconds)
        self._log_stats()  # the last second's, so the series sums to the counts below
        if self._inner is not None:
            self._inner.close()
        thinned = self.thinned()
        if thinned:
            where = "the --save file has them all" if self._sink.saving else "they were not converted"
            log.warning(
                "heavy messages not sent to the Rerun viewer because it fell behind (%s):\n%s", where,
                "\n".join(f"[{robot}] {topic}: {count}" for (robot, topic), count in sorted(thinned.items())))
