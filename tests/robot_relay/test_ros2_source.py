"""The pure parts of the rclpy source (rclpy itself is not installable here)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, cast

from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from robot_relay.sources.ros2 import adapted_qos, ament_share_dirs, message_definition


def write_msg(share: Path, name: str, text: str) -> None:
    package, type_name = name.split("/")
    path = share / package / "msg" / f"{type_name}.msg"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def test_definition_from_share_dirs_includes_every_used_type(tmp_path: Path) -> None:
    base, overlay = tmp_path / "base" / "share", tmp_path / "overlay" / "share"
    write_msg(base, "std_msgs/Header", "builtin_interfaces/Time stamp\nstring frame_id\n")
    write_msg(base, "builtin_interfaces/Time", "int32 sec\nuint32 nanosec\n")
    write_msg(overlay, "my_robot/Reading", "# comment\nint32 LIMIT=3\nfloat32 value\n")
    write_msg(
        overlay, "my_robot/Status",
        "Header header\nReading[] readings  # relative name\nReading[<=4] last\n"
        "string<=8 label\ngeometry_msgs/Point where\n",
    )
    write_msg(base, "geometry_msgs/Point", "float64 x\nfloat64 y\nfloat64 z\n")
    shares = ament_share_dirs({"AMENT_PREFIX_PATH": f"{tmp_path / 'overlay'}:{tmp_path / 'base'}"})
    assert shares == [overlay, base]
    definition = message_definition("my_robot/msg/Status", shares)
    assert definition is not None
    assert definition.encoding == "ros2msg"
    for name in ("std_msgs/Header", "builtin_interfaces/Time", "my_robot/Reading",
                 "geometry_msgs/Point"):
        assert f"MSG: {name}\n" in definition.text
    types = get_types_from_msg(definition.text, "my_robot/msg/Status")
    store = get_typestore(Stores.EMPTY)
    store.register(types)
    status = store.types["my_robot/msg/Status"]
    assert [f.name for f in dataclasses.fields(cast(Any, status)) if not f.name.startswith("__")] == [
        "header", "readings", "last", "label", "where"
    ]
    assert message_definition("my_robot/msg/Missing", shares) is None


def test_qos_follows_ros2_bag_record() -> None:
    assert adapted_qos([]).durability == "volatile"
    mixed = adapted_qos([("reliable", "transient_local", 1), ("best_effort", "volatile", 5)])
    assert (mixed.reliability, mixed.durability, mixed.depth) == ("best_effort", "volatile", 5)
    latched = adapted_qos([("reliable", "transient_local", 1), ("reliable", "transient_local", 1)])
    assert latched.durability == "transient_local"
    assert latched.reliability == "reliable"
