"""A relay whose stop hangs in a library call still ends, saying where it hung."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time

STUCK_RELAY = textwrap.dedent("""
    import threading, time
    from robot_relay import app, cli

    cli.STOP_DEADLINE_S = 1.0

    def never_returns(options, stop):
        print("relaying", flush=True)
        stop.wait()
        threading.Event().wait()  # a close that never returns (seen once in CI under load)

    app.run = never_returns
    cli.main(["--robot", "r", "--no-multicast-scouting"])
""")


def test_a_relay_still_stopping_after_the_deadline_prints_its_stacks_and_exits() -> None:
    proc = subprocess.Popen([sys.executable, "-c", STUCK_RELAY], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline() == "relaying\n"
        proc.send_signal(signal.SIGTERM)
        sent = time.monotonic()
        _, err = proc.communicate(timeout=20)
        took = time.monotonic() - sent
    finally:
        proc.kill()
    assert proc.returncode == 1
    assert 1.0 <= took < 15
    assert "SIGTERM: stopping (again to force)" in err
    assert "Timeout (0:00:01)!" in err
    assert "in never_returns" in err  # the stuck thread's stack names the call
