"""Vectorised colormaps for converters (range-coloured scans, intensity-coloured clouds).

Each map is a 256-entry table built once (OpenCV's maps, read back through ``applyColorMap``)
and indexed per value: building the map on every call cost a 720-ray scan 0.2 ms. Converters
take packed ``0xRRGGBBAA`` words (:func:`colormap_packed`), which Rerun stores as they are;
an (N, 3) uint8 array would be packed again by Rerun row by row.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import numpy.typing as npt

# OpenCV's names of the maps: cv2 (20 ms) is imported when a table is first made, not by every run.
_CV2_MAPS = {
    "turbo": "COLORMAP_TURBO",
    "viridis": "COLORMAP_VIRIDIS",
    "plasma": "COLORMAP_PLASMA",
    "inferno": "COLORMAP_INFERNO",
    "magma": "COLORMAP_MAGMA",
    "jet": "COLORMAP_JET",
    "gray": None,
}
COLORMAPS = tuple(_CV2_MAPS)


@cache
def colormap_table(name: str) -> npt.NDArray[np.uint8]:
    """The (256, 3) RGB table of a colormap (read-only, shared)."""
    if name not in _CV2_MAPS:
        msg = f"unknown colormap {name!r}; choose one of {', '.join(COLORMAPS)}"
        raise ValueError(msg)
    ramp = np.arange(256, dtype=np.uint8)
    cv_map = _CV2_MAPS[name]
    if cv_map is None:
        table = np.repeat(ramp[:, None], 3, axis=1)
    else:
        import cv2

        table = np.ascontiguousarray(cv2.applyColorMap(ramp[:, None], getattr(cv2, cv_map))[:, 0, ::-1])
    table.flags.writeable = False
    return table


@cache
def _packed_table(name: str) -> npt.NDArray[np.uint32]:
    rgb = colormap_table(name).astype(np.uint32)
    table: npt.NDArray[np.uint32] = (rgb[:, 0] << 24) | (rgb[:, 1] << 16) | (rgb[:, 2] << 8) | np.uint32(0xFF)
    table.flags.writeable = False
    return table


def colormap_index(
    values: npt.ArrayLike,
    vmin: float | npt.NDArray[np.float64] | None = None,
    vmax: float | npt.NDArray[np.float64] | None = None,
) -> npt.NDArray[np.uint8]:
    """Table index 0..255 of each value scaled from [vmin, vmax] (default: the data's range,
    NaNs ignored; NaN values get 0), in the shape of ``values``. ``vmin``/``vmax`` may be
    arrays broadcasting against ``values`` (one bound per row of a scan grid). The scaling is
    done in float64 whatever the values' type."""
    v = np.asarray(values)
    if v.size == 0:
        return np.zeros(v.shape, dtype=np.uint8)
    lo = np.float64(np.nanmin(v)) if vmin is None else np.asarray(vmin, dtype=np.float64)
    hi = np.float64(np.nanmax(v)) if vmax is None else np.asarray(vmax, dtype=np.float64)
    scaled = v - lo  # float64, a new array: the steps below work in place
    scaled /= np.where(hi > lo, hi - lo, 1.0)
    np.fmax(scaled, 0.0, out=scaled)  # fmax takes 0 over NaN: NaN values get index 0
    np.fmin(scaled, 1.0, out=scaled)
    scaled *= 255.0
    index: npt.NDArray[np.uint8] = scaled.astype(np.uint8)
    return index


def apply_colormap(
    values: npt.ArrayLike, vmin: float | None = None, vmax: float | None = None,
    name: str = "turbo",
) -> npt.NDArray[np.uint8]:
    """RGB uint8 colours, shape (N, 3), for ``values`` scaled from [vmin, vmax] (default: data range)."""
    table = colormap_table(name)
    colors: npt.NDArray[np.uint8] = table[colormap_index(values, vmin, vmax).ravel()]
    return colors


def colormap_packed(
    values: npt.ArrayLike,
    vmin: float | npt.NDArray[np.float64] | None = None,
    vmax: float | npt.NDArray[np.float64] | None = None,
    name: str = "turbo",
) -> npt.NDArray[np.uint32]:
    """The colours of :func:`apply_colormap` as opaque ``0xRRGGBBAA`` words, in the shape of
    ``values``."""
    table = _packed_table(name)
    colors: npt.NDArray[np.uint32] = table.take(colormap_index(values, vmin, vmax))
    return colors
