"""sensor_msgs Image and CompressedImage -> Rerun images, handing Rerun the message's own bytes.

Why it is built this way:

* Pixels reach Rerun as an Arrow list over ``msg.data`` itself whenever the bytes are already in
  a layout Rerun understands (unpadded rows, little-endian): no copy on the host. A copy happens
  only where the layout must change: padded rows (``step`` > row size, stripped with one strided
  view and one compaction), big-endian multi-byte pixels (byteswapped), and the reorderings below.
* Colour models Rerun has are used as they are: ``bgr8``/``bgra8``/``bgr16``/``bgra16`` are logged
  with ``ColorModel.BGR``/``BGRA`` (the viewer swizzles on the GPU), ``yuyv``/``yuv422_yuy2`` as
  ``PixelFormat.YUY2`` and ``nv12`` as ``PixelFormat.NV12``. ROS ``yuv422``/``uyvy`` and ``nv21``
  are turned into YUY2 / NV12 by swapping byte pairs (one cheap shuffle, no colour maths), ``nv24``
  is de-interleaved into ``Y_U_V24`` (all limited range, as cameras send them).
* 8-bit Bayer is logged raw with ``PixelFormat.Bayer*8``: rerun 0.41 demosaics in the viewer, so
  the host does no work and sends one byte per pixel instead of three. Rerun has no 16-bit Bayer
  format, so those are demosaiced here with OpenCV to 16-bit RGB.
* ``mono8``/``mono16``/``8UC1``/``8SC1`` are plain grey (L) images; the single-channel generic
  types of 16 bits and more (``16UC1``, ``16SC1``, ``32SC1``, ``32FC1``, ``64FC1``) are depth
  (REP 118: integer depth is millimetres -> ``meter=1000``, float depth is metres -> ``meter=1``).
  3- and 4-channel generic types are BGR/BGRA (OpenCV's order, which is what cv_bridge publishes);
  2-channel ones (and any other count) are logged one grey image per channel under ``ch<i>``.
* JPEG/PNG CompressedImages are logged as ``EncodedImage`` without decoding; those whose format
  names a video codec (``h264``, ``hevc``, ...) become ``VideoStream`` samples, also undecoded
  (see :mod:`host_bridge.converters.video`). ``compressedDepth``
  (image_transport's compressed_depth plugin: PNG or RVL after a 12-byte config header; the RVL
  codec is :mod:`host_bridge.core.rvl`) is decoded here into a ``DepthImage``, because a 32FC1 payload
  holds inverse-quantized values only the host-side formula turns back into metres.
* Images carry no ``CoordinateFrame``: they must stay in the implicit frame of their entity path
  so that they land in the image plane of the pinhole the CameraInfo converter logs at the camera
  namespace (see :mod:`host_bridge.converters.camera`).

Per-topic options: ``mode`` ``auto`` | ``depth`` | ``color`` (force single-channel images to be
depth or grey), ``depth_meter`` (raw units per metre), ``colormap`` (a Rerun colormap name, e.g.
``turbo``, ``viridis``, ``gray``), ``depth_range`` ``[min, max]`` in metres.
"""

from __future__ import annotations

import re
from functools import lru_cache
from typing import Any

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import rerun as rr

from host_bridge.converters.video import CODEC_SPELLINGS, VideoFrame, video_codec, video_entries
from host_bridge.core.contract import ConvertContext, LogEntry, LogItem, Run, header_stamp, per_message
from host_bridge.core.options import ImageOptions, converter_choices
from host_bridge.core.rvl import rvl_decode
from host_bridge.errors import ConvertError
from robot_relay.wire import MAX_DECOMPRESSED_BYTES

_MODES = converter_choices(ImageOptions)

# Rerun's own colormap names are accepted case-insensitively; these are the host's other spellings.
_COLORMAP_ALIASES = {"gray": "Grayscale", "grey": "Grayscale"}

_U8 = np.dtype(np.uint8)
_U16 = np.dtype("<u2")

_PLAIN: dict[str, tuple[np.dtype[Any], rr.ColorModel]] = {
    "rgb8": (_U8, rr.ColorModel.RGB),
    "rgba8": (_U8, rr.ColorModel.RGBA),
    "rgb16": (_U16, rr.ColorModel.RGB),
    "rgba16": (_U16, rr.ColorModel.RGBA),
    "bgr8": (_U8, rr.ColorModel.BGR),
    "bgra8": (_U8, rr.ColorModel.BGRA),
    "bgr16": (_U16, rr.ColorModel.BGR),
    "bgra16": (_U16, rr.ColorModel.BGRA),
    "mono8": (_U8, rr.ColorModel.L),
    "mono16": (_U16, rr.ColorModel.L),
}

# OpenCV's generic matrix types; the pixel data is little-endian unless is_bigendian says otherwise.
_CV_TYPE = re.compile(r"(8U|8S|16U|16S|32S|32F|64F)C([1-9]\d*)?")
_CV_DTYPES: dict[str, np.dtype[Any]] = {
    "8U": _U8,
    "8S": np.dtype(np.int8),
    "16U": _U16,
    "16S": np.dtype("<i2"),
    "32S": np.dtype("<i4"),
    "32F": np.dtype("<f4"),
    "64F": np.dtype("<f8"),
}
_CHANNEL_MODELS = {3: rr.ColorModel.BGR, 4: rr.ColorModel.BGRA}

# OpenCV names a Bayer pattern after the second row's 2nd and 3rd pixels, not the first row's
# first two as ROS does: ROS rggb is OpenCV "BG". Codes by name: cv2 (20 ms) is imported by the
# converters that call it, not by every run.
_BAYER: dict[str, tuple[rr.PixelFormat, str]] = {
    "rggb": (rr.PixelFormat.BayerRGGB8, "COLOR_BayerBG2RGB"),
    "bggr": (rr.PixelFormat.BayerBGGR8, "COLOR_BayerRG2RGB"),
    "gbrg": (rr.PixelFormat.BayerGBRG8, "COLOR_BayerGR2RGB"),
    "grbg": (rr.PixelFormat.BayerGRBG8, "COLOR_BayerGB2RGB"),
}
_BAYER_ENCODING = re.compile(r"bayer_(rggb|bggr|gbrg|grbg)(8|16)")

# image_transport compressed_depth: ConfigHeader {int32 format; float32 depthQuantA, depthQuantB}.
_DEPTH_HEADER = np.dtype([("format", "<i4"), ("quant_a", "<f4"), ("quant_b", "<f4")])

MAX_DECODED_PIXELS = MAX_DECOMPRESSED_BYTES // 2
"""The most pixels a compressed image may declare: 64 Mpx (an 8K frame is 33), whose 16-bit
depth is the 128 MiB a compressed payload may inflate to on the wire. A PNG of zeros 1000 times
smaller than its pixels, or an RVL or JPEG header claiming 65535 x 65535, must not make the host
(compressedDepth, decoded here) or the viewer (JPEG and PNG, decoded there) allocate gigabytes;
the size is read from the header before anything is decoded. OpenCV's own limit
(``CV_IO_MAX_IMAGE_PIXELS``, 2^30 by default) is not honoured by opencv-python-headless 5.0."""

_JPEG, _JPEG_MAGIC = "image/jpeg", b"\xff\xd8\xff"
_PNG, _PNG_MAGIC = "image/png", b"\x89PNG\r\n\x1a\n"
_PNG_IHDR = 8 + 4 + 4 + 8  # signature, chunk length and type, then width and height (big-endian)
# JPEG start-of-frame markers (SOF0..SOF15 but DHT, JPG and DAC), standalone markers (TEM, RSTn).
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
_JPEG_STANDALONE = frozenset({0x01, *range(0xD0, 0xD8)})

Archetype = rr.AsComponents
Pixels = npt.NDArray[Any]


# --- options -------------------------------------------------------------------------------------


def _mode(ctx: ConvertContext) -> str:
    mode = ctx.options(ImageOptions).mode
    if mode not in _MODES:
        msg = f"{ctx.topic}: image option mode={mode!r} is not one of {', '.join(_MODES)}"
        raise ConvertError(msg)
    return mode


def _colormap(ctx: ConvertContext) -> rr.components.Colormap | None:
    name = ctx.options(ImageOptions).colormap
    if name is None:
        return None
    try:
        return rr.components.Colormap.auto(_COLORMAP_ALIASES.get(str(name).lower(), str(name)))
    except ValueError:
        names = ", ".join(c.name.lower() for c in rr.components.Colormap)
        msg = f"{ctx.topic}: image option colormap={name!r} is not a Rerun colormap ({names})"
        raise ConvertError(msg) from None


def _depth_meter(ctx: ConvertContext, dtype: np.dtype[Any]) -> float:
    meter = ctx.options(ImageOptions).depth_meter
    if meter is None:
        return 1.0 if dtype.kind == "f" else 1000.0  # REP 118: metres, else millimetres
    if isinstance(meter, bool) or not isinstance(meter, int | float) or meter <= 0:
        msg = f"{ctx.topic}: image option depth_meter={meter!r} must be a positive number"
        raise ConvertError(msg)
    return float(meter)


def _depth_range(ctx: ConvertContext, meter: float) -> list[float] | None:
    """``depth_range`` is given in metres; Rerun wants it in the image's raw units."""
    value = ctx.options(ImageOptions).depth_range
    if value is None:
        return None
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        lo = hi = float("nan")
    if not lo < hi:
        msg = f"{ctx.topic}: image option depth_range={value!r} must be [min, max] in metres"
        raise ConvertError(msg)
    return [lo * meter, hi * meter]


# --- building archetypes over numpy buffers ------------------------------------------------------


def _blob(buffer: Pixels) -> Any:
    """A one-element Arrow list<uint8> over ``buffer``'s memory (no copy when contiguous).

    Rerun's component batches take an Arrow array of exactly their own type as it is, while any
    other input (bytes, numpy) is copied at least once on the way in.
    """
    flat = np.ascontiguousarray(buffer).reshape(-1).view(np.uint8)
    return pa.ListArray.from_arrays(
        pa.array([0, flat.size], type=pa.int32()),
        pa.array(flat),
        type=rr.components.ImageBufferBatch._ARROW_DATATYPE,
    )


@lru_cache(maxsize=64)
def _image_format(
    width: int, height: int, dtype: np.dtype[Any] | None = None, *,
    model: rr.ColorModel | None = None, pixel_format: rr.PixelFormat | None = None,
) -> pa.Array:
    """An ``ImageFormat`` as the Arrow array Rerun takes as it is, made once per size and
    layout: a camera sends the same one with every frame, and converting it was a quarter of a
    640x480 frame's conversion."""
    image_format = rr.components.ImageFormat(
        width=width, height=height, pixel_format=pixel_format, color_model=model,
        channel_datatype=None if dtype is None else rr.ChannelDatatype.from_np_dtype(dtype),
    )
    return rr.components.ImageFormatBatch(image_format).as_arrow_array()


def _color_image(pixels: Pixels, width: int, height: int, model: rr.ColorModel) -> rr.Image:
    return rr.Image.from_fields(buffer=_blob(pixels),
                                format=_image_format(width, height, pixels.dtype, model=model))


def _pixel_format_image(buffer: Pixels, width: int, height: int, pixel_format: rr.PixelFormat) -> rr.Image:
    return rr.Image.from_fields(buffer=_blob(buffer),
                                format=_image_format(width, height, pixel_format=pixel_format))


def _depth_image(pixels: Pixels, width: int, height: int, ctx: ConvertContext) -> rr.DepthImage:
    meter = _depth_meter(ctx, pixels.dtype)
    return rr.DepthImage.from_fields(
        buffer=_blob(pixels),
        format=_image_format(width, height, pixels.dtype),
        meter=meter,
        colormap=_colormap(ctx),
        depth_range=_depth_range(ctx, meter),
    )


def _single_channel(
    pixels: Pixels, width: int, height: int, ctx: ConvertContext, *, depth_by_default: bool
) -> Archetype:
    mode = _mode(ctx)
    if mode == "depth" or (mode == "auto" and depth_by_default):
        return _depth_image(pixels, width, height, ctx)
    return _color_image(pixels, width, height, rr.ColorModel.L)


def _refuse_depth(ctx: ConvertContext, encoding: str) -> None:
    if _mode(ctx) == "depth":
        msg = (
            f"{ctx.topic}: image option mode='depth' needs a single-channel image, but the "
            f"encoding is {encoding!r}; remove the option for this topic"
        )
        raise ConvertError(msg)


# --- raw pixel access ----------------------------------------------------------------------------


def _rows(msg: Any, ctx: ConvertContext, row_bytes: int, n_rows: int) -> npt.NDArray[np.uint8]:
    """The first ``row_bytes`` of each of ``n_rows`` rows ``step`` apart: a view, no copy."""
    data: npt.NDArray[np.uint8] = msg.data
    step = int(msg.step)
    if step < row_bytes:
        msg_ = (
            f"{ctx.topic}: Image step {step} is smaller than a row of {msg.width} "
            f"{msg.encoding} pixels ({row_bytes} bytes); the publisher filled the message wrongly"
        )
        raise ConvertError(msg_)
    needed = step * (n_rows - 1) + row_bytes
    if data.size < needed:
        msg_ = (
            f"{ctx.topic}: Image data has {data.size} bytes, but {msg.width}x{msg.height} "
            f"{msg.encoding} with step {step} needs {needed}; the message is truncated"
        )
        raise ConvertError(msg_)
    return np.lib.stride_tricks.as_strided(
        data, shape=(n_rows, row_bytes), strides=(step, 1), writeable=False
    )


def _pixels(msg: Any, ctx: ConvertContext, dtype: np.dtype[Any], channels: int) -> Pixels:
    """(height, width[, channels]) little-endian pixels; a view over msg.data when unpadded."""
    height, width = int(msg.height), int(msg.width)
    rows = np.ascontiguousarray(_rows(msg, ctx, width * channels * dtype.itemsize, height))
    if dtype.itemsize > 1 and msg.is_bigendian:
        values = rows.view(dtype.newbyteorder(">")).astype(dtype)
    else:
        values = rows.view(dtype)
    shape = (height, width) if channels == 1 else (height, width, channels)
    pixels: Pixels = values.reshape(shape)
    return pixels


def _swap_byte_pairs(rows: npt.NDArray[np.uint8]) -> None:
    """Swap bytes 0<->1, 2<->3, ... in place (UYVY->YUYV, VU->UV) of a compact array we own."""
    rows.view("<u2").byteswap(inplace=True)


# --- sensor_msgs/Image ---------------------------------------------------------------------------


def _require_even(ctx: ConvertContext, msg: Any, *, height_too: bool) -> None:
    if msg.width % 2 or (height_too and msg.height % 2):
        dims = "width and height" if height_too else "width"
        msg_ = (
            f"{ctx.topic}: {msg.encoding} image of {msg.width}x{msg.height} is chroma-subsampled "
            f"and needs an even {dims}"
        )
        raise ConvertError(msg_)


def _yuv(msg: Any, ctx: ConvertContext, encoding: str) -> Archetype:
    _refuse_depth(ctx, encoding)
    height, width = int(msg.height), int(msg.width)
    if encoding in ("uyvy", "yuv422", "yuyv", "yuv422_yuy2"):
        _require_even(ctx, msg, height_too=False)
        rows = _rows(msg, ctx, 2 * width, height)
        if encoding in ("uyvy", "yuv422"):
            rows = np.array(rows)  # a compact copy: msg.data itself is never written
            _swap_byte_pairs(rows)
        return _pixel_format_image(rows, width, height, rr.PixelFormat.YUY2)
    if encoding in ("nv12", "nv21"):
        _require_even(ctx, msg, height_too=True)
        # The interleaved chroma plane follows the luma plane with the same row stride.
        planes = _rows(msg, ctx, width, height * 3 // 2)
        if encoding == "nv21":
            planes = np.array(planes)
            _swap_byte_pairs(planes[height:])
        return _pixel_format_image(planes, width, height, rr.PixelFormat.NV12)
    # nv24: a full-resolution luma plane, then a full-resolution interleaved UV plane. ROS gives
    # it no unambiguous step (image_encodings calls it 2-channel, V4L2 a 1-byte luma stride), so
    # it is read unpadded. Rerun wants the planes separate (Y_U_V24).
    data: npt.NDArray[np.uint8] = msg.data
    n = width * height
    if data.size < 3 * n:
        msg_ = f"{ctx.topic}: nv24 image {width}x{height} needs {3 * n} bytes, got {data.size}"
        raise ConvertError(msg_)
    planar = np.empty((3, n), dtype=np.uint8)
    planar[0] = data[:n]
    planar[1:] = data[n : 3 * n].reshape(n, 2).T
    return _pixel_format_image(planar, width, height, rr.PixelFormat.Y_U_V24_LimitedRange)


def _bayer(msg: Any, ctx: ConvertContext, pattern: str, bits: str) -> Archetype:
    _refuse_depth(ctx, msg.encoding)
    height, width = int(msg.height), int(msg.width)
    pixel_format, cv_code = _BAYER[pattern]
    if bits == "8":
        return _pixel_format_image(_rows(msg, ctx, width, height), width, height, pixel_format)
    import cv2

    rgb = cv2.cvtColor(_pixels(msg, ctx, _U16, 1), getattr(cv2, cv_code))
    return _color_image(rgb, width, height, rr.ColorModel.RGB)


def _generic(msg: Any, ctx: ConvertContext, dtype: np.dtype[Any], channels: int) -> list[LogEntry]:
    height, width = int(msg.height), int(msg.width)
    pixels = _pixels(msg, ctx, dtype, channels)
    if channels == 1:
        image = _single_channel(pixels, width, height, ctx, depth_by_default=dtype.itemsize >= 2)
        return [LogItem(ctx.entity_path, (image,))]
    if channels in _CHANNEL_MODELS:
        _refuse_depth(ctx, msg.encoding)
        image = _color_image(pixels, width, height, _CHANNEL_MODELS[channels])
        return [LogItem(ctx.entity_path, (image,))]
    # No Rerun colour model has this many channels: show each as its own grey image.
    return [
        LogItem(
            ctx.child_path(f"ch{c}"),
            (_single_channel(pixels[..., c], width, height, ctx, depth_by_default=False),),
        )
        for c in range(channels)
    ]


def convert_image(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    encoding = msg.encoding.strip()
    key = encoding.lower()
    height, width = int(msg.height), int(msg.width)
    if height == 0 or width == 0:
        msg_ = f"{ctx.topic}: Image is empty ({width}x{height}, encoding {encoding!r})"
        raise ConvertError(msg_)
    if key in _PLAIN:
        dtype, model = _PLAIN[key]
        pixels = _pixels(msg, ctx, dtype, model.num_channels())
        if model == rr.ColorModel.L:
            image = _single_channel(pixels, width, height, ctx, depth_by_default=False)
        else:
            _refuse_depth(ctx, encoding)
            image = _color_image(pixels, width, height, model)
        return [LogItem(ctx.entity_path, (image,))]
    if key in ("uyvy", "yuv422", "yuyv", "yuv422_yuy2", "nv12", "nv21", "nv24"):
        return [LogItem(ctx.entity_path, (_yuv(msg, ctx, key),))]
    if bayer := _BAYER_ENCODING.fullmatch(key):
        return [LogItem(ctx.entity_path, (_bayer(msg, ctx, bayer[1], bayer[2]),))]
    if cv_type := _CV_TYPE.fullmatch(encoding.upper()):
        return _generic(msg, ctx, _CV_DTYPES[cv_type[1]], int(cv_type[2] or 1))
    msg_ = (
        f"{ctx.topic}: Image encoding {encoding!r} is not a sensor_msgs image_encodings value "
        "this converter knows (rgb/bgr/mono 8/16, 8UC1..64FC4, bayer_*, yuv422/uyvy/yuyv, "
        "nv12/nv21/nv24)"
    )
    raise ConvertError(msg_)


# --- sensor_msgs/CompressedImage -----------------------------------------------------------------


def _media_type(fmt: str, data: npt.NDArray[np.uint8]) -> str | None:
    """Media type from the format string (``jpeg``, legacy ``jpg``, ``bgr8; png compressed``...),
    else from the payload's magic bytes (some publishers leave the format empty)."""
    tokens = set(re.split(r"[\s;:,]+", fmt.lower()))
    if tokens & {"jpeg", "jpg"}:
        return _JPEG
    if "png" in tokens:
        return _PNG
    head = bytes(data[:8])
    if head.startswith(_JPEG_MAGIC):
        return _JPEG
    if head.startswith(_PNG_MAGIC):
        return _PNG
    return None


def _check_declared_size(ctx: ConvertContext, what: str, width: int, height: int) -> None:
    """A ConvertError unless a header's ``width`` x ``height`` is an image the host or the
    viewer may decode (see MAX_DECODED_PIXELS)."""
    if width <= 0 or height <= 0 or width * height > MAX_DECODED_PIXELS:
        msg = (
            f"{ctx.topic}: {what} header declares a {width}x{height} image; more than "
            f"{MAX_DECODED_PIXELS} pixels (or none) is refused without decoding it"
        )
        raise ConvertError(msg)


def _png_size(data: npt.NDArray[np.uint8]) -> tuple[int, int] | None:
    """(width, height) from a PNG's IHDR chunk, which the format puts first; None if ``data``
    does not start like a PNG (the decoder then names it)."""
    head = bytes(data[:_PNG_IHDR])
    if len(head) < _PNG_IHDR or not head.startswith(_PNG_MAGIC) or head[12:16] != b"IHDR":
        return None
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def _jpeg_size(data: npt.NDArray[np.uint8]) -> tuple[int, int] | None:
    """(width, height) from a JPEG's start-of-frame segment, found by hopping over the segments
    before it (a few, whatever the image's size); None if there is none to find."""
    view = np.ascontiguousarray(data).data  # a memoryview: its items are ints
    at = 2  # after SOI
    while at + 4 <= len(view):
        if view[at] != 0xFF:
            return None
        marker = view[at + 1]
        if marker == 0xFF:  # fill byte
            at += 1
        elif marker in _JPEG_STANDALONE:
            at += 2
        elif marker in _JPEG_SOF:
            if at + 9 > len(view):
                return None
            height = int.from_bytes(view[at + 5 : at + 7], "big")
            return int.from_bytes(view[at + 7 : at + 9], "big"), height
        else:
            at += 2 + int.from_bytes(view[at + 2 : at + 4], "big")
    return None


def _decode_compressed_depth(msg: Any, ctx: ConvertContext) -> tuple[Pixels, int, int]:
    """(depth pixels, width, height): 16UC1 stays raw millimetres, 32FC1 becomes metres."""
    original, _, codec = msg.format.partition(";")
    original = original.strip().upper()
    codec_tokens = codec.lower().split()
    data: npt.NDArray[np.uint8] = msg.data
    if original not in ("16UC1", "32FC1"):
        msg_ = (
            f"{ctx.topic}: compressedDepth image of encoding {original!r} (format {msg.format!r}); "
            "image_transport's compressed_depth only produces 16UC1 and 32FC1"
        )
        raise ConvertError(msg_)
    if data.size <= _DEPTH_HEADER.itemsize:
        msg_ = f"{ctx.topic}: compressedDepth payload of {data.size} bytes holds no image"
        raise ConvertError(msg_)
    header = data[: _DEPTH_HEADER.itemsize].view(_DEPTH_HEADER)[0]
    body = data[_DEPTH_HEADER.itemsize :]
    if "rvl" in codec_tokens:
        if body.size < 8:
            msg_ = f"{ctx.topic}: compressedDepth RVL payload has no resolution header"
            raise ConvertError(msg_)
        width, height = (int(v) for v in body[:8].view("<u4"))
        _check_declared_size(ctx, "compressedDepth RVL", width, height)
        try:
            raw: Pixels = rvl_decode(body[8:], width * height).reshape(height, width)
        except ValueError as err:
            msg_ = f"{ctx.topic}: compressedDepth RVL payload ({width}x{height}) is corrupt: {err}"
            raise ConvertError(msg_) from None
    else:
        declared = _png_size(body)
        if declared is not None:
            _check_declared_size(ctx, "compressedDepth PNG", *declared)
        import cv2

        decoded = cv2.imdecode(body, cv2.IMREAD_UNCHANGED)
        if decoded is None or decoded.dtype != np.uint16 or decoded.ndim != 2:
            msg_ = (
                f"{ctx.topic}: compressedDepth payload (format {msg.format!r}) is not a "
                "single-channel 16-bit PNG"
            )
            raise ConvertError(msg_)
        raw = decoded
        height, width = decoded.shape
    if original == "16UC1":
        return raw, width, height
    # The publisher stored quant_a / depth + quant_b; 0 marks pixels without depth.
    with np.errstate(divide="ignore"):
        depth = np.float32(header["quant_a"]) / (raw.astype(np.float32) - np.float32(header["quant_b"]))
    depth[raw == 0] = np.nan
    return depth, width, height


def _still_image(msg: Any, ctx: ConvertContext) -> LogItem:
    """A JPEG, PNG or compressedDepth CompressedImage (anything but video)."""
    if "compresseddepth" in msg.format.lower():
        depth, width, height = _decode_compressed_depth(msg, ctx)
        image = _single_channel(depth, width, height, ctx, depth_by_default=True)
        return LogItem(ctx.entity_path, (image,), times=ctx.times)
    media_type = _media_type(msg.format, msg.data)
    if media_type is None:
        msg_ = (
            f"{ctx.topic}: CompressedImage format {msg.format!r} is not one Rerun can show: "
            f"neither JPEG, PNG nor compressedDepth, nor a video codec ({CODEC_SPELLINGS}), and "
            "the payload does not start like a JPEG or PNG; its messages are dropped"
        )
        raise ConvertError(msg_)
    declared = _png_size(msg.data) if media_type == _PNG else _jpeg_size(msg.data)
    if declared is not None:
        _check_declared_size(ctx, "PNG" if media_type == _PNG else "JPEG", *declared)
    encoded = rr.EncodedImage.from_fields(blob=_blob(msg.data), media_type=media_type)
    return LogItem(ctx.entity_path, (encoded,), times=ctx.times)


def _video_codec(msg: Any) -> rr.VideoCodec | None:
    """The codec of a CompressedImage carrying video: its format names one and neither
    compressedDepth nor JPEG/PNG (by name or by the payload's first bytes)."""
    if "compresseddepth" in msg.format.lower() or _media_type(msg.format, msg.data) is not None:
        return None
    return video_codec(msg.format)


def convert_compressed_image(run: Run) -> list[LogEntry]:
    """Stills become one image each (each on its own message's times); video messages of the
    run become the rows of one ``VideoStream`` column batch."""
    msgs = run.messages()
    codecs = [_video_codec(m) for m in msgs]
    entries: list[LogEntry] = []
    if None in codecs:
        entries.extend(_still_image(m, c) for m, c, codec in zip(msgs, run.contexts(), codecs, strict=True)
                       if codec is None)
    video = [(row, codec) for row, codec in enumerate(codecs) if codec is not None]
    if video:
        frames = [VideoFrame(codec, msgs[row].data, header_stamp(msgs[row]) or 0) for row, codec in video]
        entries.extend(video_entries(run, frames, np.array([row for row, _ in video], np.intp)))
    return entries


IMAGE = per_message(convert_image)
COMPRESSED_IMAGE = convert_compressed_image

__all__ = [
    "COMPRESSED_IMAGE",
    "IMAGE",
    "convert_compressed_image",
    "convert_image",
]
