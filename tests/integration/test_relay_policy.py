"""Relay policy over real Zenoh on loopback: demand-driven subscription, compression, rate cap."""

from __future__ import annotations

import os
import statistics
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from rosbags.rosbag2 import Writer
from rosbags.typesys import Stores, get_typestore

from host_bridge.cli import main as host_main
from host_bridge.inputs.live import LiveInput
from robot_relay.policy import PolicyTable
from robot_relay.relay import Relay
from robot_relay.sources.ros2 import Ros2Source
from robot_relay.wire import (
    FLAG_LZ4,
    FLAG_ZSTD,
    Attachment,
    Catalog,
    QosProfile,
    RawMessage,
    TopicInfo,
    data_key,
)
from tests.host_bridge.inputs.received import Received
from tests.integration.procs import command, free_port, running
from tests.robot_relay.test_ros2_source import FakeNode, latched, make_source, sensor
from tests.rrd import entity_rows

pytestmark = pytest.mark.integration

STORE = get_typestore(Stores.ROS2_HUMBLE)


def wait_until(condition: Callable[[], bool], timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return condition()


def serialize(msg: Any, msgtype: str) -> bytes:
    return bytes(STORE.serialize_cdr(msg, msgtype))


def laser_scan(stamp_ns: int, ranges: np.ndarray) -> bytes:
    types = STORE.types
    header = types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9),
        frame_id="laser",
    )
    scan = types["sensor_msgs/msg/LaserScan"](
        header=header, angle_min=-np.pi, angle_max=np.pi, angle_increment=2 * np.pi / len(ranges),
        time_increment=0.0, scan_time=0.1, range_min=0.1, range_max=10.0,
        ranges=ranges.astype(np.float32), intensities=np.zeros(0, np.float32),
    )
    return serialize(scan, "sensor_msgs/msg/LaserScan")


def test_a_ros_topic_is_subscribed_only_while_a_host_listens(
    sessions: tuple[zenoh.Session, zenoh.Session],
) -> None:
    host, robot = sessions
    node = FakeNode({"/scan": (["sensor_msgs/msg/LaserScan"], [sensor()]),
                     "/tf_static": (["tf2_msgs/msg/TFMessage"], [latched()])})
    source: Ros2Source = make_source(node)
    relay = Relay(robot, Catalog("tb3", "ros2", ()), demand=source)
    forwarded: dict[str, int] = {"/scan": 0, "/tf_static": 0}

    def forward(raw: RawMessage) -> None:
        forwarded[raw.topic] += 1
        relay.publish(raw)

    stop = threading.Event()

    def ros_publishers() -> None:
        """Stands in for the ROS graph: /scan at 50 Hz to whoever subscribed."""
        while not stop.wait(0.02):
            callback = node.callbacks.get("/scan")
            if callback is not None:
                callback(b"\x00\x01\x00\x00" + b"scan" * 10, None)

    received: list[str] = []
    threads = [
        threading.Thread(target=source.run, args=(relay.update_catalog, forward, stop, 0.2)),
        threading.Thread(target=ros_publishers),
    ]
    for thread in threads:
        thread.start()
    try:
        # A host listening to /tf_static only: the latched topic is subscribed (always), /scan not.
        only_tf = host.declare_subscriber(data_key("tb3", "/tf_static"), lambda s: None)
        assert wait_until(lambda: node.subscribed == ["/tf_static"])
        time.sleep(1.0)
        assert node.subscribed == ["/tf_static"]
        assert forwarded["/scan"] == 0
        assert relay.published == 0

        scans = host.declare_subscriber(data_key("tb3", "/scan"),
                                        lambda s: received.append(str(s.key_expr)))
        assert wait_until(lambda: node.subscribed == ["/tf_static", "/scan"])
        assert wait_until(lambda: len(received) >= 10)
        assert set(received) == {"swanky/tb3/data/scan"}

        scans.undeclare()
        assert wait_until(lambda: node.unsubscribed == ["/scan"])
        time.sleep(0.2)  # samples already in flight
        after = forwarded["/scan"]
        time.sleep(0.5)
        assert forwarded["/scan"] == after  # no subscription, no traffic
        assert node.unsubscribed == ["/scan"]
        only_tf.undeclare()
    finally:
        stop.set()
        for thread in threads:
            thread.join(timeout=10)
        source.close()
        relay.close()
    assert all(not thread.is_alive() for thread in threads)


def test_compressed_payloads_reach_the_host_byte_for_byte(
    sessions: tuple[zenoh.Session, zenoh.Session],
) -> None:
    host, robot = sessions
    grid_type = STORE.types["nav_msgs/msg/OccupancyGrid"]
    info = STORE.types["nav_msgs/msg/MapMetaData"](
        map_load_time=STORE.types["builtin_interfaces/msg/Time"](sec=0, nanosec=0), resolution=0.05,
        width=200, height=200, origin=STORE.types["geometry_msgs/msg/Pose"](
            position=STORE.types["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
            orientation=STORE.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        ),
    )
    cells = np.zeros((200, 200), np.int8)
    cells[50:150, 50:150] = 100
    cells[:, :10] = -1
    grid = serialize(grid_type(header=STORE.types["std_msgs/msg/Header"](
        stamp=STORE.types["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="map",
    ), info=info, data=cells.ravel()), "nav_msgs/msg/OccupancyGrid")
    scans = [laser_scan(10**9 + i, np.full(720, 2.5 + i)) for i in range(3)]
    noise = serialize(STORE.types["std_msgs/msg/String"](data=os.urandom(3000).hex()[:3000]),
                      "std_msgs/msg/String")
    catalog = Catalog("tb3", "bag", (
        TopicInfo("/map", "nav_msgs/msg/OccupancyGrid", None,
                  QosProfile(durability="transient_local", depth=1)),
        TopicInfo("/scan", "sensor_msgs/msg/LaserScan", None),
        TopicInfo("/noise", "std_msgs/msg/String", None),
    ))
    policies = PolicyTable(topics={"/map": {"compression": "zstd"}, "*": {"compression": "lz4"}})
    wire: list[tuple[str, int, int]] = []  # (key, flags, payload size) as the wire carries them
    raw_view = host.declare_subscriber(
        "swanky/tb3/data/**",
        lambda s: wire.append((str(s.key_expr),
                               Attachment.unpack(s.attachment.to_bytes(), "").flags,  # type: ignore[union-attr]
                               len(s.payload.to_bytes()))),
    )
    relay = Relay(robot, catalog, policies)
    source = LiveInput(host, rmw_zenoh=False)
    try:
        assert relay.wait_for_host(10.0)
        time.sleep(0.5)  # the advanced subscriber's late-publisher detection settles
        sent = [RawMessage("tb3", "/map", "nav_msgs/msg/OccupancyGrid", grid)]
        sent += [RawMessage("tb3", "/scan", "sensor_msgs/msg/LaserScan", s) for s in scans]
        sent.append(RawMessage("tb3", "/noise", "std_msgs/msg/String", noise))
        for raw in sent:
            relay.publish(raw)
        received = Received()
        source.start(received.take)
        # Every message, whatever else comes (the relay joining) and in whichever order the
        # robot's two threads (small and heavy topics) hand them over.
        items = received.wait_for(
            lambda items: sum(isinstance(i, RawMessage) for i in items) >= len(sent))
    finally:
        source.close()
        raw_view.undeclare()
        relay.close()
    got = {(i.topic, bytes(i.data)) for i in items if isinstance(i, RawMessage)}
    assert got == {(raw.topic, bytes(raw.data)) for raw in sent}
    by_key = {(key, flags) for key, flags, _ in wire}
    assert by_key == {("swanky/tb3/data/map", FLAG_ZSTD), ("swanky/tb3/data/scan", FLAG_LZ4),
                      ("swanky/tb3/data/noise", 0)}  # incompressible: sent as it is
    sizes = {key: size for key, _, size in wire}
    assert sizes["swanky/tb3/data/map"] < len(grid) // 20
    assert sizes["swanky/tb3/data/scan"] < len(scans[0]) // 4
    assert sizes["swanky/tb3/data/noise"] == len(noise)


def write_bag(path: Path) -> None:
    """3 s: /level (Float64 = its index) at 100 Hz, /scan at 10 Hz."""
    float64 = STORE.types["std_msgs/msg/Float64"]
    with Writer(path, version=9) as writer:
        level = writer.add_connection("/level", "std_msgs/msg/Float64", typestore=STORE)
        scan = writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=STORE)
        start = 1_700_000_000 * 10**9
        for i in range(300):
            stamp = start + i * 10**7
            writer.write(level, stamp, serialize(float64(data=float(i)), "std_msgs/msg/Float64"))
            if i % 10 == 0:
                ranges = 1.0 + (np.arange(360) % 7) * 0.25
                writer.write(scan, stamp, laser_scan(stamp, ranges))


def test_rate_cap_and_compression_through_relay_and_host_processes(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    write_bag(bag)
    config = tmp_path / "relay.yaml"
    config.write_text("robot: capped\npolicy:\n  /level: {max_rate: 10}\n  /scan: {compression: lz4}\n")
    port = free_port()
    out = tmp_path / "live.rrd"
    host = command("host_bridge.cli", "-l", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting",
                   "--save", str(out), "--until-idle", "6", "--duration", "90")
    relay = command("robot_relay.cli", "--config", str(config), "--bag", str(bag), "--rate", "1",
                    "-e", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting", "--wait-for-host", "30")
    with running(host) as host_proc:
        time.sleep(1.0)
        with running(relay) as relay_proc:
            assert relay_proc.wait(timeout=60) == 0, relay_proc.stderr.read() if relay_proc.stderr else ""
        assert host_proc.wait(timeout=60) == 0
    rows = entity_rows(out)
    levels = rows["/capped/level"]
    values = [int(r["Scalars:scalars"][0]) for r in levels]
    receive = [r["receive_time"] for r in levels]
    rate = (len(levels) - 1) / ((receive[-1] - receive[0]) / 1e9)
    # 100 Hz for 3 s capped at 10 Hz: ~30 messages, each the newest, the last one included.
    assert 26 <= len(levels) <= 32, values
    assert 8.0 <= rate <= 10.5, (rate, receive)
    assert values[0] == 0
    assert values[-1] == 299
    assert values == sorted(values)
    assert 9 <= statistics.median(np.diff(values).tolist()) <= 11
    # receive_time is when the relay got each message, a little before it went out.
    assert 0.09e9 <= statistics.median(np.diff(receive).tolist()) <= 0.11e9, np.diff(receive)

    # lz4 on the wire, the same scans as converting the bag offline.
    offline = tmp_path / "offline.rrd"
    assert host_main(["--bag", str(bag), "--robot", "capped", "--save", str(offline)]) == 0
    live_scans = rows["/capped/scan"]
    offline_scans = entity_rows(offline)["/capped/scan"]
    assert len(live_scans) == len(offline_scans) == 30
    for live_row, offline_row in zip(live_scans, offline_scans, strict=True):
        assert live_row["ros_time"] == offline_row["ros_time"]
        assert live_row["Points3D:positions"] == offline_row["Points3D:positions"]
    assert len(offline_scans[0]["Points3D:positions"]) == 360
