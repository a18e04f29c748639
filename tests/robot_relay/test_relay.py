"""The Relay over a loopback Zenoh session: a RawMessage goes out on its key with its encoding
and attachment, and the catalog and clock queries are answered."""

from __future__ import annotations

import threading
import time

import zenoh

from host_bridge.inputs.zenoh import bundle_run
from robot_relay.policy import PolicyTable
from robot_relay.relay import (
    MAX_BLOCKING_BUNDLE_BYTES,
    MAX_BUNDLE_BYTES,
    MAX_BUNDLE_MESSAGES,
    Relay,
    _TopicPublisher,
    bundle_bounds,
)
from robot_relay.wire import (
    BUNDLE_ENTRY_SIZE,
    Attachment,
    Catalog,
    ClockReading,
    MessageDefinition,
    QosProfile,
    RawMessage,
    RelayReport,
    TopicInfo,
    catalog_key,
    clock_key,
    data_key,
    stats_key,
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


def test_every_time_the_relay_sends_comes_from_its_clock(
    sessions: tuple[zenoh.Session, zenoh.Session],
) -> None:
    """Receive times, stats reports and clock readings all read the clock the relay was given
    (here 7.5 s ahead of the PC's, as a Pi that booted without NTP), so a host that measures
    the clock through the query measures the clock of the receive times."""
    host, robot = sessions
    shift = 7_500_000_000
    received: list[zenoh.Sample] = []
    reports: list[zenoh.Sample] = []
    subscriber = host.declare_subscriber(data_key("tb3", "/chatter"), received.append)
    stats = host.declare_subscriber(stats_key("tb3"), reports.append)
    relay = Relay(robot, Catalog("tb3", "bag", (CHATTER,)), clock=lambda: time.time_ns() + shift)
    try:
        assert relay.wait_for_host(20.0)
        before = time.time_ns()
        relay.publish(RawMessage("tb3", "/chatter", STRING, cdr("one"), log_ns=123))
        # A live source's message DDS received 40 ms ago (on the system clock), held since.
        relay.publish(RawMessage("tb3", "/chatter", STRING, cdr("two"),
                                 receive_ns=time.time_ns() - 40_000_000))
        deadline = time.monotonic() + 20
        # The relay knowing of the host's subscriber does not make the host know of the relay's
        # clock queryable yet: a query sent before that has no one to answer it (3 of 35 runs
        # beside two CPU burners, none of 30 with this loop); the host's clock estimate asks again.
        replies: list[zenoh.Sample | None] = []
        while not replies and time.monotonic() < deadline:
            replies = [reply.ok for reply in host.get(clock_key("tb3"), timeout=10.0)]
        while (len(received) < 2 or not reports) and time.monotonic() < deadline:
            time.sleep(0.01)
        after = time.time_ns()
    finally:
        relay.close()
        stats.undeclare()
        subscriber.undeclare()
    first, second = (Attachment.unpack(sample.attachment.to_bytes(), "test")
                     for sample in received if sample.attachment is not None)
    assert before + shift <= first.receive_ns <= after + shift
    assert first.source_ns == 123  # the source's time is the source's, not the relay's
    # The source's receive time, moved onto the relay's clock.
    assert before + shift - 40_000_000 <= second.receive_ns <= after + shift - 40_000_000
    (reply,) = replies
    assert reply is not None
    assert str(reply.key_expr) == "swanky/tb3/clock"
    reading = ClockReading.unpack(reply.payload.to_bytes(), "test")
    assert before + shift <= reading.received_ns <= reading.replied_ns <= after + shift
    report = RelayReport.from_json(reports[0].payload.to_bytes(), "test")
    assert before + shift <= report.time_ns <= after + shift


def cdr(text: str) -> bytes:
    return b"\x00\x01\x00\x00" + text.encode()


def test_bundle_bounds_cut_at_the_byte_and_message_limits_and_leave_large_payloads_alone() -> None:
    small = b"x" * (1000 - BUNDLE_ENTRY_SIZE)  # 1000 bytes a message in the bundle
    assert list(bundle_bounds([small] * 150)) == [60, 120, 150]
    assert list(bundle_bounds([small] * 150, max_bytes=100_000)) == [100, 150]
    tiny = [b"y"] * (MAX_BUNDLE_MESSAGES + 5)
    assert list(bundle_bounds(tiny)) == [MAX_BUNDLE_MESSAGES, MAX_BUNDLE_MESSAGES + 5]
    large = b"z" * MAX_BUNDLE_BYTES
    assert list(bundle_bounds([small, small, large, small])) == [2, 3, 4]
    assert list(bundle_bounds([])) == []


def test_a_run_goes_as_bundles_with_every_message_numbered_except_on_latched_and_capped_topics(
    sessions: tuple[zenoh.Session, zenoh.Session],
) -> None:
    host, robot = sessions
    latched = TopicInfo("/map_text", STRING, None, QosProfile(durability="transient_local", depth=5))
    capped = TopicInfo("/capped", STRING, None)
    dropping = TopicInfo("/dropping", STRING, None)
    received: list[zenoh.Sample] = []
    subscriber = host.declare_subscriber("swanky/tb3/data/**", received.append)
    relay = Relay(robot, Catalog("tb3", "bag", (CHATTER, latched, capped, dropping)),
                  PolicyTable(topics={"/capped": {"max_rate": 0.001},
                                      "/dropping": {"congestion": "drop"}}))
    medium = cdr("M" * 40_000)  # two fit a blocking topic's bundle, not a dropping one's
    large = cdr("L" * MAX_BLOCKING_BUNDLE_BYTES)
    try:
        assert relay.wait_for_host(20.0)
        relay.publish_run("/chatter", [cdr(f"c{i}") for i in range(3)] + [medium, medium, large,
                                                                           cdr("c6")],
                          [100, 101, 102, 103, 104, 105, 106])
        relay.publish_run("/dropping", [cdr("d0"), cdr("d1"), medium, medium], [1, 2, 3, 4])
        relay.publish_run("/map_text", [cdr("m0"), cdr("m1")], [1, 2])
        relay.publish_run("/capped", [cdr("k0"), cdr("k1")], [1, 2])
        deadline = time.monotonic() + 20
        while len(received) < 8 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        relay.close()  # sends the capped topic's waiting message
    try:
        while len(received) < 9 and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.2)  # nothing more comes
    finally:
        subscriber.undeclare()
    by_topic: dict[str, list[tuple[int, bool, list[bytes], list[int | None]]]] = {}
    for sample in received:
        key = str(sample.key_expr)
        assert sample.attachment is not None
        attachment = Attachment.unpack(sample.attachment.to_bytes(), key)
        data = sample.payload.to_bytes()
        if attachment.bundle:
            run = bundle_run(data, attachment, key, robot="tb3", topic="", msgtype=STRING)
            assert run.log_ns is not None
            entry = (attachment.sequence, True, [bytes(p) for p in run.payloads], run.log_ns.tolist())
        else:
            entry = (attachment.sequence, False, [data], [attachment.source_ns])
        by_topic.setdefault(key.rsplit("/", 1)[-1], []).append(entry)
    assert by_topic["chatter"] == [
        (0, True, [cdr("c0"), cdr("c1"), cdr("c2"), medium, medium], [100, 101, 102, 103, 104]),
        (5, False, [large], [105]),  # too large to bundle
        (6, False, [cdr("c6")], [106]),  # a bundle of one goes as a single message
    ]
    # A topic that drops under congestion keeps its bundles under MAX_BUNDLE_BYTES (unfragmented).
    assert MAX_BUNDLE_BYTES < 2 * len(medium) < MAX_BLOCKING_BUNDLE_BYTES
    assert by_topic["dropping"] == [
        (0, True, [cdr("d0"), cdr("d1"), medium], [1, 2, 3]), (3, False, [medium], [4])]
    # A latched topic's cache keeps messages, never bundles; a capped one keeps the first
    # (sent at once) and the newest (flushed when the relay closes).
    assert by_topic["map_text"] == [(0, False, [cdr("m0")], [1]), (1, False, [cdr("m1")], [2])]
    assert by_topic["capped"] == [(0, False, [cdr("k0")], [1]), (1, False, [cdr("k1")], [2])]
    assert relay.published == 15




def test_a_topic_publisher_undeclared_while_sending_neither_raises_nor_sends_after(
    sessions: tuple[zenoh.Session, zenoh.Session],
) -> None:
    """The take loop may hold a topic's publisher when a catalog refresh undeclares it: zenoh
    raised "Already borrowed" when put and undeclare overlapped, "Undeclared publisher" when
    put came after. Neither may reach the take loop or the refresh; the message is not sent."""
    _, robot = sessions
    policy = PolicyTable().resolve(CHATTER.topic, STRING, CHATTER.qos)
    for _ in range(50):
        publisher = _TopicPublisher(robot, "tb3", CHATTER, policy, lambda messages, size: None)
        assert _undeclare_while_sending(publisher) == []


def _undeclare_while_sending(publisher: _TopicPublisher) -> list[Exception]:
    """Undeclare ``publisher`` while another thread sends on it, and go on sending a while;
    the errors either raised. Nothing may be sent after the undeclare."""
    errors: list[Exception] = []
    sending, undeclared = threading.Event(), threading.Event()

    def send_until_undeclared() -> None:
        try:
            while not undeclared.is_set():
                publisher.offer(RawMessage("tb3", "/chatter", STRING, b"\x00\x01\x00\x00" * 100), 0)
                publisher.offer_run([b"\x00\x01\x00\x00a"] * 2, [1, 2], 0, 0.0)
                sending.set()
        except Exception as err:
            errors.append(err)
        sending.set()

    thread = threading.Thread(target=send_until_undeclared)
    thread.start()
    sending.wait(10.0)
    try:
        publisher.undeclare()
    except Exception as err:
        errors.append(err)
    sent = publisher.sequence
    time.sleep(0.01)  # the sender goes on offering to the undeclared publisher
    undeclared.set()
    thread.join(timeout=30.0)
    assert publisher.sequence == sent
    return errors
