"""Heavy topics (images, point clouds, maps: the type table's ``Lane.HEAVY`` and ``Lane.PATCH`` rows)
converted in a process of their own, with its own GIL.

Why: in one process every conversion holds the one GIL for a while, and a small message that
arrives meanwhile waits for it (to be handed over by Zenoh's thread, then to be converted),
however low the heavy thread's priority. In the issue's mixed load (benchmarks/live_capacity.py:
a 300k-point cloud at 10 Hz and 640x480 images at 30 Hz beside scans, IMU and TF, the host
logging to a headless ``rerun`` viewer) the small topics' p99 latency was 7.3-9.8 ms in 8 runs
with this process, 11.3 and 11.9 ms in 2 with the heavy topics converted on their thread here.
Dropping the heavy samples unconverted (saving to /dev/null) gave 5.2-6.4 ms. The heavy topics'
own latency grows (their payloads cross a socket; a cloud's p50 went from 11-13 to 23-27 ms):
they are the ones that go latest-only.

When: a live host whose one Rerun destination is a gRPC viewer (``--rerun-addr``, ``--spawn``):
another process can log into the same recording there (same application and recording id). A
``--save`` file and the ``--serve-web`` server belong to this process, so with either, heavy
topics stay on their robots' heavy threads here (inputs/queues.py).

What stays here: everything about a heavy run but its conversion: the taps (``/_stats``,
``--record-mcap``), the topic's settings (entity path, options, the layout's views), its
counters and sequence gaps, the robot's frame tree. The converter process gets the run's
payloads and the topic's settings, decodes, converts and logs the run with a
:class:`~host_bridge.pipeline.dispatch.Conversion` of its own (whose slow lane runs the slow converters,
walls, too), and answers with what the run's counters gained and the frames its entries named.
The placements those frames call for are logged here (frames.py): a placement shares its
entity with /tf_static's transform of the frame and must never be written after it, which only
the stream that logs /tf can ensure.

Protocol, over a socket pair with multiprocessing's framing: the child first sends
``("ready", None)`` once its sink is open, or ``("failed", why)``. Then per run the host sends a
:class:`RunHead` and each message's payload as bytes (no pickling of the data); the child
answers one :class:`Outcome`. ``None`` asks the child to finish: it answers a last Outcome (the
frames its slow converters named since), closes its sink while the host closes its own, and
says ``("closed", None)``, or why the viewer may lack some of its data.

Failure: a child that cannot start, dies or stops answering is warned about once, naming why;
the run in hand and every later heavy run are converted here, so nothing is lost but the
conversion that was in the child when it died. Robots share the one child, a run at a time.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from typing import TYPE_CHECKING, Any

from host_bridge.errors import ConvertError, HostError
from host_bridge.inputs.queues import HEAVY_NICENESS, TypeLanes
from host_bridge.table.registry import Lane
from robot_relay.wire import MessageDefinition, RawMessage

if TYPE_CHECKING:
    from host_bridge.core.contract import LogEntry
    from host_bridge.core.counters import TopicCounters
    from host_bridge.pipeline.dispatch import Dispatcher, TopicBinding

log = logging.getLogger("swanky.host")

READY_TIMEOUT_S = 30.0
"""How long the first heavy run waits for the child to import Rerun and reach the viewer."""
POLL_S = 0.5
"""How often a wait for the child looks whether it is still alive."""
CHILD_MAIN = "import sys; from host_bridge.pipeline.offload import main; sys.exit(main(sys.argv[1:]))"
"""The child's program: :func:`main` of this module by its name (as ``__main__`` the records it
sends back would be unpickled as the host's ``__main__``'s)."""
ROUND_TRIP_VALID_S = 1.0
"""How long the child's round trip to the viewer, reported with a run's outcome, counts."""
CLOSE_TIMEOUT_S = 15.0
"""How long the child may take to log what it holds, and then to close its sink (RerunSink
gives a viewer that stopped answering about 9 s: a probe, then 6 s to disconnect), before it is
killed."""


@dataclass(frozen=True, slots=True)
class RunHead:
    """A run of one heavy topic, but its payloads (sent after it as bytes, one per message)."""

    robot: str
    topic: str
    msgtype: str
    definition: MessageDefinition | None
    settings: tuple[str, Mapping[str, Any], bool] | None
    """The topic's entity path, options and restamp for its type, with the first run of each
    type only (settings belong to a topic's type: dispatch.py)."""
    times: list[tuple[int | None, int | None, int | None]]
    """Each message's receive time, log time and wire sequence number."""


@dataclass(slots=True)
class Outcome:
    """What converting a run added to its topic's counters, and the frames its entries named
    that the child had not named before."""

    converted: int = 0
    dropped: int = 0
    warnings: int = 0
    seconds: float = 0.0
    relations: dict[str, list[tuple[str, str]]] = field(default_factory=dict)
    frames: dict[str, list[str]] = field(default_factory=dict)
    """Per robot."""
    error: str | None = None
    """An error that escaped the child's dispatcher (``--strict``, or a bug)."""
    viewer_round_trip: float = 0.0
    """How long the child's flushes take to reach the viewer (viewer_lag.py), as the run was
    logged: the host thins heavy runs by it too (thinning.py)."""


def _child_environment() -> dict[str, str]:
    """This environment, with the directory host_bridge was imported from first on the path
    (a benchmark or a checkout may have put it on sys.path by hand)."""
    root = str(Path(__file__).resolve().parent.parent)
    paths = [root, *(p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p)]
    return {**os.environ, "PYTHONPATH": os.pathsep.join(paths)}


class HeavyProcess:
    """The host's side of the converter process: :meth:`convert` hands it a heavy run and
    waits for its outcome (on the robot's heavy thread, so that thread's queue goes latest-only
    while the child is busy, as it would converting here)."""

    def __init__(
        self, dispatcher: Dispatcher, viewer: str, recording_id: str,
        give_up: Callable[[], bool] = lambda: False,
    ) -> None:
        """``give_up()`` true: the host is stopping, so the child stops waiting for a slow
        viewer too (it is told so by SIGTERM)."""
        self._dispatcher = dispatcher
        self._give_up = give_up
        self._told_to_give_up = False
        self._lanes = TypeLanes(dispatcher.registry)
        self._lock = threading.Lock()
        self._problem: str | None = None
        """Why the child is gone; heavy runs are then converted here."""
        self._warned = False
        self._round_trip = (0.0, 0.0)
        """The child's round trip to the viewer as of its last answer, and when that came."""
        self._ready = False
        self._sent: set[tuple[str, str, str]] = set()
        """The (robot, topic, type)s whose settings the child has."""
        ours, theirs = socket.socketpair()
        command = [sys.executable, "-c", CHILD_MAIN, str(theirs.fileno()), viewer, recording_id,
                   "--log-level", str(log.getEffectiveLevel())]
        if dispatcher.strict:
            command.append("--strict")
        with theirs:
            self._process = subprocess.Popen(
                command, pass_fds=(theirs.fileno(),), env=_child_environment(),
                stdin=subprocess.DEVNULL,
            )
        self._connection = Connection(ours.detach())

    def takes(self, raw: RawMessage) -> bool:
        """Whether ``raw``'s topic is converted in the child (while the child works)."""
        return self._problem is None and self._lanes(raw) is not Lane.SMALL

    def convert(self, run: Sequence[RawMessage], topic: TopicBinding, counters: TopicCounters) -> None:
        """Convert ``run`` in the child, or here once the child is gone."""
        first = run[0]
        with self._lock:
            outcome = self._exchange(run, topic) if self._problem is None else None
            if outcome is None and not self._warned:
                self._warned = True
                self._dispatcher.warn(first.robot, first.topic, HostError(
                    f"the heavy topics' converter process {self._problem}; converting heavy "
                    "topics in the host process from now on"))
        if outcome is None:
            self._dispatcher.conversion.convert(run, topic, counters)
            return
        counters.converted += outcome.converted
        counters.dropped += outcome.dropped
        counters.warnings += outcome.warnings
        counters.convert_seconds += outcome.seconds
        self._round_trip = (outcome.viewer_round_trip, time.monotonic())
        self._note_frames(outcome)
        if outcome.error is not None:
            raise ConvertError(f"{first.topic}: {outcome.error}")

    @property
    def viewer_round_trip(self) -> float:
        """The child's round trip to the viewer as of its last answer, for ROUND_TRIP_VALID_S:
        a child sent nothing more (its runs thinned) is not known to be behind any longer."""
        seconds, at = self._round_trip
        return seconds if time.monotonic() - at < ROUND_TRIP_VALID_S else 0.0

    def _exchange(self, run: Sequence[RawMessage], topic: TopicBinding) -> Outcome | None:
        """The child's outcome of ``run``; None (and ``_problem`` set) when it is gone."""
        first = run[0]
        key = (first.robot, first.topic, first.msgtype)
        settings = None if key in self._sent else (
            topic.entity_path, dict(topic.state.values), topic.restamp)
        head = RunHead(first.robot, first.topic, first.msgtype, first.definition, settings,
                       [(raw.receive_ns, raw.log_ns, raw.sequence) for raw in run])
        try:
            if not self._ready:
                self._await_ready()
            self._connection.send(head)
            for raw in run:
                self._connection.send_bytes(raw.data)
            self._sent.add(key)
            answer = self._receive(None)
        except (OSError, EOFError) as err:
            self._stop_child(f"stopped answering ({err})")
            return None
        except HostError as err:
            self._stop_child(str(err))
            return None
        assert isinstance(answer, Outcome)
        return answer

    def _await_ready(self) -> None:
        kind, why = self._receive(READY_TIMEOUT_S)
        if kind != "ready":
            raise HostError(f"could not start: {why}")
        self._ready = True

    def _receive(self, timeout: float | None) -> Any:
        """The child's next message; HostError when it exits or ``timeout`` passes first."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self._connection.poll(POLL_S):
            if self._give_up() and not self._told_to_give_up:
                self._told_to_give_up = True
                self._process.terminate()
            code = self._process.poll()
            if code is not None and not self._connection.poll(0):
                raise HostError(f"exited (code {code})")
            if deadline is not None and time.monotonic() > deadline:
                raise HostError(f"did not answer within {timeout:.0f} s")
        return self._connection.recv()

    def _stop_child(self, why: str) -> None:
        self._problem = why
        if self._process.poll() is None:
            self._process.kill()
            self._process.wait()
        self._connection.close()

    def _note_frames(self, outcome: Outcome) -> None:
        for robot in outcome.relations.keys() | outcome.frames.keys():
            self._dispatcher.log_frames(
                robot, outcome.relations.get(robot, ()), outcome.frames.get(robot, ()))

    def close(self) -> None:
        """Let the child convert and log what it holds; the frames it named last are noted
        here. It then closes its sink while the host closes its own: :meth:`finish`."""
        with self._lock:
            if self._problem is not None:
                return
            try:
                if not self._ready:
                    self._await_ready()
                self._connection.send(None)
                last = self._receive(CLOSE_TIMEOUT_S)
            except (OSError, EOFError, HostError) as err:
                self._stop_child(f"did not close ({err})")
                return
            self._problem = "closed"
        self._note_frames(last)

    def finish(self) -> str | None:
        """Once :meth:`close` returned: wait for the child to close its sink and end (killed
        after ``CLOSE_TIMEOUT_S``); why the viewer may lack some of its data, None if not."""
        why: str | None = None
        if self._problem is None:  # not closed: the host is ending on an error
            self._stop_child("stopped with the host")
        if not self._connection.closed:
            try:
                _, why = self._receive(CLOSE_TIMEOUT_S)
            except (OSError, EOFError, HostError) as err:
                why = f"the heavy topics' converter process did not close its viewer ({err})"
            self._connection.close()
        try:
            self._process.wait(CLOSE_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()
        return why


# -- the child ------------------------------------------------------------------------------


class _FrameNotes:
    """The relations and frames a robot's entries named that were not reported yet."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._seen: set[tuple[str, Any]] = set()
        self._pending = Outcome()

    def add(self, robot: str, entries: Sequence[LogEntry]) -> None:
        from host_bridge.core.frames import frames_logged

        relations, frames = frames_logged(entries)
        with self._lock:
            for relation in relations:
                if (robot, relation) not in self._seen:
                    self._seen.add((robot, relation))
                    self._pending.relations.setdefault(robot, []).append(relation)
            for frame in frames:
                if (robot, frame) not in self._seen:
                    self._seen.add((robot, frame))
                    self._pending.frames.setdefault(robot, []).append(frame)

    def take(self, outcome: Outcome) -> Outcome:
        """``outcome`` with the frames noted since the last one."""
        with self._lock:
            outcome.relations, outcome.frames = self._pending.relations, self._pending.frames
            self._pending = Outcome()
        return outcome


def _serve(connection: Connection, viewer: str, recording_id: str, strict: bool) -> int:
    from host_bridge.core.counters import TopicCounters
    from host_bridge.core.decode import Decoder
    from host_bridge.core.destinations import SinkOptions
    from host_bridge.core.state import TopicState
    from host_bridge.errors import SinkError
    from host_bridge.outputs.sink import RerunSink
    from host_bridge.pipeline.dispatch import Conversion, TopicBinding
    from host_bridge.table.registry import default_registry

    notes = _FrameNotes()
    giving_up = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: giving_up.set())
    try:
        # keep_up: like the host's own sink, it stops sending to a viewer that stopped taking
        # data rather than wait for it (the host thins what it sends here: thinning.py).
        sink = RerunSink(SinkOptions(connect=viewer, recording_id=recording_id),
                         give_up=giving_up.is_set, keep_up=True)
    except SinkError as err:
        connection.send(("failed", str(err)))
        return 1
    def log_noting_frames(robot: str, entries: Sequence[LogEntry], times: Mapping[str, int]) -> None:
        """Logs like the host's dispatcher, but leaves the frame tree to the host: the frames
        the entries name are noted for the host instead."""
        notes.add(robot, entries)
        sink.log(entries, times)

    conversion = Conversion(sink, log_noting_frames, registry=default_registry(), decoder=Decoder(),
                            counters={}, strict=strict)
    topics: dict[tuple[str, str, str], TopicBinding] = {}
    connection.send(("ready", None))
    while True:
        try:
            head = connection.recv()
            if head is None:
                break
            run = [RawMessage(head.robot, head.topic, head.msgtype, connection.recv_bytes(),
                              head.definition, *times) for times in head.times]
        except (EOFError, OSError):
            break  # the host is gone: finish what is held
        key = (head.robot, head.topic, head.msgtype)
        if head.settings is not None:
            entity_path, options, restamp = head.settings
            topics[key] = TopicBinding(head.msgtype, entity_path, TopicState(options), True, restamp)
        counters = conversion.counters[(head.robot, head.topic)] = TopicCounters(head.msgtype)
        outcome = Outcome()
        try:
            conversion.convert(run, topics[key], counters)
        except Exception as err:  # --strict, or a bug: the host reports it
            outcome.error = f"{type(err).__name__}: {err}"
        outcome.converted, outcome.dropped = counters.converted, counters.dropped
        outcome.warnings, outcome.seconds = counters.warnings, counters.convert_seconds
        if sink.viewer_lag is not None:
            outcome.viewer_round_trip = sink.viewer_lag.round_trip
        try:
            connection.send(notes.take(outcome))
        except OSError:
            break
    conversion.close()
    with contextlib.suppress(OSError):  # unless the host is gone
        connection.send(notes.take(Outcome()))
    problem = None
    try:
        sink.close()
    except SinkError as err:
        problem = f"heavy topics: {err}"
    with contextlib.suppress(OSError):
        connection.send(("closed", problem))
    if sink.abandoned:
        os._exit(1)  # Rerun's exit handler would wait for the viewer too (sink.py)
    return 0 if problem is None else 1


def main(argv: Iterable[str] | None = None) -> int:
    """The converter process (``FD VIEWER RECORDING_ID [--strict] [--log-level N]``), which only
    :class:`HeavyProcess` starts."""
    parser = argparse.ArgumentParser(prog="swanky-host's heavy topics' converter process")
    parser.add_argument("fd", type=int)
    parser.add_argument("viewer")
    parser.add_argument("recording_id")
    parser.add_argument("--strict", action="store_true")
    parser.add_argument("--log-level", type=int, default=logging.INFO)
    args = parser.parse_args(None if argv is None else list(argv))
    # Ctrl-C reaches the whole process group: the host closes this process in its own order.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # Its lines on the host's stderr read as the host's own (cli.py).
    logging.basicConfig(level=args.log_level, format="%(name)s: %(levelname)s: %(message)s")
    if sys.platform == "linux":
        # Like the heavy threads of inputs/queues.py: the host's small topics get a core first.
        os.nice(HEAVY_NICENESS)
    return _serve(Connection(args.fd), args.viewer, args.recording_id, args.strict)
