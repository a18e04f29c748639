"""One laser scan as SLAM uses it: the beams in angle order, each ending in a hit or in free
space, in the robot's base frame.

What real lasers report beside echoes is sorted out here once (REP 117 and older drivers):

* a finite range in ``[range_min, range_max)`` is an echo: free space up to it, an obstacle at it;
* ``+inf``, or a range at or beyond ``range_max`` (drivers that report "no return" as
  ``range_max``), is no echo: free space up to ``range_max`` (or the SLAM ``max_range``), no
  obstacle;
* ``NaN``, ``-inf``, ``0`` and anything below ``range_min`` say nothing: the beam is left out
  (``0`` is "no return" for some drivers and "error" for others; neither tells how far the
  space is free).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


@dataclass(frozen=True, slots=True)
class Scan:
    """Beams of one scan in angle order, in the base frame.

    ``ends[i]`` is where beam ``i`` stops: its echo when ``hit[i]``, else the end of the free
    space it saw. ``adjacent[i]`` says beams ``i`` and ``i + 1`` were neighbours in the scan (no
    beam left out between them), so the free space between them is the triangle they span.
    ``origin`` is the laser's position in the base frame.
    """

    origin: FloatArray
    ends: FloatArray
    hit: BoolArray
    adjacent: BoolArray
    beams: int
    """How many beams the scan had, used or not."""

    @property
    def points(self) -> FloatArray:
        """The echoes, (n, 2)."""
        points: FloatArray = self.ends[self.hit]
        return points

    def moved(self, matrix: FloatArray) -> Scan:
        """The scan seen from another frame: ``matrix`` (4x4) maps this scan's frame into it.
        A laser mounted upside down or tilted is flattened into the plane of that frame."""
        def apply(xy: FloatArray) -> FloatArray:
            moved: FloatArray = xy @ matrix[:2, :2].T + matrix[:2, 3]
            return moved

        return Scan(apply(self.origin[None, :])[0], apply(self.ends), self.hit, self.adjacent,
                    self.beams)


def scan_from_ranges(
    ranges: npt.ArrayLike, angle_min: float, angle_increment: float, range_min: float,
    range_max: float, *, max_range: float | None = None,
) -> Scan:
    """The beams of a LaserScan, in the laser's frame (see the module docstring for which
    readings count). ``max_range``: echoes beyond it are taken as free space up to it, as the
    far returns of a long-range laser are too sparse to map walls with."""
    r = np.asarray(ranges, dtype=np.float64)
    count = r.size
    limit = range_max if max_range is None else min(range_max, max_range)
    with np.errstate(invalid="ignore"):
        lower = max(range_min, 0.0)
        echo = np.isfinite(r) & (r >= lower) & (r > 0.0) & (r < range_max)
        no_echo = (r == np.inf) | (np.isfinite(r) & (r >= range_max))
    beyond = echo & (r > limit)
    echo &= ~beyond
    no_echo |= beyond
    used = echo | no_echo
    index = np.flatnonzero(used)
    reach = np.where(echo[index], r[index], limit)
    angles = angle_min + angle_increment * index.astype(np.float64)
    ends = np.stack([reach * np.cos(angles), reach * np.sin(angles)], axis=-1)
    # Neighbours in the scan: consecutive indices, or the last and first beam of a full turn.
    adjacent = np.diff(index) == 1
    return Scan(np.zeros(2), ends, echo[index], adjacent, count)


def scan_from_msg(msg: Any, max_range: float | None = None) -> Scan:
    """:func:`scan_from_ranges` of a sensor_msgs/LaserScan."""
    return scan_from_ranges(
        msg.ranges, float(msg.angle_min), float(msg.angle_increment), float(msg.range_min),
        float(msg.range_max), max_range=max_range,
    )


def finite_scan_geometry(msg: Any) -> str | None:
    """What is wrong with a LaserScan's geometry (non-finite angles or limits), or None."""
    for name in ("angle_min", "angle_increment", "range_min", "range_max"):
        value = float(getattr(msg, name))
        if not math.isfinite(value):
            return f"{name} is {value}"
    if float(msg.range_max) <= 0.0:
        return f"range_max is {float(msg.range_max)}"
    return None
