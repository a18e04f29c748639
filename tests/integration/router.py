"""A Zenoh router on loopback for multi-process tests (there is no zenohd on PyPI; zenoh-python
opens a session in router mode): ``python -m tests.integration.router PORT [CONFIG]``, CONFIG a
router's configuration file (deploy/zenoh-router.json5, the lab's: benchmarks/fleet.py) whose
endpoints are replaced by loopback's PORT."""

from __future__ import annotations

import json
import signal
import socket
import sys
import threading
import time
from pathlib import Path

import zenoh

from tests.integration.procs import command


def router_command(port: int, config: Path | None = None) -> list[str]:
    return command("tests.integration.router", str(port), *([str(config)] if config else []))


def wait_for_port(port: int, timeout: float = 30.0) -> None:
    """Until something accepts TCP connections on 127.0.0.1:``port``."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=1.0):
                return
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


def main() -> None:
    config = zenoh.Config.from_file(sys.argv[2]) if len(sys.argv) > 2 else zenoh.Config()
    config.insert_json5("mode", '"router"')
    config.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{sys.argv[1]}"]))
    config.insert_json5("scouting/multicast/enabled", "false")
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    with zenoh.open(config):
        stop.wait(600)  # bounded even if nobody stops it


if __name__ == "__main__":
    main()
