"""The rclpy source against fake nodes that answer like rclpy's graph API: discovery, QoS,
demand, re-deliveries, sequence gaps and definitions (tests/integration/test_ros2_live.py runs
it against real rclpy nodes)."""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import pytest
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from host_bridge.core.decode import Decoder
from robot_relay.config import DEFAULT_DENY
from robot_relay.relay import Relay
from robot_relay.sources.base import topic_filter
from robot_relay.sources.qos import adapted_qos, live_qos
from robot_relay.sources.ros2 import (
    MessageInfo,
    Ros2Source,
    ament_share_dirs,
    message_class,
    message_definition,
)
from robot_relay.wire import Catalog, QosProfile, RawMessage, TopicInfo
from tests.integration.procs import open_loopback


def write_msg(share: Path, name: str, text: str) -> None:
    package, type_name = name.split("/")
    path = share / package / "msg" / f"{type_name}.msg"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def test_definition_from_share_dirs_includes_every_used_type(tmp_path: Path) -> None:
    base, overlay = tmp_path / "base" / "share", tmp_path / "overlay" / "share"
    write_msg(base, "std_msgs/Header", "builtin_interfaces/Time stamp\nstring frame_id\n")
    write_msg(base, "builtin_interfaces/Time", "int32 sec\nuint32 nanosec\n")
    write_msg(overlay, "my_robot/Reading", "# comment\nint32 LIMIT=3\nfloat32 value\n")
    write_msg(
        overlay, "my_robot/Status",
        "Header header\nReading[] readings  # relative name\nReading[<=4] last\n"
        "string<=8 label\ngeometry_msgs/Point where\n",
    )
    write_msg(base, "geometry_msgs/Point", "float64 x\nfloat64 y\nfloat64 z\n")
    shares = ament_share_dirs({"AMENT_PREFIX_PATH": f"{tmp_path / 'overlay'}:{tmp_path / 'base'}"})
    assert shares == [overlay, base]
    definition = message_definition("my_robot/msg/Status", shares)
    assert definition is not None
    assert definition.encoding == "ros2msg"
    for name in ("std_msgs/Header", "builtin_interfaces/Time", "my_robot/Reading",
                 "geometry_msgs/Point"):
        assert f"MSG: {name}\n" in definition.text
    types = get_types_from_msg(definition.text, "my_robot/msg/Status")
    store = get_typestore(Stores.EMPTY)
    store.register(types)
    status = store.types["my_robot/msg/Status"]
    assert [f.name for f in dataclasses.fields(cast(Any, status)) if not f.name.startswith("__")] == [
        "header", "readings", "last", "label", "where"
    ]
    assert message_definition("my_robot/msg/Missing", shares) is None


def test_qos_follows_ros2_bag_record() -> None:
    assert adapted_qos([]).durability == "volatile"
    mixed = adapted_qos([("reliable", "transient_local", 1), ("best_effort", "volatile", 5)])
    assert (mixed.reliability, mixed.durability, mixed.depth) == ("best_effort", "volatile", 5)
    # Several /tf_static broadcasters: the cache must hold each one's latched message.
    latched = adapted_qos([("reliable", "transient_local", 1), ("reliable", "transient_local", 1)])
    assert (latched.reliability, latched.durability, latched.depth) == ("reliable", "transient_local", 2)
    # rosbag2 asks reliable only when every publisher offers it (an unknown one does not).
    assert adapted_qos([("reliable", "volatile", 10), ("unknown", "volatile", 10)]).reliability == (
        "best_effort"
    )


def test_live_queues_hold_enough_where_fast_dds_reports_depth_0() -> None:
    assert adapted_qos([("reliable", "volatile", 0)]).depth == 1  # a bag's offers: as recorded
    # Both ride out a stall of the relay and its latency budget.
    assert live_qos([("best_effort", "volatile", 0)]).depth == 100
    assert live_qos([("reliable", "volatile", 0)]).depth == 100
    assert live_qos([("reliable", "volatile", 0), ("reliable", "volatile", 160)]).depth == 160
    assert live_qos([("reliable", "transient_local", 0)]).depth == 10
    twelve_latched = [("reliable", "transient_local", 0)] * 12
    assert live_qos(twelve_latched).depth == 12


def test_idl_only_package_gives_a_ros2idl_definition_rosbags_parses(tmp_path: Path) -> None:
    share = tmp_path / "share"
    (share / "idl_pkg" / "msg").mkdir(parents=True)
    (share / "idl_pkg" / "msg" / "Basic.idl").write_text(
        "module idl_pkg {\n  module msg {\n    struct Basic {\n      float value;\n    };\n  };\n};\n"
    )
    (share / "idl_pkg" / "msg" / "Complex.idl").write_text(
        '// written in IDL\n#include "idl_pkg/msg/Basic.idl"\n\n'
        "module idl_pkg {\n  module msg {\n    struct Complex {\n"
        "      idl_pkg::msg::Basic first;\n      sequence<idl_pkg::msg::Basic> rest;\n"
        "    };\n  };\n};\n"
    )
    definition = message_definition("idl_pkg/msg/Complex", [share])
    assert definition is not None
    assert definition.encoding == "ros2idl"
    separator = "=" * 80 + "\n"
    blocks = definition.text.split(separator)[1:]
    assert [b.split("\n", 1)[0] for b in blocks] == ["IDL: idl_pkg/msg/Complex", "IDL: idl_pkg/msg/Basic"]
    # The host's decoder reads it (block by block, as rosbags' AnyReader reads rosbag2's ros2idl).
    store = Decoder(get_typestore(Stores.EMPTY)).typestore_for("idl_pkg/msg/Complex", definition)
    complex_type = store.types["idl_pkg/msg/Complex"]
    fields = [f.name for f in dataclasses.fields(cast(Any, complex_type)) if not f.name.startswith("__")]
    assert fields == ["first", "rest"]
    assert message_definition("idl_pkg/action/Go_FeedbackMessage", [share]) is None


@dataclass
class Policies:
    reliability: enum.Enum
    durability: enum.Enum
    depth: int


@dataclass
class Endpoint:
    """rclpy.topic_endpoint_info.TopicEndpointInfo, as far as the source reads it."""

    qos_profile: Policies


class Reliability(enum.IntEnum):  # rclpy.qos.ReliabilityPolicy
    SYSTEM_DEFAULT = 0
    RELIABLE = 1
    BEST_EFFORT = 2


class Durability(enum.IntEnum):  # rclpy.qos.DurabilityPolicy
    SYSTEM_DEFAULT = 0
    TRANSIENT_LOCAL = 1
    VOLATILE = 2


def sensor(depth: int = 5) -> Endpoint:
    return Endpoint(Policies(Reliability.BEST_EFFORT, Durability.VOLATILE, depth))


def latched() -> Endpoint:
    return Endpoint(Policies(Reliability.RELIABLE, Durability.TRANSIENT_LOCAL, 1))


@dataclass
class FakeNode:
    """Answers like rclpy.node.Node's graph API; records subscriptions made through it."""

    graph: dict[str, tuple[list[str], list[Endpoint]]] = field(default_factory=dict)
    subscribed: list[str] = field(default_factory=list)
    unsubscribed: list[str] = field(default_factory=list)
    callbacks: dict[str, Callable[[bytes, MessageInfo | None], None]] = field(default_factory=dict)

    def get_topic_names_and_types(self) -> list[tuple[str, list[str]]]:
        return [(topic, types) for topic, (types, _) in self.graph.items()]

    def get_publishers_info_by_topic(self, topic: str) -> list[Endpoint]:
        return self.graph[topic][1]

    def subscribe(self, info: TopicInfo, callback: Callable[[bytes, MessageInfo | None], None]) -> str:
        self.subscribed.append(info.topic)
        self.callbacks[info.topic] = callback
        return info.topic

    def unsubscribe(self, handle: str) -> None:
        self.unsubscribed.append(handle)
        del self.callbacks[handle]


def make_source(node: FakeNode, shares: list[Path] | None = None) -> Ros2Source:
    return Ros2Source(
        node, "tb3", lambda topic: not topic.startswith("/secret"), shares or [],
        subscribe=node.subscribe, unsubscribe=node.unsubscribe,
    )


def test_discovery_follows_new_vanished_and_changed_topics(tmp_path: Path) -> None:
    write_msg(tmp_path, "my_robot/Reading", "float32 value\n")
    node = FakeNode({
        "/scan": (["sensor_msgs/msg/LaserScan"], [sensor()]),
        "/reading": (["my_robot/msg/Reading"], [sensor(1)]),
        "/cmd_vel": (["geometry_msgs/msg/Twist"], []),  # only subscribers: nothing to forward
        "/secret/pose": (["geometry_msgs/msg/Pose"], [sensor()]),  # denied
        "/both": (["std_msgs/msg/String", "std_msgs/msg/Int32"], [sensor()]),  # ambiguous
    })
    source = make_source(node, [tmp_path])
    catalog = source.discover()
    assert catalog is not None
    assert catalog.source == "ros2"
    assert [(t.topic, t.msgtype) for t in catalog.topics] == [
        ("/reading", "my_robot/msg/Reading"), ("/scan", "sensor_msgs/msg/LaserScan"),
    ]
    reading = catalog.topics[0]
    assert reading.definition is not None
    assert reading.definition.text == "float32 value\n"  # a custom package, from its share dir
    assert reading.qos.reliability == "best_effort"
    assert source.discover() is None  # nothing changed

    # A second, latched publisher joins /tf_static; a reliable one joins /scan; /reading leaves.
    node.graph["/tf_static"] = (["tf2_msgs/msg/TFMessage"], [latched(), latched()])
    node.graph["/scan"] = (["sensor_msgs/msg/LaserScan"],
                           [sensor(), Endpoint(Policies(Reliability.RELIABLE, Durability.VOLATILE, 10))])
    del node.graph["/reading"]
    catalog = source.discover()
    assert catalog is not None
    infos = {t.topic: t for t in catalog.topics}
    assert sorted(infos) == ["/scan", "/tf_static"]
    assert infos["/tf_static"].latched
    assert infos["/tf_static"].qos.depth == 10
    assert (infos["/scan"].qos.reliability, infos["/scan"].qos.depth) == ("best_effort", 100)

    # Publishers coming and going within what the request serves change nothing; a deeper
    # queue is asked for once needed, and never given back while the topic lives.
    node.graph["/tf_static"][1].pop()
    assert source.discover() is None
    node.graph["/tf_static"][1].extend(latched() for _ in range(11))
    catalog = source.discover()
    assert catalog is not None
    assert [t.qos.depth for t in catalog.topics if t.topic == "/tf_static"] == [12]
    del node.graph["/tf_static"][1][2:]
    assert source.discover() is None
    assert source.publisher_counts == {"/scan": 2, "/tf_static": 2}


def test_demand_subscribes_and_unsubscribes_and_forwards_raw_bytes() -> None:
    node = FakeNode({"/scan": (["sensor_msgs/msg/LaserScan"], [sensor()]),
                     "/tf_static": (["tf2_msgs/msg/TFMessage"], [latched()])})
    source = make_source(node)
    assert source.discover() is not None
    published: list[RawMessage] = []
    source.apply_demand(published.append)
    assert node.subscribed == []  # nobody asked

    source.on_demand("/scan", True)
    source.on_demand("/tf_static", True)
    assert source.wake.is_set()
    source.apply_demand(published.append)
    assert node.subscribed == ["/scan", "/tf_static"]
    node.callbacks["/scan"](b"\x00\x01\x00\x00cdr", None)
    assert [(m.robot, m.topic, m.msgtype, m.data) for m in published] == [
        ("tb3", "/scan", "sensor_msgs/msg/LaserScan", b"\x00\x01\x00\x00cdr")
    ]

    # Listening again changes nothing; off then on before the thread runs changes nothing.
    source.on_demand("/scan", True)
    source.on_demand("/tf_static", False)
    source.on_demand("/tf_static", True)
    source.apply_demand(published.append)
    assert node.subscribed == ["/scan", "/tf_static"]

    source.on_demand("/scan", False)
    source.apply_demand(published.append)
    assert node.unsubscribed == ["/scan"]

    # The publisher's QoS changes while a host listens: re-subscribed with the new QoS (the
    # relay keeps its publisher, so no demand comes: the source sees the change itself).
    node.graph["/tf_static"][1].append(sensor())
    assert source.discover() is not None
    source.apply_demand(published.append)
    assert node.unsubscribed == ["/scan", "/tf_static"]
    assert node.subscribed == ["/scan", "/tf_static", "/tf_static"]
    assert not source.subscriptions["/tf_static"][0].latched
    source.close()
    assert sorted(node.unsubscribed) == ["/scan", "/tf_static", "/tf_static"]


def info(sequence: int, source_ns: int = 1) -> MessageInfo:
    """rclpy's message info dict as Jazzy hands it to a two-argument callback."""
    return {"source_timestamp": source_ns, "received_timestamp": source_ns + 5,
            "publication_sequence_number": sequence, "reception_sequence_number": None}


def test_a_new_subscription_does_not_forward_the_latched_history_again() -> None:
    node = FakeNode({"/robot_description": (["std_msgs/msg/String"], [latched()])})
    source = make_source(node)
    source.discover()
    published: list[RawMessage] = []
    source.on_demand("/robot_description", True)
    source.apply_demand(published.append)
    node.callbacks["/robot_description"](b"urdf", info(1, source_ns=100))
    for sequence in range(2, 30):  # more than the queue's depth: the first is still remembered
        node.callbacks["/robot_description"](b"update", info(sequence, source_ns=100 + sequence))

    # Twelve publishers: a deeper queue, so subscribed again; the history comes again.
    node.graph["/robot_description"][1].extend(latched() for _ in range(11))
    source.discover()
    source.apply_demand(published.append)
    assert node.subscribed == ["/robot_description", "/robot_description"]
    published.clear()
    node.callbacks["/robot_description"](b"urdf", info(1, source_ns=100))  # the same message
    node.callbacks["/robot_description"](b"urdf", info(30, source_ns=200))  # republished
    assert [m.data for m in published] == [b"urdf"]
    # Without message info (Humble), identical bytes are the same message.
    node.callbacks["/robot_description"](b"other", None)
    node.callbacks["/robot_description"](b"other", None)
    assert [m.data for m in published] == [b"urdf", b"other"]


def test_sequence_gaps_of_a_single_publisher_count_as_drops() -> None:
    node = FakeNode({"/odom": (["nav_msgs/msg/Odometry"], [sensor()]),
                     "/status": (["std_msgs/msg/String"], [sensor(), sensor()])})
    source = make_source(node)
    source.discover()
    published: list[RawMessage] = []
    for topic in ("/odom", "/status"):
        source.on_demand(topic, True)
    source.apply_demand(published.append)
    for sequence in (4, 5, 8, 9, 12):
        node.callbacks["/odom"](b"odom", info(sequence))
    node.callbacks["/odom"](b"odom", info(1))  # the publisher restarted: no drop, a new start
    node.callbacks["/odom"](b"odom", info(2))
    # Two publishers: their numbers interleave and the info does not say whose they are.
    for sequence in (1, 1, 2, 5):
        node.callbacks["/status"](b"status", info(sequence))
    assert source.drop_counts() == {"/odom": 4}
    assert len(published) == 11  # gaps are counted, never a reason to drop

    # A new subscription (the host came back) starts counting afresh.
    source.on_demand("/odom", False)
    source.apply_demand(published.append)
    source.on_demand("/odom", True)
    source.apply_demand(published.append)
    node.callbacks["/odom"](b"odom", info(40))
    node.callbacks["/odom"](b"odom", info(41))
    assert source.drop_counts() == {"/odom": 4}


def test_message_class_is_imported_from_the_package_as_ros_installs_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    package = tmp_path / "fake_msgs" / "msg"
    package.mkdir(parents=True)
    (tmp_path / "fake_msgs" / "__init__.py").write_text("")
    (package / "__init__.py").write_text("class Reading:\n    pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert message_class("fake_msgs/msg/Reading").__name__ == "Reading"
    with pytest.raises(AttributeError):
        message_class("fake_msgs/msg/Missing")
    with pytest.raises(ImportError):
        message_class("absent_msgs/msg/Reading")


def test_relay_keeps_a_latched_publisher_and_its_cache_when_only_the_depth_changes() -> None:
    session = open_loopback()  # no peers: only the declarations matter here
    description = TopicInfo("/robot_description", "std_msgs/msg/String", None,
                            QosProfile("reliable", "transient_local", 10))
    relay = Relay(session, Catalog("tb3", "ros2", (description,)))
    try:
        first = relay._publishers["/robot_description"]
        deeper = dataclasses.replace(description, qos=QosProfile("reliable", "transient_local", 12))
        relay.update_catalog(Catalog("tb3", "ros2", (deeper,)))
        assert relay._publishers["/robot_description"] is first  # a new one would resend its cache
        assert first.info == deeper
        retyped = dataclasses.replace(deeper, msgtype="std_msgs/msg/Int32")
        relay.update_catalog(Catalog("tb3", "ros2", (retyped,)))
        assert relay._publishers["/robot_description"] is not first
    finally:
        relay.close()
        session.close()


def test_parameter_events_and_hidden_topics_are_forwarded_only_when_named() -> None:
    everything = topic_filter(["*"], DEFAULT_DENY)
    assert [everything(t) for t in ("/odom", "/parameter_events", "/nav/_action/status")] == [
        True, False, False
    ]
    named = topic_filter(["/parameter_events", "/o*"], DEFAULT_DENY)
    assert [named(t) for t in ("/parameter_events", "/odom", "/scan")] == [True, True, False]
    assert not topic_filter(["/p*"], DEFAULT_DENY)("/parameter_events")  # a glob does not name it
