"""swanky-host opens its bag on a thread while the app imports (inputs/bag_opener.py)."""

from __future__ import annotations

import tempfile
import threading
import time
from pathlib import Path

import pytest
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from host_bridge.errors import InputError
from host_bridge.inputs.bag import source_runs
from host_bridge.inputs.bag_opener import BagOpener
from robot_relay.sources import mcap_stream

T0 = 1_700_000_000_000_000_000
GENEROUS_S = 60.0
"""Bounds a wait that a loaded machine may stretch."""
STORE = get_typestore(Stores.ROS2_HUMBLE)


def compressed_bag(directory: Path, texts: list[str]) -> Path:
    """A bag as ``ros2 bag record --compression-mode file`` writes it: opening it starts its
    decompression on a thread of its own (robot_relay/sources/mcap_stream.py)."""
    writer = Writer(directory, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.FILE, CompressionFormat.ZSTD)
    string = STORE.types["std_msgs/msg/String"]
    with writer:
        topic = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=STORE)
        for i, text in enumerate(texts):
            writer.write(topic, T0 + i, STORE.serialize_cdr(string(data=text), "std_msgs/msg/String"))
    return directory


def unzstd_threads() -> list[threading.Thread]:
    return [thread for thread in threading.enumerate() if thread.name == "bag-unzstd"]


def temporary_files(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Where rosbags' TemporaryDirectory would decompress bags to, in this test."""
    directory = tmp_path / "tmp"
    directory.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(directory))
    return directory


def test_the_bag_taken_is_opened_and_read_to_its_end(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    temporary = temporary_files(tmp_path, monkeypatch)
    bag = compressed_bag(tmp_path / "bag", ["a", "b", "c"])
    opener = BagOpener(bag, "robot")
    source = opener.take()
    opener.close()  # the bag is the taker's now: still open
    assert source.message_count == 3
    runs = list(source_runs(source))
    source.close()
    assert [(m.topic, bytes(m.data)[8:9], m.log_ns) for run in runs for m in run] == [
        ("/chatter", b"a", T0), ("/chatter", b"b", T0 + 1), ("/chatter", b"c", T0 + 2)]
    assert list(temporary.iterdir()) == []  # streamed: no decompressed copy
    assert unzstd_threads() == []


def test_a_bag_never_taken_is_closed_with_the_opener(monkeypatch: pytest.MonkeyPatch,
                                                     tmp_path: Path) -> None:
    """Three chunks of 1 MiB, one at a time decompressed ahead: the decompressing thread waits
    until the bag is closed."""
    monkeypatch.setattr(mcap_stream, "AHEAD", 1)
    bag = compressed_bag(tmp_path / "bag", ["a" * 1_100_000] * 3)
    opener = BagOpener(bag, "robot")
    deadline = time.monotonic() + GENEROUS_S
    while not unzstd_threads() and time.monotonic() < deadline:
        time.sleep(0.01)  # opening on its own thread, not waiting for take()
    assert len(unzstd_threads()) == 1
    opener.close()
    assert unzstd_threads() == []  # its decompression went with the bag


def test_a_bag_that_cannot_be_opened_is_named_when_taken(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    opener = BagOpener(tmp_path / "empty", "robot")
    with pytest.raises(InputError, match=r"empty is a directory without metadata.yaml"):
        opener.take()
    opener.close()
