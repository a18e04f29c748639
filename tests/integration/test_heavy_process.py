"""``swanky-host --rerun-addr`` (a viewer its one destination) converts heavy topics in a second
process (host_bridge/pipeline/offload.py): the viewer gets one recording with every message the host's
summary says it converted, heavy and small alike, and the second process ends with the host."""

from __future__ import annotations

import signal
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from rerun.chunk import RrdReader

from host_bridge.outputs.sink import DISCONNECT_TIMEOUT_S
from tests.integration.procs import (
    alive,
    command,
    converter_processes,
    headless_viewer,
    saving_viewer,
)
from tests.integration.robot_bags import Lines
from tests.integration.test_host_stop import STARTUP_S, STOP_WITHIN_S, converted, started, stop_and_wait
from tests.rrd import entity_rows

pytestmark = [pytest.mark.integration, pytest.mark.filterwarnings("ignore:RRD file has no footer")]

HEAVY = ("/camera/image_raw", "/camera/depth/image_raw", "/camera/depth/points")
SMALL = ("/scan", "/odom")


@contextmanager
def demo_to(url: str) -> Iterator[tuple[subprocess.Popen[str], Lines, int]]:
    """``swanky-host --demo --rerun-addr url`` once its robot joined and data flowed: the host,
    its stderr and its converter process."""
    with started(command("host_bridge.cli", "--demo", "--rerun-addr", url)) as (host, lines):
        lines.wait_for("robot sim joined", timeout=STARTUP_S)
        time.sleep(3)  # images and clouds through both processes
        (child,) = converter_processes(host.pid)
        yield host, lines, child


def test_demo_to_a_viewer_converts_heavy_topics_in_a_second_process(tmp_path: Path) -> None:
    received = tmp_path / "viewer.rrd"
    with saving_viewer(received, STARTUP_S) as (url, _), demo_to(url) as (host, lines, child):
        took = stop_and_wait(host, signal.SIGTERM)
    assert (host.returncode, "Traceback" in lines.text) == (0, False), lines.text
    assert took < STOP_WITHIN_S
    assert not alive(child), "the converter outlived the host"
    (recording,) = RrdReader(received).recordings()
    assert recording.application_id == "swanky"
    rows = entity_rows(received)
    for topic in (*HEAVY, *SMALL):
        count = converted(lines.text, "sim", topic)
        assert count > 0, (topic, lines.text)
        logged = [r for r in rows[f"/sim{topic}"] if not r["static"]]
        assert len(logged) == count, topic


def test_a_frozen_viewer_is_left_behind_by_both_processes_within_seconds() -> None:
    """The host's stop reaches the converter process too: neither waits for ever on a viewer
    that stopped answering, and they leave it at once, not one after the other."""
    with headless_viewer() as (url, _, viewer), demo_to(url) as (host, lines, child):
        viewer.send_signal(signal.SIGSTOP)
        time.sleep(1)
        took = stop_and_wait(host, signal.SIGTERM)
    assert host.returncode == 1, lines.text
    assert took < DISCONNECT_TIMEOUT_S + STOP_WITHIN_S, lines.text
    assert f"swanky-host: error: gave up closing {url}" in lines.text
    assert "Traceback" not in lines.text
    assert not alive(child), "the converter outlived the host"


def test_the_converter_process_ends_when_the_host_is_killed() -> None:
    """No orphan: a host gone without a word (SIGKILL) closes the converter's socket."""
    with headless_viewer() as (url, _, _), demo_to(url) as (host, _, child):
        host.kill()
        host.wait(timeout=30)
        deadline = time.monotonic() + STOP_WITHIN_S + DISCONNECT_TIMEOUT_S
        while alive(child):
            assert time.monotonic() < deadline, "the converter outlived the host"
            time.sleep(0.1)
