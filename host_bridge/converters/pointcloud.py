"""sensor_msgs/PointCloud2 -> Points3D, read through one structured numpy view of the buffer.

Every layout a driver may send (padding inside a point, padding at row ends, big-endian, any
PointField datatype, ``count > 1``) is described to numpy as one structured dtype with explicit
offsets and ``itemsize = point_step``, laid over ``msg.data`` with row and point strides, so no
Python code ever runs per point.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
import rerun as rr

from host_bridge.colormap import apply_colormap
from host_bridge.contract import ConvertContext, LogEntry, LogItem, per_message
from host_bridge.converters._common import frame_components
from host_bridge.errors import ConvertError
from host_bridge.options import PointCloudOptions

# PointField.datatype -> numpy type code (byte order is added per cloud).
_DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
# PCL packs colour as four bytes B,G,R,A of a little-endian word, usually declared FLOAT32; read
# as an unsigned word in the cloud's byte order the value is always 0xAARRGGBB.
_PACKED_COLOR_FIELDS = ("rgba", "rgb")


def cloud_view(msg: Any, topic: str) -> npt.NDArray[np.void]:
    """The points of ``msg`` as a (height, width) structured array viewing ``msg.data``.

    Fields named ``rgb``/``rgba`` of 4-byte type are typed as unsigned words so their packed
    bytes can be split; fields without a name or repeating an earlier name are left out.
    """
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    order = ">" if msg.is_bigendian else "<"
    names: list[str] = []
    formats: list[np.dtype[Any]] = []
    offsets: list[int] = []
    for field in msg.fields:
        if not field.name or field.name in names:
            continue
        code = _DATATYPES.get(int(field.datatype))
        if code is None:
            msg_ = (
                f"{topic}: PointCloud2 field {field.name!r} has datatype {field.datatype}, "
                "which is not one of the PointField types 1..8 (INT8..FLOAT64); fix the publisher"
            )
            raise ConvertError(msg_)
        if field.name in _PACKED_COLOR_FIELDS and code[1] == "4":
            code = "u4"
        base = np.dtype(order + code)
        count = max(int(field.count), 1)
        fmt = base if count == 1 else np.dtype((base, (count,)))
        if int(field.offset) + fmt.itemsize > point_step:
            msg_ = (
                f"{topic}: PointCloud2 field {field.name!r} (offset {field.offset}, "
                f"{fmt.itemsize} bytes) does not fit in point_step {point_step}"
            )
            raise ConvertError(msg_)
        names.append(field.name)
        formats.append(fmt)
        offsets.append(int(field.offset))
    dtype = np.dtype(
        {"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step}
    )
    data = msg.data
    if height * width == 0:
        return np.zeros((height, width), dtype=dtype)
    if height == 1:
        # One row needs no stride; some drivers leave row_step 0 for unorganised clouds.
        row_step = width * point_step
    if row_step < width * point_step:
        msg_ = (
            f"{topic}: PointCloud2 row_step {row_step} is shorter than a row of {width} points "
            f"of point_step {point_step} ({width * point_step} bytes); fix the publisher"
        )
        raise ConvertError(msg_)
    needed = (height - 1) * row_step + width * point_step
    if len(data) < needed:
        msg_ = (
            f"{topic}: PointCloud2 of {height}x{width} points with point_step {point_step} and "
            f"row_step {row_step} needs {needed} bytes, but data has {len(data)} bytes; the "
            "message is truncated"
        )
        raise ConvertError(msg_)
    view: npt.NDArray[np.void] = np.ndarray(
        shape=(height, width), dtype=dtype, buffer=data, strides=(row_step, point_step)
    )
    return view


def _scalar_field(
    points: npt.NDArray[np.void], name: str, keep: npt.NDArray[np.bool_] | slice, topic: str
) -> npt.NDArray[Any]:
    values = points[name]
    if values.ndim != points.ndim:
        msg = (
            f"{topic}: PointCloud2 field {name!r} has count > 1; only single-valued fields "
            "can be positions or colour sources (choose another color_field)"
        )
        raise ConvertError(msg)
    # Flattening copies only this field, and only when rows are padded.
    return values.reshape(-1)[keep]


def _colors(
    points: npt.NDArray[np.void], keep: npt.NDArray[np.bool_] | slice, ctx: ConvertContext
) -> npt.NDArray[np.uint8]:
    """Colours of the kept points: packed rgb(a), else r/g/b(/a) fields, else a colormap."""
    names = points.dtype.names or ()
    options = ctx.options(PointCloudOptions)
    requested = options.color_field
    if requested is None:
        packed = next((n for n in _PACKED_COLOR_FIELDS if n in names), None)
        if packed is not None and points.dtype[packed].kind == "u":
            word = _scalar_field(points, packed, keep, ctx.topic).astype(np.uint32)
            shifts = (16, 8, 0, 24) if packed == "rgba" else (16, 8, 0)
            return np.stack([(word >> s) & 0xFF for s in shifts], axis=-1).astype(np.uint8)
        if {"r", "g", "b"} <= set(names):
            channels = [c for c in ("r", "g", "b", "a") if c in names]
            rgba = np.stack([_scalar_field(points, c, keep, ctx.topic) for c in channels], -1)
            finite = rgba[np.isfinite(rgba)] if rgba.dtype.kind == "f" else rgba[:0]
            if finite.size and finite.max() <= 1.0:
                rgba = rgba * 255.0  # float channels in [0, 1] (Open3D-style clouds)
            bytes8: npt.NDArray[np.uint8] = np.clip(np.nan_to_num(rgba), 0, 255).astype(np.uint8)
            return bytes8
        requested = "intensity" if "intensity" in names else "z"
    if requested not in names:
        msg = (
            f"{ctx.topic}: color_field {requested!r} is not a field of this PointCloud2; "
            f"its fields are {', '.join(names)}"
        )
        raise ConvertError(msg)
    try:
        return apply_colormap(
            _scalar_field(points, requested, keep, ctx.topic),
            vmin=options.color_min,
            vmax=options.color_max,
            name=options.colormap,
        )
    except ValueError as err:  # an unknown colormap name in the topic's options
        raise ConvertError(f"{ctx.topic}: {err}") from err


def convert_pointcloud2(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    view = cloud_view(msg, ctx.topic)
    names = view.dtype.names or ()
    missing = [axis for axis in "xyz" if axis not in names]
    if missing:
        msg_ = (
            f"{ctx.topic}: PointCloud2 has no {'/'.join(missing)} field (fields: "
            f"{', '.join(names) or 'none'}); only clouds with x, y, z positions can be shown"
        )
        raise ConvertError(msg_)
    everything = slice(None)
    positions = np.stack(
        [_scalar_field(view, axis, everything, ctx.topic) for axis in "xyz"], axis=-1
    ).astype(np.float32)
    finite = np.all(np.isfinite(positions), axis=1)
    keep: npt.NDArray[np.bool_] | slice = everything if bool(finite.all()) else finite
    points = rr.Points3D(
        positions[keep], colors=_colors(view, keep, ctx), radii=ctx.options(PointCloudOptions).radius
    )
    frame = frame_components(ctx.frame(msg.header.frame_id))
    return [LogItem(ctx.entity_path, (points, *frame))]


SPEC = per_message(convert_pointcloud2)
