"""Bundled definitions: which one an rmw_zenoh publisher's type hash names."""

from __future__ import annotations

from rosbags.typesys import Stores, get_typestore

from host_bridge.core.schemas import BundledDefinitions

HUMBLE = get_typestore(Stores.ROS2_HUMBLE)
JAZZY = get_typestore(Stores.ROS2_JAZZY)
SCAN_HASH = HUMBLE.hash_rihs01("sensor_msgs/msg/LaserScan")


def test_definitions_follow_the_type_hash() -> None:
    definitions = BundledDefinitions()
    assert definitions.lookup("sensor_msgs/msg/LaserScan", None) == (None, None)
    assert definitions.lookup("sensor_msgs/msg/LaserScan", SCAN_HASH) == (None, None)
    # Jazzy added Range.variance: its hash picks the Jazzy definition, not Humble's.
    definition, warning = definitions.lookup(
        "sensor_msgs/msg/Range", JAZZY.hash_rihs01("sensor_msgs/msg/Range")
    )
    assert warning is None
    assert definition is not None
    assert "float32 variance" in definition.text
    assert definitions.lookup("sensor_msgs/msg/Range", HUMBLE.hash_rihs01("sensor_msgs/msg/Range")) \
        == (None, None)
    definition, warning = definitions.lookup("sensor_msgs/msg/LaserScan", "RIHS01_" + "0" * 64)
    assert definition is None
    assert warning is not None
    assert "sensor_msgs/msg/LaserScan" in warning
