"""SIGINT and SIGTERM for both programs: the first stops cleanly, a second exits at once."""

from __future__ import annotations

import faulthandler
import itertools
import logging
import os
import signal
import sys
import threading


class StopSignals:
    """Sets ``stop`` on the first SIGINT or SIGTERM; a second one ends the process at once
    (``128 + signum``): the user does not want to wait for files and viewers.

    ``deadline_s``: a process still stopping this long after the first signal prints every
    thread's stack and exits (a library call that never returns must not keep it alive)."""

    def __init__(
        self, program: str, log: logging.Logger, stop: threading.Event | None = None,
        deadline_s: float | None = None,
    ) -> None:
        self.program = program
        self.log = log
        self.stop = stop or threading.Event()
        self.deadline_s = deadline_s
        self.received = False
        self._signals = itertools.count()

    def install(self, *signums: signal.Signals) -> None:
        for signum in signums or (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, self.on_signal)

    def on_signal(self, signum: int, frame: object) -> None:
        # Python runs a handler between any two bytecodes of the main thread, another handler's
        # too: two signals that arrive together (SIGINT and SIGTERM sent to a stopped process)
        # nest. ``next`` on a count is one C call, so exactly one of them is the first.
        first = next(self._signals) == 0
        name = signal.Signals(signum).name
        if not first:
            print(f"{self.program}: {name} again, exiting at once", file=sys.stderr, flush=True)
            os._exit(128 + signum)
        self.received = True
        self.stop.set()
        if self.deadline_s is not None:
            faulthandler.dump_traceback_later(self.deadline_s, exit=True)
        self.log.info("%s: stopping (again to force)", name)

    def cancel_deadline(self) -> None:
        """Stopped in time (a test calling ``main`` again must not be ended by the last one)."""
        if self.deadline_s is not None:
            faulthandler.cancel_dump_traceback_later()
