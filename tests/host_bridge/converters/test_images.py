"""Image and CompressedImage conversion: for every ROS image encoding, the pixels Rerun receives
(read back from the archetypes' Arrow arrays and interpreted as Rerun documents its formats)
equal an OpenCV reference conversion of the message's own bytes."""

from __future__ import annotations

import struct
import tracemalloc
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import pytest
import rerun as rr
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from host_bridge.converters.images import (
    MAX_DECODED_PIXELS,
    convert_compressed_image,
    convert_image,
)
from host_bridge.core.contract import ColumnsItem, LogEntry, LogItem
from host_bridge.errors import ConvertError
from host_bridge.pipeline.dispatch import Dispatcher
from robot_relay.wire import RawMessage
from tests.host_bridge.sensor_test_support import convert, convert_run, make_ctx
from tests.host_bridge.test_config import RecordingSink
from tests.reliability import Record

TYPESTORE = get_typestore(Stores.ROS2_HUMBLE)
T = TYPESTORE.types
ROBOT = "tb3"
RNG_SEED = 7

# --- helpers shared with test_camera -------------------------------------------------------------


def header(frame_id: str = "camera_optical_frame") -> Any:
    stamp = T["builtin_interfaces/msg/Time"](sec=12, nanosec=345)
    return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)


def first_message(bag: Path, topic: str) -> Any:
    with AnyReader([bag], default_typestore=TYPESTORE) as reader:
        connections = [c for c in reader.connections if c.topic == topic]
        for connection, _, raw in reader.messages(connections=connections):
            return reader.deserialize(raw, connection.msgtype)
    raise AssertionError(f"{topic} not in {bag}")


# --- local helpers -------------------------------------------------------------------------------

IMAGE_TOPIC = "/camera/image_raw"


def make_image(
    encoding: str,
    pixels: npt.NDArray[Any],
    *,
    width: int,
    height: int,
    pad: int = 0,
    bigendian: bool = False,
) -> Any:
    """An Image whose rows are ``pixels``' bytes (row-major) followed by ``pad`` junk bytes."""
    raw = np.ascontiguousarray(pixels)
    if bigendian:
        raw = raw.astype(raw.dtype.newbyteorder(">"))
    rows = raw.view(np.uint8).reshape(raw.shape[0], -1)
    padded = np.concatenate([rows, np.full((rows.shape[0], pad), 0xAB, np.uint8)], axis=1)
    return T["sensor_msgs/msg/Image"](
        header=header(),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=int(bigendian),
        step=padded.shape[1],
        data=padded.ravel(),
    )


def convert_one(msg: Any, **options: Any) -> Any:
    entries = convert_image(msg, make_ctx(IMAGE_TOPIC, options, robot=ROBOT, times={}))
    return only_archetype(entries, f"/{ROBOT}{IMAGE_TOPIC}")


def only_archetype(entries: list[LogEntry], path: str) -> Any:
    assert len(entries) == 1
    item = entries[0]
    assert isinstance(item, LogItem)
    assert item.path == path
    assert len(item.archetypes) == 1, "images carry no CoordinateFrame (see camera.py)"
    return item.archetypes[0]


def pylist(batch: Any) -> list[Any]:
    """A component batch's values as Python objects (what Rerun would store)."""
    assert batch is not None
    values: list[Any] = batch.as_arrow_array().to_pylist()
    return values


def arrow_address(batch: Any) -> int:
    """Address of the bytes behind a blob batch, to tell a view of msg.data from a copy."""
    address: int = batch.as_arrow_array().values.buffers()[1].address
    return address


def received_bytes(archetype: Any) -> npt.NDArray[np.uint8]:
    batch: Any = archetype.blob if isinstance(archetype, rr.EncodedImage) else archetype.buffer
    values: npt.NDArray[np.uint8] = batch.as_arrow_array().flatten().to_numpy()
    return values


def image_format(archetype: Any) -> dict[str, Any]:
    return archetype.format.as_arrow_array()[0].as_py()  # type: ignore[no-any-return]


def received_pixels(archetype: Any) -> npt.NDArray[Any]:
    """(h, w, c) channel values as stored, for colour-model and depth images."""
    fmt = image_format(archetype)
    dtype = rr.ChannelDatatype(fmt["channel_datatype"]).to_np_dtype()
    channels = 1 if fmt["color_model"] is None else rr.ColorModel(fmt["color_model"]).num_channels()
    return received_bytes(archetype).view(dtype).reshape(fmt["height"], fmt["width"], channels)


_RGB_ORDER = {
    rr.ColorModel.L: [0],
    rr.ColorModel.RGB: [0, 1, 2],
    rr.ColorModel.RGBA: [0, 1, 2, 3],
    rr.ColorModel.BGR: [2, 1, 0],
    rr.ColorModel.BGRA: [2, 1, 0, 3],
}


def seen_as_rgb(archetype: Any) -> npt.NDArray[Any]:
    """What the viewer shows, in R, G, B[, A] order (or L), per Rerun's documented formats."""
    fmt = image_format(archetype)
    width, height = fmt["width"], fmt["height"]
    if fmt["pixel_format"] is not None:
        buf = received_bytes(archetype)
        pixel_format = rr.PixelFormat(fmt["pixel_format"])
        if pixel_format == rr.PixelFormat.YUY2:
            return cv2.cvtColor(buf.reshape(height, width, 2), cv2.COLOR_YUV2RGB_YUY2)
        assert pixel_format == rr.PixelFormat.NV12, pixel_format
        return cv2.cvtColor(buf.reshape(height * 3 // 2, width), cv2.COLOR_YUV2RGB_NV12)
    return received_pixels(archetype)[..., _RGB_ORDER[rr.ColorModel(fmt["color_model"])]]


def random_pixels(shape: tuple[int, ...], dtype: Any) -> npt.NDArray[Any]:
    rng = np.random.default_rng(RNG_SEED)
    info = np.iinfo(dtype) if np.dtype(dtype).kind in "iu" else None
    if info is None:
        return rng.uniform(0.2, 9.0, shape).astype(dtype)
    return rng.integers(info.min, info.max, shape, dtype=dtype, endpoint=True)


H, W = 6, 8


def _same(raw: npt.NDArray[Any]) -> npt.NDArray[Any]:
    return raw if raw.ndim == 3 else raw[..., None]


def _cv(code: int) -> Callable[[npt.NDArray[Any]], npt.NDArray[Any]]:
    return lambda raw: cv2.cvtColor(raw, code)


# encoding -> (numpy dtype of a channel, shape of the message's pixel array, OpenCV reference)
COLOR_CASES: dict[str, tuple[Any, tuple[int, ...], Callable[[npt.NDArray[Any]], npt.NDArray[Any]]]] = {
    "rgb8": (np.uint8, (H, W, 3), _same),
    "rgba8": (np.uint8, (H, W, 4), _same),
    "rgb16": (np.uint16, (H, W, 3), _same),
    "rgba16": (np.uint16, (H, W, 4), _same),
    "bgr8": (np.uint8, (H, W, 3), _cv(cv2.COLOR_BGR2RGB)),
    "bgra8": (np.uint8, (H, W, 4), _cv(cv2.COLOR_BGRA2RGBA)),
    "bgr16": (np.uint16, (H, W, 3), _cv(cv2.COLOR_BGR2RGB)),
    "bgra16": (np.uint16, (H, W, 4), _cv(cv2.COLOR_BGRA2RGBA)),
    "mono8": (np.uint8, (H, W), _same),
    "mono16": (np.uint16, (H, W), _same),
    "8UC1": (np.uint8, (H, W), _same),
    "8SC1": (np.int8, (H, W), _same),
    "8UC3": (np.uint8, (H, W, 3), _cv(cv2.COLOR_BGR2RGB)),
    "8UC4": (np.uint8, (H, W, 4), _cv(cv2.COLOR_BGRA2RGBA)),
    "16UC3": (np.uint16, (H, W, 3), _cv(cv2.COLOR_BGR2RGB)),
    "32FC4": (np.float32, (H, W, 4), _cv(cv2.COLOR_BGRA2RGBA)),
    "yuv422": (np.uint8, (H, W, 2), _cv(cv2.COLOR_YUV2RGB_UYVY)),
    "uyvy": (np.uint8, (H, W, 2), _cv(cv2.COLOR_YUV2RGB_UYVY)),
    "yuv422_yuy2": (np.uint8, (H, W, 2), _cv(cv2.COLOR_YUV2RGB_YUY2)),
    "yuyv": (np.uint8, (H, W, 2), _cv(cv2.COLOR_YUV2RGB_YUY2)),
    "nv12": (np.uint8, (H * 3 // 2, W), _cv(cv2.COLOR_YUV2RGB_NV12)),
    "nv21": (np.uint8, (H * 3 // 2, W), _cv(cv2.COLOR_YUV2RGB_NV21)),
    # Verified against hand-made mosaics in test_bayer_patterns_follow_ros_naming.
    "bayer_rggb16": (np.uint16, (H, W), _cv(cv2.COLOR_BayerBG2RGB)),
    "bayer_bggr16": (np.uint16, (H, W), _cv(cv2.COLOR_BayerRG2RGB)),
    "bayer_gbrg16": (np.uint16, (H, W), _cv(cv2.COLOR_BayerGR2RGB)),
    "bayer_grbg16": (np.uint16, (H, W), _cv(cv2.COLOR_BayerGB2RGB)),
}

EXPECTED_FORMAT = {
    "bgr8": rr.ColorModel.BGR,
    "bgra8": rr.ColorModel.BGRA,
    "bgr16": rr.ColorModel.BGR,
    "bgra16": rr.ColorModel.BGRA,
    "8UC3": rr.ColorModel.BGR,
    "8UC4": rr.ColorModel.BGRA,
    "mono8": rr.ColorModel.L,
    "mono16": rr.ColorModel.L,
    "8UC1": rr.ColorModel.L,
    "8SC1": rr.ColorModel.L,
    "yuv422": rr.PixelFormat.YUY2,
    "yuyv": rr.PixelFormat.YUY2,
    "nv12": rr.PixelFormat.NV12,
    "nv21": rr.PixelFormat.NV12,
}

DEPTH_CASES = {
    "16UC1": (np.uint16, 1000.0),
    "16SC1": (np.int16, 1000.0),
    "32SC1": (np.int32, 1000.0),
    "32FC1": (np.float32, 1.0),
    "64FC1": (np.float64, 1.0),
}


def _format_of(archetype: Any) -> rr.ColorModel | rr.PixelFormat:
    fmt = image_format(archetype)
    if fmt["pixel_format"] is not None:
        return rr.PixelFormat(fmt["pixel_format"])
    return rr.ColorModel(fmt["color_model"])


# --- sensor_msgs/Image ---------------------------------------------------------------------------


@pytest.mark.parametrize("encoding", list(COLOR_CASES))
def test_colour_encodings_match_opencv(encoding: str) -> None:
    dtype, shape, reference = COLOR_CASES[encoding]
    raw = random_pixels(shape, dtype)
    archetype = convert_one(make_image(encoding, raw, width=W, height=H))
    assert isinstance(archetype, rr.Image)
    fmt = image_format(archetype)
    assert (fmt["width"], fmt["height"]) == (W, H)
    if encoding in EXPECTED_FORMAT:
        assert _format_of(archetype) == EXPECTED_FORMAT[encoding]
    np.testing.assert_array_equal(seen_as_rgb(archetype), _same(reference(raw)))


@pytest.mark.parametrize("encoding", ["bgr8", "bgra16", "yuyv", "nv12", "bayer_gbrg8", "rgb8"])
def test_unpadded_little_endian_pixels_reach_rerun_without_a_copy(encoding: str) -> None:
    """BGR keeps its byte order (the viewer swizzles), and the Arrow buffer is msg.data itself."""
    dtype, shape, _ = COLOR_CASES.get(encoding, (np.uint8, (H, W), _same))
    msg = make_image(encoding, random_pixels(shape, dtype), width=W, height=H)
    archetype = convert_one(msg)
    assert arrow_address(archetype.buffer) == msg.data.ctypes.data
    np.testing.assert_array_equal(received_bytes(archetype), msg.data)


@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
def test_bayer_patterns_follow_ros_naming(pattern: str) -> None:
    """A uniform scene mosaicked the ROS way (first row starts with pattern[0], pattern[1]) must
    come out as that colour: 16-bit through OpenCV, 8-bit as the Rerun format of the same name."""
    colour = {"r": 1000, "g": 2000, "b": 3000}
    tile = np.array([[colour[pattern[0]], colour[pattern[1]]], [colour[pattern[2]], colour[pattern[3]]]])
    mosaic16 = np.tile(tile, (H // 2, W // 2)).astype(np.uint16)

    rgb = seen_as_rgb(convert_one(make_image(f"bayer_{pattern}16", mosaic16, width=W, height=H)))
    np.testing.assert_array_equal(rgb[1:-1, 1:-1], np.broadcast_to([1000, 2000, 3000], (H - 2, W - 2, 3)))

    mosaic8 = (mosaic16 // 20).astype(np.uint8)
    archetype = convert_one(make_image(f"bayer_{pattern}8", mosaic8, width=W, height=H))
    pixel_format = _format_of(archetype)
    assert pixel_format == getattr(rr.PixelFormat, f"Bayer{pattern.upper()}8")
    # Rerun documents BayerXYZW8 as X, Y on even rows and Z, W on odd rows: the ROS layout.
    np.testing.assert_array_equal(received_bytes(archetype).reshape(H, W), mosaic8)


def test_nv24_is_split_into_planar_yuv() -> None:
    rng = np.random.default_rng(RNG_SEED)
    y, u, v = (rng.integers(16, 240, (H, W), dtype=np.uint8) for _ in range(3))
    data = np.concatenate([y.ravel(), np.stack([u, v], axis=-1).ravel()])
    archetype = convert_one(make_image("nv24", data.reshape(H, -1), width=W, height=H))
    assert _format_of(archetype) == rr.PixelFormat.Y_U_V24_LimitedRange
    np.testing.assert_array_equal(received_bytes(archetype).reshape(3, H, W), np.stack([y, u, v]))


@pytest.mark.parametrize("encoding", list(DEPTH_CASES))
def test_depth_encodings_become_depth_images_with_rep118_units(encoding: str) -> None:
    dtype, meter = DEPTH_CASES[encoding]
    raw = random_pixels((H, W), dtype)
    archetype = convert_one(make_image(encoding, raw, width=W, height=H))
    assert isinstance(archetype, rr.DepthImage)
    assert pylist(archetype.meter) == [meter]
    assert archetype.colormap is None
    assert archetype.depth_range is None
    np.testing.assert_array_equal(received_pixels(archetype)[..., 0], raw)


def test_depth_options_meter_colormap_and_range_in_metres() -> None:
    raw = random_pixels((H, W), np.uint16)
    msg = make_image("16UC1", raw, width=W, height=H)
    archetype = convert_one(msg, depth_meter=4000, colormap="viridis", depth_range=[0.5, 4])
    assert pylist(archetype.meter) == [4000.0]
    assert pylist(archetype.colormap) == [rr.components.Colormap.Viridis.value]
    assert pylist(archetype.depth_range) == [[2000.0, 16000.0]]
    gray = convert_one(msg, colormap="gray")
    assert pylist(gray.colormap) == [rr.components.Colormap.Grayscale.value]


def test_mode_forces_depth_or_colour() -> None:
    depth16 = random_pixels((H, W), np.uint16)
    as_grey = convert_one(make_image("16UC1", depth16, width=W, height=H), mode="color")
    assert isinstance(as_grey, rr.Image)
    assert _format_of(as_grey) == rr.ColorModel.L
    np.testing.assert_array_equal(received_pixels(as_grey)[..., 0], depth16)

    as_depth = convert_one(make_image("mono16", depth16, width=W, height=H), mode="depth")
    assert isinstance(as_depth, rr.DepthImage)
    assert pylist(as_depth.meter) == [1000.0]
    mono8 = convert_one(make_image("mono8", depth16.astype(np.uint8), width=W, height=H), mode="depth")
    assert isinstance(mono8, rr.DepthImage)


@pytest.mark.parametrize(
    ("encoding", "dtype", "shape"),
    [
        ("rgb8", np.uint8, (H, W, 3)),
        ("bgra16", np.uint16, (H, W, 4)),
        ("mono16", np.uint16, (H, W)),
        ("32FC1", np.float32, (H, W)),
        ("yuv422", np.uint8, (H, W, 2)),
        ("nv21", np.uint8, (H * 3 // 2, W)),
        ("bayer_grbg8", np.uint8, (H, W)),
        ("bayer_bggr16", np.uint16, (H, W)),
    ],
)
def test_row_padding_is_stripped(encoding: str, dtype: Any, shape: tuple[int, ...]) -> None:
    raw = random_pixels(shape, dtype)
    tight = convert_one(make_image(encoding, raw, width=W, height=H))
    padded_msg = make_image(encoding, raw, width=W, height=H, pad=13)
    assert padded_msg.step > padded_msg.width * raw.itemsize
    padded = convert_one(padded_msg)
    assert image_format(padded) == image_format(tight)
    np.testing.assert_array_equal(received_bytes(padded), received_bytes(tight))


@pytest.mark.parametrize(
    ("encoding", "dtype", "shape"),
    [
        ("mono16", np.uint16, (H, W)),
        ("rgb16", np.uint16, (H, W, 3)),
        ("16UC1", np.uint16, (H, W)),
        ("16SC1", np.int16, (H, W)),
        ("32FC1", np.float32, (H, W)),
        ("64FC1", np.float64, (H, W)),
        ("bayer_rggb16", np.uint16, (H, W)),
    ],
)
def test_big_endian_data_is_byteswapped(encoding: str, dtype: Any, shape: tuple[int, ...]) -> None:
    raw = random_pixels(shape, dtype)
    little = convert_one(make_image(encoding, raw, width=W, height=H))
    big_msg = make_image(encoding, raw, width=W, height=H, bigendian=True, pad=3)
    assert bytes(big_msg.data[:2]) == raw.astype(raw.dtype.newbyteorder(">")).tobytes()[:2]
    np.testing.assert_array_equal(received_bytes(convert_one(big_msg)), received_bytes(little))


@pytest.mark.parametrize(("encoding", "dtype"), [("8UC2", np.uint8), ("32FC2", np.float32)])
def test_two_channel_images_show_each_channel(encoding: str, dtype: Any) -> None:
    raw = random_pixels((H, W, 2), dtype)
    image = make_image(encoding, raw, width=W, height=H)
    entries = convert_image(image, make_ctx(IMAGE_TOPIC, robot=ROBOT, times={}))
    assert [e.path for e in entries] == [f"/{ROBOT}{IMAGE_TOPIC}/ch0", f"/{ROBOT}{IMAGE_TOPIC}/ch1"]
    for channel, entry in enumerate(entries):
        assert isinstance(entry, LogItem)
        (image,) = entry.archetypes
        assert _format_of(image) == rr.ColorModel.L
        np.testing.assert_array_equal(received_pixels(image)[..., 0], raw[..., channel])


@pytest.mark.parametrize(
    ("encoding", "layout", "options", "needle"),
    [
        ("rgb9", (W, H, H * W * 3, W * 3), {}, "'rgb9'"),
        ("64UC1", (W, H, H * W * 8, W * 8), {}, "'64UC1'"),
        ("rgb8", (W, H, H * W * 3 - 1, W * 3), {}, "truncated"),
        ("rgb8", (W, H, H * W * 3, W * 2), {}, "step"),
        ("rgb8", (0, 0, 0, 0), {}, "empty"),
        ("yuv422", (3, 2, 12, 6), {}, "even width"),
        ("nv12", (4, 3, 18, 4), {}, "even width and height"),
        ("rgb8", (W, H, H * W * 3, W * 3), {"mode": "depth"}, "single-channel"),
        ("mono8", (W, H, H * W, W), {"mode": "sideways"}, "mode"),
        ("16UC1", (W, H, H * W * 2, W * 2), {"colormap": "rainbow"}, "colormap"),
        ("16UC1", (W, H, H * W * 2, W * 2), {"depth_range": [3, 1]}, "depth_range"),
        ("16UC1", (W, H, H * W * 2, W * 2), {"depth_meter": -1}, "depth_meter"),
        ("16UC1", (W, H, H * W * 2, W * 2), {"depth_meter": True}, "depth_meter"),
    ],
)
def test_bad_images_raise_convert_error_naming_the_topic(
    encoding: str, layout: tuple[int, int, int, int], options: dict[str, Any], needle: str
) -> None:
    """``layout`` is (width, height, bytes of data, step)."""
    width, height, data_size, step = layout
    msg = T["sensor_msgs/msg/Image"](
        header=header(),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=step,
        data=np.zeros(data_size, np.uint8),
    )
    with pytest.raises(ConvertError, match=IMAGE_TOPIC) as info:
        convert_image(msg, make_ctx(IMAGE_TOPIC, options, robot=ROBOT, times={}))
    assert needle in str(info.value)


# --- sensor_msgs/CompressedImage ------------------------------------------------------------------

COMPRESSED_TOPIC = "/camera/image_raw/compressed"


def make_compressed(fmt: str, data: bytes | npt.NDArray[np.uint8]) -> Any:
    return T["sensor_msgs/msg/CompressedImage"](
        header=header(), format=fmt, data=np.frombuffer(bytes(data), np.uint8)
    )


def convert_compressed(msg: Any, **options: Any) -> Any:
    ctx = make_ctx(COMPRESSED_TOPIC, options, robot=ROBOT, times={})
    entries = convert(convert_compressed_image, msg, ctx)
    return only_archetype(entries, f"/{ROBOT}{COMPRESSED_TOPIC}")


def encode(ext: str, image: npt.NDArray[Any]) -> bytes:
    ok, buf = cv2.imencode(ext, image)
    assert ok
    return buf.tobytes()


@pytest.mark.parametrize(
    ("fmt", "ext", "media_type"),
    [
        ("jpeg", ".jpg", "image/jpeg"),
        ("jpg", ".jpg", "image/jpeg"),
        ("rgb8; jpeg compressed bgr8", ".jpg", "image/jpeg"),
        ("png", ".png", "image/png"),
        ("bgr8; png compressed", ".png", "image/png"),
        ("mono16; png compressed ", ".png", "image/png"),
        ("", ".jpg", "image/jpeg"),
        ("unknown", ".png", "image/png"),
    ],
)
def test_jpeg_and_png_are_passed_through_undecoded(fmt: str, ext: str, media_type: str) -> None:
    payload = encode(ext, random_pixels((H, W, 3), np.uint8))
    msg = make_compressed(fmt, payload)
    archetype = convert_compressed(msg)
    assert isinstance(archetype, rr.EncodedImage)
    assert pylist(archetype.media_type) == [media_type]
    assert received_bytes(archetype).tobytes() == payload
    assert arrow_address(archetype.blob) == msg.data.ctypes.data


def test_a_run_of_jpegs_keeps_each_message_on_its_own_times() -> None:
    """The dispatcher logs a run's entries with the last message's arrival times unless an
    entry carries its own: each JPEG of a run must stay on its own stamp."""
    payload = encode(".jpg", random_pixels((H, W, 3), np.uint8))
    msgs = [make_compressed("jpeg", payload) for _ in range(3)]
    for msg, ns in zip(msgs, (10, 20, 30), strict=True):
        msg.header.stamp = T["builtin_interfaces/msg/Time"](sec=0, nanosec=ns)
    ctxs = [make_ctx(COMPRESSED_TOPIC, robot=ROBOT, times={"log_time": ns + 1}) for ns in (10, 20, 30)]
    entries = convert_run(convert_compressed_image, msgs, ctxs)
    assert [e.times for e in entries] == [
        {"ros_time": 10, "log_time": 11}, {"ros_time": 20, "log_time": 21}, {"ros_time": 30, "log_time": 31},
    ]
    assert all(isinstance(e, LogItem) and isinstance(e.archetypes[0], rr.EncodedImage) for e in entries)


def test_unrecognised_compressed_format_raises_naming_topic_and_format() -> None:
    """The dispatcher shows a ConvertError once per topic and counts the rest, so this text is
    the one warning a user with an unsupported camera format sees."""
    with pytest.raises(ConvertError) as caught:
        convert_compressed(make_compressed("theora", b"\x00\x00\x00\x01gd"))
    assert str(caught.value) == (
        f"{COMPRESSED_TOPIC}: CompressedImage format 'theora' is not one Rerun can show: neither "
        "JPEG, PNG nor compressedDepth, nor a video codec (h264/avc, h265/hevc, av1, vp8, vp9), "
        "and the payload does not start like a JPEG or PNG; its messages are dropped"
    )


# The start of a picture of each codec: an H.264 IDR slice, an H.265 IDR_W_RADL slice, an AV1
# temporal delimiter OBU.
VIDEO_PAYLOADS = {
    rr.VideoCodec.H264: b"\x00\x00\x00\x01\x65\x88\x84",
    rr.VideoCodec.H265: b"\x00\x00\x00\x01\x26\x01\xaf",
    rr.VideoCodec.AV1: b"\x12\x00",
}


@pytest.mark.parametrize(
    ("fmt", "codec"),
    [("h264", rr.VideoCodec.H264), ("H264", rr.VideoCodec.H264), ("rgb8; h264", rr.VideoCodec.H264),
     ("hevc", rr.VideoCodec.H265), ("H.265", rr.VideoCodec.H265), ("av1", rr.VideoCodec.AV1)],
)
def test_compressed_images_carrying_video_become_video_stream_samples(
    fmt: str, codec: rr.VideoCodec
) -> None:
    """Any spelling of a video codec turns the topic into a VideoStream (test_video.py beside
    this file checks real encoded streams); JPEG and PNG stay EncodedImages above."""
    payload = VIDEO_PAYLOADS[codec]
    ctx = make_ctx(COMPRESSED_TOPIC, robot=ROBOT, times={})
    entries = convert(convert_compressed_image, make_compressed(fmt, payload), ctx)
    static, rows = entries
    assert isinstance(static, LogItem)
    assert static.static
    (video,) = static.archetypes
    assert isinstance(video, rr.VideoStream)
    assert video.codec is not None
    assert video.codec.as_arrow_array().to_pylist() == [codec.value]
    assert isinstance(rows, ColumnsItem)
    (sample,) = [c for c in rows.columns if c.component_descriptor().component == "VideoStream:sample"]
    assert sample.as_arrow_array().to_pylist() == [[list(payload)]]


def depth_header(quant_a: float = 0.0, quant_b: float = 0.0) -> bytes:
    return np.array([(0, quant_a, quant_b)], dtype="<i4,<f4,<f4").tobytes()


def test_compressed_depth_png_16uc1_is_raw_millimetres() -> None:
    depth_mm = random_pixels((H, W), np.uint16)
    for fmt in ("16UC1; compressedDepth png", "16UC1; compressedDepth"):
        msg = make_compressed(fmt, depth_header() + encode(".png", depth_mm))
        archetype = convert_compressed(msg, colormap="turbo")
        assert isinstance(archetype, rr.DepthImage)
        assert pylist(archetype.meter) == [1000.0]
        assert pylist(archetype.colormap) == [rr.components.Colormap.Turbo.value]
        np.testing.assert_array_equal(received_pixels(archetype)[..., 0], depth_mm)


def quantize_inverse_depth(
    depth_m: npt.NDArray[np.float32],
) -> tuple[npt.NDArray[np.uint16], float, float]:
    """image_transport's compressed_depth 32FC1 encoder (depth_quantization 100, depth_max 10)."""
    quant_a = np.float32(100.0 * (100.0 + 1.0))
    quant_b = np.float32(1.0 - quant_a / 10.0)
    with np.errstate(divide="ignore"):
        inverse = quant_a / depth_m + quant_b
    valid = (depth_m > 0) & (depth_m < 10)
    return np.where(valid, inverse, 0).astype(np.uint16), float(quant_a), float(quant_b)


def test_compressed_depth_png_32fc1_undoes_inverse_quantization() -> None:
    depth_m = random_pixels((H, W), np.float32)
    depth_m[0, :3] = 0.0  # no return
    inverse, quant_a, quant_b = quantize_inverse_depth(depth_m)
    msg = make_compressed(
        "32FC1; compressedDepth png", depth_header(quant_a, quant_b) + encode(".png", inverse)
    )
    archetype = convert_compressed(msg)
    assert isinstance(archetype, rr.DepthImage)
    assert pylist(archetype.meter) == [1.0]
    got = received_pixels(archetype)[..., 0]
    assert got.dtype == np.float32
    assert np.isnan(got[0, :3]).all()
    valid = inverse > 0
    expected = np.float32(quant_a) / (inverse[valid].astype(np.float32) - np.float32(quant_b))
    np.testing.assert_array_equal(got[valid], expected)
    np.testing.assert_allclose(got[valid], depth_m[valid], rtol=0.01)  # quantization error only


@pytest.mark.parametrize(
    ("fmt", "payload", "needle"),
    [
        ("16UC1; compressedDepth rvl", depth_header() + b"\x04\x00\x00\x00\x04\x00\x00\x00", "RVL"),
        ("16UC1; compressedDepth png", depth_header() + b"not a png", "16-bit PNG"),
        ("16UC1; compressedDepth png", b"\x00" * 8, "holds no image"),
        ("8UC3; compressedDepth png", depth_header() + b"x", "8UC3"),
    ],
)
def test_bad_compressed_depth_raises(fmt: str, payload: bytes, needle: str) -> None:
    with pytest.raises(ConvertError, match=COMPRESSED_TOPIC) as info:
        convert_compressed(make_compressed(fmt, payload))
    assert needle in str(info.value)


# --- real recordings ------------------------------------------------------------------------------


def test_real_rgb8_image(shared_data: Path) -> None:
    msg = first_message(shared_data / "ros_numpy_msgs_synthetic/ros_numpy_test.bag", "/image")
    assert (msg.encoding, msg.width, msg.height, msg.step) == ("rgb8", 360, 240, 1080)
    archetype = convert_one(msg)
    assert image_format(archetype) == {
        "width": 360,
        "height": 240,
        "pixel_format": None,
        "color_model": rr.ColorModel.RGB.value,
        "channel_datatype": rr.ChannelDatatype.U8.value,
    }
    np.testing.assert_array_equal(seen_as_rgb(archetype), msg.data.reshape(240, 360, 3))


def test_real_png_compressed_image(shared_data: Path) -> None:
    bag = shared_data / "ros_numpy_msgs_synthetic/ros_numpy_test.bag"
    msg = first_message(bag, "/compressedimage")
    archetype = convert_compressed(msg)
    assert pylist(archetype.media_type) == ["image/png"]
    assert received_bytes(archetype).tobytes() == msg.data.tobytes()
    assert cv2.imdecode(received_bytes(archetype), cv2.IMREAD_UNCHANGED) is not None


def test_real_legacy_jpg_compressed_image_with_exif(shared_data: Path) -> None:
    bag = shared_data / "raspicam_aruco_ubiquity/aruco_images.bag"
    msg = first_message(bag, "/raspicam_node/image/compressed")
    assert msg.format == "jpg"
    archetype = convert_compressed(msg)
    assert pylist(archetype.media_type) == ["image/jpeg"]
    blob = received_bytes(archetype)
    assert blob.size == msg.data.size == 593883
    assert blob[:4].tobytes() == b"\xff\xd8\xff\xe1"
    assert blob.tobytes() == msg.data.tobytes()
    decoded = cv2.imdecode(blob, cv2.IMREAD_COLOR)
    assert decoded is not None
    assert decoded.shape == (960, 1280, 3)


# --- declared sizes over the decoding cap (issue 14) ------------------------------------------------


def png_chunk(kind: bytes, data: bytes) -> bytes:
    return len(data).to_bytes(4, "big") + kind + data + zlib.crc32(kind + data).to_bytes(4, "big")


def zero_png16(width: int, height: int) -> bytes:
    """A real, valid 16-bit grey PNG of zeros, deflated row by row: 2 bytes a pixel when decoded,
    about 1/1000 of that as a file."""
    deflate = zlib.compressobj(9)
    row = bytes(1 + 2 * width)  # filter type 0, then the row's pixels
    idat = b"".join(deflate.compress(row) for _ in range(height)) + deflate.flush()
    ihdr = struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)
    return PNG_SIGNATURE + png_chunk(b"IHDR", ihdr) + png_chunk(b"IDAT", idat) + png_chunk(b"IEND", b"")


def with_png_size(png: bytes, width: int, height: int) -> bytes:
    """``png`` whose IHDR declares ``width`` x ``height``, its CRC recomputed."""
    ihdr = struct.pack(">II", width, height) + png[24:29]
    return png[:8] + png_chunk(b"IHDR", ihdr) + png[33:]


def with_jpeg_size(jpeg: bytes, width: int, height: int) -> bytes:
    """``jpeg`` whose baseline start-of-frame segment declares ``width`` x ``height``."""
    sof = jpeg.index(b"\xff\xc0")
    return jpeg[:sof + 5] + struct.pack(">HH", height, width) + jpeg[sof + 9:]


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAP = MAX_DECODED_PIXELS


def test_images_declaring_more_pixels_than_the_cap_are_refused_before_decoding(
    reliability: Record,
) -> None:
    small = random_pixels((6, 8, 3), np.uint8)
    depth_bomb = zero_png16(8193, 8192)  # 67,117,056 pixels, one row over 2^26
    assert len(depth_bomb) < 200_000
    rvl_claim = struct.pack("<II", 65535, 65535) + bytes(16)
    hostile = [
        ("/depth_png", "16UC1; compressedDepth png", depth_header() + depth_bomb,
         f"compressedDepth PNG header declares a 8193x8192 image; more than {CAP} pixels (or "
         "none) is refused without decoding it"),
        ("/depth_rvl", "16UC1; compressedDepth rvl", depth_header() + rvl_claim,
         f"compressedDepth RVL header declares a 65535x65535 image; more than {CAP} pixels (or "
         "none) is refused without decoding it"),
        ("/png", "png", with_png_size(encode(".png", small), 20000, 20000),
         f"PNG header declares a 20000x20000 image; more than {CAP} pixels (or none) is refused "
         "without decoding it"),
        ("/jpeg", "jpeg", with_jpeg_size(encode(".jpg", small), 65535, 65535),
         f"JPEG header declares a 65535x65535 image; more than {CAP} pixels (or none) is "
         "refused without decoding it"),
    ]
    good = encode(".png", small)
    sink = RecordingSink()
    dispatcher = Dispatcher(sink)
    tracemalloc.start()
    try:
        for step, (topic, fmt, payload, _) in enumerate(hostile):
            dispatcher.dispatch([
                RawMessage(ROBOT, topic, COMPRESSED, compressed_cdr(fmt, payload), log_ns=step),
                RawMessage(ROBOT, COMPRESSED_TOPIC, COMPRESSED, compressed_cdr("png", good),
                           log_ns=step),
            ])
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    dispatcher.close()
    warnings = sink.warnings()
    assert warnings == [
        f"[{ROBOT}] {topic}: {text} (further ConvertErrors on this topic are counted, not shown)"
        for topic, _, _, text in hostile
    ]
    for topic, *_ in hostile:
        counters = dispatcher.counters[(ROBOT, topic)]
        assert (counters.received, counters.converted, counters.dropped) == (1, 0, 1)
    stills = [a for entry, _ in sink.logged if isinstance(entry, LogItem)
              and entry.path == f"/{ROBOT}{COMPRESSED_TOPIC}" for a in entry.archetypes]
    assert len(stills) == len(hostile)
    assert all(received_bytes(still).tobytes() == good for still in stills)
    assert peak < 16 << 20  # decoding the depth bomb alone would take 128 MiB
    reliability("Hostile input", "compressed images declaring more than 64 Mpx: a real "
                f"{len(depth_bomb) // 1000} KB 16-bit PNG of 8193x8192 zeros (compressedDepth, "
                "128 MiB decoded), an RVL header of 65535x65535, a PNG and a JPEG whose headers "
                "claim 20000x20000 and 65535x65535",
                tried=f"{len(hostile)} messages",
                survived=f"host (traced peak {peak / 2**20:.1f} MB, nothing decoded); each "
                f"refused naming its topic and declared size; {len(stills)} of {len(hostile)} good "
                "PNGs beside them logged byte for byte",
                lost=f"the {len(hostile)} oversized images only")


def test_an_image_of_exactly_the_cap_is_logged() -> None:
    png = with_png_size(encode(".png", random_pixels((6, 8, 3), np.uint8)), 8192, 8192)
    archetype = convert_compressed(make_compressed("png", png))
    assert received_bytes(archetype).tobytes() == png  # 2^26 pixels: passed on for the viewer


def compressed_cdr(fmt: str, payload: bytes) -> bytes:
    return bytes(TYPESTORE.serialize_cdr(make_compressed(fmt, payload), COMPRESSED))
