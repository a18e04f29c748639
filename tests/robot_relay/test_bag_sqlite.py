"""A rosbag2 in sqlite3 storage read in bulk (robot_relay/sources/sqlite.py) gives exactly what
the record-by-record rosbags path gives: every topic's payloads and log times in rosbags' order,
unpaced in windows within their bounds, paced record by record, and through ``swanky-host
--bag``'s runs; a damaged row is skipped and counted as the rosbags path counts it. Each holds
whether the rows are fetched in the reader's process or read ahead by a process of their own
(host_bridge/inputs/rows_ahead.py, what the host does), and that process ends with the bag.

The bag is test_bag_bulk's (Imu, String, a latched TFMessage, 100 KB images, ties between topics),
written by rosbags' Writer with sqlite3 storage, as one .db3 of a rosbag2 directory, or split in
two files.
"""

from __future__ import annotations

import logging
import os
import signal
import sqlite3
import subprocess
from pathlib import Path

import pytest
from rosbags.rosbag2 import StoragePlugin, Writer

from host_bridge.inputs.bag import bag_runs
from host_bridge.inputs.base import MessageRun
from host_bridge.inputs.rows_ahead import read_ahead
from robot_relay.errors import SourceError
from robot_relay.sources.bag import BagSource
from robot_relay.sources.mcap import LARGE_PAYLOAD
from robot_relay.sources.sqlite import Sqlite3File
from robot_relay.sources.sqlite_rows import BATCH_SHARE
from tests.integration.procs import READER_MAIN, children
from tests.robot_relay.test_bag_bulk import (
    COUNTS,
    STORE,
    TYPES,
    bag_messages,
    bulk_runs,
    per_topic,
    record_runs,
    written,
)

IMAGE_BYTES = len(next(data for topic, _, data in bag_messages() if topic == "/camera/image_raw"))


def sqlite_bag(path: Path) -> Path:
    with Writer(path, version=9, storage_plugin=StoragePlugin.SQLITE3) as writer:
        connections = {topic: writer.add_connection(topic, msgtype, typestore=STORE)
                       for topic, msgtype in TYPES.items()}
        for topic, log_ns, data in bag_messages():
            writer.write(connections[topic], log_ns, data)
    return path


def long_sqlite_bag(path: Path, rows: int) -> Path:
    """``rows`` copies of one message: at one row a batch, more frames than the reading process's
    pipe holds, so it is still writing while the host reads the first."""
    topic, _, data = next(iter(bag_messages()))
    with Writer(path, version=9, storage_plugin=StoragePlugin.SQLITE3) as writer:
        connection = writer.add_connection(topic, TYPES[topic], typestore=STORE)
        for row in range(rows):
            writer.write(connection, 1_000_000_000 + row, data)
    return path


AHEAD = pytest.mark.parametrize("ahead", [False, True], ids=["here", "read-ahead"])


def readers() -> list[int]:
    """The processes reading a sqlite3 file ahead for this one."""
    return children(os.getpid(), READER_MAIN)


@AHEAD
def test_a_sqlite3_bag_is_read_in_bulk_as_rosbags_reads_it(tmp_path: Path, ahead: bool) -> None:
    bag = sqlite_bag(tmp_path / "bag")
    with BagSource(bag, "tb3") as source:
        files = source.bulk_files()
        assert files is not None
        assert [type(opened) for opened in files] == [Sqlite3File]
        record = record_runs(source)
        if ahead:
            read_ahead(source, 0, 10**9)
            assert len(readers()) == 1
        bulk = bulk_runs(source)
        assert readers() == []  # its pass read, it ended
        messages = [(m.topic, m.log_ns, bytes(m.data)) for m in source.messages()]
    assert messages == bag_messages()  # rosbags' order is the order written
    assert per_topic(bulk) == per_topic(record) == written()
    assert len(bulk) < 20  # unpaced: windows of many messages, a run per topic each
    images = [payload for info, payloads, _ in bulk if info.topic == "/camera/image_raw"
              for payload in payloads]
    assert len(images) == COUNTS["/camera/image_raw"]
    assert all(isinstance(payload, memoryview) for payload in images)
    infos = {info.topic: info for info, _, _ in bulk}
    assert infos["/imu"].msgtype == "sensor_msgs/msg/Imu"
    assert infos["/imu"].definition is not None  # rosbags' Writer stores the definitions
    assert infos["/tf_static"].qos.durability == "transient_local"  # conventionally latched


def test_a_paced_replay_reads_the_sqlite3_bag_record_by_record_in_bulk(tmp_path: Path) -> None:
    with BagSource(sqlite_bag(tmp_path / "bag"), "tb3", rate=1000) as source:
        assert per_topic(bulk_runs(source)) == written()


@AHEAD
@pytest.mark.parametrize(("messages", "payload_bytes"), [(100, 10**9), (10**6, 1_000_000), (1, 1)])
def test_windows_keep_their_bounds_and_rosbags_order(
    tmp_path: Path, messages: int, payload_bytes: int, ahead: bool
) -> None:
    """At most ``messages`` a window, about ``payload_bytes`` of payload (at most one batch over:
    a quarter of the bound, or one message), and each topic's messages in order."""
    with BagSource(sqlite_bag(tmp_path / "bag"), "tb3") as source:
        files = source.bulk_files()
        assert files is not None
        if ahead:
            read_ahead(source, 0, payload_bytes)
        windows = [window for opened in files for window in opened.windows(messages, payload_bytes)]
    got: dict[str, list[tuple[bytes, int]]] = {}
    for window in windows:
        sizes = [len(payload) for run in window for payload in run.payloads()]
        assert 1 <= len(sizes) <= messages
        assert sum(sizes) <= payload_bytes + max(payload_bytes // BATCH_SHARE, IMAGE_BYTES)
        for run in window:
            got.setdefault(run.info.topic, []).extend(
                (bytes(payload), stamp) for payload, stamp in
                zip(run.payloads(), run.log_ns.tolist(), strict=True))
    assert got == written()
    assert len(windows) >= (sum(COUNTS.values()) // messages if messages < 10**6 else 3)


def test_a_split_sqlite3_bag_is_read_file_by_file(tmp_path: Path) -> None:
    """Two .db3 files of one bag (rosbag2's --max-bag-size): their messages one file after the
    other, as rosbags reads them, through the host's runs."""
    bag = sqlite_bag(tmp_path / "bag")
    second = sqlite_bag(tmp_path / "second")
    (bag / "bag_1.db3").write_bytes((second / "second.db3").read_bytes())
    metadata = (bag / "metadata.yaml").read_text()
    assert "- bag.db3\n" in metadata
    (bag / "metadata.yaml").write_text(metadata.replace("- bag.db3\n", "- bag.db3\n  - bag_1.db3\n", 1))
    runs = list(bag_runs(bag, "tb3"))
    bulk = [run for run in runs if isinstance(run, MessageRun)]
    assert len(bulk) == len(runs)  # the bulk reader's runs, not rosbags' RawMessages
    got: dict[str, list[tuple[bytes, int]]] = {}
    for run in bulk:
        got.setdefault(run.topic, []).extend((bytes(m.data), m.log_ns or 0) for m in run)
    assert got == {topic: messages * 2 for topic, messages in written().items()}


@AHEAD
def test_a_damaged_row_is_skipped_counted_and_named(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, ahead: bool
) -> None:
    bag = sqlite_bag(tmp_path / "bag")
    with sqlite3.connect(bag / "bag.db3") as db:
        db.execute("UPDATE messages SET timestamp = 'x' WHERE id = 3")
        db.execute("UPDATE messages SET data = 'text' WHERE id = 5")
        # a payload large enough to be fetched apart (sqlite_rows.LEFT_IN_FILE), but text
        image = "SELECT messages.id FROM messages JOIN topics ON topic_id = topics.id WHERE name = ?"
        ids = [row_id for (row_id,) in db.execute(image, ("/camera/image_raw",))]
        db.execute("UPDATE messages SET data = hex(data) WHERE id = ?", (ids[1],))
    with caplog.at_level(logging.WARNING), BagSource(bag, "tb3") as source:
        if ahead:
            read_ahead(source, 0, 10**9)
        bulk = per_topic(bulk_runs(source))
    assert sum(len(messages) for messages in bulk.values()) == sum(COUNTS.values()) - 3
    assert len(bulk["/camera/image_raw"]) == COUNTS["/camera/image_raw"] - 1
    [warning] = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert f"bag {bag} is damaged" in warning
    assert "lost: 3 messages whose log time or payload is malformed" in warning


def test_a_read_error_mid_file_names_the_bag_and_where_it_stopped(tmp_path: Path) -> None:
    bag = sqlite_bag(tmp_path / "bag")
    with BagSource(bag, "tb3") as source:
        files = source.bulk_files()
        assert files is not None
        [opened] = files
        windows = opened.windows(50, 1_000_000)  # batches of a few rows: the rest unread
        next(windows)
        with (bag / "bag.db3").open("r+b") as file:  # every page past the first 400 KB
            size = file.seek(0, 2)
            file.seek(400_000)
            file.write(b"\xa5" * (size - 400_000))
        with pytest.raises(SourceError, match=rf"bag {bag} is damaged: reading stopped after log "
                                              r"time \d+ ns, after \d+ messages"):
            list(windows)
    assert LARGE_PAYLOAD < IMAGE_BYTES  # the images above are the large, uncopied kind


def test_a_read_error_mid_file_read_ahead_names_the_bag_and_where_it_stopped(tmp_path: Path) -> None:
    """Pages in the middle of the file overwritten before the reading process starts: what it
    read before them is handed on, then the error, as when the rows are fetched here."""
    bag = sqlite_bag(tmp_path / "bag")
    with BagSource(bag, "tb3") as source:
        with (bag / "bag.db3").open("r+b") as file:
            file.seek(400_000)
            file.write(b"\xa5" * 400_000)
        read_ahead(source, 0, 10**9)
        files = source.bulk_files()
        assert files is not None
        windows = files[0].windows(10, 10**9)
        first = next(windows)
        with pytest.raises(SourceError, match=rf"bag {bag} is damaged: reading stopped after log "
                                              r"time \d+ ns, after \d+ messages \(CorruptError: "):
            next(windows)
    assert sum(len(run.log_ns) for run in first) == 10


def test_a_reading_process_that_dies_names_the_bag_and_loses_nothing_before(tmp_path: Path) -> None:
    # The bag of the other tests fitted in the pipe: its reader could finish before the kill
    # (the suite at 00:44, 2026-11-30).
    bag = long_sqlite_bag(tmp_path / "bag", 40_000)
    with BagSource(bag, "tb3") as source:
        files = source.bulk_files()
        assert files is not None
        read_ahead(source, 0, 1)  # one-row batches: the process is still writing when it dies
        windows = files[0].windows(10, 10**9)
        first = next(windows)
        [reader] = readers()
        os.kill(reader, signal.SIGKILL)
        with pytest.raises(SourceError, match=rf"bag {bag}: the process reading {bag / 'bag.db3'} "
                                              rf"ended \(exit code -{signal.SIGKILL}\) after \d+ "
                                              "messages; the rest of the bag is lost"):
            list(windows)
    assert sum(len(run.log_ns) for run in first) == 10


def test_where_no_process_starts_the_rows_are_fetched_here(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def refused(*args: object, **kwargs: object) -> None:
        raise OSError(11, "Resource temporarily unavailable")

    monkeypatch.setattr(subprocess, "Popen", refused)
    with BagSource(sqlite_bag(tmp_path / "bag"), "tb3") as source:
        read_ahead(source, 0, 10**9)
        assert per_topic(bulk_runs(source)) == written()


def test_a_bag_closed_unread_ends_its_reading_process(tmp_path: Path) -> None:
    with BagSource(sqlite_bag(tmp_path / "bag"), "tb3") as source:
        read_ahead(source, 0, 1)
        [reader] = readers()
    assert readers() == []
    with pytest.raises(ChildProcessError):  # waited for: no zombie left
        os.waitpid(reader, os.WNOHANG)


# What each rosbag2 sqlite3 schema drops from the newest one rosbags' Writer writes (4: schema and
# message_definitions tables, type hashes); 2 is Foxy's and Galactic's QoS column without a schema
# table, 1 Dashing's and Eloquent's topics.
OLDER_SCHEMAS = {
    4: [],
    2: ["DROP TABLE schema", "DROP TABLE message_definitions",
        "ALTER TABLE topics DROP COLUMN type_description_hash"],
    1: ["DROP TABLE schema", "DROP TABLE message_definitions",
        "ALTER TABLE topics DROP COLUMN type_description_hash",
        "ALTER TABLE topics DROP COLUMN offered_qos_profiles"],
}


@pytest.mark.parametrize("schema", sorted(OLDER_SCHEMAS))
def test_a_sqlite3_file_opens_with_rosbags_connections_but_no_counts(tmp_path: Path, schema: int) -> None:
    from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader

    from robot_relay.sources.rosbag2 import Rosbag2Reader
    from robot_relay.sources.sqlite import UncountedSqlite3Reader

    bag = sqlite_bag(tmp_path / "bag")
    [db3] = bag.glob("*.db3")
    with sqlite3.connect(db3) as db:
        for statement in OLDER_SCHEMAS[schema]:
            db.execute(statement)
    db.close()
    opened = []
    for reader in (Sqlite3Reader(db3), UncountedSqlite3Reader(db3)):
        reader.open()
        opened.append((reader.schema, [c._replace(owner=None) for c in reader.connections]))
        reader.close()
    (rosbags_schema, counted), (schema_read, uncounted) = opened
    assert schema_read == rosbags_schema == schema
    assert [c.msgcount for c in counted] == [COUNTS[c.topic] for c in counted]
    assert uncounted == [c._replace(msgcount=0) for c in counted]
    if schema == 4:
        assert {c.msgdef.format.name for c in uncounted} == {"MSG"}
    with Rosbag2Reader(bag) as directory:  # a directory's: the counts are metadata.yaml's
        storages = directory.storage.storages  # type: ignore[attr-defined]  # its DirectoryReader
        assert [type(storage) for storage in storages] == [UncountedSqlite3Reader]
        assert {c.topic: c.msgcount for c in directory.connections} == COUNTS
        assert directory.message_count == sum(COUNTS.values())
