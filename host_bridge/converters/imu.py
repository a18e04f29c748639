"""sensor_msgs/Imu and MagneticField -> orientation, vector arrows and scalar plots.

The orientation is a ``Transform3D`` from the sensor frame to the implicit frame of the
``orientation`` sub-entity, never a named frame relation: /tf may already relate the sensor
frame, and Rerun allows one parent per frame. The acceleration and angular-velocity arrows sit in
that rotated frame, so they turn with the attitude the IMU estimates.

Raw IMUs send no orientation: ROS marks that with ``orientation_covariance[0] == -1``, and many
drivers (the phidgets bag) send the all-zero quaternion instead. Both become the identity
rotation, never a normalised NaN, so the arrows stay attached to the sensor frame and the
scalars are unaffected. A MagneticField of three NaNs (no new sample) is skipped.

Options (:class:`~host_bridge.core.options.ImuOptions`): ``acceleration_scale`` (m of arrow per
m/s^2), ``angular_velocity_scale`` (m per rad/s), ``axis_length`` (m).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import rerun as rr

from host_bridge.converters._common import stamps_ns, vectors
from host_bridge.converters.scalars import XYZ, columns_series, vector_plots
from host_bridge.core.columns import Columns
from host_bridge.core.contract import (
    ColumnsItem,
    LogEntry,
    LogItem,
    Run,
    component_columns,
    repeated_texts,
)
from host_bridge.core.options import ImuOptions

_VECTORS = ("linear_acceleration", "angular_velocity")
# Arrow colours: acceleration amber, angular velocity violet (RGBA).
_ARROW_COLORS = np.array([[255, 170, 0, 255], [170, 80, 255, 255]], dtype=np.uint8)
_ARROW_LABELS = ["linear_acceleration", "angular_velocity"]
_IDENTITY = np.array([0.0, 0.0, 0.0, 1.0])
_MIN_NORM = 1e-6


def orientations(
    quaternions: npt.NDArray[np.float64], covariance0: npt.NDArray[np.float64]
) -> npt.NDArray[np.float64]:
    """Unit xyzw quaternions, shape (n, 4); identity where the message has no orientation."""
    norms = np.linalg.norm(quaternions, axis=1)
    valid = np.isfinite(norms) & (norms > _MIN_NORM) & (covariance0 != -1.0)
    safe = np.where(valid, norms, 1.0)[:, None]
    return np.where(valid[:, None], quaternions / safe, _IDENTITY)


@dataclass(slots=True)
class _ImuTopic:
    """Per Imu topic: whether its orientation's axes (static) were logged."""

    logged: bool = False


def convert_imu(run: Run) -> list[LogEntry]:
    """One row per message: the orientation transform with its two arrows, one block of rows
    per frame id, and the two vectors' scalars; read as columns."""
    columns = run.columns()
    quaternions = vectors(columns, "orientation", "xyzw")
    covariance0 = columns["orientation_covariance"][:, 0].astype(np.float64)
    # Both vectors of every message in one array, (n, 2, 3): the plots' values and the arrows'.
    measured = np.stack(
        [columns[f"{name}.{axis}"] for name in _VECTORS for axis in XYZ], axis=-1
    ).astype(np.float64).reshape(-1, len(_VECTORS), len(XYZ))
    options = run.options(ImuOptions)
    scales = np.array([options.acceleration_scale, options.angular_velocity_scale])
    arrows = measured * scales[:, None]
    unit = orientations(quaternions, covariance0)
    stamps = stamps_ns(columns)
    run_times = run.times(stamps)
    orientation_path = run.child_path("orientation")
    items: list[LogEntry] = []
    axes = run.state(_ImuTopic)
    if not axes.logged:
        axes.logged = True
        # The arrows' colours and labels never change: static, not repeated in every row.
        items.append(LogItem(orientation_path, (
            rr.TransformAxes3D(options.axis_length),
            rr.Arrows3D.from_fields(colors=_ARROW_COLORS, labels=_ARROW_LABELS),
        ), static=True))
    groups = columns.groups("header.frame_id")
    for frame_id, frame_rows in groups:
        # Without a frame id the orientation hangs under the topic entity, as Rerun would default.
        parent = run.frame(str(frame_id)) or f"tf#{run.entity_path}"
        # One frame id (the usual case): its rows are the run's, and so are their times.
        frame_times = run_times if len(groups) == 1 else run.times(stamps[frame_rows], frame_rows)
        for entries, times in frame_times:
            rows = frame_rows[entries]
            n = len(rows)
            transform = component_columns(
                rr.Transform3D, quaternion=unit[rows], parent_frame=repeated_texts([parent], n)
            )
            arrow_vectors = component_columns(
                rr.Arrows3D, np.full(n, len(_VECTORS)), vectors=arrows[rows].reshape(-1, 3)
            )
            items.append(ColumnsItem(orientation_path, [*transform, *arrow_vectors], times))
    plots = [((name,), measured[:, which]) for which, name in enumerate(_VECTORS)]
    return [*items, *vector_plots(run, plots, stamps)]


def _magnetic_field(columns: Columns) -> npt.NDArray[np.float64]:
    return vectors(columns, "magnetic_field")


IMU = convert_imu
# Drivers publish NaN for "no new reading" (the phidgets magnetometer samples at half the IMU
# rate, so every other message is NaN); such a message has nothing to plot, and NaN rows would
# only cut the plotted line into pieces.
MAGNETIC_FIELD = columns_series(_magnetic_field, {(): XYZ}, skip_unread=True)
