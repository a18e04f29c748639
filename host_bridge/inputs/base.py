"""What every host input is: the :class:`Input` protocol and the items inputs deliver.

An input (a bag, the robots reached over Zenoh, the demo) turns what it reads into runs of
:data:`InputItem`: RawMessages, the problems it met on the way (a sample it could not parse) and
robots joining or leaving. ``host_bridge/app.py`` starts one with
:meth:`Dispatcher.take <host_bridge.pipeline.dispatch.Dispatcher.take>` as the place to put them, waits
until it ends (a bag) or the host stops (live), and closes it. Push, not pull: live inputs
receive on Zenoh's threads and convert each robot on a thread of its own (inputs/queues.py), so
one slow robot delays only itself; a bag reads on its own thread and pushes its runs the same
way, and the app waits on both alike.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Protocol, overload

import numpy as np
import numpy.typing as npt
import rerun as rr

from host_bridge.core.columns import PackedPayloads
from host_bridge.core.contract import TIMELINE_RECEIVE, LogItem
from robot_relay.wire import MessageDefinition, RawMessage

PRESENCE_PATH = "/_swanky/robots"


@dataclass(frozen=True, slots=True)
class InputProblem:
    """A sample the input had to drop; the dispatcher reports it once per kind."""

    robot: str
    topic: str
    error: Exception


@dataclass(frozen=True, slots=True)
class RobotEvent:
    """A robot joined or left (its liveliness token(s) appeared or all disappeared)."""

    robot: str
    joined: bool
    source: str

    @property
    def text(self) -> str:
        return f"robot {self.robot} {'joined' if self.joined else 'left'} ({self.source})"


def presence_items(event: RobotEvent, now_ns: int) -> list[LogItem]:
    """A robot joining or leaving, as a line of the /_swanky/robots TextLog at ``now_ns``."""
    text = rr.TextLog(event.text, level=rr.TextLogLevel.INFO)
    return [LogItem(PRESENCE_PATH, (text,), times={TIMELINE_RECEIVE: now_ns})]


@dataclass(frozen=True, slots=True, eq=False)
class MessageRun(Sequence[RawMessage]):
    """Messages of one topic (one type and definition) in their order, as a bag input reads
    them and a relay's bundles bring them: the payloads, their times and wire sequence numbers
    as arrays, not a record per message. The dispatcher reads a columnar type's run straight
    from :attr:`payloads` and :attr:`log_ns`; whoever iterates it (a tap, the message path)
    gets RawMessages, built as they are asked for."""

    robot: str
    topic: str
    msgtype: str
    definition: MessageDefinition | None
    payloads: Sequence[bytes | memoryview]
    log_ns: npt.NDArray[np.int64] | None = None
    receive_ns: npt.NDArray[np.int64] | None = None
    sequence: npt.NDArray[np.int64] | None = None

    def __len__(self) -> int:
        return len(self.payloads)

    @overload
    def __getitem__(self, index: int) -> RawMessage: ...
    @overload
    def __getitem__(self, index: slice) -> Sequence[RawMessage]: ...
    def __getitem__(self, index: int | slice) -> RawMessage | Sequence[RawMessage]:
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        return RawMessage(
            self.robot, self.topic, self.msgtype, self.payloads[index], self.definition,
            *(None if column is None else int(column[index])
              for column in (self.receive_ns, self.log_ns, self.sequence)),
        )

    def part(self, start: int, stop: int) -> MessageRun:
        """Messages ``start`` to ``stop`` as a run of their own (a slice gives RawMessages)."""
        return MessageRun(
            self.robot, self.topic, self.msgtype, self.definition, self.payloads[start:stop],
            *(None if column is None else column[start:stop]
              for column in (self.log_ns, self.receive_ns, self.sequence)),
        )

    def __iter__(self) -> Iterator[RawMessage]:
        count = len(self.payloads)
        columns = [[None] * count if column is None else column.tolist()
                   for column in (self.receive_ns, self.log_ns, self.sequence)]
        for data, receive_ns, log_ns, sequence in zip(self.payloads, *columns, strict=True):
            yield RawMessage(self.robot, self.topic, self.msgtype, data, self.definition,
                             receive_ns, log_ns, sequence)


def _joinable(run: MessageRun, after: MessageRun) -> bool:
    """Whether ``after`` can follow ``run`` in one run: same type and definition, payloads in
    buffers, and the same times and sequence columns present."""
    return (
        (run.msgtype, run.definition) == (after.msgtype, after.definition)
        and isinstance(run.payloads, PackedPayloads) and isinstance(after.payloads, PackedPayloads)
        and all((mine is None) == (theirs is None) for mine, theirs in (
            (run.log_ns, after.log_ns), (run.receive_ns, after.receive_ns),
            (run.sequence, after.sequence)))
    )


def _concatenated(runs: Sequence[MessageRun]) -> MessageRun:
    """One run of ``runs`` (joinable, of one topic) after each other."""
    first = runs[0]
    buffers: list[bytes | memoryview] = []
    sources = []
    for run in runs:
        assert isinstance(run.payloads, PackedPayloads)
        sources.append(run.payloads.sources + len(buffers))
        buffers.extend(run.payloads.buffers)
    payloads = PackedPayloads(
        tuple(buffers), np.concatenate(sources),
        *(np.concatenate([getattr(run.payloads, name) for run in runs]) for name in ("starts", "ends")),
    )
    columns = [None if getattr(first, name) is None
               else np.concatenate([getattr(run, name) for run in runs])
               for name in ("log_ns", "receive_ns", "sequence")]
    return MessageRun(first.robot, first.topic, first.msgtype, first.definition, payloads, *columns)


def gathered(items: Sequence[InputItem]) -> list[InputItem]:
    """``items`` with the runs of each topic joined into one where nothing of that topic lies
    between them (each topic's order kept): a live host behind takes what waits as one run per
    topic, as long as the wait, since the run's conversion costs Rerun calls, not its length."""
    out: list[InputItem | list[MessageRun]] = []
    open_runs: dict[tuple[str, str], list[MessageRun]] = {}
    for item in items:
        if isinstance(item, MessageRun):
            key = (item.robot, item.topic)
            joined = open_runs.get(key)
            if joined is not None and _joinable(joined[0], item):
                joined.append(item)
                continue
            open_runs[key] = [item]
            out.append(open_runs[key])
        else:
            if isinstance(item, RawMessage):
                open_runs.pop((item.robot, item.topic), None)
            out.append(item)
    return [
        (item[0] if len(item) == 1 else _concatenated(item)) if isinstance(item, list) else item
        for item in out
    ]


InputItem = RawMessage | MessageRun | InputProblem | RobotEvent
"""What inputs deliver: a bag hands over :class:`MessageRun` s, live inputs a record per
message."""
Deliver = Callable[[Sequence[InputItem]], None]
"""Where an input puts its runs (the dispatcher's ``take``); it may raise (``--strict``)."""


class Input(Protocol):
    """A source of robots' messages for the host, in the manner of rosbags' storage plugins:
    the app only ever calls these four members."""

    def start(self, deliver: Deliver) -> None:
        """Begin handing runs of items to ``deliver``, from the input's own threads: one
        robot's runs one at a time and in order, different robots' possibly at once. Returns
        at once (the demo first writes its bags, watching the host's stop)."""

    def ended(self) -> bool:
        """True once the input has delivered all it ever will (a bag read to its end; a live
        input never ends). Raises what stopped it: an unreadable bag, or the error ``deliver``
        raised (``--strict``)."""

    @property
    def last_activity(self) -> float:
        """``time.monotonic()`` when data, a problem or a robot event last arrived: what
        ``--until-idle`` waits on."""

    def close(self) -> None:
        """Stop reading; what was already read is still delivered (a saved .rrd is then
        complete). Idempotent."""
