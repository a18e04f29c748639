"""``swanky-host --demo``: the simulated robot through the real relay -> Zenoh -> host path.

The simulator writes a real rosbag2 file; an in-process relay replays it (looping, real time)
over a loopback Zenoh link to this host, exactly as ``swanky-relay --bag`` would.
"""

from __future__ import annotations

import argparse
import logging
import socket
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path

from host_bridge.sim import write_demo_bag
from robot_relay.relay import Relay
from robot_relay.session import open_session
from robot_relay.sources.bag import BagSource

log = logging.getLogger("swanky.demo")

DEMO_ROBOT = "sim"
DEMO_BAG_SECONDS = 60.0


def free_loopback_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _relay_args(endpoint: str) -> argparse.Namespace:
    return argparse.Namespace(
        mode=None, connect=[endpoint], listen=[], config=None, cfg=[],
        no_multicast_scouting=True,
    )


def _replay(bag: Path, endpoint: str, stop: threading.Event, host_stop: threading.Event) -> None:
    try:
        session = open_session(_relay_args(endpoint))
        try:
            with BagSource(bag, DEMO_ROBOT, rate=1.0, loop=True) as source:
                relay = Relay(session, source.catalog())
                if relay.wait_for_host(timeout=30.0):
                    relay.publish_all(source.messages(), stop)
                relay.close()
        finally:
            session.close()
    except Exception:
        log.exception("demo relay failed; stopping the demo")
        host_stop.set()


def run_demo(args: argparse.Namespace, run_host: Callable[[], None], stop: threading.Event) -> None:
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    args.listen = [*args.listen, endpoint]
    args.no_multicast_scouting = True
    relay_stop = threading.Event()
    with tempfile.TemporaryDirectory(prefix="swanky-demo-") as tmp:
        bag = write_demo_bag(Path(tmp) / "demo", DEMO_BAG_SECONDS)
        log.info("demo: simulated robot %r, bag %s, loopback %s", DEMO_ROBOT, bag, endpoint)
        relay = threading.Thread(
            target=_replay, args=(bag, endpoint, relay_stop, stop), name="demo-relay", daemon=True
        )
        relay.start()
        try:
            run_host()
        finally:
            relay_stop.set()
            stop.set()
            relay.join(timeout=5.0)
