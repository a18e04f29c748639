"""The decoder (host_bridge/core/decode.py): custom types from the definitions a robot's catalog
carries, one typestore per definition, and errors that name the type."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from host_bridge.core.decode import Decoder
from host_bridge.errors import DecodeError, UnknownTypeError
from robot_relay.wire import Catalog, MessageDefinition, RawMessage, TopicInfo

READING = "acme_msgs/msg/Reading"
# Uses std_msgs/Header and builtin_interfaces/Time without defining them, as a relay sends a
# definition whose dependencies are standard ROS types.
READING_TEXT = """std_msgs/Header header
float64 celsius
string sensor
uint16[3] raw
"""
# An older layout of the same type name, as another robot (or a ROS 1 bag) may still send.
OLD_READING_TEXT = "float32 celsius\n"


def serialize(text: str, **fields: Any) -> bytes:
    """CDR of a READING with ``text`` as its definition, by an independent rosbags store."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg(text, READING))
    return bytes(store.serialize_cdr(store.types[READING](**fields), READING))


def header(sec: int, frame_id: str) -> Any:
    t = get_typestore(Stores.ROS2_HUMBLE).types
    return t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=5), frame_id=frame_id
    )


def definition_from_catalog(text: str) -> MessageDefinition | None:
    """The definition as the host gets it: a relay's catalog JSON, parsed."""
    sent = Catalog("tb3", "ros2", (TopicInfo("/temperature", READING, MessageDefinition("ros2msg", text)),))
    [topic] = Catalog.from_json(sent.to_json(), "swanky/tb3/catalog").topics
    return topic.definition


def test_a_custom_type_decodes_with_the_definition_from_the_catalog() -> None:
    data = serialize(
        READING_TEXT, header=header(12, "deck"), celsius=21.5, sensor="t1",
        raw=np.array([1, 2, 65535], dtype=np.uint16),
    )
    raw = RawMessage("tb3", "/temperature", READING, data, definition_from_catalog(READING_TEXT))
    msg = Decoder().decode(raw)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (12, 5, "deck")
    assert (msg.celsius, msg.sensor, msg.raw.tolist()) == (21.5, "t1", [1, 2, 65535])


def test_two_definitions_of_one_type_name_decode_side_by_side() -> None:
    decoder = Decoder()
    new = RawMessage(
        "tb3", "/temperature", READING,
        serialize(READING_TEXT, header=header(1, "a"), celsius=-3.25, sensor="new",
                  raw=np.zeros(3, dtype=np.uint16)),
        definition_from_catalog(READING_TEXT),
    )
    old = RawMessage(
        "tb2", "/temperature", READING, serialize(OLD_READING_TEXT, celsius=7.5),
        definition_from_catalog(OLD_READING_TEXT),
    )
    decoded_new, decoded_old = decoder.decode(new), decoder.decode(old)
    assert (decoded_new.celsius, decoded_new.sensor) == (-3.25, "new")
    assert decoded_old.celsius == 7.5
    assert not hasattr(decoded_old, "sensor")


def test_an_unknown_type_without_definition_is_an_error_naming_the_type() -> None:
    raw = RawMessage("tb3", "/mystery", "acme_msgs/msg/Mystery", b"\x00\x01\x00\x00")
    with pytest.raises(UnknownTypeError, match="acme_msgs/msg/Mystery"):
        Decoder().decode(raw)


def test_a_definition_that_names_an_undefined_type_is_an_error_naming_both() -> None:
    text = "acme_msgs/Calibration calibration\nfloat64 celsius\n"
    raw = RawMessage("tb3", "/temperature", READING, b"\x00\x01\x00\x00", definition_from_catalog(text))
    with pytest.raises(UnknownTypeError) as caught:
        Decoder().decode(raw)
    assert READING in str(caught.value)
    assert "acme_msgs/msg/Calibration" in str(caught.value)


def test_a_truncated_payload_is_a_decode_error_naming_the_type() -> None:
    data = serialize(OLD_READING_TEXT, celsius=7.5)
    raw = RawMessage("tb3", "/temperature", READING, data[:5], definition_from_catalog(OLD_READING_TEXT))
    with pytest.raises(DecodeError, match=f"5-byte {READING} payload"):
        Decoder().decode(raw)
