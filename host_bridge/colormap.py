"""Vectorised colormaps for converters (range-coloured scans, intensity-coloured clouds)."""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt

_CV2_MAPS = {
    "turbo": cv2.COLORMAP_TURBO,
    "viridis": cv2.COLORMAP_VIRIDIS,
    "plasma": cv2.COLORMAP_PLASMA,
    "inferno": cv2.COLORMAP_INFERNO,
    "magma": cv2.COLORMAP_MAGMA,
    "jet": cv2.COLORMAP_JET,
    "gray": None,
}
COLORMAPS = tuple(_CV2_MAPS)


def apply_colormap(
    values: npt.ArrayLike, vmin: float | None = None, vmax: float | None = None,
    name: str = "turbo",
) -> npt.NDArray[np.uint8]:
    """RGB uint8 colours, shape (N, 3), for ``values`` scaled from [vmin, vmax] (default: data range)."""
    if name not in _CV2_MAPS:
        msg = f"unknown colormap {name!r}; choose one of {', '.join(COLORMAPS)}"
        raise ValueError(msg)
    v = np.asarray(values, dtype=np.float64).ravel()
    if v.size == 0:
        return np.zeros((0, 3), dtype=np.uint8)
    lo = float(np.nanmin(v)) if vmin is None else vmin
    hi = float(np.nanmax(v)) if vmax is None else vmax
    span = hi - lo if hi > lo else 1.0
    scaled = np.nan_to_num((v - lo) / span, nan=0.0)
    index = (np.clip(scaled, 0.0, 1.0) * 255.0).astype(np.uint8)
    cv_map = _CV2_MAPS[name]
    if cv_map is None:
        return np.repeat(index[:, None], 3, axis=1)
    bgr = cv2.applyColorMap(index.reshape(-1, 1), cv_map).reshape(-1, 3)
    return np.ascontiguousarray(bgr[:, ::-1])
