"""Per-robot bounded queues between the Zenoh callbacks and the dispatcher.

Each robot gets its own queue and, once :meth:`RobotQueues.serve` runs, its own worker threads,
so a robot whose messages are slow to convert (or that floods the host) delays the others by no
more than its turn (below): its queue fills and drops its own oldest messages while the other
robots keep flowing. Latched messages (``/tf_static``, ``/robot_description``, maps) are never
the ones dropped: a late copy of them is all a viewer will ever get.

Heavy topics (the type table's ``Lane.HEAVY`` rows: images, point clouds, maps) are converted
on a thread of their own per robot, with the patches of such messages (``Lane.PATCH`` rows: grid
updates, which must follow their grid), and go latest-only once the host is behind on them: with
more than :data:`HEAVY_BACKLOG` heavy items waiting, all robots together, a heavy topic keeps
only its newest message (or run), and a newer one of its type replaces it. (Latest-only as soon
as one waits lost frames to every short stall of a loaded host, which a user asking for every
frame, ``congestion: block``, does not expect.)

The small topics (IMU, TF, scans) never wait behind a heavy conversion: in the issue's mixed
load a 300k-point cloud took its robot's one worker for 5-10 ms (more on a loaded host), and
every scan, IMU and TF message that came meanwhile waited for it
(``benchmarks/live_capacity.py``). The heavy thread also runs at a lower priority
(:data:`HEAVY_NICENESS`), so on a busy machine the small topics get a core first. A robot's
small topics are dropped only when its whole queue is full.

A fleet shares the host fairly: the robots' threads take turns (:class:`Turns`), in the order
they asked, :data:`SMALL_TURNS` robots converting small topics at a time and one converting heavy
ones. A robot waiting for its turn gathers what arrives meanwhile, so the busier the host, the
longer the runs it converts in one call: a run costs its calls more than its length (one demo
robot's odometry message converted alone took 2.2 ms of CPU, an IMU message 0.65 ms, in runs of
ten 0.14 ms each), and a demo robot whose every message is converted alone costs about 0.3 of
a core, so 25 of them converting on threads of their own would need 7 cores. A host that cannot
convert every robot's images and clouds thins them evenly, each robot converting the newest of
its own at each turn, none starved. The first time the host thins heavy topics it says so once,
naming the robots and topics thinned then; the small topics are never thinned.

Order: each topic's messages are handed over in order, on one thread (each message's type
decides its thread, so a message of another type, garbage, changes nothing for the topic's
others). Between a heavy topic and a small one there is no order, as there is none between two
robots; the dispatcher keeps what a robot's threads share consistent (frames, the model).

A robot's queue is full at :data:`MAX_PER_ROBOT` messages, a
:class:`~host_bridge.inputs.base.MessageRun` (a bundle of one topic's messages from the wire)
counting ``len(run)``, or at :data:`MAX_ITEMS_PER_ROBOT` items (records or runs); a dropped or
replaced run counts ``len(run)`` drops, and a heavy topic's run is replaced as a whole, like
one heavy message.

Every message dropped here is counted per topic (:attr:`RobotQueues.dropped`, the drop summary
the host prints when it stops) and shows in ``/_stats/<robot><topic>/host_drops`` (stats.py reads
:meth:`RobotQueues.dropped_when_taken` and keeps these drops out of the wire ``drops``, though
they leave sequence gaps too). A topic's first drop is warned about once, in
``/_swanky/warnings`` as well: the warning leads the next batch of the topic's thread, so it
shows when the drops begin, not after the backlog (and takes no message's place in the queue).
"""

from __future__ import annotations

import functools
import gc
import logging
import os
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from host_bridge.core.contract import STATS_ROOT
from host_bridge.errors import HostError
from host_bridge.inputs.base import InputItem, InputProblem, MessageRun
from host_bridge.table.registry import Lane
from robot_relay.wire import RawMessage

if TYPE_CHECKING:
    from host_bridge.table.registry import Registry

log = logging.getLogger("swanky.host")

MAX_PER_ROBOT = 100_000
"""Messages waiting per robot, small and heavy topics together, beyond which the oldest go (a
MessageRun counts its messages): what a full-speed replay's bundles pile up in a second here
(benchmarks/live_capacity.py dropped 30-48k of its 94k messages at 5,000); tens of MB of small
messages."""
MAX_ITEMS_PER_ROBOT = 5000
"""Items (records or runs) waiting per robot: each costs at least one conversion call, about a
millisecond for a small message, so a robot sending one message per sample lags at most a few
seconds before its oldest go."""
# A worker takes everything waiting, up to this many messages, at once: what arrived while it
# converted one batch is the next, so a loaded host converts runs (send_columns) that grow with
# the load, and an idle one converts a message as soon as it comes. A fixed 5 ms wait for more
# added its whole length to the latency of the mixed load (p50 15 ms against 5 ms
# without; benchmarks/live_capacity.py) and converted no more per second when flooded. A
# flooded host takes as many as a bag's run (inputs/bag.py's windows are twice that): at 1024 a
# full-speed replay's runs were cut to about a thousand messages, and a run costs its Rerun
# calls, not its length (live_capacity.py: live / offline 0.47 at 1024, 0.78 at 16384).
MAX_BATCH = 16384
# How long a thread that wants the GIL waits for the one holding it before asking it to let go
# (Python's default is 5 ms). The Zenoh callbacks and a robot's two workers hand messages to
# each other all the time: at 5 ms, a small message waited that long behind a heavy conversion
# running in Python on the robot's other thread.
GIL_SWITCH_INTERVAL_S = 0.0005
HEAVY_NICENESS = 10
"""How much lower a robot's heavy thread runs than the rest of the host (Linux ``nice``, per
thread): the small topics, the Zenoh callbacks and Rerun's threads get a core first when the
heavy one would take it. The issue's mixed load, 3 runs each of benchmarks/live_capacity.py
--only latency --seconds 10, alternated: small-topic p99 10.36/10.34/9.47 ms at the same
priority, 8.74/10.08/7.46 at +10 (p50 unchanged, the heavy topics' own p99 too); at +19 the
clouds' p99 grew from 17 to 45 ms."""
SMALL_TURNS = 2
"""Robots converting their small topics at once. Two: one robot's calls into Rerun and numpy,
which let the GIL go, leave room for another's Python; more threads only share the one GIL.
Against no turns (25 demo robots, benchmarks/fleet.py's fleet phase, two runs each, alternated,
on the shared 2-core machine at load 10-15): 0.38 and 0.49 ms of host CPU per message converted,
against 0.44 and 0.57."""
STALLED_TURN_S = 0.25
"""A turn whose thread has used no CPU for this long stops holding its slot: a robot whose
conversion waits on something that may never come (a mesh fetched from a robot that does not
answer) delays the fleet a glimpse. A turn that converts keeps its slot however long it takes: a
host behind by seconds converts turns of a thousand messages and more, and when such turns also
counted as stalled, every robot converted at once. 25 demo robots over ``--workers 2``
(``swanky-host --demo --robots 25 --workers 2 --no-slam --duration 30``, each batch timed): 13
robots' turns ran together, each using 0.5 s of CPU in 17-20 s of wall time."""
HEAVY_BACKLOG = 32
"""Heavy items waiting, all robots' together, beyond which the host is behind on them and heavy
topics go latest-only: more than arrive during a short stall (a second of one robot's 15 Hz
images and 5 Hz clouds)."""

ItemDeliver = Callable[[Sequence[InputItem]], None]
"""Where the workers put each robot's batches: live records and the MessageRuns of bundles (any
:data:`~host_bridge.inputs.base.Deliver` takes them)."""

LaneOf = Callable[[RawMessage | MessageRun], Lane]


class HostBehindError(HostError):
    """The host dropped messages of a topic: it converts the robot's messages slower than they
    arrive."""


class HeavyTopicsThinnedError(HostBehindError):
    """The host converts only the newest message of heavy topics: said once per host, naming the
    robots and topics thinned when it began."""


class TypeLanes:
    """The lane of a message (or run): its type table row's, remembered per type and topic; the
    table is built on first use unless given."""

    def __init__(self, registry: Registry | None = None) -> None:
        self._registry = registry
        self._known: dict[tuple[str, str], Lane] = {}

    def __call__(self, raw: RawMessage | MessageRun) -> Lane:
        key = (raw.msgtype, raw.topic)
        found = self._known.get(key)
        if found is None:
            if self._registry is None:
                from host_bridge.table.registry import default_registry

                self._registry = default_registry()
            found = self._known[key] = self._registry.row(raw.msgtype, raw.topic).lane
        return found


def _topic(item: InputItem) -> str:
    return item.topic if isinstance(item, RawMessage | MessageRun | InputProblem) else ""


@dataclass(slots=True)
class _Entry:
    item: InputItem
    topic: str
    latched: bool
    size: int
    """Messages it holds: a MessageRun's length, else 1."""
    order: int
    """When it came among its robot's items: the oldest is dropped first."""
    replaceable: tuple[str, str] | None = None
    """The topic and type of a non-latched heavy message (or run), which a newer one of the same
    topic and type may replace (one of another type, garbage, may not)."""


class _Lane:
    """One worker thread's share of a robot's queue: its small topics, or its heavy ones."""

    def __init__(self, lock: threading.Lock, thread_name: str, turns: Turns, *, heavy: bool) -> None:
        self.thread_name = thread_name
        self.turns = turns
        """The robots' turns on this kind of lane (all their small lanes share one, all their
        heavy lanes another)."""
        self.heavy = heavy
        self.items: deque[_Entry] = deque()
        self.messages = 0
        # Heavy lane: the waiting non-latched entries per topic and type (one, but for the
        # moment a newer one comes), so nothing is searched when none waits.
        self.replaceable: dict[tuple[str, str], int] = {}
        self.ready = threading.Condition(lock)
        self.worker: threading.Thread | None = None
        self.dropped: dict[str, int] = {}
        # Topics whose first drop from a full queue has been warned about.
        self.warned: set[str] = set()
        # ``dropped`` as it was when the worker took its current batch.
        self.dropped_taken: dict[str, int] = {}
        self.dropped_since_taken = False
        # Each topic's first drop, to be warned about ahead of the waiting messages.
        self.warnings: list[InputProblem] = []

    def append(self, entry: _Entry) -> None:
        self.items.append(entry)
        self.messages += entry.size
        self.turns.waiting_items += 1
        if entry.replaceable is not None:
            self.replaceable[entry.replaceable] = self.replaceable.get(entry.replaceable, 0) + 1

    def forget(self, entry: _Entry) -> None:
        """``entry`` has left the queue (taken by the worker or dropped)."""
        self.messages -= entry.size
        self.turns.waiting_items -= 1
        if entry.replaceable is not None:
            self.replaceable[entry.replaceable] -= 1

    def oldest_droppable(self) -> int | None:
        """The index of the oldest entry that may be dropped (a non-latched message or run)."""
        for index, entry in enumerate(self.items):
            if not entry.latched and isinstance(entry.item, RawMessage | MessageRun):
                return index
        return None


class _Turn:
    """A lane's turn under way, and when its thread last used CPU (its own CPU clock, read by
    the threads waiting for a slot)."""

    __slots__ = ("_clock", "_cpu_s", "_progress_at")

    def __init__(self) -> None:
        # Where the platform has no per-thread CPU clock, a turn stalls STALLED_TURN_S after it
        # began, as every turn did before.
        self._clock = (
            time.pthread_getcpuclockid(threading.get_ident())
            if hasattr(time, "pthread_getcpuclockid") else None
        )
        self._cpu_s = self._cpu()
        self._progress_at = time.monotonic()

    def _cpu(self) -> float:
        return 0.0 if self._clock is None else time.clock_gettime(self._clock)

    def stalls_at(self, now: float) -> float:
        """When this turn counts as stalled, unless its thread uses CPU before then."""
        cpu_s = self._cpu()
        if cpu_s != self._cpu_s:
            self._cpu_s, self._progress_at = cpu_s, now
        return self._progress_at + STALLED_TURN_S


class Turns:
    """Robots' lanes of one kind take turns: ``slots`` convert at a time, in the order they asked
    (first come, first served), so each robot with messages waiting converts once before any
    converts twice. A turn whose thread uses no CPU for :data:`STALLED_TURN_S` stops holding its
    slot, so a robot whose conversion hangs (a mesh fetched from a robot that does not answer)
    delays the others by that much only. Also counts the items waiting in those lanes, all robots
    together. Used under the queues' lock; only the first in line is woken, never the whole
    fleet."""

    def __init__(self, lock: threading.Lock, slots: int) -> None:
        self.slots = slots
        self.waiting_items = 0
        self._lock = lock
        self._asked: deque[threading.Condition] = deque()
        self._started: dict[_Lane, _Turn] = {}
        """The lanes converting, each taken on its own thread."""

    def take(self, lane: _Lane) -> None:
        """Wait for ``lane``'s turn (the lock held, released while waiting), on its thread."""
        ticket = threading.Condition(self._lock)
        self._asked.append(ticket)
        while True:
            if self._asked[0] is not ticket:
                ticket.wait()
                continue
            now = time.monotonic()
            holding = sorted(stalls_at for stalls_at in
                             (turn.stalls_at(now) for turn in self._started.values())
                             if stalls_at > now)
            if len(holding) < self.slots:
                break
            # Until enough turns stall, unless one is given back first.
            ticket.wait(holding[len(holding) - self.slots] - now)
        self._asked.popleft()
        self._started[lane] = _Turn()
        self._wake_next()  # it may start too

    def give_back(self, lane: _Lane) -> None:
        del self._started[lane]
        self._wake_next()

    def _wake_next(self) -> None:
        if self._asked:
            self._asked[0].notify()


@dataclass(slots=True)
class _RobotLanes:
    """One robot's two lanes (its small topics and its heavy ones) and their counts."""

    small: _Lane
    heavy: _Lane
    arrivals: int = 0
    # Both lanes' drops per topic as counted when each took its current batch: replaced, never
    # changed (read without the lock by the /_stats tap).
    dropped_when_taken: Mapping[str, int] = field(default_factory=dict)

    @property
    def lanes(self) -> tuple[_Lane, _Lane]:
        return self.small, self.heavy

    @property
    def messages(self) -> int:
        return self.small.messages + self.heavy.messages

    @property
    def items(self) -> int:
        return len(self.small.items) + len(self.heavy.items)


def _summed(counts: Iterable[Mapping[str, int]]) -> dict[str, int]:
    total: dict[str, int] = {}
    for count in counts:
        for topic, n in count.items():
            total[topic] = total.get(topic, 0) + n
    return total


@functools.cache
def _tune_for_latency() -> None:
    """Once per process, when live messages start to flow between threads: a short GIL switch
    interval (see :data:`GIL_SWITCH_INTERVAL_S`), and the start-up's objects (modules, type
    stores, the registry) moved out of the garbage collector's sight: they live as long as the
    host, and each full collection walked them all (a 27 ms pause in the live benchmark)."""
    sys.setswitchinterval(min(sys.getswitchinterval(), GIL_SWITCH_INTERVAL_S))
    gc.collect()
    gc.freeze()


def _run_nicer(increment: int) -> None:
    """Lower the calling thread's scheduling priority by ``increment`` (Linux gives each thread
    a nice value of its own); elsewhere, or where it is refused, it runs as it is."""
    if sys.platform != "linux":
        return
    thread = threading.get_native_id()
    try:
        os.setpriority(os.PRIO_PROCESS, thread, os.getpriority(os.PRIO_PROCESS, thread) + increment)
    except OSError as err:
        log.debug("could not lower the priority of thread %s: %s", threading.current_thread().name, err)


class RobotQueues:
    """Bounded per-robot queues, two threads per robot: heavy topics latest-only on their own,
    full queues drop their oldest non-latched message; each drop counted."""

    def __init__(
        self,
        max_per_robot: int = MAX_PER_ROBOT,
        *,
        max_items_per_robot: int = MAX_ITEMS_PER_ROBOT,
        lanes: LaneOf | None = None,
        heavy_backlog: int = HEAVY_BACKLOG,
        small_turns: int = SMALL_TURNS,
    ) -> None:
        self.max_per_robot = max_per_robot
        self.max_items_per_robot = max_items_per_robot
        self.lanes = lanes if lanes is not None else TypeLanes()
        self.heavy_backlog = heavy_backlog
        self.superseded: dict[tuple[str, str], int] = {}
        """Of those, the heavy ones a newer message of their topic replaced."""
        # Data, problems and robots joining or leaving: what --until-idle waits on, so a robot
        # that joins but starts slowly (loading its bag) keeps the host waiting for it.
        self.last_activity = time.monotonic()
        self.error: BaseException | None = None
        self._lock = threading.Lock()
        self._robots: dict[str, _RobotLanes] = {}
        self._small_turns = Turns(self._lock, small_turns)
        self._heavy_turns = Turns(self._lock, 1)
        self._thinning_said = False
        self._handler: ItemDeliver | None = None
        self._closing = False

    def put(self, item: InputItem, latched: bool = False) -> None:
        name, topic = item.robot, _topic(item)
        size = len(item) if isinstance(item, MessageRun) else 1
        message = item if isinstance(item, RawMessage | MessageRun) else None
        type_lane = self.lanes(message) if message is not None else Lane.SMALL
        # Patches of a heavy message (grid updates) go in order with it, and are never replaced.
        replaceable = (
            (topic, message.msgtype) if message is not None and type_lane is Lane.HEAVY and not latched
            else None
        )
        with self._lock:
            robot = self._robots.get(name)
            if robot is None:
                robot = self._robots[name] = _RobotLanes(
                    _Lane(self._lock, f"robot-{name}", self._small_turns, heavy=False),
                    _Lane(self._lock, f"robot-{name}-heavy", self._heavy_turns, heavy=True),
                )
            lane = robot.small if type_lane is Lane.SMALL else robot.heavy
            if (replaceable is not None and self._heavy_turns.waiting_items > self.heavy_backlog
                    and lane.replaceable.get(replaceable)):
                self._supersede(name, lane, replaceable)
            if not self._fits(robot, size) and not self._make_room(name, robot, size) and not latched:
                self._count_drop(name, lane, topic, size)
            else:
                robot.arrivals += 1
                lane.append(_Entry(item, topic, latched, size, robot.arrivals, replaceable))
            self.last_activity = time.monotonic()
            self._start_worker(robot, lane)
            lane.ready.notify()

    def _supersede(self, robot: str, lane: _Lane, replaceable: tuple[str, str]) -> None:
        """Drop the waiting non-latched messages of a heavy topic and type: a newer one has
        come."""
        kept: deque[_Entry] = deque()
        for entry in lane.items:
            if entry.replaceable == replaceable:
                lane.forget(entry)
                self._count_drop(robot, lane, entry.topic, entry.size, superseded=True)
            else:
                kept.append(entry)
        lane.items = kept

    def _fits(self, robot: _RobotLanes, size: int) -> bool:
        """Whether one more item of ``size`` messages fits in ``robot``'s queue."""
        return (robot.messages + size <= self.max_per_robot
                and robot.items < self.max_items_per_robot)

    def _make_room(self, name: str, robot: _RobotLanes, size: int) -> bool:
        """Drop the oldest non-latched messages of a full queue until one more item of ``size``
        messages fits; False if it does not (all that waits is latched), unless the queue is
        empty."""
        while robot.items and not self._fits(robot, size):
            found = [(lane, index) for lane in robot.lanes
                     if (index := lane.oldest_droppable()) is not None]
            if not found:
                return False
            lane, index = min(found, key=lambda at: at[0].items[at[1]].order)
            entry = lane.items[index]
            del lane.items[index]
            lane.forget(entry)
            self._count_drop(name, lane, entry.topic, entry.size)
            lane.ready.notify()  # a lane left with only the warning delivers it
        return True

    def _count_drop(
        self, robot: str, lane: _Lane, topic: str, size: int, superseded: bool = False
    ) -> None:
        # The dispatcher warns (stderr and /_swanky/warnings) once per topic and kind; thinned
        # heavy topics are warned about once per host, however many robots and topics.
        if superseded and not self._thinning_said:
            self._thinning_said = True
            lane.warnings.append(InputProblem(robot, topic, HeavyTopicsThinnedError(
                self._thinning_text(robot, topic))))
        elif not superseded and topic not in lane.warned:
            lane.warned.add(topic)
            lane.warnings.append(InputProblem(robot, topic, HostBehindError(
                "the host converts this robot's messages slower than they arrive; dropping its "
                f"oldest ones (counted in {STATS_ROOT}/{robot}{topic}/host_drops, other robots "
                "unaffected)"
            )))
        lane.dropped[topic] = lane.dropped.get(topic, 0) + size
        lane.dropped_since_taken = True
        if superseded:
            key = (robot, topic)
            self.superseded[key] = self.superseded.get(key, 0) + size

    def _thinning_text(self, robot: str, topic: str) -> str:
        """What the host says once when it first thins heavy topics: the robots and topics with
        heavy messages waiting then, those it thins first."""
        thinned = {robot: {topic}}
        for name, state in self._robots.items():
            for entry in state.heavy.items:
                if entry.replaceable is not None:
                    thinned.setdefault(name, set()).add(entry.topic)
        topics = sorted(set().union(*thinned.values()))
        robots = ", ".join(thinned)
        return (
            "the host converts heavy topics (images, clouds, maps) slower than they arrive: from "
            "now on it converts only the newest message of each, robots taking turns, and every "
            f"message of the small topics (drops counted in {STATS_ROOT}/<robot><topic>/host_drops "
            f"and in the summary at the stop); thinning now {len(thinned)} "
            f"robot{'s' if len(thinned) > 1 else ''} ({robots}): {', '.join(topics)}"
        )

    @property
    def dropped(self) -> dict[tuple[str, str], int]:
        """Messages dropped per (robot, topic), for either reason."""
        with self._lock:
            return {
                (name, topic): count
                for name, robot in self._robots.items()
                for topic, count in _summed(lane.dropped for lane in robot.lanes).items()
            }

    @property
    def waiting(self) -> dict[str, tuple[int, int]]:
        """Messages waiting per robot, of its small topics and of its heavy ones (a host that
        converts slower than they arrive holds them here)."""
        with self._lock:
            return {name: (robot.small.messages, robot.heavy.messages)
                    for name, robot in self._robots.items()}

    def dropped_when_taken(self, robot: str) -> Mapping[str, int]:
        """``robot``'s messages dropped per topic, as counted when the thread of that topic took
        the batch it hands over now: each older than every message of its topic still to be
        handed over after it. Read without the lock on the robot's threads (the /_stats tap);
        never changed once returned."""
        state = self._robots.get(robot)
        return {} if state is None else state.dropped_when_taken

    # -- two worker threads per robot --------------------------------------------------------

    def serve(self, handler: ItemDeliver) -> None:
        """From now on every robot's items go to ``handler`` from that robot's own threads."""
        _tune_for_latency()
        with self._lock:
            self._handler = handler
            for robot in self._robots.values():
                for lane in robot.lanes:
                    if lane.items or lane.warnings:
                        self._start_worker(robot, lane)

    def _start_worker(self, robot: _RobotLanes, lane: _Lane) -> None:
        if self._handler is None or lane.worker is not None:
            return
        lane.worker = threading.Thread(
            target=self._work, args=(robot, lane, self._handler), name=lane.thread_name,
            daemon=True,
        )
        lane.worker.start()

    def _work(self, robot: _RobotLanes, lane: _Lane, handler: ItemDeliver) -> None:
        if lane.heavy:
            _run_nicer(HEAVY_NICENESS)
        while True:
            with self._lock:
                while not lane.items and not lane.warnings and not self._closing:
                    lane.ready.wait()
                if not lane.items and not lane.warnings:
                    return
                # Its batch is taken once its turn comes: all that arrived by then.
                lane.turns.take(lane)
                batch: list[InputItem] = list(lane.warnings)  # a drop leaves items waiting
                lane.warnings.clear()
                taken = 0
                while lane.items and taken < MAX_BATCH:
                    entry = lane.items.popleft()
                    lane.forget(entry)
                    taken += entry.size
                    batch.append(entry.item)
                if lane.dropped_since_taken:
                    lane.dropped_taken = dict(lane.dropped)
                    lane.dropped_since_taken = False
                    robot.dropped_when_taken = _summed(other.dropped_taken for other in robot.lanes)
            try:
                if batch:  # its items may have been dropped while it waited for its turn
                    handler(batch)
            except BaseException as err:  # --strict: the main thread re-raises it
                self.error = err
                return
            finally:
                with self._lock:
                    lane.turns.give_back(lane)

    def close(self, timeout: float = 30.0) -> None:
        """Let the workers finish what is queued (a saved .rrd is then complete)."""
        with self._lock:
            self._closing = True
            lanes = [lane for robot in self._robots.values() for lane in robot.lanes]
            for lane in lanes:
                lane.ready.notify_all()
        deadline = time.monotonic() + timeout
        for lane in lanes:
            if lane.worker is not None:
                lane.worker.join(max(0.0, deadline - time.monotonic()))

    def drop_summary(self) -> str:
        """One line per topic that lost messages here, saying why."""
        lines = []
        dropped = self.dropped
        for key, count in sorted(dropped.items()):
            robot, topic = key
            superseded = self.superseded.get(key, 0)
            reasons = [f"{count - superseded} queue full"] if count > superseded else []
            if superseded:
                reasons.append(f"{superseded} replaced by a newer one while the host was behind")
            lines.append(f"[{robot}] {topic}: {count} dropped ({', '.join(reasons)})")
        return "\n".join(lines)
