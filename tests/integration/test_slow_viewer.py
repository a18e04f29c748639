"""A viewer slower than the data (issues 14, 24): a relay replays camera images of random noise
(nothing compresses them) on loopback to a host logging to a ``rerun --port N --save`` viewer
that is frozen (SIGSTOP) for FROZEN_S, then resumes. Rerun's gRPC client alone would buffer all
of it. The images are logged by the host's converter process (host_bridge/pipeline/offload.py); the host
sees the viewer fall behind (that process's round trip to it, host_bridge/outputs/viewer_lag.py), sends
it fewer images (host_bridge/pipeline/thinning.py: those are not converted at all) and, once it is more
than 5 s behind, none (host_bridge/outputs/sink.py's SUSPEND_S, in the converter process too), so both
processes' memory stays bounded without holding anything back, and the resumed viewer gets the
newest images. The viewer saves what it receives, so the test reads what it got."""

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

from host_bridge.core.contract import TIMELINE_RECEIVE
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
AFTER_S = 8.0
"""Running after SIGCONT: the viewer catches up and is sent images at full rate again."""
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


def thinned(stderr: str) -> int:
    """The images the viewer was not sent (nor converted), from the host's closing count."""
    match = re.search(rf"^\[cam\] {TOPIC}: (\d+)$", stderr, re.M)
    assert match is not None, stderr
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
        time.sleep(AFTER_S)  # the viewer catches up and gets new frames
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

    # Sent less: the images the viewer was not sent are named, counted and not converted.
    received, converted = summary_counts(stderr)
    not_sent = thinned(stderr)
    assert received == converted + not_sent, stderr
    assert not_sent > 0
    assert re.search(rf"WARNING: \[cam\] {TOPIC}: the Rerun viewer {re.escape(url)} is [\d.]+ s behind: "
                     r"it gets the newest message of this topic at most every", stderr), stderr
    # ... and none at all while it was more than 5 s behind, by either process.
    assert re.search(rf"WARNING: the Rerun viewer {re.escape(url)} is \d+ s behind: it gets no data but "
                     "static data until it has caught up", stderr), stderr
    assert f"INFO: the Rerun viewer {url} caught up: it was sent nothing for" in stderr

    # What the viewer received (exit 0 above: the host's last flush to it succeeded): images the
    # host converted, few while it was frozen (a second in flight allowed), and a second's worth
    # and more after SIGCONT.
    receive_ns = receive_times(received_rrd, f"/cam{TOPIC}")
    assert len(receive_ns) <= converted
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
                 f"would add {data_mb:.0f} MB); the viewer received {len(receive_ns)} of the "
                 f"{converted} images the host converted, {while_frozen} of them stamped while it "
                 f"was frozen, {after} after SIGCONT; host exit 0 on SIGTERM",
        lost=f"{not_sent} images not sent to the viewer (nor converted) while it was behind, named "
             "and counted; what the converter process logged while the viewer was 5 s behind",
    )
