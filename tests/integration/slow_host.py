"""``swanky-host`` whose output is slowed down, as if its converters or its viewer could not keep
up: ``python -m tests.integration.slow_host SECONDS ROBOT QUEUE HOST-FLAGS...``.

Each message of robot ROBOT (``*``: every robot) is held SECONDS on its way to the dispatcher;
QUEUE, unless 0, replaces the per-robot queue length (5,000), so a test need not wait for a full
default queue to drain at exit. Everything else is the real host.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence


def main(argv: Sequence[str]) -> int:
    seconds_text, robot, queue_text, *host_argv = argv
    seconds, queue = float(seconds_text), int(queue_text)
    from host_bridge.cli import main as host_main
    from host_bridge.inputs.queues import RobotQueues
    from host_bridge.pipeline.dispatch import Dispatcher

    dispatch = Dispatcher.dispatch
    make_queues = RobotQueues.__init__

    def slow_dispatch(self: Dispatcher, batch: Sequence[object]) -> None:
        held = sum(robot in ("*", getattr(raw, "robot", "")) for raw in batch)
        time.sleep(seconds * held)
        dispatch(self, batch)  # type: ignore[arg-type]

    def queues_of_length(self: RobotQueues, max_per_robot: int = queue, **kwargs: object) -> None:
        make_queues(self, queue, **kwargs)  # type: ignore[arg-type]

    Dispatcher.dispatch = slow_dispatch  # type: ignore[method-assign]
    if queue:
        RobotQueues.__init__ = queues_of_length  # type: ignore[method-assign]
    return host_main(list(host_argv))


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
