"""What an input delivers, taken the way the host takes it: as the ``deliver`` of
``Input.start`` (or ``RobotQueues.serve``), from the input's own threads."""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence

from host_bridge.inputs.base import Input, InputItem

TIMEOUT_S = 20.0  # generous: the machine is shared; every wait ends as soon as its condition holds


class Received:
    def __init__(self) -> None:
        self.items: list[InputItem] = []
        self._changed = threading.Condition()

    def take(self, batch: Sequence[InputItem]) -> None:
        with self._changed:
            self.items.extend(batch)
            self._changed.notify_all()

    def wait_for(
        self, done: Callable[[list[InputItem]], bool], timeout: float = TIMEOUT_S
    ) -> list[InputItem]:
        with self._changed:
            self._changed.wait_for(lambda: done(self.items), timeout)
            return list(self.items)


def collect(source: Input, count: int, timeout: float = 10.0) -> list[InputItem]:
    """Start ``source`` and return once ``count`` items arrived (or ``timeout`` passed)."""
    received = Received()
    source.start(received.take)
    return received.wait_for(lambda items: len(items) >= count, timeout)
