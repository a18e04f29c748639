"""Reading .rrd files back for assertions, with Rerun's own reader (rerun.chunk.RrdReader)."""

from __future__ import annotations

import subprocess
from collections import defaultdict
from pathlib import Path
from typing import Any

import pyarrow as pa
from rerun.chunk import RrdReader

from tests.integration.procs import rerun_binary

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


def row_count(path: Path, entity: str) -> int:
    """Rows of ``entity`` in the file, without reading their values (a bag's worth of scans)."""
    return sum(chunk.num_rows for chunk in RrdReader(path).stream() if chunk.entity_path == entity)


def verify(*paths: Path) -> None:
    """What Rerun's own tools need of saved files: ``rerun rrd verify`` (footer checks on)
    accepts every one, and each opens with ``RrdReader(path).store()``, which reads the index
    in its footer."""
    done = subprocess.run([str(rerun_binary()), "rrd", "verify", *map(str, paths)],
                          capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stdout + done.stderr
    for path in paths:
        assert len(RrdReader(path).store()) > 0, path


def saved_views(path: Path) -> list[dict[str, Any]]:
    """Views of every blueprint store in a .rrd: class, name, origin and contents queries."""
    reader = RrdReader(path)
    found: dict[str, dict[str, Any]] = {}
    for store in reader.blueprints():
        for chunk in reader.stream(store=store):
            if not chunk.entity_path.startswith("/view/"):
                continue
            batch = chunk.to_record_batch()
            # /view/<id> and its parts (/view/<id>/ViewContents, ...)
            view = found.setdefault("/".join(chunk.entity_path.split("/")[:3]), {})
            for column, key in (("ViewBlueprint:class_identifier", "class"),
                                ("ViewBlueprint:display_name", "name"),
                                ("ViewBlueprint:space_origin", "origin"),
                                ("ViewContents:query", "contents")):
                if column in batch.schema.names:
                    value = batch.column(column).to_pylist()[-1]
                    view[key] = value if key == "contents" else value[0]
    return list(found.values())
