"""Per-robot bounded queues between the Zenoh callbacks and the dispatcher.

Each robot gets its own queue and, once :meth:`RobotQueues.serve` runs, its own worker thread,
so a robot whose messages are slow to convert (or that floods the host) only delays itself:
its queue fills and drops its own oldest messages while the other robots keep flowing. Latched
messages (``/tf_static``, ``/robot_description``, maps) are never the ones dropped: a late copy
of them is all a viewer will ever get.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque

from host_bridge.inputs.base import Deliver, InputItem, InputProblem
from robot_relay.wire import RawMessage

log = logging.getLogger("swanky.host")

MAX_PER_ROBOT = 5000
MAX_BATCH = 1024
# A worker that wakes for one message waits this long for more, so high-rate topics reach the
# converters as runs (send_columns) instead of one call per message.
GATHER_S = 0.005


class _RobotQueue:
    def __init__(self, lock: threading.Lock) -> None:
        self.items: deque[tuple[InputItem, bool]] = deque()
        self.ready = threading.Condition(lock)
        self.worker: threading.Thread | None = None


class RobotQueues:
    """Bounded per-robot FIFOs; full queues drop their oldest non-latched message, counted."""

    def __init__(self, max_per_robot: int = MAX_PER_ROBOT) -> None:
        self.max_per_robot = max_per_robot
        self.dropped: dict[tuple[str, str], int] = {}
        # Data, problems and robots joining or leaving: what --until-idle waits on, so a robot
        # that joins but starts slowly (loading its bag) keeps the host waiting for it.
        self.last_activity = time.monotonic()
        self.error: BaseException | None = None
        self._lock = threading.Lock()
        self._any = threading.Condition(self._lock)
        self._robots: dict[str, _RobotQueue] = {}
        self._handler: Deliver | None = None
        self._closing = False

    def put(self, item: InputItem, latched: bool = False) -> None:
        robot = item.robot
        with self._lock:
            state = self._robots.get(robot)
            if state is None:
                state = self._robots[robot] = _RobotQueue(self._lock)
                self._start_worker(robot, state)
            full = len(state.items) >= self.max_per_robot
            if full and not self._make_room(robot, state) and not latched:
                self._count_drop(robot, item)
                return
            state.items.append((item, latched))
            self.last_activity = time.monotonic()
            state.ready.notify()
            self._any.notify()

    def _make_room(self, robot: str, state: _RobotQueue) -> bool:
        """Drop the oldest non-latched message of a full queue; False if all are latched."""
        for index, (item, latched) in enumerate(state.items):
            if not latched and isinstance(item, RawMessage):
                del state.items[index]
                self._count_drop(robot, item)
                return True
        return False

    def _count_drop(self, robot: str, item: InputItem) -> None:
        topic = item.topic if isinstance(item, RawMessage | InputProblem) else ""
        key = (robot, topic)
        if key not in self.dropped:
            log.warning(
                "[%s] %s: the host converts this robot's messages slower than they arrive; "
                "dropping its oldest ones (counted, other robots unaffected)", robot, topic,
            )
        self.dropped[key] = self.dropped.get(key, 0) + 1

    # -- one worker thread per robot ---------------------------------------------------------

    def serve(self, handler: Deliver) -> None:
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

    def _work(self, state: _RobotQueue, handler: Deliver) -> None:
        while True:
            with self._lock:
                while not state.items and not self._closing:
                    state.ready.wait()
                if not state.items:
                    return
                wait_for_more = len(state.items) < MAX_BATCH and not self._closing
            if wait_for_more:
                time.sleep(GATHER_S)
            with self._lock:
                count = min(len(state.items), MAX_BATCH)
                batch = [state.items.popleft()[0] for _ in range(count)]
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
        return "\n".join(
            f"[{robot}] {topic}: {count} dropped (queue full)"
            for (robot, topic), count in sorted(self.dropped.items())
        )
