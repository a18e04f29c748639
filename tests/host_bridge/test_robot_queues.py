"""Per-robot queues: bounded (in messages, a MessageRun counting its own), drop-oldest for
non-latched messages, heavy topics latest-only on a thread of their own, small topics on another
per robot."""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import pytest

import host_bridge.inputs.queues as queues_module
from host_bridge.core.contract import WARNINGS_PATH
from host_bridge.core.destinations import SinkOptions
from host_bridge.inputs.base import InputItem, InputProblem, MessageRun, RobotEvent
from host_bridge.inputs.queues import (
    GIL_SWITCH_INTERVAL_S,
    HEAVY_NICENESS,
    HeavyTopicsThinnedError,
    HostBehindError,
    RobotQueues,
    TypeLanes,
)
from host_bridge.outputs.sink import RerunSink
from host_bridge.outputs.stats import StatsTracker, topic_stats_items
from host_bridge.pipeline.dispatch import Dispatcher
from host_bridge.table.registry import Lane
from robot_relay.wire import RawMessage
from tests.host_bridge.inputs.received import TIMEOUT_S, Received
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
GRID, TF = "nav_msgs/msg/OccupancyGrid", "tf2_msgs/msg/TFMessage"
GRID_UPDATE = "map_msgs/msg/OccupancyGridUpdate"
SCAN = "sensor_msgs/msg/LaserScan"


def typed(robot: str, topic: str, msgtype: str, n: int) -> RawMessage:
    """Message ``n`` of ``topic``: its payload byte, and its wire sequence number."""
    return RawMessage(robot, topic, msgtype, bytes([n]), receive_ns=T0 + n * MS, sequence=n)


def run_of(robot: str, topic: str, msgtype: str, numbers: Sequence[int]) -> MessageRun:
    """A bundle of ``topic``'s messages ``numbers`` (payload bytes), as a live input puts it."""
    return MessageRun(
        robot, topic, msgtype, None, [bytes([n]) for n in numbers],
        receive_ns=np.array([T0 + n * MS for n in numbers], np.int64),
    )


S, MS = 10**9, 10**6
T0 = 1_700_000_000 * S


class ByThread:
    """Batches as the workers hand them over, each item with the thread that handed it."""

    def __init__(self) -> None:
        self.items: list[tuple[str, InputItem]] = []
        self._changed = threading.Condition()

    def take(self, batch: Sequence[InputItem]) -> None:
        name = threading.current_thread().name
        with self._changed:
            self.items.extend((name, item) for item in batch)
            self._changed.notify_all()

    def wait_for(
        self, done: Callable[[list[tuple[str, InputItem]]], bool]
    ) -> list[tuple[str, InputItem]]:
        with self._changed:
            self._changed.wait_for(lambda: done(self.items), TIMEOUT_S)
            return list(self.items)

    def messages(self, count: int) -> dict[str, list[tuple[str, int]]]:
        """Per thread, (topic, payload byte) of the first ``count`` messages handed over (a
        MessageRun's each), in order; the warnings of first drops are left out (see
        test_a_topics_first_drop_is_warned_about_once_ahead_of_the_backlog)."""

        def numbers(items: list[tuple[str, InputItem]]) -> int:
            return sum(len(i) if isinstance(i, MessageRun) else isinstance(i, RawMessage)
                       for _, i in items)

        found: dict[str, list[tuple[str, int]]] = {}
        for name, item in self.wait_for(lambda items: numbers(items) >= count):
            if isinstance(item, InputProblem):
                assert isinstance(item.error, HostBehindError)
                continue
            assert isinstance(item, RawMessage | MessageRun)
            runs = item if isinstance(item, MessageRun) else [item]
            found.setdefault(name, []).extend((raw.topic, raw.data[0]) for raw in runs)
        return found


def delivered(queues: RobotQueues, count: int) -> dict[str, list[tuple[str, int]]]:
    """Serve the filled queues; per worker thread, (topic, payload byte) of the ``count``
    messages delivered, in order (each thread's order is defined, not the order between
    threads)."""
    by_thread = ByThread()
    queues.serve(by_thread.take)
    found = by_thread.messages(count)
    queues.close(timeout=5)
    return found


def test_lanes_come_from_the_type_table() -> None:
    lanes = TypeLanes()
    types = (IMAGE, CLOUD, GRID, GRID_UPDATE, IMU, "std_msgs/msg/Int32", "sensor_msgs/msg/CompressedImage")
    assert [lanes(typed("a", "/t", t, 0)) for t in types] == [
        Lane.HEAVY, Lane.HEAVY, Lane.HEAVY, Lane.PATCH, Lane.SMALL, Lane.SMALL, Lane.SMALL,
    ]
    assert lanes(run_of("a", "/t", CLOUD, [0, 1])) is Lane.HEAVY
    assert lanes(run_of("a", "/t", IMU, [0])) is Lane.SMALL


def test_heavy_topics_go_to_a_thread_of_their_own_keeping_only_their_newest() -> None:
    # Heavy: the type table's rows (Image, PointCloud2); behind as soon as one waits.
    queues = RobotQueues(heavy_backlog=0)
    queues.put(typed("a", "/camera", IMAGE, 100))
    for n in range(3):
        queues.put(typed("a", "/imu", IMU, n))
    queues.put(typed("a", "/camera", IMAGE, 101))  # its thread is busy (not started): replaces 100
    queues.put(typed("a", "/points", CLOUD, 200))  # no cloud waiting: queued
    queues.put(typed("a", "/imu", IMU, 3))
    queues.put(typed("a", "/camera", IMAGE, 102))  # replaces 101
    queues.put(typed("a", "/points", CLOUD, 201))  # replaces 200
    queues.put(typed("a", "/imu", IMU, 4))
    queues.put(typed("b", "/camera", IMAGE, 150))  # another robot's own
    assert queues.waiting == {"a": (5, 2), "b": (0, 1)}  # (small, heavy), the replaced ones gone
    assert delivered(queues, 8) == {
        "robot-a": [("/imu", 0), ("/imu", 1), ("/imu", 2), ("/imu", 3), ("/imu", 4)],
        "robot-a-heavy": [("/camera", 102), ("/points", 201)],
        "robot-b-heavy": [("/camera", 150)],
    }
    assert queues.dropped == {("a", "/camera"): 2, ("a", "/points"): 1}
    assert queues.superseded == queues.dropped
    assert queues.drop_summary() == (
        "[a] /camera: 2 dropped (2 replaced by a newer one while the host was behind)\n"
        "[a] /points: 1 dropped (1 replaced by a newer one while the host was behind)"
    )


@pytest.mark.skipif(sys.platform != "linux", reason="threads have nice values of their own on Linux")
def test_the_heavy_thread_runs_at_a_lower_priority_than_the_small_topics() -> None:
    queues = RobotQueues()
    niceness: dict[str, int] = {}

    def take(items: Sequence[InputItem]) -> None:
        niceness[threading.current_thread().name] = os.getpriority(
            os.PRIO_PROCESS, threading.get_native_id())

    queues.put(typed("a", "/camera", IMAGE, 100))
    queues.put(typed("a", "/imu", IMU, 0))
    queues.serve(take)
    deadline = time.monotonic() + TIMEOUT_S
    while len(niceness) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    queues.close(timeout=5)
    ours = os.getpriority(os.PRIO_PROCESS, 0)
    assert niceness == {"robot-a": ours, "robot-a-heavy": min(ours + HEAVY_NICENESS, 19)}


def test_heavy_topics_go_latest_only_once_behind_and_grid_patches_follow_their_grid() -> None:
    queues = RobotQueues(heavy_backlog=3)
    for n in range(3):  # a short stall: every frame is kept
        queues.put(typed("a", "/camera", IMAGE, n))
    queues.put(typed("a", "/map", GRID, 10))
    queues.put(typed("a", "/map_updates", GRID_UPDATE, 11))
    queues.put(typed("a", "/camera", IMAGE, 3))  # 5 wait: behind, replaces 0-2
    queues.put(typed("a", "/map_updates", GRID_UPDATE, 12))  # a patch: never replaced
    queues.put(typed("a", "/map", GRID, 13))  # 4 wait: behind, replaces 10, not the patches
    queues.put(typed("a", "/map_updates", GRID_UPDATE, 14))
    assert delivered(queues, 5) == {"robot-a-heavy": [
        ("/map_updates", 11), ("/camera", 3), ("/map_updates", 12), ("/map", 13),
        ("/map_updates", 14)]}
    assert queues.dropped == {("a", "/camera"): 3, ("a", "/map"): 1}


def test_small_topics_never_wait_for_a_heavy_conversion() -> None:
    queues = RobotQueues(heavy_backlog=0)
    converting, release = threading.Event(), threading.Event()
    small: list[int] = []
    heavy: list[int] = []

    def handle(batch: Sequence[InputItem]) -> None:
        for item in batch:
            if not isinstance(item, RawMessage):
                continue  # the warning of /points' first drop
            if item.msgtype == CLOUD:
                converting.set()
                release.wait(20)  # a cloud that takes long to convert
                heavy.append(item.data[0])
            else:
                small.append(item.data[0])

    queues.serve(handle)
    queues.put(typed("a", "/points", CLOUD, 0))
    assert converting.wait(20)
    for n in range(1, 6):
        queues.put(typed("a", "/imu", IMU, n))
        queues.put(typed("a", "/points", CLOUD, 100 + n))  # each replaces the one before
    deadline = time.monotonic() + 20
    while len(small) < 5 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert small == [1, 2, 3, 4, 5]
    assert heavy == []  # still converting cloud 0
    release.set()
    queues.close(timeout=10)
    assert heavy == [0, 105]
    assert queues.dropped == {("a", "/points"): 4}
    assert queues.error is None


def test_latched_heavy_messages_are_never_replaced() -> None:
    queues = RobotQueues(heavy_backlog=0)
    for n in range(3):
        queues.put(typed("a", "/map", GRID, n), latched=True)
    queues.put(typed("a", "/camera", IMAGE, 10))
    queues.put(typed("a", "/camera", IMAGE, 11))
    assert delivered(queues, 4) == {
        "robot-a-heavy": [("/map", 0), ("/map", 1), ("/map", 2), ("/camera", 11)]
    }
    assert queues.dropped == {("a", "/camera"): 1}


def test_a_message_of_another_type_neither_replaces_nor_moves_a_topics_messages() -> None:
    """Garbage on a robot's keys: a cloud claimed on /camera does not replace the image waiting
    there, and an image claimed on /scan takes the scans to neither the heavy thread nor
    latest-only; each message's own type decides."""
    queues = RobotQueues(heavy_backlog=0)
    queues.put(typed("a", "/camera", IMAGE, 0))
    queues.put(typed("a", "/camera", CLOUD, 1))  # another type: both wait
    queues.put(typed("a", "/camera", IMAGE, 2))  # replaces image 0 only
    queues.put(typed("a", "/scan", IMAGE, 10))
    for n in range(11, 14):
        queues.put(typed("a", "/scan", SCAN, n))
    queues.put(typed("a", "/scan", IMAGE, 14))  # replaces image 10 only
    assert delivered(queues, 6) == {
        "robot-a": [("/scan", 11), ("/scan", 12), ("/scan", 13)],
        "robot-a-heavy": [("/camera", 1), ("/camera", 2), ("/scan", 14)],
    }
    assert queues.dropped == {("a", "/camera"): 1, ("a", "/scan"): 1}


def test_a_full_queue_and_replacement_count_each_drop_once() -> None:
    queues = RobotQueues(max_per_robot=4, heavy_backlog=0)
    queues.put(typed("a", "/camera", IMAGE, 0))
    for n in range(1, 5):  # the fourth small one finds the queue full: the image, oldest, goes
        queues.put(typed("a", "/imu", IMU, n))
    queues.put(typed("a", "/camera", IMAGE, 5))  # full: /imu 1 goes; no image waits to replace
    queues.put(typed("a", "/camera", IMAGE, 6))  # replaces 5, which makes the room
    assert delivered(queues, 4) == {
        "robot-a": [("/imu", 2), ("/imu", 3), ("/imu", 4)], "robot-a-heavy": [("/camera", 6)]
    }
    assert queues.dropped == {("a", "/camera"): 2, ("a", "/imu"): 1}
    assert queues.superseded == {("a", "/camera"): 1}
    assert queues.drop_summary() == (
        "[a] /camera: 2 dropped (1 queue full, 1 replaced by a newer one while the host was behind)\n"
        "[a] /imu: 1 dropped (1 queue full)"
    )


def test_a_heavy_message_dropped_for_a_small_one_is_warned_about_on_its_own_thread() -> None:
    queues = RobotQueues(max_per_robot=2)
    queues.put(typed("a", "/camera", IMAGE, 0))
    queues.put(typed("a", "/imu", IMU, 1))
    queues.put(typed("a", "/imu", IMU, 2))  # full: the image, oldest, goes; its lane is empty
    by_thread = ByThread()
    queues.serve(by_thread.take)
    items = by_thread.wait_for(lambda items: len(items) == 3)
    queues.close(timeout=5)
    threads: dict[str, list[tuple[str, str]]] = {}
    for name, item in items:
        assert isinstance(item, RawMessage | InputProblem)
        threads.setdefault(name, []).append((item.topic, type(item).__name__))
    assert threads == {
        "robot-a": [("/imu", "RawMessage"), ("/imu", "RawMessage")],
        "robot-a-heavy": [("/camera", "InputProblem")],  # the warning alone: nothing else waits
    }
    assert queues.dropped == {("a", "/camera"): 1}


def test_messages_dropped_here_are_host_drops_in_stats_not_link_drops() -> None:
    queues = RobotQueues(heavy_backlog=0)
    tracker = StatsTracker(host_dropped=queues.dropped_when_taken)
    tracked = threading.Lock()  # as the /_stats tap's: the robot's two threads share it
    first_taken, release = threading.Event(), threading.Event()
    warned: list[str] = []

    def handle(batch: Sequence[InputItem]) -> None:  # as the dispatcher and its /_stats tap do
        with tracked:
            warned.extend(i.topic for i in batch if isinstance(i, InputProblem))
            assert tracker.observe_batch(
                [i for i in batch if isinstance(i, RawMessage)], host_ns=T0 + 500 * MS) == []
        if any(isinstance(i, RawMessage) and i.msgtype == IMAGE for i in batch):
            first_taken.set()
            release.wait(20)  # the first image converts slowly: newer ones replace each other

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


def test_runs_count_as_their_messages_in_the_bound_and_the_drops() -> None:
    queues = RobotQueues(max_per_robot=10)
    queues.put(run_of("a", "/imu", IMU, [0, 1, 2, 3]))
    queues.put(typed("a", "/tf_static", TF, 50), latched=True)
    queues.put(run_of("a", "/imu", IMU, [4, 5, 6, 7]))  # 9 messages wait
    queues.put(run_of("a", "/imu", IMU, [8, 9]))  # 11 would not fit: the oldest run, 4, goes
    queues.put(typed("a", "/imu", IMU, 10))
    assert delivered(queues, 8) == {"robot-a": [
        ("/tf_static", 50), ("/imu", 4), ("/imu", 5), ("/imu", 6), ("/imu", 7), ("/imu", 8),
        ("/imu", 9), ("/imu", 10)]}
    assert queues.dropped == {("a", "/imu"): 4}
    assert queues.drop_summary() == "[a] /imu: 4 dropped (4 queue full)"


def test_a_run_that_does_not_fit_beside_latched_messages_is_dropped_whole() -> None:
    queues = RobotQueues(max_per_robot=3)
    for n in range(3):
        queues.put(typed("a", "/tf_static", TF, n), latched=True)
    queues.put(run_of("a", "/scan", "sensor_msgs/msg/LaserScan", [10, 11]))
    assert delivered(queues, 3) == {
        "robot-a": [("/tf_static", 0), ("/tf_static", 1), ("/tf_static", 2)]
    }
    assert queues.dropped == {("a", "/scan"): 2}


def test_a_heavy_run_is_replaced_as_a_whole_counting_its_messages() -> None:
    queues = RobotQueues(heavy_backlog=0)
    queues.put(run_of("a", "/camera", IMAGE, [0, 1, 2]))
    queues.put(typed("a", "/camera", IMAGE, 3))  # replaces the run: 3 dropped
    queues.put(run_of("a", "/camera", IMAGE, [4, 5]))  # replaces 3: 1 more
    queues.put(run_of("a", "/points", CLOUD, [6]))
    assert delivered(queues, 3) == {
        "robot-a-heavy": [("/camera", 4), ("/camera", 5), ("/points", 6)]
    }
    assert queues.dropped == queues.superseded == {("a", "/camera"): 4}
    assert queues.drop_summary() == (
        "[a] /camera: 4 dropped (4 replaced by a newer one while the host was behind)"
    )


def test_serving_live_robots_shortens_the_gil_switch_interval() -> None:
    queues = RobotQueues()
    queues.serve(Received().take)
    queues.close(timeout=5)
    # A small message's thread waits at most this long for a heavy conversion's thread (and the
    # Zenoh callbacks) to hand over the GIL: Python's default is 5 ms.
    assert sys.getswitchinterval() <= GIL_SWITCH_INTERVAL_S == 0.0005


def test_the_item_bound_drops_the_oldest_item_whole_however_few_messages_wait() -> None:
    # Each item costs a conversion call: a robot sending one message per sample lags at most
    # max_items_per_robot calls; bundles are bounded by their messages (max_per_robot).
    queues = RobotQueues(max_per_robot=1000, max_items_per_robot=3)
    queues.put(run_of("a", "/imu", IMU, [0, 1]))
    queues.put(typed("a", "/imu", IMU, 2))
    queues.put(run_of("a", "/imu", IMU, [3, 4, 5]))
    queues.put(typed("a", "/imu", IMU, 6))  # a fourth item: the oldest, a run of 2, goes
    assert delivered(queues, 5) == {"robot-a": [("/imu", n) for n in range(2, 7)]}
    assert queues.dropped == {("a", "/imu"): 2}


def test_heavy_topics_are_thinned_across_robots_and_the_host_says_so_once() -> None:
    # Behind is counted over all robots: 2 robots' 3 waiting heavy messages exceed 2.
    queues = RobotQueues(heavy_backlog=2)
    queues.put(typed("r0", "/camera", IMAGE, 0))
    queues.put(typed("r1", "/camera", IMAGE, 1))
    queues.put(typed("r1", "/points", CLOUD, 2))
    queues.put(typed("r0", "/camera", IMAGE, 3))  # replaces 0: the host says so
    queues.put(typed("r1", "/camera", IMAGE, 4))  # replaces 1: said already
    by_thread = ByThread()
    queues.serve(by_thread.take)
    items = by_thread.wait_for(lambda items: len(items) == 4)
    queues.close(timeout=5)
    problems = [item for _, item in items if isinstance(item, InputProblem)]
    assert len(problems) == 1
    assert (problems[0].robot, problems[0].topic) == ("r0", "/camera")
    assert isinstance(problems[0].error, HeavyTopicsThinnedError)
    assert str(problems[0].error) == (
        "the host converts heavy topics (images, clouds, maps) slower than they arrive: from now "
        "on it converts only the newest message of each, robots taking turns, and every message "
        "of the small topics (drops counted in /_stats/<robot><topic>/host_drops and in the "
        "summary at the stop); thinning now 2 robots (r0, r1): /camera, /points"
    )
    assert sorted((name, item.data[0]) for name, item in items if isinstance(item, RawMessage)) == [
        ("robot-r0-heavy", 3), ("robot-r1-heavy", 2), ("robot-r1-heavy", 4)]
    assert queues.superseded == {("r0", "/camera"): 1, ("r1", "/camera"): 1}


def test_a_fleet_the_host_cannot_keep_up_with_keeps_its_small_topics_and_shares_the_heavy(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Eight robots send images and clouds much faster than the host converts them (4 ms each,
    one at a time): every robot's every small message is converted, in order; the heavy threads
    convert one at a time, robots taking turns, so each converts some of its newest frames and
    none converts far more often than another."""
    monkeypatch.setattr(queues_module, "STALLED_TURN_S", 30.0)  # a loaded machine's 4 ms sleep
    robots = [f"r{i}" for i in range(8)]
    rounds = 120
    queues = RobotQueues()
    lock = threading.Lock()
    small: dict[str, list[int]] = {robot: [] for robot in robots}
    turns: list[str] = []
    converting = 0
    most_at_once = 0
    thinned: list[InputProblem] = []

    def handle(batch: Sequence[InputItem]) -> None:
        nonlocal converting, most_at_once
        messages = [item for item in batch if isinstance(item, RawMessage)]
        with lock:
            thinned.extend(i for i in batch if isinstance(i, InputProblem))
            if not messages or messages[0].msgtype == IMU:
                for message in messages:
                    small[message.robot].append(message.data[0])
                return
            turns.append(messages[0].robot)
            converting += 1
            most_at_once = max(most_at_once, converting)
        time.sleep(0.004)  # a heavy conversion
        with lock:
            converting -= 1

    queues.serve(handle)
    for n in range(rounds):
        for robot in robots:
            queues.put(typed(robot, "/imu", IMU, n))
            queues.put(typed(robot, "/camera", IMAGE, n))
            queues.put(typed(robot, "/points", CLOUD, n))
        time.sleep(0.001)
    queues.close(timeout=30)
    assert queues.error is None
    assert small == {robot: list(range(rounds)) for robot in robots}
    assert not any(topic == "/imu" for _, topic in queues.dropped)
    assert most_at_once == 1
    per_robot = {robot: turns.count(robot) for robot in robots}
    assert min(per_robot.values()) >= 3, per_robot
    assert max(per_robot.values()) - min(per_robot.values()) <= 2, per_robot
    # Thinned: most frames were replaced by newer ones, every one of them counted.
    assert sum(queues.superseded.values()) > len(robots) * rounds
    assert sum(queues.dropped.values()) == sum(queues.superseded.values())
    assert [type(problem.error) for problem in thinned] == [HeavyTopicsThinnedError]


def test_a_turn_that_converts_keeps_its_slot_however_long_it_takes(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A host behind by seconds converts long turns: robot a's turn uses CPU for four times
    STALLED_TURN_S, and b waits for it to end (when long turns counted as stalled, a fleet's
    robots all converted at once, each getting a sliver of the GIL)."""
    monkeypatch.setattr(queues_module, "STALLED_TURN_S", 0.1)
    queues = RobotQueues(small_turns=1)
    converting = threading.Event()
    ends: dict[str, float] = {}
    starts: dict[str, float] = {}

    def handle(batch: Sequence[InputItem]) -> None:
        robot = next(item.robot for item in batch if isinstance(item, RawMessage))
        starts[robot] = time.monotonic()
        if robot == "a":
            converting.set()
            busy_until = time.thread_time() + 0.4  # converting: CPU, not waiting
            while time.thread_time() < busy_until:
                pass
        ends[robot] = time.monotonic()

    queues.serve(handle)
    queues.put(typed("a", "/imu", IMU, 0))
    assert converting.wait(20)
    queues.put(typed("b", "/imu", IMU, 0))
    queues.close(timeout=30)
    assert queues.error is None
    assert starts["b"] >= ends["a"]


def test_robots_take_turns_gathering_what_comes_meanwhile_and_a_hung_turn_ends(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """One small-topic turn at a time: robot b's messages wait while robot a converts, and b
    converts them in one batch (one run: the busier the host, the longer its runs); a's turn
    hangs, so after STALLED_TURN_S it stops holding the slot and b goes on without it."""
    monkeypatch.setattr(queues_module, "STALLED_TURN_S", 0.2)
    queues = RobotQueues(small_turns=1)
    converting, release = threading.Event(), threading.Event()
    batches: list[tuple[str, list[int]]] = []

    def handle(batch: Sequence[InputItem]) -> None:
        messages = [item for item in batch if isinstance(item, RawMessage)]
        if messages[0].robot == "a":
            converting.set()
            release.wait(20)  # a mesh fetched from a robot that never answers
        batches.append((messages[0].robot, [m.data[0] for m in messages]))

    queues.serve(handle)
    queues.put(typed("a", "/robot_description", "std_msgs/msg/String", 0))
    assert converting.wait(20)
    started = time.monotonic()
    for n in range(5):
        queues.put(typed("b", "/imu", IMU, n))
    deadline = started + 20
    while not batches and time.monotonic() < deadline:
        time.sleep(0.01)
    waited = time.monotonic() - started
    release.set()
    queues.close(timeout=10)
    assert batches == [("b", [0, 1, 2, 3, 4]), ("a", [0])]
    assert waited >= 0.2
