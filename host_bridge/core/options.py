"""Converter options as typed records: one frozen dataclass per family of converters.

A type's row in the table (:mod:`host_bridge.table.registry`) names its record: the one its converter
reads (``ctx.options(LaserScanOptions)``, attributes mypy checks). The record is the one place
a default is written and says which options the type takes; :mod:`host_bridge.table.config` checks a
config file's option names, the ``converter`` choices and the built-in layer of
``--print-config`` against the row's record. ``schemas/host.schema.json`` describes the options
to users and says which values are valid; it holds no defaults, and
``tests/host_bridge/test_options.py`` walks the table to keep it in step with the records (same
names, compatible types, the same converter choices).

A default of ``None`` means the converter derives the value from the data (a costmap's palette
from its topic name, a wall's thickness from the grid's resolution); such options are not
printed. ``mode`` is the ``converter`` choice of the types that have alternatives, a ``Literal``
of them.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal, TypeVar

Options = TypeVar("Options")
"""A converter family's options record (one of the dataclasses below)."""

CONVERTER_OPTION = "mode"
"""The field holding the ``converter`` choice (points/rays/both, auto/depth/color)."""

LaserScanMode = Literal["points", "rays", "both"]
ImageMode = Literal["auto", "depth", "color"]


@dataclass(frozen=True, slots=True)
class LaserScanOptions:
    mode: LaserScanMode = "points"
    color_by: str = "range"
    colormap: str = "turbo"
    radius: float = 0.02


@dataclass(frozen=True, slots=True)
class ImageOptions:
    mode: ImageMode = "auto"
    depth_meter: float | None = None  # REP 118: 1000 for integer depth, 1 for float depth
    colormap: str | None = None
    depth_range: tuple[float, float] | None = None


@dataclass(frozen=True, slots=True)
class PointCloudOptions:
    color_field: str | None = None  # packed rgb(a), r/g/b, intensity, else z
    color_min: float | None = None  # the cloud's minimum
    color_max: float | None = None  # the cloud's maximum
    colormap: str = "turbo"
    radius: float | None = None  # Rerun's default point size


@dataclass(frozen=True, slots=True)
class GridDrawingOptions:
    """How a grid is drawn, a map or a nav2 costmap (see converters/occupancy.py)."""

    color_scheme: str | None = None  # costmap on topics containing "costmap", else map
    opacity: float | None = None  # 0.7 for costmaps, 1 for maps
    draw_order: float | None = None  # 0 for maps, 1 global / 2 local costmaps


@dataclass(frozen=True, slots=True)
class GridOptions(GridDrawingOptions):
    """An occupancy grid's drawing and its walls (see walls.py); a nav2 costmap has no walls."""

    walls: bool | None = None  # on for topics named map
    wall_height: float = 0.5
    wall_thickness: float | None = None  # one cell, at least 0.05 m
    wall_color: tuple[int, int, int] = (170, 180, 200)
    occupied_threshold: int = 65
    merge_distance: float | None = None  # 4.5 cells, at least 0.1 m
    merge_angle_deg: float = 5.0
    merge_gap: float = 0.35
    min_length: float = 0.3
    join_reach: float | None = None  # 4 cells, at least 0.15 m
    hough_votes: int = 8
    hough_min_length: float | None = None  # 4 cells
    hough_max_gap: float | None = None  # 2 cells


@dataclass(frozen=True, slots=True)
class GridUpdateOptions(GridOptions):
    grid_topic: str | None = None  # this topic without _updates


@dataclass(frozen=True, slots=True)
class CostmapUpdateOptions(GridDrawingOptions):
    grid_topic: str | None = None  # this topic without _updates


@dataclass(frozen=True, slots=True)
class PoseOptions:
    trail_length: int = 500
    trail_period: float = 0.1  # s between two trail rows; 0: a row for every message that moved
    axis_length: float = 0.3


@dataclass(frozen=True, slots=True)
class PoseCovarianceOptions(PoseOptions):
    sigma: float = 1.0  # RViz's default: a one-sigma ellipsoid


@dataclass(frozen=True, slots=True)
class PoseArrayOptions:
    arrow_length: float = 0.3


@dataclass(frozen=True, slots=True)
class PathOptions:
    arrows: bool = False
    arrow_length: float = 0.1


@dataclass(frozen=True, slots=True)
class ImuOptions:
    acceleration_scale: float = 0.1
    angular_velocity_scale: float = 1.0
    axis_length: float = 0.2


@dataclass(frozen=True, slots=True)
class NavSatFixOptions:
    radius: float = 5.0


@dataclass(frozen=True, slots=True)
class TfOptions:
    static: bool | None = None  # true on */tf_static


@dataclass(frozen=True, slots=True)
class GenericOptions:
    max_array: int = 64


@dataclass(frozen=True, slots=True)
class NoOptions:
    """Types whose converter takes no options (``plain`` in the schema)."""


def converter_choices(kind: type[Any]) -> tuple[str, ...]:
    """The alternative converters of ``kind``'s types (its ``mode`` Literal), () for one."""
    hint = typing.get_type_hints(kind).get(CONVERTER_OPTION)
    return typing.get_args(hint) if hint is not None else ()


def option_names(kind: type[Any]) -> tuple[str, ...]:
    """The options a config file may set for ``kind``'s types (``mode`` is their converter)."""
    return tuple(f.name for f in dataclasses.fields(kind) if f.name != CONVERTER_OPTION)


def fixed_defaults(kind: type[Any]) -> dict[str, Any]:
    """The defaults ``kind`` writes down (not the derived ones), as YAML would spell them."""
    found = {}
    for option in dataclasses.fields(kind):
        if option.default is not None and option.default is not dataclasses.MISSING:
            value = option.default
            found[option.name] = list(value) if isinstance(value, tuple) else value
    return found


def _accepts_float(hint: Any) -> bool:
    return hint is float or (isinstance(hint, types.UnionType) and float in typing.get_args(hint))


def options_from(kind: type[Options], values: Mapping[str, Any]) -> Options:
    """``kind`` with ``values`` (a topic's options as the configuration resolved them) over its
    defaults: YAML integers become floats where the option is a number, lists tuples.

    Raises ValueError naming options ``kind`` does not have: the configuration only lets through
    the options of the topic's type, so that is a converter asking for the wrong record.
    """
    hints = typing.get_type_hints(kind)
    unknown = sorted(set(values) - set(hints))
    if unknown:
        msg = f"{kind.__name__} takes no option {', '.join(unknown)} (its options: {', '.join(hints)})"
        raise ValueError(msg)
    return kind(**{name: _typed(value, hints[name]) for name, value in values.items()})


def _typed(value: Any, hint: Any) -> Any:
    if isinstance(value, list):
        return tuple(value)
    if isinstance(value, int) and not isinstance(value, bool) and _accepts_float(hint):
        return float(value)
    return value
