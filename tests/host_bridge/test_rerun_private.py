"""host_bridge/core/rerun_private.py on the installed Rerun: the version it was checked against, and
each private call exercised for real (rows logged through it into a file, read back with Rerun's
own reader), so a Rerun upgrade that changes one fails here under that call's name."""

from __future__ import annotations

from importlib.metadata import version
from pathlib import Path

import numpy as np
import pyarrow as pa
import rerun as rr

from host_bridge.core.contract import component_columns
from host_bridge.core.rerun_private import CHECKED_VERSIONS, column_values, log_row, native, set_times
from tests.rrd import entity_rows


def test_the_installed_rerun_is_one_rerun_private_was_checked_against() -> None:
    installed = version("rerun-sdk")
    major_minor = tuple(int(part) for part in installed.split(".")[:2])
    low, high = CHECKED_VERSIONS
    assert low <= major_minor < high, (
        f"rerun-sdk {installed} is not one host_bridge/core/rerun_private.py was checked against "
        f"({'.'.join(map(str, low))} up to, not including, {'.'.join(map(str, high))}). Re-check "
        "each of its calls in the new Rerun's source: rerun_bindings.reset_time, "
        "set_time_timestamp_nanos_since_epoch and log_arrow_msg (rerun_bindings.pyi), "
        "RecordingStream.to_native (rerun/recording_stream.py), ComponentColumn.component_batch "
        "(rerun/_baseclasses.py); run this file and tests/host_bridge/test_sink_rows.py; measure "
        "again whether the public calls (rr.set_time, rr.log, as_arrow_array) still cost more "
        "(benchmarks/live_capacity.py); then move CHECKED_VERSIONS and the rerun-sdk pin in "
        "pyproject.toml together."
    )


def cells(archetype: rr.AsComponents) -> dict[rr.ComponentDescriptor, pa.Array]:
    """The archetype's components as the descriptor -> Arrow cells a row is logged with."""
    return {batch.component_descriptor(): batch.as_arrow_array()
            for batch in archetype.as_component_batches()}


def test_set_times_and_log_row_write_the_rows_and_times_given(tmp_path: Path) -> None:
    out = tmp_path / "rows.rrd"
    stream = rr.RecordingStream("swanky-test")
    rr.set_log_time_enabled(False, recording=stream)
    rr.set_log_tick_enabled(False, recording=stream)
    stream.set_sinks(rr.FileSink(str(out)))
    handle = native(stream)
    set_times(handle, {"ros_time": 10, "receive_time": 11})
    log_row(handle, "/r/points", cells(rr.Points3D([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], radii=0.5)))
    # Setting the times again replaces them all: receive_time is no longer set.
    set_times(handle, {"ros_time": 20})
    log_row(handle, "/r/points", cells(rr.Points3D([[7.0, 8.0, 9.0]])))
    stream.disconnect()
    rows = entity_rows(out)["/r/points"]
    assert [row["ros_time"] for row in rows] == [10, 20]
    assert [row.get("receive_time") for row in rows] == [11, None]
    assert [row["Points3D:positions"] for row in rows] == [
        [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], [[7.0, 8.0, 9.0]]]
    assert [row.get("Points3D:radii") for row in rows] == [[0.5], None]
    assert [row["static"] for row in rows] == [False, False]
    assert {key for row in rows for key in row} <= {
        "ros_time", "receive_time", "Points3D:positions", "Points3D:radii", "static"}


def test_column_values_are_every_rows_cells_in_order() -> None:
    vectors = np.arange(9, dtype=np.float32).reshape(3, 3)
    # The lean columns converters build (rows of none, one and two arrows) ...
    (lean,) = component_columns(rr.Arrows3D, [0, 1, 2], vectors=vectors)
    assert column_values(lean).to_pylist() == vectors.tolist()
    assert column_values(lean).equals(lean.as_arrow_array().values)
    # ... and Rerun's own.
    frames = [column for column in rr.Transform3D.columns(parent_frame=["r/odom", "r/map"])
              if column.component_descriptor().component == "Transform3D:parent_frame"]
    assert [column_values(column).to_pylist() for column in frames] == [["r/odom", "r/map"]]
