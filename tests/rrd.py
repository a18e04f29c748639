"""Reading .rrd files back for assertions, with Rerun's own reader (rerun.chunk.RrdReader)."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from typing import Any

import pyarrow as pa
from rerun.chunk import RrdReader

ROW_ID = "rerun.controls.RowId"


def entity_rows(path: Path, entity: str | None = None) -> dict[str, list[dict[str, Any]]]:
    """Rows per entity path: each row maps column names (timelines, components) to values.

    Timelines come back as int64 nanoseconds; rows of one entity are sorted by the first of
    ros_time / log_time / receive_time present, static rows first in the order they were logged
    (their row ids: the viewer keeps the last of them, whatever order the chunks were written in;
    rows logged one by one go through Rerun's batcher, send_columns' chunks straight to the file).
    """
    found: dict[str, list[tuple[tuple[Any, ...], dict[str, Any]]]] = defaultdict(list)
    for chunk in RrdReader(path).stream():
        if entity is not None and chunk.entity_path != entity:
            continue
        batch = chunk.to_record_batch()
        row_ids = batch.column(ROW_ID).to_pylist()
        columns = {}
        for name in batch.schema.names:
            if name == ROW_ID:
                continue
            column = batch.column(name)
            if pa.types.is_timestamp(column.type):
                column = column.cast(pa.int64())
            columns[name] = column.to_pylist()
        for i in range(chunk.num_rows):
            row = {name: values[i] for name, values in columns.items()}
            row["static"] = chunk.is_static
            found[chunk.entity_path].append((_row_order(row, row_ids[i]), row))
    # Stable: temporal rows at one time keep the order they were read in.
    return {path: [row for _, row in sorted(pairs, key=lambda pair: pair[0])]
            for path, pairs in found.items()}


def _row_order(row: dict[str, Any], row_id: bytes) -> tuple[Any, ...]:
    """Static rows first, by row id (a row id begins with the time it was logged at, big
    endian); then by the first timeline present."""
    for timeline in ("ros_time", "log_time", "receive_time"):
        if row.get(timeline) is not None:
            return (1, row[timeline])
    return (0, row_id)
