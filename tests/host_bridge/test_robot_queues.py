"""Per-robot queues: bounded, drop-oldest for non-latched messages, one worker per robot."""

from __future__ import annotations

import threading
import time

from host_bridge.inputs.queues import InputProblem, QueueItem, RobotEvent, RobotQueues
from robot_relay.wire import RawMessage


def raw(robot: str, topic: str, n: int) -> RawMessage:
    return RawMessage(robot, topic, "std_msgs/msg/Int32", bytes([n]))


def test_full_queue_drops_oldest_non_latched_and_counts() -> None:
    queues = RobotQueues(max_per_robot=3)
    queues.put(raw("a", "/tf_static", 0), latched=True)
    for n in range(1, 6):
        queues.put(raw("a", "/scan", n))
    queues.put(raw("b", "/scan", 9))
    items = queues.drain(wait=0.5)
    a = [i.data[0] for i in items if isinstance(i, RawMessage) and i.robot == "a"]
    assert a == [0, 4, 5]  # the latched one survives, then the newest scans
    assert [i.data[0] for i in items if isinstance(i, RawMessage) and i.robot == "b"] == [9]
    assert queues.dropped == {("a", "/scan"): 3}
    assert "[a] /scan: 3 dropped" in queues.drop_summary()


def test_drain_takes_robots_in_turn() -> None:
    queues = RobotQueues()
    for n in range(4):
        queues.put(raw("a", "/x", n))
    queues.put(raw("b", "/x", 10))
    items = queues.drain(max_items=2, wait=0.5)
    assert sorted(i.robot for i in items) == ["a", "b"]


def test_a_stalled_robot_does_not_stall_the_others() -> None:
    queues = RobotQueues(max_per_robot=50)
    release = threading.Event()
    seen: dict[str, list[int]] = {"slow": [], "fast": []}

    def handle(items: list[QueueItem]) -> None:
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

    def handle(items: list[QueueItem]) -> None:
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
    assert next(i for i in queues.drain(wait=0.5) if isinstance(i, RobotEvent)).text == (
        "robot a joined (rmw_zenoh)"
    )
