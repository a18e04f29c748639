"""sensor_msgs/PointCloud2 -> Points3D, read through one structured numpy view of the buffer.

Every layout a driver may send (padding inside a point, padding at row ends, big-endian, any
PointField datatype, ``count > 1``) is described to numpy as one structured dtype with explicit
offsets and ``itemsize = point_step``, laid over ``msg.data`` with row and point strides, so no
Python code ever runs per point.

Copies, for the common float32 x, y, z at adjacent offsets: none when the points are just those
12 bytes (Rerun gets a view of the CDR buffer); otherwise one, of the 12 bytes of every point as
one opaque record (3x faster than gathering three strided floats). Points with a non-finite
coordinate are dropped, but the per-point mask and the copy it selects are made only when a
flat ``isfinite(...).all()`` over the positions fails. Colours go to Rerun as packed
``0xRRGGBBAA`` words (a packed rgb field is one shift and one or), which it stores as they are.
300k PCL XYZRGB points (32-byte points, NaNs): about 2.5 ms (``benchmarks/converters.py``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import numpy.typing as npt
import rerun as rr

from host_bridge.converters._common import frame_components
from host_bridge.core.colormap import colormap_packed
from host_bridge.core.contract import ConvertContext, LogEntry, LogItem, per_message
from host_bridge.core.options import PointCloudOptions
from host_bridge.errors import ConvertError

# PointField.datatype -> numpy type code (byte order is added per cloud).
_DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
# PCL packs colour as four bytes B,G,R,A of a little-endian word, usually declared FLOAT32; read
# as an unsigned word in the cloud's byte order the value is always 0xAARRGGBB.
_PACKED_COLOR_FIELDS = ("rgba", "rgb")
_XYZ_RECORD = np.dtype((np.void, 12))
MAX_POINT_STEP = 1 << 16
"""Bytes per point accepted. Far above any real point type (PCL's largest descriptor, VFH's 308
floats, is 1232 bytes), and it keeps every numpy record type built from a message's sizes small:
numpy refuses record types of 2 GiB and more with a bare ValueError."""


def cloud_view(msg: Any, topic: str) -> npt.NDArray[np.void]:
    """The points of ``msg`` as a (height, width) structured array viewing ``msg.data``.

    Fields named ``rgb``/``rgba`` of 4-byte type are typed as unsigned words so their packed
    bytes can be split; fields without a name or repeating an earlier name are left out.
    """
    height, width = int(msg.height), int(msg.width)
    point_step = int(msg.point_step)
    if point_step > MAX_POINT_STEP:
        msg_ = (
            f"{topic}: PointCloud2 point_step {point_step} is over {MAX_POINT_STEP} bytes per "
            "point, more than any point type holds; the message is corrupt"
        )
        raise ConvertError(msg_)
    # The declared sizes are checked against the data before any array is made from them.
    row_step = _checked_row_step(msg, topic, height, width, point_step)
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
        if int(field.offset) + count * base.itemsize > point_step:
            msg_ = (
                f"{topic}: PointCloud2 field {field.name!r} (offset {field.offset}, "
                f"{count * base.itemsize} bytes) does not fit in point_step {point_step}"
            )
            raise ConvertError(msg_)
        fmt = base if count == 1 else np.dtype((base, (count,)))
        names.append(field.name)
        formats.append(fmt)
        offsets.append(int(field.offset))
    dtype = np.dtype(
        {"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step}
    )
    if height * width == 0:
        return np.zeros((height, width), dtype=dtype)
    view: npt.NDArray[np.void] = np.ndarray(
        shape=(height, width), dtype=dtype, buffer=msg.data, strides=(row_step, point_step)
    )
    return view


def _checked_row_step(msg: Any, topic: str, height: int, width: int, point_step: int) -> int:
    """The stride between rows, once the declared height x width points of ``point_step``
    bytes are known to lie inside ``msg.data`` (a message declaring 10^9 points in a few bytes
    is refused here, naming both sizes)."""
    if height * width == 0:
        return 0
    row_step = int(msg.row_step)
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
    if len(msg.data) < needed:
        msg_ = (
            f"{topic}: PointCloud2 declares {height}x{width} points with point_step "
            f"{point_step} and row_step {row_step}, which needs {needed} bytes, but data has "
            f"{len(msg.data)} bytes; the message is truncated or its sizes are wrong"
        )
        raise ConvertError(msg_)
    return row_step


def _single_valued(points: npt.NDArray[np.void], name: str, topic: str) -> npt.NDArray[Any]:
    """Field ``name`` of every point, (height, width), still a view of the buffer."""
    values = points[name]
    if values.ndim != points.ndim:
        msg = (
            f"{topic}: PointCloud2 field {name!r} has count > 1; only single-valued fields "
            "can be positions or colour sources (choose another color_field)"
        )
        raise ConvertError(msg)
    return values


def _kept(values: npt.NDArray[Any], keep: npt.NDArray[np.bool_] | None) -> npt.NDArray[Any]:
    """``values`` (one per point, any shape) flattened, at the kept points only. Flattening
    copies only where rows are padded."""
    flat = values.reshape(-1)
    return flat if keep is None else flat[keep]


def _positions(points: npt.NDArray[np.void], topic: str) -> npt.NDArray[np.float32]:
    """(N, 3) float32 positions: a view of the buffer itself when the cloud is native-order
    float32 x, y, z back to back in points of 12 bytes; one copy of those 12 bytes per point
    when the points hold more; one copy with a conversion for any other layout."""
    fields: Mapping[str, tuple[Any, ...]] = points.dtype.fields or {}
    (x_type, x_at), (y_type, y_at), (z_type, z_at) = (fields[a][:2] for a in "xyz")
    adjacent = y_at == x_at + 4 and z_at == x_at + 8
    if adjacent and x_type == y_type == z_type and x_type.kind == "f" and x_type.itemsize == 4:
        # x, y, z as one opaque 12-byte record per point: copied whole, they move 3x faster
        # than three strided floats, and not at all when the points are nothing else.
        record = np.dtype(
            {"names": ["xyz"], "formats": [_XYZ_RECORD], "offsets": [x_at],
             "itemsize": points.itemsize}
        )
        records = np.ascontiguousarray(points.view(record)["xyz"])
        positions: npt.NDArray[np.float32] = records.view(x_type).reshape(-1, 3)
        if positions.dtype.isnative and positions.flags.aligned:
            return positions
        return positions.astype(np.float32)
    converted = np.empty((*points.shape, 3), dtype=np.float32)
    for k, axis in enumerate("xyz"):
        converted[..., k] = _single_valued(points, axis, topic)
    return converted.reshape(-1, 3)


def _finite_points(
    positions: npt.NDArray[np.float32],
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.bool_] | None]:
    """The points with finite x, y and z, and the mask that chose them (None: all were).

    The whole-array test is one flat reduction; the per-point mask and the copy it selects
    are made only for clouds that hold invalid points.
    """
    finite = np.isfinite(positions)
    if finite.all():
        return positions, None
    keep = finite[:, 0] & finite[:, 1] & finite[:, 2]
    # Rows as 12-byte records: a 1-D boolean index is many times faster than on (N, 3).
    rows = positions.view(_XYZ_RECORD).reshape(-1)
    return rows[keep].view(np.float32).reshape(-1, 3), keep


def _packed_rgba(channels: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint32]:
    """(N, 3 or 4) uint8 channels as ``0xRRGGBBAA`` words (opaque without an alpha channel)."""
    words = channels.astype(np.uint32)
    alpha = words[:, 3] if channels.shape[1] == 4 else np.uint32(0xFF)
    red, green, blue = (words[:, k] << np.uint32(24 - 8 * k) for k in range(3))
    packed: npt.NDArray[np.uint32] = red | green | blue | alpha
    return packed


def _colors(
    points: npt.NDArray[np.void], keep: npt.NDArray[np.bool_] | None, ctx: ConvertContext
) -> npt.NDArray[np.uint32]:
    """``0xRRGGBBAA`` colours of the kept points: packed rgb(a), else r/g/b(/a) fields, else a
    colormap. Rerun stores packed words as they are (channel arrays it packs row by row)."""
    names = points.dtype.names or ()
    options = ctx.options(PointCloudOptions)
    requested = options.color_field
    if requested is None:
        packed = next((n for n in _PACKED_COLOR_FIELDS if n in names), None)
        if packed is not None and points.dtype[packed].kind == "u":
            word = _single_valued(points, packed, ctx.topic)
            # 0x__RRGGBB / 0xAARRGGBB in the cloud's byte order -> 0xRRGGBBAA.
            alpha = word >> 24 if packed == "rgba" else 0xFF
            return _kept((word << 8) | alpha, keep).astype(np.uint32, copy=False)
        if {"r", "g", "b"} <= set(names):
            channels = [c for c in ("r", "g", "b", "a") if c in names]
            rgba = np.stack([_kept(_single_valued(points, c, ctx.topic), keep) for c in channels], -1)
            finite = rgba[np.isfinite(rgba)] if rgba.dtype.kind == "f" else rgba[:0]
            if finite.size and finite.max() <= 1.0:
                rgba = rgba * 255.0  # float channels in [0, 1] (Open3D-style clouds)
            return _packed_rgba(np.clip(np.nan_to_num(rgba), 0, 255).astype(np.uint8))
        requested = "intensity" if "intensity" in names else "z"
    if requested not in names:
        msg = (
            f"{ctx.topic}: color_field {requested!r} is not a field of this PointCloud2; "
            f"its fields are {', '.join(names)}"
        )
        raise ConvertError(msg)
    try:
        return colormap_packed(
            _kept(_single_valued(points, requested, ctx.topic), keep),
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
    positions, keep = _finite_points(_positions(view, ctx.topic))
    points = rr.Points3D(
        positions, colors=_colors(view, keep, ctx), radii=ctx.options(PointCloudOptions).radius
    )
    frame = frame_components(ctx.frame(msg.header.frame_id))
    return [LogItem(ctx.entity_path, (points, *frame))]


SPEC = per_message(convert_pointcloud2)
