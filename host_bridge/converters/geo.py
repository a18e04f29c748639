"""sensor_msgs/NavSatFix -> GeoPoints on a map view, plus altitude as a scalar.

Fixes with ``status == STATUS_NO_FIX`` (-1) or a NaN latitude/longitude are dropped: drivers
publish them while searching for satellites, and a point at (0, 0) or NaN would send the map to
the Gulf of Guinea. With a known covariance the point's radius is the 1-sigma horizontal error in
metres (GeoPoints takes positive radii as metres, negative as UI points), so the dot shows how
much to trust the fix; otherwise it is ``radius`` UI points (option).
"""

from __future__ import annotations

import numpy as np
import rerun as rr

from host_bridge.converters._common import stamps_ns
from host_bridge.converters.scalars import scalar_columns
from host_bridge.core.contract import ColumnsItem, LogEntry, Run
from host_bridge.core.options import NavSatFixOptions

STATUS_NO_FIX = -1
COVARIANCE_TYPE_UNKNOWN = 0


def convert_navsatfix(run: Run) -> list[LogEntry]:
    """A fix per message with a fix, and its altitude, read as columns."""
    columns = run.columns()
    fixes = np.stack(
        [columns[name].astype(np.float64) for name in ("latitude", "longitude", "altitude")], axis=1
    )
    status = columns["status.status"]
    covariance = columns["position_covariance"].astype(np.float64)
    known = columns["position_covariance_type"] != COVARIANCE_TYPE_UNKNOWN
    with np.errstate(invalid="ignore"):
        sigma = np.sqrt(np.maximum(covariance[:, 0], covariance[:, 4]))  # east, north variances
    ui_radius = -abs(run.options(NavSatFixOptions).radius)
    radii = np.where(known & np.isfinite(sigma) & (sigma > 0.0), sigma, ui_radius)
    valid = (status != STATUS_NO_FIX) & np.isfinite(fixes[:, :2]).all(axis=1)
    stamps = stamps_ns(columns)
    items: list[LogEntry] = []
    rows = np.flatnonzero(valid)
    for entries, times in run.times(stamps[rows], rows):
        points = rr.GeoPoints.columns(positions=fixes[rows[entries], :2], radii=radii[rows[entries]])
        items.append(ColumnsItem(run.entity_path, list(points), times))
    rows = np.flatnonzero(valid & np.isfinite(fixes[:, 2]))
    for entries, times in run.times(stamps[rows], rows):
        items.append(scalar_columns(run.child_path("altitude"), fixes[rows[entries], 2], times))
    return items


SPEC = convert_navsatfix
