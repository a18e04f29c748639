"""Damaged bags (issue 14): cut mid-chunk, bytes flipped in a chunk, an index or the summary, a
zero-length or corrupt-row sqlite3 file. ``swanky-host --bag X --save out.rrd`` converts what can
be read and names the rest in one warning naming the file (exit 0); a bag of which nothing can be
read is one error naming the file (exit 2).

The bags are made here: MCAP with zstd and lz4 chunks by the ``mcap`` writer (rosbags' writes no
compressed chunks), sqlite3 by rosbags' Writer, ROS 1 with bz2/lz4 chunks by rosbags' ROS 1
Writer. Every bag holds 300 /speed Float64 (value i) and 300 /mode String messages; what survives
a cut is counted by the ``mcap`` package's own stream reader, an independent decoder.
"""

from __future__ import annotations

import io
import logging
import sqlite3
import struct
from pathlib import Path
from typing import Any

import pytest
from rosbags.rosbag1 import Reader as Ros1Reader
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from host_bridge.cli import main as host_main
from robot_relay.errors import SourceError
from robot_relay.sources.bag import BagSource
from tests.reliability import Record
from tests.rrd import entity_rows

mcap_writer = pytest.importorskip("mcap.writer")
mcap_stream = pytest.importorskip("mcap.stream_reader")
mcap_records = pytest.importorskip("mcap.records")
mcap_reader = pytest.importorskip("mcap.reader")

STORE = get_typestore(Stores.ROS2_HUMBLE)


def field_data(payload: bytes | memoryview, msgtype: str) -> Any:
    """The ``data`` field of a std_msgs message in CDR."""
    msg: Any = STORE.deserialize_cdr(bytes(payload), msgtype)
    return msg.data
ROS1 = get_typestore(Stores.ROS1_NOETIC)
COUNT = 300
FLOAT64, STRING = "std_msgs/msg/Float64", "std_msgs/msg/String"


def _cdr(msgtype: str, value: Any) -> bytes:
    return bytes(STORE.serialize_cdr(STORE.types[msgtype](data=value), msgtype))


def _stamp(i: int) -> int:
    return (i + 1) * 10_000_000


def write_mcap(path: Path, compression: str) -> Path:
    """Chunks of ~2 KB (13 of them), so a cut lands inside one with whole ones before it."""
    with path.open("wb") as file:
        writer = mcap_writer.Writer(
            file, chunk_size=2048, compression=mcap_writer.CompressionType[compression.upper()]
        )
        writer.start(profile="ros2", library="swanky tests")
        speed = writer.register_channel("/speed", "cdr", writer.register_schema(
            FLOAT64, "ros2msg", b"float64 data\n"))
        mode = writer.register_channel("/mode", "cdr", writer.register_schema(
            STRING, "ros2msg", b"string data\n"))
        for i in range(COUNT):
            writer.add_message(speed, log_time=_stamp(i), data=_cdr(FLOAT64, float(i)),
                               publish_time=_stamp(i))
            writer.add_message(mode, log_time=_stamp(i), data=_cdr(STRING, f"m{i}"),
                               publish_time=_stamp(i))
        writer.finish()
    return path


def write_db3(path: Path) -> Path:
    with Writer(path, version=9, storage_plugin=StoragePlugin.SQLITE3) as writer:
        speed = writer.add_connection("/speed", FLOAT64, typestore=STORE)
        mode = writer.add_connection("/mode", STRING, typestore=STORE)
        for i in range(COUNT):
            writer.write(speed, _stamp(i), _cdr(FLOAT64, float(i)))
            writer.write(mode, _stamp(i), _cdr(STRING, f"m{i}"))
    return path


def write_ros1(path: Path, compression: str) -> Path:
    writer = Ros1Writer(path)
    if compression != "none":
        writer.set_compression(Ros1Writer.CompressionFormat[compression.upper()])
    writer.chunk_threshold = 1024
    with writer:
        speed = writer.add_connection("/speed", FLOAT64, typestore=ROS1)
        mode = writer.add_connection("/mode", STRING, typestore=ROS1)
        for i in range(COUNT):
            writer.write(speed, _stamp(i), ROS1.serialize_ros1(
                ROS1.types[FLOAT64](data=float(i)), FLOAT64))
            writer.write(mode, _stamp(i), ROS1.serialize_ros1(ROS1.types[STRING](data=f"m{i}"),
                                                              STRING))
    return path


def cut(path: Path, fraction: float) -> Path:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])
    return path


def readable_speeds(path: Path) -> list[float]:
    """The /speed values the ``mcap`` package's stream reader gets from ``path`` before it
    stops at the damage."""
    values: list[float] = []
    topics: dict[int, str] = {}
    try:
        for record in mcap_stream.StreamReader(io.BytesIO(path.read_bytes())).records:
            if isinstance(record, mcap_records.Channel):
                topics[record.id] = record.topic
            elif isinstance(record, mcap_records.Message) and topics[record.channel_id] == "/speed":
                values.append(field_data(record.data, FLOAT64))
    except Exception:  # the damage: mcap raises what its parser hits there
        pass
    return values


def convert(bag: Path, out: Path) -> tuple[int, list[float]]:
    code = host_main(["--bag", str(bag), "--save", str(out), "--no-blueprint"])
    rows = entity_rows(out) if out.exists() else {}
    return code, [row["Scalars:scalars"][0] for row in rows.get("/robot/speed", [])]


def damage_warnings(caplog: pytest.LogCaptureFixture, bag: Path) -> list[str]:
    """The warnings naming ``bag``: the relay's bag source's, or the host's bulk MCAP reader's."""
    return [r.getMessage() for r in caplog.records
            if r.name in ("swanky.relay", "swanky.host") and r.levelno == logging.WARNING
            and bag.name in r.getMessage()]


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_an_mcap_cut_mid_chunk_converts_every_whole_chunk(
    compression: str, tmp_path: Path, caplog: pytest.LogCaptureFixture, reliability: Record
) -> None:
    bag = cut(write_mcap(tmp_path / f"{compression}.mcap", compression), 0.6)
    expected = readable_speeds(bag)
    assert 0 < len(expected) < COUNT  # the cut lost some, whole chunks before it remain
    with caplog.at_level(logging.WARNING):
        code, speeds = convert(bag, tmp_path / "out.rrd")
    assert code == 0
    assert speeds == expected == [float(i) for i in range(len(expected))]
    [warning] = damage_warnings(caplog, bag)
    assert "is damaged" in warning
    assert "the file ends inside a record" in warning
    assert "(cut short)" in warning
    reliability("Damaged bags", f"MCAP ({compression} chunks) cut at 60 %, mid-chunk", tried="1 bag",
                survived=f"{len(speeds)} of {COUNT} /speed messages (every whole chunk, as the "
                "mcap package's reader counts them), exit 0, one warning naming the file",
                lost=f"{COUNT - len(speeds)} /speed messages in the cut chunk and after")


def _summary_start(data: bytes) -> int:
    # Footer: opcode, length, summary_start u64, summary_offset_start u64, crc u32; then magic.
    footer = len(data) - 8 - 29
    return int(struct.unpack_from("<Q", data, footer + 9)[0])


def test_an_mcap_with_a_damaged_summary_is_read_from_its_data_section(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, reliability: Record
) -> None:
    bag = write_mcap(tmp_path / "summary.mcap", "zstd")
    data = bytearray(bag.read_bytes())
    start = _summary_start(bytes(data))
    for at in range(start + 200, start + 600, 7):  # across the chunk indexes
        data[at] ^= 0x5A
    bag.write_bytes(bytes(data))
    with caplog.at_level(logging.WARNING):
        code, speeds = convert(bag, tmp_path / "out.rrd")
    assert code == 0
    assert speeds == [float(i) for i in range(COUNT)]
    [warning] = damage_warnings(caplog, bag)
    assert "cannot be opened" in warning
    assert "no message (every chunk read)" in warning
    reliability("Damaged bags", "MCAP with 58 bytes flipped in its summary (chunk indexes)",
                tried="1 bag", survived=f"all {COUNT} /speed messages, exit 0, one warning",
                lost="0 messages")


def chunk_indexes(bag: Path) -> list[Any]:
    """The chunk indexes of the summary, by the ``mcap`` package's reader, in file order."""
    with bag.open("rb") as stream:
        summary = mcap_reader.make_reader(stream).get_summary()
    assert summary is not None
    return sorted(summary.chunk_indexes, key=lambda index: index.chunk_start_offset)


def held_speeds(index: Any) -> list[float]:
    """The /speed values of a chunk: messages are written in log-time order, /speed i at
    _stamp(i), so a chunk holds those of its time range."""
    return [float(i) for i in range(COUNT)
            if index.message_start_time <= _stamp(i) <= index.message_end_time]


def skipped_chunk(bag: Path, index: Any, why: str) -> str:
    held = len(held_speeds(index))
    return (f"bag {bag} is damaged (the readable part was read); lost: the chunk at byte "
            f"{index.chunk_start_offset} ({held} /mode, {held} /speed messages per its index) "
            f"is skipped: {why}")


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_an_indexed_mcap_with_a_corrupt_chunk_loses_that_chunk_only(
    compression: str, tmp_path: Path, caplog: pytest.LogCaptureFixture, reliability: Record
) -> None:
    """40 bytes flipped inside the third chunk's compressed records: its codec or its CRC says
    so; the host's bulk reader skips it and converts the 12 others (it was exit 2, nothing)."""
    bag = write_mcap(tmp_path / f"chunk-{compression}.mcap", compression)
    indexes = chunk_indexes(bag)
    third = indexes[2]
    lost = held_speeds(third)
    data = bytearray(bag.read_bytes())
    records = third.chunk_start_offset + third.chunk_length - third.compressed_size
    for at in range(records + 40, records + 80):
        data[at] ^= 0xFF
    bag.write_bytes(bytes(data))
    with caplog.at_level(logging.WARNING):
        code, speeds = convert(bag, tmp_path / "out.rrd")
    assert code == 0
    assert len(indexes) == 13
    assert len(lost) == 24
    assert speeds == [float(i) for i in range(COUNT) if float(i) not in lost]
    [warning] = damage_warnings(caplog, bag)
    head = skipped_chunk(bag, third, "")
    assert warning.startswith(head)
    why = warning[len(head):]
    assert why == "its CRC does not match (corrupt)" or why.startswith(
        f"{compression} does not decompress it (")
    reliability("Damaged bags", f"indexed MCAP ({compression} chunks) with 40 bytes flipped in "
                "one chunk, through the host's bulk reader", tried="1 bag",
                survived=f"{len(speeds)} of {COUNT} /speed messages (the 12 other chunks), exit 0, "
                "one warning naming the file, the chunk and what its index held",
                lost=f"the {len(lost)} /speed and {len(lost)} /mode messages of that chunk "
                f"(before: exit 2, 0 of {COUNT} converted)")


def _flip_message_index_offset(data: bytearray, index: Any) -> None:
    """The second entry of the chunk's first message index points 64 bytes off its message."""
    at = min(index.message_index_offsets.values())
    entry = at + 9 + 2 + 4 + 16  # record header, channel id, entries' length, first entry
    (offset,) = struct.unpack_from("<Q", data, entry + 8)
    struct.pack_into("<Q", data, entry + 8, offset ^ 0x40)


def _flip_chunk_offset(data: bytearray, index: Any) -> None:
    """The chunk index's chunk_start_offset points past the end of the file."""
    summary = _summary_start(bytes(data))
    at = data.index(struct.pack("<Q", index.chunk_start_offset), summary)
    struct.pack_into("<Q", data, at, len(data) + 1000)


@pytest.mark.parametrize("damage", ["message index offset", "chunk index offset"])
def test_an_indexed_mcap_with_a_flipped_index_offset(
    damage: str, tmp_path: Path, caplog: pytest.LogCaptureFixture, reliability: Record
) -> None:
    """A message index entry pointing off its message loses that chunk (its records cannot be
    trusted to be the indexed ones); a chunk index pointing past the end of the file is repaired
    from the chunk's message indexes, which follow it: nothing lost."""
    bag = write_mcap(tmp_path / "offset.mcap", "zstd")
    third = chunk_indexes(bag)[2]
    data = bytearray(bag.read_bytes())
    if damage == "message index offset":
        _flip_message_index_offset(data, third)
    else:
        _flip_chunk_offset(data, third)
    bag.write_bytes(bytes(data))
    with caplog.at_level(logging.WARNING):
        code, speeds = convert(bag, tmp_path / "out.rrd")
    assert code == 0
    [warning] = damage_warnings(caplog, bag)
    if damage == "message index offset":
        lost = held_speeds(third)
        (first_at,) = struct.unpack_from(
            "<Q", data, min(third.message_index_offsets.values()) + 9 + 2 + 4 + 16 + 8)
        assert warning == skipped_chunk(
            bag, third, f"no message of the indexed channel and time at {first_at}")
    else:
        lost = []
        assert warning == (
            f"bag {bag} is damaged (the chunk index of the chunk at byte "
            f"{third.chunk_start_offset} points at byte {len(data) + 1000}; the chunk was found "
            "before its message indexes; the readable part was read); lost: no message")
    assert speeds == [float(i) for i in range(COUNT) if float(i) not in lost]
    reliability("Damaged bags", f"indexed MCAP (zstd) with a flipped {damage}", tried="1 bag",
                survived=f"{len(speeds)} of {COUNT} /speed messages, exit 0, one warning naming "
                "the file and the chunk", lost=f"{len(lost)} /speed and {len(lost)} /mode "
                "messages (that chunk's)" if lost else "0 messages (before: exit 2, 92 of 600 "
                "messages converted)")


def test_a_db3_with_corrupt_rows_loses_those_rows_only(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, reliability: Record
) -> None:
    bag = write_db3(tmp_path / "rows")
    with sqlite3.connect(next(bag.glob("*.db3"))) as db:
        # Rows 11, 31 and 41 are /speed 5, 15 and 20: a 2-byte payload, a text timestamp, and a
        # row of a topic id no topic has.
        db.execute("UPDATE messages SET data = x'0001' WHERE id = 11")
        db.execute("UPDATE messages SET timestamp = 'x' WHERE id = 31")
        db.execute("UPDATE messages SET topic_id = 99 WHERE id = 41")
    with caplog.at_level(logging.WARNING):
        code, speeds = convert(bag, tmp_path / "out.rrd")
    assert code == 0
    assert speeds == [float(i) for i in range(COUNT) if i not in (5, 15, 20)]
    [warning] = damage_warnings(caplog, bag)
    assert "lost: 1 messages whose log time or payload is malformed" in warning
    decode = [r.getMessage() for r in caplog.records if "does not deserialize" in r.getMessage()]
    assert len(decode) == 1
    assert "/speed" in decode[0]
    reliability("Damaged bags", "sqlite3 .db3 with 3 corrupt rows (2-byte payload, text "
                "timestamp, unknown topic id)", tried="1 bag",
                survived=f"{len(speeds)} of {COUNT} /speed messages and all {COUNT} /mode, exit 0",
                lost="the 3 corrupt rows (2 named in warnings, the orphan row unread by rosbags)")


@pytest.mark.parametrize("damage", ["zero-length", "cut in half"])
def test_a_db3_with_nothing_readable_is_one_error_naming_the_file(
    damage: str, tmp_path: Path, capsys: pytest.CaptureFixture[str], reliability: Record
) -> None:
    if damage == "zero-length":
        bag = tmp_path / "empty.db3"
        bag.write_bytes(b"")
    else:
        bag = write_db3(tmp_path / "half")
        cut(next(bag.glob("*.db3")), 0.5)
    code, speeds = convert(bag, tmp_path / "out.rrd")
    err = capsys.readouterr().err
    assert code == 2
    assert speeds == []
    errors = [line for line in err.splitlines() if line.startswith("swanky-host: error:")]
    assert len(errors) == 1
    assert f"bag {bag}" in errors[0]
    assert "cannot be opened" in errors[0]
    assert "Traceback" not in err
    reliability("Damaged bags", f"sqlite3 .db3 {damage}", tried="1 bag",
                survived="host: one error naming the file, exit 2, no traceback",
                lost=f"the bag ({COUNT * 2} messages; sqlite cannot open it)")


def intact_speeds(bag: Path, cut_at: int, compression: str) -> int:
    """How many /speed messages of the whole ROS 1 ``bag`` lie before byte ``cut_at``, from
    rosbags' own index of it: those of chunks that end before the cut and, in an uncompressed
    chunk, each message record that does (its bytes are in the file as written)."""
    data = bag.read_bytes()
    with Ros1Reader(bag) as reader:
        (speed,) = [c for c in reader.connections if c.topic == "/speed"]
        kept = 0
        for entry in reader.indexes[speed.id]:
            chunk = reader.chunks[entry.chunk_pos]
            end = chunk.datapos + chunk.datasize
            if compression == "none":
                at = chunk.datapos + entry.offset
                (header,) = struct.unpack_from("<I", data, at)
                (size,) = struct.unpack_from("<I", data, at + 4 + header)
                end = at + 8 + header + size
            kept += end <= cut_at
    return kept


@pytest.mark.parametrize("compression", ["bz2", "lz4", "none"])
def test_a_ros1_bag_cut_mid_chunk_converts_what_was_written(
    compression: str, tmp_path: Path, caplog: pytest.LogCaptureFixture, reliability: Record
) -> None:
    """rosbags reads a ROS 1 bag from its index, at the end of the file: a cut bag has none
    (it was exit 2, nothing converted). Read from the start, every whole chunk converts, and
    of an uncompressed chunk the cut falls in, every whole message record."""
    whole = write_ros1(tmp_path / f"{compression}.bag", compression)
    cut_at = int(whole.stat().st_size * 0.6)
    expected = intact_speeds(whole, cut_at, compression)
    assert 0 < expected < COUNT
    bag = cut(whole, 0.6)
    with caplog.at_level(logging.WARNING):
        code, speeds = convert(bag, tmp_path / "out.rrd")
    assert code == 0
    assert speeds == [float(i) for i in range(expected)]
    [warning] = damage_warnings(caplog, bag)
    assert warning.startswith(
        f"bag {bag} is damaged (bag {bag} cannot be opened: Bag index looks damaged: ('Header "
        "could not be read from file.',); the readable part was read); lost: "
        f"{bag.name}: ")
    assert warning.endswith(" (cut short): nothing after it")
    with BagSource(bag, "tb3") as source:
        assert source.message_count == len(list(source.messages()))
        modes = [m for m in source.messages() if m.topic == "/mode"]
    assert [field_data(m.data, STRING) for m in modes] == [
        f"m{i}" for i in range(len(modes))]
    assert len(modes) in (expected, expected - 1)  # /mode i is written after /speed i
    chunks = "uncompressed" if compression == "none" else f"{compression} chunks"
    reliability("Damaged bags", f"ROS 1 .bag ({chunks}) cut at 60 %, mid-chunk",
                tried="1 bag", survived=f"{len(speeds)} of {COUNT} /speed messages (all "
                f"{expected} before the cut, by rosbags' index of the whole bag), exit 0, one "
                "warning naming the file", lost=f"{COUNT - len(speeds)} /speed messages after "
                "the cut (before: all 600 messages, exit 2)")


def test_a_ros1_bag_with_a_corrupt_chunk_and_index_loses_that_chunk_only(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, reliability: Record
) -> None:
    bag = write_ros1(tmp_path / "flipped.bag", "bz2")
    with Ros1Reader(bag) as reader:
        (speed,) = [c for c in reader.connections if c.topic == "/speed"]
        infos = sorted(reader.chunk_infos, key=lambda info: info.pos)
        third = reader.chunks[infos[2].pos]
        before = sum(info.connection_counts.get(speed.id, 0) for info in infos[:2])
        in_third = infos[2].connection_counts[speed.id]
    data = bytearray(bag.read_bytes())
    for at in range(third.datapos + 20, third.datapos + 60):  # the third chunk's bz2 stream
        data[at] ^= 0xFF
    for at in range(len(data) - 300, len(data), 7):  # the chunk infos of the index
        data[at] ^= 0x5A
    bag.write_bytes(bytes(data))
    with caplog.at_level(logging.WARNING):
        code, speeds = convert(bag, tmp_path / "out.rrd")
    assert code == 0
    lost = range(before, before + in_third)
    assert speeds == [float(i) for i in range(COUNT) if i not in lost]
    [warning] = damage_warnings(caplog, bag)
    assert "cannot be opened: Bag index looks damaged" in warning
    assert f"the chunk at byte {infos[2].pos} does not decompress (bz2: Invalid data stream), " \
        "skipped" in warning
    reliability("Damaged bags", "ROS 1 .bag (bz2) with 40 bytes flipped in a chunk and 43 in "
                "its index", tried="1 bag", survived=f"{len(speeds)} of {COUNT} /speed messages "
                "(every other chunk), exit 0, one warning naming the file and the chunk",
                lost=f"the {in_third} /speed messages of the corrupt chunk")


def test_a_zero_length_ros1_bag_is_one_error_naming_the_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], reliability: Record
) -> None:
    bag = tmp_path / "empty.bag"
    bag.write_bytes(b"")
    code, speeds = convert(bag, tmp_path / "out.rrd")
    err = capsys.readouterr().err
    assert (code, speeds) == (2, [])
    errors = [line for line in err.splitlines() if line.startswith("swanky-host: error:")]
    assert len(errors) == 1
    assert errors[0].startswith(f"swanky-host: error: bag {bag} cannot be opened: ")
    assert errors[0].endswith("nothing of it can be read (empty.bag: it does not start with the "
                              "ROS 1 bag magic (#ROSBAG V2.0): nothing was read)")
    assert "Traceback" not in err
    reliability("Damaged bags", "ROS 1 .bag of zero length", tried="1 bag",
                survived="host: one error naming the file, exit 2, no traceback",
                lost="the bag (it holds nothing)")


def test_the_relay_replays_a_cut_mcap_up_to_the_cut(tmp_path: Path) -> None:
    bag = cut(write_mcap(tmp_path / "cut.mcap", "zstd"), 0.6)
    expected = readable_speeds(bag)
    with BagSource(bag, "tb3") as source:
        assert source.message_count == 2 * len(expected)
        assert {t.topic for t in source.catalog().topics} == {"/speed", "/mode"}
        speeds = [field_data(m.data, FLOAT64)
                  for m in source.messages() if m.topic == "/speed"]
    assert speeds == expected


def test_a_corrupt_chunk_in_an_indexed_mcap_ends_the_replay_with_one_error(tmp_path: Path) -> None:
    """rosbags opens the file (its summary is whole) and fails on the chunk whose bytes were
    flipped: the relay sends what came before it, then one SourceError names the file."""
    bag = write_mcap(tmp_path / "chunk.mcap", "zstd")
    data = bytearray(bag.read_bytes())
    third_chunk = data.find(b"zstd", data.find(b"zstd", data.find(b"zstd") + 1) + 1)
    for at in range(third_chunk + 40, third_chunk + 80):
        data[at] ^= 0xFF
    bag.write_bytes(bytes(data))
    speeds: list[float] = []
    with BagSource(bag, "tb3") as source, pytest.raises(SourceError) as raised:
        speeds.extend(field_data(m.data, FLOAT64)
                      for m in source.messages() if m.topic == "/speed")
    assert 0 < len(speeds) < COUNT
    assert speeds == [float(i) for i in range(len(speeds))]
    assert f"bag {bag} is damaged: reading stopped after log time" in str(raised.value)
    assert "the rest of the bag is lost" in str(raised.value)


