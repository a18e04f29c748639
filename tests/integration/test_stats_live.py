"""Live health data over loopback: the relay's stats report, /_stats in Rerun, and --list."""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pytest
import zenoh
from rosbags.typesys import Stores, get_typestore

from host_bridge.core.destinations import SinkOptions
from host_bridge.inputs.base import InputItem
from host_bridge.inputs.live import LiveInput
from host_bridge.outputs.sink import RerunSink
from host_bridge.outputs.stats import StatsTap
from robot_relay.relay import Relay
from robot_relay.wire import Catalog, RawMessage, TopicInfo, stats_key
from tests.integration.procs import command, free_port, running
from tests.rrd import entity_rows

pytestmark = pytest.mark.integration

STORE = get_typestore(Stores.ROS2_HUMBLE)




def test_relay_reports_cpu_and_the_host_logs_stats(
    sessions: tuple[zenoh.Session, zenoh.Session], tmp_path: Path,
) -> None:
    host, robot = sessions
    reports: list[dict[str, Any]] = []
    raw_reports = host.declare_subscriber(
        stats_key("tb3"), lambda s: reports.append(json.loads(s.payload.to_bytes()))
    )
    data = bytes(STORE.serialize_cdr(STORE.types["std_msgs/msg/String"](data="x" * 96),
                                     "std_msgs/msg/String"))
    out = tmp_path / "stats.rrd"
    sink = RerunSink(SinkOptions(save=out))
    source = LiveInput(host, rmw_zenoh=False)
    tap = StatsTap(sink, {}, session=host)
    relay = Relay(robot, Catalog("tb3", "bag", (TopicInfo("/chat", "std_msgs/msg/String", None),)))
    stop = threading.Event()

    def publish() -> None:  # 50 Hz until stopped
        while not stop.wait(0.02):
            relay.publish(RawMessage("tb3", "/chat", "std_msgs/msg/String", data))

    def take(items: Sequence[InputItem]) -> None:  # as the dispatcher hands runs to its taps
        batch = [i for i in items if isinstance(i, RawMessage)]
        if batch:
            tap(batch)

    try:
        source.start(take)
        assert relay.wait_for_host(10.0)
        publisher = threading.Thread(target=publish)
        publisher.start()
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and len(reports) < 4:
            time.sleep(0.1)
        stop.set()
        publisher.join()
    finally:
        stop.set()
        raw_reports.undeclare()
        tap.close()
        source.close()
        relay.close()
        sink.close()
    assert len(reports) >= 4
    cores = os.cpu_count() or 1
    assert all(0.0 <= r["cpu_percent"] <= 100.0 * cores for r in reports)
    assert all(r["robot"] == "tb3" and r["version"] == 1 for r in reports)
    counts = [r["messages"] for r in reports]
    assert counts == sorted(counts)
    assert counts[-1] > counts[0]
    assert all(r["bytes"] == r["messages"] * len(data) for r in reports)

    rows = entity_rows(out)
    cpu = [r["Scalars:scalars"][0] for r in rows["/_stats/tb3/relay/cpu_percent"]]
    assert len(cpu) >= 3
    assert all(0.0 <= c <= 100.0 * cores for c in cpu)
    sent = [r["Scalars:scalars"][0] for r in rows["/_stats/tb3/relay/sent_hz"]]
    assert all(10 < s < 60 for s in sent)  # 50 Hz asked; a loaded machine sends fewer
    rates = [r["Scalars:scalars"][0] for r in rows["/_stats/tb3/chat/rate_hz"]]
    assert len(rates) >= 2
    assert all(r <= 51 for r in rates)
    assert max(rates) > 10
    kbps = [r["Scalars:scalars"][0] for r in rows["/_stats/tb3/chat/bandwidth_kbps"]]
    assert kbps == pytest.approx([r * len(data) * 8 / 1000 for r in rates])
    latency = [r["Scalars:scalars"][0] for r in rows["/_stats/tb3/chat/latency_ms"]]
    assert all(0 <= ms < 2000 for ms in latency)  # one clock: never negative
    assert all(r["Scalars:scalars"][0] == 0 for r in rows["/_stats/tb3/chat/drops"])


def test_list_shows_robots_topics_and_rates(shared_data: Path) -> None:
    bag = shared_data / "hokuyo_scan_ccny" / "laser_scan_matcher_demo.bag"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    relay = command("robot_relay.cli", "--robot", "hokuyo", "--bag", str(bag), "-l", endpoint,
                    "--no-multicast-scouting", "--wait-for-host", "60")
    host = command("host_bridge.cli", "--list", "--duration", "5", "-e", endpoint,
                   "--no-multicast-scouting")
    with running(relay) as relay_proc:
        time.sleep(3.0)
        assert relay_proc.poll() is None
        with running(host) as host_proc:
            stdout, stderr = host_proc.communicate(timeout=90)
            assert host_proc.returncode == 0, stderr
    lines = stdout.splitlines()
    assert lines[0].split() == ["robot", "topic", "type", "qos", "msgs", "rate", "bandwidth"]
    (row,) = [line.split() for line in lines[1:]]
    robot, topic, msgtype, qos, count, rate, hz, bandwidth, unit = row
    assert (robot, topic, msgtype, qos, hz, unit) == (
        "hokuyo", "/scan", "sensor_msgs/msg/LaserScan", "reliable", "Hz", "KB/s"
    )
    assert int(count) >= 10
    assert 8.0 <= float(rate) <= 12.0  # the bag's scans come at 10 Hz
    # 681 float32 ranges + header per scan, ten a second.
    assert 25.0 <= float(bandwidth) <= 32.0
