"""The demo bag: a rosbag2 (MCAP or sqlite3) that reads back with its QoS, and decodes with
the official MCAP reader."""

from __future__ import annotations

import threading
from collections import Counter
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.interfaces import ConnectionExtRosbag2, QosDurability

from host_bridge.demo import bag, messages, robot
from host_bridge.errors import InputError
from tests.host_bridge.demo.support import stamp_ns

LATCHED = {"/tf_static", "/robot_description", "/ground_truth/walls"}


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_demo_bag_reads_back(tmp_path: Path, storage: Literal["mcap", "sqlite3"]) -> None:
    expected = Counter(m.topic for m in messages.simulate(2.0))
    path = bag.write_demo_bag(tmp_path / "demo", 2.0, storage=storage)
    with AnyReader([path], default_typestore=messages.typestore()) as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == {
            spec.topic: spec.msgtype for spec in messages.TOPICS
        }
        durability = {}
        for c in reader.connections:
            assert isinstance(c.ext, ConnectionExtRosbag2)
            durability[c.topic] = c.ext.offered_qos_profiles[0].durability
        assert {t for t, d in durability.items() if d is QosDurability.TRANSIENT_LOCAL} == LATCHED
        assert {d for t, d in durability.items() if t not in LATCHED} == {QosDurability.VOLATILE}
        read: Counter[str] = Counter()
        for conn, log_ns, raw in reader.messages():
            msg: Any = reader.deserialize(raw, conn.msgtype)
            if conn.topic == "/scan":
                assert len(msg.ranges) == 360
                assert stamp_ns(msg.header) == log_ns
            read[conn.topic] += 1
        assert read == expected
    with pytest.raises(InputError, match="exists already"):
        bag.write_demo_bag(path, 1.0, storage=storage)


def test_demo_mcap_decodes_with_the_official_mcap_reader(tmp_path: Path) -> None:
    """An independent ROS 2 CDR decoder agrees on the recorded schemas and payloads."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path = bag.write_demo_bag(tmp_path / "demo", 1.0)
    (mcap_file,) = path.glob("*.mcap")
    firsts: dict[str, messages.SimMessage] = {}
    for m in messages.simulate(1.0):
        firsts.setdefault(m.topic, m)
    store = messages.typestore()
    expected_scan: Any = store.deserialize_cdr(firsts["/scan"].data, "sensor_msgs/msg/LaserScan")
    expected_cloud = firsts["/camera/depth/points"]
    compared = 0
    topics: Counter[str] = Counter()
    with mcap_file.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            topics[channel.topic] += 1
            assert schema is not None
            assert schema.name == next(s.msgtype for s in messages.TOPICS if s.topic == channel.topic)
            if message.log_time != firsts[channel.topic].log_ns:
                continue
            if channel.topic == "/scan":
                np.testing.assert_array_equal(
                    np.asarray(decoded.ranges, np.float32), expected_scan.ranges
                )
                assert decoded.header.frame_id == "base_scan"
                compared += 1
            elif channel.topic == "/camera/depth/points":
                assert [f.name for f in decoded.fields] == ["x", "y", "z", "rgb"]
                expected: Any = store.deserialize_cdr(expected_cloud.data, expected_cloud.msgtype)
                assert bytes(decoded.data) == bytes(expected.data)
                compared += 1
            elif channel.topic == "/robot_description":
                assert decoded.data == robot.robot_description()
                compared += 1
    assert compared == 3
    assert topics == Counter(m.topic for m in messages.simulate(1.0))


def test_a_stop_abandons_the_bag_unfinished(tmp_path: Path) -> None:
    """The host stopping while the demo simulates: no more messages, and no metadata written
    (rosbags takes a second for it), so nothing reads the bag as complete."""
    stop = threading.Event()
    stop.set()
    path = bag.write_demo_bag(tmp_path / "demo", 60.0, stop=stop)
    assert not (path / "metadata.yaml").exists()
    with pytest.raises(FileNotFoundError, match="metadata"):
        AnyReader([path]).open()
