"""A rosbag2 recorded with ``--compression-mode file`` (its MCAP file zstd'ed whole, xxx.mcap.zstd)
read while it is decompressed, by the bulk reader of :mod:`robot_relay.sources.mcap`.

rosbags decompresses such a file whole into a temporary directory when it opens the bag, before
the first message. Here a thread decompresses it record by record with ``zstandard`` (which
releases the GIL; half the CPU of rosbags' ``backports.zstd`` on the 600 MB image file of
``benchmarks/bag_conversion.py``), ahead of the reader: each Chunk record, decompressed into a
buffer of its own (exactly its size: no copy, and freed memory is reused), becomes with the
MessageIndex records after it a :class:`~robot_relay.sources.mcap.Chunk` of the bulk reader, and
Schema and Channel records (in the data section, or inside chunks, where rosbags' writer and
``ros2 bag record`` put them) become rosbags connections, as rosbags' MCAP reader makes them. The
summary, at the end, is not waited for.

The order is rosbags' (log time, then the chunk's place in the file, then the record's in its
chunk): the bulk reader sorts each group of chunks whose time ranges overlap. Without the
summary's chunk indexes, chunks are held until HOLD_BYTES of later chunks have come; a group that
ends before the first of those starts is then taken as complete and handed on (a message written
up to HOLD_BYTES of recording after later ones still finds its place). A chunk that starts before
messages already handed on (the recording's clock went back: a simulated clock restarted)
cannot be put back among them: its messages come after them, and a warning after the file names
it (rosbags, which reads the summary first, would interleave them).

Opening (:class:`StreamedMcap`, the storage of :class:`~robot_relay.sources.rosbag2.Rosbag2Reader`
for such a bag) reads ahead until every topic of metadata.yaml has its channel (the connections
come before the first message), READ_AHEAD bytes at most, and keeps what it read for the first
pass; a file it does not take (not an MCAP of the ros2 profile, a chunk without message indexes
or a message outside chunks before every channel is known, channels found too late) raises
:class:`NotStreamableError` and rosbags opens the bag as before. :meth:`StreamedMcap.messages`
(BagSource's reference path) is rosbags' own, on the file decompressed into a temporary
directory on first use.

A damaged stream ends the file: the chunks read before the damage are handed on (a truncated
file: every chunk before the cut; corrupt zstd data: every chunk before the record it is in, as
far as zstd finds the damage there), and a warning names the file, the byte of the
decompressed file where it stopped and that the rest is lost.
"""

from __future__ import annotations

import logging
import shutil
import threading
from collections import deque
from collections.abc import Collection, Generator, Iterator, Mapping
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any, BinaryIO

import zstandard
from rosbags.interfaces import Connection, ConnectionExtRosbag2
from rosbags.rosbag2.metadata import ReaderMetadata
from rosbags.rosbag2.storage_mcap import Schema, get_msgdef, get_qos

from robot_relay.sources.mcap import (
    CHUNK_HEAD,
    DECOMPRESSORS,
    MAGIC,
    OP_CHANNEL,
    OP_CHUNK,
    OP_DATA_END,
    OP_FOOTER,
    OP_HEADER,
    OP_MESSAGE,
    OP_MESSAGE_INDEX,
    OP_SCHEMA,
    RECORD,
    U16,
    U32,
    U64,
    Buffer,
    Chunk,
    McapFile,
    gap_records,
    overlapping_groups,
    string_at,
)
from robot_relay.wire import TopicInfo

log = logging.getLogger("swanky.relay")

COMPRESSED_READ = 1024 * 1024
"""Compressed bytes read from the file a step."""
AHEAD = 64 * 1024 * 1024
"""Bytes of the decompressed file the thread frames ahead of the reader, at most."""
HOLD_BYTES = 16 * 1024 * 1024
"""Chunks held back (of the decompressed file) before a group of chunks is complete."""
LARGEST_RECORD = 4 * 1024**3
"""A record longer than this is damage, not a record (it is not read into memory)."""
READ_AHEAD = 64 * 1024 * 1024
"""Decompressed bytes opening reads, at most, to find every topic's channel."""


class NotStreamableError(Exception):
    """The file is not one this reader takes (the message says why): rosbags opens the bag."""


class _StreamDamageError(Exception):
    """The decompressed file ends early or does not decompress (the message says where)."""


@dataclass(frozen=True, slots=True)
class _Item:
    """What the thread found next: channels first seen (before or inside ``chunk``), and a chunk
    (None for channels outside chunks) with why it cannot be read ('' if it can)."""

    connections: tuple[Connection, ...]
    chunk: Chunk | None
    unreadable: str
    size: int


@dataclass(frozen=True, slots=True)
class _End:
    """The end of a pass: ``damage`` says why the file ended early, '' if it ended well."""

    damage: str
    header_read: bool


class _Decompressed:
    """The decompressed file read record by record: each read exactly the bytes asked (one
    buffer a chunk, no copy), ``offset`` the place in the decompressed file."""

    def __init__(self, file: BinaryIO) -> None:
        self._reader = zstandard.ZstdDecompressor().stream_reader(
            file, read_size=COMPRESSED_READ, read_across_frames=True)
        self.offset = 0

    def read(self, size: int) -> bytes:
        """The next ``size`` bytes; a file that ends before them is truncated."""
        try:
            data: bytes = self._reader.read(size)
        except zstandard.ZstdError as err:
            msg = f"the zstd stream does not decompress ({err})"
            raise _StreamDamageError(msg) from err
        if len(data) < size:
            msg = ("the file ends before its data end record (it is truncated)" if not data
                   and size == RECORD.size else "the file ends inside a record (it is truncated)")
            raise _StreamDamageError(msg)
        self.offset += size
        return data

    def record(self) -> tuple[int, int]:
        """The next record's opcode and length (its content follows)."""
        op, length = RECORD.unpack(self.read(RECORD.size))
        if length > LARGEST_RECORD:  # damage zstd did not see: the length is not one
            msg = f"a record of {length} bytes (the file is damaged)"
            raise _StreamDamageError(msg)
        return int(op), int(length)


class _Framer:
    """On the pass's thread: the decompressed file's records framed into :class:`_Item`\\ s."""

    def __init__(self, path: Path, owner: StreamedMcap) -> None:
        self._path = path
        self._owner = owner
        self._schemas: dict[int, Schema] = {}
        self._channels: set[int] = set()
        self._decompressed: _Decompressed | None = None
        self.header_read = False

    @property
    def offset(self) -> int:
        """How far the file was read: where the next record starts (or inside the one under
        way)."""
        return self._decompressed.offset if self._decompressed is not None else 0

    def items(self) -> Iterator[_Item]:
        with self._path.open("rb") as file:
            self._decompressed = stream = _Decompressed(file)
            if stream.read(len(MAGIC)) != MAGIC:
                msg = "not an MCAP file"
                raise _StreamDamageError(msg)
            op, length = stream.record()
            if op != OP_HEADER or string_at(stream.read(length), 0)[0] != "ros2":
                msg = "not an MCAP file of the ros2 profile"
                raise _StreamDamageError(msg)
            self.header_read = True
            yield from self._records(stream)

    def _records(self, stream: _Decompressed) -> Iterator[_Item]:
        found: list[Connection] = []
        following: tuple[int, int] | None = None  # a record read after a chunk's indexes
        while True:
            at = stream.offset - (RECORD.size if following else 0)
            op, length = following or stream.record()
            following = None
            if op == OP_CHUNK:
                content = stream.read(length)
                indexes = []
                while True:  # its message indexes follow it
                    following = stream.record()
                    if following[0] != OP_MESSAGE_INDEX:
                        break
                    indexes.append(RECORD.pack(*following) + stream.read(following[1]))
                chunk, unreadable = _chunk(content, b"".join(indexes), at)
                if not unreadable:
                    found += self._inside(chunk)
                yield _Item(tuple(found), chunk, unreadable, len(content))
                found = []
            elif op == OP_MESSAGE:  # outside chunks: the bulk reader finds no index of it
                stream.read(length)
                yield _Item(tuple(found), None, f"a message outside chunks at byte {at}", length)
                found = []
            elif op in (OP_SCHEMA, OP_CHANNEL):
                self._record(op, stream.read(length), found)
            elif op in (OP_DATA_END, OP_FOOTER):
                if found:
                    yield _Item(tuple(found), None, "", 0)
                return
            else:
                stream.read(length)

    def _inside(self, chunk: Chunk) -> list[Connection]:
        """The channels a chunk's records hold (those of a damaged chunk: none; the reader skips it)."""
        found: list[Connection] = []
        try:
            loaded = McapFile._load(chunk)
            for op, start, end in gap_records(chunk, loaded):
                if op in (OP_SCHEMA, OP_CHANNEL):
                    self._record(op, loaded.data[start:end], found)
        except Exception:  # the reader, loading the chunk, skips it and names the damage
            return []
        return found

    def _record(self, op: int, content: Buffer, found: list[Connection]) -> None:
        """A Schema or Channel record's content: a channel not seen before is a connection, as
        rosbags' MCAP reader makes it."""
        (key,) = U16.unpack_from(content, 0)
        if op == OP_SCHEMA:
            name, at = string_at(content, 2)
            encoding, at = string_at(content, at)
            (size,) = U32.unpack_from(content, at)
            data = str(content[at + 4 : at + 4 + size], "utf-8")
            self._schemas[key] = Schema(key, name, encoding, data)
            return
        if key in self._channels:
            return
        (schema_id,) = U16.unpack_from(content, 2)
        topic, at = string_at(content, 4)
        encoding, at = string_at(content, at)
        (size,) = U32.unpack_from(content, at)
        metadata = bytes(content[at + 4 : at + 4 + size])
        schema = self._schemas.get(schema_id)
        self._channels.add(key)
        found.append(Connection(
            key, topic, schema.name if schema else "__schemaless__", get_msgdef(schema), "", 0,
            ConnectionExtRosbag2(encoding, get_qos(metadata)), self._owner,
        ))


def _chunk(content: bytes, indexes: bytes, file_offset: int) -> tuple[Chunk, str]:
    """The Chunk record of ``content`` with the MessageIndex records after it (``indexes``),
    and why the bulk reader cannot read it ('' if it can)."""
    start_ns, end_ns, uncompressed_size, crc = CHUNK_HEAD.unpack_from(content, 0)
    compression, at = string_at(content, CHUNK_HEAD.size)
    (compressed_size,) = U64.unpack_from(content, at)
    records_offset = at + 8
    message_indexes = []
    at = 0
    while at < len(indexes):
        (index_length,) = U64.unpack_from(indexes, at + 1)
        (channel,) = U16.unpack_from(indexes, at + RECORD.size)
        message_indexes.append((channel, at))
        at += RECORD.size + index_length
    unreadable = ""
    if compression not in DECOMPRESSORS:
        unreadable = f"chunk compression {compression!r} is not zstd, lz4 or none"
    elif records_offset + compressed_size > len(content):
        unreadable = "its records run past its end"
    elif not message_indexes and uncompressed_size:
        unreadable = "no message index follows it"
    chunk = Chunk(file_offset, start_ns, end_ns, records_offset, compression, compressed_size,
                  uncompressed_size, crc, tuple(sorted(message_indexes)), file_offset, content,
                  indexes)
    return chunk, unreadable


class _Pass:
    """One reading of the file: a thread decompressing and framing it, at most AHEAD bytes of
    chunks ahead of the reader (the first pass starts at open: swanky-host opens the bag while
    it imports the app, host_bridge/inputs/bag_opener.py). More ahead gains little (the thread
    decompresses faster than the host converts) and costs memory the process must fault in
    afresh (the 600 MB file: 128k page faults with 32 MiB ahead, 151k with 256 MiB)."""

    def __init__(self, path: Path, owner: StreamedMcap) -> None:
        self._framer = _Framer(path, owner)
        self._found: deque[_Item | _End] = deque()
        self._ahead = 0  # bytes of the items found and not taken
        self._changed = threading.Condition()
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name="bag-unzstd", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        damage = ""
        try:
            for item in self._framer.items():
                if not self._put(item):
                    return
        except _StreamDamageError as err:
            damage = f"{err}, at byte {self._framer.offset} of the decompressed file"
        except Exception as err:  # a record that does not parse: the file ends there
            damage = (f"the record at byte {self._framer.offset} of the decompressed file does "
                      f"not parse ({type(err).__name__}: {err})")
        self._put(_End(damage, self._framer.header_read))

    def _put(self, item: _Item | _End) -> bool:
        """Hand ``item`` on once there is room (False: the pass was stopped)."""
        size = item.size if isinstance(item, _Item) else 0
        with self._changed:
            self._changed.wait_for(lambda: self._stopping or self._ahead + size <= AHEAD
                                   or not self._found)
            if self._stopping:
                return False
            self._found.append(item)
            self._ahead += size
            self._changed.notify_all()
        return True

    def items(self) -> Iterator[_Item | _End]:
        """What the thread found, in file order, to the pass's :class:`_End`."""
        while True:
            with self._changed:
                self._changed.wait_for(lambda: self._found)
                item = self._found.popleft()
                self._ahead -= item.size if isinstance(item, _Item) else 0
                self._changed.notify_all()
            yield item
            if isinstance(item, _End):
                return

    def stop(self) -> None:
        """End the thread (what it read ahead is dropped) and the reading of :meth:`items`,
        which may be waiting on another thread."""
        with self._changed:
            self._stopping = True
            self._changed.notify_all()
        self._thread.join()
        with self._changed:
            self._found.clear()
            self._ahead = 0
            self._found.append(_End("", header_read=True))
            self._changed.notify_all()


class StreamedMcap:
    """The one .mcap.zstd file of a rosbag2 recorded with ``--compression-mode file``, as the
    storage of rosbags' DirectoryReader: ``path``, ``connections`` (the file's channels, found
    by :meth:`open`), ``messages`` (rosbags' own reading); :class:`StreamedMcapFile` reads it in
    bulk, pass after pass."""

    def __init__(self, path: Path, topics: Collection[str]) -> None:
        self.path = path
        self.connections: list[Connection] = []
        # The file's own counts and times are in its summary, not read: the bag's are
        # metadata.yaml's (rosbags' DirectoryReader reports those).
        self.metadata = ReaderMetadata(0, 2**63 - 1, 0, 0, None, None, None, None)
        self._topics = set(topics)
        self._ahead: list[_Item | _End] = []
        self._pass: _Pass | None = None
        self._reference: Any = None  # rosbags' McapReader of the decompressed copy
        self._stack = ExitStack()

    def open(self) -> None:
        """Start the first pass and read ahead until every topic has its channel (NotStreamableError
        when the file is not one to stream)."""
        self._pass = _Pass(self.path, self)
        read = 0
        missing = set(self._topics)
        for item in self._pass.items():
            self._ahead.append(item)
            if isinstance(item, _End):
                if not item.header_read:
                    self.close()
                    raise NotStreamableError(item.damage)
                break
            if item.unreadable:
                self.close()
                where = f"the chunk at byte {item.chunk.file_offset}: " if item.chunk else ""
                raise NotStreamableError(f"{where}{item.unreadable}")
            self.connections += item.connections
            missing -= {connection.topic for connection in item.connections}
            read += item.size
            if not missing:
                break
            if read > READ_AHEAD:
                self.close()
                msg = f"no channel of {', '.join(sorted(missing))} in its first {read} bytes"
                raise NotStreamableError(msg)

    def read(self) -> Iterator[_Item | _End]:
        """A pass over the file (the first continues what :meth:`open` read ahead)."""
        if self._pass is None:
            self._pass = _Pass(self.path, self)
        ahead, self._ahead = self._ahead, []
        current = self._pass
        try:
            yield from ahead
            if not any(isinstance(item, _End) for item in ahead):
                yield from current.items()
        finally:
            current.stop()
            if self._pass is current:
                self._pass = None

    def messages(
        self, connections: Collection[Connection], start: int | None = None, stop: int | None = None
    ) -> Generator[tuple[Connection, int, bytes], None, None]:
        """rosbags' reading of the file: decompressed whole on first use into a temporary
        directory, as rosbags' DirectoryReader does at open, and read by rosbags' MCAP reader
        (the same channel ids)."""
        if self._reference is None:
            from rosbags.rosbag2.storage_mcap import McapReader

            directory = self._stack.enter_context(TemporaryDirectory())
            copy = Path(directory, self.path.stem)
            with (self.path.open("rb") as bio,
                  zstandard.ZstdDecompressor().stream_reader(bio, read_across_frames=True) as infile,
                  copy.open("wb") as out):
                shutil.copyfileobj(infile, out)
            reader = McapReader(copy)
            reader.open()
            self._stack.callback(reader.close)
            self._reference = reader
        yield from self._reference.messages(connections, start, stop)

    def stop_pass(self) -> None:
        """End the pass under way, if any."""
        if self._pass is not None:
            self._pass.stop()
            self._pass = None
        self._ahead = []

    def close(self) -> None:
        self.stop_pass()
        self._stack.close()


class StreamedMcapFile(McapFile):
    """:class:`~robot_relay.sources.mcap.McapFile` of a :class:`StreamedMcap`: the chunks come
    from a pass over the decompressing file, in groups handed on as they are complete."""

    def __init__(self, storage: StreamedMcap, channels: Mapping[int, TopicInfo]) -> None:
        self.path = storage.path
        self.channels = channels
        self.chunks: list[Chunk] = []
        self._storage = storage
        self._known = {connection.id for connection in storage.connections}
        self._outside = 0
        self._repaired: list[str] = []
        self._skipped: list[str] = []

    def close(self) -> None:
        self._storage.stop_pass()

    def _chunk_groups(self) -> Iterator[list[Chunk]]:
        held: list[Chunk] = []  # not handed on yet
        held_bytes = 0
        check_at = 2 * HOLD_BYTES
        newest: deque[Chunk] = deque()  # the newest chunks, HOLD_BYTES of them
        newest_bytes = 0
        handed_end = -1
        late: list[str] = []
        unknown: list[str] = []
        outside = 0  # messages outside chunks: no index finds them
        for item in self._storage.read():
            if isinstance(item, _End):
                if item.damage:
                    self._skipped.append(f"{item.damage}: the rest of the file is lost")
                break
            unknown += [f"{c.topic} (channel {c.id})" for c in item.connections
                        if c.id not in self._known]
            chunk = item.chunk
            if item.unreadable:
                if chunk is None:
                    outside += 1
                else:
                    self._skip(chunk, item.unreadable)
                continue
            if chunk is None or not chunk.message_indexes:
                continue
            if chunk.start_ns <= handed_end:
                late.append(f"the chunk at byte {chunk.file_offset} starts at {chunk.start_ns} ns")
            held.append(chunk)
            held_bytes += item.size
            newest.append(chunk)
            newest_bytes += item.size
            while newest_bytes - len(newest[0].buffer) >= HOLD_BYTES:
                newest_bytes -= len(newest.popleft().buffer)
            if held_bytes < check_at:
                continue
            # Every group of the held chunks that ends before the newest HOLD_BYTES of chunks
            # start is complete (the module docstring): hand it on.
            watermark = min(newest_chunk.start_ns for newest_chunk in newest)
            groups = list(overlapping_groups(_in_order(held)))
            for done, group in enumerate(groups):
                group_end = max(c.end_ns for c in group)
                if group_end >= watermark:
                    held = [c for kept in groups[done:] for c in kept]
                    break
                yield group
                handed_end = max(handed_end, group_end)
            else:
                held = []
            held_bytes = sum(len(c.buffer) for c in held)
            check_at = held_bytes + HOLD_BYTES
        yield from overlapping_groups(_in_order(held))
        if outside:
            self._skipped.append(f"{outside} messages outside chunks")
        if late:
            log.warning("%s: chunks start before messages already read (%s): their messages are "
                        "read after those, not in log-time order", self.path, "; ".join(late))
        if unknown:
            log.warning("%s: channels first found after the bag was opened, not read: %s",
                        self.path, ", ".join(unknown))


def _in_order(chunks: list[Chunk]) -> list[Chunk]:
    return sorted(chunks, key=lambda chunk: (chunk.start_ns, chunk.file_offset))

