"""What every relay source is: the :class:`Source` protocol, and the :class:`Outlet` it pushes to.

A source (a bag replayed, the live ROS graph through rclpy) knows the robot's topics (its
catalog) and hands over their messages as RawMessages, never decoded. ``robot_relay/app.py``
declares the Relay from the source's first catalog, starts the source with an outlet that
publishes (and learns the files a /robot_description names), waits until it ends (a bag) or the
relay stops (live), and closes it. Push, as the host's inputs (host_bridge/inputs/base.py): the
live graph delivers on its take loop's thread (``sources/take_loop.py``), so a bag replays on a
thread of its own too and the app waits on both alike.
"""

from __future__ import annotations

import fnmatch
import threading
from collections.abc import Callable, Mapping, Sequence
from typing import Protocol

from robot_relay.wire import Catalog, RawMessage, TopicInfo

TopicFilter = Callable[[str], bool]


def topic_filter(include: Sequence[str], exclude: Sequence[str]) -> TopicFilter:
    """Topics matching an ``include`` glob and no ``exclude`` glob; a topic named exactly in
    ``include`` is taken whatever ``exclude`` says (asking for /parameter_events by name)."""
    named = {g for g in include if not any(c in g for c in "*?[")}

    def accept(topic: str) -> bool:
        name = "/" + topic.lstrip("/")
        return name in named or (any(fnmatch.fnmatchcase(name, g) for g in include) and not any(
            fnmatch.fnmatchcase(name, g) for g in exclude
        ))

    return accept


class Outlet(Protocol):
    """Where a source puts what it reads (the app's relay and file server)."""

    def publish(self, raw: RawMessage) -> None:
        """Forward one message (from the source's thread)."""

    def publish_run(
        self, info: TopicInfo, payloads: Sequence[bytes | memoryview], log_ns: Sequence[int]
    ) -> None:
        """Forward several messages of one topic, all due now, in their order (a replay)."""

    def update_catalog(self, catalog: Catalog) -> None:
        """The robot's topics changed (a live graph); the relay re-declares its publishers."""


class Source(Protocol):
    """A robot's ROS topics for the relay, in the manner of rosbags' storage plugins: the app
    only ever calls these members."""

    def catalog(self) -> Catalog:
        """The topics known before :meth:`start` (all of a bag's; none yet of a live graph,
        which sends them through :meth:`Outlet.update_catalog` as it discovers them)."""

    def start(self, outlet: Outlet) -> None:
        """Begin handing messages (and catalog updates) to ``outlet`` from the source's own
        threads. Returns at once."""

    def ended(self) -> bool:
        """True once the source has handed over all it ever will (a bag replayed to its end; a
        live graph never ends). Raises what stopped it early."""

    def on_demand(self, topic: str, wanted: bool) -> None:
        """A host started (``wanted``) or stopped listening to ``topic`` (the Relay calls it from
        Zenoh's threads); a live source subscribes in ROS only while someone listens, a bag
        ignores it."""

    def drop_counts(self) -> Mapping[str, int]:
        """Messages per topic the source knows it lost before the relay (the relay's stats)."""

    def close(self) -> None:
        """Stop handing over messages and release what the source holds (ROS, the bag file).
        Idempotent."""


class SourceThread:
    """A source's worker thread, whose exception :meth:`ended` raises on the app's thread."""

    def __init__(self, name: str, target: Callable[[], None]) -> None:
        self._target = target
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        try:
            self._target()
        except BaseException as err:  # raised on the app's thread by ended()
            self._error = err

    def ended(self) -> bool:
        if self._error is not None:
            raise self._error
        return self._thread.ident is not None and not self._thread.is_alive()

    def join(self) -> None:
        if self._thread.ident is not None:
            self._thread.join()
