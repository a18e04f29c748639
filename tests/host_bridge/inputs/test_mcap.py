"""The bulk MCAP reader of ``--bag`` and of the relay's replays (robot_relay/sources/mcap.py)
yields exactly the RawMessages rosbags yields through BagSource (topic, type, definition, bytes,
log time, order), on MCAP files written here (zstd, lz4 and uncompressed chunks, channels
interleaved, log times out of order across chunks and tied between them, payloads above and below
the memoryview size, split bags), on the shared recordings, and falls back to rosbags for what it
does not take."""

from __future__ import annotations

import logging
import struct
from collections import Counter
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.writer import CompressionType, IndexType, Writer
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin
from rosbags.rosbag2 import Writer as BagWriter
from rosbags.typesys import Stores, get_typestore

from host_bridge.core.columns import PackedPayloads, read_columns
from host_bridge.inputs.bag import bag_runs, message_run
from host_bridge.inputs.base import MessageRun
from robot_relay.sources.bag import BagSource
from robot_relay.sources.mcap import LARGE_PAYLOAD, Chunk, McapFile, NotIndexedError
from robot_relay.wire import MessageDefinition, RawMessage

STORE = get_typestore(Stores.ROS2_HUMBLE)
T = STORE.types
QOS = ("- history: 3\n  depth: 0\n  reliability: 1\n  durability: 2\n  deadline:\n    sec: 0\n"
       "    nsec: 0\n  lifespan:\n    sec: 0\n    nsec: 0\n  liveliness: 1\n"
       "  liveliness_lease_duration:\n    sec: 0\n    nsec: 0\n  avoid_ros_namespace_conventions: false")


def string_cdr(text: str) -> bytes:
    return bytes(STORE.serialize_cdr(T["std_msgs/msg/String"](data=text), "std_msgs/msg/String"))


def image_cdr(index: int, width: int) -> bytes:
    stamp = T["builtin_interfaces/msg/Time"](sec=index, nanosec=7)
    pixels = (np.arange(width * 60 * 3) + index).astype(np.uint8)
    image = T["sensor_msgs/msg/Image"](
        header=T["std_msgs/msg/Header"](stamp=stamp, frame_id="camera"), height=60, width=width,
        encoding="rgb8", is_bigendian=0, step=3 * width, data=pixels)
    return bytes(STORE.serialize_cdr(image, "sensor_msgs/msg/Image"))


def mcap_messages() -> list[tuple[str, int, bytes]]:
    """(topic, log time, CDR): three channels interleaved; /chatter's times go backwards every
    eighth message (out of order across chunks) and /tie shares /chatter's times (ties across
    chunks); every fifth image is larger than LARGE_PAYLOAD."""
    messages = []
    for i in range(120):
        chatter_ns = 10**9 + 1_000_000 * (i - 40 * (i % 8 == 7))
        messages.append(("/chatter", chatter_ns, string_cdr(f"hello {i}")))
        messages.append(("/tie", chatter_ns, string_cdr(f"tie {i}")))
        if i % 3 == 0:
            messages.append(("/camera/image_raw", 10**9 + 1_000_000 * i + 500,
                             image_cdr(i, 400 if i % 5 == 0 else 20)))
    return messages


def write_mcap(path: Path, compression: CompressionType, **options: Any) -> Path:
    """An MCAP with the ros2 profile and ros2msg schemas, as rosbag2 writes it, 4 KB chunks."""
    with path.open("wb") as stream:
        writer = Writer(stream, chunk_size=4096, compression=compression, **options)
        writer.start(profile="ros2", library="test")
        channels = {}
        for topic, msgtype in (("/chatter", "std_msgs/msg/String"), ("/tie", "std_msgs/msg/String"),
                               ("/camera/image_raw", "sensor_msgs/msg/Image")):
            text = STORE.generate_msgdef(msgtype, ros_version=2)[0]
            schema = writer.register_schema(msgtype, "ros2msg", text.encode())
            channels[topic] = writer.register_channel(
                topic, "cdr", schema, {"offered_qos_profiles": QOS})
        for sequence, (topic, log_ns, data) in enumerate(mcap_messages()):
            writer.add_message(channels[topic], log_ns, data, log_ns, sequence)
        writer.finish()  # type: ignore[no-untyped-call]
    return path


def fields(raw: RawMessage) -> tuple[Any, ...]:
    return (raw.robot, raw.topic, raw.msgtype, bytes(raw.data), raw.definition, raw.receive_ns,
            raw.log_ns, raw.sequence)


def rosbags_messages(bag: Path) -> list[tuple[Any, ...]]:
    with BagSource(bag, "tb3") as source:
        return [fields(raw) for raw in source.messages()]


def bulk_messages(bag: Path, size: int = 7) -> list[RawMessage]:
    """The bulk reader's records (what a paced relay replay sends), ``size`` a step; rosbags'
    messages where the bulk reader does not take the bag."""
    with BagSource(bag, "tb3") as source:
        files = source.bulk_files()
        if files is None:
            return list(source.messages())
        return [RawMessage("tb3", info.topic, info.msgtype, data, info.definition, None, stamp)
                for opened in files for records in opened.records(size) for info, stamp, data in records]


@pytest.mark.parametrize("compression", [CompressionType.ZSTD, CompressionType.LZ4,
                                         CompressionType.NONE])
def test_bulk_reader_yields_what_rosbags_yields(tmp_path: Path, compression: CompressionType) -> None:
    bag = write_mcap(tmp_path / "bag.mcap", compression)
    McapFile(bag, {}).close()  # indexed: the bulk reader takes it, no fallback
    expected = rosbags_messages(bag)
    got = bulk_messages(bag)
    assert [fields(raw) for raw in got] == expected
    assert len(got) == 280
    order = [(raw.topic, raw.log_ns) for raw in got]
    assert order[:3] == [("/chatter", 967_000_000), ("/tie", 967_000_000), ("/chatter", 975_000_000)]
    stamps = [raw.log_ns or 0 for raw in got]
    assert stamps == sorted(stamps)
    big = [raw for raw in got if len(raw.data) >= LARGE_PAYLOAD]
    assert len(big) == 8
    assert all(isinstance(raw.data, memoryview) for raw in big)  # no copy of large payloads
    assert all(isinstance(raw.data, bytes) for raw in got if len(raw.data) < LARGE_PAYLOAD)
    image: Any = STORE.deserialize_cdr(big[1].data, "sensor_msgs/msg/Image")
    assert (image.header.stamp.sec, image.width, image.data[:3].tolist()) == (15, 400, [15, 16, 17])


def mcap_windows(bag: Path, messages: int, payload_bytes: int) -> list[list[MessageRun]]:
    with BagSource(bag, "tb3") as source:
        storages = source.mcap_storages()
        assert storages is not None
        ((path, channels),) = storages
        with McapFile(path, channels) as opened:
            return [[message_run("tb3", run) for run in window]
                    for window in opened.windows(messages, payload_bytes)]


def test_runs_are_windows_split_by_topic(tmp_path: Path) -> None:
    """Windows of 64 messages, each as one run per topic holding that topic's messages of the
    window in rosbags' order, the run with the window's last message last; bag_runs gives the
    same runs one after the other."""
    bag = write_mcap(tmp_path / "bag.mcap", CompressionType.ZSTD)
    expected = rosbags_messages(bag)
    windows = mcap_windows(bag, 64, 10**9)
    assert [sum(map(len, window)) for window in windows] == [64, 64, 64, 64, 24]
    for number, window in enumerate(windows):
        part = expected[64 * number : 64 * (number + 1)]
        assert sorted(run.topic for run in window) == sorted({m[1] for m in part})
        for run in window:
            assert [fields(raw) for raw in run] == [m for m in part if m[1] == run.topic]
            assert run.log_ns is not None
            assert run.log_ns.tolist() == [m[6] for m in part if m[1] == run.topic]
        assert fields(window[-1][-1]) == part[-1]
    assert [run.topic for run in windows[0]] == ["/camera/image_raw", "/chatter", "/tie"]
    got = [[fields(raw) for raw in run] for run in bag_runs(bag, "tb3", run_size=64)]
    assert got == [[fields(raw) for raw in run] for window in windows for run in window]


def test_runs_hold_at_most_their_bytes(tmp_path: Path) -> None:
    """A window ends before its payloads pass the byte bound (a run of images must not hold a
    whole bag), unless one message alone is larger; large payloads stay memoryviews."""
    bag = write_mcap(tmp_path / "bag.mcap", CompressionType.LZ4)
    expected = rosbags_messages(bag)
    bound = 100_000
    windows = mcap_windows(bag, 1000, bound)
    sizes = [sum(len(data) for run in window for data in run.payloads) for window in windows]
    counts = [sum(map(len, window)) for window in windows]
    assert all(size <= bound or count == 1 for size, count in zip(sizes, counts, strict=True))
    assert sum(counts) == 280
    # Each window is as long as the bound allows: the next message would have passed it.
    starts = np.cumsum(counts)[:-1]
    assert all(size + len(expected[start][3]) > bound for size, start in zip(sizes, starts, strict=False))
    assert len(windows) == 8
    flat = [raw for window in windows for run in window for raw in run]
    for topic in ("/chatter", "/tie", "/camera/image_raw"):
        assert [fields(raw) for raw in flat if raw.topic == topic] == [
            m for m in expected if m[1] == topic]
    big = [data for window in windows for run in window for data in run.payloads
           if len(data) >= LARGE_PAYLOAD]
    assert len(big) == 8
    assert all(isinstance(data, memoryview) for data in big)


@pytest.mark.parametrize("compression", [CompressionType.ZSTD, CompressionType.NONE])
def test_runs_across_chunks_read_as_columns_equal_rosbags(
    tmp_path: Path, compression: CompressionType
) -> None:
    """A window's runs keep their payloads in the chunks' buffers (small ones) and memoryviews
    (large ones); read as columns, a run spanning chunks, with payloads of many lengths, small
    and large images mixed, gives what rosbags decodes from each message."""
    bag = write_mcap(tmp_path / "bag.mcap", compression)
    runs = [run for window in mcap_windows(bag, 64, 10**9) for run in window]
    assert sum(map(len, runs)) == 280
    assert all(isinstance(run.payloads, PackedPayloads) for run in runs)
    spanning = [run for run in runs if len(set(run.payloads.sources.tolist())) > 1]  # type: ignore[attr-defined]
    assert {run.topic for run in spanning} == {"/chatter", "/tie", "/camera/image_raw"}
    for run in runs:
        columns = read_columns(run.payloads, run.msgtype, STORE, max_blocks=len(run))
        assert columns is not None
        messages: list[Any] = [STORE.deserialize_cdr(bytes(data), run.msgtype) for data in run.payloads]
        if run.msgtype == "std_msgs/msg/String":
            assert columns["data"].tolist() == [message.data for message in messages]
            continue
        assert columns["width"].tolist() == [message.width for message in messages]
        for block in columns.blocks:
            for row, pixels in zip(block.rows.tolist(), block.numbers["data"], strict=True):
                assert pixels.tobytes() == messages[row].data.tobytes(), (run.topic, row)


def test_message_run_is_a_sequence_of_raw_messages() -> None:
    definition = MessageDefinition("ros2msg", "string data")
    run = MessageRun("tb3", "/chatter", "std_msgs/msg/String", definition,
                     [b"a", memoryview(b"bc"), b"d"], np.array([5, 6, 7], np.int64))
    first = RawMessage("tb3", "/chatter", "std_msgs/msg/String", b"a", definition, None, 5)
    assert len(run) == 3
    assert run[0] == first
    assert [fields(raw) for raw in run[1:]] == [
        ("tb3", "/chatter", "std_msgs/msg/String", b"bc", definition, None, 6, None),
        ("tb3", "/chatter", "std_msgs/msg/String", b"d", definition, None, 7, None)]
    assert [fields(raw) for raw in run] == [fields(run[i]) for i in range(3)]
    assert next(iter(run)) == first
    assert run[-1].log_ns == 7
    assert type(run[-1].log_ns) is int


@pytest.mark.parametrize("compression", [CompressionMode.NONE, CompressionMode.STORAGE,
                                         CompressionMode.FILE], ids=lambda mode: mode.name.lower())
def test_rosbag2_directory_from_rosbags_writer(tmp_path: Path, compression: CompressionMode) -> None:
    """rosbags' own writer: schemas and channels inside the first chunk, 1 MiB chunks, zstd chunks
    with storage compression, the whole file zstd'ed with file compression (rosbag2's
    ``--compression-mode file``: read in bulk from the file rosbags decompressed), a topic without
    its leading slash. (Split bags: the shared recordings.)"""
    directory = tmp_path / "bag"
    writer = BagWriter(directory, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(compression, CompressionFormat.ZSTD)
    with writer:
        chatter = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=STORE)
        camera = writer.add_connection("camera/image_raw", "sensor_msgs/msg/Image", typestore=STORE)
        for i in range(40):
            writer.write(chatter, 10 * i, string_cdr(f"hello {i}"))
            writer.write(camera, 10 * i + 5, image_cdr(i, 640))  # 115 KB: several chunks
    expected = rosbags_messages(directory)
    got = bulk_messages(directory, size=5)
    assert [fields(raw) for raw in got] == expected
    assert len(got) == 80
    assert got[1].topic == "/camera/image_raw"
    assert isinstance(got[1].data, memoryview)  # read in bulk, not by the rosbags fallback
    assert got[1].definition is not None
    assert got[1].definition.encoding == "ros2msg"
    stored = [path.name for path in directory.iterdir() if path.name != "metadata.yaml"]
    assert stored == ["bag.mcap.zstd" if compression == CompressionMode.FILE else "bag.mcap"]


@pytest.mark.parametrize(
    "options",
    [{"use_chunking": False}, {"index_types": IndexType.NONE}, {"use_summary_offsets": False,
                                                                  "index_types": IndexType.CHUNK}],
    ids=["unchunked", "no-indexes", "no-message-indexes"],
)
def test_unindexed_files_are_read_by_rosbags(
    tmp_path: Path, options: dict[str, Any], request: pytest.FixtureRequest
) -> None:
    bag = tmp_path / "bag.mcap"
    with bag.open("wb") as stream:
        writer = Writer(stream, chunk_size=4096, compression=CompressionType.ZSTD, **options)
        writer.start(profile="ros2", library="test")
        text = STORE.generate_msgdef("std_msgs/msg/String", ros_version=2)[0]
        schema = writer.register_schema("std_msgs/msg/String", "ros2msg", text.encode())
        channel = writer.register_channel("/chatter", "cdr", schema)
        for i in range(300):
            writer.add_message(channel, 1000 * i, string_cdr(f"hello {i}"), 1000 * i)
        writer.finish()  # type: ignore[no-untyped-call]
    with pytest.raises(NotIndexedError):
        McapFile(bag, {})
    expected = rosbags_messages(bag)
    assert [fields(raw) for raw in bulk_messages(bag)] == expected
    # rosbags finds a chunk's messages through its message indexes: without them it reads none
    # (a loss of today's reader too, kept rather than hidden: the same RawMessages either way).
    assert len(expected) == (0 if "no-message" in request.node.name else 300)


def test_empty_bag(tmp_path: Path) -> None:
    directory = tmp_path / "empty"
    with BagWriter(directory, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        writer.add_connection("/chatter", "std_msgs/msg/String", typestore=STORE)
    assert bulk_messages(directory) == []
    assert list(bag_runs(directory, "tb3")) == []


def skipped(bag: Path, caplog: pytest.LogCaptureFixture) -> tuple[list[RawMessage], list[str]]:
    """The bulk reader's messages of a damaged ``bag`` and the warnings naming it."""
    with caplog.at_level(logging.WARNING, "swanky.relay"):
        got = bulk_messages(bag)
    return got, [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING
                 and r.name == "swanky.relay" and str(bag) in r.getMessage()]


def lost_chunk(
    bag: Path, chunk: Chunk, index_says: Mapping[str, str] | None = None
) -> tuple[str, list[tuple[Any, ...]]]:
    """The start of the warning naming ``chunk`` of the uncompressed ``bag`` as skipped (with
    ``index_says``' counts for topics whose index is damaged), and rosbags' messages of the
    other chunks."""
    content = bag.read_bytes()
    inside = content[chunk.records_offset : chunk.records_offset + chunk.compressed_size]
    # A message is the chunk's if its time is in the chunk's range and its payload in its records.
    held = [m for m in rosbags_messages(bag)
            if chunk.start_ns <= m[6] <= chunk.end_ns and m[3] in inside]
    counts = Counter(m[1] for m in held)
    what = ", ".join((index_says or {}).get(topic, f"{count} {topic}")
                     for topic, count in sorted(counts.items()))
    return (f"bag {bag} is damaged (the readable part was read); lost: the chunk at byte "
            f"{chunk.file_offset} ({what} messages per its index) is skipped: ",
            [m for m in rosbags_messages(bag) if m not in held])


def test_damaged_chunk_is_skipped_and_named(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A payload byte flipped in an uncompressed chunk: its CRC says so; the chunk is skipped,
    every other message read, and one warning names the file and the chunk."""
    bag = write_mcap(tmp_path / "bag.mcap", CompressionType.NONE)
    content = bytearray(bag.read_bytes())
    at = content.index(string_cdr("hello 3")[8:])
    with McapFile(bag, {}) as opened:
        [chunk] = [c for c in opened.chunks
                   if c.records_offset <= at < c.records_offset + c.compressed_size]
    head, expected = lost_chunk(bag, chunk)
    content[at] ^= 0xFF
    bag.write_bytes(bytes(content))
    got, warnings = skipped(bag, caplog)
    assert [fields(raw) for raw in got] == expected
    assert len(expected) == 280 - 10
    assert warnings == [f"{head}its CRC does not match (corrupt)"]


@pytest.mark.parametrize("damage", ["offset", "unindexed", "past the end"])
def test_message_index_disagreeing_with_its_chunk_skips_the_chunk(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, damage: str
) -> None:
    """A message index entry pointing a byte off its message, one left out (the message is
    then unindexed), or a message index whose length runs past the end of the file."""
    bag = write_mcap(tmp_path / "bag.mcap", CompressionType.NONE, enable_crcs=False)
    content = bytearray(bag.read_bytes())
    with McapFile(bag, {}) as opened:
        chunk = opened.chunks[1]
    _, index_at = chunk.message_indexes[0]  # /chatter's: it holds one message
    head, expected = lost_chunk(bag, chunk, {
        "offset": {}, "unindexed": {"/chatter": "0 /chatter"},
        "past the end": {"/chatter": "? /chatter"}}[damage])
    entry = index_at + 15
    (size,) = struct.unpack_from("<I", content, index_at + 11)
    (first,) = struct.unpack_from("<Q", content, entry + 8)
    why = {"offset": f"no message of the indexed channel and time at {first + 1}",
           "unindexed": f"the message at {first} is not indexed",
           "past the end": f"its message index at byte {index_at} is not one"}[damage]
    if damage == "offset":
        struct.pack_into("<Q", content, entry + 8, first + 1)
    elif damage == "unindexed":  # the first entry dropped: the later ones move up
        content[entry : index_at + 15 + size] = content[entry + 16 : index_at + 15 + size] + bytes(16)
        struct.pack_into("<I", content, index_at + 11, size - 16)
    else:
        struct.pack_into("<I", content, index_at + 11, 16 * len(content))
    bag.write_bytes(bytes(content))
    got, warnings = skipped(bag, caplog)
    assert [fields(raw) for raw in got] == expected
    assert len(expected) < 280
    assert warnings == [f"{head}{why}"]

@pytest.mark.parametrize("bag", [
    "tf_nav2_sim_evo/nav2_turtlebot.mcap", "rosbag2_format_fixtures/mcap_wbag",
    "rosbag2_format_fixtures/mcap_cdr_test", "rosbag2_format_fixtures/mcap_talker",
])
def test_shared_recordings(shared_data: Path, bag: str) -> None:
    got = bulk_messages(shared_data / bag, size=2048)
    assert [fields(raw) for raw in got] == rosbags_messages(shared_data / bag)
    assert got
