"""Stopping ``swanky-host`` and ``swanky-relay``: one SIGINT or SIGTERM ends either within
seconds, exit 0 and no traceback, in any state (waiting for a host, a robot or a link, replaying,
holding, converting, serving the web viewer, running the demo, with a viewer that is there or
gone); a second signal exits at once, and a ``--save`` file holds every message the summary says
was converted."""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from host_bridge.outputs.sink import DISCONNECT_TIMEOUT_S
from robot_relay.session import close_session
from tests.integration.procs import READER_MAIN, children, command, free_port, headless_viewer, open_loopback
from tests.integration.robot_bags import (
    Entry,
    Lines,
    joint_state,
    laser_scan,
    write_bag,
    write_copies,
)
from tests.reliability import Record
from tests.robot_relay.test_bag_sqlite import sqlite_bag
from tests.rrd import entity_rows, row_count, verify

pytestmark = pytest.mark.integration

STOP_WITHIN_S = 10.0
""""Within a few seconds", with slack for a loaded 2-core machine."""
STARTUP_S = 120.0
TOPICS_CHECKED = ("/odom", "/scan")


@contextmanager
def started(
    cmd: Sequence[str], new_session: bool = False, env: Mapping[str, str] | None = None
) -> Iterator[tuple[subprocess.Popen[str], Lines]]:
    """``cmd`` with its stderr collected (``env`` added to the environment); killed if the test
    leaves it running."""
    proc = subprocess.Popen(
        list(cmd), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}, start_new_session=new_session,
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
        "stopped answering"
    )
    assert "Traceback" not in lines.text
    verify(rrd)  # the file has its own stream, closed before the viewer's
    assert_saved_everything(rrd, lines.text)


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


def test_ctrl_c_while_a_sqlite3_bag_is_read_ahead_is_the_hosts_alone(tmp_path: Path) -> None:
    """The process fetching a sqlite3 bag's rows (host_bridge/inputs/rows_ahead.py) is in a
    session of its own: Ctrl-C stops the host, which ends that process, and nothing else speaks."""
    bag = sqlite_bag(tmp_path / "bag")
    with started(command(
        "host_bridge.cli", "--bag", str(bag), "--save", str(tmp_path / "bag.rrd")
    ), new_session=True) as (host, lines):
        reader = wait_for_reader(host.pid)
        os.killpg(host.pid, signal.SIGINT)
        host.wait(timeout=60)
    assert (host.returncode, "Traceback" in lines.text) == (0, False), lines.text
    assert "KeyboardInterrupt" not in lines.text
    assert "the process reading" not in lines.text
    with pytest.raises(ProcessLookupError):  # ended and waited for by the host
        os.kill(reader, 0)


def wait_for_reader(host: int) -> int:
    """The pid of ``host``'s process reading a sqlite3 file ahead, once it runs."""
    deadline = time.monotonic() + STARTUP_S
    while not (found := children(host, READER_MAIN)) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert found, f"no process of {host} reads the bag ahead"
    return found[0]


ONE_SIGNAL_S = 2.0
"""Issue 22: one SIGINT or SIGTERM ends either program "within a second or two", in any state."""
ROBOT = "r"
REPLAYED = 600
"""JointStates in the relay's bag: 30 s at 20 Hz."""
SCANS = 50_000
"""LaserScans (681 readings) in the bag the host converts: 136 MB, seconds of conversion."""
ROS_ENV = {
    "AMENT_PREFIX_PATH": sys.prefix, "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
    "ROS_DOMAIN_ID": str(1 + os.getpid() % 100), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
    "ROS_LOG_DIR": "{dir}",
}


@dataclass(frozen=True, slots=True)
class Place:
    """Where one run of a state works: the module's bags, its own directory, a free loopback
    endpoint (the relay's or the host's ``-l``, or an ``-e`` with nothing there)."""

    bags: Path
    directory: Path
    endpoint: str


@dataclass
class Run:
    """A program brought to a state for one signal."""

    signum: int
    place: Place
    proc: subprocess.Popen[str]
    lines: Lines
    heard: list[int] = field(default_factory=list)
    """Samples a listener standing in for a host took from the relay."""


@dataclass(frozen=True, slots=True)
class State:
    """A state of ``swanky-relay`` or ``swanky-host`` in which one SIGINT or SIGTERM must end it."""

    what: str
    command: Callable[[Place], list[str]]
    ready: Callable[[Run], bool]
    listener: bool = False
    """A Zenoh subscriber to the relay's data on the endpoint: a host, as far as a relay can tell."""
    check: Callable[[Run, str], tuple[str, str]] | None = None
    """Asserts what the stop left, given the run and its stderr; (what survived, what was lost)
    for docs/RELIABILITY.md."""
    env: Mapping[str, str] = field(default_factory=dict)
    """Added to the environment, ``{dir}`` the run's directory."""


def said(text: str) -> Callable[[Run], bool]:
    return lambda run: text in run.lines.text


def holds_data(name: str) -> Callable[[Run], bool]:
    """The run's ``name`` has converted data in it (Rerun writes a bag's batches as they come)."""
    return lambda run: (run.place.directory / name).exists() and (
        (run.place.directory / name).stat().st_size > 1_000_000)


def relay(bag: str, *flags: str, link: str = "-l") -> Callable[[Place], list[str]]:
    """``swanky-relay`` replaying the module's ``bag`` with ``flags``, listening on the run's
    endpoint (``link="-e"``: connecting to it)."""
    return lambda place: command(
        "robot_relay.cli", "--robot", ROBOT, "--bag", str(place.bags / bag), "--no-multicast-scouting",
        link, place.endpoint, *flags,
    )


def host(*flags: str) -> Callable[[Place], list[str]]:
    """``swanky-host`` with ``flags``; ``{bags}``, ``{dir}`` and ``{endpoint}`` filled in, and
    ``{port}`` a new free port each."""

    def line(place: Place) -> list[str]:
        filled = [flag.format(bags=place.bags, dir=place.directory, endpoint=place.endpoint,
                              port="{port}") for flag in flags]
        return command("host_bridge.cli", "--no-multicast-scouting",
                       *(str(free_port()) if flag == "{port}" else flag for flag in filled))

    return line


def replay_stopped(run: Run, stderr: str) -> tuple[str, str]:
    found = re.search(f"robot {ROBOT}: replay stopped, ([0-9]+) messages sent", stderr)
    assert found is not None, stderr
    sent = int(found[1])
    assert 0 < sent < REPLAYED, stderr
    return f"{sent} of {REPLAYED} messages sent before the stop", f"the other {REPLAYED - sent} (not sent)"


def nothing_saved(run: Run, stderr: str) -> tuple[str, str]:
    assert set(entity_rows(run.place.directory / "live.rrd")) == {"/__properties"}
    return "the .rrd complete and readable (no robot, no data)", "nothing"


def scans_converted(run: Run, stderr: str) -> tuple[str, str]:
    count = converted(stderr, "robot", "/scan")
    assert 0 < count < SCANS, stderr
    assert row_count(run.place.directory / "bag.rrd", "/robot/scan") == count
    return (f"{count} of {SCANS} scans converted, each in the .rrd", f"the other {SCANS - count} "
            "(not converted)")


def demo_saved(run: Run, stderr: str) -> tuple[str, str]:
    assert_saved_everything(run.place.directory / "demo.rrd", stderr)
    return "every /odom and /scan message converted is in the .rrd", "nothing"


STATES = {
    "relay-waiting-for-a-host": State(
        "swanky-relay --bag BAG --rate 1 -l ENDPOINT, no host yet (the issue's command)",
        relay("joint_states", "--rate", "1"), said("topics from")),
    "relay-waiting-for-a-host-wait-for-host": State(
        "swanky-relay --bag BAG --rate 1 --wait-for-host 3600 -l ENDPOINT, no host yet",
        relay("joint_states", "--rate", "1", "--wait-for-host", "3600"), said("topics from")),
    "relay-waiting-for-a-link": State(
        "swanky-relay --bag BAG --rate 1 -e ENDPOINT, nothing listening there",
        relay("joint_states", "--rate", "1", link="-e"), said("no zenoh peer answers")),
    "relay-mid-replay": State(
        f"swanky-relay --bag BAG --rate 1 ({REPLAYED} messages in 30 s), a host listening, "
        "mid-replay", relay("joint_states", "--rate", "1"), lambda run: len(run.heard) >= 10,
        listener=True, check=replay_stopped),
    "relay-at-its-hold": State(
        "swanky-relay --bag BAG --rate 0 --hold inf, a host listening, the replay done",
        relay("joint_states", "--rate", "0", "--hold", "inf"),
        said("serving latched topics and files for inf s"), listener=True),
    "relay-live-ros-graph": State(
        "swanky-relay on a live ROS 2 graph (rclpy, Fast DDS), no host",
        lambda place: command("robot_relay.cli", "--robot", ROBOT, "--no-multicast-scouting",
                              "-l", place.endpoint),
        said("/rosout: subscribed"), env=ROS_ENV),
    "host-waiting-for-robots": State(
        "swanky-host -l ENDPOINT --save FILE, no robot",
        host("-l", "{endpoint}", "--save", "{dir}/live.rrd"),
        lambda run: (run.place.directory / "live.rrd").exists(), check=nothing_saved),
    "host-waiting-for-a-link": State(
        "swanky-host -e ENDPOINT --save FILE, nothing listening there",
        host("-e", "{endpoint}", "--save", "{dir}/live.rrd"), said("no zenoh peer answers")),
    "host-converting-a-bag": State(
        f"swanky-host --bag BAG --save FILE, mid-conversion ({SCANS} LaserScans)",
        host("--bag", "{bags}/scans", "--save", "{dir}/bag.rrd"), holds_data("bag.rrd"),
        check=scans_converted),
    "host-serving-a-bag-on-the-web": State(
        "swanky-host --bag BAG --serve-web, the bag converted, serving the web viewer",
        host("--bag", "{bags}/joint_states", "--serve-web", "--web-port", "{port}",
             "--grpc-port", "{port}"),
        said("serving the web viewer until Ctrl-C")),
    "host-serving-live-robots-on-the-web": State(
        "swanky-host -l ENDPOINT --serve-web, no robot",
        host("-l", "{endpoint}", "--serve-web", "--web-port", "{port}", "--grpc-port", "{port}"),
        said("the recording is served on")),
    "host-writing-the-demo-bag": State(
        "swanky-host --demo --save FILE while it simulates the demo's bag",
        host("--demo", "--save", "{dir}/demo.rrd"), said("demo: simulating sim")),
    "host-running-the-demo": State(
        "swanky-host --demo --save FILE, the simulated robot relaying",
        # 30 s: a live file is handed its rows every LIVE_FILE_FLUSH_S (5 s) and must hold some.
        host("--demo", "--duration", "30", "--save", "{dir}/demo.rrd"), holds_data("demo.rrd"),
        check=demo_saved),
}
NEEDS_RCLPY = pytest.mark.skipif(importlib.util.find_spec("rclpy") is None,
                                 reason="rclpy is not installed: pip install -e '.[ros-test]'")


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The relay's bag and the host's long one; the long one removed afterwards (136 MB)."""
    directory = tmp_path_factory.mktemp("stop_bags")
    write_bag(directory / "joint_states", [
        Entry("/joint_states", "sensor_msgs/msg/JointState", i * 5 * 10**7,
              joint_state(i * 5 * 10**7, [i, -i]))
        for i in range(REPLAYED)
    ])
    write_copies(directory / "scans", "/scan", "sensor_msgs/msg/LaserScan", laser_scan(0, 681),
                 count=SCANS, period_ns=10**8)
    yield directory
    shutil.rmtree(directory / "scans")


def stop_together(runs: Sequence[Run]) -> list[float]:
    """Send each run its signal, one right after the other (neither shuts down while the other
    still works at full speed); the seconds from each one's signal to its end."""
    sent = []
    for run in runs:
        run.proc.send_signal(run.signum)
        sent.append(time.monotonic())
    took: dict[int, float] = {}
    deadline = time.monotonic() + 60
    while len(took) < len(runs):
        assert time.monotonic() < deadline, [run.lines.text for run in runs]
        for i, run in enumerate(runs):
            if i not in took and run.proc.poll() is not None:
                took[i] = time.monotonic() - sent[i]
        time.sleep(0.01)
    return [took[i] for i in range(len(runs))]


@contextmanager
def brought_to(state: State, signum: int, bags: Path, directory: Path) -> Iterator[Run]:
    """``state``'s program started for ``signum`` (with its listener), killed if left running."""
    directory.mkdir()
    place = Place(bags, directory, f"tcp/127.0.0.1:{free_port()}")
    with ExitStack() as stack:
        env = {name: value.format(dir=directory) for name, value in state.env.items()}
        proc, lines = stack.enter_context(started(state.command(place), env=env))
        run = Run(signum, place, proc, lines)
        if state.listener:
            listener = open_loopback("-e", place.endpoint)
            stack.callback(close_session, listener)
            listener.declare_subscriber(f"swanky/{ROBOT}/data/**", lambda sample: run.heard.append(1))
        yield run


@pytest.mark.filterwarnings("ignore:RRD file has no footer")
@pytest.mark.parametrize("name", [
    pytest.param(name, id=name, marks=[NEEDS_RCLPY] if STATES[name].env else [])
    for name in STATES
])
def test_one_signal_stops_either_program_in_any_state(
    name: str, bags: Path, tmp_path: Path, reliability: Record
) -> None:
    """A SIGINT to one run and a SIGTERM to another, both brought to the state side by side:
    each ends within ONE_SIGNAL_S, exit 0, no traceback, and leaves what it should."""
    state = STATES[name]
    with ExitStack() as stack:
        runs = [stack.enter_context(brought_to(state, signum, bags, tmp_path / signal.Signals(signum).name))
                for signum in (signal.SIGINT, signal.SIGTERM)]
        deadline = time.monotonic() + STARTUP_S
        for run in runs:
            while not state.ready(run):
                assert run.proc.poll() is None, run.lines.text
                assert time.monotonic() < deadline, f"not there within {STARTUP_S} s: {run.lines.text}"
                time.sleep(0.05)
        took = stop_together(runs)
    notes = []
    for run, seconds in zip(runs, took, strict=True):
        stderr = run.lines.all_text()
        signame = signal.Signals(run.signum).name
        assert (run.proc.returncode, "Traceback" in stderr) == (0, False), stderr
        assert f"{signame}: stopping (again to force)" in stderr
        assert seconds < ONE_SIGNAL_S, f"{signame}: {seconds:.2f} s\n{stderr}"
        if state.check is not None:
            notes.append(state.check(run, stderr))
    survived = (f"both ended, exit 0, no traceback: {took[0]:.2f} s after SIGINT, {took[1]:.2f} s "
                "after SIGTERM")
    lost = "nothing"
    if notes:
        survived += "; " + " / ".join(note for note, _ in notes)
        lost = " / ".join(loss for _, loss in notes)
    reliability("Stopping", state.what, tried="1 SIGINT, 1 SIGTERM (a run each)",
                survived=survived, lost=lost)
