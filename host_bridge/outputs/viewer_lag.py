"""How far behind the Rerun viewers are: the round trip of what the host logs, out of this
process and into the viewer.

A flush of the viewers' stream alone measures only this side: it returns once Rerun's gRPC
client has handed everything logged before it to the connection. A native viewer buffers far
more than that before it draws it: its gRPC server passes messages to the viewer through two
channels of up to 128 MiB each (Rerun 0.41's re_grpc_server and re_log_channel), which only
hold the connection back once full. Measured: a native viewer under Xvfb with software GL
(llvmpipe), sent 10 MB/s of images and points, was 12 s behind the data and then 15 s, while
every flush returned within 0.13-0.42 s.

So after the flush, each viewer on this PC is asked for its state over its viewer-control
service (``rerun.experimental.ViewerClient.get_state``): the request reaches the viewer through
the same channels as the data, after everything the flush delivered, and is answered when the
viewer has taken all of it in (in that experiment the call took 12 and 15 s, and the state it
returned ended at the data logged when it was asked). A flush's round trip is the time from
its start to the last answer; the lag, what ``/_stats/host/viewer_lag_ms`` shows, adds the
flush period, which the oldest rows of a flush waited for it. A viewer that cannot answer (on
another PC, whose control service serves loopback clients only; ``rerun --serve-grpc``, which
has no viewer; ``rerun --save``, which only writes) is measured by the flush alone, a lower
bound; so is the ``--serve-web`` server, whose viewer is a browser.

While a measurement is under way its age counts: a viewer that stopped reading shows a lag that
grows by the second, not one that is known only once it reads again. The converter process's
own round trip (offload.py: its heavy topics reach the viewer over a connection of their own)
counts too.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import rerun as rr
    from rerun.experimental import ViewerClient

log = logging.getLogger("swanky.host")

SHORTEST_PERIOD_S = 0.2
"""How often the viewers' stream is flushed (and a measurement starts) while they keep up: the
rows of a topic go to them in one chunk per period (Rerun's default batching, 0.2 s)."""
LONGEST_PERIOD_S = 0.5
"""The longest a viewer slow to take chunks in is made to wait for its rows (thinning.py): the
lag it adds must leave room under a second."""
BATCHER_TICK_S = 2.0
"""The viewers' stream's batcher sends its rows on its own only after this long: the flushes
every :attr:`ViewerLag.period` decide how they are batched (and a measurement that waits long
for a slow viewer does not hold them longer than this)."""
FLUSH_STEP_S = 1.0
"""A flush is waited on in steps this long, so a stop is seen in between."""
PROBE_TRIES = 4
"""A viewer that never answers in this many tries (``ViewerClient`` waits 15 s for an answer,
Rerun's own limit) is measured by flushes only: a ``rerun --save`` viewer has the service but
no viewer to answer."""


@dataclass(frozen=True, slots=True)
class LaggingViewer:
    """A viewer the host sends to: ``name`` for messages, ``url`` where its viewer-control
    service may answer (None: a destination that cannot, the ``--serve-web`` server)."""

    name: str
    url: str | None


class ViewerLag:
    """A thread flushing the viewers' stream every :attr:`period` and measuring how long each
    flush takes to reach the viewers (one measurement after another). Another thread first
    finds which viewers answer questions (a ``rerun --save`` viewer takes a minute to be found
    out, meanwhile measured by flushes only).

    Rerun's viewer takes in messages for at most 10 ms per frame it draws (re_viewer's
    ``receive_messages``), and each chunk, a message, costs it about the same whatever its
    rows: a viewer under software GL drew a frame a second with one demo robot and took in 46
    chunks a frame (0.26 ms each, a puffin profile of 20 frames). So the period is also how the
    viewers are sent less without losing anything: each topic's rows of a period go in one
    chunk, and a longer period means fewer chunks (thinning.py lengthens it while they fall
    behind)."""

    def __init__(
        self, recording: rr.RecordingStream, viewers: Sequence[LaggingViewer],
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._recording = recording
        self.viewers = tuple(viewers)
        self._clock = clock
        self.period = SHORTEST_PERIOD_S
        """Seconds from one flush's start to the next (a flush still under way delays it)."""
        self._answering: dict[str, ViewerClient] = {}
        """The viewers whose viewer-control service answered, by name: asked every time."""
        self.others: list[Callable[[], float]] = []
        """The round trips of other streams into the same viewers (the converter process's:
        offload.py), counted in :attr:`round_trip`."""
        self._started: float | None = None
        self._last = 0.0
        self._last_answers = 0.0
        self._stopping = threading.Event()
        for target, name in ((self._find_answering, "viewer-lag-probe"), (self._run, "viewer-lag")):
            threading.Thread(target=target, name=name, daemon=True).start()

    @property
    def names(self) -> str:
        return "; ".join(viewer.name for viewer in self.viewers)

    @property
    def round_trip(self) -> float:
        """Seconds from a flush's start to the viewers having taken in what it sent: the last
        one's, or the age of the one under way if longer; another stream's if longer still."""
        started = self._started
        pending = 0.0 if started is None else self._clock() - started
        return max(self._last, pending, *(other() for other in self.others))

    @property
    def answers(self) -> float:
        """Seconds the viewers took to answer after the last flush: their part of its round
        trip (0 for viewers measured by flushes only)."""
        return self._last_answers

    @property
    def seconds(self) -> float:
        """How far behind the viewers are: how old data can be when they have it, the round
        trip of a flush plus the period its rows waited for it."""
        return self.round_trip + self.period

    def _run(self) -> None:
        while not self._stopping.is_set():
            started = self._started = self._clock()
            if not self._flushed():
                self._started = None
                return
            flushed = self._clock()
            self._ask(list(self._answering.items()))
            answered = self._clock()
            self._last, self._last_answers = answered - started, answered - flushed
            self._started = None
            log.debug("viewer round trip %.3f s: flush %.3f s, then the viewers' answers %.3f s",
                      self._last, flushed - started, self._last_answers)
            self._stopping.wait(max(0.0, self.period - self._last))

    def _flushed(self) -> bool:
        """Until the viewers' stream has sent everything logged so far; False if it failed (a
        viewer went away: RerunSink names it when it closes) or measuring stopped."""
        while not self._stopping.is_set():
            try:
                self._recording.flush(timeout_sec=FLUSH_STEP_S)
                return True
            except RuntimeError as err:
                if "timed out" not in str(err):  # Rerun's words for a viewer that is only slow
                    return False
        return False

    def _ask(self, viewers: Sequence[tuple[str, ViewerClient]]) -> None:
        """Ask each viewer for its state: it answers once it took in what the flush delivered.
        One that times out (15 s) is that far behind or more; one that fails otherwise (it went
        away) is no longer asked."""
        for name, client in viewers:
            if self._stopping.is_set():
                return
            try:
                client.get_state()
            except TimeoutError:
                pass
            except (ConnectionError, RuntimeError) as err:
                log.debug("viewer lag of %s: no longer asked (%s)", name, err)
                self._answering.pop(name, None)

    def _find_answering(self) -> None:
        """Ask each viewer on this PC once, up to PROBE_TRIES times while it does not answer
        in time (a viewer still starting); those that answer are asked at every measurement."""
        from rerun.experimental import ViewerClient

        for viewer in self.viewers:
            if viewer.url is None:
                continue
            for _ in range(PROBE_TRIES):
                if self._stopping.is_set():
                    return
                try:
                    client = ViewerClient(viewer.url)
                    client.get_state()
                except TimeoutError:
                    continue  # starting, or `rerun --save`, which never answers
                except (ConnectionError, RuntimeError, ValueError) as err:
                    log.debug("viewer lag of %s: flushes only (%s)", viewer.name, err)
                    break
                self._answering[viewer.name] = client
                break

    def stop(self) -> None:
        """Stop measuring; a flush or question under way is not waited for."""
        self._stopping.set()
