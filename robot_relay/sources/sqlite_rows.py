"""A rosbag2 sqlite3 file's message rows in batches, each packed as flat columns: what
:mod:`robot_relay.sources.sqlite` reads in the host's process or, run as a program, in a process
of its own ahead of the host.

A batch is packed the same way in both: its channels, log times and payload sizes as arrays of
int64 and its payloads joined into one buffer (:class:`Packed`), so the reader needs no Python
per row past sqlite's own row tuples. Fetching the rows is what a sqlite3 bag costs beyond an
MCAP one (apsw makes a tuple per row: 0.45 s of CPU for the 470,000 rows of
``benchmarks/bag_conversion.py``'s small-message file), and it cannot move to a thread of the
host: apsw lets the GIL go for every row it steps, so a fetching thread waits for the GIL once a
row while the converting thread holds it. As a program (``python -m
robot_relay.sources.sqlite_rows FILE PAYLOAD_BYTES ID...``) it fetches on a core of its own and
writes the batches to its standard output as frames (:data:`FRAME`), up to :data:`AHEAD_BYTES`
ahead of the reader, then an end frame, or an error frame with what stopped it. It imports no
numpy, so it starts in the time Python does.

rosbags' query, so the rows come in the order rosbags reads them. A row whose timestamp is not an
integer or whose data is not a blob (what rosbag2 never writes) is skipped and counted.
"""

from __future__ import annotations

import functools
import itertools
import struct
import sys
import threading
from array import array
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import IO, Any, TypeVar

LEFT_IN_FILE = 64 * 1024
"""Payloads from this size on (images, clouds) are not in a batch: the batch gives their row ids,
and the reader fetches each where it is used, once (a process reading ahead would copy them into
its pipe and the reader out of it again: 600 MB of images and clouds took 0.65 s more of CPU)."""
# rosbags' query (Sqlite3Reader.messages), so the same order, with each payload's size and row
# id, and no payload left in the file (sqlite reads a blob's size from its row's header, not its
# pages). The size is NULL for a malformed row, so one look at the sizes finds them.
QUERY = ("SELECT topics.id,messages.timestamp,"
         f"CASE WHEN length(messages.data)<{LEFT_IN_FILE} THEN messages.data END,"
         "CASE WHEN typeof(messages.timestamp)='integer' AND typeof(messages.data)='blob' "
         "THEN length(messages.data) END,"
         "messages.id FROM messages JOIN topics ON messages.topic_id=topics.id "
         "WHERE topics.id IN ({}) ORDER BY timestamp")
Row = tuple[Any, Any, Any, Any, Any]
"""(channel, log time, payload or None if left in the file, payload size or None if the row is
malformed, row id), as :data:`QUERY` gives them."""
FIRST_BATCH = 16
MOST_BATCH = 8192
# A batch holds so many rows that, were each as large as the largest payload read so far, they
# would be this share of a window's payload bytes: a window of images ends near its byte bound,
# and no more rows than that are in memory beyond it.
BATCH_SHARE = 4
AHEAD_BYTES = 256 * 1024 * 1024
"""Payload bytes the program fetches ahead of its reader: the whole small-message file of
``benchmarks/bag_conversion.py`` (137 MB) while the host imports its app."""

FRAME = struct.Struct("<Bqqqq")
"""A frame's header: kind (:data:`BATCH`, :data:`END`, :data:`FAILED`), rows in the batch (or
read in all, for the other two kinds), rows skipped as malformed so far, the last log time read
(-1 before any), bytes after the arrays. A batch's header is followed by its :class:`Packed`
arrays (channels, log times, payload sizes, row ids: int64 each) and its joined
payloads; a failure's by its message (UTF-8)."""
BATCH, END, FAILED = 0, 1, 2
_T = TypeVar("_T")


@dataclass(frozen=True, slots=True)
class Packed:
    """One batch of rows as flat columns, native-endian int64 arrays (the payloads' sizes and
    row ids: those of :data:`LEFT_IN_FILE` bytes and more are left in the file), and the other
    payloads joined."""

    channels: array[int] | memoryview
    log_ns: array[int] | memoryview
    sizes: array[int] | memoryview
    row_ids: array[int] | memoryview
    payloads: bytes | memoryview

    def __len__(self) -> int:
        return len(self.log_ns)


class RowsError(Exception):
    """Reading the rows stopped: ``read`` rows read before, the last at ``last_ns`` (None before
    any)."""

    def __init__(self, cause: str, read: int, last_ns: int | None) -> None:
        super().__init__(cause)
        self.read = read
        self.last_ns = last_ns


class Rows:
    """The rows of ``channels`` (storage connection ids) on an apsw or sqlite3 ``connection``,
    read once, in batches sized for windows of about ``payload_bytes``, at most ``most`` rows
    each."""

    def __init__(
        self, connection: Any, channels: Sequence[int], payload_bytes: int, most: int = MOST_BATCH
    ) -> None:
        self._connection = connection
        self._channels = tuple(channels)
        self._payload_bytes = payload_bytes
        self._most = most
        self.malformed = 0
        self.read = 0
        self.last_ns: int | None = None

    def batches(self) -> Iterator[Packed]:
        """The batches; a read error (a corrupt page) as a :class:`RowsError`."""
        cursor = self._fetch(lambda: self._connection.execute(
            QUERY.format(",".join("?" * len(self._channels))), self._channels))
        size = min(FIRST_BATCH, self._most)
        largest = 1
        while rows := self._fetch(functools.partial(_take, cursor, size)):
            packed = self._pack(rows)
            if packed is None:
                continue
            largest = max(largest, *packed.sizes)
            size = max(1, min(self._most, self._payload_bytes // BATCH_SHARE // largest))
            yield packed

    def _fetch(self, call: Callable[[], _T]) -> _T:
        try:
            return call()
        except Exception as err:  # apsw raises whatever sqlite hits in a damaged file
            raise RowsError(f"{type(err).__name__}: {err}", self.read, self.last_ns) from err

    def _pack(self, rows: list[Row]) -> Packed | None:
        """The rows packed, those whose timestamp is not an integer or whose data is not a blob
        left out (counted); None when none is left."""
        channels, stamps, payloads, sizes, row_ids = zip(*rows, strict=True)
        if None in sizes:
            kept = [row for row in rows if row[3] is not None]
            self.malformed += len(rows) - len(kept)
            if not kept:
                return None
            channels, stamps, payloads, sizes, row_ids = zip(*kept, strict=True)
        self.read += len(stamps)
        self.last_ns = stamps[-1]
        return Packed(array("q", channels), array("q", stamps), array("q", sizes),
                      array("q", row_ids), b"".join(filter(None, payloads)))


def _take(cursor: Iterator[Row], size: int) -> list[Row]:
    return list(itertools.islice(cursor, size))


class _Ahead:
    """Frames between the fetching thread and the writing one, at most :data:`AHEAD_BYTES` of
    payload held (and always at least one frame)."""

    def __init__(self) -> None:
        self._frames: deque[tuple[bytes, ...] | None] = deque()
        self._held = 0
        self._closed = False
        self._changed = threading.Condition()

    def put(self, frame: tuple[bytes, ...] | None) -> None:
        """Hand ``frame`` on (None: the last was); BrokenPipeError once the writer is gone."""
        size = 0 if frame is None else sum(map(len, frame))
        with self._changed:
            self._changed.wait_for(lambda: self._closed or not self._frames
                                   or self._held + size <= AHEAD_BYTES)
            if self._closed:
                raise BrokenPipeError
            self._frames.append(frame)
            self._held += size
            self._changed.notify_all()

    def take(self) -> tuple[bytes, ...] | None:
        with self._changed:
            self._changed.wait_for(lambda: bool(self._frames))
            frame = self._frames.popleft()
            self._held -= 0 if frame is None else sum(map(len, frame))
            self._changed.notify_all()
            return frame

    def close(self) -> None:
        with self._changed:
            self._closed = True
            self._changed.notify_all()


def frames(rows: Rows) -> Iterator[tuple[bytes, ...]]:
    """``rows`` as frames (:data:`FRAME`), the last an end or a failure."""
    try:
        for packed in rows.batches():
            yield (FRAME.pack(BATCH, len(packed), rows.malformed, _ns(rows.last_ns),
                              len(packed.payloads)),
                   *map(bytes, (packed.channels, packed.log_ns, packed.sizes, packed.row_ids)),
                   bytes(packed.payloads))
    except RowsError as err:
        yield failure(str(err), err.read, rows.malformed, err.last_ns)
        return
    yield (FRAME.pack(END, rows.read, rows.malformed, _ns(rows.last_ns), 0),)


def failure(cause: str, read: int, malformed: int, last_ns: int | None) -> tuple[bytes, ...]:
    """The frame saying that reading stopped, and why."""
    text = cause.encode()
    return FRAME.pack(FAILED, read, malformed, _ns(last_ns), len(text)), text


def _ns(last_ns: int | None) -> int:
    return -1 if last_ns is None else last_ns


def _write(ahead: _Ahead, out: IO[bytes]) -> None:
    try:
        while (frame := ahead.take()) is not None:
            for part in frame:
                out.write(part)
    except BrokenPipeError:  # the reader is gone (the host stopped): nothing to say
        ahead.close()


def main(argv: Sequence[str]) -> int:
    """The program: ``FILE PAYLOAD_BYTES ID...``, frames on standard output."""
    import apsw  # rosbags' sqlite binding: the same sqlite, the same errors

    path, payload_bytes, *ids = argv
    ahead = _Ahead()
    writer = threading.Thread(target=_write, args=(ahead, sys.stdout.buffer), daemon=True)
    writer.start()
    try:
        try:
            connection = apsw.Connection(path, flags=apsw.SQLITE_OPEN_READONLY)
        except apsw.Error as err:
            ahead.put(failure(f"{type(err).__name__}: {err}", 0, 0, None))
        else:
            for frame in frames(Rows(connection, [int(i) for i in ids], int(payload_bytes))):
                ahead.put(frame)
        ahead.put(None)
    except BrokenPipeError:
        return 0
    writer.join()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
