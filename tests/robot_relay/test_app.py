"""robot_relay/app.py runs a Source: a fake one written against the protocol (and a real bag)
relayed over a loopback Zenoh session to a subscriber; a stop closes everything, the source
first."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path

import pytest
import zenoh

from host_bridge.inputs.zenoh import bundle_run
from robot_relay import app
from robot_relay.session import ZenohOptions
from robot_relay.sources.base import Outlet, Source
from robot_relay.wire import (
    Attachment,
    Catalog,
    RawMessage,
    TopicInfo,
    alive_key,
    catalog_key,
    data_key,
)
from tests.integration.procs import free_port, open_loopback
from tests.robot_relay.test_bag_source import chatter_bag, chatter_cdr

ROBOT = "fake"
STRING = "std_msgs/msg/String"


def wait_until(condition: Callable[[], bool], timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.02)


def robot_alive(host: zenoh.Session) -> bool:
    return any(reply.ok is not None for reply in host.liveliness().get(alive_key(ROBOT), timeout=2.0))


class FakeSource:
    """A live-like source: one topic known at start, a second one discovered later; it sends
    three messages once a host wants /chatter."""

    def __init__(self, host: zenoh.Session) -> None:
        self.host = host
        self.events: list[str] = []
        self.alive_at_close: bool | None = None
        self._wanted = threading.Event()
        self._thread: threading.Thread | None = None

    def catalog(self) -> Catalog:
        return Catalog(ROBOT, "ros2", (TopicInfo("/chatter", STRING, None),))

    def start(self, outlet: Outlet) -> None:
        self.events.append("start")

        def send() -> None:
            if not self._wanted.wait(20):
                return
            for i in range(3):
                outlet.publish(RawMessage(ROBOT, "/chatter", STRING, f"cdr {i}".encode()))
            outlet.update_catalog(Catalog(ROBOT, "ros2", (
                TopicInfo("/chatter", STRING, None), TopicInfo("/odom", "nav_msgs/msg/Odometry", None),
            )))

        self._thread = threading.Thread(target=send, name="fake-source")
        self._thread.start()

    def ended(self) -> bool:
        return False

    def on_demand(self, topic: str, wanted: bool) -> None:
        self.events.append(f"{topic} {'wanted' if wanted else 'unwanted'}")
        if topic == "/chatter" and wanted:
            self._wanted.set()

    def drop_counts(self) -> Mapping[str, int]:
        return {"/chatter": 0}

    def close(self) -> None:
        if self._thread is not None:
            self._thread.join()
        self.events.append("close")
        self.alive_at_close = robot_alive(self.host)


def test_the_app_relays_a_source_until_stopped_and_closes_the_source_first() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    host = open_loopback("-l", endpoint)
    received: list[bytes] = []
    subscriber = host.declare_subscriber(
        data_key(ROBOT, "/chatter"), lambda sample: received.append(sample.payload.to_bytes())
    )
    options = app.RelayOptions(
        robot=ROBOT, zenoh=ZenohOptions(connect=(endpoint,), multicast_scouting=False)
    )
    fake = FakeSource(host)
    source: Source = fake
    stop = threading.Event()
    codes: list[int] = []
    runner = threading.Thread(target=lambda: codes.append(app.relay_source(options, source, stop)))
    runner.start()
    try:
        wait_until(lambda: len(received) == 3)
        assert received == [b"cdr 0", b"cdr 1", b"cdr 2"]

        def topics() -> list[str]:
            replies = [r.ok for r in host.get(catalog_key(ROBOT), timeout=2.0) if r.ok is not None]
            if not replies:
                return []
            catalog = Catalog.from_json(replies[0].payload.to_bytes(), "test")
            return [info.topic for info in catalog.topics]

        wait_until(lambda: topics() == ["/chatter", "/odom"])
        # The host listened before the relay declared /chatter: demand may come before start.
        assert sorted(fake.events) == ["/chatter wanted", "start"]
    finally:
        stop.set()
        runner.join(timeout=30)
        subscriber.undeclare()
    try:
        assert codes == [0]
        assert fake.events[-1] == "close"
        assert fake.alive_at_close is True  # the relay was still up when the source closed
        wait_until(lambda: not robot_alive(host))  # then the relay and its session went
    finally:
        host.close()


def test_the_app_replays_a_bag_to_a_host_and_ends(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    host = open_loopback("-l", endpoint)
    received: list[bytes] = []
    samples: list[Attachment] = []

    def unbundle(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        assert sample.attachment is not None
        samples.append(Attachment.unpack(sample.attachment.to_bytes(), key))
        run = bundle_run(sample.payload.to_bytes(), samples[-1], key, robot=ROBOT,
                         topic="/chatter", msgtype=STRING)
        received.extend(bytes(payload) for payload in run.payloads)

    subscriber = host.declare_subscriber(data_key(ROBOT, "/chatter"), unbundle)
    options = app.RelayOptions(
        robot=ROBOT, zenoh=ZenohOptions(connect=(endpoint,), multicast_scouting=False),
        bag=chatter_bag(tmp_path / "bag"), rate=0, wait_for_host=20.0,
    )
    try:
        assert app.run(options, threading.Event()) == 0
        wait_until(lambda: len(received) == 3)
        assert received == [chatter_cdr(f"hello {i}") for i in range(3)]
        # Unpaced, the replay hands the three over at once: one bundle, sequence numbers 0-2.
        assert [(a.bundle, a.sequence) for a in samples] == [(True, 0)]
        # Nothing of the bag matches: said, and nothing is opened.
        nothing = app.RelayOptions(robot=ROBOT, bag=options.bag, topics=("/none",))
        assert app.run(nothing, threading.Event()) == 1
    finally:
        subscriber.undeclare()
        host.close()


@pytest.mark.parametrize("wait_for_host", [None, 3600.0], ids=["for-ever", "3600-s"])
def test_a_replay_waiting_for_a_host_ends_when_stopped(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, wait_for_host: float | None
) -> None:
    """Issue 22: the wait for a host woke on nothing but a host, so a stop signal was ignored."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    observer = open_loopback("-l", endpoint)  # sees the relay's token, subscribes to nothing
    options = app.RelayOptions(
        robot=ROBOT, zenoh=ZenohOptions(connect=(endpoint,), multicast_scouting=False),
        bag=chatter_bag(tmp_path / "bag"), rate=1.0, wait_for_host=wait_for_host,
    )
    stop = threading.Event()
    codes: list[int] = []
    relay = threading.Thread(target=lambda: codes.append(app.run(options, stop)), daemon=True)
    caplog.set_level(logging.INFO, "swanky.relay")
    relay.start()
    try:
        wait_until(lambda: robot_alive(observer))
        stop.set()
        stopped = time.monotonic()
        relay.join(20.0)
        took = time.monotonic() - stopped
    finally:
        observer.close()
    assert codes == [0]
    assert took < 2.0, took  # polled every STOP_POLL_S (0.05 s), then closed
    assert f"robot {ROBOT}: stopped before a host subscribed; nothing replayed" in caplog.text
