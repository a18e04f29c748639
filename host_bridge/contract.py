"""The converter contract: what a converter gets (a run of one topic's messages and their
contexts) and what it returns (log items or columns); it never calls ``rr.log``, the sink does.

A converter is a pure function ``(msg, ctx) -> list[LogEntry]``; converters of high-rate small
types also offer the run form, which turns many messages of one topic into columns for
``rr.send_columns``, and the columnar form (:func:`columnar`), which reads the run's payloads as
numpy columns (:mod:`host_bridge.columns`) with no Python per message. Kept apart from
:mod:`host_bridge.registry` (the type table) so converters, the sink, queues and the layout
import the contract without importing every converter.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import rerun as rr

from host_bridge.errors import ConvertError, PartialConvertError
from host_bridge.options import Options
from host_bridge.state import RobotState, State, TopicState

TIMELINE_ROS = "ros_time"
TIMELINE_RECEIVE = "receive_time"
TIMELINE_LOG = "log_time"
WARNINGS_PATH = "/_swanky/warnings"
"""Where every warning of the host goes, beside its log line."""
STATS_ROOT = "/_stats"
"""Root of the health series (stats.py) and of SLAM's (slam/feeder.py)."""

if TYPE_CHECKING:
    from host_bridge.columns import Columns

Int64Array = npt.NDArray[np.int64]
RowIndex = npt.NDArray[np.intp]


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


@functools.cache
def _component(
    archetype: type[rr.AsComponents], field_name: str
) -> tuple[rr.ComponentDescriptor, Any, _Floats | None]:
    descriptor: rr.ComponentDescriptor = getattr(archetype, f"descriptor_{field_name}")()
    component = (descriptor.component_type or "").rsplit(".", 1)[-1]
    datatype: pa.DataType = getattr(rr.components, component).arrow_type()
    floats = None
    if pa.types.is_floating(datatype):
        floats = _Floats(datatype, np.dtype(datatype.to_pandas_dtype()), None)
    elif pa.types.is_fixed_size_list(datatype) and pa.types.is_floating(datatype.value_type):
        floats = _Floats(datatype, np.dtype(datatype.value_type.to_pandas_dtype()), datatype.list_size)
    return descriptor, getattr(rr.components, f"{component}Batch"), floats


@dataclass(frozen=True, slots=True)
class _Floats:
    """A component whose cells are floats, or ``width`` floats each (vectors, quaternions)."""

    datatype: pa.DataType
    dtype: np.dtype[Any]
    width: int | None

    def cells(self, values: Any) -> pa.Array | None:
        """Numbers, shape (n,) or (n, width), as the Arrow array Rerun's batch makes of them:
        cast and wrapped as it does, without its checks of every other kind of input; None
        for anything else."""
        if not isinstance(values, np.ndarray) or values.dtype.kind not in "fiu":
            return None
        flat = values.astype(self.dtype, copy=False).ravel()
        if self.width is None:
            return pa.array(flat, self.datatype)
        if values.ndim != 2 or values.shape[1] != self.width:
            return None
        return pa.FixedSizeListArray.from_arrays(flat, type=self.datatype)


class RowsColumn(rr.ComponentColumn):
    """A component column that keeps its rows' offsets at hand: the sink logs a few rows as
    slices of the batch (``_offsets`` is Rerun's private attribute; the public way builds an
    Arrow list array per column and a list scalar per row)."""

    def __init__(
        self, descriptor: rr.ComponentDescriptor, batch: Any, offsets: npt.NDArray[np.int32]
    ) -> None:
        super().__init__(descriptor, batch, offsets=offsets)
        self.row_offsets = offsets


def component_columns(
    archetype: type[rr.AsComponents], lengths: npt.ArrayLike | None = None, **fields: Any
) -> list[rr.ComponentColumn]:
    """``archetype.columns(**fields)`` without making an archetype: each field's component
    batch, in rows of ``lengths`` instances (default: one a row). Rerun's own ``columns`` costs
    50-200 us a call whatever the rows (it builds and checks the whole archetype), more than the
    rest of converting and logging a live message of one row."""
    offsets = None
    if lengths is not None:
        lengths = np.asarray(lengths)
        offsets = np.zeros(lengths.size + 1, np.int32)
        np.add.accumulate(lengths, out=offsets[1:])  # np.cumsum, without its Python wrapper
    made: list[rr.ComponentColumn] = []
    for name, values in fields.items():
        descriptor, batch, floats = _component(archetype, name)
        arrow = None if floats is None else floats.cells(values)
        cells = batch(values if arrow is None else arrow)
        rows = offsets if offsets is not None else np.arange(len(cells) + 1, dtype=np.int32)
        made.append(RowsColumn(descriptor, cells, rows))
    return made


_FEW_TEXTS = 32  # up to this many (a live run of one message) a list converts faster


def repeated_texts(texts: Sequence[str], rows: npt.NDArray[np.integer[Any]] | int) -> pa.Array:
    """The strings ``texts[rows]`` as one Arrow utf8 array, made from its buffers: the column of
    a few strings repeated over many rows (frame names, arrow labels) for ``rr.*.columns``,
    which takes it as it is (a list of Python strings is encoded there one at a time). ``rows``
    a number: ``texts`` in order, that many times over."""
    if isinstance(rows, int) and rows * len(texts) <= _FEW_TEXTS:
        return pa.array(list(texts) * rows, pa.utf8())
    if not isinstance(rows, int) and len(rows) <= _FEW_TEXTS:
        return pa.array([texts[row] for row in rows.tolist()], pa.utf8())
    if not isinstance(rows, int) and len(rows) % len(texts) == 0 and (
        rows.reshape(-1, len(texts)) == np.arange(len(texts))
    ).all():  # texts in order again and again (a TF run's transforms): joined once, repeated
        rows = len(rows) // len(texts)
    encoded = [text.encode() for text in texts]
    sizes = np.array([len(text) for text in encoded], np.int64)
    row_sizes = np.tile(sizes, rows) if isinstance(rows, int) else sizes[rows]
    offsets = np.zeros(len(row_sizes) + 1, np.int64)
    np.cumsum(row_sizes, out=offsets[1:])
    if isinstance(rows, int) or len(encoded) == 1:
        data = np.frombuffer(b"".join(encoded) * (rows if isinstance(rows, int) else len(rows)), np.uint8)
    else:
        width = int(sizes.max()) if len(sizes) else 0
        table = np.zeros((len(encoded), width), np.uint8)
        for row, text in enumerate(encoded):
            table[row, : len(text)] = np.frombuffer(text, np.uint8)
        data = table[rows][np.arange(width) < row_sizes[:, None]]
    return pa.StringArray.from_buffers(
        len(row_sizes), pa.py_buffer(offsets.astype(np.int32)), pa.py_buffer(data)
    )


class TopicContext:
    """What both contexts say about their topic: options, state records, frame names, paths."""

    __slots__ = ()
    robot: str
    topic: str
    entity_path: str
    topic_state: TopicState
    robot_state: RobotState

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


@dataclass(frozen=True, slots=True)
class ConvertContext(TopicContext):
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
    # ros_time is the arrival time, not the header stamp (the topic's ``restamp`` setting).
    restamp: bool = False


@dataclass(frozen=True, slots=True)
class RunContext(TopicContext):
    """A run of ``size`` messages of one topic, converted in columns: the topic's context and
    each message's arrival times (``None`` for a timeline the input does not give: receive_time
    offline, log_time live). A columnar converter takes each row's ros_time from its header
    stamps through :meth:`stamped`, which applies ``restamp`` and the zero-stamp rule."""

    robot: str
    topic: str
    entity_path: str
    size: int
    receive_ns: Int64Array | None = None
    log_ns: Int64Array | None = None
    restamp: bool = False
    topic_state: TopicState = field(default_factory=TopicState)
    robot_state: RobotState = field(default_factory=RobotState)

    def stamped(
        self, stamps: Int64Array | None, rows: RowIndex | None = None
    ) -> list[tuple[RowIndex, dict[str, Int64Array]]]:
        """The timelines of entries made from the run's messages ``rows`` (default: one entry
        per message), ``stamps`` their header stamps in ns (None: a type without a header), in
        groups ``(entry indices, times)``: one group, two when some stamps are zero, none
        without rows. A zero
        stamp means "no stamp", as one message gets no ros_time then (``message_times``), and
        one send_columns call cannot leave a timeline out for some rows only."""
        every_message = rows is None
        rows = np.arange(self.size) if rows is None else rows
        if not len(rows):
            return []
        arrivals = {
            name: values if every_message else values[rows]
            for name, values in ((TIMELINE_RECEIVE, self.receive_ns), (TIMELINE_LOG, self.log_ns))
            if values is not None
        }
        arrival = self.receive_ns if self.receive_ns is not None else self.log_ns
        every = rows if every_message else np.arange(len(rows))
        if self.restamp and arrival is not None:
            return [(every, {TIMELINE_ROS: arrival if every_message else arrival[rows], **arrivals})]
        if stamps is None:
            return [(every, arrivals)]
        unstamped = stamps == 0
        if not unstamped.any():
            return [(every, {TIMELINE_ROS: stamps, **arrivals})]
        groups: list[tuple[RowIndex, dict[str, Int64Array]]] = []
        stamped_rows = np.flatnonzero(~unstamped)
        if stamped_rows.size:
            times = {name: values[stamped_rows] for name, values in arrivals.items()}
            groups.append((stamped_rows, {TIMELINE_ROS: stamps[stamped_rows], **times}))
        unstamped_rows = np.flatnonzero(unstamped)
        if unstamped_rows.size:
            groups.append(
                (unstamped_rows, {name: values[unstamped_rows] for name, values in arrivals.items()})
            )
        return groups

    def last_times(self) -> dict[str, int]:
        """The last message's arrival times: where a warning about the run goes."""
        return {
            name: int(values[-1])
            for name, values in ((TIMELINE_RECEIVE, self.receive_ns), (TIMELINE_LOG, self.log_ns))
            if values is not None and len(values)
        }


Converter = Callable[[Any, ConvertContext], list[LogEntry]]
RunConverter = Callable[[Sequence[Any], Sequence[ConvertContext]], list[LogEntry]]
ColumnsConverter = Callable[["Columns", RunContext], "list[LogEntry] | None"]
"""A run's payloads as columns -> entries; None: this run needs the message path."""


@dataclass(frozen=True, slots=True)
class ConverterSpec:
    """A converter, batch-first: ``convert_run`` takes a run of one topic's messages (with one
    context each) and returns log items or columns for ``rr.send_columns``; one message is the
    special case (:meth:`convert`).

    ``single`` is the converter's own one-message form where it has one (cheaper than a run of
    one, or logging rows where the run logs columns). ``message_by_message`` marks a run that is
    only a loop over ``single`` (:func:`per_message`): the dispatcher then converts message by
    message, so a bad message costs only itself and no message's state is applied twice.

    ``convert_columns`` is the columnar form (:func:`columnar`): the dispatcher reads a run's
    payloads with :func:`host_bridge.columns.read_columns` and hands the columns over, decoding
    nothing message by message.
    """

    convert_run: RunConverter
    single: Converter | None = None
    message_by_message: bool = False
    convert_columns: ColumnsConverter | None = None

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


def run_context(ctxs: Sequence[ConvertContext]) -> RunContext:
    """The run context of messages given one context each (decoded messages in columns)."""
    ctx = ctxs[0]

    def arrivals(name: str) -> Int64Array | None:
        if not all(name in c.times for c in ctxs):
            return None
        return np.fromiter((c.times[name] for c in ctxs), dtype=np.int64, count=len(ctxs))

    return RunContext(
        robot=ctx.robot,
        topic=ctx.topic,
        entity_path=ctx.entity_path,
        size=len(ctxs),
        receive_ns=arrivals(TIMELINE_RECEIVE),
        log_ns=arrivals(TIMELINE_LOG),
        restamp=ctx.restamp,
        topic_state=ctx.topic_state,
        robot_state=ctx.robot_state,
    )


def columnar(convert_columns: ColumnsConverter) -> ConverterSpec:
    """The spec of a converter written against columns only. Its message form (tests, a run the
    dispatcher had to decode message by message) serializes the messages again and reads them
    as columns, so the one body serves both and both give the same rows."""

    def convert_run(msgs: Sequence[Any], ctxs: Sequence[ConvertContext]) -> list[LogEntry]:
        from host_bridge.columns import columns_of_messages

        if not msgs:
            return []
        entries = convert_columns(columns_of_messages(msgs, ctxs[0].topic), run_context(ctxs))
        if entries is None:
            msg = f"{ctxs[0].topic}: its converter needs columns the messages do not give"
            raise ConvertError(msg)
        return entries

    return ConverterSpec(convert_run, convert_columns=convert_columns)


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

    column_forms = [s.convert_columns for s in specs]

    def column_part(form: ColumnsConverter, columns: Columns, ctx: RunContext) -> list[LogEntry]:
        entries = form(columns, ctx)
        if entries is None:  # the other parts would run twice on the message path
            msg = f"{ctx.topic}: one part of its converter declined the columns"
            raise ConvertError(msg)
        return entries

    def convert_columns(columns: Columns, ctx: RunContext) -> list[LogEntry] | None:
        return gather([lambda f=f: column_part(f, columns, ctx) for f in column_forms])  # type: ignore[misc]

    return ConverterSpec(
        convert_run,
        single=convert,
        message_by_message=all(s.message_by_message for s in specs),
        convert_columns=convert_columns if None not in column_forms else None,
    )
