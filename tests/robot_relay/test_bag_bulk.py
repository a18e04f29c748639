"""An indexed MCAP replayed in bulk (robot_relay/sources/mcap.py) gives the relay exactly what the
record-by-record rosbags path gives: every topic's payloads and log times in the same order, so
over a Relay the same samples carry the same wire sequence numbers; a file the bulk reader does
not take is replayed by rosbags, and a damaged chunk costs that chunk only, named once.

The bags are written here: a rosbag2 by rosbags' Writer with zstd chunks (its storage
compression; 1 MiB chunks), and a bare .mcap with lz4 chunks by the ``mcap`` package's writer
(rosbags writes no lz4 chunks), each holding Imu, String, a latched TFMessage and 100 KB images
(larger than a bundle, and than the reader's memoryview size), every topic spanning chunks.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from host_bridge.inputs.zenoh import bundle_run
from robot_relay.policy import PolicyTable
from robot_relay.relay import Relay
from robot_relay.sources.bag import BagSource
from robot_relay.sources.mcap import McapFile
from robot_relay.wire import Attachment, Catalog, TopicInfo
from tests.host_bridge.test_corrupt_bags import (
    chunk_indexes,
    field_data,
    held_speeds,
    skipped_chunk,
)
from tests.host_bridge.test_corrupt_bags import write_mcap as write_speed_mode_mcap

mcap_writer = pytest.importorskip("mcap.writer")

STORE = get_typestore(Stores.ROS2_HUMBLE)
T = STORE.types
T0 = 1_700_000_000_000_000_000
MS = 1_000_000
IMU, STRING = "sensor_msgs/msg/Imu", "std_msgs/msg/String"
TF, IMAGE = "tf2_msgs/msg/TFMessage", "sensor_msgs/msg/Image"
TYPES = {"/imu": IMU, "/chatter": STRING, "/tf_static": TF, "/camera/image_raw": IMAGE}
COUNTS = {"/imu": 600, "/chatter": 300, "/tf_static": 2, "/camera/image_raw": 24}
IMAGE_WIDTH = 200  # 200 x 170 rgb8: 102,000 bytes of pixels

Run = tuple[TopicInfo, Sequence[bytes | memoryview], Sequence[int]]
PerTopic = dict[str, list[tuple[bytes, int]]]


def header(log_ns: int, frame: str) -> Any:
    stamp = T["builtin_interfaces/msg/Time"](sec=log_ns // 10**9, nanosec=log_ns % 10**9)
    return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)


def cdr(topic: str, i: int, log_ns: int) -> bytes:
    """Message ``i`` of ``topic``, each one's bytes its own."""
    if topic == "/imu":
        message = T[IMU](
            header=header(log_ns, "imu_link"),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=i / 1000, w=1.0),
            orientation_covariance=np.full(9, i, np.float64),
            angular_velocity=T["geometry_msgs/msg/Vector3"](x=float(i), y=0.0, z=0.0),
            angular_velocity_covariance=np.zeros(9), linear_acceleration_covariance=np.zeros(9),
            linear_acceleration=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=9.81))
    elif topic == "/chatter":
        message = T[STRING](data=f"hello {i}")
    elif topic == "/tf_static":
        message = T[TF](transforms=[T["geometry_msgs/msg/TransformStamped"](
            header=header(log_ns, "base_link"), child_frame_id=f"sensor_{i}",
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=float(i), y=0.0, z=0.0),
                rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)))])
    else:
        message = T[IMAGE](
            header=header(log_ns, "camera"), height=170, width=IMAGE_WIDTH, encoding="rgb8",
            is_bigendian=0, step=3 * IMAGE_WIDTH,
            data=((np.arange(170 * 3 * IMAGE_WIDTH) + i) % 251).astype(np.uint8))
    return bytes(STORE.serialize_cdr(message, TYPES[topic]))


def bag_messages() -> list[tuple[str, int, bytes]]:
    """(topic, log time, CDR) in log-time order over 3 s: Imu at 200 Hz, String at 100 Hz on
    every other Imu's time (ties between topics), images at 8 Hz, two /tf_static at the start."""
    spacing = {"/imu": 5 * MS, "/chatter": 10 * MS, "/tf_static": 1, "/camera/image_raw": 125 * MS}
    messages = [(topic, T0 + i * spacing[topic], i) for topic in TYPES for i in range(COUNTS[topic])]
    messages.sort(key=lambda m: m[1])  # stable: ties keep the topics' order above
    return [(topic, log_ns, cdr(topic, i, log_ns)) for topic, log_ns, i in messages]


def written() -> PerTopic:
    per_topic: PerTopic = {}
    for topic, log_ns, data in bag_messages():
        per_topic.setdefault(topic, []).append((data, log_ns))
    return per_topic


def rosbags_zstd_bag(path: Path) -> Path:
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with writer:
        connections = {topic: writer.add_connection(topic, msgtype, typestore=STORE)
                       for topic, msgtype in TYPES.items()}
        for topic, log_ns, data in bag_messages():
            writer.write(connections[topic], log_ns, data)
    return path


def mcap_lz4_bag(path: Path, **options: Any) -> Path:
    with path.open("wb") as stream:
        writer = mcap_writer.Writer(stream, chunk_size=64 * 1024,
                                    compression=mcap_writer.CompressionType.LZ4, **options)
        writer.start(profile="ros2", library="swanky tests")
        channels = {}
        for topic, msgtype in TYPES.items():
            text = STORE.generate_msgdef(msgtype, ros_version=2)[0]
            schema = writer.register_schema(msgtype, "ros2msg", text.encode())
            channels[topic] = writer.register_channel(topic, "cdr", schema)
        for sequence, (topic, log_ns, data) in enumerate(bag_messages()):
            writer.add_message(channels[topic], log_ns, data, log_ns, sequence)
        writer.finish()
    return path


@pytest.fixture(params=["zstd", "lz4"])
def bag(request: pytest.FixtureRequest, tmp_path: Path) -> Path:
    if request.param == "zstd":
        return rosbags_zstd_bag(tmp_path / "zstd")
    return mcap_lz4_bag(tmp_path / "lz4.mcap")


def per_topic(runs: Iterable[Run]) -> PerTopic:
    got: PerTopic = {}
    for info, payloads, log_ns in runs:
        got.setdefault(info.topic, []).extend(
            (bytes(data), stamp) for data, stamp in zip(payloads, log_ns, strict=True))
    return got


def record_runs(bag: BagSource) -> list[Run]:
    """The runs of the record-by-record path, which every bag took before the bulk reader."""
    bag.bulk_files = lambda: None  # type: ignore[method-assign]
    try:
        return list(bag.runs())
    finally:
        del bag.bulk_files


def bulk_runs(bag: BagSource) -> list[Run]:
    """The runs of the bulk path; rosbags' record reader must not be asked for a message."""

    def no_records() -> Iterator[Any]:
        raise AssertionError("rosbags read a record")

    bag._read = no_records  # type: ignore[method-assign]
    try:
        return list(bag.runs())
    finally:
        del bag._read


def test_the_bag_has_several_chunks_and_every_topic_spans_them(bag: Path) -> None:
    with BagSource(bag, "tb3") as source:
        files = source.bulk_files()
        assert files is not None
        [opened] = files
        assert isinstance(opened, McapFile)
        with opened:
            chunks = opened.chunks
    assert {chunk.compression for chunk in chunks} == {bag.name.removesuffix(".mcap")}
    assert len(chunks) >= 3
    for topic, messages in written().items():
        holding = {n for n, chunk in enumerate(chunks) for _, log_ns in messages
                   if chunk.start_ns <= log_ns <= chunk.end_ns}
        assert len(holding) >= (1 if topic == "/tf_static" else 3), topic


def test_bulk_runs_equal_the_record_path_topic_by_topic(bag: Path) -> None:
    with BagSource(bag, "tb3") as source:
        record = record_runs(source)
        bulk = bulk_runs(source)
        messages = [(m.topic, m.log_ns, bytes(m.data)) for m in source.messages()]
    assert per_topic(bulk) == per_topic(record) == written()
    assert messages == bag_messages()  # rosbags' order is the order written
    # Unpaced: windows of many messages, one run per topic each (the record path gathers alike).
    assert len(bulk) < 20
    assert sum(len(payloads) for _, payloads, _ in bulk) == sum(COUNTS.values())
    images = [payload for info, payloads, _ in bulk if info.topic == "/camera/image_raw"
              for payload in payloads]
    assert all(isinstance(payload, memoryview) for payload in images)  # no copy of large ones


def test_a_fast_paced_replay_in_bulk_sends_the_same_messages(bag: Path) -> None:
    """At rate 1000 the 3 s bag lasts 3 ms: the replay is behind at once and gathers what is
    due; whatever the runs, every topic's messages and times are those written."""
    with BagSource(bag, "tb3", rate=1000) as source:
        assert per_topic(bulk_runs(source)) == written()


def decoded(samples: Iterable[zenoh.Sample]) -> dict[str, list[tuple[int, bool, bytes, int]]]:
    """Each topic's messages in ``samples`` as a host reads them: (wire sequence number, whether
    it came in a bundle, payload, source time)."""
    got: dict[str, list[tuple[int, bool, bytes, int]]] = {}
    for sample in samples:
        key = str(sample.key_expr)
        assert sample.attachment is not None
        attachment = Attachment.unpack(sample.attachment.to_bytes(), key)
        data = sample.payload.to_bytes()
        topic = "/" + key.split("/data/", 1)[1]
        if attachment.bundle:
            run = bundle_run(data, attachment, key, robot="tb3", topic=topic, msgtype="")
            assert run.log_ns is not None
            assert run.sequence is not None
            got.setdefault(topic, []).extend(
                (sequence, True, bytes(payload), stamp) for sequence, payload, stamp in
                zip(run.sequence.tolist(), run.payloads, run.log_ns.tolist(), strict=True))
        else:
            got.setdefault(topic, []).append(
                (attachment.sequence, False, data, attachment.source_ns))
    return got


def published(sessions: tuple[zenoh.Session, zenoh.Session], runs: Iterable[Run],
              catalog: Catalog) -> dict[str, list[tuple[int, bool, bytes, int]]]:
    """What a host receives of a Relay (a fresh one: numbered from 0) publishing ``runs``."""
    host, robot = sessions
    received: list[zenoh.Sample] = []
    subscriber = host.declare_subscriber("swanky/tb3/data/**", received.append)
    # Blocking: nothing may be dropped on a loaded machine.
    relay = Relay(robot, catalog, PolicyTable(defaults={"congestion": "block"}))
    total = sum(COUNTS.values())
    try:
        assert relay.wait_for_host(20.0)
        for info, payloads, log_ns in runs:
            relay.publish_run(info.topic, payloads, log_ns)
        assert relay.published == total
        deadline = time.monotonic() + 30
        while sum(map(len, decoded(list(received)).values())) < total:
            assert time.monotonic() < deadline, "timed out"
            time.sleep(0.02)
    finally:
        relay.close()
        subscriber.undeclare()
    return decoded(received)


def test_over_a_relay_both_paths_send_the_same_numbered_messages(
    bag: Path, sessions: tuple[zenoh.Session, zenoh.Session]
) -> None:
    with BagSource(bag, "tb3") as source:
        catalog = source.catalog()
        record = published(sessions, record_runs(source), catalog)
        bulk = published(sessions, bulk_runs(source), catalog)
    assert bulk == record
    expected = written()
    for topic, messages in bulk.items():
        assert [sequence for sequence, *_ in messages] == list(range(COUNTS[topic])), topic
        assert [(data, stamp) for *_, data, stamp in messages] == expected[topic], topic
    bundled = {topic: {in_bundle for _, in_bundle, _, _ in messages}
               for topic, messages in bulk.items()}
    # Bundles (every topic blocks here: images too, nine 100 KB ones a bundle), but never of
    # the latched topic.
    assert bundled == {"/imu": {True}, "/chatter": {True}, "/tf_static": {False},
                       "/camera/image_raw": {True}}


def test_an_mcap_the_bulk_reader_does_not_take_is_replayed_by_rosbags(tmp_path: Path) -> None:
    """No chunks (so no chunk indexes): rosbags reads it record by record, as before."""
    bag = mcap_lz4_bag(tmp_path / "unchunked.mcap", use_chunking=False)
    with BagSource(bag, "tb3") as source:
        assert source.bulk_files() is None
        with pytest.raises(AssertionError, match="rosbags read a record"):
            bulk_runs(source)
        assert per_topic(source.runs()) == written()


def test_a_corrupt_chunk_costs_the_replay_that_chunk_only(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """40 bytes flipped in the third of 13 zstd chunks: the replay skips that chunk and sends
    the rest, with the one warning ``swanky-host --bag`` gives (the same reader), where the
    record-by-record replay stopped at that chunk with an error (test_corrupt_bags.py)."""
    bag = write_speed_mode_mcap(tmp_path / "chunk.mcap", "zstd")
    third = chunk_indexes(bag)[2]
    data = bytearray(bag.read_bytes())
    records = third.chunk_start_offset + third.chunk_length - third.compressed_size
    for at in range(records + 40, records + 80):
        data[at] ^= 0xFF
    bag.write_bytes(bytes(data))
    with caplog.at_level(logging.WARNING, "swanky.relay"), BagSource(bag, "tb3") as source:
        got = per_topic(bulk_runs(source))
    lost = held_speeds(third)
    speeds = [field_data(payload, "std_msgs/msg/Float64") for payload, _ in got["/speed"]]
    assert len(lost) == 24
    assert speeds == [float(i) for i in range(300) if float(i) not in lost]
    assert len(got["/mode"]) == 300 - 24
    [warning] = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    head = skipped_chunk(bag, third, "")
    assert warning.startswith(head)
    why = warning[len(head):]
    assert why == "its CRC does not match (corrupt)" or why.startswith("zstd does not decompress it (")
