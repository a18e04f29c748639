"""The host's Zenoh input against real publishers in a second session over loopback."""

from __future__ import annotations

import time

import pytest
import zenoh
from rosbags.typesys import Stores, get_typestore

from host_bridge.inputs.base import InputProblem
from host_bridge.inputs.live import LiveInput
from robot_relay.relay import Relay
from robot_relay.wire import Attachment, Catalog, RawMessage, TopicInfo, cdr_encoding, data_key
from tests.host_bridge.inputs.received import collect

pytestmark = pytest.mark.integration

STORE = get_typestore(Stores.ROS2_HUMBLE)


def test_wrong_attachment_version_is_named_and_other_samples_flow(
    sessions: tuple[zenoh.Session, zenoh.Session],
) -> None:
    host, robot = sessions
    data = bytes(STORE.serialize_cdr(STORE.types["std_msgs/msg/String"](data="hi"),
                                     "std_msgs/msg/String"))
    catalog = Catalog("tb3", "bag", (TopicInfo("/chat", "std_msgs/msg/String", None),))
    relay = Relay(robot, catalog)
    source = LiveInput(host, rmw_zenoh=False)
    try:
        assert relay.wait_for_host(10.0)
        bad = bytearray(Attachment(0, 1).pack())
        bad[0] = 7
        robot.put(data_key("tb3", "/chat"), data, encoding=cdr_encoding("std_msgs/msg/String"),
                  attachment=bytes(bad))
        relay.publish(RawMessage("tb3", "/chat", "std_msgs/msg/String", data, log_ns=5))
        items = collect(source, 3)  # the relay joining, the bad sample, the good one
    finally:
        source.close()
        relay.close()
    problems = [i for i in items if isinstance(i, InputProblem)]
    messages = [i for i in items if isinstance(i, RawMessage)]
    assert len(problems) == 1
    assert "swanky/tb3/data/chat" in str(problems[0].error)
    assert "wire version 7" in str(problems[0].error)
    assert len(messages) == 1
    assert messages[0].data == data
    assert messages[0].log_ns == 5
    assert messages[0].topic == "/chat"
    assert messages[0].sequence == 0


def test_latched_topic_reaches_a_host_that_starts_late(
    sessions: tuple[zenoh.Session, zenoh.Session],
) -> None:
    host, robot = sessions
    tf = STORE.types["tf2_msgs/msg/TFMessage"](transforms=[])
    data = bytes(STORE.serialize_cdr(tf, "tf2_msgs/msg/TFMessage"))
    from robot_relay.wire import QosProfile

    catalog = Catalog("tb3", "bag", (
        TopicInfo("/tf_static", "tf2_msgs/msg/TFMessage", None,
                  QosProfile(durability="transient_local", depth=1)),
    ))
    relay = Relay(robot, catalog)
    try:
        relay.publish(RawMessage("tb3", "/tf_static", "tf2_msgs/msg/TFMessage", data))
        time.sleep(0.5)
        source = LiveInput(host, rmw_zenoh=False)  # subscribes only now
        try:
            items = collect(source, 2)  # the relay joining, the latched message
        finally:
            source.close()
    finally:
        relay.close()
    assert [i.topic for i in items if isinstance(i, RawMessage)] == ["/tf_static"]
