"""Fallback for every type without a converter: numeric fields as Scalars, text as TextLog.

Works on any rosbags message object, custom types included, so an unknown type is plotted
rather than dropped. Numeric arrays up to ``max_array`` (option, default 64) elements become
one multi-series Scalars entity; longer ones are left out (an image or cloud belongs to a real
converter). The header is the time axis, not data, so it is skipped.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterator, Sequence
from dataclasses import fields, is_dataclass
from typing import Any

import numpy as np
import rerun as rr

from host_bridge.converters._common import time_columns
from host_bridge.registry import ColumnsItem, ConvertContext, ConverterSpec, LogEntry

_TIME_TYPES = ("builtin_interfaces/msg/Time", "builtin_interfaces/msg/Duration")
_MAX_SEQUENCE_MESSAGES = 16


def flatten(msg: Any, prefix: str, max_array: int) -> Iterator[tuple[str, float | str | Any]]:
    """(path, value) leaves of a message: floats, strings, or small numeric numpy arrays."""
    for f in fields(msg):
        if f.name.startswith("__") or (f.name == "header" and prefix == ""):
            continue
        yield from _leaves(getattr(msg, f.name), f"{prefix}{f.name}", max_array)


def _leaves(value: Any, path: str, max_array: int) -> Iterator[tuple[str, float | str | Any]]:
    if is_dataclass(value):
        if getattr(value, "__msgtype__", "") in _TIME_TYPES:
            yield path, getattr(value, "sec") + getattr(value, "nanosec") * 1e-9  # noqa: B009
        else:
            yield from flatten(value, path + "/", max_array)
    elif isinstance(value, (bool, int, float, np.number, np.bool_)):
        yield path, float(value)
    elif isinstance(value, str):
        yield path, value
    elif isinstance(value, np.ndarray):
        if value.dtype.kind in "biuf" and 0 < value.size <= max_array:
            yield path, value.astype(np.float64).ravel()
    elif isinstance(value, (list, tuple)):
        for i, item in enumerate(value[:_MAX_SEQUENCE_MESSAGES]):
            yield from _leaves(item, f"{path}/{i}", max_array)


def convert_generic_run(msgs: Sequence[Any], ctxs: Sequence[ConvertContext]) -> list[LogEntry]:
    max_array = int(ctxs[0].options.get("max_array", 64))
    rows: dict[str, tuple[list[int], list[Any]]] = defaultdict(lambda: ([], []))
    for row, msg in enumerate(msgs):
        for path, value in flatten(msg, "", max_array):
            indices, values = rows[path]
            indices.append(row)
            values.append(value)
    items: list[LogEntry] = []
    for path, (indices, values) in rows.items():
        entity = ctxs[0].child_path(path)
        times = time_columns([ctxs[i] for i in indices])
        if isinstance(values[0], str):
            columns = rr.TextLog.columns(text=[str(v) for v in values])
        elif isinstance(values[0], np.ndarray):
            lengths = [np.size(v) for v in values]
            flat = np.concatenate([np.atleast_1d(np.asarray(v, dtype=np.float64)) for v in values])
            columns = rr.Scalars.columns(scalars=flat).partition(lengths)
        else:
            columns = rr.Scalars.columns(scalars=np.asarray(values, dtype=np.float64))
        items.append(ColumnsItem(entity, columns, times))
    return items


def convert_generic(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    return convert_generic_run([msg], [ctx])


SPEC = ConverterSpec(convert_generic, convert_generic_run)
