"""What a damaged MCAP file or ROS 1 bag still holds, read record by record from its start.

A recording killed mid-write (power cut, a full disk, ``kill -9``) leaves an MCAP without its
summary and footer, or a ROS 1 bag without the index and connection records ``rosbag`` writes at
the end, usually cut inside a chunk; a bad sector or a bad copy flips bytes in a chunk or an
index. rosbags refuses such a file whole: it reads a ROS 1 bag from its index alone. Both formats
are plain sequences of records, so everything before the damage (and every intact chunk after a
corrupt one) can still be read without the summary or index: connections and messages in file
order, and the whole records of the chunk the cut falls in (what its decompressor gives of the
part that was written). What is lost is collected as :class:`Damage` so the bag source names it
once.

rosbags' own readers are used for intact files; this runs only when they refuse one. Standard
library only, but for compressed chunks: bz2 is stdlib, lz4 and zstandard are rosbags'
dependencies (imported when a chunk needs them; without them that chunk is named as not read
and why).
"""

from __future__ import annotations

import bz2
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


class _Salvage:
    """A damaged file read from its start: :meth:`messages` yields ``(connection or channel id,
    log time, payload)`` in file order and leaves in ``damage`` what was lost."""

    path: Path
    damage: Damage

    def messages(self) -> Iterator[tuple[int, int, bytes]]:
        raise NotImplementedError

    def _stopped(self, offset: int, chunk: int | None, what: str) -> None:
        """Note a record cut short at ``offset``: the file's end, or inside ``chunk``."""
        if chunk is None:
            self.damage.stopped = (
                f"the file ends inside {what} at byte {offset} (cut short): nothing after it"
            )
        else:
            self.damage.skipped.append(
                f"the chunk at byte {chunk} ends inside {what} at byte {offset}; the rest of "
                "that chunk is lost"
            )

    def scan(self) -> tuple[int, int, int]:
        """Read the whole file once: its connections, and (messages, first, last log time)."""
        count, first, last = 0, None, None
        for _, log_ns, _ in self.messages():
            count += 1
            first = log_ns if first is None else min(first, log_ns)
            last = log_ns if last is None else max(last, log_ns)
        return count, first or 0, last or 0


class McapSalvage(_Salvage):
    """The records of an MCAP file in file order, read past damage where the format allows.

    ``channels`` are those seen so far (all of them after :meth:`scan`); :meth:`messages` yields
    ``(channel id, log time, payload)``; ``damage`` says what was lost.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.damage = Damage()

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


# -- ROS 1 ------------------------------------------------------------------------------------
# http://wiki.ros.org/Bags/Format/2.0: after the magic, records of a header (u32 length, then
# u32-length-prefixed "name=value" fields, "op" the record type) and data (u32 length, bytes).

ROS1_MAGIC = b"#ROSBAG V2.0\n"
_ROS1_MESSAGE, _ROS1_CHUNK, _ROS1_CONNECTION = b"\x02", b"\x05", b"\x07"
_ROS1_TIME = struct.Struct("<II")


@dataclass(frozen=True, slots=True)
class Ros1Connection:
    """A ROS 1 connection record: its topic and the connection header's fields (``msgtype`` as
    the bag names it, ``std_msgs/Float64``)."""

    id: int
    topic: str
    msgtype: str
    md5sum: str
    definition: str
    callerid: str | None
    latching: str | None


def _ros1_fields(data: memoryview) -> dict[str, bytes]:
    """The ``name=value`` fields of a record header or of a connection header."""
    fields = {}
    reader = _Reader(data)
    while reader.at < len(data):
        (size,) = reader.unpack(_U32)
        name, equals, value = bytes(reader.take(size)).partition(b"=")
        if not equals:
            msg = f"a header field without '=' ({name[:20]!r})"
            raise ValueError(msg)
        fields[name.decode("utf-8")] = value
    return fields


def _ros1_decompressor(compression: str, whole: bool) -> Callable[[bytes], bytes]:
    """The decompressor of a chunk; not ``whole``: one that gives what it can of a chunk cut
    short (its complete blocks) instead of failing on the missing end."""
    if compression == "none":
        return lambda data: data
    if compression == "bz2":
        return bz2.decompress if whole else bz2.BZ2Decompressor().decompress
    if compression == "lz4":
        try:
            import lz4.frame
        except ModuleNotFoundError as err:
            msg = f"lz4 is not installed ({err}); pip install lz4"
            raise ValueError(msg) from err
        if whole:
            return lambda data: bytes(lz4.frame.decompress(data))
        return lambda data: bytes(lz4.frame.LZ4FrameDecompressor().decompress(data))
    msg = f"compression {compression!r} is not one ROS 1 bags use"
    raise ValueError(msg)


class Ros1Salvage(_Salvage):
    """The records of a ROS 1 bag (format 2.0) in file order, without its index.

    ``connections`` are those seen so far (all of them after :meth:`scan`); :meth:`messages`
    yields ``(connection id, log time, payload)``; ``damage`` says what was lost.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.connections: dict[int, Ros1Connection] = {}
        self.damage = Damage()
        self._orphans = 0

    def messages(self) -> Iterator[tuple[int, int, bytes]]:
        self.damage = Damage()
        self._orphans = 0
        with self.path.open("rb") as file:
            size = self.path.stat().st_size
            if size < len(ROS1_MAGIC) or file.read(len(ROS1_MAGIC)) != ROS1_MAGIC:
                self.damage.stopped = (
                    "it does not start with the ROS 1 bag magic (#ROSBAG V2.0): nothing was read"
                )
                return
            with mmap.mmap(file.fileno(), 0, access=mmap.ACCESS_READ) as mapped:
                yield from self._records(memoryview(mapped)[len(ROS1_MAGIC) :], len(ROS1_MAGIC), None)
        if self._orphans:
            self.damage.skipped.append(
                f"{self._orphans} messages of connections whose connection record was lost"
            )

    def _records(
        self, data: memoryview, base: int, chunk: int | None
    ) -> Iterator[tuple[int, int, bytes]]:
        """Records of ``data`` (the file after its magic, or one chunk's records); ``base`` is
        where it starts in the file, ``chunk`` the file offset of the chunk it is."""
        at = 0
        while at < len(data):
            start = at
            if at + 4 > len(data):
                self._stopped(base + at, chunk, "a record header")
                return
            (header_size,) = _U32.unpack_from(data, at)
            header_end = at + 4 + header_size
            if header_end + 4 > len(data):
                self._stopped(base + at, chunk, f"a record header of {header_size} bytes")
                return
            (data_size,) = _U32.unpack_from(data, header_end)
            content_start = header_end + 4
            at = content_start + data_size
            try:
                fields = _ros1_fields(data[start + 4 : header_end])
                op = fields.get("op")
                if at > len(data):
                    if chunk is None and op == _ROS1_CHUNK:
                        yield from self._cut_chunk(fields, data[content_start:], base + start)
                    self._stopped(base + start, chunk, f"a record of {data_size} bytes")
                    return
                content = data[content_start:at]
                if op == _ROS1_MESSAGE:
                    (connection,) = _U32.unpack(fields["conn"])
                    sec, nsec = _ROS1_TIME.unpack(fields["time"])
                    if connection in self.connections:
                        # A copy: a view would keep the file's mapping from closing.
                        yield connection, sec * 1_000_000_000 + nsec, bytes(content)
                    else:
                        self._orphans += 1
                elif op == _ROS1_CHUNK and chunk is None:
                    yield from self._chunk(fields, content, base + start)
                elif op == _ROS1_CONNECTION:
                    self._connection(fields, content)
            except (_TruncatedError, struct.error, KeyError, ValueError) as err:
                what = "a chunk's record" if chunk is not None else "a record"
                reason = str(err) or "a field runs past the end of its record"
                self.damage.skipped.append(
                    f"{what} at byte {base + start} is malformed ({type(err).__name__}: "
                    f"{reason}), skipped"
                )
                if at > len(data):
                    return

    def _chunk(
        self, fields: dict[str, bytes], content: memoryview, offset: int
    ) -> Iterator[tuple[int, int, bytes]]:
        compression = fields["compression"].decode("utf-8")
        (size,) = _U32.unpack(fields["size"])
        try:
            records = _ros1_decompressor(compression, whole=True)(bytes(content))
        except Exception as err:
            # bz2's OSError, lz4's RuntimeError, our ValueError: what a codec says of bad data.
            self.damage.skipped.append(
                f"the chunk at byte {offset} does not decompress ({compression}: {err}), skipped"
            )
            return
        if len(records) != size:
            self.damage.skipped.append(
                f"the chunk at byte {offset} holds {len(records)} bytes, not the {size} its "
                "header says (corrupt), skipped"
            )
            return
        yield from self._records(memoryview(records), offset, offset)

    def _cut_chunk(
        self, fields: dict[str, bytes], written: memoryview, offset: int
    ) -> Iterator[tuple[int, int, bytes]]:
        """The whole records of the part of a chunk written before the file ends."""
        compression = fields["compression"].decode("utf-8")
        try:
            records = _ros1_decompressor(compression, whole=False)(bytes(written))
        except Exception as err:
            self.damage.skipped.append(
                f"the chunk at byte {offset} is cut short and what was written of it does not "
                f"decompress ({compression}: {err})"
            )
            return
        yield from self._records(memoryview(records), offset, offset)

    def _connection(self, fields: dict[str, bytes], content: memoryview) -> None:
        (connection,) = _U32.unpack(fields["conn"])
        if connection in self.connections:
            return
        header = _ros1_fields(content)

        def text(name: str) -> str | None:
            value = header.get(name)
            return None if value is None else value.decode("utf-8")

        self.connections[connection] = Ros1Connection(
            id=connection,
            topic=fields["topic"].decode("utf-8"),
            msgtype=header["type"].decode("utf-8"),
            md5sum=text("md5sum") or "",
            definition=text("message_definition") or "",
            callerid=text("callerid"),
            latching=text("latching"),
        )
