"""The Relay over a loopback Zenoh session: a RawMessage goes out on its key with its encoding
and attachment, and the catalog is answered."""

from __future__ import annotations

import time

import zenoh

from robot_relay.relay import Relay
from robot_relay.wire import (
    Attachment,
    Catalog,
    MessageDefinition,
    RawMessage,
    TopicInfo,
    catalog_key,
    data_key,
)

STRING = "std_msgs/msg/String"
CHATTER = TopicInfo("/chatter", STRING, MessageDefinition("ros2msg", "string data"))


def test_a_message_goes_out_with_its_key_encoding_and_attachment(
    sessions: tuple[zenoh.Session, zenoh.Session],
) -> None:
    host, robot = sessions
    received: list[zenoh.Sample] = []
    subscriber = host.declare_subscriber(data_key("tb3", "/chatter"), received.append)
    relay = Relay(robot, Catalog("tb3", "bag", (CHATTER,)))
    try:
        assert relay.wait_for_host(20.0)
        before = time.time_ns()
        relay.publish(RawMessage("tb3", "/chatter", STRING, b"\x00\x01\x00\x00cdr 1", log_ns=123))
        relay.publish(RawMessage("tb3", "/chatter", STRING, b"\x00\x01\x00\x00cdr 2"))
        after = time.time_ns()
        deadline = time.monotonic() + 20
        while len(received) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        replies = [reply.ok for reply in host.get(catalog_key("tb3"), timeout=10.0)]
    finally:
        relay.close()
        subscriber.undeclare()
    assert [str(s.key_expr) for s in received] == ["swanky/tb3/data/chatter"] * 2
    assert [str(s.encoding) for s in received] == [f"application/cdr;{STRING}"] * 2
    assert [s.payload.to_bytes() for s in received] == [b"\x00\x01\x00\x00cdr 1",
                                                       b"\x00\x01\x00\x00cdr 2"]
    attachments = [Attachment.unpack(s.attachment.to_bytes(), "test") for s in received
                   if s.attachment is not None]
    assert [(a.sequence, a.source_ns, a.flags) for a in attachments] == [(0, 123, 0), (1, 0, 0)]
    assert all(before <= a.receive_ns <= after for a in attachments)
    assert relay.published == 2
    assert len(replies) == 1
    assert replies[0] is not None
    catalog = Catalog.from_json(replies[0].payload.to_bytes(), "test")
    assert catalog == Catalog("tb3", "bag", (CHATTER,))
