"""The converter contract: what a converter gets (a :class:`Run` of one topic's messages) and
what it returns (log items or columns); it never calls ``rr.log``, the sink does.

One form: a converter is a function ``(run) -> list[LogEntry]``. The run gives the messages
decoded, or their fields as numpy columns (:mod:`host_bridge.core.columns`, no Python per message),
each on demand, and the one rule of every timeline (:meth:`Run.times`). A converter written for
one message at a time is made one by :func:`per_message`. Kept apart from
:mod:`host_bridge.table.registry` (the type table) so converters, the sink, queues and the layout
import the contract without importing every converter.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import rerun as rr

from host_bridge.core.options import Options
from host_bridge.core.state import RobotState, State, TopicState
from host_bridge.errors import ConvertError, HostError, PartialConvertError

TIMELINE_ROS = "ros_time"
TIMELINE_RECEIVE = "receive_time"
TIMELINE_LOG = "log_time"
WARNINGS_PATH = "/_swanky/warnings"
"""Where every warning of the host goes, beside its log line."""
STATS_ROOT = "/_stats"
"""Root of the health series (stats.py) and of SLAM's (slam/feeder.py)."""

if TYPE_CHECKING:
    from host_bridge.core.columns import Columns

Int64Array = npt.NDArray[np.int64]
RowIndex = npt.NDArray[np.intp]


@dataclass(frozen=True, slots=True)
class LogItem:
    """Archetypes to log at one entity path.

    ``times`` are its timelines (:meth:`Run.times`; :func:`per_message` gives each message's
    items its own); ``None``: the timelines of its run's last message (:meth:`Run.row_times`,
    with its stamp), where the dispatcher logs the run. Static items ignore times.
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



def scalar_rows(rows: Sequence[tuple[str, Mapping[str, int], float]]) -> list[ColumnsItem]:
    """A Scalars row per entry (its entity path, its timelines and its value), the values made
    into one batch: the sink logs each item as a row of its own, a slice of that batch (a few
    rows: ``RerunSink._log_rows``). A ``rr.Scalars`` and a ``log`` per row cost the 2,275 rows a
    second of the host's ``/_stats`` of 25 robots 100-130 ms of CPU a second; these about half
    (benchmarks/RESULTS.md, issue 24's fleet of 25)."""
    descriptor, batch, floats = _component(rr.Scalars, "scalars")
    values = np.fromiter((value for _, _, value in rows), np.float64, len(rows))
    cells = batch(values if floats is None else floats.cells(values))
    offsets = np.arange(len(rows) + 1, dtype=np.int32)
    return [
        ColumnsItem(path, [RowsColumn(descriptor, cells, offsets[row:row + 2])],
                    {name: np.array([at], np.int64) for name, at in times.items()})
        for row, (path, times, _) in enumerate(rows)
    ]

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
    """One message's context, as :func:`per_message` hands it to a converter written for one
    message at a time: its topic's, and the message's timelines (``times``, by the run's rule,
    :meth:`Run.times`).

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


TimeGroups = list[tuple[RowIndex, dict[str, Int64Array]]]
"""Rows in groups ``(row indices, their timelines)``: one ``send_columns`` each."""


class MessageSource(Protocol):
    """Where a run's messages come from: payloads the dispatcher decodes on demand
    (dispatch.py), or messages already decoded (:func:`message_run`)."""

    def __len__(self) -> int: ...

    def decode(self, row: int) -> Any:
        """Message ``row``; a HostError naming the problem when its payload does not decode."""
        ...

    def columns(self) -> Columns:
        """Every message's fields as columns; a HostError when they cannot be read so."""
        ...

    def part(self, row: int) -> MessageSource:
        """Message ``row`` alone."""
        ...


class Run(TopicContext):
    """A run of one topic's messages of one type, in their order: all a converter gets.

    Its topic's context (options, state records, frame names, entity paths); the messages,
    decoded (:meth:`messages`) or read as numpy columns with no Python per message
    (:meth:`columns`), each on demand and once; and the one rule giving every row its
    timelines (:meth:`times`). ``receive_ns`` and ``log_ns`` are each message's arrival times
    (None: a timeline the input does not give: receive_time offline, log_time live)."""

    __slots__ = ("_columns", "_contexts", "_messages", "_size", "_source", "entity_path",
                 "log_ns", "receive_ns", "restamp", "robot", "robot_state", "topic", "topic_state")

    def __init__(
        self,
        source: MessageSource,
        *,
        robot: str,
        topic: str,
        entity_path: str,
        receive_ns: Int64Array | None = None,
        log_ns: Int64Array | None = None,
        restamp: bool = False,
        topic_state: TopicState | None = None,
        robot_state: RobotState | None = None,
        messages: Sequence[Any] | None = None,
        contexts: list[ConvertContext] | None = None,
    ) -> None:
        """``messages``, ``contexts``: the source's messages and their contexts, when they are
        known already."""
        self._source = source
        self._size = len(source)
        self.robot = robot
        self.topic = topic
        self.entity_path = entity_path
        self.receive_ns = receive_ns
        self.log_ns = log_ns
        self.restamp = restamp
        self.topic_state = TopicState() if topic_state is None else topic_state
        self.robot_state = RobotState() if robot_state is None else robot_state
        self._messages = messages
        self._contexts = contexts
        self._columns: Columns | None = None

    def __len__(self) -> int:
        return self._size

    def messages(self) -> Sequence[Any]:
        """The messages, decoded (a HostError naming the first that does not decode)."""
        if self._messages is None:
            self._messages = [self._source.decode(row) for row in range(self._size)]
        return self._messages

    def columns(self) -> Columns:
        """The messages' fields as columns (:mod:`host_bridge.core.columns`), read from their
        payloads without decoding them; a HostError when the run cannot be read so (a payload
        that does not decode, nested sequences of differing lengths)."""
        if self._columns is None:
            self._columns = self._source.columns()
        return self._columns

    def stamps(self) -> Int64Array | None:
        """The messages' header stamps in ns, decoding them; None for a type without a header."""
        stamps = [header_stamp(m) for m in self.messages()]
        if not stamps or stamps[0] is None:
            return None
        return np.array(stamps, np.int64)

    def times(self, stamps: Int64Array | None, rows: RowIndex | None = None) -> TimeGroups:
        """The timelines of entries made from the run's messages ``rows`` (default: one entry
        per message), ``stamps`` their stamps in ns (None: a type without a header), in groups
        ``(entry indices, times)``: one group, two when some stamps are zero, none without
        rows. The one rule of every timeline: ``ros_time`` is the stamp, or the arrival time
        when the topic is restamped; a zero stamp means "no stamp", so its rows have no
        ros_time (one send_columns call cannot leave a timeline out for some rows only);
        ``receive_time`` and ``log_time`` are the arrival times the input gives."""
        if rows is None:  # every message (the usual case): the arrival arrays as they are
            if not self._size:
                return []
            every = np.arange(self._size)
            receive, logged = self.receive_ns, self.log_ns
        else:
            if not len(rows):
                return []
            every = np.arange(len(rows))
            receive = None if self.receive_ns is None else self.receive_ns[rows]
            logged = None if self.log_ns is None else self.log_ns[rows]
        arrivals: dict[str, Int64Array] = {}
        if receive is not None:
            arrivals[TIMELINE_RECEIVE] = receive
        if logged is not None:
            arrivals[TIMELINE_LOG] = logged
        arrival = receive if receive is not None else logged
        if self.restamp and arrival is not None:
            return [(every, {TIMELINE_ROS: arrival, **arrivals})]
        if stamps is None:
            return [(every, arrivals)]
        if np.count_nonzero(stamps) == len(stamps):  # (ndarray.all costs more on a short run)
            return [(every, {TIMELINE_ROS: stamps, **arrivals})]
        groups: TimeGroups = []
        unstamped = stamps == 0
        stamped_rows = np.flatnonzero(~unstamped)
        if stamped_rows.size:
            times = {name: values[stamped_rows] for name, values in arrivals.items()}
            groups.append((stamped_rows, {TIMELINE_ROS: stamps[stamped_rows], **times}))
        unstamped_rows = np.flatnonzero(unstamped)
        groups.append(
            (unstamped_rows, {name: values[unstamped_rows] for name, values in arrivals.items()})
        )
        return groups

    def row_times(self, row: int = -1, stamp: int | None = None) -> dict[str, int]:
        """Message ``row``'s timelines by :meth:`times`, ``stamp`` its stamp (None: unknown, or
        none): what the dispatcher logs about it (a warning; an item without times), and each
        message's context. :meth:`times`' rule for one row, with no arrays: a live message
        alone (the usual live run) would spend more on making them than on converting; the
        test of both paths (tests/host_bridge/test_run_paths.py) holds the two to one rule."""
        receive = None if self.receive_ns is None else int(self.receive_ns[row])
        logged = None if self.log_ns is None else int(self.log_ns[row])
        times: dict[str, int] = {}
        arrival = receive if receive is not None else logged
        if self.restamp and arrival is not None:
            times[TIMELINE_ROS] = arrival
        elif stamp:  # zero: no stamp
            times[TIMELINE_ROS] = stamp
        if receive is not None:
            times[TIMELINE_RECEIVE] = receive
        if logged is not None:
            times[TIMELINE_LOG] = logged
        return times

    def last_times(self) -> Mapping[str, int]:
        """The timelines of the run's last message (where items without times of their own go):
        its context's, when the contexts are made."""
        if self._contexts is not None:
            return self._contexts[-1].times
        return self.row_times(-1, self.stamp(-1))

    def stamp(self, row: int = -1) -> int | None:
        """Message ``row``'s header stamp: from the columns or messages the run has read, else
        decoded alone; None for a type without a header, or a message that does not decode."""
        if self._columns is not None and self._messages is None:
            if "header.stamp.sec" not in self._columns.paths:
                return None
            seconds, nanoseconds = (self._columns[f"header.stamp.{part}"] for part in ("sec", "nanosec"))
            return int(seconds[row]) * 1_000_000_000 + int(nanoseconds[row])
        try:
            message = (self._source.decode(row % self._size) if self._messages is None
                       else self._messages[row])
        except HostError:
            return None
        return header_stamp(message)

    def contexts(self) -> list[ConvertContext]:
        """One context per message, at its timelines (the messages decoded for their stamps)."""
        if self._contexts is None:
            if self._size == 1:  # a live message alone: no arrays (see row_times)
                per_row = [self.row_times(0, header_stamp(self.messages()[0]))]
            else:
                per_row = [{}] * self._size
                for rows, times in self.times(self.stamps()):
                    columns = {name: values.tolist() for name, values in times.items()}
                    for entry, row in enumerate(rows.tolist()):
                        per_row[row] = {name: column[entry] for name, column in columns.items()}
            self._contexts = [
                ConvertContext(self.robot, self.topic, self.entity_path, times, self.topic_state,
                               self.robot_state, self.restamp)
                for times in per_row
            ]
        return self._contexts

    def one(self, row: int) -> Run:
        """Message ``row`` as a run of its own (decoded and its context made, if this run's
        are)."""
        row %= self._size
        return Run(
            self._source.part(row), robot=self.robot, topic=self.topic,
            entity_path=self.entity_path,
            receive_ns=None if self.receive_ns is None else self.receive_ns[row : row + 1],
            log_ns=None if self.log_ns is None else self.log_ns[row : row + 1],
            restamp=self.restamp, topic_state=self.topic_state, robot_state=self.robot_state,
            messages=None if self._messages is None else [self._messages[row]],
            contexts=None if self._contexts is None else [self._contexts[row]],
        )

    def split(self) -> list[Run]:
        """The run message by message, a run of one each."""
        return [self.one(row) for row in range(self._size)]


def header_stamp(msg: Any) -> int | None:
    """A message's header stamp in ns; None for a type without a header."""
    stamp = getattr(getattr(msg, "header", None), "stamp", None)
    return None if stamp is None else int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


@dataclass(frozen=True, slots=True)
class _Decoded:
    """Messages already decoded, as a run's source (:func:`message_run`)."""

    messages: Sequence[Any]
    topic: str

    def __len__(self) -> int:
        return len(self.messages)

    def decode(self, row: int) -> Any:
        return self.messages[row]

    def columns(self) -> Columns:
        from host_bridge.core.columns import columns_of_messages

        return columns_of_messages(self.messages, self.topic)

    def part(self, row: int) -> _Decoded:
        return _Decoded([self.messages[row]], self.topic)


def message_run(msgs: Sequence[Any], ctxs: Sequence[ConvertContext]) -> Run:
    """The run of messages already decoded (tests, benchmarks, a user's script), given one
    context each: the first one's topic and restamp, each one's arrival times (a timeline some
    lack is left out); ros_time follows the run's rule (:meth:`Run.times`), from the stamps."""
    ctx = ctxs[0]

    def arrivals(name: str) -> Int64Array | None:
        if not all(name in c.times for c in ctxs):
            return None
        return np.fromiter((c.times[name] for c in ctxs), dtype=np.int64, count=len(ctxs))

    return Run(
        _Decoded(msgs, ctx.topic), robot=ctx.robot, topic=ctx.topic, entity_path=ctx.entity_path,
        receive_ns=arrivals(TIMELINE_RECEIVE), log_ns=arrivals(TIMELINE_LOG), restamp=ctx.restamp,
        topic_state=ctx.topic_state, robot_state=ctx.robot_state, messages=msgs,
    )


Converter = Callable[[Run], list[LogEntry]]
"""The one form of every converter: a run of one topic's messages -> its log entries."""
MessageConverter = Callable[[Any, ConvertContext], list[LogEntry]]
"""A converter written for one message at a time, made a :data:`Converter` by :func:`per_message`."""


def _timed(entries: Iterable[LogEntry], times: Mapping[str, int]) -> list[LogEntry]:
    """``entries`` with each LogItem that has no times of its own (and is not static) at
    ``times``."""
    return [
        LogItem(e.path, e.archetypes, False, times)
        if isinstance(e, LogItem) and e.times is None and not e.static else e
        for e in entries
    ]


@dataclass(frozen=True, slots=True)
class PerMessage:
    """The converter of a type converted one message at a time (maps, meshes, images): each
    message with its own context, its items at its own times. The dispatcher hands it runs of
    one message, so a bad message costs only itself and no message's state is applied twice."""

    convert: MessageConverter

    def __call__(self, run: Run) -> list[LogEntry]:
        if len(run) == 1:
            # A message alone (the usual live run): its items without times of their own go at
            # the run's last message's timelines, which are its own (see LogItem).
            return self.convert(run.messages()[0], run.contexts()[0])
        entries: list[LogEntry] = []
        errors: list[str] = []
        for msg, ctx in zip(run.messages(), run.contexts(), strict=True):
            try:
                items = self.convert(msg, ctx)
            except PartialConvertError as err:
                items = err.items
                errors.append(str(err))
            entries.extend(_timed(items, ctx.times))
        if errors:
            raise PartialConvertError("; ".join(errors), entries)
        return entries


def per_message(convert: MessageConverter) -> PerMessage:
    """The converter of a function written for one message at a time."""
    return PerMessage(convert)


def combine(*converters: Converter) -> Converter:
    """One converter running several on the same run (JointState: the robot's kinematics and
    the joint plots); a part that fails does not cost the others' output."""

    def convert(run: Run) -> list[LogEntry]:
        entries: list[LogEntry] = []
        errors: list[ConvertError] = []
        for part in converters:
            try:
                entries.extend(part(run))
            except PartialConvertError as err:
                entries.extend(err.items)
                errors.append(err)
            except ConvertError as err:
                errors.append(err)
        if errors:
            raise PartialConvertError("; ".join(str(e) for e in errors), entries)
        return entries

    return convert
