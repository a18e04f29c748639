"""Two robots on one timeline though one's clock is 7.5 s ahead (a Raspberry Pi without a
real-time clock or NTP): two real relays over loopback Zenoh, one given a clock shifted at its
source, into a real host saving to .rrd. The host measures the shifted relay's clock within a
few milliseconds, puts its receive times and latency on the PC's clock, and leaves its header
stamps as the robot wrote them."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest

from host_bridge.inputs.clocks import BURST
from robot_relay.relay import Relay
from robot_relay.session import close_session
from robot_relay.wire import Catalog, RawMessage, TopicInfo
from tests.integration.procs import command, free_port, open_loopback, running, wait_listening
from tests.integration.robot_bags import STORE, Lines, header
from tests.integration.test_bad_links import NO_SHM
from tests.rrd import entity_rows

pytestmark = pytest.mark.integration

SHIFT_NS = 7_500_000_000
MS = 1_000_000
POINT = "geometry_msgs/msg/PointStamped"
TARGET = TopicInfo("/target", POINT, None)
MESSAGES = 120
PERIOD_S = 0.05
STARTUP_S = 60.0
DONE_S = 120.0
"""The host ends (idle once the relays close) within this on a loaded 2-core machine."""


def point_cdr(index: int, stamp_ns: int) -> bytes:
    msg = STORE.types[POINT](
        header=header(stamp_ns, "map"),
        point=STORE.types["geometry_msgs/msg/Point"](x=float(index), y=0.0, z=0.0),
    )
    return bytes(STORE.serialize_cdr(msg, POINT))


def shifted_clock() -> int:
    return time.time_ns() + SHIFT_NS


def publish(relays: dict[str, Relay]) -> dict[str, list[int]]:
    """MESSAGES points, the ``index``-th from every robot at once, each stamped (header) by its
    robot's own clock; the stamps each robot wrote."""
    stamps: dict[str, list[int]] = {name: [] for name in relays}
    for index in range(MESSAGES):
        for name, relay in relays.items():
            stamp = relay.clock()
            stamps[name].append(stamp)
            relay.publish(RawMessage(name, TARGET.topic, POINT, point_cdr(index, stamp)))
        time.sleep(PERIOD_S)
    return stamps


def scalars(rows: dict[str, list[dict[str, Any]]], path: str) -> list[float]:
    return [row["Scalars:scalars"][0] for row in rows[path]]


def by_index(rows: list[dict[str, Any]], column: str) -> dict[int, int]:
    """``column`` (a timeline) of each point row, by the index its x carries."""
    return {round(row["Points3D:positions"][0][0]): row[column] for row in rows}


def test_a_relay_clock_shifted_by_seconds_lands_on_the_pcs_timeline(tmp_path: Path) -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    out = tmp_path / "clocks.rrd"
    host_command = command("host_bridge.cli", "-l", endpoint, *NO_SHM, "--no-rmw-zenoh",
                           "--save", str(out), "--until-idle", "5", "--duration", str(DONE_S))
    clocks: dict[str, Callable[[], int]] = {"steady": time.time_ns, "shifted": shifted_clock}
    with running(host_command) as host:
        lines = Lines(host)
        wait_listening(port, STARTUP_S, "the host")
        with ExitStack() as closing:
            relays = {}
            for name, clock in clocks.items():
                session = open_loopback("-e", endpoint, *NO_SHM)
                closing.callback(close_session, session)
                relays[name] = Relay(session, Catalog(name, "ros2", (TARGET,)), clock=clock)
                closing.callback(relays[name].close)
            for relay in relays.values():
                assert relay.wait_for_host(STARTUP_S)
            stamps = publish(relays)
            time.sleep(2.5)  # a relay stats report and a periodic clock query more
        assert host.wait(timeout=DONE_S) == 0, lines.all_text()
    rows = entity_rows(out)

    # The shifted relay's clock, measured: the truth within every estimate's bound, and within
    # 5 ms once the first burst is over (its first samples, one by one, may be further off;
    # the robot's data waited for the burst's end).
    offsets = {name: scalars(rows, f"/_stats/{name}/clock/offset_ms") for name in relays}
    uncertainties = {name: scalars(rows, f"/_stats/{name}/clock/uncertainty_ms") for name in relays}
    for name, truth_ms in (("steady", 0.0), ("shifted", SHIFT_NS / MS)):
        assert len(offsets[name]) > BURST, name  # the burst, then every 2 s
        assert all(abs(ms - truth_ms) <= bound for ms, bound in
                   zip(offsets[name], uncertainties[name], strict=True)), name
        settled = offsets[name][BURST - 1:]
        assert all(abs(ms - truth_ms) < 5.0 for ms in settled), (name, settled)

    # Both robots' points, published together, together on receive_time; their header stamps
    # (ros_time) as each robot wrote them, 7.5 s apart.
    points = {name: rows[f"/{name}/target"] for name in relays}
    assert all(len(points[name]) == MESSAGES for name in relays)
    received = {name: by_index(points[name], "receive_time") for name in relays}
    for name in relays:
        assert by_index(points[name], "ros_time") == dict(enumerate(stamps[name])), name
    # Each robot's relay stamped a point just after the robot did (the next line of code): on
    # the PC's clock, its receive time is its stamp less the robot's true offset, plus that.
    truths = {"steady": 0, "shifted": SHIFT_NS}
    lags = {name: [received[name][i] - (stamps[name][i] - truths[name]) for i in range(MESSAGES)]
            for name in relays}
    assert all(min(lag) > -MS for lag in lags.values()), lags  # the estimate's error
    assert all(statistics.median(lag) < MS for lag in lags.values()), lags
    # Between the robots: what the test's thread took between the two publishes (a loaded
    # machine may preempt it there), not 7.5 s.
    gaps = [abs(received["shifted"][i] - received["steady"][i]) for i in range(MESSAGES)]
    assert statistics.median(gaps) < 2 * MS, gaps
    assert max(gaps) < 100 * MS, gaps

    # Latency on the PC's clock: as the unshifted robot's, not 7.5 s less. Both robots' periods
    # end at the same seconds of the PC's clock; the first ones hold the host's start.
    latency = {name: {row["receive_time"]: row["Scalars:scalars"][0]
                      for row in rows[f"/_stats/{name}/target/latency_ms"]} for name in relays}
    assert latency["shifted"].keys() == latency["steady"].keys()
    assert len(latency["steady"]) >= 5
    assert all(0 <= ms < 2000 for name in relays for ms in latency[name].values()), latency
    differences = [abs(latency["shifted"][end] - ms) for end, ms in latency["steady"].items()]
    assert statistics.median(differences) < 3.0, latency

    # The relay's own reports on the PC's clock too, among the points, not 7.5 s after them.
    first, last = min(received["steady"].values()), max(received["steady"].values())
    report_times = [row["receive_time"] for row in rows["/_stats/shifted/relay/cpu_percent"]]
    assert report_times
    assert all(first - 2_000 * MS <= at <= last + 3_000 * MS for at in report_times)

    # Said once, for the shifted robot only, with what is corrected.
    warnings = [row["TextLog:text"][0] for row in rows["/_swanky/warnings"]]
    (clock_warning,) = [text for text in warnings if "clock" in text]
    assert clock_warning.startswith("[shifted] swanky/shifted/clock: robot shifted's clock is "
                                    "7.500 s ahead of this PC's (±")
    assert "receive_time and latency_ms are corrected" in clock_warning
