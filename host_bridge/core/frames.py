"""Keeping every frame of a robot reachable from its 3D view, and choosing the frame it looks from.

Rerun draws an entity in a 3D view only if the entity's frame has a transform path to the view's
target frame; otherwise the view shows ``No transform path from ... to the view's target frame``
for it. Robots leave such gaps all the time: a bag with no /tf at all, a sensor frame no
transform names, a model whose root nothing places, data that arrives before the /tf that links
it. :class:`RobotFrames` watches what a robot's converters log and keeps its frames one tree:

* Every named frame of robot ``R`` (``R/<frame>``) that no relation names as a child is placed
  at the robot's entity root (``tf#/R``) by a static identity ``Transform3D`` on the entity
  /tf_static would use for it (:func:`~host_bridge.core.state.static_transform_path`). A real
  relation that comes later replaces it: from /tf_static or the URDF on that very entity, from
  /tf or joint states from their first stamp on (Rerun lets a temporal entity win over a static
  one for the same frame). Entities without a named frame (``tf#/R/...``) hang from ``tf#/R``
  already, so they join the same tree.
* The view's target frame is ``R/map`` once seen, else ``R/odom``, else the root link of the
  robot model, logged as the static ``CoordinateFrame`` of ``/R``: a 3D view whose origin is
  ``/R`` and whose blueprint names no target looks from the origin entity's frame. With none of
  those frames the viewer's own choice stands (the common root of everything, ``tf#/``).

Several robots stay apart (``R/map`` and ``R2/map`` are different frames) and share the "All
robots" view at ``/`` through their roots at ``tf#/R`` and ``tf#/R2``.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterable, Sequence
from typing import Any, cast

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import rerun as rr

from host_bridge.core.contract import ColumnsItem, LogEntry, LogItem
from host_bridge.core.rerun_private import column_values
from host_bridge.core.state import RobotModel, RobotState, static_transform_path

log = logging.getLogger("swanky.host")

# Preferred target frames (REP 105), most global first.
TARGET_FRAMES = ("map", "odom")

# Up to this many rows (a live run of one message) Python strings cost less than numpy's calls.
_FEW_ROWS = 32
_LONGEST_PERIOD = 8
"""Frame columns repeating this few strings (a TF message's transforms) are told apart by period."""

_PARENT = "Transform3D:parent_frame"
_CHILD = "Transform3D:child_frame"
_FRAME = "CoordinateFrame:frame"


def robot_root_frame(robot: str) -> str:
    """The implicit frame of the robot's entity root, where its unplaced frames are put."""
    return f"tf#/{robot}"


def _flat(array: pa.Array) -> pa.Array:
    """A component column (one list per row) or batch as one array of values."""
    if not (pa.types.is_list(array.type) or pa.types.is_large_list(array.type)):
        return array
    if array.null_count:
        return array.flatten()
    # The values the rows' offsets span: flatten() without importing pyarrow.compute (80 ms).
    offsets = array.offsets
    start, end = offsets[0].as_py(), offsets[len(array)].as_py()
    return array.values.slice(start, end - start)


def _column_values(columns: Iterable[Any]) -> dict[str, pa.Array]:
    found = {}
    for column in columns:
        name = column.component_descriptor().component
        if name in (_PARENT, _CHILD, _FRAME):
            # A ComponentColumn's rows span its whole batch: the batch is the values.
            found[name] = (column_values(column) if isinstance(column, rr.ComponentColumn)
                           else _flat(column.as_arrow_array()))
    return found


def _archetype_values(archetype: Any) -> dict[str, pa.Array]:
    found = {}
    if isinstance(archetype, rr.Transform3D):
        for name, batch in ((_PARENT, archetype.parent_frame), (_CHILD, archetype.child_frame)):
            if batch is not None:
                found[name] = _flat(batch.as_arrow_array())
    elif isinstance(archetype, rr.CoordinateFrame) and archetype.frame is not None:
        found[_FRAME] = _flat(archetype.frame.as_arrow_array())
    return found


def _distinct(*arrays: pa.Array) -> set[tuple[Any, ...]]:
    """The distinct rows of equally long arrays (a TF run repeats a few relations many times).
    Strings are compared as bytes with numpy, and only one row of each distinct value becomes
    Python strings: a run's frame columns have hundreds of thousands of rows."""
    if not arrays or len(arrays[0]) <= _FEW_ROWS:
        return set(zip(*(array.to_pylist() for array in arrays), strict=True))
    # An Imu run's parent frame is one string on every row; a TF run's frames are the same
    # few strings again and again, message after message.
    for period in range(1, _LONGEST_PERIOD + 1):
        if all(_repeats(array, period) for array in arrays):
            return {tuple(array[row].as_py() for array in arrays) for row in range(period)}
    byte_rows = [_string_bytes(array) for array in arrays]
    if any(rows is None for rows in byte_rows):
        return set(zip(*(array.to_pylist() for array in arrays), strict=True))
    table = np.hstack(cast(list[npt.NDArray[np.uint8]], byte_rows))
    if not len(table):
        return set()
    if (table == table[0]).all():
        firsts: Sequence[int] = [0]
    else:
        firsts = _distinct_rows(table)
    return {tuple(array[row].as_py() for array in arrays) for row in firsts}


def _distinct_rows(table: npt.NDArray[np.uint8]) -> list[int]:
    """The index of one row of each distinct value of ``table``'s rows: rows hashed to one
    number each (sorting numbers is cheaper than sorting byte strings), then checked equal to
    the row they share their hash with, as byte strings should they not all be."""
    words = np.zeros((len(table), -(-table.shape[1] // 8) * 8), np.uint8)
    words[:, : table.shape[1]] = table
    columns = words.view(np.uint64)
    hashes = columns[:, 0].copy()
    for column in columns.T[1:]:
        hashes = hashes * np.uint64(0x100000001B3) ^ column
    _, firsts, which = np.unique(hashes, return_index=True, return_inverse=True)
    distinct: list[int]
    if (words == words[firsts[which.ravel()]]).all():
        distinct = firsts.tolist()
        return distinct
    distinct = np.unique(words.view(np.dtype((np.void, words.shape[1]))).ravel(),
                                    return_index=True)[1].tolist()
    return distinct


def _repeats(array: pa.Array, period: int) -> bool:
    """Whether ``array`` is a utf8 array without nulls whose first ``period`` strings repeat
    over all its rows (whole periods only)."""
    count = len(array)
    if not pa.types.is_string(array.type) or array.null_count or count < period or count % period:
        return False
    _, offsets_buffer, data_buffer = array.buffers()
    offsets = np.frombuffer(offsets_buffer, np.int32, count + 1, array.offset * 4)
    sizes = np.diff(offsets).reshape(-1, period)
    if not (sizes == sizes[0]).all():
        return False
    block = int(sizes[0].sum())
    if not block:
        return True  # every row empty
    data = np.frombuffer(data_buffer, np.uint8, block * len(sizes), int(offsets[0])).reshape(-1, block)
    return bool((data == data[0]).all())


def _string_bytes(array: pa.Array) -> npt.NDArray[np.uint8] | None:
    """A utf8 array without nulls as one row per string: its byte length (4 bytes), then its
    bytes padded with zeros, so equal rows are equal strings; None for any other array."""
    if not pa.types.is_string(array.type) or array.null_count:
        return None
    count = len(array)
    _, offsets_buffer, data_buffer = array.buffers()
    offsets = np.frombuffer(offsets_buffer, np.int32, count + 1, array.offset * 4).astype(np.intp)
    data = np.frombuffer(data_buffer, np.uint8) if data_buffer is not None else np.zeros(1, np.uint8)
    sizes = np.diff(offsets)
    width = int(sizes.max()) if count else 0
    if count and (sizes == width).all():  # one size: the strings lie back to back
        text = data[offsets[0] : offsets[0] + count * width].reshape(count, width)
    else:
        columns = np.arange(width)
        inside = columns < sizes[:, None]
        text = np.where(inside, data[np.minimum(offsets[:-1, None] + columns, len(data) - 1)], 0)
    return np.hstack([sizes.astype("<u4").view(np.uint8).reshape(count, 4),
                      text.astype(np.uint8, copy=False)])


def frames_logged(entries: Sequence[LogEntry]) -> tuple[set[tuple[str, str]], set[str]]:
    """The (child, parent) relations and the entity frames that ``entries`` log. A transform
    with a parent frame but no child frame places the entity's own implicit frame (the IMU's
    orientation hangs from the IMU frame so)."""
    relations: set[tuple[str, str]] = set()
    frames: set[str] = set()
    for entry in entries:
        parts: Iterable[dict[str, pa.Array]]
        if isinstance(entry, ColumnsItem):
            parts = [_column_values(entry.columns)]
        else:
            parts = [_archetype_values(a) for a in entry.archetypes]
        for values in parts:
            if _FRAME in values:
                frames.update(f for (f,) in _distinct(values[_FRAME]) if f)
            if _PARENT not in values:
                continue
            parents = values[_PARENT]
            if _CHILD in values and len(values[_CHILD]) == len(parents):
                pairs = _distinct(values[_CHILD], parents)
            else:
                pairs = {(f"tf#{entry.path}", parent) for (parent,) in _distinct(parents)}
            relations.update((child, parent) for child, parent in pairs if child and parent)
    return relations, frames


class RobotFrames:
    """The frame graph of one robot as logged so far, and what keeps it one tree.

    Thread-safe: a robot's conversions and the slow converters may log for it at once.
    """

    def __init__(self, robot: str) -> None:
        self.robot = robot
        self._prefix = f"{robot}/"
        self._parents: dict[str, str] = {}
        self._named: set[str] = set()
        self._placed: set[str] = set()
        self._model: RobotModel | None = None
        self.target: str | None = None
        self._lock = threading.Lock()

    def observe(self, entries: Sequence[LogEntry], robot_state: RobotState) -> list[LogItem]:
        """Take note of the frames ``entries`` log; the items to log next: placements of frames
        that have no parent, and the view's target frame when it changed."""
        return self.note(*frames_logged(entries), robot_state)

    def note(
        self, relations: Iterable[tuple[str, str]], frames: Iterable[str], robot_state: RobotState
    ) -> list[LogItem]:
        """:meth:`observe` of what :func:`frames_logged` found in entries logged elsewhere (the
        heavy topics' process, offload.py)."""
        relations, frames = list(relations), list(frames)
        model = robot_state.model
        with self._lock:
            known = len(self._named), len(self._parents)
            for child, parent in relations:
                self._parents[child] = parent
            self._named.update(
                f for f in (*frames, *(f for relation in relations for f in relation))
                if f.startswith(self._prefix)
            )
            if (len(self._named), len(self._parents)) == known and model is self._model:
                return []
            self._model = model
            return self._placements(robot_state) + self._target_item()

    def _placements(self, robot_state: RobotState) -> list[LogItem]:
        unplaced = sorted(f for f in self._named - self._placed if f not in self._parents)
        if not unplaced:
            return []
        root = robot_root_frame(self.robot)
        # Usual while a robot starts (a scan before the /tf that places it): see unplaced().
        log.debug("[%s] frames %s placed at the robot's root for now", self.robot, unplaced)
        items = []
        for frame in unplaced:
            self._parents[frame] = root
            self._placed.add(frame)
            path = static_transform_path(self.robot, robot_state, frame.removeprefix(self._prefix))
            transform = rr.Transform3D(parent_frame=root, child_frame=frame)
            items.append(LogItem(path, (transform,), static=True))
        return items

    def unplaced(self) -> list[str]:
        """Frames (ROS names) no transform ever placed, but the target: they are drawn at the
        robot's root, which is worth telling once the input ends."""
        root = robot_root_frame(self.robot)
        with self._lock:
            return sorted(
                f.removeprefix(self._prefix)
                for f in self._placed
                if self._parents.get(f) == root and f != self.target
            )

    def _preferred_target(self) -> str | None:
        for name in TARGET_FRAMES:
            if self._prefix + name in self._named:
                return self._prefix + name
        if self._model is not None and self._model.root:
            return self._prefix + self._model.root.strip("/")
        return None

    def _target_item(self) -> list[LogItem]:
        target = self._preferred_target()
        if target is None or target == self.target:
            return []
        self.target = target
        return [LogItem(f"/{self.robot}", (rr.CoordinateFrame(target),), static=True)]
