"""The Swanky wire protocol (schemas/wire.md) and the record every input becomes. (rmw_zenoh's
keys, which only the host reads, are host_bridge/inputs/rmw_keys.py.)

Pure Python with no third-party imports, so the relay on a Raspberry Pi and the host share it.
"""

from __future__ import annotations

import json
import math
import re
import struct
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, TypeVar

from robot_relay.errors import WireError

PREFIX = "swanky"
# Version 2 added bundles (FLAG_BUNDLE). A relay marks a single message's attachment version 1,
# which every host reads, and a bundle's version 2, which a version-1 host refuses by name.
ATTACHMENT_VERSION = 2
SINGLE_MESSAGE_VERSION = 1
CATALOG_VERSION = 1
STATS_VERSION = 1
CLOCK_VERSION = 1
CDR_ENCODING = "application/cdr"
ROBOT_NAME_PATTERN = re.compile(r"^[A-Za-z0-9_-]+$")

FLAG_LZ4 = 0x01
FLAG_ZSTD = 0x02
FLAG_BUNDLE = 0x04
_KNOWN_FLAGS = FLAG_LZ4 | FLAG_ZSTD | FLAG_BUNDLE

_ATTACHMENT = struct.Struct("<BBHIqqQ")
ATTACHMENT_SIZE = _ATTACHMENT.size

# A bundle: u32 message count, u32 reserved, then i64 source times, u32 payload sizes, payloads.
_BUNDLE_HEAD = struct.Struct("<II")
BUNDLE_HEAD_SIZE = _BUNDLE_HEAD.size
BUNDLE_ENTRY_SIZE = 8 + 4

# A clock reading: u8 version, 7 reserved bytes, i64 when the query reached the relay, i64 when
# it replied (both ns since the Unix epoch on the relay's clock).
_CLOCK_READING = struct.Struct("<B7xqq")

# The most a compressed payload may inflate to. Zeros compress a thousandfold, so without a bound
# a 300 KB sample would hold 300 MB of the host's memory; no ROS message a robot sends over its
# link comes near this (a 4K 16-bit depth image is 17 MB, a 128-beam lidar cloud about 12 MB).
MAX_DECOMPRESSED_BYTES = 128 * 1024 * 1024

DefinitionEncoding = Literal["ros2msg", "ros2idl"]


def check_robot_name(robot: str) -> str:
    """Return ``robot`` if it can be a key chunk, entity root and frame prefix."""
    if not ROBOT_NAME_PATTERN.match(robot):
        msg = (
            f"robot name {robot!r} is not allowed: use letters, digits, '_' and '-' only "
            "(it becomes a Zenoh key chunk, a Rerun entity root and a frame prefix)"
        )
        raise WireError(msg)
    return robot


def absolute_topic(topic: str) -> str:
    """ROS topic with exactly one leading slash (rosbag2 allows names without it)."""
    return "/" + topic.lstrip("/")


def data_key(robot: str, topic: str) -> str:
    return f"{PREFIX}/{robot}/data/{topic.lstrip('/')}"


def data_selector(robots: str = "*") -> str:
    """Key expression matching every data sample of the robots matched by ``robots``."""
    return f"{PREFIX}/{robots}/data/**"


def catalog_key(robot: str) -> str:
    return f"{PREFIX}/{robot}/catalog"


def clock_key(robot: str) -> str:
    return f"{PREFIX}/{robot}/clock"


def alive_key(robot: str) -> str:
    return f"{PREFIX}/{robot}/alive"


def alive_selector(robots: str = "*") -> str:
    """Key expression matching the liveliness tokens of the robots matched by ``robots``."""
    return f"{PREFIX}/{robots}/alive"


def files_prefix(robot: str) -> str:
    """The start of every key of ``robot``'s file server; the rest is ``<package>/<path>``."""
    return f"{PREFIX}/{check_robot_name(robot)}/files/"


def files_key(robot: str, package: str, relpath: str) -> str:
    return f"{files_prefix(robot)}{package}/{relpath}"


def files_selector(robot: str) -> str:
    """Key expression of every file request to ``robot``'s file server."""
    return f"{files_prefix(robot)}**"


def parse_data_key(key: str) -> tuple[str, str]:
    """Split a data key into (robot, absolute topic); the robot name must be one a relay can
    have, since it becomes an entity root and a frame prefix."""
    parts = key.split("/", 3)
    if len(parts) != 4 or parts[0] != PREFIX or parts[2] != "data" or not parts[3]:
        msg = f"key {key!r} is not a Swanky data key ({PREFIX}/<robot>/data/<topic>)"
        raise WireError(msg)
    try:
        check_robot_name(parts[1])
    except WireError as err:
        msg = f"key {key!r}: {err}"
        raise WireError(msg) from err
    return parts[1], "/" + parts[3]


def parse_robot_key(key: str) -> str:
    """Robot name of any key under ``swanky/<robot>/``."""
    parts = key.split("/")
    if len(parts) < 3 or parts[0] != PREFIX:
        msg = f"key {key!r} is not under {PREFIX}/<robot>/"
        raise WireError(msg)
    return parts[1]


def cdr_encoding(msgtype: str) -> str:
    return f"{CDR_ENCODING};{msgtype}"


def parse_cdr_encoding(encoding: str, key: str) -> str:
    """ROS type name carried as the schema of an ``application/cdr`` encoding."""
    base, _, schema = encoding.partition(";")
    if base != CDR_ENCODING or not schema:
        msg = f"sample on {key!r} has encoding {encoding!r}, expected '{CDR_ENCODING};<ros type>'"
        raise WireError(msg)
    return schema


def pack_attachment(sequence: int, receive_ns: int, source_ns: int = 0, flags: int = 0) -> bytes:
    """The bytes of ``Attachment(sequence, receive_ns, source_ns, flags)`` without making one:
    the relay packs one per message."""
    version = ATTACHMENT_VERSION if flags & FLAG_BUNDLE else SINGLE_MESSAGE_VERSION
    return _ATTACHMENT.pack(version, flags, 0, sequence & 0xFFFFFFFF, receive_ns, source_ns, 0)


@dataclass(frozen=True, slots=True)
class Attachment:
    """Per-sample metadata sent beside the CDR bytes; for a bundle, ``sequence`` is its first
    message's and ``source_ns`` 0 (each message's is in the bundle)."""

    sequence: int
    receive_ns: int
    source_ns: int = 0
    flags: int = 0

    @property
    def bundle(self) -> bool:
        return bool(self.flags & FLAG_BUNDLE)

    def pack(self) -> bytes:
        return pack_attachment(self.sequence, self.receive_ns, self.source_ns, self.flags)

    @classmethod
    def unpack(cls, data: bytes, key: str) -> Attachment:
        if len(data) != ATTACHMENT_SIZE:
            msg = (
                f"attachment on {key!r} is {len(data)} bytes, expected {ATTACHMENT_SIZE}: "
                "relay and host speak different wire versions"
            )
            raise WireError(msg)
        version, flags, _, sequence, receive_ns, source_ns, _ = _ATTACHMENT.unpack(data)
        if not SINGLE_MESSAGE_VERSION <= version <= ATTACHMENT_VERSION:
            msg = (
                f"attachment on {key!r} has wire version {version}, this host speaks "
                f"{ATTACHMENT_VERSION}: upgrade the older side"
            )
            raise WireError(msg)
        known = _KNOWN_FLAGS if version == ATTACHMENT_VERSION else _KNOWN_FLAGS & ~FLAG_BUNDLE
        if flags & ~known or flags & (FLAG_LZ4 | FLAG_ZSTD) == FLAG_LZ4 | FLAG_ZSTD:
            msg = f"attachment on {key!r} has unknown flags {flags:#04x}"
            raise WireError(msg)
        if version == ATTACHMENT_VERSION and not flags & FLAG_BUNDLE:
            msg = f"attachment on {key!r} has wire version {version} but is not a bundle"
            raise WireError(msg)
        return cls(sequence, receive_ns, source_ns, flags)


def pack_bundle(payloads: Sequence[bytes | memoryview], source_ns: Sequence[int]) -> bytes:
    """Several CDR payloads of one topic as one sample's payload (schemas/wire.md, Bundles)."""
    count = len(payloads)
    return b"".join([
        _BUNDLE_HEAD.pack(count, 0),
        struct.pack(f"<{count}q", *source_ns),
        struct.pack(f"<{count}I", *map(len, payloads)),
        *payloads,
    ])


def bundle_count(data: bytes | memoryview, key: str) -> int:
    """How many messages the bundle ``data`` holds, once its header is checked against its
    length; WireError naming ``key`` when it cannot be a bundle (the sizes are the reader's
    to check against the rest)."""
    if len(data) < BUNDLE_HEAD_SIZE:
        msg = f"bundle on {key!r} is {len(data)} bytes, shorter than its {BUNDLE_HEAD_SIZE}-byte header"
        raise WireError(msg)
    count, reserved = _BUNDLE_HEAD.unpack_from(data)
    if not count or reserved or BUNDLE_HEAD_SIZE + count * BUNDLE_ENTRY_SIZE > len(data):
        msg = (
            f"bundle on {key!r} says it holds {count} messages (reserved {reserved}), which "
            f"its {len(data)} bytes cannot: a corrupt or cut-short sample"
        )
        raise WireError(msg)
    return int(count)


COMPRESSION_FLAGS = {"lz4": FLAG_LZ4, "zstd": FLAG_ZSTD}
# The Python package each compression needs (the optional extra ``swanky[compression]``).
COMPRESSION_PACKAGES = {"lz4": "lz4", "zstd": "zstandard"}


def compressor(name: str) -> Callable[[bytes], bytes]:
    """A function compressing one payload into an lz4 or zstd frame; ImportError when the
    package is missing (imported here, not at module level: the relay runs without them)."""
    if name == "lz4":
        import lz4.frame

        return lz4.frame.compress  # type: ignore[no-any-return]
    if name == "zstd":
        import zstandard

        # One context per topic, reused (zstd contexts are costly to make); not thread-safe,
        # so each caller keeps its own.
        return zstandard.ZstdCompressor().compress
    msg = f"unknown compression {name!r} (expected one of: {', '.join(COMPRESSION_FLAGS)})"
    raise ValueError(msg)


def decompress(payload: bytes, flags: int, key: str) -> bytes:
    """Undo the compression named by the attachment flags; a frame that is cut short, or would
    inflate past MAX_DECOMPRESSED_BYTES, is refused without inflating it."""
    if not flags & (FLAG_LZ4 | FLAG_ZSTD):
        return payload
    try:
        data = _lz4_decompress(payload) if flags & FLAG_LZ4 else _zstd_decompress(payload)
    except ImportError as err:
        msg = f"sample on {key!r} is compressed but {err.name} is not installed"
        raise WireError(msg) from err
    except Exception as err:
        msg = f"sample on {key!r} does not decompress: {err}"
        raise WireError(msg) from err
    if data is None:
        msg = (
            f"sample on {key!r} would decompress to more than {MAX_DECOMPRESSED_BYTES} bytes "
            "(no ROS message is that big: a corrupt or hostile frame); dropped"
        )
        raise WireError(msg)
    return data


def _lz4_decompress(payload: bytes) -> bytes | None:
    """The frame's content, None past the bound. Inflated 8 MiB at a time and counted as it
    grows (python-lz4 sizes one big output buffer twice over)."""
    import lz4.frame

    decompressor = lz4.frame.LZ4FrameDecompressor()
    parts: list[bytes] = []
    size = 0
    pending = payload
    while True:
        part = decompressor.decompress(pending, max_length=8 << 20)
        pending = b""
        size += len(part)
        if size > MAX_DECOMPRESSED_BYTES:
            return None
        parts.append(part)
        if decompressor.eof:
            return b"".join(parts)
        if decompressor.needs_input:
            raise ValueError(f"the lz4 frame ends early, after {size} bytes of content")


def _zstd_decompress(payload: bytes) -> bytes | None:
    """The frame's content, None past the bound. A frame declaring its size (the relay's do) is
    checked before anything is allocated; one without is fed in small pieces, so what it
    inflates to is counted as it grows."""
    import zstandard

    declared = zstandard.frame_content_size(payload)
    if declared > MAX_DECOMPRESSED_BYTES:
        return None
    if declared >= 0:
        return bytes(zstandard.ZstdDecompressor().decompress(payload))
    stream = zstandard.ZstdDecompressor().decompressobj()
    parts: list[bytes] = []
    size = 0
    # 1 KiB of zstd inflates to at most ~32 MiB (one RLE block per 3 bytes).
    for start in range(0, len(payload), 1024):
        part = stream.decompress(payload[start:start + 1024])
        size += len(part)
        if size > MAX_DECOMPRESSED_BYTES:
            return None
        parts.append(part)
        if stream.eof:
            return b"".join(parts)
    raise ValueError(f"the zstd frame ends early, after {size} bytes of content")


@dataclass(frozen=True, slots=True)
class MessageDefinition:
    """Full text of a message type and every type it uses."""

    encoding: DefinitionEncoding
    text: str


@dataclass(frozen=True, slots=True)
class QosProfile:
    reliability: Literal["reliable", "best_effort"] = "reliable"
    durability: Literal["volatile", "transient_local"] = "volatile"
    depth: int = 10


@dataclass(frozen=True, slots=True)
class TopicInfo:
    topic: str
    msgtype: str
    definition: MessageDefinition | None
    qos: QosProfile = field(default_factory=QosProfile)

    @property
    def latched(self) -> bool:
        return self.qos.durability == "transient_local"


T = TypeVar("T")


def _field(value: Any, kind: type[T], what: str) -> T:
    """``value`` if it is a ``kind`` (JSON's true is no integer here), else a TypeError naming
    ``what``: a catalog's fields end up in Rerun entity paths and decoders."""
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        msg = f"{what} is {value!r}, expected {kind.__name__}"
        raise TypeError(msg)
    return value


def _choice(value: Any, choices: tuple[str, ...], what: str) -> Any:
    if value not in choices:
        msg = f"{what} is {value!r}, expected one of {', '.join(choices)}"
        raise ValueError(msg)
    return value


def parse_versioned_json(
    text: str | bytes, key: str, what: str, version: int, build: Callable[[Any], T]
) -> T:
    """``build(doc)`` of a JSON document carrying ``"version": version``; anything else (bad JSON,
    another version, a missing or mistyped field) is a WireError naming ``what`` and ``key``."""
    try:
        doc: Any = json.loads(text)
        if doc["version"] != version:
            msg = f"{what} on {key!r} has version {doc['version']}, expected {version}"
            raise WireError(msg)
        return build(doc)
    except WireError:
        raise
    # RecursionError: JSON nested deeper than Python recurses; OverflowError: 1e400 as an int;
    # AttributeError: an object where the document has a list (or the other way round).
    except (ValueError, KeyError, TypeError, AttributeError, OverflowError, RecursionError) as err:
        msg = f"{what} on {key!r} is not valid: {err!r}"
        raise WireError(msg) from err


@dataclass(frozen=True, slots=True)
class Catalog:
    robot: str
    source: str
    topics: tuple[TopicInfo, ...]

    def to_json(self) -> str:
        return json.dumps(
            {
                "version": CATALOG_VERSION,
                "robot": self.robot,
                "source": self.source,
                "topics": [
                    {
                        "topic": t.topic,
                        "type": t.msgtype,
                        "latched": t.latched,
                        "qos": {
                            "reliability": t.qos.reliability,
                            "durability": t.qos.durability,
                            "depth": t.qos.depth,
                        },
                        "definition": None
                        if t.definition is None
                        else {"encoding": t.definition.encoding, "text": t.definition.text},
                    }
                    for t in self.topics
                ],
            }
        )

    @classmethod
    def from_json(cls, text: str | bytes, key: str) -> Catalog:
        def topic(t: Any) -> TopicInfo:
            name = _field(t["topic"], str, "a topic's name")
            definition = t["definition"]
            qos = t["qos"]
            return TopicInfo(
                topic=name,
                msgtype=_field(t["type"], str, f"the type of {name}"),
                definition=None if definition is None else MessageDefinition(
                    _choice(definition["encoding"], ("ros2msg", "ros2idl"),
                            f"the definition encoding of {name}"),
                    _field(definition["text"], str, f"the definition of {name}"),
                ),
                qos=QosProfile(
                    reliability=_choice(qos["reliability"], ("reliable", "best_effort"),
                                        f"the reliability of {name}"),
                    durability=_choice(qos["durability"], ("volatile", "transient_local"),
                                       f"the durability of {name}"),
                    depth=_depth(_field(qos["depth"], int, f"the QoS depth of {name}")),
                ),
            )

        def build(doc: Any) -> Catalog:
            return cls(
                robot=_field(doc["robot"], str, "robot"),
                source=_field(doc["source"], str, "source"),
                topics=tuple(topic(t) for t in _field(doc["topics"], list, "topics")),
            )

        return parse_versioned_json(text, key, "catalog", CATALOG_VERSION, build)


def _depth(depth: int) -> int:
    if depth < 0:
        msg = f"QoS history depth {depth} is negative"
        raise ValueError(msg)
    return depth


def _finite(value: float, what: str) -> float:
    if not math.isfinite(value):
        msg = f"{what} is {value}"
        raise ValueError(msg)
    return value


def stats_key(robot: str) -> str:
    return f"{PREFIX}/{robot}/stats"


def stats_selector(robots: str = "*") -> str:
    return f"{PREFIX}/{robots}/stats"


@dataclass(frozen=True, slots=True)
class RelayReport:
    """The relay's health once a second (robot_relay/stats.py puts it, the host plots it).

    Counts are cumulative, so a lost report loses nothing. ``drops``: per topic, messages lost
    before the relay (publication sequence gaps).
    """

    robot: str
    time_ns: int
    cpu_percent: float
    messages: int
    payload_bytes: int
    drops: Mapping[str, int] = field(default_factory=dict)

    def to_json(self) -> str:
        return json.dumps({
            "version": STATS_VERSION,
            "robot": self.robot,
            "time_ns": self.time_ns,
            "cpu_percent": round(self.cpu_percent, 2),
            "messages": self.messages,
            "bytes": self.payload_bytes,
            "drops": dict(self.drops),
        })

    @classmethod
    def from_json(cls, text: str | bytes, key: str) -> RelayReport:
        return parse_versioned_json(
            text, key, "relay stats", STATS_VERSION,
            lambda doc: cls(
                robot=str(doc["robot"]),
                time_ns=int(doc["time_ns"]),
                cpu_percent=_finite(float(doc["cpu_percent"]), "cpu_percent"),
                messages=int(doc["messages"]),
                payload_bytes=int(doc["bytes"]),
                # Added to version 1 later: a relay without it reports no drops.
                drops={str(topic): int(count) for topic, count in doc.get("drops", {}).items()},
            ),
        )


@dataclass(frozen=True, slots=True)
class ClockReading:
    """A relay's answer to a clock query (schemas/wire.md, Clock): its wall clock, the clock of
    every receive time it sends, when the query reached it and when it replied."""

    received_ns: int
    replied_ns: int

    def pack(self) -> bytes:
        return _CLOCK_READING.pack(CLOCK_VERSION, self.received_ns, self.replied_ns)

    @classmethod
    def unpack(cls, data: bytes, key: str) -> ClockReading:
        if len(data) != _CLOCK_READING.size or data[0] != CLOCK_VERSION:
            msg = (
                f"clock reading on {key!r}: {len(data)} bytes, version "
                f"{data[0] if data else 'missing'}; expected {_CLOCK_READING.size} bytes of version "
                f"{CLOCK_VERSION}: relay and host speak different wire versions"
            )
            raise WireError(msg)
        _, received_ns, replied_ns = _CLOCK_READING.unpack(data)
        return cls(received_ns, replied_ns)


@dataclass(frozen=True, slots=True)
class RawMessage:
    """One undecoded ROS message; every input (relay, rmw_zenoh, bag) yields these.

    ``data`` is CDR with its encapsulation header. ``receive_ns`` is when the relay got it
    (live only), ``log_ns`` the bag log time (replays, direct or through a relay).
    """

    robot: str
    topic: str
    msgtype: str
    data: bytes | memoryview
    definition: MessageDefinition | None = None
    receive_ns: int | None = None
    log_ns: int | None = None
    sequence: int | None = None
