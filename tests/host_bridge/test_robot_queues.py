"""Per-robot queues: bounded, drop-oldest for non-latched messages, one worker per robot."""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence

from host_bridge.inputs.base import InputItem, InputProblem, RobotEvent
from host_bridge.inputs.queues import RobotQueues
from robot_relay.wire import RawMessage
from tests.host_bridge.inputs.received import Received


def raw(robot: str, topic: str, n: int) -> RawMessage:
    return RawMessage(robot, topic, "std_msgs/msg/Int32", bytes([n]))


def test_full_queue_drops_oldest_non_latched_and_counts() -> None:
    queues = RobotQueues(max_per_robot=3)
    queues.put(raw("a", "/tf_static", 0), latched=True)
    for n in range(1, 6):
        queues.put(raw("a", "/scan", n))
    queues.put(raw("b", "/scan", 9))
    received = Received()
    queues.serve(received.take)  # the workers start only now: the queues are full
    items = received.wait_for(lambda items: len(items) == 4)
    queues.close(timeout=5)
    a = [i.data[0] for i in items if isinstance(i, RawMessage) and i.robot == "a"]
    assert a == [0, 4, 5]  # the latched one survives, then the newest scans
    assert [i.data[0] for i in items if isinstance(i, RawMessage) and i.robot == "b"] == [9]
    assert queues.dropped == {("a", "/scan"): 3}
    assert "[a] /scan: 3 dropped" in queues.drop_summary()


def test_each_robot_is_served_on_its_own_thread() -> None:
    queues = RobotQueues()
    for n in range(4):
        queues.put(raw("a", "/x", n))
    queues.put(raw("b", "/x", 10))
    threads: dict[str, set[str]] = {}

    def take(items: Sequence[InputItem]) -> None:
        for item in items:
            threads.setdefault(item.robot, set()).add(threading.current_thread().name)

    queues.serve(take)
    queues.close(timeout=5)
    assert sorted(threads) == ["a", "b"]
    assert threads == {"a": {"robot-a"}, "b": {"robot-b"}}


def test_a_stalled_robot_does_not_stall_the_others() -> None:
    queues = RobotQueues(max_per_robot=50)
    release = threading.Event()
    seen: dict[str, list[int]] = {"slow": [], "fast": []}

    def handle(items: Sequence[InputItem]) -> None:
        for item in items:
            if isinstance(item, RawMessage):
                if item.robot == "slow":
                    release.wait(10)
                seen[item.robot].append(item.data[0])

    queues.serve(handle)
    for n in range(200):
        queues.put(raw("slow", "/scan", n))
    for n in range(30):
        queues.put(raw("fast", "/scan", n))
    deadline = time.monotonic() + 10
    while len(seen["fast"]) < 30 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert seen["fast"] == list(range(30))
    assert seen["slow"] == []
    release.set()
    queues.close(timeout=10)
    # The stalled robot lost its oldest scans (bounded queue), kept the newest, in order.
    assert seen["slow"] == sorted(seen["slow"])
    assert seen["slow"][-1] == 199
    assert queues.dropped[("slow", "/scan")] == 200 - len(seen["slow"]) > 0
    assert ("fast", "/scan") not in queues.dropped


def test_worker_error_is_kept_for_the_main_thread() -> None:
    queues = RobotQueues()

    def handle(items: Sequence[InputItem]) -> None:
        raise ValueError("strict")

    queues.serve(handle)
    queues.put(InputProblem("a", "/x", ValueError("bad")))
    queues.close(timeout=5)
    assert isinstance(queues.error, ValueError)


def test_robot_events_count_as_activity() -> None:
    queues = RobotQueues()
    before = queues.last_activity
    time.sleep(0.01)
    queues.put(RobotEvent("a", True, "rmw_zenoh"))
    assert queues.last_activity > before
    received = Received()
    queues.serve(received.take)
    items = received.wait_for(lambda items: len(items) == 1)
    queues.close(timeout=5)
    assert next(i for i in items if isinstance(i, RobotEvent)).text == (
        "robot a joined (rmw_zenoh)"
    )
