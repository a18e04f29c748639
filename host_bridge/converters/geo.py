"""sensor_msgs/NavSatFix -> GeoPoints on a map view, plus altitude as a scalar.

Fixes with ``status == STATUS_NO_FIX`` (-1) or a NaN latitude/longitude are dropped: drivers
publish them while searching for satellites, and a point at (0, 0) or NaN would send the map to
the Gulf of Guinea. With a known covariance the point's radius is the 1-sigma horizontal error in
metres (GeoPoints takes positive radii as metres, negative as UI points), so the dot shows how
much to trust the fix; otherwise it is ``radius`` UI points (option).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import rerun as rr

from host_bridge.contract import ColumnsItem, ConvertContext, ConverterSpec, LogEntry
from host_bridge.converters._common import time_columns
from host_bridge.converters.scalars import scalar_columns
from host_bridge.options import NavSatFixOptions

STATUS_NO_FIX = -1
COVARIANCE_TYPE_UNKNOWN = 0


def convert_navsatfix_run(
    msgs: Sequence[Any], ctxs: Sequence[ConvertContext]
) -> list[LogEntry]:
    ctx0 = ctxs[0]
    n = len(msgs)
    fixes = np.array(
        [(m.latitude, m.longitude, m.altitude, m.status.status) for m in msgs], dtype=np.float64
    ).reshape(n, 4)
    covariance = np.array([m.position_covariance for m in msgs], dtype=np.float64).reshape(n, 9)
    known = np.array([m.position_covariance_type for m in msgs]) != COVARIANCE_TYPE_UNKNOWN
    with np.errstate(invalid="ignore"):
        sigma = np.sqrt(np.maximum(covariance[:, 0], covariance[:, 4]))  # east, north variances
    ui_radius = -abs(ctx0.options(NavSatFixOptions).radius)
    radii = np.where(known & np.isfinite(sigma) & (sigma > 0.0), sigma, ui_radius)
    valid = (fixes[:, 3] != STATUS_NO_FIX) & np.isfinite(fixes[:, :2]).all(axis=1)
    rows = np.flatnonzero(valid).tolist()
    items: list[LogEntry] = []
    if rows:
        points = rr.GeoPoints.columns(positions=fixes[rows, :2], radii=radii[rows])
        times = time_columns([ctxs[i] for i in rows])
        items.append(ColumnsItem(ctx0.entity_path, list(points), times))
    altitude_rows = np.flatnonzero(valid & np.isfinite(fixes[:, 2])).tolist()
    if altitude_rows:
        times = time_columns([ctxs[i] for i in altitude_rows])
        items.append(scalar_columns(ctx0.child_path("altitude"), fixes[altitude_rows, 2], times))
    return items


def convert_navsatfix(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    return convert_navsatfix_run([msg], [ctx])


SPEC = ConverterSpec(convert_navsatfix_run, single=convert_navsatfix)
