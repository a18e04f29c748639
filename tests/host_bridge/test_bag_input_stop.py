"""The bag input stops within a fraction of a second (issue 22): a topic that is slow to convert
goes on in deliveries of about DELIVERY_SECONDS, a fast one still in whole runs (an indexed MCAP
and a sqlite3 bag, read in bulk, as a bag read message by message), and a window read message by
message (here a bag with message compression; ROS 1) ends when the input closes."""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import pytest
from rosbags.rosbag2 import CompressionMode, StoragePlugin

from host_bridge.inputs import bag as bag_input
from host_bridge.inputs.bag import BagInput, bag_runs
from host_bridge.inputs.base import InputItem, MessageRun
from robot_relay.wire import RawMessage
from tests.integration.robot_bags import START_NS, joint_state, write_copies

MESSAGES = 2000
PERIOD_NS = 10**7
SLOW_S = 0.001
"""What the slow test's delivery takes per message."""
GENEROUS_S = 60.0


def copies(path: Path, storage: StoragePlugin,
           compression: CompressionMode = CompressionMode.NONE) -> Path:
    return write_copies(path, "/joint_states", "sensor_msgs/msg/JointState", joint_state(0, [1.0, 2.0]),
                        count=MESSAGES, period_ns=PERIOD_NS, storage=storage, compression=compression)


class Deliveries:
    """A deliver function that records each delivery's log times, taking ``per_message`` s a
    message as a slow converter would."""

    def __init__(self, per_message: float) -> None:
        self.per_message = per_message
        self.log_ns: list[list[int | None]] = []
        self.kinds: set[type] = set()

    def __call__(self, items: Sequence[InputItem]) -> None:
        """A MessageRun (read in bulk) or RawMessages (a window read message by message)."""
        self.kinds.update(type(item) for item in items)
        messages = [raw for item in items for raw in (item if isinstance(item, MessageRun) else [item])]
        time.sleep(self.per_message * len(messages))
        self.log_ns.append([raw.log_ns for raw in messages if isinstance(raw, RawMessage)])

    @property
    def sizes(self) -> list[int]:
        return [len(times) for times in self.log_ns]

    @property
    def in_order(self) -> bool:
        """Every message of the bag delivered once, in order."""
        delivered = list(itertools.chain.from_iterable(self.log_ns))
        return delivered == [START_NS + i * PERIOD_NS for i in range(MESSAGES)]


def converted(deliveries: Deliveries, bag: Path) -> None:
    source = BagInput(bag, "robot")
    source.start(deliveries)
    assert source.finished.wait(GENEROUS_S)
    source.close()
    assert source.ended()


STORAGES = [
    pytest.param(StoragePlugin.MCAP, CompressionMode.NONE, MessageRun, id="mcap-runs"),
    pytest.param(StoragePlugin.SQLITE3, CompressionMode.NONE, MessageRun, id="sqlite3-runs"),
    pytest.param(StoragePlugin.SQLITE3, CompressionMode.MESSAGE, RawMessage,
                 id="message-compressed-windows"),
]


@pytest.mark.parametrize(("storage", "compression", "kind"), STORAGES)
def test_a_fast_topic_goes_on_in_whole_runs(
    storage: StoragePlugin, compression: CompressionMode, kind: type, tmp_path: Path
) -> None:
    deliveries = Deliveries(per_message=0.0)
    converted(deliveries, copies(tmp_path / "bag", storage, compression))
    first = bag_input.FIRST_DELIVERY
    assert deliveries.sizes == [first, MESSAGES - first]  # the first times the topic
    assert deliveries.kinds == {kind}
    assert deliveries.in_order


@pytest.mark.parametrize(("storage", "compression", "kind"), STORAGES)
def test_a_slow_topic_goes_on_in_short_deliveries(
    storage: StoragePlugin, compression: CompressionMode, kind: type, tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(bag_input, "DELIVERY_SECONDS", 0.05)
    monkeypatch.setattr(bag_input, "FIRST_DELIVERY", 100)
    deliveries = Deliveries(per_message=SLOW_S)
    converted(deliveries, copies(tmp_path / "bag", storage, compression))
    # A message takes SLOW_S or more (a sleep is never shorter), so 0.05 s holds 50 at most.
    assert deliveries.sizes[0] == 100
    assert 1 <= min(deliveries.sizes[1:]) <= max(deliveries.sizes[1:]) <= 50
    assert deliveries.kinds == {kind}
    assert deliveries.in_order


def test_closing_ends_after_the_delivery_under_way(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(bag_input, "FIRST_DELIVERY", 100)
    deliveries = Deliveries(per_message=SLOW_S * 5)  # 10 s for the whole bag
    source = BagInput(copies(tmp_path / "bag", StoragePlugin.MCAP), "robot")
    source.start(deliveries)
    deadline = time.monotonic() + GENEROUS_S
    while len(deliveries.sizes) < 2:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    started = time.monotonic()
    source.close()
    took = time.monotonic() - started
    assert source.finished.is_set()
    assert sum(deliveries.sizes) < MESSAGES
    # One delivery of about DELIVERY_SECONDS (0.25 s) was under way; generous for a busy machine.
    assert took < 2.0, took


def test_a_window_read_message_by_message_ends_at_a_stop(tmp_path: Path) -> None:
    bag = copies(tmp_path / "bag", StoragePlugin.SQLITE3, CompressionMode.MESSAGE)
    assert [len(window) for window in bag_runs(bag, "robot")] == [MESSAGES]
    stop = threading.Event()
    stop.set()
    windows = list(bag_runs(bag, "robot", stop=stop))
    assert [[raw.log_ns for raw in window] for window in windows] == [[START_NS]]
