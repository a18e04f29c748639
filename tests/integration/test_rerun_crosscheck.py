"""Swanky against Rerun's own ROS 2 importer, on one rosbag2 MCAP both can read.

The bag is written here with rosbags (storage MCAP) and holds every common type that both
`rerun mcap convert` (Rerun's Rust importer, an independent CDR decoder and converter) and
Swanky turn into Rerun data. Both .rrd files are read back and compared value by value, and
both are compared with the ground truth: the pixels, points and numbers written into the bag.

Where the two differ on purpose, the difference itself is asserted and explained next to it,
so a change on either side shows up here. Entity paths differ by design (Swanky puts every
topic under ``/<robot>`` and names frames ``<robot>/<frame_id>``; some types are laid out
differently): each comparison names both entities explicitly.
"""

from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from host_bridge.cli import main as host_main
from tests.rrd import entity_rows

pytestmark = pytest.mark.integration

RERUN = Path(sys.executable).parent / "rerun"
STORE = get_typestore(Stores.ROS2_HUMBLE)
T = STORE.types
ROBOT = "robot"
WIDTH, HEIGHT = 6, 4
STAMP_SEC, STAMP_NANOSEC = 1_700_000_000, 250_000_000
STAMP_NS = STAMP_SEC * 1_000_000_000 + STAMP_NANOSEC
LOG_NS = STAMP_NS + 40_000_000  # the bag's record time: a little after the header stamp

# Image encodings and bytes per pixel. Rows are unpadded; nv12 adds half as many chroma rows.
PIXEL_BYTES = {
    "rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "rgb16": 6, "bgra16": 8, "8UC3": 3,
    "yuyv": 2, "nv12": 1, "bayer_rggb8": 1,
    "16UC1": 2, "16SC1": 2, "32SC1": 4, "32FC1": 4, "64FC1": 8,
    "mono8": 1, "8UC1": 1, "8SC1": 1, "mono16": 2,
    "yuv422": 2,
}
SAME_COLOR = ("rgb8", "bgr8", "rgba8", "bgra8", "rgb16", "bgra16", "8UC3", "yuyv", "nv12",
              "bayer_rggb8")
SAME_DEPTH = ("16UC1", "16SC1", "32SC1", "32FC1", "64FC1")
GREY_NOT_DEPTH = ("mono8", "8UC1", "8SC1", "mono16")
FLOAT_DEPTH = {"32FC1": np.float32, "64FC1": np.float64}

IMAGE_FORMAT_KEYS = ("width", "height", "color_model", "channel_datatype", "pixel_format")

CAMERA_K = [525.0, 0.0, 319.5, 0.0, 526.0, 239.5, 0.0, 0.0, 1.0]
# (parent, child, translation, rotation xyzw, stamp offset ns) of the two /tf messages' transforms.
TF = [
    ("odom", "base_link", (1.0, 2.0, 0.0), (0.0, 0.0, 0.6, 0.8), 0),
    ("map", "odom", (-0.5, 0.25, 0.0), (0.0, 0.0, 0.0, 1.0), 7_000_000),
]
TF_STATIC = [("base_link", "laser", (0.1, 0.0, 0.2), (0.0, 0.0, 1.0, 0.0))]
CLOUD_XYZ = [(0.0, 1.0, 2.0), (1.5, -1.0, 0.5), (float("nan"), 0.0, 0.0), (-2.0, 0.25, 1.0)]
CLOUD_RGB = [0x00FF8000, 0x000080FF, 0x00123456, 0x0000FF00]
BATTERY = {"voltage": 12.5, "current": -1.25, "charge": 2.0, "percentage": 0.75,
           "temperature": 31.5}
CELLS = [4.125, 4.0]
JOINTS = {"shoulder": 0.5, "elbow": -0.25}
URDF = """<robot name="arm">
  <link name="base_link"/><link name="upper"/><link name="lower"/>
  <joint name="shoulder" type="revolute"><parent link="base_link"/><child link="upper"/>
    <axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="elbow" type="revolute"><parent link="upper"/><child link="lower"/>
    <origin xyz="0 0 0.5"/><axis xyz="0 1 0"/><limit lower="-3" upper="3" effort="1" velocity="1"/>
  </joint>
</robot>
"""
# topic -> (type, value) of the one-number sensor messages Rerun imports as Measurements.
MEASUREMENTS = {
    "/temperature": ("sensor_msgs/msg/Temperature", "temperature", 21.5),
    "/pressure": ("sensor_msgs/msg/FluidPressure", "fluid_pressure", 101325.0),
    "/illuminance": ("sensor_msgs/msg/Illuminance", "illuminance", 320.0),
    "/humidity": ("sensor_msgs/msg/RelativeHumidity", "relative_humidity", 0.375),
}
NUMBERS = {"/speed": ("std_msgs/msg/Float64", 1.5), "/count": ("std_msgs/msg/Int32", -7)}
IMU_GYRO, IMU_ACCEL, IMU_Q = (0.125, -0.25, 0.5), (0.5, 1.0, 9.75), (0.0, 0.0, 0.6, 0.8)
RANGE = (1.25, 0.125, 4.0)  # range, min_range, max_range
FIX = (39.951, -75.19, 12.5)
LOG_WARN = 30  # rcl_interfaces/Log.WARN


@dataclass(frozen=True)
class Bag:
    """What was written (the ground truth) and the two tools' readings of it."""

    pixels: dict[str, npt.NDArray[np.uint8]]
    jpeg: bytes
    rerun: dict[str, list[dict[str, Any]]]
    swanky: dict[str, list[dict[str, Any]]]


def image_topic(encoding: str) -> str:
    return f"/image_{encoding.lower()}"


def ours(topic: str) -> str:
    """Swanky's entity of a topic: under the robot's name."""
    return f"/{ROBOT}{topic}"


def frame(name: str) -> str:
    """Swanky's name of a ROS frame; Rerun's importer keeps the bare frame_id."""
    return f"{ROBOT}/{name}"


def header(frame_id: str, offset_ns: int = 0) -> Any:
    ns = STAMP_NANOSEC + offset_ns
    stamp = T["builtin_interfaces/msg/Time"](sec=STAMP_SEC, nanosec=ns)
    return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)


def pixel_bytes(encoding: str, rng: np.random.Generator) -> npt.NDArray[np.uint8]:
    rows = HEIGHT * 3 // 2 if encoding == "nv12" else HEIGHT
    if encoding in FLOAT_DEPTH:  # real distances, not random bit patterns (NaNs)
        depth = rng.uniform(0.3, 8.0, size=(rows, WIDTH)).astype(FLOAT_DEPTH[encoding])
        return depth.view(np.uint8).reshape(-1)
    return rng.integers(0, 256, size=rows * WIDTH * PIXEL_BYTES[encoding], dtype=np.uint8)


def write_bag(path: Path) -> tuple[dict[str, npt.NDArray[np.uint8]], bytes]:
    rng = np.random.default_rng(118)
    pixels = {encoding: pixel_bytes(encoding, rng) for encoding in PIXEL_BYTES}
    jpeg_ok, jpeg_array = cv2.imencode(".jpg", rng.integers(0, 256, (16, 16, 3), dtype=np.uint8))
    assert jpeg_ok
    jpeg = jpeg_array.tobytes()
    vector3, quaternion = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]

    def transform(parent: str, child: str, xyz: Any, q: Any, offset: int) -> Any:
        return T["geometry_msgs/msg/TransformStamped"](
            header=header(parent, offset), child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](
                translation=vector3(*xyz), rotation=quaternion(*q)),
        )

    messages: list[tuple[str, str, Any]] = []
    for encoding, data in pixels.items():
        step = WIDTH * PIXEL_BYTES[encoding]
        image = T["sensor_msgs/msg/Image"](
            header=header("camera_optical"), height=HEIGHT, width=WIDTH, encoding=encoding,
            is_bigendian=0, step=step, data=data,
        )
        messages.append((image_topic(encoding), "sensor_msgs/msg/Image", image))
    messages.append(("/camera/image_raw/compressed", "sensor_msgs/msg/CompressedImage",
                     T["sensor_msgs/msg/CompressedImage"](
                         header=header("camera_optical"), format="jpeg",
                         data=np.frombuffer(jpeg, np.uint8))))
    roi = T["sensor_msgs/msg/RegionOfInterest"](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    messages.append(("/camera/camera_info", "sensor_msgs/msg/CameraInfo",
                     T["sensor_msgs/msg/CameraInfo"](
                         header=header("camera_optical"), height=480, width=640,
                         distortion_model="plumb_bob", d=np.zeros(5), k=np.array(CAMERA_K),
                         r=np.eye(3).reshape(-1), p=np.zeros(12), binning_x=0, binning_y=0,
                         roi=roi)))
    cloud = np.zeros(len(CLOUD_XYZ), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                            ("rgb", "<u4")])
    cloud["x"], cloud["y"], cloud["z"] = np.array(CLOUD_XYZ, dtype=np.float32).T
    cloud["rgb"] = CLOUD_RGB
    field = T["sensor_msgs/msg/PointField"]
    messages.append(("/points", "sensor_msgs/msg/PointCloud2", T["sensor_msgs/msg/PointCloud2"](
        header=header("lidar"), height=1, width=len(cloud),
        # PCL declares the packed colour FLOAT32 (datatype 7), like x, y and z.
        fields=[field(name=n, offset=4 * i, datatype=7, count=1)
                for i, n in enumerate(("x", "y", "z", "rgb"))],
        is_bigendian=False, point_step=16, row_step=16 * len(cloud),
        data=cloud.view(np.uint8).reshape(-1), is_dense=False,
    )))
    tf_message = T["tf2_msgs/msg/TFMessage"]
    messages.append(("/tf", "tf2_msgs/msg/TFMessage",
                     tf_message(transforms=[transform(*TF[0])])))
    messages.append(("/tf", "tf2_msgs/msg/TFMessage",
                     tf_message(transforms=[transform(*TF[1])])))
    messages.append(("/tf_static", "tf2_msgs/msg/TFMessage",
                     tf_message(transforms=[transform(*t, 0) for t in TF_STATIC])))
    for topic, (msgtype, field_name, value) in MEASUREMENTS.items():
        messages.append((topic, msgtype, T[msgtype](
            header=header("env"), variance=0.0, **{field_name: value})))
    for topic, (msgtype, number) in NUMBERS.items():
        messages.append((topic, msgtype, T[msgtype](data=number)))
    messages.append(("/battery", "sensor_msgs/msg/BatteryState", T["sensor_msgs/msg/BatteryState"](
        header=header("battery"), capacity=3.0, design_capacity=3.0, power_supply_status=2,
        power_supply_health=1, power_supply_technology=2, present=True,
        cell_voltage=np.array(CELLS, np.float32), cell_temperature=np.zeros(0, np.float32),
        location="base", serial_number="sn", **BATTERY)))
    messages.append(("/joint_states", "sensor_msgs/msg/JointState", T["sensor_msgs/msg/JointState"](
        header=header(""), name=list(JOINTS), position=np.array(list(JOINTS.values())),
        velocity=np.zeros(0), effort=np.zeros(0))))
    zeros9 = np.zeros(9)
    messages.append(("/imu", "sensor_msgs/msg/Imu", T["sensor_msgs/msg/Imu"](
        header=header("imu_link"), orientation=quaternion(*IMU_Q), orientation_covariance=zeros9,
        angular_velocity=vector3(*IMU_GYRO), angular_velocity_covariance=zeros9,
        linear_acceleration=vector3(*IMU_ACCEL), linear_acceleration_covariance=zeros9)))
    messages.append(("/range", "sensor_msgs/msg/Range", T["sensor_msgs/msg/Range"](
        header=header("sonar"), radiation_type=0, field_of_view=0.5, min_range=RANGE[1],
        max_range=RANGE[2], range=RANGE[0])))
    messages.append(("/fix", "sensor_msgs/msg/NavSatFix", T["sensor_msgs/msg/NavSatFix"](
        header=header("gps"), status=T["sensor_msgs/msg/NavSatStatus"](status=0, service=1),
        latitude=FIX[0], longitude=FIX[1], altitude=FIX[2],
        position_covariance=np.diag([4.0, 4.0, 9.0]).reshape(-1), position_covariance_type=2)))
    log = T["rcl_interfaces/msg/Log"]
    messages.append(("/rosout", "rcl_interfaces/msg/Log", log(
        stamp=header("").stamp, level=LOG_WARN, name="planner", msg="no path", file="p.cpp",
        function="plan", line=42)))

    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections: dict[str, Any] = {}
        for topic, msgtype, msg in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=STORE)
            writer.write(connections[topic], LOG_NS, STORE.serialize_cdr(msg, msgtype))
    return pixels, jpeg


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Bag:
    tmp = tmp_path_factory.mktemp("crosscheck")
    pixels, jpeg = write_bag(tmp / "bag")
    (mcap,) = (tmp / "bag").glob("*.mcap")
    subprocess.run([str(RERUN), "mcap", "convert", str(mcap), "-o", str(tmp / "rerun.rrd")],
                   check=True, capture_output=True, timeout=120)
    urdf = tmp / "arm.urdf"
    urdf.write_text(URDF)
    argv = ["--bag", str(tmp / "bag"), "--robot", ROBOT, "--urdf", str(urdf),
            "--save", str(tmp / "swanky.rrd"), "--strict"]
    assert host_main(argv) == 0
    return Bag(pixels, jpeg, entity_rows(tmp / "rerun.rrd"), entity_rows(tmp / "swanky.rrd"))


def value(rows: dict[str, list[dict[str, Any]]], entity: str, column: str) -> Any:
    """The one logged value of ``column`` at ``entity`` (Rerun's importer spreads one message
    over several rows: channel info, frame, components)."""
    found = [row[column] for row in rows.get(entity, []) if row.get(column) is not None]
    assert len(found) == 1, f"{entity} {column}: {len(found)} rows hold it"
    return found[0]


def has(rows: dict[str, list[dict[str, Any]]], entity: str, column: str) -> bool:
    return any(row.get(column) is not None for row in rows.get(entity, []))


def time_of(rows: dict[str, list[dict[str, Any]]], entity: str, column: str) -> dict[str, int]:
    (row,) = [r for r in rows[entity] if r.get(column) is not None]
    return {name: row[name] for name in ("ros_time", "ros2_timestamp", "log_time",
                                         "message_log_time") if name in row}


# --- images --------------------------------------------------------------------------------------


def image_format(rows: dict[str, list[dict[str, Any]]], entity: str, archetype: str) -> dict[str, Any]:
    fmt = value(rows, entity, f"{archetype}:format")[0]
    return {key: fmt[key] for key in IMAGE_FORMAT_KEYS}


@pytest.mark.parametrize("encoding", SAME_COLOR)
def test_color_images_are_the_same_bytes_and_format_as_rerun_logs(bag: Bag, encoding: str) -> None:
    topic = image_topic(encoding)
    written = bag.pixels[encoding].tolist()
    assert value(bag.rerun, topic, "Image:buffer") == [written]
    assert value(bag.swanky, ours(topic), "Image:buffer") == [written]
    fmt = image_format(bag.swanky, ours(topic), "Image")
    assert fmt == image_format(bag.rerun, topic, "Image")
    assert (fmt["width"], fmt["height"]) == (WIDTH, HEIGHT)


@pytest.mark.parametrize("encoding", SAME_DEPTH)
def test_depth_images_are_the_same_bytes_and_scale_as_rerun_logs(bag: Bag, encoding: str) -> None:
    topic = image_topic(encoding)
    written = bag.pixels[encoding].tolist()
    assert value(bag.rerun, topic, "DepthImage:buffer") == [written]
    assert value(bag.swanky, ours(topic), "DepthImage:buffer") == [written]
    assert image_format(bag.swanky, ours(topic), "DepthImage") == image_format(
        bag.rerun, topic, "DepthImage")
    # Rerun's importer leaves the meter to the viewer's default (1 for float depth, 1000 for
    # integer depth); Swanky states the same REP 118 units explicitly, so config can change them.
    assert not has(bag.rerun, topic, "DepthImage:meter")
    expected_meter = 1.0 if encoding in FLOAT_DEPTH else 1000.0
    assert value(bag.swanky, ours(topic), "DepthImage:meter") == [expected_meter]


@pytest.mark.parametrize("encoding", GREY_NOT_DEPTH)
def test_mono_and_8_bit_single_channel_are_grey_images_where_rerun_shows_depth(
    bag: Bag, encoding: str
) -> None:
    # On purpose: REP 118 depth is 16UC1 (mm) or 32FC1 (m). mono8/mono16 are camera intensities
    # (IR, greyscale cameras) and 8-bit single channel is a mask or a grey image; shown as depth
    # they would be back-projected into 3D as nonsense distances. Same bytes, same pixel type.
    topic = image_topic(encoding)
    written = bag.pixels[encoding].tolist()
    assert value(bag.rerun, topic, "DepthImage:buffer") == [written]
    assert not has(bag.rerun, topic, "Image:buffer")
    assert value(bag.swanky, ours(topic), "Image:buffer") == [written]
    assert not has(bag.swanky, ours(topic), "DepthImage:buffer")
    rerun_format = image_format(bag.rerun, topic, "DepthImage")
    swanky_format = image_format(bag.swanky, ours(topic), "Image")
    assert swanky_format["color_model"] == 1  # L
    assert {k: v for k, v in swanky_format.items() if k != "color_model"} == {
        k: v for k, v in rerun_format.items() if k != "color_model"}


def test_uyvy_yuv422_is_converted_where_rerun_rejects_it(bag: Bag) -> None:
    # ROS "yuv422" is UYVY byte order, which Rerun has no pixel format for: its importer logs
    # no image at all (it only knows yuyv/yuv422_yuy2). Swanky swaps each byte pair into YUY2,
    # which decodes to exactly the colours OpenCV's own UYVY conversion gives.
    topic = image_topic("yuv422")
    assert not has(bag.rerun, topic, "Image:buffer")
    assert not has(bag.rerun, topic, "DepthImage:buffer")
    fmt = image_format(bag.swanky, ours(topic), "Image")
    assert fmt["pixel_format"] == image_format(bag.rerun, image_topic("yuyv"), "Image")[
        "pixel_format"]
    yuy2 = np.array(value(bag.swanky, ours(topic), "Image:buffer")[0], np.uint8)
    uyvy = bag.pixels["yuv422"]
    ours_rgb = cv2.cvtColor(yuy2.reshape(HEIGHT, WIDTH, 2), cv2.COLOR_YUV2RGB_YUY2)
    opencv_rgb = cv2.cvtColor(uyvy.reshape(HEIGHT, WIDTH, 2), cv2.COLOR_YUV2RGB_UYVY)
    np.testing.assert_array_equal(ours_rgb, opencv_rgb)


def test_jpeg_is_passed_through_unchanged_by_both(bag: Bag) -> None:
    topic = "/camera/image_raw/compressed"
    assert bytes(value(bag.rerun, topic, "EncodedImage:blob")[0]) == bag.jpeg
    assert bytes(value(bag.swanky, ours(topic), "EncodedImage:blob")[0]) == bag.jpeg
    # Rerun's importer lets the viewer sniff the media type; Swanky names it from the format.
    assert value(bag.swanky, ours(topic), "EncodedImage:media_type") == ["image/jpeg"]


def test_camera_info_gives_the_same_pinhole(bag: Bag) -> None:
    # Rerun logs the pinhole on the CameraInfo topic and puts images in a "<frame>_image_plane"
    # frame; Swanky logs it on the camera namespace so its images sit in the image plane by
    # entity path (see host_bridge/converters/camera.py for why).
    rerun_entity, swanky_entity = "/camera/camera_info", ours("/camera")
    k = value(bag.rerun, rerun_entity, "Pinhole:image_from_camera")
    assert value(bag.swanky, swanky_entity, "Pinhole:image_from_camera") == k
    # Both are column-major 3x3: fx, 0, 0, 0, fy, 0, cx, cy, 1.
    assert k == [list(np.array(CAMERA_K).reshape(3, 3).T.reshape(-1))]
    assert value(bag.swanky, swanky_entity, "Pinhole:resolution") == value(
        bag.rerun, rerun_entity, "Pinhole:resolution") == [[640.0, 480.0]]
    assert value(bag.rerun, rerun_entity, "Pinhole:parent_frame") == ["camera_optical"]
    assert value(bag.swanky, swanky_entity, "Pinhole:parent_frame") == [frame("camera_optical")]


# --- point clouds --------------------------------------------------------------------------------


def test_point_cloud_positions_match_and_colours_come_from_the_packed_word(bag: Bag) -> None:
    written = np.array(CLOUD_XYZ, dtype=np.float32)
    finite = [bool(np.isfinite(point).all()) for point in written]
    theirs = np.array(value(bag.rerun, "/points", "Points3D:positions"), dtype=np.float32)
    mine = np.array(value(bag.swanky, ours("/points"), "Points3D:positions"), dtype=np.float32)
    # Rerun's importer keeps NaN points; Swanky drops them (they cannot be drawn) with the same
    # mask for the colours. Every finite point is the same in both and as written.
    np.testing.assert_array_equal(theirs, written)
    np.testing.assert_array_equal(mine, written[finite])
    # Rerun's importer carries the packed "rgb" field as the float32 it is declared as, and
    # shows no colours; Swanky unpacks that same word into RGBA (0xRRGGBBAA, opaque).
    packed = np.array(value(bag.rerun, "/points", "Points3D:rgb"), np.float32).view(np.uint32)
    assert packed.tolist() == CLOUD_RGB
    assert not has(bag.rerun, "/points", "Points3D:colors")
    colours = value(bag.swanky, ours("/points"), "Points3D:colors")
    assert colours == [(word << 8) | 0xFF for word, keep in zip(CLOUD_RGB, finite, strict=True)
                       if keep]
    assert value(bag.rerun, "/points", "CoordinateFrame:frame") == ["lidar"]
    assert value(bag.swanky, ours("/points"), "CoordinateFrame:frame") == [frame("lidar")]


# --- transforms ----------------------------------------------------------------------------------


def transform_rows(rows: list[dict[str, Any]], prefix: str) -> list[tuple[Any, ...]]:
    found = []
    for row in rows:
        if row.get("Transform3D:child_frame") is None:
            continue
        parent, child = row["Transform3D:parent_frame"][0], row["Transform3D:child_frame"][0]
        assert parent.startswith(prefix)
        assert child.startswith(prefix)
        found.append((parent[len(prefix):], child[len(prefix):],
                      tuple(np.float32(row["Transform3D:translation"][0]).tolist()),
                      tuple(np.float32(row["Transform3D:quaternion"][0]).tolist())))
    return sorted(found)


def expected_transforms(table: list[Any]) -> list[tuple[Any, ...]]:
    return sorted((p, c, tuple(np.float32(t).tolist()), tuple(np.float32(q).tolist()))
                  for p, c, t, q, *_ in table)


def test_tf_gives_the_same_transforms(bag: Bag) -> None:
    expected = expected_transforms(TF)
    assert transform_rows(bag.rerun["/tf"], "") == expected
    assert transform_rows(bag.swanky[ours("/tf")], f"{ROBOT}/") == expected
    # Rerun's importer stamps /tf rows with the bag's log time only; Swanky also puts each
    # transform at its own header stamp on ros_time (what TF lookups use).
    stamps = sorted(r["ros_time"] for r in bag.swanky[ours("/tf")])
    assert stamps == [STAMP_NS + offset for *_, offset in TF]
    assert all("ros2_timestamp" not in r for r in bag.rerun["/tf"])


def test_tf_static_gives_the_same_transforms_logged_static(bag: Bag) -> None:
    expected = expected_transforms([(*t, 0) for t in TF_STATIC])
    assert transform_rows(bag.rerun["/tf_static"], "") == expected
    # Rerun's importer logs /tf_static on the timeline; Swanky logs it static (always valid,
    # also before the first message time), one entity per child frame.
    rows = [r for r in bag.swanky[ours("/tf_static/laser")] if "Transform3D:child_frame" in r]
    assert transform_rows(rows, f"{ROBOT}/") == expected
    assert all(r["static"] for r in rows)


# --- scalars and other numbers -------------------------------------------------------------------


@pytest.mark.parametrize("topic", MEASUREMENTS)
def test_environment_sensors_give_the_same_value(bag: Bag, topic: str) -> None:
    # Rerun's importer logs these as Measurements (value, variance, unit); Swanky plots the value
    # as Scalars on the same timelines.
    written = MEASUREMENTS[topic][2]
    assert value(bag.rerun, topic, "Measurements:values") == [written]
    assert value(bag.swanky, ours(topic), "Scalars:scalars") == [written]
    rerun_times = time_of(bag.rerun, topic, "Measurements:values")
    swanky_times = time_of(bag.swanky, ours(topic), "Scalars:scalars")
    assert rerun_times["ros2_timestamp"] == swanky_times["ros_time"] == STAMP_NS
    assert rerun_times["message_log_time"] == swanky_times["log_time"] == LOG_NS


@pytest.mark.parametrize("topic", NUMBERS)
def test_std_msgs_numbers_are_the_same_value(bag: Bag, topic: str) -> None:
    # Rerun's importer keeps std_msgs numbers as the decoded message (no plot); Swanky plots them.
    msgtype, written = NUMBERS[topic]
    column = msgtype.replace("/", ".") + ":message"
    assert value(bag.rerun, topic, column) == [{"data": written}]
    assert value(bag.swanky, ours(topic), "Scalars:scalars") == [float(written)]
    assert time_of(bag.swanky, ours(topic), "Scalars:scalars") == {"log_time": LOG_NS}


def test_battery_state_gives_the_same_series(bag: Bag) -> None:
    # Rerun: one entity, the series named by SeriesLines; Swanky: one entity per quantity.
    names = value(bag.rerun, "/battery", "SeriesLines:names")
    theirs = dict(zip(names, value(bag.rerun, "/battery", "Scalars:scalars"), strict=True))
    mine = {name: value(bag.swanky, ours(f"/battery/{name}"), "Scalars:scalars")[0]
            for name in names}
    expected = {name: float(np.float32(v)) for name, v in BATTERY.items()}
    assert theirs == mine == expected
    # Swanky also plots the per-cell voltages, which Rerun's importer leaves out.
    cells = value(bag.swanky, ours("/battery/cell_voltage"), "Scalars:scalars")
    assert cells == [float(np.float32(v)) for v in CELLS]


def test_joint_positions_are_the_same(bag: Bag) -> None:
    # Rerun: /joint_states/position with one series per joint; Swanky: /joint_states/<joint>/
    # position, and it moves the robot model's links by them.
    names = value(bag.rerun, "/joint_states/position", "SeriesLines:names")
    theirs = dict(zip(names, value(bag.rerun, "/joint_states/position", "Scalars:scalars"),
                      strict=True))
    mine = {name: value(bag.swanky, ours(f"/joint_states/{name}/position"), "Scalars:scalars")[0]
            for name in JOINTS}
    assert theirs == mine == JOINTS


def test_imu_gives_the_same_rates_accelerations_and_orientation(bag: Bag) -> None:
    names = value(bag.rerun, "/imu", "SeriesLines:names")
    theirs = dict(zip(names, value(bag.rerun, "/imu", "Scalars:scalars"), strict=True))
    gyro = value(bag.swanky, ours("/imu/angular_velocity"), "Scalars:scalars")
    accel = value(bag.swanky, ours("/imu/linear_acceleration"), "Scalars:scalars")
    assert [theirs[f"gyroscope/{axis}"] for axis in "xyz"] == gyro == list(IMU_GYRO)
    assert [theirs[f"accelerometer/{axis}"] for axis in "xyz"] == accel == list(IMU_ACCEL)
    # Rerun keeps the orientation as message data; Swanky turns the sensor's frame by it.
    assert value(bag.rerun, "/imu", "sensor_msgs.msg.Imu:orientation") == list(IMU_Q)
    rotation = value(bag.swanky, ours("/imu/orientation"), "Transform3D:quaternion")[0]
    np.testing.assert_allclose(rotation, IMU_Q, rtol=1e-6)


def test_range_gives_the_same_distance(bag: Bag) -> None:
    names = value(bag.rerun, "/range", "SeriesLines:names")
    theirs = dict(zip(names, value(bag.rerun, "/range", "Scalars:scalars"), strict=True))
    assert theirs["range"] == value(bag.swanky, ours("/range/range"), "Scalars:scalars")[0]
    assert theirs["range"] == RANGE[0]
    # Swanky draws the cone in the sensor frame instead of plotting the fixed limits.
    assert value(bag.swanky, ours("/range"), "CoordinateFrame:frame") == [frame("sonar")]


def test_navsatfix_gives_the_same_position_and_altitude(bag: Bag) -> None:
    position = [list(FIX[:2])]
    assert value(bag.rerun, "/fix", "GeoPoints:positions") == position
    assert value(bag.swanky, ours("/fix"), "GeoPoints:positions") == position
    assert value(bag.rerun, "/fix", "altitude") == [FIX[2]]
    assert value(bag.swanky, ours("/fix/altitude"), "Scalars:scalars") == [FIX[2]]
    # Swanky sizes the dot by the 1-sigma horizontal error (metres): sqrt(4) = 2.
    assert value(bag.swanky, ours("/fix"), "GeoPoints:radii") == [2.0]


def test_rosout_gives_the_same_text_and_level(bag: Bag) -> None:
    for rows, entity in ((bag.rerun, "/rosout"), (bag.swanky, ours("/rosout"))):
        assert value(rows, entity, "TextLog:text") == ["[planner] no path"]
        assert value(rows, entity, "TextLog:level") == ["WARN"]

