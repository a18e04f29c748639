"""The SLAM tap in the host: it queues and never waits on a live robot, so a robot's small
topics and the other robots never wait for its SLAM; a bag waits instead, losing nothing."""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping, Sequence
from typing import Any

import pytest

from host_bridge.core.contract import LogEntry
from host_bridge.core.decode import Decoder
from host_bridge.core.state import RobotState
from host_bridge.slam import engine
from host_bridge.slam.feeder import SlamTap
from host_bridge.slam.settings import SlamSettings
from robot_relay.wire import RawMessage
from tests.host_bridge.slam.robot_logs import LaserLog, messages, simulate

pytest.importorskip("gtsam", reason="host-side SLAM needs the [slam] extra (gtsam, small-gicp)")


class Recorder:
    """What the feeder uses of the dispatcher: decoding, warnings, logging, robot state."""

    def __init__(self) -> None:
        self.decoder = Decoder()
        self.warnings: list[tuple[str, str, str]] = []
        self.logged: list[str] = []
        self._state = RobotState()

    def warn(self, robot: str, topic: str, err: Exception, times: Mapping[str, int] | None = None) -> None:
        self.warnings.append((robot, topic, str(err)))

    def log(self, robot: str, entries: Sequence[LogEntry], times: Mapping[str, int]) -> None:
        self.logged.extend(entry.path for entry in entries)

    def robot_state(self, robot: str) -> RobotState:
        return self._state


def raw_messages(robot: str, seconds: float) -> list[RawMessage]:
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    return [RawMessage(robot, topic, msgtype, bytes(store.serialize_cdr(msg, msgtype)), None, None, stamp)
            for topic, msgtype, stamp, msg in messages(simulate(LaserLog(seconds=seconds)))]


def test_a_live_robot_whose_slam_is_slow_never_waits_and_loses_only_its_oldest_scans(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # SLAM's first scan does not end until every message has been handed over: a tap that
    # waited for SLAM would hang here (until the gate's timeout) instead of returning.
    gate = threading.Event()
    added = monkeypatch_slow_engine(monkeypatch, seconds=0.01, gate=gate)
    recorder = Recorder()
    tap = SlamTap(recorder, lambda robot: SlamSettings(enabled=True), lossless=False)
    sent = raw_messages("slow", 10.0)
    for raw in sent:  # as a live robot's thread hands them over: one at a time
        tap([raw])
    # Every message handed over, SLAM still on its first scan.
    assert not gate.is_set()
    assert added == []
    gate.set()
    tap.close()
    scans = sum(raw.topic == "/scan" for raw in sent)
    robot = tap.robots()["slow"]
    assert robot.dropped > scans / 2
    assert len(added) + robot.dropped == scans
    # Said each time scans are skipped; the dispatcher shows the first and counts the rest.
    assert {w for w in recorder.warnings if "falls behind" in w[2]} == {
        ("slow", "/scan", "/scan: SLAM falls behind this robot's scans; the oldest queued scans are skipped")}


def test_a_bag_waits_for_slam_and_maps_every_scan(monkeypatch: pytest.MonkeyPatch) -> None:
    added = monkeypatch_slow_engine(monkeypatch, seconds=0.005)
    recorder = Recorder()
    tap = SlamTap(recorder, lambda robot: SlamSettings(enabled=True), lossless=True,
                  bag_types={"/scan": "sensor_msgs/msg/LaserScan", "/odom": "nav_msgs/msg/Odometry"})
    sent = raw_messages("bag", 10.0)
    tap(sent)
    tap.close()
    assert len(added) == sum(raw.topic == "/scan" for raw in sent)
    assert tap.robots()["bag"].dropped == 0
    assert recorder.warnings == []


def test_a_bag_that_brings_minutes_of_odometry_before_its_scans_maps_every_scan() -> None:
    """An MCAP bag is read in windows of many messages, each window topic by topic: all of a
    window's odometry (here 150 s of it) may come before the first of its scans."""
    recorder = Recorder()
    tap = SlamTap(recorder, lambda robot: SlamSettings(enabled=True), lossless=True,
                  bag_types={"/scan": "sensor_msgs/msg/LaserScan", "/odom": "nav_msgs/msg/Odometry"})
    sent = raw_messages("bag", 150.0)
    for topic in ("/tf_static", "/odom", "/scan"):
        tap([raw for raw in sent if raw.topic == topic])
    tap.close()
    robot = tap.robots()["bag"]
    assert len(robot.slam.trajectory()[0]) == sum(raw.topic == "/scan" for raw in sent) == 750
    assert recorder.warnings == []


def monkeypatch_slow_engine(
    monkeypatch: pytest.MonkeyPatch, seconds: float, gate: threading.Event | None = None
) -> list[int]:
    """Slam.add taking ``seconds`` more per scan, and not before ``gate`` is set (at most 30 s);
    the stamps it was given."""
    added: list[int] = []
    real = engine.Slam.add
    lock = threading.Lock()

    def slow_add(self: engine.Slam, scan: Any, stamp_ns: int, odom: Any) -> engine.Update:
        if gate is not None:
            gate.wait(30.0)
        time.sleep(seconds)
        with lock:
            added.append(stamp_ns)
        return real(self, scan, stamp_ns, odom)

    monkeypatch.setattr(engine.Slam, "add", slow_add)
    return added
