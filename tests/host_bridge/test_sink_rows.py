"""RerunSink logs a ColumnsItem of a few rows (a live run of one message) row by row and a larger
one with send_columns: the .rrd holds the same rows, times and values either way."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr

from host_bridge.core.contract import ColumnsItem, component_columns, repeated_texts
from host_bridge.core.destinations import SinkOptions
from host_bridge.outputs.sink import FEW_ROWS, RerunSink
from tests.rrd import entity_rows


def items(path: str, count: int, *, lean: bool = False) -> list[ColumnsItem]:
    """Transforms with a parent frame and arrows of two vectors each, and a two-series plot:
    ``count`` rows at ros_time 10, 20, ... and receive_time one more; ``lean``: the columns
    converters build (component_columns), the arrows one vector more a row, row after row."""
    stamps = 10 * np.arange(1, count + 1, dtype=np.int64)
    times = {"ros_time": stamps, "receive_time": stamps + 1}
    if lean:
        lengths = np.arange(count)  # the first row has no arrow
        vectors = np.arange(3 * int(lengths.sum()), dtype=np.float32).reshape(-1, 3)
        lean_transforms = component_columns(
            rr.Transform3D,
            translation=np.arange(3 * count, dtype=np.float64).reshape(count, 3),
            parent_frame=repeated_texts(["r/odom", "r/map"], np.arange(count) % 2),
        )
        lean_arrows = component_columns(rr.Arrows3D, lengths, vectors=vectors)
        lean_plot = component_columns(
            rr.Scalars, np.full(count, 2), scalars=np.arange(2 * count, dtype=np.float64)
        )
        return [ColumnsItem(f"{path}/pose", [*lean_transforms, *lean_arrows], times),
                ColumnsItem(f"{path}/plot", lean_plot, times)]
    transforms = rr.Transform3D.columns(
        translation=np.arange(3 * count, dtype=np.float64).reshape(count, 3),
        parent_frame=repeated_texts(["r/odom", "r/map"], np.arange(count) % 2),
    )
    arrows = rr.Arrows3D.columns(
        vectors=np.arange(6 * count, dtype=np.float32).reshape(2 * count, 3),
        labels=repeated_texts(["a", "b"], count),
    ).partition(np.full(count, 2))
    plot = rr.Scalars.columns(scalars=np.arange(2 * count, dtype=np.float64).reshape(count, 2))
    return [ColumnsItem(f"{path}/pose", [*transforms, *arrows], times),
            ColumnsItem(f"{path}/plot", list(plot), times)]


def rows_of(out: Path, path: str) -> dict[str, list[dict[str, Any]]]:
    return {entity.removeprefix(path): rows
            for entity, rows in entity_rows(out).items() if entity.startswith(path)}


def send_columns(sink: RerunSink, item: ColumnsItem) -> None:
    """What the sink does with many rows, done here for rows it would log one by one."""
    indexes = [rr.TimeColumn(name, timestamp=values.view("datetime64[ns]"))
               for name, values in item.times.items()]
    for stream in sink.streams:
        stream.send_columns(item.path, indexes=indexes, columns=list(item.columns))


def without_log_time(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{k: v for k, v in row.items() if k != "log_time"} for row in rows]


def test_few_rows_are_logged_as_send_columns_would(tmp_path: Path) -> None:
    sink = RerunSink(SinkOptions(save=tmp_path / "out.rrd"))
    for count in (1, FEW_ROWS, FEW_ROWS + 1):
        sink.log(items(f"/logged{count}", count), {})
        for item in items(f"/sent{count}", count):
            send_columns(sink, item)
    sink.close()
    out = tmp_path / "out.rrd"
    for count in (1, FEW_ROWS, FEW_ROWS + 1):
        logged, sent = rows_of(out, f"/logged{count}"), rows_of(out, f"/sent{count}")
        assert sorted(logged) == sorted(sent) == ["/plot", "/pose"]
        for entity, rows in logged.items():
            assert without_log_time(rows) == without_log_time(sent[entity])
            assert [row["ros_time"] for row in rows] == [10 * (i + 1) for i in range(count)]
            assert [row["receive_time"] for row in rows] == [10 * (i + 1) + 1 for i in range(count)]
    one = rows_of(out, "/logged1")
    assert without_log_time(one["/plot"]) == [
        {"ros_time": 10, "receive_time": 11, "Scalars:scalars": [0.0, 1.0], "static": False}]
    pose = one["/pose"][0]
    assert (pose["Transform3D:parent_frame"], pose["Transform3D:translation"]) == (
        ["r/odom"], [[0.0, 1.0, 2.0]])
    assert (pose["Arrows3D:labels"], pose["Arrows3D:vectors"]) == (
        ["a", "b"], [[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]])
    assert [row["Transform3D:parent_frame"] for row in rows_of(out, "/logged4")["/pose"]] == [
        ["r/odom"], ["r/map"], ["r/odom"], ["r/map"]]


def test_component_columns_are_rerun_columns() -> None:
    """The lean columns converters build hold what Rerun's own ``columns`` would, descriptors
    and Arrow arrays alike."""
    count = 3
    vectors = np.arange(6 * count, dtype=np.float32).reshape(2 * count, 3)
    scalars = np.arange(2 * count, dtype=np.float64).reshape(count, 2)
    frames = repeated_texts(["r/odom", "r/map"], np.arange(count) % 2)
    quaternions = np.linspace(-1.0, 1.0, 8 * count).reshape(2 * count, 4) / 3.0
    pairs = [
        (component_columns(rr.Transform3D, translation=vectors[:count], parent_frame=frames),
         list(rr.Transform3D.columns(translation=vectors[:count], parent_frame=frames))),
        (component_columns(rr.Arrows3D, np.full(count, 2), vectors=vectors),
         list(rr.Arrows3D.columns(vectors=vectors).partition(np.full(count, 2)))),
        (component_columns(rr.Scalars, np.full(count, 2), scalars=scalars),
         list(rr.Scalars.columns(scalars=scalars))),
        # float64 quaternions, a column's every other row (not contiguous), int radii: cast
        (component_columns(rr.Transform3D, quaternion=quaternions[::2]),
         list(rr.Transform3D.columns(quaternion=quaternions[::2]))),
        (component_columns(rr.Points3D, radii=np.arange(count)),
         list(rr.Points3D.columns(radii=np.arange(count)))),
    ]
    for lean, rerun_own in pairs:
        assert [c.component_descriptor() for c in lean] == [c.component_descriptor() for c in rerun_own]
        for mine, theirs in zip(lean, rerun_own, strict=True):
            assert mine.as_arrow_array().equals(theirs.as_arrow_array())
            assert len(mine.as_arrow_array()) == count


def test_few_lean_rows_are_logged_as_send_columns_would(tmp_path: Path) -> None:
    """Columns of component_columns are logged row by row as slices of their batches: rows of
    different lengths (none, one, two... arrows) keep their own values and times."""
    sink = RerunSink(SinkOptions(save=tmp_path / "out.rrd"))
    counts = (1, 2, FEW_ROWS, FEW_ROWS + 1)
    for count in counts:
        sink.log(items(f"/logged{count}", count, lean=True), {})
        for item in items(f"/sent{count}", count, lean=True):
            send_columns(sink, item)
    sink.close()
    out = tmp_path / "out.rrd"
    for count in counts:
        logged, sent = rows_of(out, f"/logged{count}"), rows_of(out, f"/sent{count}")
        assert sorted(logged) == sorted(sent) == ["/plot", "/pose"]
        for entity, rows in logged.items():
            assert without_log_time(rows) == without_log_time(sent[entity])
            assert [row["receive_time"] for row in rows] == [10 * (i + 1) + 1 for i in range(count)]
    pose = rows_of(out, f"/logged{FEW_ROWS}")["/pose"]
    assert [row["Arrows3D:vectors"] for row in pose] == [
        [], [[0.0, 1.0, 2.0]], [[3.0, 4.0, 5.0], [6.0, 7.0, 8.0]],
        [[9.0, 10.0, 11.0], [12.0, 13.0, 14.0], [15.0, 16.0, 17.0]]]
    assert [row["Transform3D:parent_frame"] for row in pose] == [
        ["r/odom"], ["r/map"], ["r/odom"], ["r/map"]]
    assert [row["Scalars:scalars"] for row in rows_of(out, "/logged2")["/plot"]] == [
        [0.0, 1.0], [2.0, 3.0]]
