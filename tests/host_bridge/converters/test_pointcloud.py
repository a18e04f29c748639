"""PointCloud2 -> Points3D: positions and colours for many byte layouts, built byte by byte."""

from __future__ import annotations

import math
import struct
import tracemalloc
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest
import rerun as rr
from rosbags.typesys import Stores, get_typestore

from host_bridge.converters.pointcloud import convert_pointcloud2
from host_bridge.core.colormap import apply_colormap
from host_bridge.core.contract import LogItem
from host_bridge.errors import ConvertError
from host_bridge.pipeline.dispatch import Dispatcher
from robot_relay.wire import RawMessage
from tests.host_bridge.sensor_test_support import (
    archetype,
    flat,
    header,
    log_item,
    make_ctx,
    msg,
    read_topic,
    rgba,
)
from tests.host_bridge.test_config import RecordingSink
from tests.reliability import Record

INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)
PATH = "/r/cloud"
CLOUD = "sensor_msgs/msg/PointCloud2"
ROBOT = "r"
STORE = get_typestore(Stores.ROS2_HUMBLE)


def field(name: str, offset: int, datatype: int, count: int = 1) -> Any:
    return msg(
        "sensor_msgs/msg/PointField", name=name, offset=offset, datatype=datatype, count=count
    )


def records(layout: dict[str, tuple[str, int]], itemsize: int, n: int) -> npt.NDArray[np.void]:
    """Zeroed point records: name -> (numpy format, byte offset)."""
    dtype = np.dtype(
        {
            "names": list(layout),
            "formats": [f for f, _ in layout.values()],
            "offsets": [o for _, o in layout.values()],
            "itemsize": itemsize,
        }
    )
    return np.zeros(n, dtype=dtype)


def cloud(
    data: bytes,
    fields: list[Any],
    width: int,
    point_step: int,
    *,
    height: int = 1,
    row_step: int | None = None,
    bigendian: bool = False,
    frame_id: str = "lidar",
) -> Any:
    return msg(
        "sensor_msgs/msg/PointCloud2",
        header=header(frame_id),
        height=height,
        width=width,
        fields=fields,
        is_bigendian=bigendian,
        point_step=point_step,
        row_step=width * point_step if row_step is None else row_step,
        data=np.frombuffer(data, dtype=np.uint8),
        is_dense=False,
    )


def convert(message: Any, **options: Any) -> tuple[npt.NDArray[Any], npt.NDArray[np.uint8], Any]:
    """Positions (n, 3), colours (n, 4) and the Points3D of one converted cloud."""
    item = log_item(convert_pointcloud2(message, make_ctx("/cloud", options)), PATH)
    points = archetype(item, rr.Points3D)
    return flat(points.positions, 3), rgba(flat(points.colors)), points


XYZ = np.array([[1.5, -2.0, 0.25], [3.0, 4.0, -5.0], [-0.5, 0.0, 7.0]], dtype=np.float32)


def test_padded_point_step_colours_by_intensity_and_sets_frame() -> None:
    rec = records({"x": ("<f4", 0), "y": ("<f4", 4), "z": ("<f4", 8), "i": ("<f4", 16)}, 32, 3)
    rec["x"], rec["y"], rec["z"] = XYZ.T
    rec["i"] = [10.0, 30.0, 20.0]
    raw = bytearray(rec.tobytes())
    raw[12:16] = b"\xff\xff\xff\xff"  # padding between fields must never be read
    fields = [
        field("x", 0, FLOAT32),
        field("y", 4, FLOAT32),
        field("z", 8, FLOAT32),
        field("intensity", 16, FLOAT32),
    ]
    message = cloud(bytes(raw), fields, 3, 32)
    positions, colors, _ = convert(message)
    np.testing.assert_array_equal(positions, XYZ)
    np.testing.assert_array_equal(colors[:, :3], apply_colormap([10.0, 30.0, 20.0]))
    item = log_item(convert_pointcloud2(message, make_ctx("/cloud")), PATH)
    assert archetype(item, rr.CoordinateFrame).frame.as_arrow_array().to_pylist() == ["r/lidar"]


def test_big_endian_float64_with_packed_uint32_rgb() -> None:
    rec = records({"x": (">f8", 0), "y": (">f8", 8), "z": (">f8", 16), "rgb": (">u4", 24)}, 28, 3)
    rec["x"], rec["y"], rec["z"] = XYZ.astype(np.float64).T
    rec["rgb"] = [0x00FF0000, 0x0000FF00, 0x00123456]
    fields = [
        field("x", 0, FLOAT64),
        field("y", 8, FLOAT64),
        field("z", 16, FLOAT64),
        field("rgb", 24, UINT32),
    ]
    positions, colors, _ = convert(cloud(rec.tobytes(), fields, 3, 28, bigendian=True))
    np.testing.assert_array_equal(positions, XYZ)
    np.testing.assert_array_equal(
        colors, [[255, 0, 0, 255], [0, 255, 0, 255], [0x12, 0x34, 0x56, 255]]
    )


def test_int16_fields_and_colour_by_z_when_no_intensity() -> None:
    rec = records({"x": ("<i2", 0), "y": ("<i2", 2), "z": ("<i2", 4)}, 6, 3)
    rec["x"], rec["y"], rec["z"] = [-300, 0, 7], [1, 2, 3], [100, -100, 0]
    fields = [field("x", 0, INT16), field("y", 2, INT16), field("z", 4, INT16)]
    positions, colors, _ = convert(cloud(rec.tobytes(), fields, 3, 6))
    np.testing.assert_array_equal(positions, [[-300, 1, 100], [0, 2, -100], [7, 3, 0]])
    np.testing.assert_array_equal(colors[:, :3], apply_colormap([100, -100, 0]))


def test_packed_rgb_declared_float32_gives_bgr_bytes_as_colour() -> None:
    rec = records({"x": ("<f4", 0), "y": ("<f4", 4), "z": ("<f4", 8), "rgb": ("<u4", 16)}, 32, 2)
    rec["x"], rec["y"], rec["z"] = XYZ[:2].T
    rec["rgb"] = [0x00A0B0C0, 0x00010203]  # bytes in memory: B, G, R, 0 (PCL's packing)
    fields = [
        field("x", 0, FLOAT32),
        field("y", 4, FLOAT32),
        field("z", 8, FLOAT32),
        field("rgb", 16, FLOAT32),
    ]
    positions, colors, _ = convert(cloud(rec.tobytes(), fields, 2, 32))
    np.testing.assert_array_equal(positions, XYZ[:2])
    np.testing.assert_array_equal(colors, [[0xA0, 0xB0, 0xC0, 255], [1, 2, 3, 255]])


def test_packed_rgba_uint32_keeps_alpha() -> None:
    rec = records({"x": ("<f4", 0), "y": ("<f4", 4), "z": ("<f4", 8), "rgba": ("<u4", 12)}, 16, 2)
    rec["x"], rec["y"], rec["z"] = XYZ[:2].T
    rec["rgba"] = [0x80FF8000, 0x10203040]
    fields = [
        field("x", 0, FLOAT32),
        field("y", 4, FLOAT32),
        field("z", 8, FLOAT32),
        field("rgba", 12, UINT32),
    ]
    _, colors, _ = convert(cloud(rec.tobytes(), fields, 2, 16))
    np.testing.assert_array_equal(colors, [[0xFF, 0x80, 0x00, 0x80], [0x20, 0x30, 0x40, 0x10]])


def test_separate_uint8_channels_with_count_gt_1_field_between() -> None:
    layout = {
        "x": ("<f4", 0),
        "y": ("<f4", 4),
        "z": ("<f4", 8),
        "normal": ("<3f4", 12),
        "r": ("u1", 24),
        "g": ("u1", 25),
        "b": ("u1", 26),
    }
    rec = records(layout, 28, 3)
    rec["x"], rec["y"], rec["z"] = XYZ.T
    rec["normal"] = np.nan
    rec["r"], rec["g"], rec["b"] = [10, 20, 30], [40, 50, 60], [70, 80, 90]
    fields = [
        field("x", 0, FLOAT32),
        field("y", 4, FLOAT32),
        field("z", 8, FLOAT32),
        field("normal", 12, FLOAT32, 3),
        field("r", 24, UINT8),
        field("g", 25, UINT8),
        field("b", 26, UINT8),
    ]
    message = cloud(rec.tobytes(), fields, 3, 28)
    positions, colors, _ = convert(message)
    np.testing.assert_array_equal(positions, XYZ)
    np.testing.assert_array_equal(colors, [[10, 40, 70, 255], [20, 50, 80, 255], [30, 60, 90, 255]])
    with pytest.raises(ConvertError, match=r"/cloud.*'normal'.*count > 1"):
        convert(message, color_field="normal")


def test_organised_2x3_cloud_with_row_padding() -> None:
    rec = records({"x": ("<f4", 0), "y": ("<f4", 4), "z": ("<f4", 8)}, 12, 6)
    grid = np.arange(18, dtype=np.float32).reshape(6, 3)
    rec["x"], rec["y"], rec["z"] = grid.T
    pad = b"\xff" * 8  # NaN-looking garbage at each row end
    data = rec[:3].tobytes() + pad + rec[3:].tobytes() + pad
    fields = [field("x", 0, FLOAT32), field("y", 4, FLOAT32), field("z", 8, FLOAT32)]
    positions, _, _ = convert(cloud(data, fields, 3, 12, height=2, row_step=44))
    np.testing.assert_array_equal(positions, grid)


def test_nan_and_inf_points_dropped_with_colours_aligned() -> None:
    rec = records({"x": ("<f4", 0), "y": ("<f4", 4), "z": ("<f4", 8), "rgb": ("<u4", 12)}, 16, 4)
    rec["x"] = [1.0, np.nan, 3.0, 4.0]
    rec["y"] = [0.0, 0.0, np.inf, 1.0]
    rec["z"] = 2.0
    rec["rgb"] = [0x00110000, 0x00220000, 0x00330000, 0x00440000]
    fields = [
        field("x", 0, FLOAT32),
        field("y", 4, FLOAT32),
        field("z", 8, FLOAT32),
        field("rgb", 12, FLOAT32),
    ]
    positions, colors, _ = convert(cloud(rec.tobytes(), fields, 4, 16))
    np.testing.assert_array_equal(positions, [[1.0, 0.0, 2.0], [4.0, 1.0, 2.0]])
    np.testing.assert_array_equal(colors[:, 0], [0x11, 0x44])


def test_colormap_over_kept_points_only_with_options() -> None:
    rec = records(
        {"x": ("<f4", 0), "y": ("<f4", 4), "z": ("<f4", 8), "intensity": ("<f4", 12)}, 16, 3
    )
    rec["x"] = [0.0, np.nan, 2.0]
    rec["intensity"] = [5.0, 1000.0, 15.0]  # the dropped point must not stretch the range
    fields = [
        field("x", 0, FLOAT32),
        field("y", 4, FLOAT32),
        field("z", 8, FLOAT32),
        field("intensity", 12, FLOAT32),
    ]
    message = cloud(rec.tobytes(), fields, 3, 16)
    _, colors, points = convert(message, colormap="gray", radius=0.05)
    np.testing.assert_array_equal(colors[:, :3], [[0, 0, 0], [255, 255, 255]])
    np.testing.assert_allclose(flat(points.radii), [0.05])
    _, by_x, _ = convert(message, color_field="x", colormap="gray", color_min=0.0, color_max=4.0)
    np.testing.assert_array_equal(by_x[:, 0], [0, 127])


def test_bad_layouts_raise_convert_error_naming_topic() -> None:
    xy = [field("x", 0, FLOAT32), field("y", 4, FLOAT32)]
    with pytest.raises(ConvertError, match=r"/cloud.*no z field"):
        convert(cloud(bytes(8), xy, 1, 8))
    xyz = [*xy, field("z", 8, FLOAT32)]
    with pytest.raises(ConvertError, match=r"/cloud.*needs 24 bytes.*has 20"):
        convert(cloud(bytes(20), xyz, 2, 12))
    with pytest.raises(ConvertError, match=r"/cloud.*'z'.*does not fit in point_step 10"):
        convert(cloud(bytes(10), xyz, 1, 10))
    with pytest.raises(ConvertError, match=r"/cloud.*datatype 9"):
        convert(cloud(bytes(12), [*xy, field("z", 8, 9)], 1, 12))
    with pytest.raises(ConvertError, match=r"/cloud.*color_field 'rgb'.*x, y, z"):
        convert(cloud(bytes(12), xyz, 1, 12), color_field="rgb")
    with pytest.raises(ConvertError, match=r"/cloud: unknown colormap 'rainbow'"):
        convert(cloud(bytes(12), xyz, 1, 12), colormap="rainbow")
    with pytest.raises(ConvertError, match=r"/cloud.*row_step 20 is shorter than a row of 2"):
        convert(cloud(bytes(44), xyz, 2, 12, height=2, row_step=20))


def test_single_row_cloud_ignores_a_zero_row_step() -> None:
    xyz = [field("x", 0, FLOAT32), field("y", 4, FLOAT32), field("z", 8, FLOAT32)]
    positions, _, _ = convert(cloud(XYZ.tobytes(), xyz, 3, 12, row_step=0))
    np.testing.assert_array_equal(positions, XYZ)


def test_float_colour_channels_all_nan_give_black_without_numpy_warnings() -> None:
    rec = records({"x": ("<f4", 0), "y": ("<f4", 4), "z": ("<f4", 8), "r": ("<f4", 12),
                   "g": ("<f4", 16), "b": ("<f4", 20)}, 24, 1)
    rec["r"] = rec["g"] = rec["b"] = np.nan
    fields = [field(name, 4 * i, FLOAT32) for i, name in enumerate("xyzrgb")]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, colors, _ = convert(cloud(rec.tobytes(), fields, 1, 24))
    np.testing.assert_array_equal(colors, [[0, 0, 0, 255]])


def test_empty_cloud_and_empty_frame_id() -> None:
    xyz = [field("x", 0, FLOAT32), field("y", 4, FLOAT32), field("z", 8, FLOAT32)]
    message = cloud(b"", xyz, 0, 12, frame_id="")
    item = log_item(convert_pointcloud2(message, make_ctx("/cloud")), PATH)
    assert [type(a) for a in item.archetypes] == [rr.Points3D]
    assert flat(archetype(item, rr.Points3D).positions, 3).shape == (0, 3)


def test_real_synthetic_cloud_matches_per_field_reference(shared_data: Path) -> None:
    bag = shared_data / "ros_numpy_msgs_synthetic" / "ros_numpy_test.bag"
    (message,) = read_topic(bag, "/pointcloud")
    assert (message.width, message.height, message.point_step) == (100, 1, 15)
    raw = message.data.tobytes()
    offsets = {f.name: f.offset for f in message.fields}

    rows = np.frombuffer(raw, dtype=np.uint8).reshape(100, 15)

    def column(name: str, dtype: str) -> npt.NDArray[Any]:
        size = np.dtype(dtype).itemsize
        chunk = rows[:, offsets[name] : offsets[name] + size].copy()
        return np.frombuffer(chunk.tobytes(), dtype=dtype)

    expected_xyz = np.stack([column(a, "<f4") for a in "xyz"], axis=-1)
    expected_rgb = np.stack([column(c, "u1") for c in "rgb"], axis=-1)
    keep = np.isfinite(expected_xyz).all(axis=1)
    positions, colors, _ = convert(message)
    np.testing.assert_array_equal(positions, expected_xyz[keep])
    np.testing.assert_array_equal(colors[:, :3], expected_rgb[keep])
    assert keep.sum() == len(positions) > 0
    item = log_item(convert_pointcloud2(message, make_ctx("/cloud")), PATH)
    assert not any(isinstance(a, rr.CoordinateFrame) for a in item.archetypes)  # empty frame_id


# --- the fast paths against a per-point reference -------------------------------------------------
#
# The converter reads x, y, z as one 12-byte record per point (or views them in place), filters
# non-finite points only when there are any and packs colours into words. The reference below
# reads each point with struct, as ROS 1's point_cloud2.read_points does, on clouds that have
# every layout those paths distinguish, with NaN/inf coordinates sprinkled in.

POINTS = 257


def reference(
    data: bytes, offsets: dict[str, int], formats: dict[str, str], point_step: int,
    packed: str | None, *, width: int, height: int = 1, row_step: int | None = None,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.uint8]]:
    """Positions and RGBA of the points with finite x, y, z, one point at a time."""
    row_step = width * point_step if row_step is None else row_step
    positions, colors = [], []
    for row in range(height):
        for col in range(width):
            start = row * row_step + col * point_step
            xyz = [struct.unpack_from(formats[a], data, start + offsets[a])[0] for a in "xyz"]
            if not all(math.isfinite(v) for v in xyz):
                continue
            positions.append(xyz)
            if packed is not None:
                order = formats["x"][0]
                (word,) = struct.unpack_from(order + "I", data, start + offsets[packed])
                alpha = word >> 24 if packed == "rgba" else 255
                colors.append([(word >> 16) & 0xFF, (word >> 8) & 0xFF, word & 0xFF, alpha])
    return (np.array(positions, dtype=np.float32).reshape(-1, 3),
            np.array(colors, dtype=np.uint8).reshape(-1, 4))


# name: (layout {field: (numpy format, offset)}, point_step, packed colour field or None)
LAYOUTS = {
    "xyz only, 12-byte points (viewed in place)": (
        {"x": ("<f4", 0), "y": ("<f4", 4), "z": ("<f4", 8)}, 12, None),
    "PCL XYZRGB, 32-byte points with padding": (
        {"x": ("<f4", 0), "y": ("<f4", 4), "z": ("<f4", 8), "rgb": ("<u4", 16)}, 32, "rgb"),
    "xyz at offset 4 after an intensity, rgba packed": (
        {"i": ("<f4", 0), "x": ("<f4", 4), "y": ("<f4", 8), "z": ("<f4", 12),
         "rgba": ("<u4", 16)}, 20, "rgba"),
    "big-endian float32 with rgb": (
        {"x": (">f4", 0), "y": (">f4", 4), "z": (">f4", 8), "rgb": (">u4", 12)}, 16, "rgb"),
    "big-endian xyz only, 12-byte points": (
        {"x": (">f4", 0), "y": (">f4", 4), "z": (">f4", 8)}, 12, None),
    "float64 positions": (
        {"x": ("<f8", 0), "y": ("<f8", 8), "z": ("<f8", 16), "rgb": ("<u4", 24)}, 32, "rgb"),
    "y before x (not adjacent in order)": (
        {"y": ("<f4", 0), "x": ("<f4", 4), "z": ("<f4", 8), "rgb": ("<u4", 12)}, 16, "rgb"),
}


def random_cloud_bytes(
    layout: dict[str, tuple[str, int]], point_step: int, n: int, seed: int
) -> bytes:
    rng = np.random.default_rng(seed)
    rec = records(layout, point_step, n)
    for axis in "xyz":
        values = rng.normal(0.0, 10.0, n)
        values[rng.random(n) < 0.05] = np.nan
        values[rng.random(n) < 0.02] = rng.choice([np.inf, -np.inf])
        rec[axis] = values
    for name in ("rgb", "rgba", "i"):
        if name in layout:
            rec[name] = rng.integers(0, 1 << 32, n, dtype=np.uint64) if name != "i" else 1.0
    raw = bytearray(rec.tobytes())
    used = np.zeros(point_step, dtype=bool)
    for fmt, offset in layout.values():
        used[offset : offset + np.dtype(fmt).itemsize] = True
    padding = np.flatnonzero(~used)
    view = np.frombuffer(raw, dtype=np.uint8).reshape(n, point_step)
    view[:, padding] = 0xFF  # padding must never be read (0xFF.. is a NaN as a float)
    return bytes(raw)


@pytest.mark.parametrize("name", LAYOUTS)
def test_fast_paths_match_a_per_point_reference(name: str) -> None:
    layout, point_step, packed = LAYOUTS[name]
    data = random_cloud_bytes(layout, point_step, POINTS, seed=len(name))
    datatypes = {"f4": FLOAT32, "f8": FLOAT64, "u4": FLOAT32}  # packed colour declared FLOAT32
    fields = [field(n, o, datatypes[f[1:]]) for n, (f, o) in layout.items()]
    big = layout["x"][0].startswith(">")
    offsets = {n: o for n, (_, o) in layout.items()}
    formats = {n: f[0] + {"f4": "f", "f8": "d", "u4": "I"}[f[1:]] for n, (f, _) in layout.items()}
    expected_xyz, expected_rgba = reference(data, offsets, formats, point_step, packed,
                                            width=POINTS)
    positions, colors, _ = convert(cloud(data, fields, POINTS, point_step, bigendian=big))
    assert 0 < len(expected_xyz) < POINTS  # some points were invalid, most were not
    np.testing.assert_array_equal(positions, expected_xyz)
    assert colors.shape == (len(expected_xyz), 4)
    if packed is not None:
        np.testing.assert_array_equal(colors, expected_rgba)


def test_organised_cloud_with_padded_rows_and_nans_matches_reference() -> None:
    layout, point_step, packed = LAYOUTS["PCL XYZRGB, 32-byte points with padding"]
    width, height, row_step = 40, 5, 40 * 32 + 24
    rows = [random_cloud_bytes(layout, point_step, width, seed=row) for row in range(height)]
    data = b"".join(row + b"\xff" * 24 for row in rows)
    fields = [field(n, o, FLOAT32) for n, (_, o) in layout.items()]
    offsets = {n: o for n, (_, o) in layout.items()}
    formats = {"x": "<f", "y": "<f", "z": "<f", "rgb": "<I"}
    expected_xyz, expected_rgba = reference(data, offsets, formats, point_step, packed,
                                            width=width, height=height, row_step=row_step)
    message = cloud(data, fields, width, point_step, height=height, row_step=row_step)
    positions, colors, _ = convert(message)
    np.testing.assert_array_equal(positions, expected_xyz)
    np.testing.assert_array_equal(colors, expected_rgba)


def test_all_finite_12_byte_cloud_reaches_rerun_without_a_copy() -> None:
    positions = np.random.default_rng(1).normal(size=(1000, 3)).astype(np.float32)
    data = np.frombuffer(positions.tobytes(), dtype=np.uint8)
    fields = [field("x", 0, FLOAT32), field("y", 4, FLOAT32), field("z", 8, FLOAT32)]
    message = cloud(b"", fields, 1000, 12)
    message.data = data
    item = log_item(convert_pointcloud2(message, make_ctx("/cloud")), PATH)
    arrow = archetype(item, rr.Points3D).positions.as_arrow_array()
    values = arrow.flatten()
    assert values.buffers()[1].address == data.ctypes.data  # the message's own bytes
    np.testing.assert_array_equal(values.to_numpy().reshape(-1, 3), positions)


# Declared sizes a corrupt or hostile publisher may send, each in a cloud of 12 bytes of data:
# (topic, height, width, point_step, row_step, extra field (name, offset, count) or None, the
# dispatcher's warning). Before, the last four raised numpy's bare "integer won't fit into a C
# int" / "dtype size in bytes must fit into a C int" ValueError, naming nothing.
HOSTILE_SIZES = [
    ("/billion", 1, 10**9, 12, 0, None,
     "PointCloud2 declares 1x1000000000 points with point_step 12 and row_step 12000000000, "
     "which needs 12000000000 bytes, but data has 12 bytes; the message is truncated or its "
     "sizes are wrong"),
    ("/tall", 2**32 - 1, 1, 12, 2**32 - 1, None,
     "PointCloud2 declares 4294967295x1 points with point_step 12 and row_step 4294967295, "
     f"which needs {(2**32 - 2) * (2**32 - 1) + 12} bytes, but data has 12 bytes; the message "
     "is truncated or its sizes are wrong"),
    ("/step", 1, 1, 2**32 - 1, 2**32 - 1, None,
     "PointCloud2 point_step 4294967295 is over 65536 bytes per point, more than any point "
     "type holds; the message is corrupt"),
    ("/empty_step", 0, 2**32 - 1, 2**31, 0, None,
     "PointCloud2 point_step 2147483648 is over 65536 bytes per point, more than any point "
     "type holds; the message is corrupt"),
    ("/offset", 1, 1, 12, 12, ("intensity", 2**32 - 5, 1),
     "PointCloud2 field 'intensity' (offset 4294967291, 4 bytes) does not fit in point_step 12"),
    ("/count", 1, 1, 12, 12, ("intensity", 12, 2**30),
     "PointCloud2 field 'intensity' (offset 12, 4294967296 bytes) does not fit in point_step 12"),
]


def cloud_cdr(data: bytes, fields: list[Any], *, height: int, width: int, point_step: int,
              row_step: int, stamp_ns: int = 1_000_000_000) -> bytes:
    message = msg("sensor_msgs/msg/PointCloud2", header=header("lidar", stamp_ns), height=height,
                  width=width, fields=fields, is_bigendian=False, point_step=point_step,
                  row_step=row_step, data=np.frombuffer(data, dtype=np.uint8), is_dense=False)
    return bytes(STORE.serialize_cdr(message, CLOUD))


def test_hostile_declared_sizes_are_refused_naming_the_topic_beside_good_clouds(
    reliability: Record,
) -> None:
    xyz = [field("x", 0, FLOAT32), field("y", 4, FLOAT32), field("z", 8, FLOAT32)]
    sink = RecordingSink()
    dispatcher = Dispatcher(sink, strict=False)
    good = np.arange(9, dtype=np.float32).reshape(3, 3)
    tracemalloc.start()
    try:
        for step, (topic, height, width, point_step, row_step, extra, _) in enumerate(HOSTILE_SIZES):
            fields = xyz if extra is None else [*xyz, field(extra[0], extra[1], FLOAT32, extra[2])]
            bad = cloud_cdr(bytes(12), fields, height=height, width=width,
                            point_step=point_step, row_step=row_step)
            stamp = 1_000_000_000 * (step + 1)
            dispatcher.dispatch([
                RawMessage(ROBOT, topic, CLOUD, bad, log_ns=stamp),
                RawMessage(ROBOT, "/cloud", CLOUD, cloud_cdr(
                    (good + step).tobytes(), xyz, height=1, width=3, point_step=12, row_step=36,
                    stamp_ns=stamp), log_ns=stamp),
            ])
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    dispatcher.close()
    warnings = sink.warnings()
    assert warnings == [
        f"[{ROBOT}] {topic}: {text} (further ConvertErrors on this topic are counted, not shown)"
        for topic, *_, text in HOSTILE_SIZES
    ]
    for topic, *_ in HOSTILE_SIZES:
        counters = dispatcher.counters[(ROBOT, topic)]
        assert (counters.received, counters.converted, counters.dropped) == (1, 0, 1)
    clouds = [flat(archetype(entry, rr.Points3D).positions, 3) for entry, _ in sink.logged
              if isinstance(entry, LogItem) and entry.path == f"/{ROBOT}/cloud"]
    assert len(clouds) == len(HOSTILE_SIZES)
    for step, positions in enumerate(clouds):
        np.testing.assert_array_equal(positions, good + step)
    assert peak < 16 << 20  # nothing of the declared sizes was allocated
    reliability("Hostile input", "PointCloud2 declaring 10^9 points, a 4294967295-row cloud, "
                "point_step 2^32-1 and 2^31, a field at offset 2^32-5 and one of count 2^30, "
                "each in 12 bytes of data", tried=f"{len(HOSTILE_SIZES)} messages",
                survived=f"host (traced peak {peak / 2**20:.1f} MB); each refused with a warning "
                f"naming its topic and sizes; {len(clouds)} of {len(HOSTILE_SIZES)} good clouds "
                "beside them converted with exact positions",
                lost=f"the {len(HOSTILE_SIZES)} hostile messages only")
