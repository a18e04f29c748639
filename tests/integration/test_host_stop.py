"""Stopping ``swanky-host``: SIGINT/SIGTERM end it within seconds with exit 0 and no traceback
(live, --demo, --bag, with a viewer that is there or gone), a second signal exits at once, and
a ``--save`` file holds every message the summary says was converted."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import pytest

from host_bridge.sink import DISCONNECT_TIMEOUT_S
from tests.integration.procs import command, free_port, headless_viewer
from tests.integration.robot_bags import Entry, Lines, joint_state, write_bag
from tests.rrd import entity_rows

pytestmark = pytest.mark.integration

STOP_WITHIN_S = 10.0
""""Within a few seconds", with slack for a loaded 2-core machine."""
STARTUP_S = 120.0
TOPICS_CHECKED = ("/odom", "/scan")


@contextmanager
def started(cmd: Sequence[str], new_session: bool = False) -> Iterator[tuple[subprocess.Popen[str], Lines]]:
    """``cmd`` with its stderr collected; killed if the test leaves it running."""
    proc = subprocess.Popen(
        list(cmd), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"}, start_new_session=new_session,
    )
    try:
        yield proc, Lines(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=30)


def wait_for_file(path: Path, lines: Lines) -> None:
    """Until the host has opened its sinks (its signal handlers are in place long before)."""
    deadline = time.monotonic() + STARTUP_S
    while not path.exists():
        assert time.monotonic() < deadline, lines.text
        time.sleep(0.1)


def stop_and_wait(proc: subprocess.Popen[str], signum: int) -> float:
    """Send ``signum``; the seconds until the process ended."""
    sent = time.monotonic()
    proc.send_signal(signum)
    proc.wait(timeout=60)
    return time.monotonic() - sent


def converted(summary: str, robot: str, topic: str) -> int:
    """The ``converted`` column of the host's summary table for ``robot`` ``topic``."""
    for line in summary.splitlines():
        fields = line.split()
        if fields[:2] == [robot, topic]:
            return int(fields[4])
    raise AssertionError(f"{robot} {topic} not in the summary:\n{summary}")


def assert_saved_everything(rrd: Path, stderr: str) -> None:
    rows = entity_rows(rrd)
    for topic in TOPICS_CHECKED:
        count = converted(stderr, "sim", topic)
        assert count > 0, stderr
        assert len(rows[f"/sim{topic}"]) == count, topic


def test_sigterm_with_a_viewer_ends_the_demo_cleanly(tmp_path: Path) -> None:
    rrd = tmp_path / "demo.rrd"
    with headless_viewer() as (url, _, _), started(command(
        "host_bridge.cli", "--demo", "--rerun-addr", url, "--save", str(rrd)
    )) as (host, lines):
        lines.wait_for("robot sim joined", timeout=STARTUP_S)
        time.sleep(2)  # some data through the viewer and into the file
        took = stop_and_wait(host, signal.SIGTERM)
    assert (host.returncode, "Traceback" in lines.text) == (0, False), lines.text
    assert took < STOP_WITHIN_S
    assert "swanky.host: INFO: SIGTERM: stopping (again to force)" in lines.text
    assert_saved_everything(rrd, lines.text)


def test_viewer_gone_mid_run_is_named_and_the_file_completed(tmp_path: Path) -> None:
    rrd = tmp_path / "demo.rrd"
    with headless_viewer() as (url, _, viewer), started(command(
        "host_bridge.cli", "--demo", "--rerun-addr", url, "--save", str(rrd)
    )) as (host, lines):
        lines.wait_for("robot sim joined", timeout=STARTUP_S)
        time.sleep(1)
        viewer.kill()
        viewer.wait(timeout=10)
        time.sleep(2)  # data the viewer can no longer get
        took = stop_and_wait(host, signal.SIGINT)
    port = url.split(":")[-1].split("/")[0]
    assert host.returncode == 1, lines.text
    assert took < STOP_WITHIN_S
    assert lines.lines[-1].strip() == (
        f"swanky-host: error: lost the Rerun viewer at {url} (127.0.0.1:{port}: Connection "
        "refused): what it had not received yet is not shown"
    )
    assert "Traceback" not in lines.text
    assert_saved_everything(rrd, lines.text)


@pytest.mark.filterwarnings("ignore:RRD file has no footer")
def test_frozen_viewer_is_left_behind_within_seconds(tmp_path: Path) -> None:
    """A viewer that stops answering (its machine froze, its network went silent) would hold
    Rerun's disconnect for ever."""
    rrd = tmp_path / "demo.rrd"
    with headless_viewer() as (url, _, viewer), started(command(
        "host_bridge.cli", "--demo", "--rerun-addr", url, "--save", str(rrd)
    )) as (host, lines):
        lines.wait_for("robot sim joined", timeout=STARTUP_S)
        time.sleep(1)
        viewer.send_signal(signal.SIGSTOP)
        time.sleep(1)
        took = stop_and_wait(host, signal.SIGTERM)
    assert host.returncode == 1, lines.text
    assert took < DISCONNECT_TIMEOUT_S + STOP_WITHIN_S
    assert lines.lines[-1].strip() == (
        f"swanky-host: error: gave up closing {url} after {DISCONNECT_TIMEOUT_S:.0f} s: it "
        f"stopped answering; {rrd} lacks its index footer (`rerun rrd optimize` adds one)"
    )
    assert "Traceback" not in lines.text
    assert_saved_everything(rrd, lines.text)  # every message, readable without the footer


def test_second_signal_exits_at_once(tmp_path: Path) -> None:
    """While the host waits for a frozen viewer (above), a second signal ends it."""
    with headless_viewer() as (url, _, viewer), started(command(
        "host_bridge.cli", "--demo", "--rerun-addr", url, "--save", str(tmp_path / "demo.rrd")
    )) as (host, lines):
        lines.wait_for("robot sim joined", timeout=STARTUP_S)
        viewer.send_signal(signal.SIGSTOP)
        host.send_signal(signal.SIGTERM)
        lines.wait_for("SIGTERM: stopping (again to force)", timeout=30)
        time.sleep(0.5)
        took = stop_and_wait(host, signal.SIGINT)
    assert host.returncode == 128 + signal.SIGINT, lines.text
    assert took < 2.0
    assert "swanky-host: SIGINT again, exiting at once" in lines.text


def test_ctrl_c_during_demo_start_up_stops_every_process(tmp_path: Path) -> None:
    """Ctrl-C reaches the whole process group, bag-writing workers included."""
    with started(command(
        "host_bridge.cli", "--demo", "--robots", "3", "--save", str(tmp_path / "demo.rrd")
    ), new_session=True) as (host, lines):
        lines.wait_for("demo: simulating sim, sim2, sim3", timeout=STARTUP_S)
        time.sleep(1)  # the workers are writing bags
        sent = time.monotonic()
        os.killpg(host.pid, signal.SIGINT)
        host.wait(timeout=60)
        took = time.monotonic() - sent
    assert (host.returncode, took < STOP_WITHIN_S) == (0, True), lines.text
    assert "KeyboardInterrupt" not in lines.text
    assert "Traceback" not in lines.text


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_live_host_without_robots_stops_on_a_signal(tmp_path: Path, signum: int) -> None:
    rrd = tmp_path / "live.rrd"
    with started(command(
        "host_bridge.cli", "-l", f"tcp/127.0.0.1:{free_port()}", "--no-multicast-scouting",
        "--save", str(rrd),
    )) as (host, lines):
        wait_for_file(rrd, lines)
        time.sleep(1)
        took = stop_and_wait(host, signum)
    assert (host.returncode, "Traceback" in lines.text) == (0, False), lines.text
    assert took < STOP_WITHIN_S
    assert set(entity_rows(rrd)) == {"/__properties"}  # complete and readable, no data


def test_bag_being_converted_stops_on_sigterm(tmp_path: Path) -> None:
    """A long bag: the conversion stops part way (after the run of 65,536 messages it is
    converting), what was converted is saved. The host's output is slowed to 30 us a message
    (tests/integration/slow_host.py): unslowed, it converts the whole bag in less time than the
    test waits before its signal."""
    seconds = 1500
    bag = write_bag(tmp_path / "long_bag", [
        Entry("/joint_states", "sensor_msgs/msg/JointState", i * 10**7, joint_state(i * 10**7, [i, -i]))
        for i in range(seconds * 100)
    ])
    rrd = tmp_path / "bag.rrd"
    with started(command("tests.integration.slow_host", "0.00003", "*", "0",
                         "--bag", str(bag), "--save", str(rrd))) as (host, lines):
        wait_for_file(rrd, lines)
        time.sleep(0.5)
        took = stop_and_wait(host, signal.SIGTERM)
    assert (host.returncode, "Traceback" in lines.text) == (0, False), lines.text
    assert took < STOP_WITHIN_S
    count = converted(lines.text, "robot", "/joint_states")
    assert 0 < count < seconds * 100
