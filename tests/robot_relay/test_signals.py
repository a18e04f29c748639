"""Two stop signals that arrive together: the second ends the process, however they nest."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap

import pytest

# The second signal lands while the first's handler is still running (here: while it logs), as
# SIGINT and SIGTERM sent to a stopped relay did when SIGCONT let both in at once. Python then
# runs the second handler inside the first (CI, 2026-11-29: both said "stopping", exit 0).
NESTED = textwrap.dedent("""
    import logging, os, signal, time
    from robot_relay.signals import StopSignals

    class SecondSignalWhileLogging(logging.Handler):
        def emit(self, record):
            print(record.getMessage(), flush=True)
            if record.getMessage().startswith("{first}"):
                os.kill(os.getpid(), signal.{second})
                time.sleep(0.01)  # bytecodes for the pending handler to run between

    log = logging.getLogger("t")
    log.addHandler(SecondSignalWhileLogging())
    log.setLevel(logging.INFO)
    signals = StopSignals("prog", log)
    signals.install()
    os.kill(os.getpid(), signal.{first})
    time.sleep(1)
    print("still running, stopped:", signals.stop.is_set(), flush=True)
""")


@pytest.mark.parametrize(("first", "second"), [("SIGINT", "SIGTERM"), ("SIGTERM", "SIGINT")])
def test_a_second_signal_inside_the_first_handler_exits_at_once(first: str, second: str) -> None:
    done = subprocess.run(
        [sys.executable, "-c", NESTED.format(first=first, second=second)],
        check=False, capture_output=True, text=True, timeout=30,
    )
    assert done.returncode == 128 + signal.Signals[second], done
    assert done.stdout == f"{first}: stopping (again to force)\n"
    assert done.stderr == f"prog: {second} again, exiting at once\n"


def test_one_signal_stops_and_is_received() -> None:
    done = subprocess.run(
        [sys.executable, "-c", textwrap.dedent("""
            import logging, os, signal, time
            from robot_relay.signals import StopSignals
            signals = StopSignals("prog", logging.getLogger("t"))
            signals.install(signal.SIGTERM)
            assert not signals.received
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.1)
            print(signals.received, signals.stop.is_set(), flush=True)
        """)],
        check=False, capture_output=True, text=True, timeout=30,
    )
    assert (done.returncode, done.stdout) == (0, "True True\n"), done
