"""A rosbag2 recorded with ``--compression-mode file`` is read while it is decompressed
(robot_relay/sources/mcap_stream.py): the same RawMessages, in the same order, as rosbags gives
for it and for the plain MCAP; chunks that overlap in time held until complete; a chunk that goes
back before messages already read named; a truncated file read up to its damage; files the
stream reader does not take opened by rosbags."""

from __future__ import annotations

import logging
import re
import threading
from pathlib import Path
from typing import Any

import pytest
import zstandard
from mcap.writer import CompressionType, IndexType, Writer
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin
from rosbags.rosbag2 import Writer as BagWriter

from robot_relay.sources import mcap_stream
from robot_relay.sources.bag import BagSource
from robot_relay.sources.mcap_stream import StreamedMcapFile
from tests.host_bridge.inputs.test_mcap import (
    QOS,
    STORE,
    bulk_messages,
    fields,
    mcap_messages,
    rosbags_messages,
    string_cdr,
    write_mcap,
)

TYPES = {"/chatter": "std_msgs/msg/String", "/tie": "std_msgs/msg/String",
         "/camera/image_raw": "sensor_msgs/msg/Image"}


def file_compressed(directory: Path, mcap_file: Path, messages: list[tuple[str, int, bytes]]) -> Path:
    """A rosbag2 directory as ``ros2 bag record --compression-mode file`` leaves it, holding
    ``mcap_file`` zstd'ed (its metadata.yaml from rosbags' writer, of the same ``messages``)."""
    writer = BagWriter(directory, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.FILE, CompressionFormat.ZSTD)
    with writer:
        connections = {topic: writer.add_connection(topic, TYPES[topic], typestore=STORE)
                       for topic in dict.fromkeys(topic for topic, _, _ in messages)}
        for topic, log_ns, data in messages:
            writer.write(connections[topic], log_ns, data)
    (compressed,) = directory.glob("*.mcap.zstd")
    compressed.write_bytes(zstandard.ZstdCompressor().compress(mcap_file.read_bytes()))
    return directory


def plain_mcap(path: Path, messages: list[tuple[str, int, bytes]], **options: Any) -> Path:
    """``messages`` in an MCAP as the mcap library writes it, 4 KB chunks, in the order given."""
    with path.open("wb") as stream:
        writer = Writer(stream, chunk_size=4096, compression=CompressionType.NONE, **options)
        writer.start(profile="ros2", library="test")
        channels = {}
        for topic in dict.fromkeys(topic for topic, _, _ in messages):
            text = STORE.generate_msgdef(TYPES[topic], ros_version=2)[0]
            schema = writer.register_schema(TYPES[topic], "ros2msg", text.encode())
            channels[topic] = writer.register_channel(topic, "cdr", schema,
                                                      {"offered_qos_profiles": QOS})
        for sequence, (topic, log_ns, data) in enumerate(messages):
            writer.add_message(channels[topic], log_ns, data, log_ns, sequence)
        writer.finish()  # type: ignore[no-untyped-call]
    return path


def streamed(bag: Path) -> bool:
    with BagSource(bag, "tb3") as source:
        files = source.bulk_files()
        return files is not None and all(isinstance(f, StreamedMcapFile) for f in files)


def unzstd_threads() -> list[threading.Thread]:
    return [thread for thread in threading.enumerate() if thread.name == "bag-unzstd"]


def warnings(caplog: pytest.LogCaptureFixture, bag: Path) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING
            and r.name == "swanky.relay" and str(bag) in r.getMessage()]


@pytest.mark.parametrize("hold", [mcap_stream.HOLD_BYTES, 256 * 1024], ids=["default", "256k"])
def test_a_file_compressed_bag_is_streamed_and_yields_what_rosbags_yields(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch, hold: int
) -> None:
    """Channels interleaved, times going back across chunks (overlapping chunks, held: with 256
    KiB held, groups of the file's 1.5 MB are handed on as it is read) and tied between chunks,
    images above and below LARGE_PAYLOAD."""
    monkeypatch.setattr(mcap_stream, "HOLD_BYTES", hold)
    messages = mcap_messages()
    mcap_file = write_mcap(tmp_path / "plain.mcap", CompressionType.NONE)
    bag = file_compressed(tmp_path / "bag", mcap_file, messages)
    assert streamed(bag)
    plain = [fields(raw) for raw in bulk_messages(mcap_file)]
    with caplog.at_level(logging.WARNING, "swanky.relay"):
        got = [fields(raw) for raw in bulk_messages(bag, size=5)]
    assert got == rosbags_messages(bag) == plain
    assert len(got) == 280
    assert [(topic, log_ns) for _, topic, _, _, _, _, log_ns, _ in got[:3]] == [
        ("/chatter", 967_000_000), ("/tie", 967_000_000), ("/chatter", 975_000_000)]
    assert warnings(caplog, bag) == []
    assert unzstd_threads() == []


def test_zstd_chunks_inside_a_compressed_file(tmp_path: Path) -> None:
    mcap_file = write_mcap(tmp_path / "plain.mcap", CompressionType.ZSTD)
    bag = file_compressed(tmp_path / "bag", mcap_file, mcap_messages())
    assert streamed(bag)
    assert [fields(raw) for raw in bulk_messages(bag)] == rosbags_messages(mcap_file)


def test_rosbags_writer_puts_its_channels_in_the_first_chunk(tmp_path: Path) -> None:
    directory = tmp_path / "bag"
    writer = BagWriter(directory, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.FILE, CompressionFormat.ZSTD)
    with writer:
        chatter = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=STORE)
        for i in range(30_000):  # 1.1 MB: two chunks
            writer.write(chatter, 10 * i, string_cdr(f"hello {i}"))
    assert streamed(directory)
    got = bulk_messages(directory)
    assert [fields(raw) for raw in got] == rosbags_messages(directory)
    assert len(got) == 30_000
    assert got[0].definition is not None
    assert got[0].definition.encoding == "ros2msg"


def test_a_chunk_that_goes_back_before_messages_read_is_named(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The recording's clock went back (a simulated clock restarted) after more than the chunks
    held: rosbags, reading the summary first, sorts the second stretch before the first;
    streamed, it comes after the first, and the chunks are named."""
    monkeypatch.setattr(mcap_stream, "HOLD_BYTES", 16 * 1024)
    first = [("/chatter", 10**9 + 10**6 * i, string_cdr(f"first {i}")) for i in range(4000)]
    second = [("/chatter", 10**6 * i + 1, string_cdr(f"second {i}")) for i in range(400)]
    mcap_file = plain_mcap(tmp_path / "plain.mcap", first + second)
    bag = file_compressed(tmp_path / "bag", mcap_file, first + second)
    with caplog.at_level(logging.WARNING, "swanky.relay"):
        got = [(raw.log_ns, bytes(raw.data)) for raw in bulk_messages(bag)]
    reference = [(raw[6], raw[3]) for raw in rosbags_messages(bag)]
    assert sorted(got) == reference  # nothing lost
    # What was handed on before the clock went back comes first; the rest (held) in log time.
    handed = next(i for i, (_, data) in enumerate(got) if b"second" in data)
    assert 0 < handed < len(first)
    assert got[:handed] == [(log_ns, data) for _, log_ns, data in first[:handed]]
    assert got[handed:] == sorted(got[handed:])
    (warning,) = warnings(caplog, bag)
    assert warning.startswith(f"{bag / 'bag.mcap.zstd'}: chunks start before messages already "
                              "read (the chunk at byte ")
    assert warning.endswith("their messages are read after those, not in log-time order")


@pytest.mark.parametrize("damage", ["truncated", "corrupt"])
def test_a_damaged_file_is_read_up_to_its_damage(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch, damage: str
) -> None:
    """Truncated: everything before the cut is read. Corrupt: everything before the chunk
    record zstd was decompressing when it found the damage."""
    monkeypatch.setattr(mcap_stream, "COMPRESSED_READ", 4 * 1024)
    messages = [("/chatter", 10**6 * i, string_cdr(f"hello {i}")) for i in range(20_000)]
    mcap_file = plain_mcap(tmp_path / "plain.mcap", messages)  # 1.3 MB: zstd blocks of 128 KB
    bag = file_compressed(tmp_path / "bag", mcap_file, messages)
    (compressed,) = bag.glob("*.mcap.zstd")
    data = compressed.read_bytes()
    middle = len(data) // 2
    compressed.write_bytes(data[:middle] if damage == "truncated"
                           else data[:middle] + bytes(100) + data[middle + 100 :])
    with caplog.at_level(logging.WARNING, "swanky.relay"):
        got = [bytes(raw.data) for raw in bulk_messages(bag)]
    whole = [data for _, _, data in messages]
    assert 0 < len(got) < len(whole)
    assert got == whole[: len(got)]  # every message before the damage, in order
    (warning,) = warnings(caplog, bag)
    why = (r"the file ends inside a record \(it is truncated\)" if damage == "truncated"
           else r"the zstd stream does not decompress \(.+\)")
    assert re.fullmatch(
        f"bag {re.escape(str(compressed))} is damaged \\(the readable part was read\\); lost: "
        f"{why}, at byte \\d+ of the decompressed file: the rest of the file is lost", warning)


def test_a_file_without_message_indexes_is_opened_by_rosbags(tmp_path: Path) -> None:
    messages = [("/chatter", 1000 * i, string_cdr(f"hello {i}")) for i in range(300)]
    mcap_file = plain_mcap(tmp_path / "plain.mcap", messages, index_types=IndexType.NONE,
                           use_chunking=False)
    bag = file_compressed(tmp_path / "bag", mcap_file, messages)
    assert not streamed(bag)
    got = [bytes(raw.data) for raw in bulk_messages(bag)]
    assert got == [data for _, _, data in messages]


def test_closing_while_reading_ends_the_decompression(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A file many chunks long (the thread waits with its chunks read ahead); the bag is closed
    after one window: the thread ends."""
    monkeypatch.setattr(mcap_stream, "HOLD_BYTES", 16 * 1024)
    monkeypatch.setattr(mcap_stream, "AHEAD", 64 * 1024)
    messages = [("/chatter", 10**6 * i, string_cdr("x" * 2000)) for i in range(3000)]
    mcap_file = plain_mcap(tmp_path / "plain.mcap", messages)
    bag = file_compressed(tmp_path / "bag", mcap_file, messages)
    with BagSource(bag, "tb3") as source:
        files = source.bulk_files()
        assert files is not None
        windows = files[0].windows(100, 1 << 20)
        assert sum(len(run.log_ns) for run in next(windows)) == 100
        assert len(unzstd_threads()) == 1
    assert unzstd_threads() == []
    del windows  # its generator, done


def test_a_looped_replay_reads_the_file_again(tmp_path: Path) -> None:
    messages = [("/chatter", 10**6 * i, string_cdr(f"hello {i}")) for i in range(50)]
    mcap_file = plain_mcap(tmp_path / "plain.mcap", messages)
    bag = file_compressed(tmp_path / "bag", mcap_file, messages)
    with BagSource(bag, "tb3", loop=True) as source:
        runs = source.runs()
        got: list[bytes] = []
        while len(got) < 120:
            _, payloads, _ = next(runs)
            got += [bytes(payload) for payload in payloads]
        del runs
    once = [data for _, _, data in messages]
    assert got[:120] == (once * 3)[:120]
    assert unzstd_threads() == []
