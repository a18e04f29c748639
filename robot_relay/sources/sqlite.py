"""The messages of a rosbag2 sqlite3 storage file in bulk: rows fetched a batch at a time and
taken apart in C, no Python call per message past sqlite's own row tuples.

rosbags' reader (``Sqlite3Reader.messages``) yields each row through a generator, BagSource makes
a RawMessage of each, and the host groups them by topic again: on the small-message file of
``benchmarks/bag_conversion.py`` that cost ``swanky-host --bag`` 3 times the CPU of the same
messages in an MCAP. Here rosbags' own query runs (so the rows come in the same order), each batch
of rows is packed into columns (:mod:`robot_relay.sources.sqlite_rows`: arrays and one joined
buffer of payloads), and a window is handed on as the
:class:`~robot_relay.sources.mcap.TopicRun`\\ s the MCAP bulk reader gives.

The rows are fetched on the connection rosbags opened, or read from elsewhere
(:meth:`Sqlite3File.read_from`): the host converting a bag has them fetched by a process of their
own (host_bridge/inputs/rows_ahead.py), the same batches.

A damaged row (a timestamp that is not an integer, data that is not a blob: what rosbag2 never
writes) is skipped and counted, and one warning after the file names the bag and the count, as
BagSource's rosbags path does; a read error in the middle of the file (a corrupt page) ends it
with a SourceError naming the bag and where reading stopped.

A rosbag2 directory's sqlite3 files are opened by :class:`UncountedSqlite3Reader`, rosbags' reader
but for the rows it counts at open (:class:`~robot_relay.sources.rosbag2.Rosbag2Reader`).
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

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
from robot_relay.sources import sqlite_rows
from robot_relay.sources.mcap import TopicRun, topic_indexes, topic_runs
from robot_relay.sources.sqlite_rows import LEFT_IN_FILE, Packed, Rows, RowsError
from robot_relay.wire import TopicInfo

log = logging.getLogger("swanky.relay")

RECORD_BYTES = 16 * 1024 * 1024
"""About how many payload bytes a list of :meth:`Sqlite3File.records` holds."""

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


class PackedRows(Protocol):
    """Batches of a file's rows read elsewhere, in :class:`~robot_relay.sources.sqlite_rows.Rows`'
    order: what :meth:`Sqlite3File.read_from` takes."""

    malformed: int
    """Rows skipped so far as malformed."""

    def batches(self) -> Iterator[Packed]:
        """The batches; a read error as a RowsError."""
        ...

    def close(self) -> None: ...


@dataclass(frozen=True, slots=True)
class _Batch:
    """Consecutive rows: their storage connection ids, log times and payloads (message ``i`` is
    ``buffers[sources[i]][starts[i]:ends[i]]``)."""

    channels: npt.NDArray[np.int64]
    log_ns: npt.NDArray[np.int64]
    sources: npt.NDArray[np.int64]
    starts: npt.NDArray[np.int64]
    ends: npt.NDArray[np.int64]
    buffers: tuple[bytes | memoryview, ...]

    def __len__(self) -> int:
        return len(self.log_ns)

    @property
    def payload_bytes(self) -> int:
        return int((self.ends - self.starts).sum())

    def split(self, count: int) -> tuple[_Batch, _Batch]:
        """The first ``count`` rows and the rest, sharing the buffers."""
        return (self._rows(slice(None, count)), self._rows(slice(count, None)))

    def _rows(self, which: slice) -> _Batch:
        return _Batch(self.channels[which], self.log_ns[which], self.sources[which],
                      self.starts[which], self.ends[which], self.buffers)

    def records(self, infos: Mapping[int, TopicInfo]) -> list[tuple[TopicInfo, int, memoryview]]:
        views = [memoryview(buffer) for buffer in self.buffers]
        return [(infos[channel], log_ns, views[source][start:end])
                for channel, log_ns, source, start, end in
                zip(self.channels.tolist(), self.log_ns.tolist(), self.sources.tolist(),
                    self.starts.tolist(), self.ends.tolist(), strict=True)]


class Sqlite3File:
    """One sqlite3 storage file of a rosbag2, opened by rosbags (``storage``, its
    ``Sqlite3Reader``), read in bulk: the messages of the connections in ``channels`` (storage
    connection id -> topic). ``bag`` is the path warnings and errors name."""

    def __init__(self, bag: Path, storage: Any, channels: Mapping[int, TopicInfo]) -> None:
        self.bag = bag
        self.channels = channels
        self._storage = storage
        self._topic_of = topic_indexes(channels)
        self._ahead: PackedRows | None = None
        self._malformed = 0
        self._handed = 0
        self._last_ns: int | None = None

    @property
    def path(self) -> Path:
        """The sqlite3 file."""
        return Path(self._storage.path)

    def read_from(self, ahead: PackedRows) -> None:
        """The next pass takes its batches from ``ahead`` (the host's process reading this file
        ahead: host_bridge/inputs/rows_ahead.py) instead of fetching them; closed with this
        file."""
        self.close()
        self._ahead = ahead

    def close(self) -> None:
        """Close what reads ahead, if anything does; the connection is rosbags', closed with its
        reader."""
        if self._ahead is not None:
            self._ahead.close()
            self._ahead = None

    def windows(self, messages: int, payload_bytes: int) -> Iterator[list[TopicRun]]:
        """The messages in windows of at most ``messages`` messages and about ``payload_bytes``
        bytes of payload (at least one message; at most one batch over), each window as
        :func:`topic_runs`."""
        window: list[_Batch] = []
        count = window_bytes = 0
        for whole in self._batches(payload_bytes):
            rest: _Batch | None = whole
            while rest is not None:
                batch, rest = rest.split(messages - count) if len(rest) > messages - count else (rest, None)
                window.append(batch)
                count += len(batch)
                window_bytes += batch.payload_bytes
                if count >= messages or window_bytes >= payload_bytes:
                    yield self._runs(window)
                    window, count, window_bytes = [], 0, 0
        if window:
            yield self._runs(window)
        self._end()

    def records(self, size: int) -> Iterator[list[tuple[TopicInfo, int, memoryview]]]:
        """The messages as (topic, log time, payload), at most ``size`` a list."""
        for batch in self._batches(RECORD_BYTES, most=size):
            yield batch.records(self.channels)
        self._end()

    def _batches(self, payload_bytes: int, most: int = sqlite_rows.MOST_BATCH) -> Iterator[_Batch]:
        """One pass over the rows: from what reads ahead, if anything does (once), else fetched
        here."""
        ahead, self._ahead = self._ahead, None
        reader = ahead or Rows(self._storage.dbconn, tuple(self.channels), payload_bytes, most)
        packed = reader.batches()
        self._handed, self._last_ns = 0, None
        try:
            for batch in map(self._batch, packed):
                yield batch
                self._handed += len(batch)
                self._last_ns = int(batch.log_ns[-1])
        except RowsError as err:
            raise self._stopped(err) from err
        finally:
            self._malformed = reader.malformed
            if ahead is not None:
                ahead.close()

    def _batch(self, packed: Packed) -> _Batch:
        """A batch of ``packed``, its payloads left in the file fetched here (each its own
        buffer)."""
        lengths = np.frombuffer(packed.sizes, np.int64)
        left = lengths >= LEFT_IN_FILE
        joined = np.where(left, 0, lengths)
        ends = np.cumsum(joined)
        starts = ends - joined
        sources = np.zeros(len(left), np.int64)
        batch = _Batch(np.frombuffer(packed.channels, np.int64),
                       np.frombuffer(packed.log_ns, np.int64), sources, starts, ends,
                       (packed.payloads,))
        rows = np.flatnonzero(left)
        if not len(rows):
            return batch
        ids = np.frombuffer(packed.row_ids, np.int64)[rows].tolist()
        try:
            fetched = dict(self._storage.dbconn.execute(
                f"SELECT id,data FROM messages WHERE id IN ({','.join('?' * len(ids))})", ids))
        except Exception as err:  # apsw raises whatever sqlite hits in a damaged file
            raise RowsError(f"{type(err).__name__}: {err}", self._handed, self._last_ns) from err
        sources[rows] = np.arange(1, len(rows) + 1)
        starts[rows] = 0
        ends[rows] = lengths[rows]
        return dataclasses.replace(batch, buffers=(packed.payloads, *map(fetched.__getitem__, ids)))

    def _stopped(self, err: RowsError) -> SourceError:
        """A read error in the middle of the file as the SourceError that names where."""
        where = "at its start" if err.last_ns is None else f"after log time {err.last_ns} ns"
        return SourceError(f"bag {self.bag} is damaged: reading stopped {where}, after {err.read} "
                           f"messages ({err}); the rest of the bag is lost")

    def _end(self) -> None:
        """After a pass: the damaged rows it skipped, named."""
        if self._malformed:
            log.warning("bag %s is damaged (the readable part was read); lost: %d messages whose "
                        "log time or payload is malformed", self.bag, self._malformed)

    def _runs(self, window: Sequence[_Batch]) -> list[TopicRun]:
        first_buffer = np.cumsum([0, *(len(batch.buffers) for batch in window[:-1])])
        sources = np.concatenate([batch.sources + first
                                  for batch, first in zip(window, first_buffer.tolist(), strict=True)])
        columns = [np.concatenate([getattr(batch, name) for batch in window])
                   for name in ("starts", "ends", "channels", "log_ns")]
        return topic_runs(self.channels, self._topic_of,
                          tuple(itertools.chain.from_iterable(batch.buffers for batch in window)),
                          (sources, *columns))
