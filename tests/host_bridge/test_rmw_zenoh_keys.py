"""rmw_zenoh keys, liveliness tokens and attachments -> what the host needs, for the Humble
(``TypeHashNotSupported``) and Jazzy (``RIHS01_...``) forms. Tokens and attachments are also
built with independent encoders: zenoh-ros2-sdk's own key builders and zenoh-ext's serializer."""

from __future__ import annotations

import pytest
from rosbags.typesys import Stores, get_typestore
from zenoh.ext import Int64, z_serialize
from zenoh_ros2_sdk.attachment import Attachment as SdkAttachment
from zenoh_ros2_sdk.entity import EndpointEntity, EntityKind, NodeEntity
from zenoh_ros2_sdk.keyexpr import endpoint_liveliness_keyexpr, node_liveliness_keyexpr, topic_keyexpr
from zenoh_ros2_sdk.qos import QosDurability, QosProfile, QosReliability

from host_bridge.errors import GraphError
from host_bridge.inputs.rmw_zenoh import (
    BundledDefinitions,
    DataKey,
    namespace_robot,
    parse_attachment,
    parse_data_key,
    parse_qos,
    parse_token,
    resolve_robot,
    ros_type,
)
from host_bridge.inputs.zenoh import check_robot_pattern, robot_matches
from robot_relay.wire import QosProfile as WireQos

HUMBLE = get_typestore(Stores.ROS2_HUMBLE)
JAZZY = get_typestore(Stores.ROS2_JAZZY)
SCAN_HASH = HUMBLE.hash_rihs01("sensor_msgs/msg/LaserScan")


def test_ros_type_from_dds_name() -> None:
    assert ros_type("sensor_msgs::msg::dds_::LaserScan_") == "sensor_msgs/msg/LaserScan"
    assert ros_type("tf2_msgs::msg::dds_::TFMessage_") == "tf2_msgs/msg/TFMessage"
    with pytest.raises(GraphError, match="sensor_msgs/msg/LaserScan"):
        ros_type("sensor_msgs/msg/LaserScan")


@pytest.mark.parametrize(
    ("key", "expected"),
    [
        ("0/scan/sensor_msgs::msg::dds_::LaserScan_/TypeHashNotSupported",
         DataKey(0, "/scan", "sensor_msgs/msg/LaserScan", None)),
        (f"42/tb3/scan/sensor_msgs::msg::dds_::LaserScan_/{SCAN_HASH}",
         DataKey(42, "/tb3/scan", "sensor_msgs/msg/LaserScan", SCAN_HASH)),
        ("7/a/b/c/tf2_msgs::msg::dds_::TFMessage_/TypeHashNotSupported",
         DataKey(7, "/a/b/c", "tf2_msgs/msg/TFMessage", None)),
    ],
)
def test_data_keys_of_both_forms(key: str, expected: DataKey) -> None:
    assert parse_data_key(key) == expected


def test_data_key_built_by_zenoh_ros2_sdk() -> None:
    key = topic_keyexpr(3, "/pupper/scan", "sensor_msgs::msg::dds_::LaserScan_", SCAN_HASH)
    assert parse_data_key(key) == DataKey(3, "/pupper/scan", "sensor_msgs/msg/LaserScan", SCAN_HASH)


@pytest.mark.parametrize(
    "key", ["swanky/tb3/data/scan", "0/scan", "x/scan/std_msgs::msg::dds_::String_/h"]
)
def test_foreign_data_keys_are_named(key: str) -> None:
    with pytest.raises(GraphError, match="rmw_zenoh"):
        parse_data_key(key)


def test_humble_publisher_token() -> None:
    # As rmw_zenoh 0.1.x on Humble writes it: node /tb3/laser_driver, topic /tb3/scan, sensor QoS.
    key = ("@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MP/%/%tb3/laser_driver/%tb3%scan/"
           "sensor_msgs::msg::dds_::LaserScan_/TypeHashNotSupported/2::,5:,:,:,,")
    entity = parse_token(key)
    assert (entity.kind, entity.session, entity.namespace, entity.node) == (
        "MP", "aac3178e146ba6f1fc6e6a4085e77f21", "/tb3", "laser_driver")
    assert (entity.topic, entity.msgtype, entity.type_hash) == (
        "/tb3/scan", "sensor_msgs/msg/LaserScan", None)
    assert entity.qos == WireQos("best_effort", "volatile", 5)


def test_jazzy_tokens_built_by_zenoh_ros2_sdk() -> None:
    node = NodeEntity(domain_id=0, session_id="1f2e3d", node_id=4, node_name="tf_pub",
                      namespace="/")
    endpoint = EndpointEntity(
        node=node, entity_id=9, kind=EntityKind.PUBLISHER, name="/tf_static",
        dds_type_name="tf2_msgs::msg::dds_::TFMessage_", type_hash="RIHS01_abc",
        qos=QosProfile(durability=QosDurability.TRANSIENT_LOCAL, history_depth=1).encode(),
    )
    node_entity = parse_token(node_liveliness_keyexpr(node))
    assert (node_entity.kind, node_entity.namespace, node_entity.node, node_entity.topic) == (
        "NN", "/", "tf_pub", None)
    pub = parse_token(endpoint_liveliness_keyexpr(endpoint))
    assert (pub.kind, pub.domain, pub.node_id, pub.entity_id) == ("MP", 0, "4", "9")
    assert (pub.topic, pub.msgtype, pub.type_hash) == (
        "/tf_static", "tf2_msgs/msg/TFMessage", "RIHS01_abc")
    assert pub.qos == WireQos("reliable", "transient_local", 1)


def test_qos_strings() -> None:
    assert parse_qos("::,:,:,:,,") == WireQos("reliable", "volatile", 10)
    assert parse_qos(QosProfile(reliability=QosReliability.BEST_EFFORT, history_depth=3).encode()) \
        == WireQos("best_effort", "volatile", 3)
    with pytest.raises(GraphError, match="depth"):
        parse_qos("1:1:,x:,:,:,,")


def test_bad_tokens_are_named() -> None:
    with pytest.raises(GraphError, match="lacks"):
        parse_token("@ros2_lv/0/z/0/1/MP/%/%/talker")
    with pytest.raises(GraphError, match="not an rmw_zenoh one"):
        parse_token("swanky/tb3/alive")


GID = bytes(range(16))


@pytest.mark.parametrize(
    "data",
    [
        # rmw_zenoh Humble/Jazzy releases: names before each field (zenoh-ext serializer).
        z_serialize(("sequence_number", Int64(7), "source_timestamp", Int64(123),
                     "source_gid", GID)).to_bytes(),
        # ros-z: no names.
        z_serialize((Int64(7), Int64(123), GID)).to_bytes(),
        # zenoh-ros2-sdk.
        SdkAttachment(sequence_id=7, timestamp_ns=123, gid=GID).to_bytes(),
        # A fixed-size gid without its length.
        (7).to_bytes(8, "little") + (123).to_bytes(8, "little") + GID,
    ],
)
def test_attachment_forms(data: bytes) -> None:
    attachment = parse_attachment(data, "0/scan/t/h")
    assert (attachment.sequence, attachment.source_ns, attachment.gid) == (7, 123, GID)


def test_truncated_attachment_is_named() -> None:
    with pytest.raises(GraphError, match="0/scan/t/h"):
        parse_attachment(bytes(10), "0/scan/t/h")


def test_robot_from_namespace() -> None:
    assert namespace_robot("/") is None
    assert namespace_robot("/tb3") == "tb3"
    assert namespace_robot("/tb3/front") == "tb3"
    # Inside its namespace the prefix goes; /tf of a namespaced node stays /tf on that robot.
    assert resolve_robot("/tb3/scan", {"tb3"}, "robot") == ("tb3", "/scan")
    assert resolve_robot("/tf", {"tb3"}, "robot") == ("tb3", "/tf")
    # No namespace, or several robots on one topic: the --robot robot.
    assert resolve_robot("/scan", {None}, "pupper") == ("pupper", "/scan")
    assert resolve_robot("/tf", {"tb3", "tb4"}, "robot") == ("robot", "/tf")
    assert resolve_robot("/tb3/scan", {"tb3", None}, "robot") == ("tb3", "/scan")


def test_definitions_follow_the_type_hash() -> None:
    definitions = BundledDefinitions()
    assert definitions.lookup("sensor_msgs/msg/LaserScan", None) == (None, None)
    assert definitions.lookup("sensor_msgs/msg/LaserScan", SCAN_HASH) == (None, None)
    # Jazzy added Range.variance: its hash picks the Jazzy definition, not Humble's.
    definition, warning = definitions.lookup(
        "sensor_msgs/msg/Range", JAZZY.hash_rihs01("sensor_msgs/msg/Range")
    )
    assert warning is None
    assert definition is not None
    assert "float32 variance" in definition.text
    assert definitions.lookup("sensor_msgs/msg/Range", HUMBLE.hash_rihs01("sensor_msgs/msg/Range")) \
        == (None, None)
    definition, warning = definitions.lookup("sensor_msgs/msg/LaserScan", "RIHS01_" + "0" * 64)
    assert definition is None
    assert warning is not None
    assert "sensor_msgs/msg/LaserScan" in warning


def test_robot_patterns() -> None:
    assert check_robot_pattern("east-$*") == "east-$*"
    with pytest.raises(Exception, match=r"tb\$\*"):
        check_robot_pattern("tb*")
    with pytest.raises(Exception, match="one non-empty chunk"):
        check_robot_pattern("a/b")
    assert robot_matches("east-a", "east-$*")
    assert not robot_matches("west-c", "east-$*")
    assert robot_matches("tb3", "*")
