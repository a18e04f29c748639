"""Columns of a run of CDR payloads (host_bridge/core/columns.py) equal rosbags' per-message decode:
every field of every message, bitwise for floats, on messages rosbags serializes (every type of
the bundled store, both byte orders, NaN and infinities, varied string and sequence lengths), on
bytes real rclpy (Jazzy) serialized, and on the real bags in ../shared/data; and a run rosbags
would refuse a message of, or whose layout varies too much, is refused whole (None)."""

from __future__ import annotations

import math
import random
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.interfaces import Nodetype
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from host_bridge.core.columns import MESSAGES_PER_BLOCK, Columns, PackedPayloads, read_columns
from host_bridge.core.decode import Decoder
from host_bridge.core.schemas import base_typestore
from robot_relay.sources.bag import BagSource

HUMBLE = get_typestore(Stores.ROS2_HUMBLE)
JOINT_STATE = "sensor_msgs/msg/JointState"
IMU = "sensor_msgs/msg/Imu"
TF = "tf2_msgs/msg/TFMessage"

# The numpy type of each ROS number type as rosbags reads it (its 'byte' is int8, 'char' uint8).
NUMPY_TYPES: dict[str, type[np.generic]] = {
    "bool": np.bool_, "byte": np.int8, "char": np.uint8, "int8": np.int8, "uint8": np.uint8,
    "int16": np.int16, "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32,
    "int64": np.int64, "uint64": np.uint64, "float32": np.float32, "float64": np.float64,
}
SPECIAL_FLOATS = (math.nan, math.inf, -math.inf, -0.0, 5e-324, 1e-45, 3.0e38)
STRINGS = ("", "a", "imu", "base_link", "ünïcödé_frame", "x" * 17, "nul\x00inside", "trailing nul\x00")

# The high-rate types issue 13 names, columnar with the default block bound.
COVERED = (
    IMU, "nav_msgs/msg/Odometry", "geometry_msgs/msg/TwistStamped", "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped", "geometry_msgs/msg/WrenchStamped",
    "sensor_msgs/msg/NavSatFix", JOINT_STATE, "sensor_msgs/msg/Range", "sensor_msgs/msg/Temperature",
    "sensor_msgs/msg/FluidPressure", "sensor_msgs/msg/RelativeHumidity", "sensor_msgs/msg/Illuminance",
    "sensor_msgs/msg/MagneticField", "sensor_msgs/msg/BatteryState", "std_msgs/msg/Float64",
    "std_msgs/msg/Float32", "std_msgs/msg/Int32", "std_msgs/msg/Int64", "std_msgs/msg/UInt8",
    "std_msgs/msg/Bool", "std_msgs/msg/String", TF,
)


class MessageMaker:
    """Messages of any type with random values; string values and sequence lengths come from
    ``shapes`` (re-seed it to repeat a layout) and are the same for every element at one path
    of a message, so nested sequences stay rectangles."""

    def __init__(self, store: Typestore, values: np.random.Generator, shapes: random.Random) -> None:
        self.store = store
        self.values = values
        self.shapes = shapes
        self._lengths: dict[str, int] = {}

    def message(self, msgtype: str) -> Any:
        self._lengths = {}
        return self._message(msgtype, "")

    def _message(self, msgtype: str, prefix: str) -> Any:
        msgdef = self.store.get_msgdef(msgtype)
        fields = {name: self._value(desc, f"{prefix}{name}") for name, desc in msgdef.fields}
        return msgdef.cls(**fields)

    def _value(self, desc: Any, path: str) -> Any:
        node, arg = desc
        if node == Nodetype.NAME:
            return self._message(arg, f"{path}.")
        if node == Nodetype.BASE:
            return self._scalar(arg[0])
        (element_node, element_arg), size = arg
        if node == Nodetype.SEQUENCE:
            if path not in self._lengths:
                self._lengths[path] = self.shapes.randint(0, min(size, 3) if size else 3)
            size = self._lengths[path]
        if element_node == Nodetype.NAME:
            return [self._message(element_arg, f"{path}.") for _ in range(size)]
        if element_arg[0] == "string":
            return [self.shapes.choice(STRINGS) for _ in range(size)]
        return np.array([self._scalar(element_arg[0]) for _ in range(size)],
                        dtype=NUMPY_TYPES[element_arg[0]])

    def _scalar(self, basetype: str) -> Any:
        if basetype == "string":
            return self.shapes.choice(STRINGS)
        kind = NUMPY_TYPES[basetype]
        if kind is np.bool_:
            return bool(self.values.random() < 0.5)
        if issubclass(kind, np.floating):
            if self.values.random() < 0.3:
                return float(kind(self.values.choice(SPECIAL_FLOATS)))
            return float(kind(self.values.normal() * 10.0 ** self.values.integers(-5, 6)))
        info = np.iinfo(np.dtype(kind).str)
        return int(self.values.integers(info.min, info.max, endpoint=True, dtype=kind))


def serialize_run(store: Typestore, msgtype: str, count: int, variants: int, seed: int = 0) -> list[bytes]:
    """``count`` messages, message i in layout variant ``i % variants`` and alternately little
    and big endian."""
    values = np.random.default_rng(seed)
    payloads = []
    for i in range(count):
        message = MessageMaker(store, values, random.Random(i % variants)).message(msgtype)
        payloads.append(bytes(store.serialize_cdr(message, msgtype, little_endian=i % 2 == 0)))
    return payloads


def leaf_paths(store: Typestore, msgtype: str, prefix: str = "") -> dict[str, bool]:
    """Every leaf path of the type from rosbags' field list -> whether it is a string."""
    paths: dict[str, bool] = {}
    for name, desc in store.get_msgdef(msgtype).fields:
        node, arg = element_desc(desc)
        if node == Nodetype.NAME:
            paths.update(leaf_paths(store, arg, f"{prefix}{name}."))
        else:
            paths[f"{prefix}{name}"] = arg[0] == "string"
    return paths


def element_desc(desc: Any) -> tuple[Nodetype, Any]:
    """The element's (node type, argument) of an array or sequence, else the field's own."""
    node, arg = desc
    return arg[0] if node in (Nodetype.ARRAY, Nodetype.SEQUENCE) else (node, arg)


def field_value(message: Any, path: str) -> Any:
    """The value at a dotted path, mapped over lists of messages on the way."""
    if isinstance(message, list):
        return [field_value(item, path) for item in message]
    head, _, rest = path.partition(".")
    value = getattr(message, head)
    return field_value(value, rest) if rest else value


def as_tuples(value: Any) -> Any:
    return tuple(as_tuples(item) for item in value) if isinstance(value, list) else value


def assert_number(expected: Any, got: np.ndarray[Any, Any], where: str) -> None:
    """``got`` holds ``expected``'s values in rosbags' numpy type, bit for bit."""
    if isinstance(expected, np.ndarray):
        assert expected.dtype == got.dtype, where
    elif isinstance(expected, bool):
        assert got.dtype == np.bool_, where
    elif isinstance(expected, int):
        assert got.dtype.kind in "iu", where
    elif isinstance(expected, float):
        assert got.dtype.kind == "f", where
    array = np.asarray(expected, dtype=got.dtype)  # straight from Python ints: uint64 stays exact
    assert array.size == got.size, where
    if array.size:
        assert array.shape == got.shape, where
        assert array.tobytes() == got.tobytes(), where


def assert_equals_rosbags(columns: Columns | None, payloads: list[bytes], msgtype: str,
                          store: Typestore) -> None:
    """Every field of every message is what rosbags' deserialize_cdr gives."""
    assert columns is not None, f"{msgtype}: no columns"
    messages = [store.deserialize_cdr(payload, msgtype) for payload in payloads]
    assert columns.size == len(messages)
    rows = np.sort(np.concatenate([block.rows for block in columns.blocks]))
    assert rows.tolist() == list(range(len(messages)))
    paths = leaf_paths(store, msgtype)
    for block in columns.blocks:
        assert set(block.strings) == {path for path, text in paths.items() if text}
        assert set(block.numbers) == {path for path, text in paths.items() if not text}
        for path, column in block.numbers.items():
            assert len(column) == len(block.rows)
            for row, got in zip(block.rows, column, strict=True):
                assert_number(field_value(messages[row], path), got, f"{msgtype} {path} row {row}")
        for path, value in block.strings.items():
            for row in block.rows:
                assert as_tuples(field_value(messages[row], path)) == value, f"{path} row {row}"


# -- messages rosbags serialized -----------------------------------------------------------------


@pytest.mark.parametrize("msgtype", COVERED)
def test_covered_types_equal_rosbags_with_the_default_block_bound(msgtype: str) -> None:
    """192 messages in three layouts (frame ids, joint names, sequence lengths), both byte orders,
    NaN and infinities: six blocks at most, within the default bound, every value rosbags'."""
    payloads = serialize_run(HUMBLE, msgtype, 192, variants=3)
    columns = read_columns(payloads, msgtype, HUMBLE)
    assert_equals_rosbags(columns, payloads, msgtype, HUMBLE)
    assert columns is not None
    assert len(columns.blocks) <= 6 <= 1 + 192 // MESSAGES_PER_BLOCK


def test_every_type_of_the_bundled_store_equals_rosbags() -> None:
    """The layout comes from the field list alone: every ROS 2 Humble type and every type of
    schemas/msg, each message of its own random layout, reads as rosbags reads it."""
    store = base_typestore()
    msgtypes = sorted(store.fielddefs)
    assert len(msgtypes) > 150
    for number, msgtype in enumerate(msgtypes):
        payloads = serialize_run(store, msgtype, 16, variants=16, seed=number)
        columns = read_columns(payloads, msgtype, store, max_blocks=len(payloads))
        assert_equals_rosbags(columns, payloads, msgtype, store)


def test_one_layout_of_imu_is_one_block_with_its_values() -> None:
    imu = HUMBLE.types[IMU]
    header = HUMBLE.types["std_msgs/msg/Header"]
    stamp = HUMBLE.types["builtin_interfaces/msg/Time"]
    vector = HUMBLE.types["geometry_msgs/msg/Vector3"]
    quaternion = HUMBLE.types["geometry_msgs/msg/Quaternion"]
    payloads = [
        bytes(HUMBLE.serialize_cdr(imu(
            header=header(stamp=stamp(sec=100 + i, nanosec=10 * i), frame_id="imu_link"),
            orientation=quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=np.full(9, -1.0),
            angular_velocity=vector(x=0.5 * i, y=-0.0, z=math.nan),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=vector(x=0.0, y=0.0, z=9.81),
            linear_acceleration_covariance=np.eye(3).ravel(),
        ), IMU))
        for i in range(1000)
    ]
    columns = read_columns(payloads, IMU, HUMBLE)
    assert columns is not None
    assert len(columns.blocks) == 1
    assert columns.blocks[0].strings == {"header.frame_id": "imu_link"}
    assert columns["header.stamp.sec"].tolist() == list(range(100, 1100))
    assert columns["header.stamp.sec"].dtype == np.int32
    assert columns["header.stamp.nanosec"][999] == 9990
    assert columns["angular_velocity.x"][3] == 1.5
    assert np.isnan(columns["angular_velocity.z"]).all()
    assert np.signbit(columns["angular_velocity.y"]).all()
    assert columns["linear_acceleration_covariance"].shape == (1000, 9)
    assert columns["linear_acceleration_covariance"][7].tolist() == np.eye(3).ravel().tolist()
    assert columns["header.frame_id"].tolist() == ["imu_link"] * 1000


def joint_state(names: list[str], sec: int, frame: str = "base_link") -> bytes:
    header = HUMBLE.types["std_msgs/msg/Header"]
    stamp = HUMBLE.types["builtin_interfaces/msg/Time"]
    k = len(names)
    return bytes(HUMBLE.serialize_cdr(HUMBLE.types[JOINT_STATE](
        header=header(stamp=stamp(sec=sec, nanosec=0), frame_id=frame), name=names,
        position=np.arange(k) + float(sec), velocity=np.array([], dtype=np.float64),
        effort=np.full(k, -1.0 * sec),
    ), JOINT_STATE))


def test_joint_states_with_two_joint_lists_are_blocks_and_a_whole_run_column_says_so() -> None:
    arm = ["shoulder", "elbow", "wrist"]
    payloads = [joint_state(["gripper"] if i % 4 == 3 else arm, i) for i in range(64)]
    columns = read_columns(payloads, JOINT_STATE, HUMBLE)
    assert_equals_rosbags(columns, payloads, JOINT_STATE, HUMBLE)
    assert columns is not None
    by_names = {block.strings["name"]: block for block in columns.blocks}
    assert set(by_names) == {tuple(arm), ("gripper",)}
    assert by_names[("gripper",)].rows.tolist() == list(range(3, 64, 4))
    assert by_names[tuple(arm)].numbers["position"][1].tolist() == [1.0, 2.0, 3.0]
    assert by_names[tuple(arm)].numbers["velocity"].shape == (48, 0)
    assert columns["header.stamp.sec"].tolist() == list(range(64))  # same shape in every block
    with pytest.raises(ValueError, match=r"position has shapes \[\(1,\), \(3,\)\]"):
        columns["position"]
    with pytest.raises(KeyError, match="no field 'positions'"):
        columns["positions"]


def test_string_columns_keep_run_order_and_nul_characters() -> None:
    frames = ["odom", "map\x00", "odom", "base"]
    payloads = [joint_state(["j"], i, frames[i % 4]) for i in range(40)]
    columns = read_columns(payloads, JOINT_STATE, HUMBLE)
    assert_equals_rosbags(columns, payloads, JOINT_STATE, HUMBLE)
    assert columns is not None
    assert columns["header.frame_id"].tolist() == [frames[i % 4] for i in range(40)]
    assert columns["name"].shape == (40, 1)
    assert columns["name"][5, 0] == "j"


def transforms_message(count: int, sec: int) -> Any:
    types = HUMBLE.types
    header = types["std_msgs/msg/Header"]
    stamp = types["builtin_interfaces/msg/Time"]
    return types[TF](transforms=[
        types["geometry_msgs/msg/TransformStamped"](
            header=header(stamp=stamp(sec=sec, nanosec=j), frame_id="odom" if j else "map"),
            child_frame_id=f"link_{j}",
            transform=types["geometry_msgs/msg/Transform"](
                translation=types["geometry_msgs/msg/Vector3"](x=float(j), y=float(sec), z=0.0),
                rotation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            ),
        )
        for j in range(count)
    ])


def test_tf_messages_give_one_column_per_transform_field() -> None:
    payloads = [bytes(HUMBLE.serialize_cdr(transforms_message(2, sec), TF)) for sec in range(50)]
    columns = read_columns(payloads, TF, HUMBLE)
    assert_equals_rosbags(columns, payloads, TF, HUMBLE)
    assert columns is not None
    assert len(columns.blocks) == 1
    assert columns.blocks[0].strings == {
        "transforms.header.frame_id": ("map", "odom"), "transforms.child_frame_id": ("link_0", "link_1"),
    }
    assert columns["transforms.transform.translation.y"].shape == (50, 2)
    assert columns["transforms.transform.translation.y"][7].tolist() == [7.0, 7.0]
    assert columns["transforms.header.stamp.nanosec"][0].tolist() == [0, 1]


def test_empty_message_sequences_give_empty_columns() -> None:
    payloads = [bytes(HUMBLE.serialize_cdr(transforms_message(0, 0), TF))] * 3
    columns = read_columns(payloads, TF, HUMBLE)
    assert_equals_rosbags(columns, payloads, TF, HUMBLE)
    assert columns is not None
    assert columns["transforms.transform.rotation.w"].shape == (3, 0)
    assert columns.blocks[0].strings["transforms.child_frame_id"] == ()


# -- runs that are refused -----------------------------------------------------------------------


def test_nested_sequences_of_differing_lengths_in_one_message_are_refused() -> None:
    """MarkerArray with markers of 1 and 2 points is no rectangle: rosbags reads it, we don't."""
    msgtype = "visualization_msgs/msg/MarkerArray"
    maker = MessageMaker(HUMBLE, np.random.default_rng(1), random.Random(0))
    message = maker.message(msgtype)
    marker = maker.message("visualization_msgs/msg/Marker")
    point = HUMBLE.types["geometry_msgs/msg/Point"]
    marker.points = [point(x=1.0, y=2.0, z=3.0)]
    message.markers = [marker, maker.message("visualization_msgs/msg/Marker")]
    message.markers[1].points = [point(x=0.0, y=0.0, z=0.0)] * 2
    payload = bytes(HUMBLE.serialize_cdr(message, msgtype))
    decoded: Any = HUMBLE.deserialize_cdr(payload, msgtype)
    assert len(decoded.markers[1].points) == 2
    assert read_columns([payload] * 4, msgtype, HUMBLE) is None


def test_a_run_with_a_message_rosbags_refuses_is_refused_whole() -> None:
    good = joint_state(["a", "b"], 1)
    bad = {
        "truncated": good[:-5],
        "unterminated string": good.replace(b"base_link\x00", b"base_linkX"),
        "not UTF-8": good.replace(b"base_link", b"base_lin\xff"),
        "PL_CDR header": b"\x00\x03" + good[2:],
        "8 bytes after the message": good + bytes(8),
        "shorter than a header": b"\x00",
    }
    for problem, payload in bad.items():
        with pytest.raises(SerdeError):
            HUMBLE.deserialize_cdr(payload, JOINT_STATE)
        assert read_columns([good] * 20 + [payload], JOINT_STATE, HUMBLE) is None, problem
    slack = good + bytes(3)  # rosbags allows 3 bytes after the message
    columns = read_columns([good, slack], JOINT_STATE, HUMBLE, max_blocks=2)
    assert_equals_rosbags(columns, [good, slack], JOINT_STATE, HUMBLE)


def test_a_layout_per_message_is_refused_unless_allowed() -> None:
    payloads = [joint_state(["j"], i, f"frame_{i}") for i in range(64)]
    assert read_columns(payloads, JOINT_STATE, HUMBLE) is None
    columns = read_columns(payloads, JOINT_STATE, HUMBLE, max_blocks=64)
    assert_equals_rosbags(columns, payloads, JOINT_STATE, HUMBLE)
    assert read_columns([], JOINT_STATE, HUMBLE) is None


# -- bytes real rclpy (ROS 2 Jazzy, Fast CDR) serialized -------------------------------------------
# Made with rclpy.serialization.serialize_message; padding bytes are whatever Fast CDR left there.
# sensor_msgs/Imu, frame_id imu, imu_link, a, imu; NaN, -0.0, +-inf, a subnormal
RCLPY_IMUS = (
    (
        "0001000000f153650000000004000000696d750000000000000000000000000000000080000000000000e03f00000000"
        "0000f03f0000000000000000000000000000f03f00000000000000400000000000000840000000000000104000000000"
        "0000144000000000000018400000000000001c4000000000000020402be6708b68120000000000000000f0ff00000000"
        "00000a40000000000000f0bf000000000000000000000000000000000000000000000000000000000000000000000000"
        "000000000000000000000000000000000000000000000000000000001f85eb51b89e23400000000000000000039300aa"
        "4bdd4dfe0000000000000000000000000000000000000000000000000000000000000000000000000000000000000000"
        "00000000000000000000000000000000000000000000000000000000"
    ),
    (
        "0001000001f1536515cd5b0709000000696d755f6c696e6b000000009a9999999999b93f000000000000008000000000"
        "0000f87f000000000000f03f000000000000f0bf0000000000000000000000000000f03f000000000000004000000000"
        "000008400000000000001040000000000000144000000000000018400000000000001c402be6708b6812000000000000"
        "0000f0ff0000000000000a40000000000000f0bf00000000000000000000000000000000000000000000000000000000"
        "0000000000000000000000000000000000000000000000000000000000000000000000001f85eb51b89e254000000000"
        "00000000039300aa4bdd4dfe000000000000000000000000000000000000000000000000000000000000000000000000"
        "000000000000000000000000000000000000000000000000000000000000000000000000"
    ),
    (
        "0001000002f153652a9ab70e020000006100755f9a9999999999c93f0000000000000080000000000000e03f00000000"
        "0000f03f00000000000000c0000000000000f0bf0000000000000000000000000000f03f000000000000004000000000"
        "00000840000000000000104000000000000014400000000000001840000000000000f07f000000000000f0ff00000000"
        "00000a40000000000000f0bf000000000000000000000000000000000000000000000000000000000000000000000000"
        "000000000000000000000000000000000000000000000000000000001f85eb51b89e27400000000000000000039300aa"
        "4bdd4dfe0000000000000000000000000000000000000000000000000000000000000000000000000000000000000000"
        "00000000000000000000000000000000000000000000000000000000"
    ),
    (
        "0001000003f153653f67131604000000696d7500343333333333d33f0000000000000080000000000000e03f00000000"
        "0000f03f00000000000008c000000000000000c0000000000000f0bf0000000000000000000000000000f03f00000000"
        "000000400000000000000840000000000000104000000000000014402be6708b68120000000000000000f0ff00000000"
        "00000a40000000000000f0bf000000000000000000000000000000000000000000000000000000000000000000000000"
        "000000000000000000000000000000000000000000000000000000001f85eb51b89e29400000000000000000039300aa"
        "4bdd4dfe0000000000000000000000000000000000000000000000000000000000000000000000000000000000000000"
        "00000000000000000000000000000000000000000000000000000000"
    ),
)
# sensor_msgs/JointState, 6 joints; frame_id base_link, base_link, empty; a NaN effort
RCLPY_JOINT_STATES = (
    (
        "0001000011000000000000000a000000626173655f6c696e6b000100060000000d00000073686f756c6465725f70616e"
        "000000000e00000073686f756c6465725f6c69667400000006000000656c626f770000000800000077726973745f3100"
        "0800000077726973745f32000800000077726973745f33000600000000000000000000009a9999999999b93f9a999999"
        "9999c93f343333333333d33f9a9999999999d93f000000000000e03f0600000000006411000000000000008000000000"
        "0000e0bf000000000000f0bf000000000000f8bf00000000000000c000000000000004c0060000007700780300000000"
        "0000f87f00000000000000400000000000001040000000000000204000000000000030400000000000004040"
    ),
    (
        "0001000012000000050000000a000000626173655f6c696e6b000100060000000d00000073686f756c6465725f70616e"
        "000000000e00000073686f756c6465725f6c69667400000006000000656c626f770000000800000077726973745f3100"
        "0800000077726973745f32000800000077726973745f330006000000000000000000f03f9a9999999999f13f33333333"
        "3333f33fcdccccccccccf43f666666666666f63f000000000000f83f0600000000006411000000000000008000000000"
        "0000e0bf000000000000f0bf000000000000f8bf00000000000000c000000000000004c0060000007700780300000000"
        "0000f03f000000000000f87f0000000000001040000000000000204000000000000030400000000000004040"
    ),
    (
        "00010000130000000a000000010000000059c90a060000000d00000073686f756c6465725f70616e0075d50a0e000000"
        "73686f756c6465725f6c69667400000006000000656c626f7700410a0800000077726973745f31000800000077726973"
        "745f32000800000077726973745f3300060000000000000000000040cdcccccccccc00409a9999999999014066666666"
        "666602403333333333330340000000000000044006000000707d500a0000000000000080000000000000e0bf00000000"
        "0000f0bf000000000000f8bf00000000000000c000000000000004c0060000003077d50a000000000000f03f00000000"
        "00000040000000000000f87f000000000000204000000000000030400000000000004040"
    ),
)
# geometry_msgs/TransformStamped odom>base_link, map>odom, base_link>laser (TFMessage's element)
RCLPY_TRANSFORMS = (
    (
        "0001000028000000ffc99a3b050000006f646f6d000000000a000000626173655f6c696e6b0000000000000000000000"
        "0000000000000000000000c0000000000000c03f00000000000000000000000000000000cd3b7f669ea0e63fcd3b7f66"
        "9ea0e63f"
    ),
    (
        "0001000029000000fec99a3b040000006d617000050000006f646f6d006173655f6c696e000000000000f83f00000000"
        "000000c0000000000000c03f00000000000000000000000000000000cd3b7f669ea0e63fcd3b7f669ea0e63f"
    ),
    (
        "000100002a000000fdc99a3b0a000000626173655f6c696e6b006f6d060000006c617365720000000000f83f00000000"
        "0000084000000000000000c0000000000000c03f00000000000000000000000000000000cd3b7f669ea0e63fcd3b7f66"
        "9ea0e63f"
    ),
)
# JointState with an empty velocity: serialize_message leaves 8 bytes after the message
RCLPY_EMPTY_VELOCITY = (
    (
        "000100000000000000000000010000000030303001000000020000006100373401000000000000000000f03f00000000"
        "0100000000000000000000403030303630303030"
    ),
)


def test_rclpy_imu_payloads_equal_rosbags() -> None:
    payloads = [bytes.fromhex(text) for text in RCLPY_IMUS]
    columns = read_columns(payloads, IMU, HUMBLE, max_blocks=len(payloads))
    assert_equals_rosbags(columns, payloads, IMU, HUMBLE)
    assert columns is not None
    assert columns["header.frame_id"].tolist() == ["imu", "imu_link", "a", "imu"]
    assert columns["header.stamp.sec"].tolist() == [1700000000, 1700000001, 1700000002, 1700000003]
    assert np.isnan(columns["orientation.z"][1])
    assert columns["angular_velocity.x"].tolist() == [1e-310, 1e-310, math.inf, 1e-310]
    assert columns["orientation_covariance"][3].tolist() == [float(j) - 3 for j in range(9)]


def test_rclpy_joint_state_payloads_equal_rosbags() -> None:
    payloads = [bytes.fromhex(text) for text in RCLPY_JOINT_STATES]
    columns = read_columns(payloads, JOINT_STATE, HUMBLE, max_blocks=len(payloads))
    assert_equals_rosbags(columns, payloads, JOINT_STATE, HUMBLE)
    assert columns is not None
    assert columns["name"][0].tolist() == [
        "shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3"]
    assert columns["position"][2].tolist() == [2.0 + 0.1 * j for j in range(6)]
    assert np.isnan(columns["effort"][1, 1])
    assert columns["effort"][1, 5] == 32.0


def test_rclpy_transform_payloads_equal_rosbags() -> None:
    msgtype = "geometry_msgs/msg/TransformStamped"
    payloads = [bytes.fromhex(text) for text in RCLPY_TRANSFORMS]
    columns = read_columns(payloads, msgtype, HUMBLE, max_blocks=len(payloads))
    assert_equals_rosbags(columns, payloads, msgtype, HUMBLE)
    assert columns is not None
    assert columns["child_frame_id"].tolist() == ["base_link", "odom", "laser"]
    assert columns["header.stamp.nanosec"].tolist() == [999999999, 999999998, 999999997]
    assert columns["transform.translation.x"].tolist() == [0.0, 1.5, 3.0]


def test_rclpys_oversized_empty_sequence_payload_is_refused_like_rosbags_does() -> None:
    """serialize_message sizes an empty float64 sequence as if padded: 8 bytes follow the message,
    which rosbags refuses ('size mismatch'), so the run is refused and decoded one by one."""
    payload = bytes.fromhex(RCLPY_EMPTY_VELOCITY[0])
    with pytest.raises(SerdeError, match="size mismatch"):
        HUMBLE.deserialize_cdr(payload, JOINT_STATE)
    assert read_columns([payload], JOINT_STATE, HUMBLE) is None
    assert read_columns([payload[:-8]], JOINT_STATE, HUMBLE) is not None


# -- real bags -----------------------------------------------------------------------------------

REAL_BAGS = (
    "phidgets_imu_ccny/phidgets_imu_upside_down.bag",
    "gps_fix_rviz_satellite/sample.bag",
    "tf_nav2_sim_evo/nav2_turtlebot.mcap",
    "tf_nav2_sim_evo/tf_example",
    "tb3_nav_sim_paths_amr/rosbag_demo.bag",
    "hokuyo_scan_ccny/laser_scan_matcher_demo.bag",
    "raspicam_aruco_ubiquity/aruco_images.bag",
    "ros_numpy_msgs_synthetic/ros_numpy_test.bag",
    "rosbag2_format_fixtures/mcap_cdr_test",
    "rosbag2_format_fixtures/sqlite3_wbag",
)
# Topics of the high-rate types: columnar with the default block bound, not only when allowed.
HIGH_RATE = {IMU, TF, "nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped",
             "geometry_msgs/msg/TwistStamped", "sensor_msgs/msg/NavSatFix", "sensor_msgs/msg/MagneticField"}
PER_TOPIC = 1000


@pytest.mark.parametrize("bag", REAL_BAGS)
def test_real_bags_equal_rosbags(shared_data: Path, bag: str) -> None:
    """Every topic of the bag (its first 1000 messages, as the host gets them: CDR, ROS 1 bags
    converted) in columns equals rosbags' decode with the typestore the host's decoder uses."""
    decoder = Decoder()
    runs: dict[str, list[bytes]] = defaultdict(list)
    stores: dict[str, tuple[str, Typestore]] = {}
    with BagSource(shared_data / bag, "robot") as source:
        for raw in source.messages():
            if len(runs[raw.topic]) < PER_TOPIC:
                runs[raw.topic].append(bytes(raw.data))
                stores[raw.topic] = (raw.msgtype, decoder.typestore_for(raw.msgtype, raw.definition))
    assert runs
    for topic, payloads in runs.items():
        msgtype, store = stores[topic]
        columns = read_columns(payloads, msgtype, store, max_blocks=len(payloads))
        assert_equals_rosbags(columns, payloads, msgtype, store)
        if msgtype in HIGH_RATE and len(payloads) > 100:
            assert read_columns(payloads, msgtype, store) is not None, topic


def test_a_remembered_layout_claims_only_payloads_with_its_length_prefixes() -> None:
    """The second run's payloads have the first run's length but other string lengths: the
    layout remembered from the first run must not read them."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    first = [joint_state(["ab", "c"], i, "odom") for i in range(20)]
    second = [joint_state(["abcd", "e"], i, "odo") for i in range(20)]
    assert {len(p) for p in first} == {len(p) for p in second}
    for run in (first, second, first):
        columns = read_columns(run, JOINT_STATE, store)
        assert_equals_rosbags(columns, run, JOINT_STATE, store)
    assert columns is not None
    assert columns.blocks[0].strings == {"header.frame_id": "odom", "name": ("ab", "c")}


# -- payloads packed in buffers (a bag's runs) ---------------------------------------------------


def scattered(payloads: list[bytes], buffers: int) -> PackedPayloads:
    """``payloads`` spread over ``buffers`` buffers, message i in buffer i % buffers, each after
    a gap and a run of junk bytes (not back to back, as a chunk's record headers lie between)."""
    parts: list[bytearray] = [bytearray() for _ in range(buffers)]
    sources, starts, ends = [], [], []
    for i, payload in enumerate(payloads):
        part = parts[i % buffers]
        part += b"\xff" * (1 + i % 5)
        sources.append(i % buffers)
        starts.append(len(part))
        part += payload
        ends.append(len(part))
    return PackedPayloads(tuple(bytes(part) for part in parts), np.array(sources, np.intp),
                          np.array(starts, np.intp), np.array(ends, np.intp))


@pytest.mark.parametrize("buffers", [1, 3])
def test_packed_payloads_of_several_lengths_in_several_buffers_equal_rosbags(buffers: int) -> None:
    names = [["a"], ["shoulder", "elbow"], ["shoulder", "elbow", "wrist_roll"]]
    payloads = [joint_state(names[i % 3], i, frame="f" * (1 + i % 4)) for i in range(60)]
    packed = scattered(payloads, buffers)
    assert list(packed) == payloads
    assert len({int(end - start) for start, end in zip(packed.starts, packed.ends, strict=True)}) > 3
    columns = read_columns(packed, JOINT_STATE, HUMBLE, max_blocks=len(payloads))
    assert_equals_rosbags(columns, payloads, JOINT_STATE, HUMBLE)
    listed = read_columns(payloads, JOINT_STATE, HUMBLE, max_blocks=len(payloads))
    assert columns is not None
    assert listed is not None
    assert [block.rows.tolist() for block in columns.blocks] == [
        block.rows.tolist() for block in listed.blocks]
    assert len(columns.blocks) == 12  # 3 joint lists x 4 frame ids


def test_a_truncated_packed_payload_refuses_the_run_and_only_it_fails_to_decode() -> None:
    payloads = serialize_run(HUMBLE, IMU, 30, variants=1)
    payloads[13] = payloads[13][:-40]
    packed = scattered(payloads, 2)
    assert read_columns(packed, IMU, HUMBLE) is None
    refused = []
    for i, payload in enumerate(packed):
        try:
            HUMBLE.deserialize_cdr(payload, IMU)
        except SerdeError:
            refused.append(i)
    assert refused == [13]
