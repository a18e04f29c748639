"""Fallback for every type without a converter: numeric fields as Scalars, text as TextLog.

Works on any rosbags message object, custom types included, so an unknown type is plotted
rather than dropped. Numeric arrays up to ``max_array`` (option, default 64) elements become
one multi-series Scalars entity; longer ones (a custom scan, a histogram, raw bytes) a
``BarChart`` of the latest message, value against index. The header is the time axis, not data,
so it is skipped; so are the message's constants (``LIMIT=5`` in the .msg), which are not data.
A Vector3 or Point field is one plot with an x, y and z series, as the typed converters plot
them (a /cmd_vel that changes from Twist to TwistStamped stays on the same plots).

Sequences of nested messages show their first :data:`MAX_SEQUENCE_MESSAGES` elements (each
element's leaves are their own entities); the rest is reported once per topic, never dropped
silently.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterator, Sequence
from dataclasses import Field, fields, is_dataclass
from operator import attrgetter
from typing import Any

import numpy as np
import rerun as rr

from host_bridge.converters.scalars import XYZ, series_names_once
from host_bridge.core.contract import ColumnsItem, LogEntry, LogItem, Run
from host_bridge.core.options import GenericOptions
from host_bridge.errors import PartialConvertError

_TIME_TYPES = ("builtin_interfaces/msg/Time", "builtin_interfaces/msg/Duration")
_VECTOR_TYPES = ("geometry_msgs/msg/Vector3", "geometry_msgs/msg/Point", "geometry_msgs/msg/Point32")
_XYZ = attrgetter(*XYZ)
MAX_SEQUENCE_MESSAGES = 16

Leaf = float | str | np.ndarray[Any, Any] | tuple[float, ...]
"""A field's value: a number, text, an array of numbers, or a Vector3's or Point's x, y and z."""


def data_fields(msg: Any) -> list[Field[Any]]:
    """A message's data fields. rosbags' message classes also list ``__msgtype__`` and the
    constants as dataclass fields (annotated ``ClassVar`` in strings, which dataclasses cannot
    tell apart from data)."""
    return [
        f for f in fields(msg)
        if not f.name.startswith("__") and not str(f.type).startswith("ClassVar")
    ]


def flatten(msg: Any, prefix: str, truncated: set[str]) -> Iterator[tuple[str, Leaf]]:
    """(path, value) leaves of a message: floats, strings, or numeric numpy arrays.
    Paths of sequences cut at :data:`MAX_SEQUENCE_MESSAGES` are added to ``truncated``."""
    for f in data_fields(msg):
        if f.name == "header" and prefix == "":
            continue
        yield from _leaves(getattr(msg, f.name), f"{prefix}{f.name}", truncated)


def _leaves(value: Any, path: str, truncated: set[str]) -> Iterator[tuple[str, Leaf]]:
    if is_dataclass(value):
        msgtype = getattr(value, "__msgtype__", "")
        if msgtype in _TIME_TYPES:
            yield path, getattr(value, "sec") + getattr(value, "nanosec") * 1e-9  # noqa: B009
        elif msgtype in _VECTOR_TYPES:
            yield path, tuple(map(float, _XYZ(value)))
        else:
            yield from flatten(value, path + "/", truncated)
    elif isinstance(value, (bool, int, float, np.number, np.bool_)):
        yield path, float(value)
    elif isinstance(value, str):
        yield path, value
    elif isinstance(value, np.ndarray):
        if value.dtype.kind in "biuf" and value.size > 0:
            yield path, value.ravel()
    elif isinstance(value, (list, tuple)):
        if len(value) > MAX_SEQUENCE_MESSAGES:
            truncated.add(path)
        for i, item in enumerate(value[:MAX_SEQUENCE_MESSAGES]):
            yield from _leaves(item, f"{path}/{i}", truncated)


def _bar_chart(values: np.ndarray[Any, Any]) -> rr.BarChart:
    return rr.BarChart(values.astype(np.uint8) if values.dtype.kind == "b" else values)


def _column(values: Sequence[Leaf]) -> Any:
    """One path's values, one row each: text, numbers, or arrays (or vectors) of numbers."""
    if isinstance(values[0], str):
        return rr.TextLog.columns(text=[str(v) for v in values])
    if isinstance(values[0], (np.ndarray, tuple)):
        lengths = [np.size(v) for v in values]
        flat = np.concatenate([np.atleast_1d(np.asarray(v, dtype=np.float64)) for v in values])
        return rr.Scalars.columns(scalars=flat).partition(lengths)
    return rr.Scalars.columns(scalars=np.asarray(values, dtype=np.float64))


def convert_generic(run: Run) -> list[LogEntry]:
    max_array = run.options(GenericOptions).max_array
    msgs = run.messages()
    stamps = run.stamps()
    rows: dict[str, tuple[list[int], list[Leaf]]] = defaultdict(lambda: ([], []))
    items: list[LogEntry] = []
    truncated: set[str] = set()
    for row, msg in enumerate(msgs):
        for path, value in flatten(msg, "", truncated):
            if isinstance(value, np.ndarray) and value.size > max_array:
                at = run.row_times(row, None if stamps is None else int(stamps[row]))
                items.append(LogItem(run.child_path(path), (_bar_chart(value),), times=at))
                continue
            indices, values = rows[path]
            indices.append(row)
            values.append(value)
    vectors = [path for path, (_, values) in rows.items() if isinstance(values[0], tuple)]
    items += series_names_once(run, {tuple(path.split("/")): XYZ for path in vectors})
    for path, (indices, values) in rows.items():
        index = np.array(indices, np.intp)
        for entries, times in run.times(None if stamps is None else stamps[index], index):
            picked = values if len(entries) == len(values) else [values[i] for i in entries.tolist()]
            items.append(ColumnsItem(run.child_path(path), _column(picked), times))
    if truncated:
        text = (
            f"{run.topic}: no converter for {getattr(msgs[0], '__msgtype__', 'this type')}; "
            f"the generic one shows the first {MAX_SEQUENCE_MESSAGES} elements of "
            f"{', '.join(sorted(truncated))}"
        )
        raise PartialConvertError(text, items)
    return items


SPEC = convert_generic
