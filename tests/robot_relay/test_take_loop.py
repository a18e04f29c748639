"""The take loop against real rclpy (the ``[ros-test]`` extra): a node of this process publishes,
the loop takes the raw bytes; subscriptions come and go from another thread, a stop ends it."""

from __future__ import annotations

import functools
import importlib.util
import os
import threading
import time
from collections.abc import Callable, Iterator, Mapping
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
