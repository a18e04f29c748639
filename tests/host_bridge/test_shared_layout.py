"""Hosts sharing a viewer (the same ``--recording-id``) send one layout with every robot of the
fleet, whichever host sends last (host_bridge/outputs/shared_layout.py): two hosts' Zenoh
sessions on loopback, each following its own robots' topics."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager

import pytest
import rerun.blueprint as rrb
import zenoh

from host_bridge.outputs.blueprint import BlueprintFollower
from host_bridge.outputs.shared_layout import SharedLayout, layout_prefix
from robot_relay.session import ZenohOptions, close_session, open_session
from tests.integration.procs import free_port

SCAN, IMU = "sensor_msgs/msg/LaserScan", "sensor_msgs/msg/Imu"
WAIT_S = 10.0


class Layouts:
    """Stands in for RerunSink.send_blueprint: the robot tabs of each layout sent."""

    def __init__(self) -> None:
        self.tabs: list[list[str]] = []
        self._changed = threading.Condition()

    def __call__(self, blueprint: rrb.Blueprint) -> None:
        root = blueprint.root_container
        names = ([str(tab.name) for tab in root.contents] if isinstance(root, rrb.Tabs)
                 else [str(root.name)])
        with self._changed:
            self.tabs.append(names)
            self._changed.notify_all()

    def wait_for(self, tabs: list[str]) -> None:
        with self._changed:
            assert self._changed.wait_for(lambda: self.tabs[-1:] == [tabs], WAIT_S), self.tabs


@contextmanager
def host_sessions() -> Iterator[Callable[[], zenoh.Session]]:
    """Sessions of hosts on one Zenoh network: the first listens on loopback, the others connect."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    opened_before: list[zenoh.Session] = []
    with ExitStack() as stack:
        def session() -> zenoh.Session:
            first = not opened_before
            opened = open_session(ZenohOptions(
                listen=(endpoint,) if first else (), connect=() if first else (endpoint,),
                multicast_scouting=False))
            stack.callback(close_session, opened)
            opened_before.append(opened)
            return opened
        yield session


def host(
    session: zenoh.Session, recording_id: str, robot: str, stack: ExitStack,
) -> tuple[BlueprintFollower, Layouts]:
    """A host of ``recording_id`` following ``robot``'s scan, sharing its layout."""
    layouts = Layouts()
    follower = BlueprintFollower(layouts, interval=0.1)
    stack.callback(follower.close)
    stack.callback(SharedLayout(session, recording_id, follower).close)
    follower.topic_seen(robot, "/scan", SCAN, f"/{robot}/scan")
    return follower, layouts


def test_two_hosts_of_one_recording_each_lay_out_every_robot() -> None:
    with host_sessions() as session, ExitStack() as stack:
        east, east_layouts = host(session(), "fleet", "east-1", stack)
        _, west_layouts = host(session(), "fleet", "west-1", stack)
        east_layouts.wait_for(["All robots", "east-1", "west-1"])
        west_layouts.wait_for(["All robots", "east-1", "west-1"])

        east.topic_seen("east-2", "/imu", IMU, "/east-2/imu")  # a robot joins one host
        west_layouts.wait_for(["All robots", "east-1", "east-2", "west-1"])


def test_a_host_that_starts_later_gets_the_others_topics_at_once() -> None:
    with host_sessions() as session, ExitStack() as stack:
        first = session()
        _, east_layouts = host(first, "fleet", "east-1", stack)
        east_layouts.wait_for(["east-1"])
        time.sleep(0.5)  # east's topics were put before west subscribed: west must ask
        _, west_layouts = host(session(), "fleet", "west-1", stack)
        west_layouts.wait_for(["All robots", "east-1", "west-1"])


def test_hosts_of_other_recordings_keep_their_own_layouts() -> None:
    with host_sessions() as session, ExitStack() as stack:
        _, east_layouts = host(session(), "fleet", "east-1", stack)
        _, lab_layouts = host(session(), "lab", "tb3", stack)
        _, west_layouts = host(session(), "fleet", "west-1", stack)
        west_layouts.wait_for(["All robots", "east-1", "west-1"])
        east_layouts.wait_for(["All robots", "east-1", "west-1"])
        assert lab_layouts.tabs == [["tb3"]]


def test_garbage_at_a_layout_key_is_named_and_changes_nothing(caplog: pytest.LogCaptureFixture) -> None:
    with host_sessions() as session, ExitStack() as stack:
        _, east_layouts = host(session(), "fleet", "east-1", stack)
        east_layouts.wait_for(["east-1"])
        intruder = session()
        time.sleep(0.5)  # connected
        bad_key = f"{layout_prefix('fleet')}/intruder"
        with caplog.at_level(logging.WARNING, logger="swanky.host"):
            intruder.put(bad_key, b'{"not": "a list"}')
            intruder.put(bad_key, b"\xff\xfe")
            deadline = time.monotonic() + WAIT_S
            while len(caplog.records) < 2 and time.monotonic() < deadline:
                time.sleep(0.05)
        assert [r.getMessage() for r in caplog.records] == [
            f"layout shared at {bad_key}: ignored, not a list of [robot, topic, type, entity path]",
            f"layout shared at {bad_key}: ignored, not JSON (Expecting value: line 1 column 1 (char 0))",
        ]
        assert east_layouts.tabs == [["east-1"]]



def test_closing_while_other_hosts_arrive_is_no_error() -> None:
    """Each host met puts this host's layout again, from Zenoh's callback thread: close() ran
    into such a put once in ``.ci/run`` (zenoh: "Already borrowed"), and with many hosts' layouts
    queued that put went to this host's own full subscriber queue and waited for ever."""
    with host_sessions() as session, ExitStack() as stack:
        first, peers = session(), session()
        time.sleep(0.5)  # connected
        for attempt in range(20):
            recording_id = f"fleet-{attempt}"
            layouts = Layouts()
            follower = BlueprintFollower(layouts, interval=0.1)
            stack.callback(follower.close)
            layout = SharedLayout(first, recording_id, follower)
            follower.topic_seen("east-1", "/scan", SCAN, "/east-1/scan")
            layouts.wait_for(["east-1"])
            assert _close_while_hosts_arrive(layout, peers, layout_prefix(recording_id)) == []


def _close_while_hosts_arrive(layout: SharedLayout, peers: zenoh.Session, prefix: str) -> list[Exception]:
    """Close ``layout`` while ``peers`` puts the layouts of 2,000 hosts it has not met; what
    close() raised. Asserts close() ended within WAIT_S."""
    errors: list[Exception] = []
    arriving = threading.Event()

    def arrive() -> None:
        for peer in range(2000):
            peers.put(f"{prefix}/peer-{peer}", b"[]")
            arriving.set()

    def close() -> None:
        try:
            layout.close()
        except Exception as err:
            errors.append(err)

    thread = threading.Thread(target=arrive)
    thread.start()
    arriving.wait(WAIT_S)
    time.sleep(0.01)
    closer = threading.Thread(target=close)
    closer.start()
    closer.join(WAIT_S)
    thread.join(WAIT_S)
    assert not closer.is_alive(), "close() still waits"
    return errors
