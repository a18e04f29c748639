"""What SLAM is told: which topics feed it and how its engine is tuned (``slam:`` in the host
configuration, ``--slam`` on the command line). The defaults live here only; the JSON Schema
(``schemas/host.schema.json``, ``$defs/slam``) describes each key for users, and a test checks
the two name the same keys."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

ODOMETRY_FROM_TF = "tf"
NO_ODOMETRY = "none"


@dataclass(frozen=True, slots=True)
class SlamSettings:
    """One robot's SLAM settings; lengths in metres, angles in degrees."""

    enabled: bool = False
    scan: str = "/scan"
    """The sensor_msgs/LaserScan topic (a topic glob: the first matching topic is used)."""
    odometry: str = "/odom"
    """A nav_msgs/Odometry topic; ``tf`` for the ``odom_frame -> base_frame`` transforms of /tf;
    ``none`` for scan matching alone."""
    odom_frame: str = "odom"
    base_frame: str | None = None
    """The robot's base frame; default: the Odometry's child_frame_id, else base_footprint or
    base_link, whichever /tf moves."""
    map_frame: str = "map"
    resolution: float = 0.05
    max_range: float | None = 20.0
    """Echoes farther than this are taken as free space up to it; null: the laser's range_max.
    slam_toolbox's default (max_laser_range): far echoes are too sparse to draw walls with, and
    drawing an 80 m laser's free space costs a 3,200-cell-wide patch per keyframe."""
    min_points: int = 20
    """Scans with fewer echoes are skipped."""
    keyframe_distance: float = 0.25
    keyframe_angle: float = 15.0
    local_keyframes: int = 20
    """How many of the latest keyframes make the local map each scan is matched against."""
    max_correspondence: float = 0.3
    min_matched: float = 0.3
    """A scan match whose fraction of echoes with a partner in the map is lower is not trusted:
    the odometry's prediction is used instead."""
    max_correction: float = 0.5
    """A scan match moving the pose farther than this from the odometry's prediction is not
    trusted (metres; the angle bound is ten times this in radians' degrees, 5 deg per 0.1 m)."""
    loop_radius: float = 3.0
    """Keyframes this close to a new keyframe (by the current estimate) are loop candidates..."""
    loop_min_separation: int = 30
    """... if at least this many keyframes lie between them (so neighbours do not count)."""
    loop_min_matched: float = 0.65
    odometry_jump: float = 0.5
    """An odometry step between two scans longer than this (or turning more than 45 deg) is a
    reset or a jump, not motion: a new trajectory segment starts and the map is kept."""
    map_period: float = 1.0
    """Seconds of robot time between two maps logged (the last one at the end, always)."""

    def check(self) -> list[str]:
        """What is out of range, each as ``key: problem``."""
        problems = []
        positive = ("resolution", "keyframe_distance", "keyframe_angle", "max_correspondence",
                    "max_correction", "loop_radius", "odometry_jump", "map_period")
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                problems.append(f"{name}: {value} must be a positive number")
        if self.max_range is not None and not (math.isfinite(self.max_range) and self.max_range > 0):
            problems.append(f"max_range: {self.max_range} must be a positive number of metres")
        for name in ("min_matched", "loop_min_matched"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                problems.append(f"{name}: {value} must be a fraction in [0, 1]")
        for name in ("min_points", "local_keyframes", "loop_min_separation"):
            if getattr(self, name) < 1:
                problems.append(f"{name}: {getattr(self, name)} must be at least 1")
        return problems


FIELDS: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(SlamSettings))


def settings_from(values: Mapping[str, Any], base: SlamSettings | None = None) -> SlamSettings:
    """``base`` (default: the defaults) with ``values`` over it; YAML integers become floats
    where a key is a length. Raises ValueError naming keys that are not settings."""
    unknown = sorted(set(values) - set(FIELDS))
    if unknown:
        msg = f"unknown SLAM setting {', '.join(unknown)} (the settings: {', '.join(FIELDS)})"
        raise ValueError(msg)
    base = base or SlamSettings()
    floats = {f.name for f in dataclasses.fields(SlamSettings) if "float" in str(f.type)}
    typed: dict[str, Any] = {
        k: float(v) if k in floats and isinstance(v, int) and not isinstance(v, bool) else v
        for k, v in values.items()
    }
    return dataclasses.replace(base, **typed)
