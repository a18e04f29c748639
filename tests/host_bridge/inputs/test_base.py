"""The items inputs deliver (host_bridge/inputs/base.py): a run read as RawMessages, and runs of
one topic waiting together joined by ``gathered`` with every topic's order kept."""

from __future__ import annotations

import numpy as np

from host_bridge.core.columns import PackedPayloads
from host_bridge.inputs.base import InputItem, InputProblem, MessageRun, gathered
from robot_relay.errors import WireError
from robot_relay.wire import MessageDefinition, RawMessage

IMU = "sensor_msgs/msg/Imu"
DEFINITION = MessageDefinition("ros2msg", "float64 x\n")


def bundle(
    topic: str, first: int, count: int, definition: MessageDefinition | None = DEFINITION
) -> MessageRun:
    """A run as a bundle brings it: payloads ``<topic>:<n>`` in one buffer, times and numbers."""
    texts = [f"{topic}:{n}".encode() for n in range(first, first + count)]
    packed = PackedPayloads.of(texts)
    numbers = np.arange(first, first + count, dtype=np.int64)
    return MessageRun("tb3", topic, IMU, definition, packed, log_ns=numbers * 10,
                      receive_ns=numbers + 1000, sequence=numbers)


def test_runs_of_a_topic_waiting_together_become_one_with_their_order_and_columns() -> None:
    items: list[InputItem] = [bundle("/imu", 0, 2), bundle("/tf", 0, 1), bundle("/imu", 2, 3)]
    joined = gathered(items)
    assert [(type(i).__name__, i.topic, len(i)) for i in joined if isinstance(i, MessageRun)] == [
        ("MessageRun", "/imu", 5), ("MessageRun", "/tf", 1)]
    imu = joined[0]
    assert isinstance(imu, MessageRun)
    assert [bytes(p) for p in imu.payloads] == [f"/imu:{n}".encode() for n in range(5)]
    assert imu.log_ns is not None
    assert imu.log_ns.tolist() == [0, 10, 20, 30, 40]
    assert imu.receive_ns is not None
    assert imu.receive_ns.tolist() == [1000, 1001, 1002, 1003, 1004]
    assert imu.sequence is not None
    assert imu.sequence.tolist() == [0, 1, 2, 3, 4]
    assert list(imu)[3] == RawMessage("tb3", "/imu", IMU, b"/imu:3", DEFINITION, 1003, 30, 3)
    assert joined[1] is items[1]  # alone: handed on as it came


def test_a_message_of_the_topic_between_two_runs_keeps_them_apart() -> None:
    single = RawMessage("tb3", "/imu", IMU, b"/imu:2", DEFINITION, 1002, 20, 2)
    problem = InputProblem("tb3", "/imu", WireError("bad sample"))
    other_definition = bundle("/imu", 10, 1, definition=None)
    items: list[InputItem] = [bundle("/imu", 0, 2), problem, single, bundle("/imu", 3, 2),
                              bundle("/imu", 5, 1), other_definition]
    joined = gathered(items)
    assert [(type(i).__name__, len(i) if isinstance(i, MessageRun) else None) for i in joined] == [
        ("MessageRun", 2), ("InputProblem", None), ("RawMessage", None), ("MessageRun", 3),
        ("MessageRun", 1)]
    assert joined[4] is other_definition  # another definition: another run
    assert isinstance(joined[3], MessageRun)
    assert [bytes(p) for p in joined[3].payloads] == [b"/imu:3", b"/imu:4", b"/imu:5"]
