"""sensor_msgs/Range -> the sensing cone in the sensor frame, plus the range as a scalar.

The sensor looks along its frame's +x axis (REP 117). A range reading means "something at this
distance somewhere in the field of view", so the cone is drawn as the spherical sector of that
radius: its rim and four edges are all ``range`` away from the sensor, which also keeps wide
(>= 180 degree) fields of view finite. A field of view of ~0 (a laser rangefinder) is a segment.

Readings outside [min_range, max_range] or non-finite clear the cone (an empty LineStrips3D,
so the last good cone does not linger) while the scalar still records the reading; infinities
become NaN there so the plot shows a gap instead of breaking its scale. REP 117's fixed-distance
sensors (min_range == max_range) report a detection as -inf: that draws the cone at max_range.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt
import rerun as rr

from host_bridge.converters._common import frame_components
from host_bridge.core.contract import ConvertContext, LogEntry, LogItem, per_message

_RIM_SEGMENTS = 32
_EDGES = 4
_MIN_FOV = 1e-3  # rad; narrower beams are drawn as a single segment
_COLORS = {0: (0, 200, 255), 1: (255, 60, 60)}  # ULTRASOUND, INFRARED
_OTHER_COLOR = (255, 255, 255)


def cone_strips(distance: float, field_of_view: float) -> list[npt.NDArray[np.float32]]:
    """Line strips outlining a sector of radius ``distance`` around +x, apex at the origin."""
    if field_of_view < _MIN_FOV:
        return [np.array([[0.0, 0.0, 0.0], [distance, 0.0, 0.0]], dtype=np.float32)]
    half = min(field_of_view, 2.0 * math.pi) / 2.0
    angles = np.linspace(0.0, 2.0 * math.pi, _RIM_SEGMENTS + 1)
    rim = np.column_stack(
        [
            np.full_like(angles, distance * math.cos(half)),
            distance * math.sin(half) * np.cos(angles),
            distance * math.sin(half) * np.sin(angles),
        ]
    ).astype(np.float32)
    apex = np.zeros(3, dtype=np.float32)
    step = _RIM_SEGMENTS // _EDGES
    return [rim, *(np.stack([apex, rim[i]]) for i in range(0, _RIM_SEGMENTS, step))]


def _shown_distance(msg: Any) -> float | None:
    """Length of the cone to draw, None when the reading is no detection or invalid."""
    reading, low, high = float(msg.range), float(msg.min_range), float(msg.max_range)
    if low == high and reading == -math.inf:
        return high
    if not math.isfinite(reading) or reading < low or reading > high:
        return None
    return reading


def convert_range(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    distance = _shown_distance(msg)
    strips = [] if distance is None else cone_strips(distance, float(msg.field_of_view))
    color = _COLORS.get(int(msg.radiation_type), _OTHER_COLOR)
    cone = rr.LineStrips3D(strips, colors=color)
    reading = float(msg.range)
    scalar = rr.Scalars(reading if math.isfinite(reading) else math.nan)
    return [
        LogItem(ctx.entity_path, (cone, *frame_components(ctx.frame(msg.header.frame_id)))),
        LogItem(ctx.child_path("range"), (scalar,)),
    ]


SPEC = per_message(convert_range)
