"""The demo robots' relays: each robot's bag replayed (looping, real time) by a real
:class:`~robot_relay.relay.Relay` on a Zenoh session of its own, as ``swanky-relay --bag`` on
that robot would, the whole fleet paced by one thread.

One thread per robot, each reading its bag and sleeping until its next message was due, cost a
fleet of 25 one wake-up per message (5,150 a second) and a turn at the GIL each, which in
``swanky-host --demo`` is the host's. Here one thread merges the robots' timelines and wakes
once per :data:`TICK_S` at most, publishing every message due by then, each robot's as runs of a
topic (``Relay.publish_run``, as a bag replay that is behind publishes them: a run of one is a
single message on the wire, a longer one a bundle). The wire stays each robot's own: its
session, publishers, sequence numbers, catalog, clock query and liveliness token. 25 demo relays
keep real time in a process of their own for about 0.2 of a core (benchmarks/RESULTS.md, issue
24), the thread per robot too when not starved of CPU.
"""

from __future__ import annotations

import heapq
import logging
import threading
import time
from collections.abc import Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

import zenoh

from robot_relay.relay import Relay
from robot_relay.session import ZenohOptions, close_session, open_session
from robot_relay.sources.bag import BagSource
from robot_relay.wire import RawMessage

log = logging.getLogger("swanky.demo")

TICK_S = 0.005
"""The pacing thread wakes at most this often: a message goes out at most this late (5 ms, a
sixth of the demo's 30 Hz period), and the ~200 messages a second of a demo robot cost 25
robots 200 wake-ups a second instead of 5,000."""


@dataclass(slots=True)
class _Timeline:
    """One robot's bag, looping, with the ``time.monotonic()`` each message is due at: its log
    time since its pass's first message, a pass beginning when the previous one's last message
    was due (as :class:`~robot_relay.sources.bag.BagSource` paces a looping replay)."""

    relay: Relay
    messages: Iterator[RawMessage]
    pass_start: float
    first_ns: int | None = None
    last_ns: int = 0
    last_due: float = 0.0

    def next(self) -> tuple[float, RawMessage]:
        raw = next(self.messages)
        log_ns = raw.log_ns or 0
        if self.first_ns is None or log_ns < self.last_ns:  # the bag began again
            if self.first_ns is not None:
                self.pass_start = self.last_due
            self.first_ns = log_ns
        self.last_ns = log_ns
        self.last_due = self.pass_start + (log_ns - self.first_ns) / 1e9
        return self.last_due, raw


def relay_bags(
    bags: Mapping[str, Path], endpoint: str, stop: threading.Event, host_stop: threading.Event,
    *, mode: str | None = None, host_wait_s: float = 30.0,
) -> None:
    """Replay each robot's bag (``bags``: robot name -> bag) through its relay to the host at
    ``endpoint`` (a router's, with ``mode`` "client": benchmarks/fleet.py), looping in real
    time, until ``stop``; sets ``host_stop`` if it fails. A robot's replay starts once the host
    subscribed to it; one it did not subscribe to within ``host_wait_s`` is said and left out."""
    try:
        with ExitStack() as closing:
            timelines = []
            # At once: a session takes 0.1-0.5 s to open (25 of them, one after the other, most
            # of the benchmark's warm-up on a loaded machine).
            with ThreadPoolExecutor(len(bags), thread_name_prefix="demo-relay-open") as pool:
                opening = [pool.submit(_open, robot, bag, endpoint, mode) for robot, bag in bags.items()]
            failure = None
            for future in opening:
                try:
                    session, source, relay = future.result()
                except Exception as err:  # the others opened still close
                    failure = failure or err
                    continue
                closing.callback(close_session, session)
                closing.callback(source.close)
                closing.callback(relay.close)
                timelines.append(_Timeline(relay, source.messages(), 0.0))
            if failure is not None:
                raise failure
            deadline = time.monotonic() + host_wait_s
            listened = []
            for timeline in timelines:
                if timeline.relay.wait_for_host(max(deadline - time.monotonic(), 0.0), stop):
                    listened.append(timeline)
                elif not stop.is_set():
                    log.error("demo relay %r: the host did not subscribe within %.0f s",
                              timeline.relay.robot, host_wait_s)
            if not stop.is_set():
                _pace(listened, stop)
    except Exception:
        log.exception("the demo relays failed; stopping the demo")
        host_stop.set()


def _open(robot: str, bag: Path, endpoint: str, mode: str | None) -> tuple[zenoh.Session, BagSource, Relay]:
    """Robot ``robot``'s session, bag and relay, as ``swanky-relay --bag`` opens them."""
    session = open_session(ZenohOptions(mode=mode, connect=(endpoint,), multicast_scouting=False))
    try:
        source = BagSource(bag, robot, loop=True).open()
        try:
            return session, source, Relay(session, source.catalog())
        except BaseException:
            source.close()
            raise
    except BaseException:
        close_session(session)
        raise


def _pace(timelines: list[_Timeline], stop: threading.Event) -> None:
    """Publish every robot's messages as they fall due, until ``stop``."""
    started = time.monotonic()
    heap: list[tuple[float, int, RawMessage]] = []
    for index, timeline in enumerate(timelines):
        timeline.pass_start = started
        at, raw = timeline.next()
        heap.append((at, index, raw))
    heapq.heapify(heap)
    while heap and not stop.is_set():
        now = time.monotonic()
        runs: dict[tuple[int, str], tuple[list[bytes | memoryview], list[int]]] = {}
        while heap and heap[0][0] <= now:
            _, index, raw = heap[0]
            payloads, log_ns = runs.setdefault((index, raw.topic), ([], []))
            payloads.append(raw.data)
            log_ns.append(raw.log_ns or 0)
            at, following = timelines[index].next()
            heapq.heapreplace(heap, (at, index, following))
        for (index, topic), (payloads, log_ns) in runs.items():
            timelines[index].relay.publish_run(topic, payloads, log_ns)
        if heap:
            stop.wait(max(heap[0][0] - time.monotonic(), TICK_S))

