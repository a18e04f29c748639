"""Per-robot queues: bounded, drop-oldest for non-latched messages, heavy topics latest-only once
behind, one worker per robot."""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from pathlib import Path

from host_bridge.destinations import SinkOptions
from host_bridge.dispatch import WARNINGS_PATH, Dispatcher
from host_bridge.inputs.base import InputItem, InputProblem, RobotEvent
from host_bridge.inputs.queues import HeavyTypes, HostBehindError, RobotQueues
from host_bridge.sink import RerunSink
from host_bridge.stats import StatsTracker, topic_stats_items
from robot_relay.wire import RawMessage
from tests.host_bridge.inputs.received import Received
from tests.rrd import entity_rows


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
    items = received.wait_for(lambda items: len(items) == 5)
    queues.close(timeout=5)
    a = [i.data[0] for i in items if isinstance(i, RawMessage) and i.robot == "a"]
    assert a == [0, 4, 5]  # the latched one survives, then the newest scans
    assert [(i.robot, i.topic) for i in items if isinstance(i, InputProblem)] == [("a", "/scan")]
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



IMAGE, CLOUD, IMU = "sensor_msgs/msg/Image", "sensor_msgs/msg/PointCloud2", "sensor_msgs/msg/Imu"
GRID = "nav_msgs/msg/OccupancyGrid"


def typed(robot: str, topic: str, msgtype: str, n: int) -> RawMessage:
    """Message ``n`` of ``topic``: its payload byte, and its wire sequence number."""
    return RawMessage(robot, topic, msgtype, bytes([n]), receive_ns=T0 + n * MS, sequence=n)


S, MS = 10**9, 10**6
T0 = 1_700_000_000 * S


def delivered(queues: RobotQueues, count: int) -> dict[str, list[tuple[str, int]]]:
    """Serve the filled queues; per robot, (topic, payload byte) of the ``count`` messages
    delivered, in order (robots are served on threads of their own, so only each robot's order
    is defined). The warnings of first drops are left out (see
    test_a_topics_first_drop_is_warned_about_once_ahead_of_the_backlog)."""
    received = Received()
    queues.serve(received.take)
    items = received.wait_for(
        lambda items: sum(isinstance(i, RawMessage) for i in items) >= count
    )
    queues.close(timeout=5)
    by_robot: dict[str, list[tuple[str, int]]] = {}
    for item in items:
        if isinstance(item, InputProblem):
            assert isinstance(item.error, HostBehindError)
            continue
        assert isinstance(item, RawMessage)
        by_robot.setdefault(item.robot, []).append((item.topic, item.data[0]))
    return by_robot


def test_heavy_types_come_from_the_type_table() -> None:
    heavy = HeavyTypes()
    types = (IMAGE, CLOUD, GRID, IMU, "std_msgs/msg/Int32", "sensor_msgs/msg/CompressedImage")
    assert [heavy(typed("a", "/t", t, 0)) for t in types] == [True, True, True, False, False, False]


def test_behind_a_backlog_heavy_topics_keep_only_their_newest_and_small_ones_all_wait() -> None:
    queues = RobotQueues(heavy_backlog=3)  # heavy: the type table's rows (Image, PointCloud2)
    queues.put(typed("a", "/camera", IMAGE, 100))  # not behind: queued
    for n in range(3):
        queues.put(typed("a", "/imu", IMU, n))
    queues.put(typed("a", "/camera", IMAGE, 101))  # 4 waiting > 3: replaces 100
    queues.put(typed("a", "/points", CLOUD, 200))  # no cloud waiting: queued
    queues.put(typed("a", "/imu", IMU, 3))
    queues.put(typed("a", "/camera", IMAGE, 102))  # replaces 101
    queues.put(typed("a", "/points", CLOUD, 201))  # replaces 200
    queues.put(typed("a", "/imu", IMU, 4))
    queues.put(typed("b", "/camera", IMAGE, 150))  # another robot, with no backlog of its own
    queues.put(typed("b", "/camera", IMAGE, 151))
    assert delivered(queues, 9) == {
        "a": [("/imu", 0), ("/imu", 1), ("/imu", 2), ("/imu", 3), ("/imu", 4), ("/camera", 102),
              ("/points", 201)],  # one batch: the small topics first
        "b": [("/camera", 150), ("/camera", 151)],
    }
    assert queues.dropped == {("a", "/camera"): 2, ("a", "/points"): 1}
    assert queues.superseded == queues.dropped
    assert queues.drop_summary() == (
        "[a] /camera: 2 dropped (2 replaced by a newer one while the host was behind)\n"
        "[a] /points: 1 dropped (1 replaced by a newer one while the host was behind)"
    )


def test_once_behind_one_heavy_message_replaces_all_its_topic_had_waiting() -> None:
    queues = RobotQueues(heavy_backlog=3)
    for n in range(4):  # 0, 1, 2 and 3 each come with at most 3 waiting: all queued
        queues.put(typed("a", "/camera", IMAGE, n))
    queues.put(typed("a", "/camera", IMAGE, 4))
    assert delivered(queues, 1) == {"a": [("/camera", 4)]}
    assert queues.dropped == {("a", "/camera"): 4}


def test_latched_heavy_messages_are_never_replaced() -> None:
    queues = RobotQueues(heavy_backlog=1)
    for n in range(3):
        queues.put(typed("a", "/map", GRID, n), latched=True)
    queues.put(typed("a", "/camera", IMAGE, 10))
    queues.put(typed("a", "/camera", IMAGE, 11))
    assert delivered(queues, 4) == {
        "a": [("/map", 0), ("/map", 1), ("/map", 2), ("/camera", 11)]
    }
    assert queues.dropped == {("a", "/camera"): 1}


def test_a_full_queue_and_replacement_count_each_drop_once() -> None:
    queues = RobotQueues(max_per_robot=4, heavy_backlog=2)
    queues.put(typed("a", "/camera", IMAGE, 0))
    for n in range(1, 5):  # the fourth small one finds the queue full: the image goes
        queues.put(typed("a", "/imu", IMU, n))
    queues.put(typed("a", "/camera", IMAGE, 5))  # full: /imu 1 goes; no image waits to replace
    queues.put(typed("a", "/camera", IMAGE, 6))  # behind: replaces 5, which makes the room
    assert delivered(queues, 4) == {"a": [("/imu", 2), ("/imu", 3), ("/imu", 4), ("/camera", 6)]}
    assert queues.dropped == {("a", "/camera"): 2, ("a", "/imu"): 1}
    assert queues.superseded == {("a", "/camera"): 1}
    assert queues.drop_summary() == (
        "[a] /camera: 2 dropped (1 queue full, 1 replaced by a newer one while the host was behind)\n"
        "[a] /imu: 1 dropped (1 queue full)"
    )


def test_messages_dropped_here_are_host_drops_in_stats_not_link_drops() -> None:
    queues = RobotQueues(heavy_backlog=2)
    tracker = StatsTracker(host_dropped=queues.dropped_when_taken)
    first_taken, release = threading.Event(), threading.Event()
    warned: list[str] = []

    def handle(batch: Sequence[InputItem]) -> None:  # as the dispatcher and its /_stats tap do
        warned.extend(i.topic for i in batch if isinstance(i, InputProblem))
        assert tracker.observe_batch(
            [i for i in batch if isinstance(i, RawMessage)], host_ns=T0 + 500 * MS) == []
        first_taken.set()
        release.wait(20)  # the first batch converts slowly: a backlog builds up behind it

    queues.put(typed("a", "/camera", IMAGE, 0))
    queues.serve(handle)
    assert first_taken.wait(20)
    for n in range(3):
        queues.put(typed("a", "/imu", IMU, n))
    for n in range(1, 5):  # 1 queued, then 2, 3 and 4 each replace the one before
        queues.put(typed("a", "/camera", IMAGE, n))
    release.set()
    queues.close(timeout=10)
    assert queues.dropped == {("a", "/camera"): 3}
    assert warned == ["/camera"]
    next_second = RawMessage("a", "/imu", IMU, b"\0", receive_ns=T0 + S, sequence=3)
    closed = {s.topic: s for s in tracker.observe_batch([next_second], host_ns=T0 + S)}
    # /camera 1, 2 and 3 left a sequence gap before 4; the host dropped them, the link did not.
    assert (closed["/camera"].rate_hz, closed["/camera"].drops, closed["/camera"].host_drops) == (
        2.0, 0, 3)
    assert (closed["/imu"].rate_hz, closed["/imu"].drops, closed["/imu"].host_drops) == (3.0, 0, 0)
    paths = [item.path for item in topic_stats_items(list(closed.values()))]
    assert [p for p in paths if "drops" in p] == [
        "/_stats/a/camera/drops", "/_stats/a/camera/host_drops",
        "/_stats/a/imu/drops", "/_stats/a/imu/host_drops",
    ]
    assert tracker.host_drops_at_stop() == []  # all in the closed period


def test_a_topics_first_drop_is_warned_about_once_ahead_of_the_backlog(tmp_path: Path) -> None:
    queues = RobotQueues(max_per_robot=3)
    for n in range(1, 7):  # 4 makes room by dropping 1, 5 drops 2, 6 drops 3
        queues.put(raw("a", "/scan", n))
    received = Received()
    queues.serve(received.take)
    items = received.wait_for(lambda items: len(items) == 4)
    queues.close(timeout=5)
    warning, *scans = items  # the warning takes no message's place
    assert [i.data[0] for i in scans if isinstance(i, RawMessage)] == [4, 5, 6]
    assert queues.dropped == {("a", "/scan"): 3}
    assert isinstance(warning, InputProblem)
    assert (warning.robot, warning.topic) == ("a", "/scan")
    expected = (
        "[a] /scan: the host converts this robot's messages slower than they arrive; dropping "
        "its oldest ones (counted in /_stats/a/scan/host_drops, other robots unaffected) "
        "(further HostBehindErrors on this topic are counted, not shown)"
    )
    out = tmp_path / "warned.rrd"
    sink = RerunSink(SinkOptions(save=out))
    Dispatcher(sink).take([warning])
    sink.close()
    assert [row["TextLog:text"] for row in entity_rows(out)[WARNINGS_PATH]] == [[expected]]


def test_in_a_batch_small_topics_go_before_heavy_ones_each_in_its_order() -> None:
    queues = RobotQueues()
    queues.put(typed("a", "/points", CLOUD, 0))
    queues.put(typed("a", "/imu", IMU, 1))
    queues.put(typed("a", "/camera", IMAGE, 2))
    queues.put(typed("a", "/map", GRID, 3), latched=True)  # latched: never held back
    queues.put(typed("a", "/imu", IMU, 4))
    queues.put(typed("a", "/points", CLOUD, 5))
    assert delivered(queues, 6) == {"a": [
        ("/imu", 1), ("/map", 3), ("/imu", 4), ("/points", 0), ("/camera", 2), ("/points", 5)
    ]}
    assert queues.dropped == {}
