"""A viewer that falls behind (issue 24): the host measures how far behind it is
(``/_stats/host/viewer_lag_ms``), sends it fewer heavy messages while it is (host_bridge/
thinning.py), says which, and sends it everything again once it caught up; small topics are
never thinned and a ``--save`` file beside it gets every message.

A relay replays a bag of odometry (30 Hz) and camera images of random noise (15 Hz, 3.5 MB/s:
nothing compresses them, so a stalled reader's connection fills) on loopback. The viewer falls
behind for certain: it is stopped (SIGSTOP) for FROZEN_S, then resumed, while the robot goes on.

* A real viewer, Rerun's native viewer drawing offscreen with software GL (``rerun
  --headless``), measured through its answers (viewer_lag.py), with a ``--save`` file: heavy
  messages it is not sent are converted for the file only.
* ``rerun --port N --save`` (a gRPC server that writes what it receives, measured by flushes
  only), the host's one destination: heavy topics go through the converter process
  (offload.py), and what the viewer is not sent is not converted; its file says what it got.
"""

from __future__ import annotations

import re
import signal
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.rosbag2 import Writer

from host_bridge.pipeline.thinning import LAG_PATH
from tests.integration.procs import command, free_port, rendering_viewer, running, saving_viewer
from tests.integration.robot_bags import START_NS, STORE, Lines
from tests.integration.robot_traffic import (
    IMAGE_HZ,
    IMAGE_PERIOD_NS,
    ODOM_HZ,
    ODOM_PERIOD_NS,
    QOS,
    TYPES,
    image,
    odometry,
)
from tests.integration.test_bad_links import NO_SHM
from tests.rrd import entity_rows

pytestmark = [pytest.mark.integration, pytest.mark.filterwarnings("ignore:RRD file has no footer")]

ROBOT = "cam"
IMAGES, ODOM = "/camera/image_raw", "/odom"
WIDTH, HEIGHT = 320, 240
BAG_S = 20.0
"""The robot's whole run: healthy, the viewer frozen, then long enough for it to catch up."""
HEALTHY_S = 4.0
FROZEN_S = 4.0
"""Under the 5 s after which a viewer gets no data at all (sink.SUSPEND_S): it is thinned."""
CAUGHT_UP_WITHIN_S = 6.0
"""After SIGCONT, the lag is under a second from this long on."""
STARTUP_S = 90.0


def write_bag(path: Path) -> Path:
    """BAG_S of odometry and noise images, odometry i at x = i / 1000 m."""
    rng = np.random.default_rng(24)
    entries: list[tuple[int, str, Any]] = [
        (START_NS + i * ODOM_PERIOD_NS, ODOM, odometry(i)) for i in range(int(BAG_S * ODOM_HZ))]
    for i in range(int(BAG_S * IMAGE_HZ)):
        frame = image(i, WIDTH, HEIGHT)
        frame.data = rng.integers(0, 256, WIDTH * HEIGHT * 3, dtype=np.uint8)
        entries.append((START_NS + i * IMAGE_PERIOD_NS, IMAGES, frame))
    with Writer(path, version=9) as writer:
        connections = {topic: writer.add_connection(topic, TYPES[topic], typestore=STORE,
                                                    offered_qos_profiles=QOS[topic])
                       for topic in (ODOM, IMAGES)}
        for log_ns, topic, msg in sorted(entries, key=lambda entry: entry[0]):
            writer.write(connections[topic], log_ns, bytes(STORE.serialize_cdr(msg, TYPES[topic])))
    return path


@contextmanager
def freezing_run(bag: Path, url: str, viewer: Any, *host_flags: str) -> Iterator[tuple[Lines, int, int]]:
    """The host sending to the viewer at ``url`` and a relay replaying ``bag`` to it; the viewer
    stopped for FROZEN_S after HEALTHY_S. Yields, once the host has ended (the bag replayed,
    then --until-idle): its stderr and when (wall clock, ns) the viewer was stopped and
    resumed."""
    port = free_port()
    with ExitStack() as stack:
        host = stack.enter_context(running(command(
            "host_bridge.cli", "-l", f"tcp/127.0.0.1:{port}", *NO_SHM, "--rerun-addr", url,
            "--until-idle", "3", "--duration", "150", *host_flags)))
        lines = Lines(host)
        relay = stack.enter_context(running(command(
            "robot_relay.cli", "--robot", ROBOT, "--bag", str(bag), "-e", f"tcp/127.0.0.1:{port}",
            *NO_SHM, "--wait-for-host", "60")))
        lines.wait_for(f"robot {ROBOT} joined", timeout=STARTUP_S)
        time.sleep(HEALTHY_S)
        viewer.send_signal(signal.SIGSTOP)
        frozen_ns = time.time_ns()
        time.sleep(FROZEN_S)
        viewer.send_signal(signal.SIGCONT)
        resumed_ns = time.time_ns()
        relay.wait(timeout=BAG_S + 60)
        code = host.wait(timeout=60)
        text = lines.all_text()
        assert (code, "Traceback" in text) == (0, False), text
        yield lines, frozen_ns, resumed_ns


def scalars(rows: list[dict[str, Any]]) -> list[tuple[int, float]]:
    """(receive_time, value) of each row of a Scalars series."""
    return [(row["receive_time"], row["Scalars:scalars"][0]) for row in rows]


def odom_indices(rows: list[dict[str, Any]]) -> list[int]:
    """Which odometry message each row is (message i is at x = i / 1000 m)."""
    return [round(row["Transform3D:translation"][0][0] * 1000) for row in rows]


def temporal(rows: dict[str, list[dict[str, Any]]], entity: str) -> list[dict[str, Any]]:
    return [row for row in rows.get(entity, []) if not row["static"]]


def thinned_at_stop(stderr: str) -> int:
    """The images the viewer was not sent, from the host's closing count."""
    match = re.search(rf"^\[{ROBOT}\] {IMAGES}: (\d+)$", stderr, re.M)
    assert match is not None, stderr
    return int(match[1])


def assert_lag_measured_and_recovered(lag: list[tuple[int, float]], frozen_ns: int, resumed_ns: int) -> None:
    """The freeze shows in the lag (a second behind and more, growing while it lasts), and a
    few seconds after the viewer resumed it is under a second to the end."""
    while_frozen = [ms for ns, ms in lag if frozen_ns + 2 * 10**9 < ns <= resumed_ns + 10**9]
    assert max(while_frozen, default=0.0) > 1500, lag
    caught_up = [ms for ns, ms in lag if ns > resumed_ns + CAUGHT_UP_WITHIN_S * 10**9]
    assert len(caught_up) >= 3, lag
    assert max(caught_up) < 1000, lag


def test_a_frozen_real_viewer_is_measured_thinned_for_and_catches_up(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "bag")
    saved = tmp_path / "host.rrd"
    with rendering_viewer() as (url, viewer), \
            freezing_run(bag, url, viewer, "--save", str(saved)) as (lines, frozen_ns, resumed_ns):
        # The viewer itself has the newest data: its receive_time reaches the robot's last message.
        from rerun.experimental import ViewerClient

        (recording,) = ViewerClient(url).get_state().recordings
        (received,) = [timeline for timeline in recording.timelines if timeline.name == "receive_time"]
    stderr = lines.text
    rows = entity_rows(saved)
    odom = temporal(rows, f"/{ROBOT}{ODOM}")

    # No small-topic message lost in --save: every odometry message of the bag, once, in order.
    assert odom_indices(odom) == list(range(int(BAG_S * ODOM_HZ)))
    assert received.end is not None
    assert received.end >= odom[-1]["receive_time"]

    # Measured: the lag the host logged (into the file too) shows the freeze and its end.
    assert_lag_measured_and_recovered(scalars(temporal(rows, LAG_PATH)), frozen_ns, resumed_ns)

    # Thinned: named with its rate, counted each second and at the end, and over.
    assert re.search(rf"WARNING: \[{ROBOT}\] {IMAGES}: the Rerun viewer {re.escape(url)} is [\d.]+ s "
                     r"behind: it gets the newest message of this topic at most every [\d.]+ s "
                     r"\([\d.]+ Hz\) until it catches up; the --save file gets every one", stderr), stderr
    assert f"INFO: the Rerun viewer {url} caught up: heavy topics go to it in full again" in stderr
    thinned = thinned_at_stop(stderr)
    per_second = scalars(temporal(rows, f"/_stats/{ROBOT}{IMAGES}/viewer_thinned"))
    assert thinned > 0
    assert sum(count for _, count in per_second) == thinned
    assert sum(count for ns, count in per_second if frozen_ns < ns < resumed_ns) > 0, per_second
    # ... and the file has the images the viewer was not sent: every one the host received.
    images = temporal(rows, f"/{ROBOT}{IMAGES}")
    assert len(images) + queue_drops(stderr) == received_images(stderr)


def received_images(stderr: str) -> int:
    """The images that reached the host, from its closing summary table."""
    for line in stderr.splitlines():
        fields = line.split()
        if fields[:2] == [ROBOT, IMAGES]:
            return int(fields[3])
    raise AssertionError(f"{IMAGES} not in the summary:\n{stderr}")


def queue_drops(stderr: str) -> int:
    """Images the host's own queue dropped (a loaded machine), from its drop summary; 0 if none."""
    match = re.search(rf"^\[{ROBOT}\] {IMAGES}: (\d+) dropped", stderr, re.M)
    return 0 if match is None else int(match[1])


def test_a_frozen_viewer_alone_gets_fewer_heavy_messages_and_every_small_one(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "bag")
    received = tmp_path / "viewer.rrd"
    with saving_viewer(received, STARTUP_S) as (url, viewer), \
            freezing_run(bag, url, viewer) as (lines, frozen_ns, resumed_ns):
        viewer.send_signal(signal.SIGINT)  # it writes what it received
        viewer.wait(timeout=60)
    stderr = lines.text
    rows = entity_rows(received)
    odom = temporal(rows, f"/{ROBOT}{ODOM}")
    assert odom_indices(odom) == list(range(int(BAG_S * ODOM_HZ)))
    assert_lag_measured_and_recovered(scalars(temporal(rows, LAG_PATH)), frozen_ns, resumed_ns)
    assert re.search(rf"WARNING: \[{ROBOT}\] {IMAGES}: the Rerun viewer {re.escape(url)} is [\d.]+ s "
                     r"behind: it gets the newest message", stderr), stderr
    assert ("heavy messages not sent to the Rerun viewer because it fell behind (they were not "
            "converted)") in stderr
    # What it was not sent was not converted: the converter process got the others, all shown.
    images = temporal(rows, f"/{ROBOT}{IMAGES}")
    assert len(images) + thinned_at_stop(stderr) + queue_drops(stderr) == received_images(stderr)
    assert thinned_at_stop(stderr) > 0


def test_with_a_file_the_viewer_misses_only_the_thinned_images_and_the_file_none(tmp_path: Path) -> None:
    """The same without a display or Vulkan (CI): ``rerun --port N --save`` beside a --save
    file, the heavy topics converted in the host (a file is this process's own)."""
    bag = write_bag(tmp_path / "bag")
    received, saved = tmp_path / "viewer.rrd", tmp_path / "host.rrd"
    with saving_viewer(received, STARTUP_S) as (url, viewer), \
            freezing_run(bag, url, viewer, "--save", str(saved)) as (lines, frozen_ns, resumed_ns):
        viewer.send_signal(signal.SIGINT)  # it writes what it received
        viewer.wait(timeout=60)
    stderr = lines.text
    in_file, in_viewer = entity_rows(saved), entity_rows(received)
    for rows in (in_file, in_viewer):
        assert odom_indices(temporal(rows, f"/{ROBOT}{ODOM}")) == list(range(int(BAG_S * ODOM_HZ)))
    assert_lag_measured_and_recovered(scalars(temporal(in_file, LAG_PATH)), frozen_ns, resumed_ns)
    images = {row["ros_time"] for row in temporal(in_file, f"/{ROBOT}{IMAGES}")}
    shown = {row["ros_time"] for row in temporal(in_viewer, f"/{ROBOT}{IMAGES}")}
    assert len(images) + queue_drops(stderr) == received_images(stderr)
    assert shown < images
    assert len(images - shown) == thinned_at_stop(stderr)
