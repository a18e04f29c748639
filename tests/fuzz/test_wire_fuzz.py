"""Everything the host parses from the network, fuzzed: the attachment, the catalog and stats
JSON, every key and liveliness token parser, compressed payloads. Each input either parses into
well-typed values or is refused with the protocol's own error naming the key; nothing else
escapes (issue 14)."""

from __future__ import annotations

import json
import math
from collections import Counter
from collections.abc import Callable
from typing import Any, TypeVar, cast

import pytest
from hypothesis import given
from hypothesis import strategies as st

from host_bridge.errors import GraphError
from host_bridge.inputs.rmw_keys import (
    parse_rmw_attachment,
    parse_rmw_data_key,
    parse_rmw_qos,
    parse_rmw_token,
)
from robot_relay.errors import WireError
from robot_relay.wire import (
    ATTACHMENT_SIZE,
    FLAG_LZ4,
    FLAG_ZSTD,
    MAX_DECOMPRESSED_BYTES,
    Attachment,
    Catalog,
    MessageDefinition,
    QosProfile,
    RelayReport,
    TopicInfo,
    check_robot_name,
    decompress,
    parse_cdr_encoding,
    parse_data_key,
    parse_robot_key,
)
from tests.fuzz.fuzzing import FUZZ, mutated
from tests.reliability import Record

KEY = "swanky/tb3/catalog"
T = TypeVar("T")

CATALOG = Catalog(
    robot="tb3",
    source="ros2",
    topics=(
        TopicInfo("/scan", "sensor_msgs/msg/LaserScan",
                  MessageDefinition("ros2msg", "float32 angle_min\n"),
                  QosProfile("best_effort", "volatile", 5)),
        TopicInfo("/map", "nav_msgs/msg/OccupancyGrid", None,
                  QosProfile("reliable", "transient_local", 1)),
    ),
)

json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=8), inner,
                                                                 max_size=3),
    max_leaves=8,
)


def _paths(doc: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every place in a JSON document a value sits."""
    found = [prefix]
    if isinstance(doc, dict):
        for key, value in doc.items():
            found += _paths(value, (*prefix, key))
    elif isinstance(doc, list):
        for index, value in enumerate(doc):
            found += _paths(value, (*prefix, index))
    return found


@st.composite
def broken_documents(draw: st.DrawFn, good: str) -> str | bytes:
    """A valid JSON document with one value replaced, removed, or the text mangled."""
    doc = json.loads(good)
    kind = draw(st.sampled_from(["replace", "remove", "text", "deep", "numbers"]))
    if kind in ("replace", "remove"):
        path = draw(st.sampled_from(_paths(doc)[1:]))
        parent = doc
        for step in path[:-1]:
            parent = parent[step]
        if kind == "remove":
            del parent[path[-1]]
        else:
            parent[path[-1]] = draw(json_values)
        return json.dumps(doc)
    if kind == "deep":
        # Nesting deeper than Python's recursion limit.
        return "[" * draw(st.integers(1_000, 200_000))
    if kind == "numbers":
        # JSON numbers that are not finite floats or machine integers.
        number = draw(st.sampled_from(["1e400", "-1e400", "NaN", "Infinity", "1" * 5000]))
        path = draw(st.sampled_from(_paths(doc)[1:]))
        parent = doc
        for step in path[:-1]:
            parent = parent[step]
        parent[path[-1]] = "@NUMBER@"
        return json.dumps(doc).replace('"@NUMBER@"', number)
    return draw(mutated(good.encode()))


def _fuzz(check: Callable[[Any], str], inputs: st.SearchStrategy[Any]) -> Counter[str]:
    """Run ``check`` on the drawn inputs; count what each came to."""
    seen: Counter[str] = Counter()

    @FUZZ
    @given(inputs)
    def run(value: Any) -> None:
        seen[check(value)] += 1

    run()
    return seen


def _parse_or_refuse(parse: Callable[[], T], error: type[Exception], where: str) -> T | None:
    """``parse()``, or None when it refused the input with ``error`` naming ``where`` (as
    ``repr`` shows it: the parsers quote what they refuse)."""
    try:
        return parse()
    except error as err:
        refusal = str(err)
    assert repr(where) in refusal
    return None


def _summary(seen: Counter[str]) -> str:
    return ", ".join(f"{count} {outcome}" for outcome, count in sorted(seen.items()))


def test_attachment_parses_or_is_refused_naming_the_key(reliability: Record) -> None:
    good = Attachment(sequence=7, receive_ns=1_700_000_000, source_ns=3, flags=FLAG_ZSTD).pack()

    def check(data: bytes) -> str:
        parsed = _parse_or_refuse(lambda: Attachment.unpack(data, "swanky/tb3/data/scan"),
                                  WireError, "swanky/tb3/data/scan")
        if parsed is None:
            return "refused"
        assert len(data) == ATTACHMENT_SIZE
        assert data[0] == 1
        assert 0 <= parsed.sequence <= 0xFFFFFFFF
        assert parsed.flags in (0, FLAG_LZ4, FLAG_ZSTD)
        return "parsed"

    seen = _fuzz(check, mutated(good) | st.binary(max_size=64))
    assert seen["refused"] > 100
    assert sum(seen.values()) >= 250
    reliability("Hostile input", "fuzzed 32-byte attachments (cut, grown, flipped, random)",
                tried=f"{sum(seen.values())} attachments", survived=f"host; {_summary(seen)}",
                lost="0 crashes")


def _check_catalog(text: str | bytes) -> str:
    catalog = _parse_or_refuse(lambda: Catalog.from_json(text, KEY), WireError, KEY)
    if catalog is None:
        return "refused"
    assert isinstance(catalog.robot, str)
    assert isinstance(catalog.source, str)
    for topic in catalog.topics:
        assert isinstance(topic.topic, str)
        assert isinstance(topic.msgtype, str)
        assert topic.definition is None or (
            topic.definition.encoding in ("ros2msg", "ros2idl")
            and isinstance(topic.definition.text, str)
        )
        assert topic.qos.reliability in ("reliable", "best_effort")
        assert topic.qos.durability in ("volatile", "transient_local")
        assert type(topic.qos.depth) is int
        assert topic.qos.depth >= 0
    return "parsed"


def test_catalog_json_parses_into_typed_topics_or_is_refused(reliability: Record) -> None:
    assert Catalog.from_json(CATALOG.to_json(), KEY) == CATALOG
    seen = _fuzz(_check_catalog, broken_documents(CATALOG.to_json()) | json_values.map(json.dumps))
    assert seen["refused"] > 100
    reliability("Hostile input", "fuzzed catalog JSON (fields replaced or removed, bad numbers, "
                "200,000-deep nesting, cut or flipped text)", tried=f"{sum(seen.values())} catalogs",
                survived=f"host; {_summary(seen)} (every parsed one well-typed)", lost="0 crashes")


def test_relay_stats_json_parses_into_numbers_or_is_refused(reliability: Record) -> None:
    good = RelayReport("tb3", 5, 12.5, 100, 2000, {"/scan": 2}).to_json()

    def check(text: str | bytes) -> str:
        report = _parse_or_refuse(lambda: RelayReport.from_json(text, "swanky/tb3/stats"),
                                  WireError, "swanky/tb3/stats")
        if report is None:
            return "refused"
        assert isinstance(report.robot, str)
        assert type(report.time_ns) is int
        assert math.isfinite(report.cpu_percent)
        assert all(type(n) is int for n in report.drops.values())
        return "parsed"

    seen = _fuzz(check, broken_documents(good))
    assert seen["refused"] > 50
    reliability("Hostile input", "fuzzed relay stats JSON", tried=f"{sum(seen.values())} reports",
                survived=f"host; {_summary(seen)}", lost="0 crashes")


key_chunks = st.text(st.characters(codec="utf-8", exclude_characters="/"), max_size=12)
keys = st.lists(key_chunks, min_size=1, max_size=14).map("/".join)


@st.composite
def rmw_keys(draw: st.DrawFn) -> str:
    """Real-looking rmw_zenoh data keys and liveliness tokens with chunks replaced."""
    token = ["@ros2_lv", "0", "aac3178e146ba6f1fc6e6a4085e77f21", "0", "11", "MP", "%", "%tb3",
             "talker", "%chatter", "std_msgs::msg::dds_::String_", "RIHS01_df668c",
             "::,10:,:,:,,"]
    data = ["0", "tb3", "scan", "sensor_msgs::msg::dds_::LaserScan_", "TypeHashNotSupported"]
    parts = list(draw(st.sampled_from([token, data])))
    for _ in range(draw(st.integers(0, 3))):
        parts[draw(st.integers(0, len(parts) - 1))] = draw(
            key_chunks | st.sampled_from(["²", "-1", "99999999999999999999", "::", "1:2",
                                          "NN", "a::b::dds_::_", ":::,-5:", ":::,x:"]))
    cut = draw(st.integers(1, len(parts)))
    return "/".join(parts[:cut])


def _check_key(key: str) -> str:
    parsers: list[tuple[Callable[[], object], type[Exception], str]] = [
        (lambda: parse_data_key(key), WireError, key),
        (lambda: parse_robot_key(key), WireError, key),
        (lambda: parse_cdr_encoding(key, "swanky/tb3/data/scan"), WireError, "swanky/tb3/data/scan"),
        (lambda: parse_rmw_data_key(key), GraphError, key),
        (lambda: parse_rmw_token(key), GraphError, key),
        (lambda: parse_rmw_qos(key), GraphError, key),
    ]
    parsed = [_parse_or_refuse(*parser) for parser in parsers]
    data_key = parsed[0]
    if data_key is not None:
        robot, topic = cast(tuple[str, str], data_key)
        assert check_robot_name(robot) == robot
        assert topic.startswith("/")
        assert len(topic) > 1
    qos = parsed[-1]
    if isinstance(qos, QosProfile):
        assert qos.depth >= 0
    return "parsed" if any(p is not None for p in parsed) else "refused"


def test_key_and_token_parsers_parse_or_refuse(reliability: Record) -> None:
    swanky_keys = st.builds("swanky/{}/data/{}".format, key_chunks, keys)
    seen = _fuzz(_check_key, keys | swanky_keys | rmw_keys() | st.sampled_from([
        "swanky/tb3/data/scan", "swanky/tb 3/data/scan", "swanky/../data/x", "swanky//data/x",
        "application/cdr;sensor_msgs/msg/LaserScan", "²/tb3/scan/a::msg::dds_::B_/x",
    ]))
    assert seen["refused"] > 50
    assert seen["parsed"] > 20
    reliability("Hostile input", "fuzzed key expressions and rmw_zenoh liveliness tokens through "
                "the 6 key parsers", tried=f"{sum(seen.values())} keys",
                survived=f"host; {_summary(seen)}", lost="0 crashes")


def test_rmw_attachment_parses_or_is_refused(reliability: Record) -> None:
    keyed = (b"\x0fsequence_number" + (7).to_bytes(8, "little") + b"\x10source_timestamp"
             + (5).to_bytes(8, "little") + b"\x0asource_gid\x10" + bytes(range(16)))
    assert parse_rmw_attachment(keyed, "k").sequence == 7

    def check(data: bytes) -> str:
        parsed = _parse_or_refuse(lambda: parse_rmw_attachment(data, "0/chatter"), GraphError,
                                  "0/chatter")
        if parsed is None:
            return "refused"
        assert -(2**63) <= parsed.sequence < 2**63
        assert isinstance(parsed.gid, bytes)
        return "parsed"

    seen = _fuzz(check, mutated(keyed) | st.binary(max_size=80))
    assert seen["refused"] > 100
    reliability("Hostile input", "fuzzed rmw_zenoh attachments", tried=f"{sum(seen.values())} "
                "attachments", survived=f"host; {_summary(seen)}", lost="0 crashes")


@pytest.mark.parametrize("flag", [FLAG_LZ4, FLAG_ZSTD], ids=["lz4", "zstd"])
def test_compressed_payloads_decompress_whole_or_are_refused(
    flag: int, reliability: Record
) -> None:
    compress = _compressor(flag)
    good = compress(bytes(range(256)) * 64)

    def check(data: bytes) -> str:
        out = _parse_or_refuse(lambda: decompress(data, flag, "swanky/tb3/data/scan"), WireError,
                               "swanky/tb3/data/scan")
        if out is None:
            return "refused"
        assert len(out) <= MAX_DECOMPRESSED_BYTES
        return "decompressed"

    seen = _fuzz(check, mutated(good) | st.binary(max_size=64))
    assert seen["refused"] > 100
    name = "lz4" if flag == FLAG_LZ4 else "zstd"
    reliability("Hostile input", f"fuzzed {name} payloads", tried=f"{sum(seen.values())} payloads",
                survived=f"host; {_summary(seen)}", lost="0 crashes")


def _compressor(flag: int) -> Callable[[bytes], bytes]:
    if flag == FLAG_LZ4:
        lz4_frame = pytest.importorskip("lz4.frame")
        return lz4_frame.compress  # type: ignore[no-any-return]
    zstandard = pytest.importorskip("zstandard")
    return zstandard.ZstdCompressor().compress  # type: ignore[no-any-return]


def _bomb(flag: int, size: int) -> bytes:
    """A frame of ``size`` zero bytes, compressed a megabyte at a time (the test never holds
    ``size`` bytes itself, so its memory high-water mark measures the host's)."""
    megabyte = bytes(1 << 20)
    if flag == FLAG_LZ4:
        lz4_frame = pytest.importorskip("lz4.frame")
        packer = lz4_frame.LZ4FrameCompressor()
        parts = [packer.begin()] + [packer.compress(megabyte) for _ in range(size >> 20)]
        return b"".join([*parts, packer.compress(bytes(size & 0xFFFFF)), packer.flush()])
    zstandard = pytest.importorskip("zstandard")
    stream = zstandard.ZstdCompressor().compressobj()
    parts = [stream.compress(megabyte) for _ in range(size >> 20)]
    return b"".join([*parts, stream.compress(bytes(size & 0xFFFFF)), stream.flush()])


@pytest.mark.parametrize("flag", [FLAG_LZ4, FLAG_ZSTD], ids=["lz4", "zstd"])
def test_a_decompression_bomb_is_refused_without_inflating_it(
    flag: int, reliability: Record
) -> None:
    """Zeros compress a thousandfold: a sample of a few hundred KB would hold the host's memory
    at 300 MB per message. Past MAX_DECOMPRESSED_BYTES it is refused instead."""
    import resource

    size = 300 << 20
    bomb = _bomb(flag, size)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(WireError, match=r"swanky/tb3/data/scan.*more than 134217728 bytes"):
        decompress(bomb, flag, "swanky/tb3/data/scan")
    grown_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    assert grown_mb < 200  # the bound (128 MB) and buffers, never the 300 MB
    name = "lz4" if flag == FLAG_LZ4 else "zstd"
    reliability("Hostile input", f"{name} decompression bomb ({len(bomb):,} bytes inflating to "
                f"{size:,})", tried="1", survived=f"host (memory +{grown_mb:.0f} MB); refused "
                "naming the key", lost="that sample only")
