"""The swanky wire input (host_bridge/inputs/zenoh.py): samples of a robot session over loopback
-> the RawMessages, problems and robot events the host's queues receive, and robot patterns."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest
import zenoh
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from host_bridge.errors import NoClockError
from host_bridge.inputs.base import InputItem, InputProblem, MessageRun, RobotEvent
from host_bridge.inputs.queues import RobotQueues
from host_bridge.inputs.zenoh import ZenohInput, check_robot_pattern, robot_matches
from robot_relay.wire import (
    FLAG_BUNDLE,
    Attachment,
    Catalog,
    MessageDefinition,
    QosProfile,
    RawMessage,
    TopicInfo,
    alive_key,
    catalog_key,
    cdr_encoding,
    clock_key,
    data_key,
    pack_bundle,
)
from tests.host_bridge.inputs.received import TIMEOUT_S, Received

READING = "acme_msgs/msg/Reading"
READING_DEFINITION = MessageDefinition("ros2msg", "float64 celsius\nstring sensor\n")
STRING = "std_msgs/msg/String"


def reading_cdr(celsius: float, sensor: str) -> bytes:
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(READING_DEFINITION.text, READING))
    return bytes(store.serialize_cdr(store.types[READING](celsius=celsius, sensor=sensor), READING))


def string_cdr(text: str) -> bytes:
    store = get_typestore(Stores.ROS2_HUMBLE)
    return bytes(store.serialize_cdr(store.types[STRING](data=text), STRING))


def catalog(robot: str) -> Catalog:
    return Catalog(robot, "test", (
        TopicInfo("/temperature", READING, READING_DEFINITION),
        TopicInfo("/chat", STRING, None, QosProfile(durability="transient_local", depth=1)),
    ))


def messages(items: list[InputItem]) -> list[RawMessage]:
    return [item for item in items if isinstance(item, RawMessage)]


def serve_catalog(robot_session: zenoh.Session, host: zenoh.Session, robot: str) -> zenoh.Queryable[None]:
    """Answer ``robot``'s catalog as a relay does, once the host can reach the answer: a
    catalog that misses the input's first ask would leave its samples without definitions."""
    key = catalog_key(robot)
    queryable = robot_session.declare_queryable(
        key, lambda query: query.reply(key, catalog(robot).to_json())
    )
    deadline = time.monotonic() + TIMEOUT_S
    while not any(reply.ok is not None for reply in host.get(key, timeout=1.0)):
        assert time.monotonic() < deadline, f"the host never reached the catalog queryable {key}"
    return queryable


def publisher(robot_session: zenoh.Session, robot: str, topic: str) -> zenoh.Publisher:
    """A publisher on ``robot``'s ``topic`` once the input's subscription reached it (samples
    put before that go nowhere)."""
    pub = robot_session.declare_publisher(data_key(robot, topic))
    deadline = time.monotonic() + TIMEOUT_S
    # zenoh-python returns a MatchingStatus object (its stub says bool).
    while not pub.matching_status.matching:  # type: ignore[attr-defined]
        assert time.monotonic() < deadline, f"no subscriber for {data_key(robot, topic)}"
        time.sleep(0.02)
    return pub


@pytest.fixture
def queues() -> Iterator[RobotQueues]:
    queues = RobotQueues()
    yield queues
    queues.close(timeout=5.0)


def test_a_sample_becomes_a_raw_message_with_its_catalog_definition(
    sessions: tuple[zenoh.Session, zenoh.Session], queues: RobotQueues
) -> None:
    host, robot = sessions
    received = Received()
    queues.serve(received.take)
    queryable = serve_catalog(robot, host, "tb3")
    source = ZenohInput(host, queues=queues)
    try:
        data = reading_cdr(21.5, "deck")
        attachment = Attachment(sequence=7, receive_ns=1_700_000_000_000_000_123, source_ns=42)
        publisher(robot, "tb3", "/temperature").put(
            data, encoding=cdr_encoding(READING), attachment=attachment.pack()
        )
        items = received.wait_for(lambda items: len(messages(items)) >= 1)
    finally:
        source.close()
        queryable.undeclare()
    assert items == [
        RawMessage(
            robot="tb3", topic="/temperature", msgtype=READING, data=data,
            definition=READING_DEFINITION, receive_ns=1_700_000_000_000_000_123, log_ns=42,
            sequence=7,
        )
    ]


def test_unknown_attachment_version_is_a_problem_naming_the_key_and_the_next_sample_flows(
    sessions: tuple[zenoh.Session, zenoh.Session], queues: RobotQueues
) -> None:
    host, robot = sessions
    received = Received()
    queues.serve(received.take)
    queryable = serve_catalog(robot, host, "tb3")
    source = ZenohInput(host, queues=queues)
    try:
        chat = publisher(robot, "tb3", "/chat")
        future = bytearray(Attachment(sequence=1, receive_ns=2).pack())
        future[0] = 7  # the version byte
        data = string_cdr("hello")
        chat.put(data, encoding=cdr_encoding(STRING), attachment=bytes(future))
        chat.put(data, encoding=cdr_encoding(STRING), attachment=Attachment(2, 3).pack())
        items = received.wait_for(lambda items: len(items) >= 2)
    finally:
        source.close()
        queryable.undeclare()
    problem, message = items
    assert isinstance(problem, InputProblem)
    assert (problem.robot, problem.topic) == ("tb3", "/chat")
    assert str(problem.error) == (
        "attachment on 'swanky/tb3/data/chat' has wire version 7, this host speaks 2: "
        "upgrade the older side"
    )
    assert message == RawMessage("tb3", "/chat", STRING, data, None, 3, None, 2)


def test_only_the_robots_of_the_pattern_are_heard(
    sessions: tuple[zenoh.Session, zenoh.Session], queues: RobotQueues
) -> None:
    host, robot = sessions
    received = Received()
    queues.serve(received.take)
    queryables = [serve_catalog(robot, host, name) for name in ("east-1", "west-1")]
    tokens = [robot.liveliness().declare_token(alive_key(name)) for name in ("west-1", "east-1")]
    source = ZenohInput(host, robots="east-$*", queues=queues)
    try:
        east = publisher(robot, "east-1", "/chat")
        # Nothing on the host subscribes to west-1's data: put it unconditionally, before east's
        # sample, so it would have arrived first had the filter let it through.
        robot.put(data_key("west-1", "/chat"), string_cdr("west"), encoding=cdr_encoding(STRING),
                  attachment=Attachment(1, 1).pack())
        east.put(string_cdr("east"), encoding=cdr_encoding(STRING), attachment=Attachment(1, 1).pack())
        items = received.wait_for(lambda items: len(messages(items)) >= 1 and any(
            isinstance(item, InputProblem) for item in items))
    finally:
        source.close()
        for token in tokens:
            token.undeclare()
        for queryable in queryables:
            queryable.undeclare()
    assert [(m.robot, m.topic, m.data) for m in messages(items)] == [
        ("east-1", "/chat", string_cdr("east"))
    ]
    assert [item for item in items if isinstance(item, RobotEvent)] == [
        RobotEvent("east-1", True, "swanky relay")
    ]
    # These stand-in relays answer no clock query; only east-1's clock was asked for.
    assert [(item.robot, item.topic, type(item.error)) for item in items
            if isinstance(item, InputProblem)] == [("east-1", clock_key("east-1"), NoClockError)]


def test_robot_patterns() -> None:
    assert check_robot_pattern("east-$*") == "east-$*"
    with pytest.raises(Exception, match=r"tb\$\*"):
        check_robot_pattern("tb*")
    with pytest.raises(Exception, match="one non-empty chunk"):
        check_robot_pattern("a/b")
    assert robot_matches("east-a", "east-$*")
    assert not robot_matches("west-c", "east-$*")
    assert robot_matches("tb3", "*")


def test_a_bundle_becomes_one_run_with_each_message_and_a_broken_one_a_problem(
    sessions: tuple[zenoh.Session, zenoh.Session], queues: RobotQueues
) -> None:
    host, robot = sessions
    received = Received()
    queues.serve(received.take)
    queryable = serve_catalog(robot, host, "tb3")
    source = ZenohInput(host, queues=queues)
    readings = [reading_cdr(20.0 + i, f"s{i}") for i in range(3)]
    try:
        pub = publisher(robot, "tb3", "/temperature")
        bundle = Attachment(sequence=5, receive_ns=1_000, flags=FLAG_BUNDLE)
        pub.put(pack_bundle(readings, [11, 12, 13]), encoding=cdr_encoding(READING),
                attachment=bundle.pack())
        cut = pack_bundle(readings, [11, 12, 13])[:-3]
        pub.put(cut, encoding=cdr_encoding(READING), attachment=bundle.pack())
        after = Attachment(sequence=8, receive_ns=2_000, source_ns=14)
        pub.put(readings[0], encoding=cdr_encoding(READING), attachment=after.pack())
        items = received.wait_for(lambda items: len(items) >= 3)
    finally:
        source.close()
        queryable.undeclare()
    # The problem is reported at once; the messages wait for the robot's catalog, in order.
    problem, run, single = sorted(items, key=lambda item: not isinstance(item, InputProblem))
    assert isinstance(run, MessageRun)
    assert (run.robot, run.topic, run.msgtype, run.definition) == (
        "tb3", "/temperature", READING, READING_DEFINITION)
    assert [bytes(p) for p in run.payloads] == readings
    assert run.log_ns is not None
    assert run.log_ns.tolist() == [11, 12, 13]
    assert run.receive_ns is not None
    assert run.receive_ns.tolist() == [1_000] * 3
    assert run.sequence is not None
    assert run.sequence.tolist() == [5, 6, 7]
    assert list(run)[2] == RawMessage("tb3", "/temperature", READING, readings[2],
                                      READING_DEFINITION, 1_000, 13, 7)
    assert isinstance(problem, InputProblem)
    assert str(problem.error) == (
        "bundle on 'swanky/tb3/data/temperature': its 3 payload sizes add up to "
        f"{sum(map(len, readings))} bytes but {sum(map(len, readings)) - 3} follow them: "
        "a corrupt or cut-short sample")
    assert isinstance(single, RawMessage)
    assert single.sequence == 8
