"""Relay clocks measured over loopback Zenoh (host_bridge/inputs/clocks.py) by the wire input
(zenoh.py): a real Relay whose clock is shifted, its samples delivered on the PC's clock, a step
of its clock followed at its next sample."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator

import pytest
import zenoh

from host_bridge.errors import ClockOffsetError, NoClockError
from host_bridge.inputs.base import InputProblem
from host_bridge.inputs.clocks import QUERY_PERIOD_S, ClockEstimate
from host_bridge.inputs.queues import RobotQueues
from host_bridge.inputs.zenoh import ZenohInput
from robot_relay.relay import Relay
from robot_relay.wire import (
    Attachment,
    Catalog,
    MessageDefinition,
    RawMessage,
    TopicInfo,
    alive_key,
    cdr_encoding,
    clock_key,
)
from tests.host_bridge.inputs.received import TIMEOUT_S, Received
from tests.host_bridge.inputs.test_zenoh import messages, publisher, serve_catalog, string_cdr

STRING = "std_msgs/msg/String"
CHAT = TopicInfo("/chat", STRING, MessageDefinition("ros2msg", "string data"))
SHIFT_NS = 7_500_000_000
HOURS_NS = 2 * 3600 * 10**9


class ShiftedClock:
    """The PC's clock plus ``shift_ns``, which a test may step."""

    def __init__(self, shift_ns: int) -> None:
        self.shift_ns = shift_ns

    def __call__(self) -> int:
        return time.time_ns() + self.shift_ns


@pytest.fixture
def queues() -> Iterator[RobotQueues]:
    queues = RobotQueues()
    yield queues
    queues.close(timeout=5.0)


def wait_until(condition: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + TIMEOUT_S
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.005)


def test_a_shifted_relay_is_measured_and_its_samples_come_on_the_pcs_clock(
    sessions: tuple[zenoh.Session, zenoh.Session], queues: RobotQueues
) -> None:
    host, robot = sessions
    received = Received()
    queues.serve(received.take)
    source = ZenohInput(host, queues=queues)
    estimates: list[ClockEstimate] = []
    source.clocks.watch(lambda name, estimate: estimates.append(estimate))
    relay = Relay(robot, Catalog("tb3", "ros2", (CHAT,)), clock=ShiftedClock(SHIFT_NS))
    try:
        assert relay.wait_for_host(TIMEOUT_S)
        # Published at once: the sample waits for the relay's first burst, as for its catalog.
        before = time.time_ns()
        relay.publish(RawMessage("tb3", "/chat", STRING, string_cdr("hello"), log_ns=42))
        items = received.wait_for(lambda items: len(messages(items)) >= 1)
        after = time.time_ns()
        offset = source.clocks.offset_ns("tb3")
    finally:
        relay.close()
        source.close()
    (message,) = messages(items)
    assert message.receive_ns is not None
    assert before <= message.receive_ns <= after  # on the PC's clock, not 7.5 s ahead
    assert message.log_ns == 42  # the source's time is left as it came
    # Loopback round trips take well under a millisecond; the truth is within each bound.
    assert abs(offset - SHIFT_NS) < 1_000_000
    assert len(estimates) >= 8  # the burst
    assert all(abs(e.offset_ns - SHIFT_NS) <= e.uncertainty_ns for e in estimates)
    (problem,) = [item for item in items if isinstance(item, InputProblem)]
    assert (problem.robot, problem.topic) == ("tb3", clock_key("tb3"))
    assert isinstance(problem.error, ClockOffsetError)
    assert str(problem.error).startswith("robot tb3's clock is 7.500 s ahead of this PC's (±")
    assert "receive_time and latency_ms are corrected" in str(problem.error)


def test_a_step_of_the_relays_clock_is_followed_at_its_next_sample(
    sessions: tuple[zenoh.Session, zenoh.Session], queues: RobotQueues
) -> None:
    """A Pi booted 2 h behind; NTP reaches it and steps its clock to the truth. Its next
    sample arrives 2 h "late" by the old estimate, which prompts a query at once instead of at
    the next period."""
    host, robot = sessions
    received = Received()
    queues.serve(received.take)
    source = ZenohInput(host, queues=queues)
    estimates: list[ClockEstimate] = []
    changed = threading.Event()

    def watch(robot: str, estimate: ClockEstimate) -> None:
        estimates.append(estimate)
        changed.set()

    source.clocks.watch(watch)
    clock = ShiftedClock(-HOURS_NS)
    relay = Relay(robot, Catalog("tb3", "ros2", (CHAT,)), clock=clock)
    try:
        assert relay.wait_for_host(TIMEOUT_S)
        relay.publish(RawMessage("tb3", "/chat", STRING, string_cdr("before")))
        received.wait_for(lambda items: len(messages(items)) >= 1)
        assert abs(source.clocks.offset_ns("tb3") + HOURS_NS) < 1_000_000
        # Just after a periodic query, so that only the sample can prompt the next one soon.
        changed.clear()
        wait_until(changed.is_set, "no periodic clock query")
        clock.shift_ns = 0
        stepped = time.monotonic()
        relay.publish(RawMessage("tb3", "/chat", STRING, string_cdr("after")))
        wait_until(lambda: abs(source.clocks.offset_ns("tb3")) < 1_000_000, "the step not followed")
        followed_s = time.monotonic() - stepped
        before = time.time_ns()
        relay.publish(RawMessage("tb3", "/chat", STRING, string_cdr("later")))
        items = received.wait_for(lambda items: len(messages(items)) >= 3)
        after = time.time_ns()
        assert len(messages(items)) == 3
    finally:
        relay.close()
        source.close()
    assert followed_s < QUERY_PERIOD_S / 2
    jumped = [e for e in estimates if e.jumped]
    assert len(jumped) == 1
    assert abs(jumped[0].offset_ns) <= jumped[0].uncertainty_ns
    # The sample that prompted the query was (most likely) delivered with the old correction,
    # 2 h in the future; the next one is on the PC's clock.
    later = messages(items)[-1]
    assert later.receive_ns is not None
    assert before <= later.receive_ns <= after


def test_a_relay_that_does_not_answer_the_clock_query_is_said_once_and_left_uncorrected(
    sessions: tuple[zenoh.Session, zenoh.Session], queues: RobotQueues
) -> None:
    """A relay older than the clock query: its samples come at once, their receive times as
    the relay sent them."""
    host, robot = sessions
    received = Received()
    queues.serve(received.take)
    queryable = serve_catalog(robot, host, "old")
    token = robot.liveliness().declare_token(alive_key("old"))
    source = ZenohInput(host, queues=queues)
    try:
        chat = publisher(robot, "old", "/chat")
        for sequence in range(3):
            chat.put(string_cdr("hi"), encoding=cdr_encoding(STRING),
                     attachment=Attachment(sequence, 1_000 + sequence).pack())
        early = received.wait_for(lambda items: len(messages(items)) >= 3)
        # Said once the first burst and NO_ANSWER_AFTER_S went unanswered, not at once: a relay
        # that has just joined may not be reachable by its clock query yet.
        assert not [item for item in early if isinstance(item, InputProblem)]
        items = received.wait_for(
            lambda items: any(isinstance(item, InputProblem) for item in items))
        offset = source.clocks.offset_ns("old")
    finally:
        source.close()
        token.undeclare()
        queryable.undeclare()
    assert [m.receive_ns for m in messages(items)] == [1_000, 1_001, 1_002]
    assert offset == 0
    (problem,) = [item for item in items if isinstance(item, InputProblem)]
    assert (problem.robot, problem.topic) == ("old", clock_key("old"))
    assert isinstance(problem.error, NoClockError)
    assert str(problem.error) == (
        "robot old's relay does not answer the clock query (swanky/old/clock; a relay older than "
        "this host?): its receive_time and latency_ms stay on its own clock, uncorrected"
    )
