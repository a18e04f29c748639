"""The payloads of an indexed rosbag2 MCAP file in bulk: no Python call per record.

The one bulk reader of both sides: ``swanky-relay --bag`` replays with it
(:meth:`~robot_relay.sources.bag.BagSource.runs`: :meth:`McapFile.windows` unpaced,
:meth:`McapFile.records` paced), ``swanky-host --bag`` converts with it (host_bridge/inputs/bag.py).
It needs numpy, which the ``[bag]`` extra brings with rosbags, and decompresses chunks as rosbags
does (``backports.zstd`` / ``compression.zstd``, ``lz4``), so a robot with ``[relay,bag]`` has
all it needs; only opening an MCAP rosbag2 imports it.

rosbags' MCAP reader walks every record of every chunk with Python reads and copies each payload
out; on a 600 MB image bag that was over a third of the conversion. Here the file is
memory-mapped; the summary's chunk indexes and each chunk's MessageIndex records (fixed 16-byte
``(log_time, offset)`` entries, read with numpy) give every message's place up front; a chunk is
decompressed once when its first message is due, its record headers are read for all its
messages at once with numpy, and the payloads are slices: memoryviews for large ones (images,
clouds: no copy from the file or the decompressed chunk), bytes for small ones (so a message
kept for long does not pin its whole chunk).

The order is exactly rosbags' (``McapReader.messages``, which ``BagSource`` yields): by log time,
ties by the chunk's file offset, then by the record's place in its chunk; files of a split bag
one after the other. Messages outside their chunk's indexed time range are skipped as rosbags
skips them (said once). A file this reader does not take (no summary or chunk indexes, a chunk
without message indexes, an unknown compression, a chunk index that matches no chunk) raises
:class:`NotIndexedError` before anything is read, and the caller reads the bag with rosbags
through ``BagSource`` instead (which salvages a damaged summary from the data section).

A damaged chunk (a bad CRC, a decompression failure, a message index that is not one or whose
offsets disagree with the records, a message its index leaves out) is skipped and the other
chunks are read, as the relay's salvage reader does; after the file, one warning names it and
every chunk skipped, with what its index says it held. A chunk index whose offset was flipped
is repaired from its message indexes (they follow their chunk, which ends at the first of them).
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import mmap
import struct
import sys
import zlib
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
from numpy.lib.stride_tricks import as_strided

from robot_relay.wire import TopicInfo

log = logging.getLogger("swanky.relay")

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER = 0x01
OP_FOOTER = 0x02
OP_SCHEMA = 0x03
OP_CHANNEL = 0x04
OP_MESSAGE = 0x05
OP_CHUNK = 0x06
OP_MESSAGE_INDEX = 0x07
OP_CHUNK_INDEX = 0x08
OP_DATA_END = 0x0F
FOOTER_SIZE = 1 + 8 + 20 + len(MAGIC)
# A Message record: opcode, length, channel u16, sequence u32, log time u64, publish time u64.
MESSAGE_HEADER = 1 + 8 + 2 + 4 + 8 + 8
# Payloads from this size on are handed on as memoryviews of the chunk, smaller ones copied.
LARGE_PAYLOAD = 64 * 1024

U16 = struct.Struct("<H")
U32 = struct.Struct("<I")
U64 = struct.Struct("<Q")
RECORD = struct.Struct("<BQ")
_CHUNK_INDEX_HEAD = struct.Struct("<QQQQI")
CHUNK_HEAD = struct.Struct("<QQQI")
_INDEX_ENTRY = np.dtype([("log_time", "<u8"), ("offset", "<u8")])
Buffer = bytes | memoryview | mmap.mmap


class NotIndexedError(Exception):
    """The file is not one this reader takes (the message says why); rosbags reads it."""


class _DamagedChunkError(Exception):
    """A chunk whose records disagree with its index (the message says how): it is skipped."""


@dataclass(frozen=True, slots=True)
class Chunk:
    """One chunk as its ChunkIndex and Chunk record describe it."""

    file_offset: int
    start_ns: int
    end_ns: int
    records_offset: int
    compression: str
    compressed_size: int
    uncompressed_size: int
    crc: int
    message_indexes: tuple[tuple[int, int], ...]  # (channel id, offset of its MessageIndex)
    indexed_at: int  # where the chunk index says the chunk is: file_offset unless repaired
    buffer: Buffer
    """What ``records_offset`` is a place in: the file's map, or the Chunk record's content as a
    stream of the file gave it (:mod:`robot_relay.sources.mcap_stream`)."""
    index_buffer: Buffer
    """What the message indexes' offsets are places in: the file's map, or the MessageIndex
    records after the chunk in the stream."""


def string_at(buffer: Buffer, at: int) -> tuple[str, int]:
    """The MCAP string at ``at`` and where it ends."""
    (size,) = U32.unpack_from(buffer, at)
    return str(buffer[at + 4 : at + 4 + size], "utf-8"), at + 4 + size


def _chunk_record(
    buffer: Buffer, file_offset: int, compression: str, compressed_size: int
) -> tuple[int, int] | None:
    """(where its records start, its CRC) of the Chunk record at ``file_offset`` if there is one
    with this compression and compressed size, else None."""
    if not 0 <= file_offset < len(buffer):
        return None
    try:
        op, _ = RECORD.unpack_from(buffer, file_offset)
        _, _, _, crc = CHUNK_HEAD.unpack_from(buffer, file_offset + RECORD.size)
        stored, records_at = string_at(buffer, file_offset + RECORD.size + CHUNK_HEAD.size)
        (records_size,) = U64.unpack_from(buffer, records_at)
    except (struct.error, UnicodeDecodeError):
        return None
    if op != OP_CHUNK or stored != compression or records_size != compressed_size:
        return None
    return records_at + 8, crc


def _chunk(buffer: mmap.mmap, at: int) -> Chunk:
    """The ChunkIndex record's content at ``at``, checked against the Chunk record it names."""
    index_at = at
    start_ns, end_ns, indexed_at, length, map_size = _CHUNK_INDEX_HEAD.unpack_from(buffer, at)
    at += _CHUNK_INDEX_HEAD.size
    indexes = tuple(struct.iter_unpack("<HQ", buffer[at : at + map_size]))
    compression, at = string_at(buffer, at + map_size + 8)
    compressed_size, uncompressed_size = struct.unpack_from("<QQ", buffer, at)
    file_offset = indexed_at
    found = _chunk_record(buffer, file_offset, compression, compressed_size)
    if found is None and indexes:
        # A flipped chunk offset: the chunk's message indexes follow it (the MCAP spec), so the
        # chunk, ``length`` bytes long, ends where the first of them starts.
        file_offset = min(offset for _, offset in indexes) - length
        found = _chunk_record(buffer, file_offset, compression, compressed_size)
    if found is None:
        msg = f"the chunk index at byte {index_at} does not match the chunk at byte {indexed_at}"
        raise NotIndexedError(msg)
    records_offset, crc = found
    if records_offset + compressed_size > len(buffer):
        msg = f"the chunk at byte {file_offset} runs past the end of the file"
        raise NotIndexedError(msg)
    if compression not in DECOMPRESSORS:
        msg = f"chunk compression {compression!r} is not zstd, lz4 or none"
        raise NotIndexedError(msg)
    if not indexes and uncompressed_size:
        msg = f"the chunk at byte {file_offset} has no message index"
        raise NotIndexedError(msg)
    return Chunk(file_offset, start_ns, end_ns, records_offset, compression, compressed_size,
                 uncompressed_size, crc, tuple(sorted(indexes)), indexed_at, buffer, buffer)


def read_chunks(buffer: mmap.mmap) -> list[Chunk]:
    """Every chunk of the file, from its summary section."""
    if len(buffer) < 2 * len(MAGIC) + FOOTER_SIZE or buffer[: len(MAGIC)] != MAGIC:
        msg = "not an MCAP file"
        raise NotIndexedError(msg)
    footer = len(buffer) - FOOTER_SIZE
    op, _ = RECORD.unpack_from(buffer, footer)
    (summary_start,) = U64.unpack_from(buffer, footer + RECORD.size)
    if buffer[-len(MAGIC) :] != MAGIC or op != OP_FOOTER:
        msg = "the file has no MCAP footer (a recording cut short)"
        raise NotIndexedError(msg)
    if not summary_start:
        msg = "the file has no summary section"
        raise NotIndexedError(msg)
    chunks = []
    at = summary_start
    while at < footer:
        op, size = RECORD.unpack_from(buffer, at)
        at += RECORD.size
        if op == OP_CHUNK_INDEX:
            chunks.append(_chunk(buffer, at))
        at += size
    if not chunks:
        msg = "the summary has no chunk indexes"
        raise NotIndexedError(msg)
    return sorted(chunks, key=lambda chunk: (chunk.start_ns, chunk.file_offset))


def _zstd(data: memoryview, size: int) -> bytes:
    # rosbags' own zstd (its dependency), so a robot with only [relay,bag] reads these chunks.
    if sys.version_info >= (3, 14):
        from compression import zstd
    else:
        from backports import zstd

    # Bounded: a damaged frame header must not make it allocate more than the chunk says.
    decompressed: bytes = zstd.ZstdDecompressor().decompress(data, max_length=size)
    return decompressed


def _lz4(data: memoryview, size: int) -> bytes:
    import lz4.frame

    return lz4.frame.decompress(data)  # type: ignore[no-any-return]


DECOMPRESSORS: Mapping[str, Callable[[memoryview, int], bytes]] = {
    "zstd": _zstd, "lz4": _lz4, "": lambda data, size: bytes(data)
}


@dataclass(slots=True)
class _Loaded:
    """A chunk's records in memory: ``data`` (bytes, or for an uncompressed chunk the buffer it
    lies in: the file's map, or a view of the stream's), a memoryview of it, and where the
    records start in it."""

    data: Buffer
    view: memoryview
    base: int


def overlapping_groups(chunks: Sequence[Chunk]) -> Iterator[list[Chunk]]:
    """Chunks (sorted by start time) in groups whose time ranges overlap: every message of a
    later group is later than every message of an earlier one, so each group sorts alone."""
    group: list[Chunk] = []
    end_ns = -1
    for chunk in chunks:
        if group and chunk.start_ns > end_ns:
            yield group
            group = []
        group.append(chunk)
        end_ns = max(end_ns, chunk.end_ns)
    if group:
        yield group


@dataclass(frozen=True, slots=True)
class TopicRun:
    """One topic's messages of a window, in rosbags' order, with no object per message: message
    ``i`` is ``buffers[sources[i]][starts[i]:ends[i]]``, logged at ``log_ns[i]``."""

    info: TopicInfo
    buffers: tuple[bytes | memoryview, ...]
    sources: npt.NDArray[np.int64]
    starts: npt.NDArray[np.int64]
    ends: npt.NDArray[np.int64]
    log_ns: npt.NDArray[np.int64]

    def payloads(self) -> list[memoryview]:
        """Each message's payload, a memoryview of its buffer (valid as long as the run)."""
        views = [memoryview(buffer) for buffer in self.buffers]
        if len(views) == 1:
            view = views[0]
            return [view[start:end] for start, end in
                    zip(self.starts.tolist(), self.ends.tolist(), strict=True)]
        return [views[source][start:end] for source, start, end in
                zip(self.sources.tolist(), self.starts.tolist(), self.ends.tolist(), strict=True)]


class McapFile:
    """One indexed MCAP storage file of a rosbag2, opened; :meth:`messages` reads it."""

    def __init__(self, path: Path, channels: Mapping[int, TopicInfo]) -> None:
        self.path = path
        self.channels = channels
        with path.open("rb") as file:
            try:
                self._map = mmap.mmap(file.fileno(), 0, access=mmap.ACCESS_READ)
            except ValueError as err:  # an empty file
                raise NotIndexedError(str(err)) from err
        try:
            self.chunks = read_chunks(self._map)
        except (struct.error, UnicodeDecodeError) as err:
            self.close()
            msg = f"the summary does not parse: {err}"
            raise NotIndexedError(msg) from err
        except NotIndexedError:
            self.close()
            raise
        self._outside = 0
        # What the warning after the file says: chunk indexes repaired, chunks skipped.
        self._repaired = [
            f"the chunk index of the chunk at byte {chunk.file_offset} points at byte "
            f"{chunk.indexed_at}; the chunk was found before its message indexes"
            for chunk in self.chunks if chunk.indexed_at != chunk.file_offset
        ]
        self._skipped: list[str] = []

    def __enter__(self) -> McapFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Unmap the file, unless payloads handed on still view it (then it goes with them)."""
        with contextlib.suppress(BufferError):
            self._map.close()

    def _index(self, group: Sequence[Chunk]) -> tuple[npt.NDArray[np.int64], ...]:
        """(chunk number in ``group``, record offset, channel, log time) of the wanted messages
        of the chunks in ``group``, in rosbags' order."""
        parts: list[tuple[int, int, npt.NDArray[np.void]]] = []
        for number, chunk in enumerate(group):
            try:
                parts += [(number, channel, self._entries(chunk, channel, at))
                          for channel, at in chunk.message_indexes if channel in self.channels]
            except _DamagedChunkError as damage:
                self._skip(chunk, str(damage))
        if not parts:
            empty = np.zeros(0, np.int64)
            return empty, empty, empty, empty
        numbers = np.concatenate([np.full(len(e), n) for n, _, e in parts])
        channels = np.concatenate([np.full(len(e), c) for _, c, e in parts])
        entries = np.concatenate([e for _, _, e in parts])
        log_ns = entries["log_time"].astype(np.int64)
        offsets = entries["offset"].astype(np.int64)
        starts = np.array([c.start_ns for c in group], np.int64)[numbers]
        ends = np.array([c.end_ns for c in group], np.int64)[numbers]
        inside = (log_ns >= starts) & (log_ns <= ends)
        if not inside.all():
            self._outside += int((~inside).sum())
            numbers, channels, log_ns, offsets = (
                a[inside] for a in (numbers, channels, log_ns, offsets))
        file_offsets = np.array([c.file_offset for c in group], np.int64)[numbers]
        order = np.lexsort((offsets, file_offsets, log_ns))
        return numbers[order], offsets[order], channels[order], log_ns[order]

    @staticmethod
    def _entries(chunk: Chunk, channel: int, at: int) -> npt.NDArray[np.void]:
        """The entries of the chunk's MessageIndex record of ``channel`` at ``at``."""
        buffer = chunk.index_buffer
        try:
            op, _ = RECORD.unpack_from(buffer, at)
            (stored,) = U16.unpack_from(buffer, at + RECORD.size)
            (size,) = U32.unpack_from(buffer, at + RECORD.size + 2)
            if op != OP_MESSAGE_INDEX or stored != channel or size % _INDEX_ENTRY.itemsize:
                raise ValueError
            entries: npt.NDArray[np.void] = np.frombuffer(
                buffer, _INDEX_ENTRY, size // _INDEX_ENTRY.itemsize, at + RECORD.size + 6)
            return np.array(entries)  # a copy: the map may close
        except (struct.error, ValueError) as err:  # ValueError: it runs past the end of the file
            msg = f"its message index at byte {at} is not one"
            raise _DamagedChunkError(msg) from err

    def _chunk_groups(self) -> Iterator[list[Chunk]]:
        """The file's chunks in groups to sort alone (:func:`overlapping_groups`), in order."""
        return overlapping_groups(self.chunks)

    def _skip(self, chunk: Chunk, why: str) -> None:
        """Note a damaged chunk for the warning, with what its index says it held."""
        held: dict[str, int | None] = {}  # None: its index cannot be read
        for channel, at in chunk.message_indexes:
            if channel in self.channels:
                topic = self.channels[channel].topic
                try:
                    count = len(self._entries(chunk, channel, at))
                except _DamagedChunkError:
                    held[topic] = None
                    continue
                if topic not in held or held[topic] is not None:
                    held[topic] = (held.get(topic) or 0) + count
        what = ", ".join(f"{'?' if count is None else count} {topic}"
                         for topic, count in sorted(held.items()))
        self._skipped.append(f"the chunk at byte {chunk.file_offset} ({what or 'no'} messages "
                             f"per its index) is skipped: {why}")

    @staticmethod
    def _load(chunk: Chunk) -> _Loaded:
        records = memoryview(chunk.buffer)[
            chunk.records_offset : chunk.records_offset + chunk.compressed_size]
        if chunk.compression:
            try:
                data: Buffer = DECOMPRESSORS[chunk.compression](
                    records, chunk.uncompressed_size)
            except Exception as err:
                msg = f"{chunk.compression} does not decompress it ({err})"
                raise _DamagedChunkError(msg) from err
            base = 0
            if len(data) != chunk.uncompressed_size:
                msg = f"{len(data)} bytes decompressed, {chunk.uncompressed_size} expected"
                raise _DamagedChunkError(msg)
        else:
            data, base = chunk.buffer, chunk.records_offset
            if chunk.compressed_size != chunk.uncompressed_size:
                raise _DamagedChunkError("uncompressed sizes differ")
        view = memoryview(data)
        if chunk.crc and zlib.crc32(view[base : base + chunk.uncompressed_size]) != chunk.crc:
            raise _DamagedChunkError("its CRC does not match (corrupt)")
        return _Loaded(data, view, base)

    def _payloads(
        self, chunk: Chunk, loaded: _Loaded, offsets: npt.NDArray[np.int64],
        channels: npt.NDArray[np.int64], log_ns: npt.NDArray[np.int64],
    ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
        """Start and end of each payload in ``loaded.data``, from the record headers of the
        messages at ``offsets`` (all read at once), checked against the index."""
        size = chunk.uncompressed_size
        if len(offsets) and (offsets.min() < 0 or offsets.max() > size - MESSAGE_HEADER):
            raise _DamagedChunkError("a message offset is outside the chunk")
        records = np.frombuffer(loaded.data, np.uint8, size, loaded.base)
        words = _numbers_at(records, "<u8")
        lengths = words[offsets + 1].astype(np.int64)
        bad = (
            (records[offsets] != OP_MESSAGE)
            | (lengths < MESSAGE_HEADER - 9)
            | (offsets + 9 + lengths > size)
            | (_numbers_at(records, "<u2")[offsets + 9] != channels)
            | (words[offsets + 15].astype(np.int64) != log_ns)
        )
        del records, words
        if bad.any():
            at = int(offsets[np.argmax(bad)])
            raise _DamagedChunkError(f"no message of the indexed channel and time at {at}")
        starts = loaded.base + offsets + MESSAGE_HEADER
        return starts, loaded.base + offsets + 9 + lengths

    @staticmethod
    def _unindexed_messages(chunk: Chunk, loaded: _Loaded) -> None:
        """Raise if the chunk holds a message record its index leaves out (rosbags, walking the
        records, would read it)."""
        gap_records(chunk, loaded)

    def _ranges(self) -> Iterator[tuple[Mapping[int, _Loaded], list[npt.NDArray[np.int64]]]]:
        """The wanted channels' messages in rosbags' order, in ranges whose chunks are all
        loaded: (the loaded chunks by number, the range's columns: chunk number, payload start
        and end, channel, log time). The chunks change once the next range is asked for.
        Each pass (a looped replay reads the file again) ends with its own warnings."""
        self._outside, self._skipped = 0, []
        for group in self._chunk_groups():
            numbers, offsets, channels, log_ns = self._index(group)
            starts, ends = np.empty_like(offsets), np.empty_like(offsets)
            # Each chunk's messages in yielding order: it loads before its first, goes after its last.
            by_chunk = np.argsort(numbers, kind="stable")
            bounds = np.searchsorted(numbers[by_chunk], np.arange(len(group) + 1)).tolist()
            used = [n for n in range(len(group)) if bounds[n] < bounds[n + 1]]
            first = {n: int(by_chunk[bounds[n]]) for n in used}
            last = {n: int(by_chunk[bounds[n + 1] - 1]) for n in used}
            loaded: dict[int, _Loaded] = {}
            skipped: list[int] = []
            columns = (numbers, starts, ends, channels, log_ns)
            done = 0
            for position in [*sorted(first.values()), len(numbers)]:
                # Every message before ``position`` has its chunk loaded or skipped: hand them on.
                if done < position:
                    part = [c[done:position] for c in columns]
                    if skipped:
                        kept = ~np.isin(part[0], skipped)
                        part = [c[kept] for c in part]
                    if len(part[0]):
                        yield loaded, part
                for gone in [n for n in loaded if last[n] < position]:
                    del loaded[gone]
                done = position
                if position == len(numbers):
                    break
                number = int(numbers[position])
                where = by_chunk[bounds[number] : bounds[number + 1]]
                try:
                    chunk = self._load(group[number])
                    starts[where], ends[where] = self._checked(
                        group[number], chunk, offsets[where], channels[where], log_ns[where])
                except _DamagedChunkError as damage:
                    self._skip(group[number], str(damage))
                    skipped.append(number)
                else:
                    loaded[number] = chunk
        if self._outside:
            log.warning("%s: %d messages lie outside their chunk's indexed time range and are "
                        "skipped, as rosbags skips them", self.path, self._outside)
        if self._repaired or self._skipped:
            log.warning("bag %s is damaged (%sthe readable part was read); lost: %s", self.path,
                        "".join(f"{repair}; " for repair in self._repaired),
                        "; ".join(self._skipped) or "no message")

    def records(self, size: int) -> Iterator[list[tuple[TopicInfo, int, bytes | memoryview]]]:
        """The wanted channels' messages in rosbags' order as (topic, log time, payload), at
        most ``size`` a list (lists, not single messages: a generator step per message would
        cost more than everything else here)."""
        infos = self.channels
        for loaded, columns in self._ranges():
            for begin in range(0, len(columns[0]), size):
                numbers, starts, ends, channels, log_ns = (c[begin : begin + size] for c in columns)
                yield list(zip(map(infos.__getitem__, channels.tolist()), log_ns.tolist(),
                               _payloads(loaded, numbers, starts, ends), strict=True))

    def windows(self, messages: int, payload_bytes: int) -> Iterator[list[TopicRun]]:
        """The wanted channels' messages in windows of at most ``messages`` messages and
        ``payload_bytes`` bytes of payload (but at least one message), each window as one
        :class:`TopicRun` per topic: in each, a topic's messages keep rosbags' order, and the
        run holding the window's last message comes last. No record per message is made."""
        window = _Window(self.channels)
        for loaded, columns in self._ranges():
            sizes = columns[2] - columns[1]
            # Window bytes at the end of each message of the range if it all joined the window.
            reach = np.cumsum(sizes)
            at = 0
            while at < len(sizes):
                before = int(reach[at - 1]) if at else 0
                fits = int(np.searchsorted(reach, before + payload_bytes - window.payload_bytes,
                                           side="right")) - at
                take = min(messages - window.count, fits, len(sizes) - at)
                if take > 0 or not window.count:
                    take = max(take, 1)
                    window.add(loaded, [c[at : at + take] for c in columns],
                               int(reach[at + take - 1]) - before)
                    at += take
                if window.count >= messages or window.payload_bytes >= payload_bytes or take <= 0:
                    yield window.take()
        if window.count:
            yield window.take()

    def _checked(
        self, chunk: Chunk, loaded: _Loaded, offsets: npt.NDArray[np.int64],
        channels: npt.NDArray[np.int64], log_ns: npt.NDArray[np.int64],
    ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
        """:meth:`_payloads` of a chunk just loaded, which must hold no unindexed message."""
        try:
            payloads = self._payloads(chunk, loaded, offsets, channels, log_ns)
            self._unindexed_messages(chunk, loaded)
        except (IndexError, ValueError, struct.error) as err:
            raise _DamagedChunkError(f"{type(err).__name__}: {err}") from err
        return payloads


def _numbers_at(records: npt.NDArray[np.uint8], dtype: str) -> npt.NDArray[np.generic]:
    """``records`` seen as the ``dtype`` number starting at each of its bytes (overlapping,
    unaligned, no copy): fields at any offsets are then read with one gather, not a gather of
    every byte of every record header."""
    size = np.dtype(dtype).itemsize
    rows = max(len(records) - size + 1, 0)
    return as_strided(records, (rows, size), (1, 1), writeable=False).view(dtype)[:, 0]


def gap_records(chunk: Chunk, loaded: _Loaded) -> list[tuple[int, int, int]]:
    """The records of a loaded chunk between its indexed messages (a chunk's schemas and
    channels: rosbags' writer puts them there) as (opcode, where its content starts in
    ``loaded.data``, where it ends), walked in the gaps between the messages; a message record
    among them (its index leaves it out, and rosbags, walking the records, would read it) or
    records that overlap raise _DamagedChunkError."""
    indexes = chunk.index_buffer
    entries = [
        np.frombuffer(indexes, _INDEX_ENTRY, U32.unpack_from(indexes, at + 11)[0] // 16,
                      at + RECORD.size + 6)["offset"].astype(np.int64)
        for _, at in chunk.message_indexes
    ]
    offsets = np.sort(np.concatenate(entries)) if entries else np.zeros(0, np.int64)
    records = np.frombuffer(loaded.data, np.uint8, chunk.uncompressed_size, loaded.base)
    lengths = _numbers_at(records, "<u8")[offsets + 1]
    del records
    ends = offsets + 9 + lengths.astype(np.int64)
    gap_starts = np.concatenate(([0], ends))
    gap_ends = np.concatenate((offsets, [chunk.uncompressed_size]))
    overlapping = gap_starts > gap_ends
    if overlapping.any():
        raise _DamagedChunkError(f"records overlap at {int(gap_starts[np.argmax(overlapping)])}")
    found = []
    gaps = gap_starts < gap_ends  # most messages follow one another: nothing to walk
    for start, end in zip(gap_starts[gaps].tolist(), gap_ends[gaps].tolist(), strict=True):
        at = start
        while at < end:
            op, record_size = RECORD.unpack_from(loaded.data, loaded.base + at)
            if op == OP_MESSAGE:
                raise _DamagedChunkError(f"the message at {at} is not indexed")
            content = loaded.base + at + RECORD.size
            found.append((op, content, content + record_size))
            at += RECORD.size + record_size
        if at != end:
            raise _DamagedChunkError(f"records overlap at {at}")
    return found


def _payloads(
    loaded: Mapping[int, _Loaded], numbers: npt.NDArray[np.int64], starts: npt.NDArray[np.int64],
    ends: npt.NDArray[np.int64],
) -> list[bytes | memoryview]:
    """The payloads of messages of the ``loaded`` chunks ``numbers`` at ``starts:ends``:
    memoryviews of the chunk from LARGE_PAYLOAD on, copies below."""
    if len(numbers) and numbers[0] == numbers[-1] and (numbers == numbers[0]).all() and (
        ends - starts < LARGE_PAYLOAD
    ).all():  # the usual range: small messages of one chunk
        data = loaded[int(numbers[0])].data
        return [data[start:end] for start, end in zip(starts.tolist(), ends.tolist(), strict=True)]
    chunks = {number: (chunk.data, chunk.view) for number, chunk in loaded.items()}
    return [
        chunks[number][1][start:end] if end - start >= LARGE_PAYLOAD else chunks[number][0][start:end]
        for number, start, end in zip(numbers.tolist(), starts.tolist(), ends.tolist(), strict=True)
    ]


class _Window:
    """Messages gathered for :meth:`McapFile.windows`, in rosbags' order: their channels, log times
    and payloads as places in the window's buffers (no object per payload). A buffer is the
    file's map (an uncompressed chunk), a decompressed chunk most of which the window reads, else
    a copy of the bytes the window reads of it (so a run kept for long does not pin a large chunk
    for a few messages), and large payloads are memoryviews of their chunk; chunks may go once
    their range is added."""

    def __init__(self, channels: Mapping[int, TopicInfo]) -> None:
        self._infos = channels
        self._topic_of = topic_indexes(channels)
        self._buffers: list[bytes | memoryview] = []
        self._kept: dict[int, int] = {}  # id of a chunk's data or view -> its place in _buffers
        self._columns: list[tuple[npt.NDArray[np.int64], ...]] = []
        self.count = 0
        self.payload_bytes = 0

    def add(self, loaded: Mapping[int, _Loaded], columns: Sequence[npt.NDArray[np.int64]],
            payload_bytes: int) -> None:
        numbers, starts, ends, channels, log_ns = columns
        sources = np.empty(len(numbers), np.int64)
        at = starts.copy()
        large = ends - starts >= LARGE_PAYLOAD
        one_chunk = numbers[0] == numbers[-1] and (numbers == numbers[0]).all()
        for number in [int(numbers[0])] if one_chunk else np.unique(numbers).tolist():
            mine = np.ones(len(numbers), bool) if one_chunk else numbers == number
            chunk = loaded[number]
            if (small := mine & ~large).any():
                sources[small], at[small] = self._small(chunk, starts[small], ends[small])
            if (big := mine & large).any():
                sources[big] = self._keep(chunk.view)
        self._columns.append((sources, at, at + (ends - starts), channels, log_ns))
        self.count += len(numbers)
        self.payload_bytes += payload_bytes

    def _keep(self, buffer: bytes | memoryview) -> int:
        place = self._kept.get(id(buffer))
        if place is None:
            place = self._kept[id(buffer)] = len(self._buffers)
            self._buffers.append(buffer)
        return place

    def _small(self, chunk: _Loaded, starts: npt.NDArray[np.int64],
               ends: npt.NDArray[np.int64]) -> tuple[int, npt.NDArray[np.int64]]:
        """The buffer and places of the small payloads at ``starts:ends`` of ``chunk``: the
        file's map for an uncompressed chunk, the decompressed chunk itself when they lie in most
        of it, else a copy of the bytes they lie in when they fill most of those (small messages
        one after another), else of each."""
        if not isinstance(chunk.data, bytes):  # the file's map: viewed, never copied
            return self._keep(chunk.view), starts
        low, high = int(starts.min()), int(ends.max())
        if 2 * (high - low) >= len(chunk.data):
            return self._keep(chunk.data), starts
        sizes = ends - starts
        if 2 * int(sizes.sum()) >= high - low:
            return self._keep(chunk.data[low:high]), starts - low
        copied = b"".join([chunk.data[start:end] for start, end in
                           zip(starts.tolist(), ends.tolist(), strict=True)])
        return self._keep(copied), np.cumsum(sizes) - sizes

    def take(self) -> list[TopicRun]:
        """The window as :func:`topic_runs`, and empties it."""
        sources, starts, ends, channels, log_ns = (
            np.concatenate(column) for column in zip(*self._columns, strict=True))
        runs = topic_runs(self._infos, self._topic_of, tuple(self._buffers),
                          (sources, starts, ends, channels, log_ns))
        self._buffers, self._kept, self._columns = [], {}, []
        self.count = self.payload_bytes = 0
        return runs


def topic_indexes(channels: Mapping[int, TopicInfo]) -> dict[int, int]:
    """Channel id -> the index of its topic: one topic's channels make one run."""
    topics = sorted({info.topic for info in channels.values()})
    return {channel: topics.index(info.topic) for channel, info in channels.items()}


def topic_runs(
    infos: Mapping[int, TopicInfo], topic_of: Mapping[int, int],
    buffers: tuple[bytes | memoryview, ...], columns: Sequence[npt.NDArray[np.int64]],
) -> list[TopicRun]:
    """A window's messages, in order (``columns``: each message's buffer, start and end in it,
    channel and log time), as runs: one per stretch of a topic's messages with one channel (a
    topic recorded on two channels alternates runs when its messages do), each in the window's
    order, the run holding the window's last message last."""
    sources, starts, ends, channels, log_ns = columns
    topics = np.array([topic_of[c] for c in np.unique(channels).tolist()])
    keys = topics[np.searchsorted(np.unique(channels), channels)]
    order = np.argsort(keys, kind="stable")
    ordered_keys, ordered_channels = keys[order], channels[order]
    cuts = np.flatnonzero((ordered_keys[1:] != ordered_keys[:-1])
                          | (ordered_channels[1:] != ordered_channels[:-1])) + 1
    bounds = [0, *cuts.tolist(), len(order)]
    runs = []
    for begin, end in itertools.pairwise(bounds):
        rows = order[begin:end]
        info = infos[int(ordered_channels[begin])]
        runs.append((int(rows[-1]), TopicRun(
            info, buffers, sources[rows], starts[rows], ends[rows], log_ns[rows])))
    return [run for _, run in sorted(runs, key=lambda pair: pair[0])]
