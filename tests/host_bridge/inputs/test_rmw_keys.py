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
from host_bridge.inputs.rmw_keys import (
    RmwDataKey,
    parse_rmw_attachment,
    parse_rmw_data_key,
    parse_rmw_qos,
    parse_rmw_token,
    rmw_ros_type,
)
from robot_relay.wire import QosProfile as WireQos

SCAN_HASH = get_typestore(Stores.ROS2_HUMBLE).hash_rihs01("sensor_msgs/msg/LaserScan")


def test_ros_type_from_dds_name() -> None:
    assert rmw_ros_type("sensor_msgs::msg::dds_::LaserScan_") == "sensor_msgs/msg/LaserScan"
    assert rmw_ros_type("tf2_msgs::msg::dds_::TFMessage_") == "tf2_msgs/msg/TFMessage"
    with pytest.raises(GraphError, match="sensor_msgs/msg/LaserScan"):
        rmw_ros_type("sensor_msgs/msg/LaserScan")


@pytest.mark.parametrize(
    ("key", "expected"),
    [
        ("0/scan/sensor_msgs::msg::dds_::LaserScan_/TypeHashNotSupported",
         RmwDataKey(0, "/scan", "sensor_msgs/msg/LaserScan", None)),
        (f"42/tb3/scan/sensor_msgs::msg::dds_::LaserScan_/{SCAN_HASH}",
         RmwDataKey(42, "/tb3/scan", "sensor_msgs/msg/LaserScan", SCAN_HASH)),
        ("7/a/b/c/tf2_msgs::msg::dds_::TFMessage_/TypeHashNotSupported",
         RmwDataKey(7, "/a/b/c", "tf2_msgs/msg/TFMessage", None)),
    ],
)
def test_data_keys_of_both_forms(key: str, expected: RmwDataKey) -> None:
    assert parse_rmw_data_key(key) == expected


def test_data_key_built_by_zenoh_ros2_sdk() -> None:
    key = topic_keyexpr(3, "/pupper/scan", "sensor_msgs::msg::dds_::LaserScan_", SCAN_HASH)
    assert parse_rmw_data_key(key) == RmwDataKey(3, "/pupper/scan", "sensor_msgs/msg/LaserScan", SCAN_HASH)


@pytest.mark.parametrize(
    "key", ["swanky/tb3/data/scan", "0/scan", "x/scan/std_msgs::msg::dds_::String_/h"]
)
def test_foreign_data_keys_are_named(key: str) -> None:
    with pytest.raises(GraphError, match="rmw_zenoh"):
        parse_rmw_data_key(key)


def test_humble_publisher_token() -> None:
    # As rmw_zenoh 0.1.x on Humble writes it: node /tb3/laser_driver, topic /tb3/scan, sensor QoS.
    key = ("@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MP/%/%tb3/laser_driver/%tb3%scan/"
           "sensor_msgs::msg::dds_::LaserScan_/TypeHashNotSupported/2::,5:,:,:,,")
    entity = parse_rmw_token(key)
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
    node_entity = parse_rmw_token(node_liveliness_keyexpr(node))
    assert (node_entity.kind, node_entity.namespace, node_entity.node, node_entity.topic) == (
        "NN", "/", "tf_pub", None)
    pub = parse_rmw_token(endpoint_liveliness_keyexpr(endpoint))
    assert (pub.kind, pub.domain, pub.node_id, pub.entity_id) == ("MP", 0, "4", "9")
    assert (pub.topic, pub.msgtype, pub.type_hash) == (
        "/tf_static", "tf2_msgs/msg/TFMessage", "RIHS01_abc")
    assert pub.qos == WireQos("reliable", "transient_local", 1)


def test_qos_strings() -> None:
    assert parse_rmw_qos("::,:,:,:,,") == WireQos("reliable", "volatile", 10)
    assert parse_rmw_qos(QosProfile(reliability=QosReliability.BEST_EFFORT, history_depth=3).encode()) \
        == WireQos("best_effort", "volatile", 3)
    with pytest.raises(GraphError, match="depth"):
        parse_rmw_qos("1:1:,x:,:,:,,")


def test_bad_tokens_are_named() -> None:
    with pytest.raises(GraphError, match="lacks"):
        parse_rmw_token("@ros2_lv/0/z/0/1/MP/%/%/talker")
    with pytest.raises(GraphError, match="not an rmw_zenoh one"):
        parse_rmw_token("swanky/tb3/alive")


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
    attachment = parse_rmw_attachment(data, "0/scan/t/h")
    assert (attachment.sequence, attachment.source_ns, attachment.gid) == (7, 123, GID)


def test_truncated_attachment_is_named() -> None:
    with pytest.raises(GraphError, match="0/scan/t/h"):
        parse_rmw_attachment(bytes(10), "0/scan/t/h")
