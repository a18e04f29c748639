"""A viewer slower than the data (issue 14): a relay replays camera images of random noise
(nothing compresses them) on loopback to a host logging to a ``rerun --serve-grpc`` viewer that
is frozen (SIGSTOP) for FROZEN_S, then resumes. Rerun's gRPC client alone would buffer all of
it; the pacer (host_bridge.sink._ViewerPacer) of the host's converter process, which logs the
images (host_bridge/offload.py), holds it back instead, and with it the robot's heavy thread that
waits on it, so both processes' memory stays bounded, the host's queue drops (and counts) the
images, and the resumed viewer gets the newest ones. The viewer saves what it receives, so the
test reads what it got."""

from __future__ import annotations

import re
import signal
import time
from contextlib import ExitStack
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from rerun.chunk import RrdReader
from rosbags.rosbag2 import Writer

from host_bridge.contract import TIMELINE_RECEIVE
from tests.integration.proc_sampler import Sampler
from tests.integration.procs import (
    command,
    converter_processes,
    free_port,
    running,
    saving_viewer,
)
from tests.integration.robot_bags import START_NS, STORE, Lines
from tests.integration.robot_traffic import IMAGE_HZ, IMAGE_PERIOD_NS, QOS, TYPES, image
from tests.integration.test_bad_links import NO_SHM
from tests.reliability import Record

pytestmark = pytest.mark.integration

TOPIC = "/camera/image_raw"
WIDTH, HEIGHT = 480, 360
FRAME_BYTES = WIDTH * HEIGHT * 3
BAG_FRAMES = 45
"""Three seconds of 15 Hz frames, replayed in a loop."""
FROZEN_S = 10.0
STARTUP_S = 90.0


def write_noise_bag(path: Path) -> Path:
    rng = np.random.default_rng(14)
    with Writer(path, version=9) as writer:
        connection = writer.add_connection(TOPIC, TYPES[TOPIC], typestore=STORE,
                                           offered_qos_profiles=QOS[TOPIC])
        for index in range(BAG_FRAMES):
            frame = image(index, WIDTH, HEIGHT)
            frame.data = rng.integers(0, 256, FRAME_BYTES, dtype=np.uint8)
            writer.write(connection, START_NS + index * IMAGE_PERIOD_NS,
                         bytes(STORE.serialize_cdr(frame, TYPES[TOPIC])))
    return path


def receive_times(path: Path, entity: str) -> list[int]:
    """The receive_time of each row of ``entity``, without reading its images."""
    times: list[int] = []
    for chunk in RrdReader(path).stream():
        if chunk.entity_path == entity and not chunk.is_static:
            times += chunk.to_record_batch().column(TIMELINE_RECEIVE).cast(pa.int64()).to_pylist()
    return times


def summary_counts(stderr: str) -> tuple[int, int]:
    """received and converted of the image topic in the host's closing summary table."""
    for line in stderr.splitlines():
        fields = line.split()
        if fields[:2] == ["cam", TOPIC]:
            return int(fields[3]), int(fields[4])
    raise AssertionError(f"{TOPIC} not in the summary:\n{stderr}")


def queue_drops(stderr: str) -> int:
    """The images the host's queue replaced by newer ones, from its drop summary."""
    match = re.search(rf"^\[cam\] {TOPIC}: (\d+) dropped \((\d+) replaced by a newer one", stderr, re.M)
    assert match is not None, stderr
    assert match[1] == match[2], match[0]  # none for a full queue: latest-only kept it short
    return int(match[1])


@pytest.mark.filterwarnings("ignore:RRD file has no footer")
def test_frozen_viewer_keeps_host_memory_bounded_and_gets_the_newest_data_after(
    tmp_path: Path, reliability: Record,
) -> None:
    bag = write_noise_bag(tmp_path / "noise")
    received_rrd = tmp_path / "received.rrd"
    port = free_port()
    with ExitStack() as stack:
        url, viewer = stack.enter_context(saving_viewer(received_rrd))
        host = stack.enter_context(running(command(
            "host_bridge.cli", "-l", f"tcp/127.0.0.1:{port}", *NO_SHM, "--no-stats",
            "--rerun-addr", url, "--duration", "120")))
        host_lines = Lines(host)
        stack.enter_context(running(command(
            "robot_relay.cli", "--robot", "cam", "--bag", str(bag), "--loop",
            "-e", f"tcp/127.0.0.1:{port}", *NO_SHM, "--wait-for-host", "60")))
        host_lines.wait_for("robot cam joined", timeout=STARTUP_S)
        # The images are converted and logged in the host's converter process (offload.py).
        (converter,) = converter_processes(host.pid)
        samplers = [Sampler(pid, period_s=0.1) for pid in (host.pid, converter)]
        time.sleep(3)  # healthy: every frame through to the viewer
        healthy = time.monotonic()
        viewer.send_signal(signal.SIGSTOP)
        frozen, frozen_ns = time.monotonic(), time.time_ns()
        time.sleep(FROZEN_S)
        viewer.send_signal(signal.SIGCONT)
        resumed, resumed_ns = time.monotonic(), time.time_ns()
        time.sleep(3)  # the viewer catches up and gets new frames
        for sampler in samplers:
            sampler.stop()
        host.send_signal(signal.SIGTERM)
        code = host.wait(timeout=60)
        stopped = time.monotonic()
        viewer.send_signal(signal.SIGINT)  # it writes what it received
        viewer.wait(timeout=60)
    stderr = host_lines.text
    assert (code, "Traceback" in stderr) == (0, False), stderr  # 0: the viewer took every frame

    # Memory: a frozen viewer left to Rerun's client would cost the host every frame sent meanwhile.
    data_mb = IMAGE_HZ * FRAME_BYTES * FROZEN_S / 2**20
    for sampler in samplers:
        before = sampler.peak_mb(healthy - 3, healthy)
        during = sampler.peak_mb(frozen, resumed)
        assert during - before < data_mb / 2, (sampler.pid, before, during, data_mb)

    # Drops: counted in the summary, and said why.
    received, converted = summary_counts(stderr)
    assert received == converted, stderr
    dropped = queue_drops(stderr)
    assert dropped > 0
    assert f"WARNING: the Rerun viewer {url} takes the data slower than it comes" in stderr
    assert f"INFO: the Rerun viewer {url} fell behind " in stderr

    # What the viewer received (exit 0 above: the host's last flush to it succeeded): every
    # image the host converted; while it was frozen only what the pacer let through before it
    # held the host back (a second in flight allowed), and a second's worth and more after SIGCONT.
    receive_ns = receive_times(received_rrd, f"/cam{TOPIC}")
    assert len(receive_ns) == converted
    while_frozen = sum(frozen_ns + 10**9 < ns < resumed_ns for ns in receive_ns)
    after = sum(ns > resumed_ns for ns in receive_ns)
    assert while_frozen < FROZEN_S * IMAGE_HZ / 4, (while_frozen, after, len(receive_ns))
    assert after >= IMAGE_HZ, (while_frozen, after, len(receive_ns))
    reliability(
        "Slow consumer",
        f"the Rerun viewer (rerun --port N --save, no window) frozen with SIGSTOP for {FROZEN_S:.0f} s, then "
        f"resumed, while a relay sends {WIDTH}x{HEIGHT} rgb8 noise images at {IMAGE_HZ} Hz "
        f"({IMAGE_HZ * FRAME_BYTES / 2**20:.1f} MB/s, loopback) to the host",
        tried=f"1 run, {stopped - healthy:.0f} s",
        survived=f"host RSS {before:.0f} MB -> peak {during:.0f} MB while frozen (the frames "
                 f"would add {data_mb:.0f} MB); the viewer received all {converted} images the host "
                 f"converted, {while_frozen} of them stamped while it was frozen, {after} after "
                 "SIGCONT; host exit 0 on SIGTERM",
        lost=f"{dropped} images, the host queue's older ones, counted in its drop summary",
    )
