"""Relay forwarding against a bare Zenoh publisher of the same pre-serialised payloads (issue 13,
target 3), two processes on loopback.

The payloads are CDR ``std_msgs/msg/UInt8MultiArray`` messages of 1 MB and of 3 KB (8 distinct
ones per size, made once with rosbags). The subscriber is this process: one Zenoh session on
loopback, a callback that only counts (the host's place). The publisher is another process, one
of, in turn:

- baseline: a bare zenoh-python publisher (``declare_publisher`` then ``put`` in a loop, as
  zenoh's ``z_pub_thr`` example) putting the payloads as fast as it can, congestion control
  ``block`` so nothing is lost;
- ``relay``: the relay itself (``robot_relay.app.relay_source``: Relay, policy, attachment, file
  server) fed by a source that hands it the same payloads as fast as it takes them once a host
  listens: what ``swanky-relay`` adds to forwarding, without a ROS or bag reader in front;
- with ``--bag-replay``, also ``swanky-relay --bag``: the command replaying a rosbag2 of the
  same payloads with ``--rate 0 --loop`` (rosbags' MCAP reader included), for reference.

Every publisher uses the same payload objects, key, encoding (``application/cdr`` with the type
as schema), priority ``data`` and congestion ``block`` (the relay's built-in policy for a
reliable topic of this type). Each round runs every publisher once, the order reversed every
other round: on this shared machine the load drifts within a round, so a fixed order would
favour one contender. After a warm-up, messages received by the subscriber and the publisher's
CPU time (user + system, from /proc) are taken over the same window. Printed per size:
messages/s received and CPU microseconds per message of each, the ratio relay / bare
messages/s, median of the rounds. Targets: ratio >= 0.9 at 1 MB; relay CPU
<= 20 us per message at 3 KB.

At 1 MB both copy the payload once more than they send: zenoh-python copies ``bytes`` into a
buffer of its own, and zenoh copies that into shared memory for a subscriber on this machine
(about 70 % of either's CPU is memmove). The relay writes payloads of 64 KiB and more straight
into a shared-memory buffer (``robot_relay.session.SharedMemoryPool``), so it copies once; a
subscriber without shared memory (a remote host) costs it what it costs the bare publisher.

    .venv/bin/python benchmarks/relay_throughput.py [--rounds 3] [--seconds 3] [--warmup 1] [--bag-replay]
"""

from __future__ import annotations

import argparse
import itertools
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # run as a script: the project's packages and benchmarks.*
    sys.path.insert(0, str(ROOT))

import zenoh  # noqa: E402
from relay_cpu import cpu_seconds  # noqa: E402  (beside this script)

from robot_relay.app import RelayOptions, relay_source  # noqa: E402
from robot_relay.session import ZenohOptions, open_session  # noqa: E402
from robot_relay.sources.base import Outlet  # noqa: E402
from robot_relay.wire import Catalog, RawMessage, TopicInfo, cdr_encoding, data_key  # noqa: E402
from tests.integration.procs import free_port, listening, open_loopback, stop  # noqa: E402

# python -m benchmarks gives each script this many seconds at most.
BUDGET_SECONDS = 120

ROBOT = "bench"
TOPIC = "/payload"
MSGTYPE = "std_msgs/msg/UInt8MultiArray"
SIZES = {"1 MB": 1_000_000, "3 KB": 3_000}
DISTINCT_PAYLOADS = 8
BAG_BYTES = 48_000_000  # the replayed bag's size, about; --loop replays it again and again
THROUGHPUT_TARGET = 0.9  # relay / bare messages/s at 1 MB
CPU_TARGET_US = 20.0  # relay CPU per message at 3 KB
START_TIMEOUT_S = 30.0


def payloads(size: int, count: int = DISTINCT_PAYLOADS) -> list[bytes]:
    """``count`` CDR UInt8MultiArray messages with ``size`` data bytes each, all different."""
    import numpy as np
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    layout = store.types["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
    rng = np.random.default_rng(size)
    return [
        bytes(store.serialize_cdr(store.types[MSGTYPE](
            layout=layout, data=rng.integers(0, 256, size, dtype=np.uint8)), MSGTYPE))
        for _ in range(count)
    ]


KEY = data_key(ROBOT, TOPIC)


# -- the publisher processes ------------------------------------------------------------------


def loopback_options(endpoint: str) -> ZenohOptions:
    return ZenohOptions(listen=(endpoint,), multicast_scouting=False)


def bare_publisher(endpoint: str, size: int) -> None:
    """The baseline: puts the payloads in a loop until SIGTERM."""
    messages = payloads(size)
    session = open_session(loopback_options(endpoint))
    publisher = session.declare_publisher(
        KEY, encoding=zenoh.Encoding(cdr_encoding(MSGTYPE)),
        congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.DATA,
    )
    for payload in itertools.cycle(messages):
        publisher.put(payload)


class PayloadSource:
    """A relay :class:`~robot_relay.sources.base.Source` handing over the payloads as fast as the
    relay takes them, from the moment a host listens until it is closed."""

    def __init__(self, size: int) -> None:
        self._messages = [RawMessage(ROBOT, TOPIC, MSGTYPE, p) for p in payloads(size)]
        self._wanted = threading.Event()
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None

    def catalog(self) -> Catalog:
        return Catalog(ROBOT, "ros2", (TopicInfo(TOPIC, MSGTYPE, None),))

    def start(self, outlet: Outlet) -> None:
        publish = outlet.publish

        def feed() -> None:
            self._wanted.wait()
            for raw in itertools.cycle(self._messages):
                if self._closing.is_set():
                    return
                publish(raw)

        self._thread = threading.Thread(target=feed, name="payloads", daemon=True)
        self._thread.start()

    def ended(self) -> bool:
        return False

    def on_demand(self, topic: str, wanted: bool) -> None:
        if wanted:
            self._wanted.set()

    def drop_counts(self) -> dict[str, int]:
        return {}

    def close(self) -> None:
        self._closing.set()
        self._wanted.set()
        if self._thread is not None:
            self._thread.join()


def relay_publisher(endpoint: str, size: int) -> None:
    """The relay as ``swanky-relay`` runs it, with :class:`PayloadSource`, until SIGTERM."""
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    relay_source(RelayOptions(ROBOT, zenoh=loopback_options(endpoint)), PayloadSource(size), stop)


# -- this process: the subscriber -------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Window:
    messages: int
    cpu_seconds: float
    seconds: float

    @property
    def rate(self) -> float:
        return self.messages / self.seconds

    @property
    def cpu_us(self) -> float:
        return self.cpu_seconds / self.messages * 1e6 if self.messages else float("nan")


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def measure(command: Sequence[str], port: int, warmup: float, seconds: float) -> Window:
    """Start ``command`` (a publisher listening on ``port``), count what arrives over
    ``seconds`` after the first message and ``warmup``, with the publisher's CPU meanwhile."""
    received = [0]
    first = threading.Event()

    def count(sample: zenoh.Sample) -> None:
        received[0] += 1  # one Zenoh callback thread per subscriber: no lock needed
        first.set()

    proc = subprocess.Popen(list(command), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    started = time.monotonic()
    # Connecting before the publisher listens would wait for Zenoh's reconnection back-off.
    while not listening(port) and proc.poll() is None and time.monotonic() - started < START_TIMEOUT_S:
        time.sleep(0.02)
    session = open_loopback("-e", endpoint(port))
    subscriber = session.declare_subscriber(KEY, count)
    try:
        if not first.wait(START_TIMEOUT_S):
            proc.kill()
            _, err = proc.communicate(timeout=10)
            msg = f"{' '.join(command)}: nothing received within {START_TIMEOUT_S} s\n{err[-2000:]}"
            raise RuntimeError(msg)
        time.sleep(warmup)
        cpu, messages, started = cpu_seconds(proc.pid), received[0], time.monotonic()
        time.sleep(seconds)
        window = Window(received[0] - messages, cpu_seconds(proc.pid) - cpu,
                        time.monotonic() - started)
    finally:
        stop(proc, wait_s=15.0)
        subscriber.undeclare()
        session.close()
    return window


def write_bag(directory: Path, size: int) -> Path:
    """A rosbag2 (MCAP) of the same payloads, about :data:`BAG_BYTES` long."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    messages = payloads(size)
    count = max(len(messages), BAG_BYTES // size)
    with Writer(directory, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection(TOPIC, MSGTYPE, typestore=store)
        for i, payload in zip(range(count), itertools.cycle(messages)):
            writer.write(connection, 1_700_000_000 * 10**9 + i * 1_000_000, payload)
    return directory


Contender = Callable[[str], list[str]]  # endpoint -> the publisher's command


def contenders(size: int, bag: Path | None) -> dict[str, Contender]:
    this = [sys.executable, str(Path(__file__).resolve())]
    relay_command = str(Path(sys.executable).parent / "swanky-relay")
    chosen: dict[str, Contender] = {
        "bare zenoh publisher": lambda listen: [*this, "--bare", listen, str(size)],
        "relay": lambda listen: [*this, "--relay", listen, str(size)],
    }
    if bag is not None:
        chosen["swanky-relay --bag"] = lambda listen: [
            relay_command, "--robot", ROBOT, "--bag", str(bag), "--rate", "0", "--loop",
            "-l", listen, "--no-multicast-scouting"]
    return chosen


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=3, help="every publisher, this many times")
    parser.add_argument("--seconds", type=float, default=3.0, help="measured time per run")
    parser.add_argument("--warmup", type=float, default=1.0,
                        help="time between the first message received and the measurement")
    parser.add_argument("--sizes", nargs="+", choices=list(SIZES), default=list(SIZES),
                        help="payload sizes to time (default: both)")
    parser.add_argument("--bag-replay", action="store_true",
                        help="also time swanky-relay --bag --rate 0 --loop on a bag of the payloads")
    parser.add_argument("--bare", nargs=2, metavar=("ENDPOINT", "SIZE"), help=argparse.SUPPRESS)
    parser.add_argument("--relay", nargs=2, metavar=("ENDPOINT", "SIZE"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.bare is not None:
        bare_publisher(args.bare[0], int(args.bare[1]))
        return 0
    if args.relay is not None:
        relay_publisher(args.relay[0], int(args.relay[1]))
        return 0

    verdicts = []
    with tempfile.TemporaryDirectory(prefix="swanky_relay_bench_") as tmp:
        for label in args.sizes:
            size = SIZES[label]
            bag = write_bag(Path(tmp) / f"payloads-{size}", size) if args.bag_replay else None
            runs: dict[str, list[Window]] = {}
            for round_index in range(args.rounds):
                order = list(contenders(size, bag).items())
                for name, make_command in order[::-1] if round_index % 2 else order:
                    port = free_port()
                    window = measure(make_command(endpoint(port)), port, args.warmup, args.seconds)
                    runs.setdefault(name, []).append(window)
            print(f"{label} payloads ({size:,} data bytes), {args.rounds} rounds of "
                  f"{args.seconds:g} s, medians:")
            for name, windows in runs.items():
                rate = statistics.median(w.rate for w in windows)
                cpu = statistics.median(w.cpu_us for w in windows)
                print(f"  {name:<22} {rate:>9,.0f} msg/s ({rate * size / 1e6:>7,.1f} MB/s), "
                      f"CPU {cpu:>7.1f} us/msg; runs "
                      + ", ".join(f"{w.rate:,.0f}" for w in windows), flush=True)
            ratio = statistics.median(
                r.rate / b.rate
                for r, b in zip(runs["relay"], runs["bare zenoh publisher"], strict=True))
            relay_cpu = statistics.median(w.cpu_us for w in runs["relay"])
            print(f"  ratio relay / bare msg/s, median of {args.rounds}: {ratio:.2f}", flush=True)
            if size == SIZES["1 MB"]:
                verdicts.append(f"relay / bare msg/s at 1 MB {ratio:.2f} (target >= "
                                f"{THROUGHPUT_TARGET}: {'met' if ratio >= THROUGHPUT_TARGET else 'MISSED'})")
            if size == SIZES["3 KB"]:
                verdicts.append(f"relay CPU at 3 KB {relay_cpu:.1f} us/msg (target <= "
                                f"{CPU_TARGET_US:g}: {'met' if relay_cpu <= CPU_TARGET_US else 'MISSED'})")
    print("; ".join(verdicts))
    return 0


if __name__ == "__main__":
    sys.exit(main())
