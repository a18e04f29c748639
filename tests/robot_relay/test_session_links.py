"""Priority links on loopback (robot_relay/session.py, ``--priority-links``): a session connecting
to ``tcp/`` opens
a bulk link for ``data_low`` and a link for everything else, and still talks to a peer that
accepts one link (an older Swanky, a router with zenoh's default configuration) both ways."""

from __future__ import annotations

import re
import shutil
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import pytest
import zenoh

from robot_relay.session import ZenohOptions, open_session
from tests.integration.procs import free_port

pytestmark = pytest.mark.integration

NO_SHM = ("transport/shared_memory/enabled:false",)
"""Payloads over 3 KB between two sessions of one machine would bypass TCP through /dev/shm."""
BULK = bytes(range(256)) * 400  # 100 KB, an image's order of size
BULK_COUNT = 20
SMALL_COUNT = 20
TIMEOUT_S = 30.0


def plain_session(*, listen: str | None = None, connect: str | None = None) -> zenoh.Session:
    """A session with zenoh's defaults (one link per transport), as an older Swanky or
    a plain router opens it."""
    config = zenoh.Config()
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("transport/shared_memory/enabled", "false")
    if listen:
        config.insert_json5("listen/endpoints", f'["{listen}"]')
    if connect:
        config.insert_json5("connect/endpoints", f'["{connect}"]')
    return zenoh.open(config)


def swanky_session(*, listen: str | None = None, connect: str | None = None) -> zenoh.Session:
    return open_session(ZenohOptions(
        listen=(listen,) if listen else (), connect=(connect,) if connect else (),
        multicast_scouting=False, cfg=NO_SHM, priority_links=True,
    ))


@contextmanager
def pair(listener: Callable[..., zenoh.Session], connector: Callable[..., zenoh.Session],
         ) -> Iterator[tuple[int, zenoh.Session, zenoh.Session]]:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    listening = listener(listen=endpoint)
    connecting = connector(connect=endpoint)
    try:
        yield port, listening, connecting
    finally:
        connecting.close()
        listening.close()


def poll(condition: Callable[[], object], what: str) -> None:
    deadline = time.monotonic() + TIMEOUT_S
    while not condition():
        assert time.monotonic() < deadline, f"not within {TIMEOUT_S:.0f} s: {what}"
        time.sleep(0.05)


def matching(publisher: zenoh.Publisher) -> bool:
    status = publisher.matching_status
    # zenoh-python returns a MatchingStatus object (its stub says bool), as robot_relay.relay reads.
    return bool(getattr(status, "matching", status))


def send_both_priorities(sender: zenoh.Session, receiver: zenoh.Session, key: str) -> None:
    """``BULK_COUNT`` data_low payloads and ``SMALL_COUNT`` data_high ones, all received, each
    exactly as sent and in order within its priority."""
    received: dict[str, list[bytes]] = {"bulk": [], "small": []}
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        with lock:
            received[str(sample.key_expr).rsplit("/", 1)[1]].append(sample.payload.to_bytes())

    subscriber = receiver.declare_subscriber(f"{key}/*", on_sample)
    bulk = sender.declare_publisher(f"{key}/bulk", priority=zenoh.Priority.DATA_LOW,
                                    congestion_control=zenoh.CongestionControl.BLOCK)
    small = sender.declare_publisher(f"{key}/small", priority=zenoh.Priority.DATA_HIGH,
                                     congestion_control=zenoh.CongestionControl.BLOCK)
    poll(lambda: matching(bulk) and matching(small), f"{key}: the subscriber seen by the publishers")
    for index in range(max(BULK_COUNT, SMALL_COUNT)):
        if index < BULK_COUNT:
            bulk.put(BULK)
        if index < SMALL_COUNT:
            small.put(index.to_bytes(4, "little"))
    poll(lambda: len(received["bulk"]) == BULK_COUNT and len(received["small"]) == SMALL_COUNT,
         f"{key}: every sample received ({ {k: len(v) for k, v in received.items()} })")
    assert received["bulk"] == [BULK] * BULK_COUNT
    assert received["small"] == [i.to_bytes(4, "little") for i in range(SMALL_COUNT)]
    subscriber.undeclare()
    bulk.undeclare()
    small.undeclare()


def bytes_received_per_connection(port: int) -> list[int]:
    """What each TCP connection accepted on ``port`` received (``ss``, the kernel's counts)."""
    out = subprocess.run(["ss", "-tniH", "state", "established", f"( sport = :{port} )"],
                         capture_output=True, text=True, check=True, timeout=10).stdout
    sockets = [line for line in out.splitlines() if line and not line[0].isspace()]
    infos = [line for line in out.splitlines() if line[:1].isspace()]
    assert len(infos) == len(sockets), out
    return [int(m.group(1)) if (m := re.search(r"bytes_received:(\d+)", info)) else 0
            for info in infos]


def test_bulk_priorities_get_their_own_connection() -> None:
    if shutil.which("ss") is None:
        pytest.skip("iproute2's ss is not installed: the connections cannot be counted")
    with pair(swanky_session, swanky_session) as (port, host, relay):
        poll(lambda: len(bytes_received_per_connection(port)) == 2, "two links accepted")
        send_both_priorities(relay, host, "up")
        counts = sorted(bytes_received_per_connection(port))
        assert len(counts) == 2
        # The bulk link carried the 2 MB of data_low; the other the rest (declarations,
        # keep-alives, 20 small samples: a few KB).
        assert counts[1] >= BULK_COUNT * len(BULK), counts
        assert counts[0] < 100_000, counts
        send_both_priorities(host, relay, "down")


@pytest.mark.parametrize(("listener", "connector"), [
    (plain_session, swanky_session),  # a relay with priority links -> an older host or router
    (swanky_session, plain_session),  # an older relay -> a host accepting priority links
], ids=["split-to-plain", "plain-to-split"])
def test_priority_links_talk_to_a_one_link_peer_both_ways(
    listener: Callable[..., zenoh.Session], connector: Callable[..., zenoh.Session]
) -> None:
    with pair(listener, connector) as (_, listening, connecting):
        send_both_priorities(connecting, listening, "up")
        send_both_priorities(listening, connecting, "down")
