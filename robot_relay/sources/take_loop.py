"""Raw messages taken from rcl subscriptions in one loop over a wait set, without rclpy's executor.

rclpy's executor pays, for every single message, a new wait set built from every entity of the
node, a timer for the timeout, a generator, a handler, a Task and a coroutine before the callback
runs. :class:`TakeLoop` keeps one wait set, waits on the subscriptions and a guard condition
only, and takes everything a ready subscription holds (up to its queue's depth per turn) with
``take_message`` before it waits again, calling the forwarder directly.

Where the relay's CPU went (benchmarks/relay_cpu.py's small messages, 64 a second; perf with
software clock sampling, py-spy and cProfile of the relay; see that script's docstring for the
figures): with the executor, 82 % of it in the Python threads, half of the executor thread's
busy samples building wait sets and running the Task machinery and the rest publishing to
Zenoh; the Fast DDS receive thread 8 % and Zenoh's transmit thread 9 %. With this loop the
executor's share is gone; what is left per message is the take thread (Python ~30 % of the
relay's CPU, context switches and Zenoh's wake-up of its transmit thread), Zenoh's transmit
thread (~19 %: the TCP send to the host, in the kernel) and Fast DDS's receive thread (~17 %).

It uses rclpy's C extension (``rclpy.impl.implementation_singleton.rclpy_implementation``) the
way rclpy's own executor and ``Node.create_subscription`` do, with calls that are the same in
Humble (rclpy 3) and Jazzy (rclpy 7): ``Subscription(node, type, topic, qos)``,
``WaitSet(subscriptions, guards, timers, clients, services, events, context)``,
``clear_entities``, ``add_subscription``, ``add_guard_condition``, ``wait(ns)``,
``get_ready_entities("subscription")``, ``take_message(type, raw)`` (bytes and a dict of message
info: the timestamps, and from Iron on the sequence numbers), ``GuardCondition(context)``,
``destroy_when_not_in_use``. rclpy is handed in, never imported here: the relay imports it only
when it reads a live graph.

Wake-ups, not messages, are what a small message costs: each turn of the loop wakes the take
thread, waits on rcl again and wakes Zenoh's transmit thread for a write. With small messages at
64 a second, most at their own instant (``benchmarks/relay_cpu.py``), the relay's Python threads
used 11.0 ms of CPU a second and Zenoh's transmit thread 4.2 when every message had its own
turn; 7.9 and 1.8 in the same windows with a budget of 0.05 s (scratch per-thread schedstat of
both relays at once, beside the bare subscriber). So the loop turns at most once per
``latency_budget`` (default :data:`LATENCY_BUDGET_S`): a message that follows a quiet spell
goes at once, one that follows another within the budget waits for the next turn, and what
arrived meanwhile goes together (one wake-up, one Zenoh batch). The next turn comes sooner when,
at the rate a queue filled since the last, it would be more than half full by then (messages a
full queue overwrites are lost, reliable or not): only a topic's first budget can overflow, and
:func:`~robot_relay.sources.qos.live_qos` makes volatile queues deep enough
(:data:`~robot_relay.sources.qos.LIVE_STREAM_FLOOR`) for 1 kHz within the default budget.

Why 0.1 s by default: the host sends a viewer the rows of small topics every 0.2 s at the
soonest (Rerun's own batching period; swanky-host's viewer stream flushes no more often, only
2 MiB of rows, images, go sooner), so a viewer shows a live robot 5 times a second whatever the
relay's budget below that; the budget only adds to the delay, 0.1 s at worst. Against the bare
rclpy subscriber of ``benchmarks/relay_cpu.py`` (small messages, a remote host, 5 windows each
in the same run) the relay's CPU per message was 0.35-0.37 of it with 0.1 s and 0.52-0.55 with
0.05 s: at 64 messages a second most turns carry one or two messages, and each turn costs
wake-ups (this 2-core VM: 70-80 us of the thread's CPU per sleep, about as much for the first
Zenoh put after it).

Threads: subscriptions are created on the caller's thread (the graph thread) and handed over
with :meth:`TakeLoop.add`; :meth:`TakeLoop.remove` asks for one's end. Both take effect at the
loop's next turn (the guard condition wakes it), and only the loop's thread destroys a
subscription, so none is destroyed while rcl waits on it.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from robot_relay.wire import TopicInfo

# Waits end by themselves this often even when nothing arrives: a backstop, since a stop or a
# change triggers the guard condition at once.
WAIT_NS = 1_000_000_000
LATENCY_BUDGET_S = 0.1
"""How long a message may wait for the take loop's next turn, by default (``swanky-relay
--latency-budget``): at most 10 turns a second, 100 ms added at worst to what a viewer shows."""
MAX_LATENCY_BUDGET_S = 1.0
"""The most ``--latency-budget`` (and ``latency_budget:``) accepts: more is surely milliseconds
written as seconds."""
Take = Callable[[bytes, Mapping[str, Any]], None]


@dataclass(eq=False)
class RawSubscription:
    """One raw rcl subscription and where its messages go."""

    handle: Any
    message_type: Any
    forward: Take
    depth: int

    def drain(self) -> float:
        """Take and forward what the subscription holds, at most ``depth`` messages (a topic
        that outruns the relay cannot starve the others); how full its queue was, 0 to 1."""
        for count in range(self.depth):
            taken = self.handle.take_message(self.message_type, True)
            if taken is None:
                return count / self.depth
            self.forward(*taken)
        return 1.0


class TakeLoop:
    """The relay's raw subscriptions, waited on together and drained on one thread (:meth:`run`)."""

    def __init__(self, rclpy_implementation: Any, context_handle: Any,
                 latency_budget: float = LATENCY_BUDGET_S) -> None:
        self._latency_budget = latency_budget
        self._rclpy = rclpy_implementation
        self._context = context_handle
        self._wake = rclpy_implementation.GuardCondition(context_handle)
        self._lock = threading.Lock()
        self._added: list[RawSubscription] = []
        self._removed: list[RawSubscription] = []
        self._subscriptions: dict[int, RawSubscription] = {}
        self._stopped = False
        # Set (under the lock) before the guard condition is triggered, read without it: the loop
        # takes the lock only in the turns after a change, not once per message.
        self._changed = False

    def subscribe(self, node_handle: Any, message_type: Any, info: TopicInfo, qos: Any,
                  forward: Take) -> RawSubscription:
        """A raw subscription of ``info.topic`` with rclpy's ``qos`` profile, handed to the loop."""
        handle = self._rclpy.Subscription(node_handle, message_type, info.topic,
                                          qos.get_c_qos_profile())
        subscription = RawSubscription(handle, message_type, forward, max(info.qos.depth, 1))
        with self._lock:
            self._added.append(subscription)
            self._changed = True
        self._wake.trigger_guard_condition()
        return subscription

    def remove(self, subscription: RawSubscription) -> None:
        with self._lock:
            self._removed.append(subscription)
            self._changed = True
        self._wake.trigger_guard_condition()

    def stop(self) -> None:
        """End :meth:`run` at its next turn (at once: the guard condition wakes it)."""
        with self._lock:
            self._stopped = True
            self._changed = True
        self._wake.trigger_guard_condition()

    def _apply_changes(self) -> bool:
        """Take in the subscriptions added and destroy the ones removed; False once stopped."""
        with self._lock:
            added, self._added = self._added, []
            removed, self._removed = self._removed, []
            stopped = self._stopped
            self._changed = False
        for subscription in added:
            self._subscriptions[subscription.handle.pointer] = subscription
        for subscription in removed:
            self._subscriptions.pop(subscription.handle.pointer, None)
            subscription.handle.destroy_when_not_in_use()
        return not stopped

    def run(self) -> None:
        """Wait, drain what is ready, and again, until :meth:`stop`."""
        wait_set = None
        try:
            while self._apply_changes():
                if wait_set is not None:
                    wait_set.destroy_when_not_in_use()
                wait_set = self._rclpy.WaitSet(len(self._subscriptions), 1, 0, 0, 0, 0, self._context)
                self._take_until_changed(wait_set)
        finally:
            if wait_set is not None:
                wait_set.destroy_when_not_in_use()

    def _take_until_changed(self, wait_set: Any) -> None:
        """The loop's turns while its subscriptions stay the same, with everything a turn needs
        bound once: a turn costs its rcl wait and takes, little Python besides."""
        handles = [subscription.handle for subscription in self._subscriptions.values()]
        subscriptions = self._subscriptions
        clear, add, add_guard = (wait_set.clear_entities, wait_set.add_subscription,
                                 wait_set.add_guard_condition)
        wait, ready = wait_set.wait, wait_set.get_ready_entities
        wake = self._wake
        budget = interval = self._latency_budget
        monotonic, sleep = time.monotonic, time.sleep
        drained_at = -math.inf  # no message yet: the first goes at once
        while not self._changed:
            if interval > 0.0:
                pause = drained_at + interval - monotonic()
                if pause > 0.0:
                    sleep(pause)
            clear()
            for handle in handles:
                add(handle)
            add_guard(wake)
            wait(WAIT_NS)
            fullest = 0.0
            for pointer in ready("subscription"):
                fullest = max(fullest, subscriptions[pointer].drain())
            if fullest > 0.0:  # else a wait that timed out: the next message goes at once
                now = monotonic()
                # The next turn when the fastest-filling queue, at the rate it filled since the
                # last drain, would be half full: a whole budget may overflow a fast topic's.
                interval = min(budget, (now - drained_at) * 0.5 / fullest)
                drained_at = now

    def close(self) -> None:
        """Once :meth:`run` has returned (or never ran): destroy every subscription and the guard
        condition."""
        self._apply_changes()
        for subscription in self._subscriptions.values():
            subscription.handle.destroy_when_not_in_use()
        self._subscriptions.clear()
        self._wake.destroy_when_not_in_use()
