"""Each relay's clock measured against this PC's, so that its receive times land on the PC's
timeline.

A Raspberry Pi has no real-time clock: on a network without internet it boots with the time it
last shut down, and its relay's receive times (``receive_time``, and ``latency_ms``, the host's
clock minus them) can be hours away from the other robots'. The host measures every relay's
clock as NTP does, over the relay's clock query (``swanky/<robot>/clock``, schemas/wire.md):

* a round trip: the PC's clock when the query leaves (t1) and when the reply arrives (t4), the
  relay's when the query reached it (t2) and when it replied (t3). If the query took as long
  each way, the relay's clock is ahead of the PC's by ((t2 - t1) + (t3 - t4)) / 2; however the
  round trip ``(t4 - t1) - (t3 - t2)`` split between the two ways, the truth lies within half
  of it (the query cannot reach the relay before it left, nor the reply come back before it
  was sent). Every delay a query met (Wi-Fi retries, either side's Python waiting for its
  GIL) only widens that bound, so :class:`ClockEstimator` keeps the sample whose bound is the
  smallest: the round trip's half plus :data:`MAX_DRIFT` times its age.
* a burst of :data:`BURST` queries when a relay joins (its samples wait for it, as they wait
  for its catalog, so its first rows are corrected too), then one every
  :data:`QUERY_PERIOD_S`, over a window of the last :data:`WINDOW`: drift is followed by the
  newer samples winning as the older ones age.
* a clock that steps (NTP reaching the Pi, someone setting the date) is followed at once: a
  sample whose offset lies outside both its own bound and the estimate's cannot come from the
  same clock, so the window restarts from it and a burst refines it. The relay's data prompt
  that query within :data:`SUSPECT_GAP_S`: a message received "in the future" of the PC (a
  negative latency beyond the uncertainty) or more than :data:`SUSPECT_LATENCY_NS` in its past
  says the estimate is stale. Messages the relay stamped between the step and the new
  estimate keep the old correction.

The offset is the robot's clock minus the PC's; a relay time ``t`` is ``t - offset`` on the
PC's clock. Only the relay's receive times are corrected (zenoh.py): header stamps
(``ros_time``) and source times (``log_time``) stay as the robot wrote them.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import zenoh

from host_bridge.errors import ClockOffsetError, NoClockError
from host_bridge.inputs.base import InputProblem
from robot_relay.errors import WireError
from robot_relay.wire import ClockReading, clock_key

log = logging.getLogger("swanky.host")

MAX_DRIFT = 100e-6
"""How fast a relay's clock and the PC's may drift apart, relative: 100 ppm. A free-running
board crystal is rated ±20-50 ppm; the rest is room for the PC's own clock being slewed by
NTP meanwhile. It ages a sample's bound by 0.1 ms per second, so a fresh sample with a slightly
longer round trip wins over an old one with a shorter."""
JUMP_MARGIN_NS = 1_000_000
"""Beyond both bounds by this much, a sample says the clock stepped (1 ms: what one
nanosecond-rounded sample and a drift a little above :data:`MAX_DRIFT` never reach)."""
WINDOW = 16
BURST = 8
BURST_SPACING_S = 0.001
QUERY_PERIOD_S = 2.0
NO_ANSWER_AFTER_S = 1.0
"""A relay is said not to answer once its whole first burst and this long went unanswered: a
relay that has just joined may not have its clock query routed to this host yet."""
QUERY_TIMEOUT_S = 1.0
READY_TIMEOUT_S = 2.0
"""The most a joining relay's samples wait for its first burst."""
SUSPECT_LATENCY_NS = 1_000_000_000
SUSPECT_GAP_S = 0.25
"""At most one query prompted by a relay's data in this time."""
SLEW = 0.5
"""How fast a correction moves a relay's receive times back to a better estimate: by half the
time that passes on the relay's clock, so they still advance at half speed (in order) and a
320 ms change is made in 640 ms. Any rate below 1 keeps the order; a slower one keeps times
known to be off for longer."""
FAR_OFF_NS = 1_000_000_000
"""A relay clock further than this from the PC's is warned about (once per robot)."""


@dataclass(frozen=True, slots=True)
class ClockSample:
    """One clock query's round trip: ``sent_ns`` (t1) and ``answered_ns`` (t4) on the PC's
    clock, ``relay_received_ns`` (t2) and ``relay_replied_ns`` (t3) on the relay's."""

    sent_ns: int
    relay_received_ns: int
    relay_replied_ns: int
    answered_ns: int

    @property
    def offset_ns(self) -> int:
        """The relay's clock minus the PC's, were the round trip split evenly."""
        return (self.relay_received_ns - self.sent_ns + self.relay_replied_ns - self.answered_ns) // 2

    @property
    def round_trip_ns(self) -> int:
        """The round trip without the relay's own time: twice the bound of :attr:`offset_ns`."""
        return self.answered_ns - self.sent_ns - (self.relay_replied_ns - self.relay_received_ns)


@dataclass(frozen=True, slots=True)
class ClockEstimate:
    """A relay's clock minus the PC's, the truth within ``uncertainty_ns`` of ``offset_ns`` as
    of ``at_ns`` (the PC's clock when the newest sample came); ``jumped``: the clock stepped,
    the samples before the newest were dropped."""

    offset_ns: int
    uncertainty_ns: int
    at_ns: int
    jumped: bool = False


@dataclass(frozen=True, slots=True)
class Correction:
    """What a relay's receive time ``t`` (on its clock) loses to land on the PC's: ``to_ns``,
    the estimate's offset, reached from ``from_ns`` at :data:`SLEW` from ``since_ns`` (the
    relay's clock when the estimate came) when it moves times back; pure."""

    from_ns: int
    to_ns: int
    since_ns: int

    @classmethod
    def at_once(cls, estimate: ClockEstimate) -> Correction:
        return cls(estimate.offset_ns, estimate.offset_ns, estimate.at_ns + estimate.offset_ns)

    def offset_ns(self, relay_ns: int) -> int:
        """The offset applied to a time ``relay_ns`` stamped by the relay."""
        if self.to_ns <= self.from_ns:
            return self.to_ns
        slewed = self.from_ns + int(SLEW * max(0, relay_ns - self.since_ns))
        return min(self.to_ns, slewed)

    def then(self, estimate: ClockEstimate) -> Correction:
        """The correction once ``estimate`` came: slewed to from where this one is then, when
        it moves times back and the clock did not step."""
        since = estimate.at_ns + estimate.offset_ns
        now = self.offset_ns(since)
        if estimate.jumped or estimate.offset_ns <= now:
            return Correction.at_once(estimate)
        return Correction(now, estimate.offset_ns, since)


def bound_ns(sample: ClockSample, now_ns: int) -> int:
    """How far the truth may be from ``sample``'s offset at ``now_ns``: half its round trip,
    plus what :data:`MAX_DRIFT` may have added since."""
    half_round_trip = (sample.round_trip_ns + 1) // 2  # up: the offset was rounded down
    return half_round_trip + round(MAX_DRIFT * (now_ns - sample.answered_ns))


class ClockEstimator:
    """The offset of one relay's clock from samples (the module's doc); pure."""

    def __init__(self) -> None:
        self._samples: collections.deque[ClockSample] = collections.deque(maxlen=WINDOW)
        self.estimate: ClockEstimate | None = None

    def _best(self, now_ns: int) -> tuple[ClockSample, int]:
        best = min(self._samples, key=lambda sample: bound_ns(sample, now_ns))
        return best, bound_ns(best, now_ns)

    def add(self, sample: ClockSample) -> ClockEstimate | None:
        """The estimate with ``sample``; None (the sample ignored) when its round trip is
        negative, which only a clock stepping during it makes."""
        if sample.round_trip_ns < 0:
            return None
        now = sample.answered_ns
        jumped = False
        if self._samples:
            best, bound = self._best(now)
            jumped = (abs(sample.offset_ns - best.offset_ns)
                      > bound_ns(sample, now) + bound + JUMP_MARGIN_NS)
            if jumped:
                self._samples.clear()
        self._samples.append(sample)
        best, bound = self._best(now)
        self.estimate = ClockEstimate(best.offset_ns, bound, now, jumped)
        return self.estimate


def ask_clock(session: zenoh.Session, robot: str, timeout: float = QUERY_TIMEOUT_S) -> ClockSample | None:
    """One round trip of ``robot``'s clock query; None when no relay answered (one older than
    the query, or none there). A reply that is no clock reading raises WireError."""
    key = clock_key(robot)
    sent_ns = time.time_ns()
    for reply in session.get(key, timeout=timeout):
        answered_ns = time.time_ns()
        if reply.ok is None:
            continue
        reading = ClockReading.unpack(reply.ok.payload.to_bytes(), key)
        return ClockSample(sent_ns, reading.received_ns, reading.replied_ns, answered_ns)
    return None


def far_off(robot: str, estimate: ClockEstimate) -> ClockOffsetError:
    """The warning about a clock more than :data:`FAR_OFF_NS` off the PC's: by how much, which
    way, and what is corrected."""
    seconds = estimate.offset_ns / 1e9
    return ClockOffsetError(
        f"robot {robot}'s clock is {abs(seconds):.3f} s {'ahead of' if seconds > 0 else 'behind'} "
        f"this PC's (±{estimate.uncertainty_ns / 1e6:.1f} ms, measured over {clock_key(robot)}): "
        "its receive_time and latency_ms are corrected by it; ros_time (header stamps) and "
        "log_time stay as the robot wrote them"
    )


ClockWatcher = Callable[[str, ClockEstimate], None]


class _Follower:
    """One relay's clock, asked on a thread of its own."""

    def __init__(self, robot: str) -> None:
        self.robot = robot
        self.estimator = ClockEstimator()
        self.ready = threading.Event()
        """Set once the first burst is over (answered or not)."""
        self.wake = threading.Event()
        self.stop = threading.Event()
        self.prompted = 0.0
        self.published = False
        """Whether an estimate of this relay's clock was given out."""
        self.thread: threading.Thread | None = None


class RelayClocks:
    """Follows the clock of every relay that joins (one thread each, :meth:`follow`) and gives
    its offset from the PC's (:meth:`offset_ns`, 0 until measured) and the correction of its
    receive times (:meth:`correction_ns`, slewed to a new estimate: :class:`Correction`).
    Problems go to ``report`` (the input's queues): a relay that does not answer, a clock off
    by more than a second."""

    def __init__(self, session: zenoh.Session, report: Callable[[InputProblem], None]) -> None:
        self._session = session
        self._report = report
        self._lock = threading.Lock()
        self._followers: dict[str, _Follower] = {}
        # Read on Zenoh's threads for every sample, written whole: no lock needed.
        self._estimates: dict[str, ClockEstimate] = {}
        self._corrections: dict[str, Correction] = {}
        self._watchers: list[ClockWatcher] = []
        self._said: set[tuple[str, type[Exception]]] = set()
        self._closed = False

    def watch(self, watcher: ClockWatcher) -> None:
        """Call ``watcher(robot, estimate)`` with every new estimate (on the robot's thread)."""
        with self._lock:
            self._watchers.append(watcher)

    def offset_ns(self, robot: str) -> int:
        """``robot``'s relay clock minus the PC's, as last estimated; 0 until then."""
        estimate = self._estimates.get(robot)
        return 0 if estimate is None else estimate.offset_ns

    def correction_ns(self, robot: str, relay_ns: int) -> int:
        """What ``robot``'s relay time ``relay_ns`` loses to land on the PC's clock; 0 until
        measured."""
        correction = self._corrections.get(robot)
        return 0 if correction is None else correction.offset_ns(relay_ns)

    def follow(self, robot: str) -> None:
        """Measure ``robot``'s clock anew (its relay joined: a rebooted robot may have another
        clock), from a burst on; the offset in use stays until that gives one."""
        follower = _Follower(robot)
        with self._lock:
            if self._closed:
                return
            previous = self._followers.get(robot)
            self._followers[robot] = follower
            follower.thread = threading.Thread(
                target=self._run, args=(follower,), name=f"clock-{robot}", daemon=True
            )
        if previous is not None:
            previous.stop.set()
            previous.wake.set()
        follower.thread.start()

    def unfollow(self, robot: str) -> None:
        """Stop asking ``robot``'s clock (its relay left); its last offset stays for the
        samples still on their way."""
        with self._lock:
            follower = self._followers.pop(robot, None)
        if follower is not None:
            follower.stop.set()
            follower.wake.set()

    def wait_ready(self, robot: str, timeout: float = READY_TIMEOUT_S) -> None:
        """Wait (at most ``timeout`` s) for ``robot``'s first burst, if its clock is followed."""
        with self._lock:
            follower = self._followers.get(robot)
        if follower is not None:
            follower.ready.wait(timeout)

    def check_arrival(self, robot: str, relay_receive_ns: int) -> None:
        """A sample stamped ``relay_receive_ns`` by ``robot``'s relay arrived now: a time the
        estimate puts in the PC's future, or long past, prompts a query (the module's doc)."""
        estimate = self._estimates.get(robot)
        if estimate is None:
            return
        latency = time.time_ns() - (relay_receive_ns - estimate.offset_ns)
        if -estimate.uncertainty_ns - JUMP_MARGIN_NS <= latency <= SUSPECT_LATENCY_NS:
            return
        follower = self._followers.get(robot)
        now = time.monotonic()
        if follower is not None and now - follower.prompted >= SUSPECT_GAP_S:
            follower.prompted = now
            follower.wake.set()

    def _run(self, follower: _Follower) -> None:
        queries = BURST
        answered = False
        unanswered = 0
        said_unanswered = False
        following_since = time.monotonic()
        while not follower.stop.is_set():
            follower.wake.clear()  # before asking: a prompt that comes meanwhile asks again
            sample = self._ask(follower)
            estimate = None if sample is None else follower.estimator.add(sample)
            if estimate is not None:
                answered = True
                queries = BURST if estimate.jumped else queries
                self._publish(follower, estimate)
            elif sample is None and not answered and not said_unanswered:
                unanswered += 1
                if unanswered >= BURST and time.monotonic() - following_since >= NO_ANSWER_AFTER_S:
                    said_unanswered = True
                    self._say(follower.robot, NoClockError(
                        f"robot {follower.robot}'s relay does not answer the clock query "
                        f"({clock_key(follower.robot)}; a relay older than this host?): its "
                        "receive_time and latency_ms stay on its own clock, uncorrected"))
            queries -= 1
            if queries <= 0:
                follower.ready.set()
            current = follower.estimator.estimate
            if follower.ready.is_set() and current is not None and abs(current.offset_ns) > FAR_OFF_NS:
                self._say(follower.robot, far_off(follower.robot, current))
            follower.wake.wait(BURST_SPACING_S if queries > 0 else QUERY_PERIOD_S)

    def _ask(self, follower: _Follower) -> ClockSample | None:
        """One round trip; None when unanswered (a reply that is no clock reading is said once,
        a session closing meanwhile is no answer)."""
        try:
            return ask_clock(self._session, follower.robot)
        except WireError as err:
            self._say(follower.robot, NoClockError(str(err)))
        except zenoh.ZError as err:
            if not follower.stop.is_set():
                log.debug("clock query to %s failed: %s", follower.robot, err)
        return None

    def _publish(self, follower: _Follower, estimate: ClockEstimate) -> None:
        with self._lock:
            if self._followers.get(follower.robot) is not follower:
                return  # replaced by a newer relay's measurement
            self._estimates[follower.robot] = estimate
            previous = self._corrections.get(follower.robot)
            # A relay that joined anew may run another clock: its first estimate applies at once.
            self._corrections[follower.robot] = (
                Correction.at_once(estimate) if previous is None or not follower.published
                else previous.then(estimate))
            follower.published = True
            watchers = list(self._watchers)
        for watcher in watchers:
            watcher(follower.robot, estimate)

    def _say(self, robot: str, problem: Exception) -> None:
        """Report ``problem`` once per robot and kind."""
        with self._lock:
            if (robot, type(problem)) in self._said:
                return
            self._said.add((robot, type(problem)))
        self._report(InputProblem(robot, clock_key(robot), problem))

    def close(self) -> None:
        with self._lock:
            self._closed = True
            followers = list(self._followers.values())
            self._followers.clear()
        for follower in followers:
            follower.stop.set()
            follower.wake.set()
        for follower in followers:
            if follower.thread is not None:
                follower.thread.join(QUERY_TIMEOUT_S + 1.0)
