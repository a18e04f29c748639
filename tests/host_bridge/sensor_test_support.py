"""Helpers for the converter tests: the one context factory, ROS 2 messages, and reading back the
values Rerun would receive from archetypes and columns (as numpy, through their arrow arrays)."""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import rerun as rr
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_typestore

from host_bridge.core.columns import Columns, columns_of_messages
from host_bridge.core.contract import (
    ColumnsItem,
    ConvertContext,
    Converter,
    LogEntry,
    LogItem,
    Run,
    message_run,
)
from host_bridge.core.state import RobotState, TopicState

ROBOT = "r"
TYPES = get_typestore(Stores.ROS2_HUMBLE).types


def make_ctx(
    topic: str,
    options: Mapping[str, Any] | None = None,
    stamp_ns: int = 1_000_000_000,
    *,
    robot: str = ROBOT,
    times: Mapping[str, int] | None = None,
    topic_state: TopicState | None = None,
    robot_state: RobotState | None = None,
) -> ConvertContext:
    """A context as the dispatcher makes one: entity ``/<robot><topic>``, ``ros_time`` stamp_ns
    unless ``times`` says otherwise. Messages of one topic share a ``topic_state`` (which holds
    the topic's options: give ``options`` or a state), topics of one robot a ``robot_state``."""
    if topic_state is not None and options is not None:
        msg = "the options are the topic state's; give one of them"
        raise ValueError(msg)
    return ConvertContext(
        robot=robot,
        topic=topic,
        entity_path=f"/{robot}{topic}",
        times={"ros_time": stamp_ns} if times is None else times,
        topic_state=TopicState(options) if topic_state is None else topic_state,
        robot_state=RobotState() if robot_state is None else robot_state,
    )


def convert(converter: Converter, message: Any, ctx: ConvertContext) -> list[LogEntry]:
    """``converter`` on ``message`` alone, a run of one as the dispatcher hands a live message:
    ``ctx`` gives the topic and the arrival times (receive_time, log_time); ros_time is the
    header stamp (contract.Run.times)."""
    return converter(message_run([message], [ctx]))


def convert_run(
    converter: Converter, messages: Sequence[Any], ctxs: Sequence[ConvertContext]
) -> list[LogEntry]:
    """``converter`` on a run of ``messages`` of one topic, one context each (see convert)."""
    return converter(message_run(messages, ctxs))


class _WatchedMessages:
    """Decoded messages as a run's source, noting whether a converter asked for them decoded
    (it could have read the columns alone)."""

    def __init__(self, messages: Sequence[Any], topic: str) -> None:
        self.messages = messages
        self.topic = topic
        self.decoded = False

    def __len__(self) -> int:
        return len(self.messages)

    def decode(self, row: int) -> Any:
        self.decoded = True
        return self.messages[row]

    def columns(self) -> Columns:
        return columns_of_messages(self.messages, self.topic)

    def part(self, row: int) -> _WatchedMessages:
        return _WatchedMessages([self.messages[row]], self.topic)


def reads_columns_only(converter: Converter, messages: Sequence[Any], ctx: ConvertContext) -> bool:
    """Whether ``converter`` converts a run of ``messages`` from their columns, decoding none."""
    source = _WatchedMessages(messages, ctx.topic)
    converter(Run(source, robot=ctx.robot, topic=ctx.topic, entity_path=ctx.entity_path,
                  topic_state=ctx.topic_state, robot_state=ctx.robot_state))
    return not source.decoded


def header(frame_id: str = "", stamp_ns: int = 1_000_000_000) -> Any:
    stamp = TYPES["builtin_interfaces/msg/Time"](
        sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000
    )
    return TYPES["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)


def msg(msgtype: str, **fields: Any) -> Any:
    return TYPES[msgtype](**fields)


def log_item(entries: Sequence[LogEntry], path: str) -> LogItem:
    found = [e for e in entries if isinstance(e, LogItem) and e.path == path and not e.static]
    assert len(found) == 1, f"expected one LogItem at {path}, got {entries}"
    return found[0]


def archetype(item: LogItem, kind: type[Any]) -> Any:
    found = [a for a in item.archetypes if isinstance(a, kind)]
    assert len(found) == 1, f"expected one {kind.__name__} in {item}"
    return found[0]


def columns_item(entries: Sequence[LogEntry], path: str) -> ColumnsItem:
    found = [e for e in entries if isinstance(e, ColumnsItem) and e.path == path]
    assert len(found) == 1, f"expected one ColumnsItem at {path}, got {[e.path for e in entries]}"
    return found[0]


def flat(batch: Any, width: int = 0) -> npt.NDArray[Any]:
    """A component batch (or the values of a column) as numpy, (n, width) for vector types."""
    array = batch.as_arrow_array() if hasattr(batch, "as_arrow_array") else batch
    while hasattr(array, "flatten") and array.type.num_fields == 1:
        array = array.flatten()
    values: npt.NDArray[Any] = array.to_numpy(zero_copy_only=False)
    return values.reshape(-1, width) if width else values


def column_rows(item: ColumnsItem, component: str, width: int = 0) -> list[npt.NDArray[Any]]:
    """Per-row values of one column, e.g. ``column_rows(item, "Scalars:scalars")``."""
    found = [c for c in item.columns if c.component_descriptor().component == component]
    assert len(found) == 1, f"{item.path} has no single {component} column"
    lists = found[0].as_arrow_array()
    offsets = lists.offsets.to_numpy()
    values = flat(lists.values, width)
    return [values[a:b] for a, b in pairwise(offsets)]


def rgba(packed: npt.NDArray[Any]) -> npt.NDArray[np.uint8]:
    """Rerun's 0xRRGGBBAA colours as (n, 4) uint8."""
    words = np.asarray(packed, dtype=np.uint32)
    return np.stack([(words >> s) & 0xFF for s in (24, 16, 8, 0)], axis=-1).astype(np.uint8)


def read_topic(bag: Path, topic: str) -> Iterator[Any]:
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        connections = [c for c in reader.connections if c.topic == topic]
        for connection, _, raw in reader.messages(connections=connections):
            yield reader.deserialize(raw, connection.msgtype)


def stamp_ns(message: Any) -> int:
    return int(message.header.stamp.sec) * 1_000_000_000 + int(message.header.stamp.nanosec)


def scalars_of(item: LogItem) -> npt.NDArray[np.float64]:
    return flat(archetype(item, rr.Scalars).scalars)


def default_message(store: Any, msgtype: str) -> Any:
    """A message of ``msgtype`` with zero/empty fields, built from the typestore's field table."""
    _, fields = store.fielddefs[msgtype]
    values: dict[str, Any] = {}
    for name, (kind, arg) in fields:
        if kind == Nodetype.BASE:
            values[name] = "" if arg[0] == "string" else 0
        elif kind == Nodetype.NAME:
            values[name] = default_message(store, arg)
        elif kind == Nodetype.ARRAY:
            sub, count = arg
            if sub[0] == Nodetype.BASE and sub[1][0] != "string":
                values[name] = np.zeros(count, dtype=_dtype(sub[1][0]))
            else:
                values[name] = [default_message(store, sub[1]) if sub[0] == Nodetype.NAME else ""
                                for _ in range(count)]
        else:  # SEQUENCE
            sub = arg[0]
            if sub[0] == Nodetype.BASE and sub[1][0] != "string":
                values[name] = np.zeros(0, dtype=_dtype(sub[1][0]))
            else:
                values[name] = []
    return store.types[msgtype](**values)


def _dtype(ros_type: str) -> str:
    return {"bool": "bool", "byte": "uint8", "char": "uint8", "octet": "uint8"}.get(ros_type, ros_type)
