"""The take loop against real rclpy (the ``[ros-test]`` extra): a node of this process publishes,
the loop takes the raw bytes; subscriptions come and go from another thread, a stop ends it."""

from __future__ import annotations

import functools
import importlib.util
import math
import os
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from itertools import pairwise
from typing import Any

import pytest

from robot_relay.sources import take_loop
from robot_relay.sources.take_loop import TakeLoop
from robot_relay.wire import QosProfile, TopicInfo

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("rclpy") is None,
    reason="rclpy is not installed: pip install -e '.[ros-test]'",
)
TOPIC = "/take_loop_test"


def taken(received: list[Any], count: int) -> bool:
    return len(received) >= count


def wait_until(condition: Callable[[], bool], what: str, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"no {what} within {timeout} s"
        time.sleep(0.02)


@pytest.fixture
def ros(monkeypatch: pytest.MonkeyPatch, tmp_path: Any) -> Iterator[tuple[Any, Any]]:
    """(context, node) of a private ROS domain on localhost."""
    import rclpy
    from rclpy.context import Context
    from rclpy.signals import SignalHandlerOptions

    monkeypatch.setenv("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("ROS_LOG_DIR", str(tmp_path))
    context = Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("take_loop_test", context=context)
    yield context, node
    node.destroy_node()
    rclpy.shutdown(context=context)


def test_messages_arrive_whole_in_order_until_removed_and_a_stop_ends_the_loop_at_once(
    ros: tuple[Any, Any], monkeypatch: pytest.MonkeyPatch,
) -> None:
    from rclpy.impl.implementation_singleton import rclpy_implementation
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.serialization import deserialize_message
    from std_msgs.msg import String

    context, node = ros
    qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    publisher = node.create_publisher(String, TOPIC, qos)
    # Waits that would end by themselves only after a minute: the stop below must wake the loop.
    monkeypatch.setattr(take_loop, "WAIT_NS", 60_000_000_000)
    loop = TakeLoop(rclpy_implementation, context.handle)
    received: list[tuple[str, Mapping[str, Any]]] = []

    def forward(data: bytes, info: Mapping[str, Any]) -> None:
        received.append((deserialize_message(data, String).data, info))

    runner = threading.Thread(target=loop.run)
    runner.start()
    try:
        info = TopicInfo(TOPIC, "std_msgs/msg/String", None, QosProfile("reliable", "volatile", 50))
        subscription = loop.subscribe(node.handle, String, info, qos, forward)
        wait_until(lambda: publisher.get_subscription_count() == 1, "matched subscription")
        for burst in range(3):  # each within the queues' depth: KEEP_LAST drops beyond it
            sent = 40 * burst + 40
            for index in range(sent - 40, sent):
                publisher.publish(String(data=f"message {index}"))
            wait_until(functools.partial(taken, received, sent), f"burst {burst}")
        assert [text for text, _ in received] == [f"message {index}" for index in range(120)]
        stamps = [message_info["source_timestamp"] for _, message_info in received]
        assert stamps == sorted(stamps)
        assert stamps[0] > 0

        loop.remove(subscription)
        wait_until(lambda: publisher.get_subscription_count() == 0, "subscription destroyed")
        publisher.publish(String(data="after removal"))
        time.sleep(0.5)
        assert len(received) == 120
    finally:
        loop.stop()
        runner.join(timeout=30.0)
        loop.close()
    assert not runner.is_alive()  # woken by its guard condition: its own wait lasts a minute


@pytest.fixture
def running_loop(ros: tuple[Any, Any]) -> Iterator[Callable[[float], TakeLoop]]:
    """Starts a TakeLoop with the given latency budget on a thread; stops and closes it after."""
    from rclpy.impl.implementation_singleton import rclpy_implementation

    started: list[tuple[TakeLoop, threading.Thread]] = []

    def start(latency_budget: float) -> TakeLoop:
        loop = TakeLoop(rclpy_implementation, ros[0].handle, latency_budget)
        runner = threading.Thread(target=loop.run)
        runner.start()
        started.append((loop, runner))
        return loop

    yield start
    for loop, runner in started:
        loop.stop()
        runner.join(timeout=30.0)
        loop.close()
        assert not runner.is_alive()


def subscribe_strings(
    ros: tuple[Any, Any], loop: TakeLoop, depth: int,
) -> tuple[Any, list[tuple[float, int]]]:
    """A reliable publisher of numbered Strings and the loop's subscription of them, matched;
    what the loop forwards lands in the list as (time.monotonic(), number)."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.serialization import deserialize_message
    from std_msgs.msg import String

    qos = QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)
    publisher = ros[1].create_publisher(String, TOPIC, qos)
    received: list[tuple[float, int]] = []

    def forward(data: bytes, info: Mapping[str, Any]) -> None:
        received.append((time.monotonic(), int(deserialize_message(data, String).data)))

    info = TopicInfo(TOPIC, "std_msgs/msg/String", None, QosProfile("reliable", "volatile", depth))
    loop.subscribe(ros[1].handle, String, info, qos, forward)
    wait_until(lambda: publisher.get_subscription_count() == 1, "matched subscription")
    return publisher, received


def turns(times: list[float], gap: float = 0.01) -> int:
    """How many bursts ``times`` (ascending) fall into: calls closer than ``gap`` share one."""
    return sum(1 for before, after in pairwise([-math.inf, *times]) if after - before >= gap)


def test_messages_close_together_wait_for_one_turn_and_one_after_a_quiet_spell_goes_at_once(
    ros: tuple[Any, Any], running_loop: Callable[[float], TakeLoop],
) -> None:
    from std_msgs.msg import String

    budget = 1.0
    publisher, received = subscribe_strings(ros, running_loop(budget), depth=50)
    time.sleep(budget + 0.2)  # a quiet spell longer than the budget
    sent_at = time.monotonic()
    publisher.publish(String(data="0"))
    wait_until(functools.partial(taken, received, 1), "the first message")
    # Not held for the budget: nothing came before it within one.
    assert received[0][0] - sent_at < budget / 2

    for number in range(1, 21):  # 100 Hz for 0.2 s, right after the first: within its budget
        publisher.publish(String(data=str(number)))
        time.sleep(0.01)
    wait_until(functools.partial(taken, received, 21), "the 20 messages after it")
    assert [number for _, number in received] == list(range(21))
    # Taken together once the budget after the first message ended, not 20 wake-ups.
    assert turns([at for at, _ in received[1:]]) <= 2
    assert received[1][0] - received[0][0] >= budget * 0.9


def test_a_topic_faster_than_its_queue_holds_within_the_budget_loses_only_at_its_start(
    ros: tuple[Any, Any], running_loop: Callable[[float], TakeLoop],
) -> None:
    from std_msgs.msg import String

    # 50 deep, a 1 s budget, ~200 Hz: a whole budget's wait would overwrite 150 of every 200.
    # Once the turns came sooner, half a queue (a stall of 0.12 s) is to spare.
    publisher, received = subscribe_strings(ros, running_loop(1.0), depth=50)
    count = 1000
    for number in range(count):
        publisher.publish(String(data=str(number)))
        time.sleep(0.005)
    wait_until(lambda: bool(received) and received[-1][1] == count - 1, "the last message")
    numbers = [number for _, number in received]
    assert numbers == sorted(numbers)
    assert len(numbers) < count  # the first budget did overflow
    # The loop turned sooner as soon as it saw the queue fill: the last two seconds are whole.
    assert numbers[-400:] == list(range(count - 400, count))
