"""Small numeric messages -> Scalars: std_msgs numbers and arrays, times, environment sensors,
batteries and joint states.

These are the high-rate small types: a run of messages becomes one ``send_columns`` per
sub-entity. Types of fixed layout are read as columns (a *columns extractor*: the run's columns
-> values); the others (arrays whose length varies, batteries) are decoded and described by an
*extractor* (message -> values per sub-entity).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
import numpy.typing as npt
import rerun as rr

from host_bridge.converters._common import stamps_ns
from host_bridge.core.columns import Columns
from host_bridge.core.contract import (
    ColumnsItem,
    Converter,
    LogEntry,
    LogItem,
    Run,
    TopicContext,
    component_columns,
)
from host_bridge.errors import ConvertError

SubPath = tuple[str, ...]
"""Entity path parts below the topic entity; ``()`` is the topic entity itself."""
Values = float | Sequence[float] | npt.NDArray[Any]
Extractor = Callable[[Any, str], Mapping[SubPath, Values]]
"""(message, topic) -> values per sub-entity; several values make a multi-series plot."""


@dataclass(slots=True)
class _Legends:
    """Per topic: whether its series names were sent."""

    sent: bool = False


def series_names_once(
    ctx: TopicContext, names: Mapping[SubPath, Sequence[str]]
) -> list[LogEntry]:
    """Static ``SeriesLines`` legends (x, y, z, ...), sent with the first message of a topic."""
    legends = ctx.state(_Legends)
    if not names or legends.sent:
        return []
    legends.sent = True
    return [
        LogItem(ctx.child_path(*sub), (rr.SeriesLines(names=list(labels)),), static=True)
        for sub, labels in names.items()
    ]


def scalar_columns(
    path: str, values: npt.ArrayLike, times: Mapping[str, npt.NDArray[np.int64]]
) -> ColumnsItem:
    """One row per entry of ``values`` (shape (n,) or (n, series))."""
    values = np.asarray(values, np.float64)
    lengths = np.full(len(values), math.prod(values.shape[1:]))
    return ColumnsItem(path, component_columns(rr.Scalars, lengths, scalars=values), times)


XYZ = ("x", "y", "z")


def vector_plots(
    run: Run, vectors: Sequence[tuple[SubPath, npt.NDArray[np.float64]]], stamps: npt.NDArray[np.int64],
) -> list[LogEntry]:
    """Each Vector3 of a run (its path below the topic entity, its (n, 3) values) as one plot
    with an x, y and z series (legends sent once). One entity per vector, not per axis: each
    entity is a chunk per flush to a viewer, which takes chunks in at a cost each (an Odometry's
    twist as six entities was the largest share of a 10-robot demo's chunks in a viewer), as
    Rerun's own ROS example plots a velocity."""
    items = series_names_once(run, {sub: XYZ for sub, _ in vectors})
    for rows, times in run.times(stamps):
        items.extend(scalar_columns(run.child_path(*sub), values[rows], times)
                     for sub, values in vectors)
    return items


def _rows_column(parts: list[Values]) -> list[Any]:
    """A Scalars column with one row per part; rows may differ in length (a growing array)."""
    try:
        return list(rr.Scalars.columns(scalars=np.asarray(parts, np.float64)))
    except ValueError:  # ragged rows
        flat = [np.atleast_1d(np.asarray(p, np.float64)) for p in parts]
        columns = rr.Scalars.columns(scalars=np.concatenate(flat))
        return list(columns.partition([len(p) for p in flat]))


def series_converter(
    extract: Extractor, names: Mapping[SubPath, Sequence[str]] | None = None
) -> Converter:
    """The converter of a type whose extractor yields its values from each decoded message."""
    legends = names or {}

    def convert(run: Run) -> list[LogEntry]:
        rows: dict[SubPath, list[int]] = {}
        chunks: dict[SubPath, list[Values]] = {}
        for i, msg in enumerate(run.messages()):
            for sub, values in extract(msg, run.topic).items():
                rows.setdefault(sub, []).append(i)
                chunks.setdefault(sub, []).append(values)
        stamps = run.stamps()
        items = series_names_once(run, legends)
        for sub, parts in chunks.items():
            indices = np.array(rows[sub], np.intp)
            for entries, times in run.times(None if stamps is None else stamps[indices], indices):
                picked = parts if len(entries) == len(parts) else [parts[i] for i in entries.tolist()]
                items.append(ColumnsItem(run.child_path(*sub), _rows_column(picked), times))
        return items

    return convert


ColumnsExtractor = Callable[[Columns], npt.NDArray[Any]]
"""A run's columns -> its values, shape (n,) for one series or (n, series)."""


def columns_series(
    extract: ColumnsExtractor,
    names: Mapping[SubPath, Sequence[str]] | None = None,
    *,
    skip_unread: bool = False,
) -> Converter:
    """A plot at the topic entity of the values ``extract`` reads from a run's columns, one row
    per message at its header stamp (a type without a header: its arrival times).
    ``skip_unread``: a message whose values are all NaN ("no new reading") logs no row."""
    legends = names or {}

    def convert(run: Run) -> list[LogEntry]:
        columns = run.columns()
        values = np.asarray(extract(columns), np.float64)
        stamps = stamps_ns(columns) if "header.stamp.sec" in columns.paths else None
        rows = np.arange(len(values))
        if skip_unread:
            read = ~np.isnan(values.reshape(len(values), -1)).all(axis=1)
            rows = rows[read]
        items = series_names_once(run, legends)
        for entries, times in run.times(None if stamps is None else stamps[rows], rows):
            items.append(scalar_columns(run.entity_path, values[rows[entries]], times))
        return items

    return convert


def _column(path: str) -> ColumnsExtractor:
    def extract(columns: Columns) -> npt.NDArray[Any]:
        return columns[path]

    return extract


def _seconds(columns: Columns) -> npt.NDArray[np.float64]:
    seconds: npt.NDArray[np.float64] = columns["sec"].astype(np.float64)
    return seconds + columns["nanosec"].astype(np.float64) * 1e-9


def _array(msg: Any, _topic: str) -> Mapping[SubPath, Values]:
    return {(): msg.data}


def _battery(msg: Any, _topic: str) -> Mapping[SubPath, Values]:
    # ROS 1 (melodic) BatteryState has no temperature fields.
    series: dict[SubPath, Values] = {
        (name,): float(getattr(msg, name))
        for name in ("voltage", "current", "charge", "percentage", "temperature")
        if hasattr(msg, name)
    }
    for name in ("cell_voltage", "cell_temperature"):
        cells = getattr(msg, name, ())
        if len(cells):
            series[(name,)] = cells
    return series


JOINT_QUANTITIES = ("position", "velocity", "effort")


def convert_joint_state(run: Run) -> list[LogEntry]:
    """``<topic>/<joint>/<quantity>`` per joint and quantity of each block of messages naming
    the same joints, read as columns; a quantity a driver does not measure is empty and left
    out."""
    columns = run.columns()
    stamps = stamps_ns(columns)
    items: list[LogEntry] = []
    for block in columns.blocks:
        names = [rr.escape_entity_path_part(name) for name in cast(tuple[str, ...], block.strings["name"])]
        groups = run.times(stamps[block.rows], block.rows)
        for quantity in JOINT_QUANTITIES:
            values = block.numbers[quantity]
            if values.shape[1] == 0:
                continue
            if values.shape[1] != len(names):
                msg = (
                    f"{run.topic}: JointState has {len(names)} names but {values.shape[1]} "
                    f"{quantity} values; each of position/velocity/effort must be empty or one "
                    "per name"
                )
                raise ConvertError(msg)
            for entries, times in groups:
                items.extend(
                    scalar_columns(run.child_path(name, quantity), values[entries, i], times)
                    for i, name in enumerate(names)
                )
    return items


NUMBER = columns_series(_column("data"))
"""std_msgs' single numbers (``data``: Bool, Byte, Char, Int8 ... Float64)."""
NUMBER_ARRAY = series_converter(_array)
"""std_msgs' ``*MultiArray``: one multi-series plot (message by message: lengths vary)."""
SECONDS = columns_series(_seconds)
"""builtin_interfaces Time and Duration."""
TEMPERATURE = columns_series(_column("temperature"))
FLUID_PRESSURE = columns_series(_column("fluid_pressure"))
ILLUMINANCE = columns_series(_column("illuminance"))
RELATIVE_HUMIDITY = columns_series(_column("relative_humidity"))
BATTERY = series_converter(_battery)
JOINT_STATE = convert_joint_state
"""JointState's plots; its row combines them with joints.JOINT_STATE (the model moves)."""
