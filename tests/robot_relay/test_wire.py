from __future__ import annotations

import struct

import pytest

from robot_relay.errors import WireError
from robot_relay.wire import (
    ATTACHMENT_SIZE,
    BUNDLE_ENTRY_SIZE,
    BUNDLE_HEAD_SIZE,
    FLAG_BUNDLE,
    FLAG_LZ4,
    FLAG_ZSTD,
    Attachment,
    Catalog,
    ClockReading,
    MessageDefinition,
    QosProfile,
    TopicInfo,
    bundle_count,
    cdr_encoding,
    check_robot_name,
    clock_key,
    data_key,
    decompress,
    files_key,
    pack_bundle,
    parse_cdr_encoding,
    parse_data_key,
)


def test_data_key_round_trip_keeps_namespaces_and_adds_the_leading_slash() -> None:
    assert data_key("tb3", "/scan") == "swanky/tb3/data/scan"
    assert parse_data_key(data_key("tb3", "/robot1/odom")) == ("tb3", "/robot1/odom")
    assert parse_data_key(data_key("tb3", "AAA")) == ("tb3", "/AAA")


def test_foreign_keys_and_bad_robot_names_are_refused() -> None:
    with pytest.raises(WireError, match="not a Swanky data key"):
        parse_data_key("other/tb3/data/scan")
    with pytest.raises(WireError, match="not allowed"):
        check_robot_name("tb3/evil")


def test_files_key() -> None:
    key = files_key("tb1", "pkg", "meshes/a.stl")
    assert key == "swanky/tb1/files/pkg/meshes/a.stl"


def test_attachment_is_32_little_endian_bytes_in_the_documented_order() -> None:
    packed = Attachment(sequence=7, receive_ns=1_700_000_000_123, source_ns=42).pack()
    assert len(packed) == ATTACHMENT_SIZE == 32
    assert packed[0] == 1  # version
    assert struct.unpack_from("<I", packed, 4)[0] == 7
    assert struct.unpack_from("<q", packed, 8)[0] == 1_700_000_000_123
    assert struct.unpack_from("<q", packed, 16)[0] == 42
    assert Attachment.unpack(packed, "k") == Attachment(7, 1_700_000_000_123, 42, 0)


def test_a_clock_reading_is_24_little_endian_bytes_in_the_documented_order() -> None:
    assert clock_key("tb3") == "swanky/tb3/clock"
    packed = ClockReading(received_ns=1_700_000_007_500_000_001, replied_ns=-3).pack()
    assert len(packed) == 24
    assert packed[:8] == b"\x01" + bytes(7)  # version 1, then reserved
    assert struct.unpack_from("<qq", packed, 8) == (1_700_000_007_500_000_001, -3)
    assert ClockReading.unpack(packed, "k") == ClockReading(1_700_000_007_500_000_001, -3)
    with pytest.raises(WireError, match=r"swanky/tb3/clock.*version 2"):
        ClockReading.unpack(b"\x02" + packed[1:], "swanky/tb3/clock")
    with pytest.raises(WireError, match=r"'k': 0 bytes, version missing"):
        ClockReading.unpack(b"", "k")


def test_unknown_attachment_version_is_rejected_naming_the_key() -> None:
    packed = bytearray(Attachment(1, 2).pack())
    packed[0] = 9
    with pytest.raises(WireError, match=r"swanky/tb3/data/scan.*version 9"):
        Attachment.unpack(bytes(packed), "swanky/tb3/data/scan")
    with pytest.raises(WireError, match="is 5 bytes"):
        Attachment.unpack(b"12345", "k")
    with pytest.raises(WireError, match="unknown flags"):
        Attachment.unpack(Attachment(1, 2, flags=FLAG_LZ4 | FLAG_ZSTD).pack(), "k")


def test_compressed_payloads_decompress_to_the_same_cdr() -> None:
    lz4_frame = pytest.importorskip("lz4.frame")
    zstandard = pytest.importorskip("zstandard")
    cdr = bytes(range(256)) * 40
    assert decompress(lz4_frame.compress(cdr), FLAG_LZ4, "k") == cdr
    assert decompress(zstandard.ZstdCompressor().compress(cdr), FLAG_ZSTD, "k") == cdr
    with pytest.raises(WireError, match="does not decompress"):
        decompress(b"not lz4", FLAG_LZ4, "k")


def test_encoding_carries_the_ros_type() -> None:
    encoding = cdr_encoding("sensor_msgs/msg/LaserScan")
    assert encoding == "application/cdr;sensor_msgs/msg/LaserScan"
    assert parse_cdr_encoding(encoding, "k") == "sensor_msgs/msg/LaserScan"
    with pytest.raises(WireError, match="expected 'application/cdr"):
        parse_cdr_encoding("application/json", "k")


def test_catalog_json_round_trip() -> None:
    catalog = Catalog(
        robot="pupper",
        source="bag",
        topics=(
            TopicInfo("/scan", "sensor_msgs/msg/LaserScan", MessageDefinition("ros2msg", "x")),
            TopicInfo(
                "/tf_static", "tf2_msgs/msg/TFMessage", None,
                QosProfile(durability="transient_local", depth=1),
            ),
        ),
    )
    back = Catalog.from_json(catalog.to_json(), "swanky/pupper/catalog")
    assert back == catalog
    assert [t.latched for t in back.topics] == [False, True]
    with pytest.raises(WireError, match="swanky/pupper/catalog"):
        Catalog.from_json('{"version": 1}', "swanky/pupper/catalog")


def test_a_bundle_packs_count_source_times_sizes_then_payloads() -> None:
    payloads = [b"\x00\x01\x00\x00a", b"\x00\x01\x00\x00bcd", b""]
    packed = pack_bundle(payloads, [10, -2, 30])
    assert struct.unpack_from("<II", packed) == (3, 0)
    assert struct.unpack_from("<3q", packed, 8) == (10, -2, 30)
    assert struct.unpack_from("<3I", packed, 32) == (5, 7, 0)
    assert packed[44:] == b"".join(payloads)
    assert len(packed) == BUNDLE_HEAD_SIZE + 3 * BUNDLE_ENTRY_SIZE + 12
    assert bundle_count(packed, "k") == 3


def test_a_bundle_header_that_cannot_fit_its_sample_is_refused_naming_the_key() -> None:
    with pytest.raises(WireError, match=r"bundle on 'swanky/tb3/data/imu' is 5 bytes"):
        bundle_count(b"12345", "swanky/tb3/data/imu")
    with pytest.raises(WireError, match=r"'swanky/tb3/data/imu' says it holds 0 messages"):
        bundle_count(struct.pack("<II", 0, 0), "swanky/tb3/data/imu")
    with pytest.raises(WireError, match=r"says it holds 2 messages .*cut-short"):
        bundle_count(pack_bundle([b"ab", b"cd"], [1, 2])[:20], "swanky/tb3/data/imu")
    with pytest.raises(WireError, match=r"\(reserved 7\)"):
        bundle_count(struct.pack("<II", 1, 7) + bytes(12), "k")


def test_singles_keep_wire_version_1_and_bundles_are_version_2() -> None:
    single = Attachment(3, 4, 5, FLAG_LZ4).pack()
    bundle = Attachment(3, 4, 0, FLAG_BUNDLE | FLAG_ZSTD).pack()
    # A version-1 host reads every single message a bundling relay sends, and refuses its
    # bundles naming the version.
    assert (single[0], bundle[0]) == (1, 2)
    assert Attachment.unpack(single, "k") == Attachment(3, 4, 5, FLAG_LZ4)
    assert Attachment.unpack(bundle, "k").bundle
    v1_bundle = bytearray(bundle)
    v1_bundle[0] = 1
    with pytest.raises(WireError, match="unknown flags 0x06"):
        Attachment.unpack(bytes(v1_bundle), "k")
    v2_single = bytearray(single)
    v2_single[0] = 2
    with pytest.raises(WireError, match="wire version 2 but is not a bundle"):
        Attachment.unpack(bytes(v2_single), "k")
