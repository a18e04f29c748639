"""``swanky-host --list``: the robots and topics on the network, with rates, like
``ros2 topic list -v`` plus ``ros2 topic hz`` / ``bw``. Nothing is decoded or logged to Rerun.

It subscribes to every data key for a few seconds (which also wakes relays that publish only
while a host listens), asks each robot seen for its catalog, and prints one row per topic.
Bandwidth counts payload bytes as they travel (compressed if the relay compresses).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import zenoh

from host_bridge.inputs.live import open_host_session
from host_bridge.inputs.zenoh import fetch_catalog
from robot_relay.errors import WireError
from robot_relay.session import ZenohOptions
from robot_relay.wire import (
    Catalog,
    alive_selector,
    catalog_key,
    data_selector,
    parse_cdr_encoding,
    parse_data_key,
    parse_robot_key,
)

CATALOG_TIMEOUT_S = 3.0
DEFAULT_DURATION_S = 3.0


@dataclass(slots=True)
class TopicTraffic:
    msgtype: str = ""
    count: int = 0
    bytes: int = 0
    first_ns: int | None = None
    last_ns: int | None = None

    def add(self, size: int, at_ns: int) -> None:
        self.count += 1
        self.bytes += size
        if self.first_ns is None:
            self.first_ns = at_ns
        self.last_ns = at_ns

    @property
    def rate_hz(self) -> float | None:
        """Mean rate over the intervals seen (as ``ros2 topic hz``); None below two messages."""
        if self.count < 2 or self.first_ns is None or self.last_ns is None:
            return None
        span = self.last_ns - self.first_ns
        return (self.count - 1) * 1e9 / span if span > 0 else None

    @property
    def bytes_per_s(self) -> float | None:
        """Mean message size times the rate (as ``ros2 topic bw``)."""
        rate = self.rate_hz
        return None if rate is None else self.bytes / self.count * rate


@dataclass(slots=True)
class Listing:
    duration_s: float
    alive: set[str] = field(default_factory=set)
    catalogs: dict[str, Catalog] = field(default_factory=dict)
    traffic: dict[tuple[str, str], TopicTraffic] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)


def collect(
    session: zenoh.Session,
    robots: str = "*",
    duration_s: float = DEFAULT_DURATION_S,
    stop: threading.Event | None = None,
    clock: Callable[[], int] = time.monotonic_ns,
) -> Listing:
    listing = Listing(duration_s)
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            robot, topic = parse_data_key(key)
            msgtype = parse_cdr_encoding(str(sample.encoding), key)
        except WireError:
            return
        with lock:
            traffic = listing.traffic.setdefault((robot, topic), TopicTraffic())
            traffic.msgtype = msgtype
            traffic.add(len(sample.payload), clock())

    def on_alive(sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            with lock:
                listing.alive.add(parse_robot_key(str(sample.key_expr)))

    liveliness = session.liveliness().declare_subscriber(alive_selector(robots), on_alive, history=True)
    subscriber = session.declare_subscriber(data_selector(robots), on_sample)
    try:
        (stop or threading.Event()).wait(duration_s)
    finally:
        subscriber.undeclare()
        liveliness.undeclare()
    with lock:
        seen = listing.alive | {robot for robot, _ in listing.traffic}
    for robot in sorted(seen):
        try:
            catalog = fetch_catalog(session, robot, CATALOG_TIMEOUT_S)
        except WireError as err:
            listing.problems.append(str(err))
            continue
        if catalog is None:
            listing.problems.append(f"robot {robot} did not answer its catalog ({catalog_key(robot)})")
        else:
            listing.catalogs[robot] = catalog
    return listing


def human_bandwidth(bytes_per_s: float) -> str:
    for unit, scale in (("MB/s", 1e6), ("KB/s", 1e3)):
        if bytes_per_s >= scale:
            return f"{bytes_per_s / scale:.1f} {unit}"
    return f"{bytes_per_s:.0f} B/s"


def format_listing(listing: Listing) -> str:
    """One row per (robot, topic): catalog topics first, then topics seen without a catalog."""
    header = ("robot", "topic", "type", "qos", "msgs", "rate", "bandwidth")
    rows: list[tuple[str, ...]] = [header]
    robots = sorted(listing.alive | set(listing.catalogs) | {r for r, _ in listing.traffic})
    for robot in robots:
        catalog = listing.catalogs.get(robot)
        topics = {t.topic: t for t in catalog.topics} if catalog else {}
        names = sorted(set(topics) | {t for r, t in listing.traffic if r == robot})
        if not names:
            rows.append((robot, "(no topics)", "", "", "", "", ""))
        for name in names:
            info = topics.get(name)
            traffic = listing.traffic.get((robot, name), TopicTraffic())
            qos = "-" if info is None else (
                f"{info.qos.reliability}{', latched' if info.latched else ''}"
            )
            rate, bandwidth = traffic.rate_hz, traffic.bytes_per_s
            rows.append((
                robot,
                name,
                info.msgtype if info is not None else traffic.msgtype,
                qos,
                str(traffic.count),
                "-" if rate is None else f"{rate:.1f} Hz",
                "-" if bandwidth is None else human_bandwidth(bandwidth),
            ))
    widths = [max(len(r[i]) for r in rows) for i in range(len(header))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip() for row in rows]
    if len(robots) == 0:
        lines.append(f"no robots seen in {listing.duration_s:g} s (check -e/-l endpoints)")
    return "\n".join(lines + listing.problems)


def run_list(
    zenoh_options: ZenohOptions, robots: str, duration: float | None, stop: threading.Event
) -> int:
    """``--list``: connect like live mode, watch ``duration`` seconds (default 3), print the table."""
    session = open_host_session(zenoh_options)
    try:
        listing = collect(session, robots, DEFAULT_DURATION_S if duration is None else duration, stop)
    finally:
        session.close()
    print(format_listing(listing), flush=True)
    return 0
