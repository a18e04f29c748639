"""The messages of a rosbag2 sqlite3 storage file in bulk: rows fetched a batch at a time and
taken apart in C, no Python call per message past sqlite's own row tuples.

rosbags' reader (``Sqlite3Reader.messages``) yields each row through a generator, BagSource makes
a RawMessage of each, and the host groups them by topic again: on the small-message file of
``benchmarks/bag_conversion.py`` that cost ``swanky-host --bag`` 3 times the CPU of the same
messages in an MCAP. Here rosbags' own query runs on the connection rosbags opened (so the rows come
in the same order), its rows are split into columns with ``zip``, ``numpy.fromiter`` and
``bytes.join``, and a window is handed on as the :class:`~robot_relay.sources.mcap.TopicRun`\\ s
the MCAP bulk reader gives: small payloads joined into one buffer, large ones (from
LARGE_PAYLOAD on) each its own bytes object, not copied.

A damaged row (a timestamp that is not an integer, data that is not a blob: what rosbag2 never
writes) is skipped and counted, and one warning after the file names the bag and the count, as
BagSource's rosbags path does; a read error in the middle of the file (a corrupt page) ends it
with a SourceError naming the bag and where reading stopped.

A rosbag2 directory's sqlite3 files are opened by :class:`UncountedSqlite3Reader`, rosbags' reader
but for the rows it counts at open (:class:`~robot_relay.sources.rosbag2.Rosbag2Reader`).
"""

from __future__ import annotations

import contextlib
import itertools
import logging
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from rosbags.interfaces import (
    Connection,
    ConnectionExtRosbag2,
    MessageDefinition,
    MessageDefinitionFormat,
)
from rosbags.rosbag2.errors import ReaderError
from rosbags.rosbag2.metadata import parse_qos
from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader

from robot_relay.errors import SourceError
from robot_relay.sources.mcap import LARGE_PAYLOAD, TopicRun, topic_indexes, topic_runs
from robot_relay.wire import TopicInfo

log = logging.getLogger("swanky.relay")

# rosbags' query (rosbags.rosbag2.storage_sqlite3.Sqlite3Reader.messages), so the same order.
QUERY = ("SELECT topics.id,messages.timestamp,messages.data FROM messages JOIN topics ON "
         "messages.topic_id=topics.id WHERE topics.id IN ({}) ORDER BY timestamp")
FIRST_BATCH = 16
MOST_BATCH = 8192
# A batch holds so many rows that, were each as large as the largest payload read so far, they
# would be this share of a window's payload bytes: a window of images ends near its byte bound,
# and no more rows than that are in memory beyond it.
BATCH_SHARE = 4


DEFINITION_FORMATS = {"ros2msg": MessageDefinitionFormat.MSG, "ros2idl": MessageDefinitionFormat.IDL}


class UncountedSqlite3Reader(Sqlite3Reader):
    """rosbags' reader of one sqlite3 storage file of a rosbag2 directory, opened without
    counting its rows.

    rosbags' ``Sqlite3Reader._open`` counts every topic's messages (a join of the whole messages
    table) and then all of them again for the file's own metadata: 0.4 s of the 470k-message file
    of ``benchmarks/bag_conversion.py``, more than reading its rows in bulk takes. In a rosbag2
    directory neither count is used: rosbags' DirectoryReader reports metadata.yaml's. This
    ``_open`` (replacing rosbags 0.11's, private: pinned in pyproject.toml) reads the schema
    version, the topics and the message definitions as rosbags does, each connection with a
    message count of 0 and the file's metadata empty."""

    def _open(self) -> None:
        connection = self.dbconn
        assert connection is not None
        tables = {name for (name,) in connection.execute(
            "SELECT name FROM sqlite_master WHERE type='table'")}
        if not {"messages", "topics"} <= tables:
            msg = f"Cannot open database {self.path} or database missing tables."
            raise ReaderError(msg)
        if "schema" in tables:
            (schema,) = connection.execute("SELECT schema_version FROM schema").fetchone() or (-1,)
        else:
            topic_columns = {row[1] for row in connection.execute("PRAGMA table_info(topics)")}
            schema = 2 if "offered_qos_profiles" in topic_columns else 1
        definitions: dict[str, MessageDefinition] = {}
        if schema >= 4:
            for name, encoding, text in connection.execute(
                "SELECT topic_type, encoding, encoded_message_definition FROM message_definitions "
                "ORDER BY id"
            ):
                definitions.setdefault(name, MessageDefinition(DEFINITION_FORMATS[encoding], text))
        qos = ", offered_qos_profiles" if schema >= 2 else ", ''"
        digest = ", type_description_hash" if schema >= 4 else ", ''"
        self.schema = schema
        self.msgtypes = []  # rosbags' own record of the definitions: read by nothing but _open
        self.connections = [
            Connection(
                cid, topic, msgtype,
                definitions.get(msgtype, MessageDefinition(MessageDefinitionFormat.NONE, "")),
                type_hash, 0, ConnectionExtRosbag2(serialization, parse_qos(profiles)), self,
            )
            for cid, topic, msgtype, serialization, profiles, type_hash in connection.execute(
                f"SELECT id, name, type, serialization_format{qos}{digest} FROM topics ORDER BY id"
            )
        ]


@dataclass(frozen=True, slots=True)
class _Batch:
    """Consecutive rows of the query: their storage connection ids, log times and payloads."""

    channels: npt.NDArray[np.int64]
    log_ns: npt.NDArray[np.int64]
    payloads: tuple[bytes, ...]
    payload_bytes: int
    largest: int


class Sqlite3File:
    """One sqlite3 storage file of a rosbag2, opened by rosbags (``storage``, its
    ``Sqlite3Reader``), read in bulk: the messages of the connections in ``channels`` (storage
    connection id -> topic). ``bag`` is the path warnings and errors name."""

    def __init__(self, bag: Path, storage: Any, channels: Mapping[int, TopicInfo]) -> None:
        self.bag = bag
        self.channels = channels
        self._storage = storage
        self._topic_of = topic_indexes(channels)
        self._malformed = 0
        self._read = 0
        self._last_ns: int | None = None

    def close(self) -> None:
        """Nothing to close: the connection is rosbags', closed with its reader."""

    def windows(self, messages: int, payload_bytes: int) -> Iterator[list[TopicRun]]:
        """The messages in windows of at most ``messages`` messages and about ``payload_bytes``
        bytes of payload (at least one message), each window as :func:`topic_runs`."""
        cursor = self._start()
        size = FIRST_BATCH
        largest = 1
        ended = False
        while not ended:
            window: list[_Batch] = []
            count = window_bytes = 0
            while count < messages and window_bytes < payload_bytes:
                batch = self._take(cursor, min(size, messages - count))
                if batch is None:
                    ended = True
                    break
                window.append(batch)
                count += len(batch.payloads)
                window_bytes += batch.payload_bytes
                largest = max(largest, batch.largest)
                size = max(1, min(MOST_BATCH, payload_bytes // BATCH_SHARE // largest))
            if count:
                yield self._runs(window)
        self._end()

    def records(self, size: int) -> Iterator[list[tuple[TopicInfo, int, bytes]]]:
        """The messages as (topic, log time, payload), at most ``size`` a list."""
        cursor = self._start()
        infos = self.channels
        while (batch := self._take(cursor, size)) is not None:
            yield list(zip(map(infos.__getitem__, batch.channels.tolist()), batch.log_ns.tolist(),
                           batch.payloads, strict=True))
        self._end()

    def _start(self) -> Any:
        """A pass over the file: rosbags' query, run."""
        self._malformed = self._read = 0
        self._last_ns = None
        ids = tuple(self.channels)
        with self._reading():
            return self._storage.dbconn.execute(QUERY.format(",".join("?" * len(ids))), ids)

    def _take(self, cursor: Any, size: int) -> _Batch | None:
        """The next batch of at most ``size`` rows (at least one), None at the end."""
        while True:
            with self._reading():
                rows = list(itertools.islice(cursor, size))
            if not rows:
                return None
            batch = self._batch(rows)
            if batch is not None:
                return batch

    def _end(self) -> None:
        """After a pass: the damaged rows it skipped, named."""
        if self._malformed:
            log.warning("bag %s is damaged (the readable part was read); lost: %d messages whose "
                        "log time or payload is malformed", self.bag, self._malformed)

    @contextlib.contextmanager
    def _reading(self) -> Iterator[None]:
        """A read error in the middle of the file as the SourceError that names where."""
        try:
            yield
        except Exception as err:  # apsw raises whatever sqlite hits in a damaged file
            where = "at its start" if self._last_ns is None else f"after log time {self._last_ns} ns"
            msg = (f"bag {self.bag} is damaged: reading stopped {where}, after {self._read} "
                   f"messages ({type(err).__name__}: {err}); the rest of the bag is lost")
            raise SourceError(msg) from err

    def _batch(self, rows: list[tuple[Any, Any, Any]]) -> _Batch | None:
        """The rows as a batch, those whose timestamp is not an integer or whose data is not
        bytes left out (counted); None when none is left."""
        channels, stamps, payloads = zip(*rows, strict=True)
        if set(map(type, stamps)) != {int} or set(map(type, payloads)) != {bytes}:
            kept = [row for row in rows if type(row[1]) is int and type(row[2]) is bytes]
            self._malformed += len(rows) - len(kept)
            if not kept:
                return None
            channels, stamps, payloads = zip(*kept, strict=True)
        count = len(stamps)
        self._read += count
        self._last_ns = stamps[-1]
        sizes = np.fromiter(map(len, payloads), np.int64, count)
        return _Batch(np.fromiter(channels, np.int64, count), np.fromiter(stamps, np.int64, count),
                      payloads, int(sizes.sum()), int(sizes.max()))

    def _runs(self, window: Sequence[_Batch]) -> list[TopicRun]:
        channels = np.concatenate([batch.channels for batch in window])
        log_ns = np.concatenate([batch.log_ns for batch in window])
        payloads = tuple(itertools.chain.from_iterable(batch.payloads for batch in window))
        sizes = np.fromiter(map(len, payloads), np.int64, len(payloads))
        large = sizes >= LARGE_PAYLOAD
        small_sizes = np.where(large, 0, sizes)
        ends = np.cumsum(small_sizes)
        starts = ends - small_sizes
        sources = np.zeros(len(payloads), np.int64)
        buffers: tuple[bytes, ...]
        if large.any():
            where = np.flatnonzero(large)
            big = tuple(payloads[i] for i in where.tolist())
            small = itertools.compress(payloads, (~large).tolist())
            buffers = (b"".join(small), *big)
            sources[where] = np.arange(1, len(big) + 1)
            starts[where] = 0
            ends[where] = sizes[where]
        else:
            buffers = (b"".join(payloads),)
        return topic_runs(self.channels, self._topic_of, buffers,
                          (sources, starts, ends, channels, log_ns))
