"""The converter contract: what a converter gets (a run of one topic's messages and their
contexts) and what it returns (log items or columns); it never calls ``rr.log``, the sink does.

A converter is a pure function ``(msg, ctx) -> list[LogEntry]``; converters of high-rate small
types also offer the run form, which turns many messages of one topic into columns for
``rr.send_columns``. Kept apart from :mod:`host_bridge.registry` (the type table) so converters,
the sink, queues and the layout import the contract without importing every converter.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import rerun as rr

from host_bridge.errors import ConvertError, PartialConvertError
from host_bridge.options import Options
from host_bridge.state import RobotState, State, TopicState

TIMELINE_ROS = "ros_time"
TIMELINE_RECEIVE = "receive_time"
TIMELINE_LOG = "log_time"


@dataclass(frozen=True, slots=True)
class LogItem:
    """Archetypes to log at one entity path.

    ``times`` replaces the message's timeline values for this item (a TF message carries one
    stamp per transform); ``None`` keeps them. Static items ignore times.
    """

    path: str
    archetypes: tuple[rr.AsComponents, ...]
    static: bool = False
    times: Mapping[str, int] | None = None


@dataclass(frozen=True, slots=True)
class ColumnsItem:
    """Rows for ``rr.send_columns``: one row per entry of each ``times`` array (int64 ns)."""

    path: str
    columns: Iterable[Any]
    times: Mapping[str, npt.NDArray[np.int64]]


LogEntry = LogItem | ColumnsItem


@dataclass(frozen=True, slots=True)
class ConvertContext:
    """What a converter may know beyond the message itself.

    ``topic_state`` is kept by the dispatcher for the topic between messages: its options (read
    typed with :meth:`options`) and converter state records (:meth:`state`: odometry trails,
    marker lifetimes). ``robot_state`` is shared by all topics of one robot (the model
    /joint_states moves, the last map a grid update patches, the mesh resolver). The state
    records and ``robot_state`` are the only things a converter may mutate.
    """

    robot: str
    topic: str
    entity_path: str
    times: Mapping[str, int]
    topic_state: TopicState = field(default_factory=TopicState)
    robot_state: RobotState = field(default_factory=RobotState)

    def options(self, kind: type[Options]) -> Options:
        """The topic's options as ``kind`` (the converter family's record, see options.py)."""
        return self.topic_state.options(kind, self.topic)

    def state(self, kind: type[State]) -> State:
        """The topic's record of class ``kind``, made with its defaults on first use."""
        return self.topic_state.state(kind)

    def frame(self, frame_id: str) -> str | None:
        """Rerun frame name of a ROS frame: ``<robot>/<frame_id>``; None for an empty id."""
        frame_id = frame_id.strip("/")
        return f"{self.robot}/{frame_id}" if frame_id else None

    def child_path(self, *parts: str) -> str:
        return "/".join([self.entity_path, *parts])


Converter = Callable[[Any, ConvertContext], list[LogEntry]]
RunConverter = Callable[[Sequence[Any], Sequence[ConvertContext]], list[LogEntry]]


@dataclass(frozen=True, slots=True)
class ConverterSpec:
    """A converter, batch-first: ``convert_run`` takes a run of one topic's messages (with one
    context each) and returns log items or columns for ``rr.send_columns``; one message is the
    special case (:meth:`convert`).

    ``single`` is the converter's own one-message form where it has one (cheaper than a run of
    one, or logging rows where the run logs columns). ``message_by_message`` marks a run that is
    only a loop over ``single`` (:func:`per_message`): the dispatcher then converts message by
    message, so a bad message costs only itself and no message's state is applied twice.
    """

    convert_run: RunConverter
    single: Converter | None = None
    message_by_message: bool = False

    def convert(self, msg: Any, ctx: ConvertContext) -> list[LogEntry]:
        if self.single is not None:
            return self.single(msg, ctx)
        return self.convert_run((msg,), (ctx,))


def per_message(convert: Converter) -> ConverterSpec:
    """The spec of a converter written for one message at a time (maps, meshes, markers): its
    run is a loop until a columnar form is worth writing."""

    def convert_run(msgs: Sequence[Any], ctxs: Sequence[ConvertContext]) -> list[LogEntry]:
        return [entry for msg, ctx in zip(msgs, ctxs, strict=True) for entry in convert(msg, ctx)]

    return ConverterSpec(convert_run, single=convert, message_by_message=True)


def combine(*specs: ConverterSpec) -> ConverterSpec:
    """One spec running several converters on the same message (JointState: the robot's
    kinematics and the joint plots); a part that fails does not cost the others' output."""

    def gather(parts: Sequence[Callable[[], list[LogEntry]]]) -> list[LogEntry]:
        entries: list[LogEntry] = []
        errors: list[ConvertError] = []
        for part in parts:
            try:
                entries.extend(part())
            except PartialConvertError as err:
                entries.extend(err.items)
                errors.append(err)
            except ConvertError as err:
                errors.append(err)
        if errors:
            raise PartialConvertError("; ".join(str(e) for e in errors), entries)
        return entries

    def convert(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
        return gather([lambda s=s: s.convert(msg, ctx) for s in specs])  # type: ignore[misc]

    def convert_run(msgs: Sequence[Any], ctxs: Sequence[ConvertContext]) -> list[LogEntry]:
        return gather([lambda s=s: s.convert_run(msgs, ctxs) for s in specs])  # type: ignore[misc]

    return ConverterSpec(
        convert_run, single=convert, message_by_message=all(s.message_by_message for s in specs)
    )
