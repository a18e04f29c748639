"""Per-robot bounded queues between the Zenoh callbacks and the dispatcher.

Each robot gets its own queue and, once :meth:`RobotQueues.serve` runs, its own worker thread,
so a robot whose messages are slow to convert (or that floods the host) only delays itself:
its queue fills and drops its own oldest messages while the other robots keep flowing. Latched
messages (``/tf_static``, ``/robot_description``, maps) are never the ones dropped: a late copy
of them is all a viewer will ever get.

Heavy topics (the type table's ``heavy`` rows: images, point clouds, maps) go latest-only first:
once more than :data:`HEAVY_BACKLOG` items wait for a robot, its worker is behind, and a new
message of a heavy topic replaces the ones of that topic still waiting. The small topics queued
with them (IMU, TF, scans) then wait for one conversion of each heavy topic, not for a pile of
stale frames, and are themselves dropped only when the whole queue is full. Within a batch the
worker hands over the small topics' messages before the heavy ones (each topic's own order
kept), so they do not wait for the heavy ones that came with them either.

Every message dropped here is counted per topic (:attr:`RobotQueues.dropped`, the drop summary
the host prints when it stops) and shows in ``/_stats/<robot><topic>/host_drops`` (stats.py reads
:meth:`RobotQueues.dropped_when_taken` and keeps these drops out of the wire ``drops``, though
they leave sequence gaps too). A topic's first drop is warned about once, in
``/_swanky/warnings`` as well: the warning leads the robot's next batch, so it shows when the
drops begin, not after the backlog (and takes no message's place in the queue).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING

from host_bridge.errors import HostError
from host_bridge.inputs.base import InputItem, InputProblem
from host_bridge.stats import STATS_ROOT
from robot_relay.wire import RawMessage

if TYPE_CHECKING:
    from host_bridge.registry import Registry

log = logging.getLogger("swanky.host")

MAX_PER_ROBOT = 5000
# A worker takes everything waiting, up to this many, at once: what arrived while it converted one
# batch is the next, so a loaded host converts runs (send_columns) that grow with the load, and
# an idle one converts a message as soon as it comes. A fixed 5 ms wait for more added its whole
# length to the latency of the mixed load (p50 15 ms against 5 ms without;
# benchmarks/live_capacity.py) and converted no more per second when flooded.
MAX_BATCH = 1024
# Items waiting for a robot beyond which its worker is behind and heavy topics go latest-only:
# more than arrive during one conversion while it keeps up (a 40 ms cloud at 400 messages/s).
HEAVY_BACKLOG = 32

ItemDeliver = Callable[[Sequence[InputItem]], None]
"""Where the workers put each robot's runs: live items one record each, never a MessageRun (any
:data:`~host_bridge.inputs.base.Deliver` takes them)."""

# (item, latched, its topic if it is a non-latched message of a heavy topic, else None)
_Entry = tuple[InputItem, bool, str | None]


class HostBehindError(HostError):
    """The host dropped messages of a topic: it converts the robot's messages slower than they
    arrive."""


class HeavyTypes:
    """Whether a message is of a heavy type (its type table row says ``heavy``), remembered per
    type and topic; the table is built on first use unless given."""

    def __init__(self, registry: Registry | None = None) -> None:
        self._registry = registry
        self._known: dict[tuple[str, str], bool] = {}

    def __call__(self, raw: RawMessage) -> bool:
        key = (raw.msgtype, raw.topic)
        heavy = self._known.get(key)
        if heavy is None:
            if self._registry is None:
                from host_bridge.registry import default_registry

                self._registry = default_registry()
            heavy = self._known[key] = self._registry.row(raw.msgtype, raw.topic).heavy
        return heavy


class _RobotQueue:
    def __init__(self, lock: threading.Lock) -> None:
        self.items: deque[_Entry] = deque()
        # Non-latched heavy messages waiting, per topic: most are none, and then nothing is
        # searched when a new one comes.
        self.heavy_waiting: dict[str, int] = {}
        self.ready = threading.Condition(lock)
        self.worker: threading.Thread | None = None
        self.dropped: dict[str, int] = {}
        # ``dropped`` as it was when the worker took its current batch: replaced, never changed.
        self.dropped_when_taken: Mapping[str, int] = {}
        self.dropped_since_taken = False
        # Each topic's first drop, to be warned about ahead of the waiting messages.
        self.warnings: list[InputProblem] = []

    def append(self, entry: _Entry) -> None:
        self.items.append(entry)
        heavy_topic = entry[2]
        if heavy_topic is not None:
            self.heavy_waiting[heavy_topic] = self.heavy_waiting.get(heavy_topic, 0) + 1

    def forget(self, entry: _Entry) -> None:
        """``entry`` has left the queue (taken by the worker or dropped)."""
        heavy_topic = entry[2]
        if heavy_topic is not None:
            self.heavy_waiting[heavy_topic] -= 1


class RobotQueues:
    """Bounded per-robot FIFOs; heavy topics keep only their newest message once a robot's
    worker is behind, full queues drop their oldest non-latched message; each drop counted."""

    def __init__(
        self,
        max_per_robot: int = MAX_PER_ROBOT,
        *,
        heavy: Callable[[RawMessage], bool] | None = None,
        heavy_backlog: int = HEAVY_BACKLOG,
    ) -> None:
        self.max_per_robot = max_per_robot
        self.heavy = heavy if heavy is not None else HeavyTypes()
        self.heavy_backlog = heavy_backlog
        self.superseded: dict[tuple[str, str], int] = {}
        """Of those, the heavy ones a newer message of their topic replaced."""
        # Data, problems and robots joining or leaving: what --until-idle waits on, so a robot
        # that joins but starts slowly (loading its bag) keeps the host waiting for it.
        self.last_activity = time.monotonic()
        self.error: BaseException | None = None
        self._lock = threading.Lock()
        self._any = threading.Condition(self._lock)
        self._robots: dict[str, _RobotQueue] = {}
        self._handler: ItemDeliver | None = None
        self._closing = False

    def put(self, item: InputItem, latched: bool = False) -> None:
        robot = item.robot
        heavy_topic = (
            item.topic if not latched and isinstance(item, RawMessage) and self.heavy(item) else None
        )
        with self._lock:
            state = self._robots.get(robot)
            if state is None:
                state = self._robots[robot] = _RobotQueue(self._lock)
                self._start_worker(robot, state)
            if (heavy_topic is not None and len(state.items) > self.heavy_backlog
                    and state.heavy_waiting.get(heavy_topic)):
                self._supersede(robot, state, heavy_topic)
            full = len(state.items) >= self.max_per_robot
            if full and not self._make_room(robot, state) and not latched:
                self._count_drop(robot, state, item)
            else:
                state.append((item, latched, heavy_topic))
            self.last_activity = time.monotonic()
            state.ready.notify()
            self._any.notify()

    def _supersede(self, robot: str, state: _RobotQueue, topic: str) -> None:
        """Drop the waiting non-latched messages of heavy ``topic``: a newer one has come."""
        kept: deque[_Entry] = deque()
        for entry in state.items:
            if entry[2] == topic:
                state.forget(entry)
                self._count_drop(robot, state, entry[0], superseded=True)
            else:
                kept.append(entry)
        state.items = kept

    def _make_room(self, robot: str, state: _RobotQueue) -> bool:
        """Drop the oldest non-latched message of a full queue; False if all are latched."""
        for index, entry in enumerate(state.items):
            item, latched, _ = entry
            if not latched and isinstance(item, RawMessage):
                del state.items[index]
                state.forget(entry)
                self._count_drop(robot, state, item)
                return True
        return False

    def _count_drop(
        self, robot: str, state: _RobotQueue, item: InputItem, superseded: bool = False
    ) -> None:
        topic = item.topic if isinstance(item, RawMessage | InputProblem) else ""
        if topic not in state.dropped:
            # The dispatcher warns (stderr and /_swanky/warnings) once per topic and kind.
            state.warnings.append(InputProblem(robot, topic, HostBehindError(
                "the host converts this robot's messages slower than they arrive; "
                + ("converting only the newest message of this heavy topic" if superseded
                   else "dropping its oldest ones")
                + f" (counted in {STATS_ROOT}/{robot}{topic}/host_drops, other robots unaffected)"
            )))
        state.dropped[topic] = state.dropped.get(topic, 0) + 1
        state.dropped_since_taken = True
        if superseded:
            key = (robot, topic)
            self.superseded[key] = self.superseded.get(key, 0) + 1

    @property
    def dropped(self) -> dict[tuple[str, str], int]:
        """Messages dropped per (robot, topic), for either reason."""
        with self._lock:
            return {
                (robot, topic): count
                for robot, state in self._robots.items()
                for topic, count in state.dropped.items()
            }

    def dropped_when_taken(self, robot: str) -> Mapping[str, int]:
        """``robot``'s messages dropped per topic, as counted when its worker took the batch it
        hands over now: each older than every message of its topic still to be handed over
        after it. Read without the lock on that worker's thread (the /_stats tap); never changed
        once returned."""
        state = self._robots.get(robot)
        return {} if state is None else state.dropped_when_taken

    # -- one worker thread per robot ---------------------------------------------------------

    def serve(self, handler: ItemDeliver) -> None:
        """From now on every robot's items go to ``handler`` from that robot's own thread."""
        with self._lock:
            self._handler = handler
            for robot, state in self._robots.items():
                self._start_worker(robot, state)

    def _start_worker(self, robot: str, state: _RobotQueue) -> None:
        if self._handler is None or state.worker is not None:
            return
        state.worker = threading.Thread(
            target=self._work, args=(state, self._handler), name=f"robot-{robot}", daemon=True
        )
        state.worker.start()

    def _work(self, state: _RobotQueue, handler: ItemDeliver) -> None:
        while True:
            with self._lock:
                while not state.items and not self._closing:
                    state.ready.wait()
                if not state.items:
                    return
                batch: list[InputItem] = list(state.warnings)  # a drop leaves items waiting
                state.warnings.clear()
                heavy: list[InputItem] = []
                for _ in range(min(len(state.items), MAX_BATCH)):
                    entry = state.items.popleft()
                    state.forget(entry)
                    (batch if entry[2] is None else heavy).append(entry[0])
                if state.dropped_since_taken:
                    state.dropped_when_taken = dict(state.dropped)
                    state.dropped_since_taken = False
                # The dispatcher converts a batch topic by topic anyway; the small topics go
                # first, so they do not wait for the frames and clouds that came with them.
                batch += heavy
            try:
                handler(batch)
            except BaseException as err:  # --strict: the main thread re-raises it
                self.error = err
                return

    def close(self, timeout: float = 30.0) -> None:
        """Let the workers finish what is queued (a saved .rrd is then complete)."""
        with self._lock:
            self._closing = True
            workers = [s.worker for s in self._robots.values() if s.worker is not None]
            for state in self._robots.values():
                state.ready.notify_all()
        deadline = time.monotonic() + timeout
        for worker in workers:
            worker.join(max(0.0, deadline - time.monotonic()))

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
