"""Every use of Rerun's private or undocumented Python API, in one module.

Each is here because the public way costs measurably more on the live path (the figures below
are the ones measured when each was adopted; the commits name the scripts). Nothing else in
Swanky may import ``rerun_bindings``, reach into ``rerun``'s private modules or read the private
names (tests/test_imports.py, ``RERUN_PRIVATE_NAMES``), so a Rerun upgrade has one module to
re-check.

Checked against rerun-sdk :data:`CHECKED_VERSIONS` (0.41.x; pyproject.toml pins the same range).
tests/host_bridge/test_rerun_private.py fails, naming what to re-check, when the installed
rerun-sdk is outside that range, and exercises each call below for real (rows logged through it
into a file and read back), so an API change fails there under the call's own name.

* ``rerun_bindings``, Rerun's native module that ``rerun`` wraps, reached through
  ``RecordingStream.to_native()`` (undocumented):

  - :func:`set_times`: ``reset_time`` and ``set_time_timestamp_nanos_since_epoch``, which
    ``rr.set_time(name, timestamp=...)`` ends in after turning our nanoseconds into a
    datetime64 and back;
  - :func:`log_row`: ``log_arrow_msg``, which ``rr.log`` ends in after wrapping every cell
    array in a batch, checking it and unwrapping it again. It is as lenient as ``rr.log`` (a
    bad entity path or a component of the wrong type is not raised).

  Together, for a live run's few rows (``sink.RerunSink._log_rows``): one message dispatched
  into a real sink, Imu 514-521 -> 445-478 us, TF 448-453 -> 382-383 us (commit af35af1,
  benchmarks/RESULTS.md).

* ``ComponentColumn.component_batch`` (an undocumented attribute): :func:`column_values`, the
  values of all of a column's rows as one Arrow array, instead of the list array
  ``as_arrow_array()`` builds round them, flattened again. Used by the sink to slice a few rows
  of a column and by frames.py to read a run's frame names: with the offsets made once per
  run (contract.component_columns), a live Imu message 1176/1109 -> 634/578 us (commit 6d030dc);
  logging a two-transform /tf message's rows as slices, 476-597 -> 422-496 us (commit a06278d).

Not private, so not here: ``ComponentColumn(descriptor, batch, offsets=...)`` (a documented
parameter in 0.41; contract.RowsColumn keeps the offsets itself rather than read Rerun's
``_offsets``) and ``component_descriptor()``.
"""

from __future__ import annotations

from collections.abc import Mapping

import pyarrow as pa
import rerun as rr
import rerun_bindings

CHECKED_VERSIONS = ((0, 41), (0, 42))
"""rerun-sdk versions this module was checked against: from the first (inclusive) up to the
second (exclusive), as (major, minor)."""

NativeStream = rerun_bindings.PyRecordingStream


def native(stream: rr.RecordingStream) -> NativeStream:
    """The stream's handle in Rerun's native module, what the calls below take."""
    return stream.to_native()


def set_times(stream: NativeStream, times: Mapping[str, int]) -> None:
    """Make ``times`` (timeline -> nanoseconds since the epoch) this thread's time on
    ``stream``, and no other timeline: what ``rr.reset_time()`` then ``rr.set_time(name,
    timestamp=...)`` for each would do."""
    rerun_bindings.reset_time(stream)
    for name, ns in times.items():
        rerun_bindings.set_time_timestamp_nanos_since_epoch(name, ns, stream)


def log_row(stream: NativeStream, path: str, components: dict[rr.ComponentDescriptor, pa.Array]) -> None:
    """One temporal row at ``path`` (at this thread's time on ``stream``): each component's
    cells, as ``rr.log(path, ...)`` of archetypes holding them would log."""
    rerun_bindings.log_arrow_msg(path, components=components, static_=False, recording=stream)


def column_values(column: rr.ComponentColumn) -> pa.Array:
    """The cells of every row of ``column``, in order, as one Arrow array: its component batch."""
    return column.component_batch.as_arrow_array()
