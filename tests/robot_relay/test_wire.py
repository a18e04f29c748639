from __future__ import annotations

import struct

import pytest

from robot_relay.errors import WireError
from robot_relay.wire import (
    ATTACHMENT_SIZE,
    FLAG_LZ4,
    FLAG_ZSTD,
    Attachment,
    Catalog,
    MessageDefinition,
    QosProfile,
    TopicInfo,
    cdr_encoding,
    check_robot_name,
    data_key,
    decompress,
    files_key,
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
