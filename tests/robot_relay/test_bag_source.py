"""BagSource on a bag written here with rosbags' Writer: its catalog, its messages, and its replay
as the relay's Source (own thread, to the end or until closed)."""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from pathlib import Path

from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from robot_relay.sources.bag import RUN_WINDOW, BagSource
from robot_relay.sources.base import Source, topic_filter
from robot_relay.wire import Catalog, QosProfile, RawMessage, TopicInfo

T0 = 1_700_000_000_000_000_000
STRING = "std_msgs/msg/String"
STORE = get_typestore(Stores.ROS2_HUMBLE)


def chatter_cdr(text: str) -> bytes:
    return bytes(STORE.serialize_cdr(STORE.types[STRING](data=text), STRING))


def chatter_bag(path: Path, count: int = 3, spacing_ns: int = 10_000_000) -> Path:
    """An MCAP rosbag2 with ``count`` /chatter Strings ``spacing_ns`` apart and one
    /robot_description (latched by convention: the bag stores no QoS)."""
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        chatter = writer.add_connection("/chatter", STRING, typestore=STORE)
        description = writer.add_connection("/robot_description", STRING, typestore=STORE)
        writer.write(description, T0, chatter_cdr("<robot name='r'/>"))
        for i in range(count):
            writer.write(chatter, T0 + 1 + i * spacing_ns, chatter_cdr(f"hello {i}"))
    return path


class Collected:
    """An outlet that keeps what it is given."""

    def __init__(self) -> None:
        self.messages: list[RawMessage] = []
        self.catalogs: list[Catalog] = []

    def publish(self, raw: RawMessage) -> None:
        self.messages.append(raw)

    def publish_run(
        self, info: TopicInfo, payloads: Sequence[bytes | memoryview], log_ns: Sequence[int]
    ) -> None:
        self.messages += [
            RawMessage("tb3", info.topic, info.msgtype, data, info.definition, log_ns=stamp)
            for data, stamp in zip(payloads, log_ns, strict=True)
        ]

    def update_catalog(self, catalog: Catalog) -> None:
        self.catalogs.append(catalog)


def wait_until(condition: object, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():  # type: ignore[operator]
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def test_catalog_names_each_topic_with_type_definition_and_qos(tmp_path: Path) -> None:
    with BagSource(chatter_bag(tmp_path / "bag"), "tb3") as bag:
        catalog = bag.catalog()
    assert (catalog.robot, catalog.source) == ("tb3", "bag")
    by_topic = {info.topic: info for info in catalog.topics}
    assert sorted(by_topic) == ["/chatter", "/robot_description"]
    assert {info.msgtype for info in catalog.topics} == {STRING}
    chatter = by_topic["/chatter"]
    assert chatter.definition is not None
    assert (chatter.definition.encoding, chatter.definition.text.strip()) == ("ros2msg", "string data")
    assert chatter.qos == QosProfile()
    assert by_topic["/robot_description"].qos == QosProfile(durability="transient_local", depth=1)


def test_messages_are_the_bags_cdr_in_log_time_order_filtered_by_topic(tmp_path: Path) -> None:
    path = chatter_bag(tmp_path / "bag")
    with BagSource(path, "tb3", topics=topic_filter(["/chat*"], [])) as bag:
        assert [info.topic for info in bag.catalog().topics] == ["/chatter"]
        messages = list(bag.messages())
    assert [(m.robot, m.topic, m.msgtype, bytes(m.data), m.log_ns) for m in messages] == [
        ("tb3", "/chatter", STRING, chatter_cdr(f"hello {i}"), T0 + 1 + i * 10_000_000)
        for i in range(3)
    ]


def test_as_a_source_it_replays_everything_on_its_own_thread(tmp_path: Path) -> None:
    bag = BagSource(chatter_bag(tmp_path / "bag"), "tb3", rate=0).open()
    source: Source = bag
    outlet = Collected()
    source.on_demand("/chatter", False)  # a replay sends whoever listens
    source.start(outlet)
    wait_until(source.ended)
    source.close()
    source.close()  # idempotent
    assert [(m.topic, bytes(m.data)) for m in outlet.messages] == [
        ("/robot_description", chatter_cdr("<robot name='r'/>")),
        *[("/chatter", chatter_cdr(f"hello {i}")) for i in range(3)],
    ]
    assert outlet.catalogs == []  # a bag's catalog is known before it starts
    assert source.drop_counts() == {}
    assert "bag-replay" not in {thread.name for thread in threading.enumerate()}


def test_close_ends_a_paced_replay_without_waiting_for_the_next_message(tmp_path: Path) -> None:
    # At rate 1 the second /chatter is due 100 s after the first.
    bag = BagSource(chatter_bag(tmp_path / "bag", spacing_ns=100 * 10**9), "tb3", rate=1).open()
    outlet = Collected()
    bag.start(outlet)
    wait_until(lambda: len(outlet.messages) == 2)  # the description and the first /chatter
    started = time.monotonic()
    bag.close()
    assert time.monotonic() - started < 5.0
    assert bag.ended()
    assert [m.topic for m in outlet.messages] == ["/robot_description", "/chatter"]


def run_shapes(bag: BagSource) -> list[tuple[str, int, list[int]]]:
    return [(info.topic, len(payloads), [stamp - T0 for stamp in log_ns])
            for info, payloads, log_ns in bag.runs()]


def test_unpaced_runs_gather_each_topic_in_order_up_to_the_window(
    tmp_path: Path,
) -> None:
    with BagSource(chatter_bag(tmp_path / "bag", count=RUN_WINDOW + 5, spacing_ns=1), "tb3") as bag:
        shapes = run_shapes(bag)
        first, *_ = bag.runs()
    # The window closes after RUN_WINDOW messages: the description and RUN_WINDOW - 1 chatters.
    assert [(topic, size) for topic, size, _ in shapes] == [
        ("/robot_description", 1), ("/chatter", RUN_WINDOW - 1), ("/chatter", 6)]
    assert shapes[1][2] == list(range(1, RUN_WINDOW))
    assert shapes[2][2] == list(range(RUN_WINDOW, RUN_WINDOW + 6))
    info, payloads, _ = first
    assert (info.topic, bytes(payloads[0])) == ("/robot_description", chatter_cdr("<robot name='r'/>"))


def test_a_paced_replay_sends_each_message_alone_when_on_time_and_gathers_those_due_together(
    tmp_path: Path,
) -> None:
    waits: list[float] = []
    # A sleep that returns at once: every message is then still ahead of its time, so none
    # may wait in a run for the next one.
    on_time = BagSource(chatter_bag(tmp_path / "spaced", count=3, spacing_ns=10**9), "tb3",
                        rate=1, sleep=waits.append).open()
    with on_time:
        assert run_shapes(on_time) == [
            ("/robot_description", 1, [0]), ("/chatter", 1, [1]),
            ("/chatter", 1, [1 + 10**9]), ("/chatter", 1, [1 + 2 * 10**9])]
    # The second and third /chatter are 1 and 2 s after the first (less what reading took).
    assert len(waits) == 2
    assert 0.5 < waits[0] <= 1.0
    assert 1.5 < waits[1] <= 2.0
    # Three messages with the same log time are due at once, as the description just before.
    with BagSource(chatter_bag(tmp_path / "together", count=3, spacing_ns=0), "tb3", rate=1) as bag:
        assert run_shapes(bag) == [("/robot_description", 1, [0]), ("/chatter", 3, [1, 1, 1])]
