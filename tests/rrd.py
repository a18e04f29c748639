"""Reading .rrd files back for assertions, with Rerun's own reader (rerun.chunk.RrdReader)."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from typing import Any

import pyarrow as pa
from rerun.chunk import RrdReader


def entity_rows(path: Path, entity: str | None = None) -> dict[str, list[dict[str, Any]]]:
    """Rows per entity path: each row maps column names (timelines, components) to values.

    Timelines come back as int64 nanoseconds; rows of one entity are sorted by the first of
    ros_time / log_time / receive_time present, static rows first.
    """
    rows: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for chunk in RrdReader(path).stream():
        if entity is not None and chunk.entity_path != entity:
            continue
        batch = chunk.to_record_batch()
        columns = {}
        for name in batch.schema.names:
            if name == "rerun.controls.RowId":
                continue
            column = batch.column(name)
            if pa.types.is_timestamp(column.type):
                column = column.cast(pa.int64())
            columns[name] = column.to_pylist()
        for i in range(chunk.num_rows):
            row = {name: values[i] for name, values in columns.items()}
            row["static"] = chunk.is_static
            rows[chunk.entity_path].append(row)
    for entity_path_rows in rows.values():
        entity_path_rows.sort(key=_row_order)
    return dict(rows)


def _row_order(row: dict[str, Any]) -> tuple[int, int]:
    for timeline in ("ros_time", "log_time", "receive_time"):
        if row.get(timeline) is not None:
            return (1, row[timeline])
    return (0, 0)
