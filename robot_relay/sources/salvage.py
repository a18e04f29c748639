"""What a damaged MCAP file still holds, read record by record from its start.

A recording killed mid-write (power cut, a full disk, ``kill -9``) leaves an MCAP without its
summary and footer, usually cut inside a chunk; a bad sector or a bad copy flips bytes in a chunk
or an index. rosbags refuses such a file whole. MCAP is a plain sequence of records, so
everything before the damage (and every intact chunk after a corrupt one) can still be read
without the summary: schemas, channels and messages in file order. What is lost is collected as
:class:`Damage` so the bag source names it once.

rosbags' own readers are used for intact files; this runs only when they refuse one. Needs
rosbags' dependencies (lz4, zstandard) for compressed chunks, like the rest of the bag source.
"""

from __future__ import annotations

import mmap
import struct
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

MAGIC = b"\x89MCAP0\r\n"
_OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK, _OP_DATA_END = 0x03, 0x04, 0x05, 0x06, 0x0F
_RECORD = struct.Struct("<BQ")
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_MESSAGE = struct.Struct("<HIQQ")
_CHUNK = struct.Struct("<QQQI")


class _TruncatedError(Exception):
    """A record reaches past the end of what holds it."""


@dataclass(slots=True)
class Damage:
    """Where a file is damaged and what that cost: chunks skipped, and where reading stopped."""

    skipped: list[str] = field(default_factory=list)
    stopped: str | None = None

    def __bool__(self) -> bool:
        return bool(self.skipped) or self.stopped is not None

    def describe(self) -> str:
        parts = list(self.skipped)
        if self.stopped is not None:
            parts.append(self.stopped)
        return "; ".join(parts)


@dataclass(frozen=True, slots=True)
class Schema:
    name: str
    encoding: str
    data: bytes


@dataclass(frozen=True, slots=True)
class Channel:
    id: int
    schema: Schema | None
    topic: str
    metadata: dict[str, str]


class _Reader:
    """Little-endian fields of one record's content."""

    def __init__(self, data: memoryview) -> None:
        self.data = data
        self.at = 0

    def take(self, size: int) -> memoryview:
        if self.at + size > len(self.data):
            raise _TruncatedError
        part = self.data[self.at : self.at + size]
        self.at += size
        return part

    def unpack(self, fmt: struct.Struct) -> tuple[Any, ...]:
        return fmt.unpack(self.take(fmt.size))

    def string(self) -> str:
        (size,) = self.unpack(_U32)
        return bytes(self.take(size)).decode("utf-8", errors="replace")


def _decompressor(compression: str) -> Callable[[bytes, int], bytes]:
    if compression == "":
        return lambda data, _size: data
    if compression == "zstd":
        import zstandard

        return lambda data, size: zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    if compression == "lz4":
        import lz4.frame

        return lambda data, _size: bytes(lz4.frame.decompress(data))
    msg = f"compression {compression!r} is not one MCAP defines"
    raise ValueError(msg)


class McapSalvage:
    """The records of an MCAP file in file order, read past damage where the format allows.

    ``channels`` are those seen so far (all of them after :meth:`scan`); :meth:`messages` yields
    ``(channel id, log time, payload)``; ``damage`` says what was lost.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.damage = Damage()

    def scan(self) -> tuple[int, int, int]:
        """Read the whole file once: its channels, and (messages, first, last log time)."""
        count, first, last = 0, None, None
        for _, log_ns, _ in self.messages():
            count += 1
            first = log_ns if first is None else min(first, log_ns)
            last = log_ns if last is None else max(last, log_ns)
        return count, first or 0, last or 0

    def messages(self) -> Iterator[tuple[int, int, bytes]]:
        self.damage = Damage()
        with self.path.open("rb") as file:
            size = self.path.stat().st_size
            if size < len(MAGIC) or file.read(len(MAGIC)) != MAGIC:
                self.damage.stopped = "it does not start with the MCAP magic: nothing was read"
                return
            with mmap.mmap(file.fileno(), 0, access=mmap.ACCESS_READ) as mapped:
                yield from self._records(memoryview(mapped)[len(MAGIC) :], len(MAGIC), None)

    def _records(
        self, data: memoryview, base: int, chunk: int | None
    ) -> Iterator[tuple[int, int, bytes]]:
        """Records of ``data`` (the file after its magic, or one chunk's records); ``base`` is
        where it starts in the file, ``chunk`` the file offset of the chunk it is."""
        at = 0
        while at < len(data):
            if at + _RECORD.size > len(data):
                self._stopped(base + at, chunk, "a record header")
                return
            opcode, length = _RECORD.unpack_from(data, at)
            start = at + _RECORD.size
            if start + length > len(data):
                self._stopped(base + at, chunk, f"a record of {length} bytes")
                return
            content = data[start : start + length]
            at = start + length
            try:
                if opcode == _OP_MESSAGE:
                    channel, _, log_ns, _ = _MESSAGE.unpack_from(content)
                    if channel in self.channels:
                        # A copy: a view would keep the file's mapping from closing.
                        yield channel, log_ns, bytes(content[_MESSAGE.size :])
                elif opcode == _OP_CHUNK:
                    yield from self._chunk(content, base + start - _RECORD.size)
                elif opcode == _OP_SCHEMA:
                    self._schema(_Reader(content))
                elif opcode == _OP_CHANNEL:
                    self._channel(_Reader(content))
                elif opcode == _OP_DATA_END:
                    return
            except (_TruncatedError, struct.error, UnicodeDecodeError) as err:
                what = "a chunk's record" if chunk is not None else "a record"
                self.damage.skipped.append(
                    f"{what} (opcode {opcode:#04x}) at byte {base + start - _RECORD.size} is "
                    f"malformed ({type(err).__name__}), skipped"
                )

    def _stopped(self, offset: int, chunk: int | None, what: str) -> None:
        if chunk is None:
            self.damage.stopped = (
                f"the file ends inside {what} at byte {offset} (cut short): nothing after it"
            )
        else:
            self.damage.skipped.append(
                f"the chunk at byte {chunk} ends inside {what} at byte {offset}; the rest of "
                "that chunk is lost"
            )

    def _chunk(self, content: memoryview, offset: int) -> Iterator[tuple[int, int, bytes]]:
        reader = _Reader(content)
        _, _, size, crc = reader.unpack(_CHUNK)
        compression = reader.string()
        (compressed,) = reader.unpack(struct.Struct("<Q"))
        body = reader.take(compressed)
        try:
            records = _decompressor(compression)(bytes(body), size)
        except Exception as err:
            # zstandard, lz4 and our own ValueError: whatever the codec says of corrupt data.
            self.damage.skipped.append(
                f"the chunk at byte {offset} does not decompress ({compression}: {err}), skipped"
            )
            return
        if len(records) != size or (crc and zlib.crc32(records) != crc):
            self.damage.skipped.append(
                f"the chunk at byte {offset} fails its checksum (corrupt), skipped"
            )
            return
        yield from self._records(memoryview(records), offset, offset)

    def _schema(self, reader: _Reader) -> None:
        (schema_id,) = reader.unpack(_U16)
        name, encoding = reader.string(), reader.string()
        (size,) = reader.unpack(_U32)
        self.schemas[schema_id] = Schema(name, encoding, bytes(reader.take(size)))

    def _channel(self, reader: _Reader) -> None:
        channel_id, schema_id = reader.unpack(struct.Struct("<HH"))
        topic, _encoding = reader.string(), reader.string()
        (size,) = reader.unpack(_U32)
        pairs = _Reader(reader.take(size))
        metadata = {}
        while pairs.at < len(pairs.data):
            key = pairs.string()
            metadata[key] = pairs.string()
        if channel_id not in self.channels:
            self.channels[channel_id] = Channel(
                channel_id, self.schemas.get(schema_id), topic, metadata
            )
