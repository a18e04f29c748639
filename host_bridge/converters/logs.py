"""Text topics: /rosout (ROS 2 rcl_interfaces/Log, ROS 1 rosgraph_msgs/Log) and std_msgs/String.

/rosout of a busy graph carries hundreds of lines a second, so every type converts a run of
messages into one TextLog column.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt
import rerun as rr

from host_bridge.converters._common import stamp_ns
from host_bridge.core.contract import ColumnsItem, Converter, LogEntry, Run

# Rerun levels from least to most severe; a ROS level at or above threshold i maps to entry i+1.
_RR_LEVELS = np.array(
    [
        str(level)
        for level in (
            rr.TextLogLevel.TRACE,
            rr.TextLogLevel.DEBUG,
            rr.TextLogLevel.INFO,
            rr.TextLogLevel.WARN,
            rr.TextLogLevel.ERROR,
            rr.TextLogLevel.CRITICAL,
        )
    ],
)
_INFO = str(rr.TextLogLevel.INFO)
# DEBUG INFO WARN ERROR FATAL: rcl_interfaces/Log uses 10..50, rosgraph_msgs/Log a bit mask.
ROS2_THRESHOLDS = np.array([10, 20, 30, 40, 50])
ROS1_THRESHOLDS = np.array([1, 2, 4, 8, 16])


def rerun_levels(levels: npt.ArrayLike, thresholds: npt.NDArray[np.int_]) -> list[str]:
    """Rerun level names for ROS levels; in-between values round down, 0 (unset) is TRACE."""
    index = np.searchsorted(thresholds, np.asarray(levels), side="right")
    return [str(level) for level in _RR_LEVELS[index]]


def text_converter(
    text: Callable[[Any], str],
    levels: Callable[[Sequence[Any]], list[str]],
    stamp: Callable[[Any], Any] | None = None,
) -> Converter:
    """The converter of a text type: one TextLog row per message, at its header stamp.

    ``stamp`` reads a top-level stamp instead: rcl_interfaces/Log has no header.
    """

    def convert(run: Run) -> list[LogEntry]:
        msgs = run.messages()
        texts, message_levels = [text(m) for m in msgs], levels(msgs)
        stamps = run.stamps() if stamp is None else np.fromiter(
            (stamp_ns(stamp(m)) for m in msgs), np.int64, len(msgs))
        items: list[LogEntry] = []
        for rows, times in run.times(stamps):
            if len(rows) < len(msgs):  # some messages unstamped: a group without ros_time
                columns = rr.TextLog.columns(text=[texts[i] for i in rows.tolist()],
                                             level=[message_levels[i] for i in rows.tolist()])
            else:
                columns = rr.TextLog.columns(text=texts, level=message_levels)
            items.append(ColumnsItem(run.entity_path, list(columns), times))
        return items

    return convert


def _log_text(msg: Any) -> str:
    return f"[{msg.name}] {msg.msg}"


def _log_levels(thresholds: npt.NDArray[np.int_]) -> Callable[[Sequence[Any]], list[str]]:
    return lambda msgs: rerun_levels([m.level for m in msgs], thresholds)


ROS2_LOG = text_converter(_log_text, _log_levels(ROS2_THRESHOLDS), stamp=lambda m: m.stamp)
ROS1_LOG = text_converter(_log_text, _log_levels(ROS1_THRESHOLDS))
STRING = text_converter(lambda m: str(m.data), lambda msgs: [_INFO] * len(msgs))
