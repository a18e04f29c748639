"""Rerun's private calls (host_bridge/core/rerun_private.py) against the public ones they replace, on
the installed Rerun: whether they still earn their place after an upgrade.

Each message is what a live Imu message of one row gives the sink: a Transform3D (its rotation
and the frame it is drawn in) and six plotted scalars, two entities at the message's two times.
It is logged to an .rrd file in a temporary directory two ways, in alternating rounds:

- baseline, the public API: ``reset_time`` and ``set_time(name, timestamp=datetime64)`` on the
  stream, then ``log`` of each entity's components, each cell array taken from its column's
  Arrow list array (``as_arrow_array()``) and wrapped in a ``DescribedComponentBatch``;
- private: ``rerun_private.set_times``, then ``log_row`` of each entity's cells taken with
  ``column_values`` (what ``sink.RerunSink._log_rows`` does).

Times are the logging thread's CPU time (what a robot's worker spends; Rerun encodes and writes
on threads of its own), the median over ``--rounds`` rounds of ``--count`` messages; the ratio
is baseline over private. When it nears 1, the private calls no longer pay for the re-check
each Rerun upgrade costs: drop them. Before timing, both ways' files are read back and must
hold the same rows.

    .venv/bin/python benchmarks/rerun_private.py [--count 5000] [--rounds 5]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
import pyarrow as pa
import rerun as rr
from rerun.chunk import RrdReader

from host_bridge.core.contract import component_columns, repeated_texts
from host_bridge.core.rerun_private import column_values, log_row, native, set_times

BUDGET_SECONDS = 90
T0 = 1_700_000_000_000_000_000
STEP_NS = 5_000_000  # an Imu at 200 Hz
ROW_ID = "rerun.controls.RowId"

Message = tuple[dict[str, int], list[tuple[str, list[rr.ComponentColumn]]]]


@dataclass(frozen=True, slots=True)
class _Cells:
    """An Arrow array of one component's values, as ``log`` takes them."""

    values: pa.Array

    def as_arrow_array(self) -> pa.Array:
        return self.values


def messages(count: int) -> list[Message]:
    values = np.random.default_rng(7).normal(size=(count, 10))
    made = []
    for i in range(count):
        quaternion = values[i, :4] / np.linalg.norm(values[i, :4])
        pose = component_columns(rr.Transform3D, quaternion=quaternion[None],
                                 parent_frame=repeated_texts(["r/imu_link"], 1))
        plot = component_columns(rr.Scalars, [6], scalars=values[i, 4:])
        times = {"ros_time": T0 + i * STEP_NS, "receive_time": T0 + i * STEP_NS + 1000}
        made.append((times, [("/r/imu/orientation", pose), ("/r/imu/plot", plot)]))
    return made


def stream_to(path: Path) -> rr.RecordingStream:
    stream = rr.RecordingStream("swanky-benchmark")
    rr.set_log_time_enabled(False, recording=stream)
    rr.set_log_tick_enabled(False, recording=stream)
    stream.set_sinks(rr.FileSink(str(path)))
    return stream


def log_public(stream: rr.RecordingStream, batch: Sequence[Message]) -> None:
    for times, entities in batch:
        stream.reset_time()
        for name, ns in times.items():
            stream.set_time(name, timestamp=np.datetime64(ns, "ns"))
        for path, columns in entities:
            stream.log(path, [rr.DescribedComponentBatch(_Cells(column.as_arrow_array()[0].values),
                                                         column.component_descriptor())
                              for column in columns])


def log_private(stream: rr.RecordingStream, batch: Sequence[Message]) -> None:
    handle = native(stream)
    for times, entities in batch:
        set_times(handle, times)
        for path, columns in entities:
            log_row(handle, path, {column.component_descriptor(): column_values(column)
                                   for column in columns})


def thread_seconds(work: Callable[[], object]) -> float:
    start = time.thread_time()
    work()
    return time.thread_time() - start


def rows_of(path: Path) -> list[tuple[str, dict[str, object]]]:
    """Every row the messages made (without its row id), by entity and ros_time."""
    rows = []
    for chunk in RrdReader(path).stream():
        if not chunk.entity_path.startswith("/r/"):
            continue  # the recording's properties: its start time
        for row in chunk.to_record_batch().drop_columns([ROW_ID]).to_pylist():
            rows.append((chunk.entity_path, row))
    return sorted(rows, key=lambda pair: (pair[0], str(pair[1]["ros_time"])))


def check_same_rows(batch: Sequence[Message], directory: Path) -> None:
    rows = []
    for name, way in (("public", log_public), ("private", log_private)):
        path = directory / f"check-{name}.rrd"
        stream = stream_to(path)
        way(stream, batch)
        stream.disconnect()
        rows.append(rows_of(path))
    if rows[0] != rows[1] or len(rows[0]) != 2 * len(batch):
        raise SystemExit("the private calls logged other rows than the public ones")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--count", type=int, default=5000, help="messages a round")
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    batch = messages(args.count)
    seconds: dict[str, list[float]] = {"public": [], "private": []}
    with tempfile.TemporaryDirectory() as temporary:
        directory = Path(temporary)
        check_same_rows(batch[:50], directory)
        for round_index in range(args.rounds):
            ways = [("public", log_public), ("private", log_private)]
            for name, way in ways if round_index % 2 == 0 else ways[::-1]:
                stream = stream_to(directory / f"{name}-{round_index}.rrd")
                seconds[name].append(thread_seconds(partial(way, stream, batch)))
                stream.disconnect()
    public, private = (statistics.median(seconds[name]) / args.count * 1e6 for name in ("public", "private"))
    print(f"rerun-sdk {rr.__version__}, {args.count} Imu-like messages (2 entities, 2 timelines) a round, "
          f"median of {args.rounds}, logging thread's CPU")
    print(f"public API (baseline): {public:.1f} us a message")
    print(f"rerun_private: {private:.1f} us a message; ratio {public / private:.2f}x "
          "(no target: near 1, drop the private calls)")


if __name__ == "__main__":
    main()
