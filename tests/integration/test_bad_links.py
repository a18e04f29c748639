"""A robot behind a bad link (issue 14): the relay and the host in two network namespaces,
joined by an emulated link (tests/integration/emulated_link.py: TUN devices and a Python
process forwarding the packets, since this kernel has no netem) that loses 10 % of the packets
and delays each by 100 ms, each way, at 20 Mbit/s (tbf).

Zenoh runs over TCP (``tcp/``, as deployed: ``swanky-relay -e tcp/PC:7447``), so a lost packet
is retransmitted by the kernel's own TCP, which is what a robot on bad Wi-Fi lives with. Zenoh's
UDP transport would lose reliable messages outright. One TCP connection carries every topic, so
/odom and /scan wait behind the images in its kernel send buffer, where Zenoh's priorities no
longer apply: their latency is the images' (recorded; ``--priority-links`` would split them, see
robot_relay/session.py for why it is not the default). Both sides switch Zenoh's shared memory
off: two processes on one machine would otherwise pass every payload above 3 KB (the images)
through /dev/shm, past the link, whatever namespace they are in.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Sequence
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pytest
from rerun.chunk import RrdReader

from tests.integration.emulated_link import Link, LinkShape, emulated_link
from tests.integration.proc_sampler import Sampler
from tests.integration.procs import command, running
from tests.integration.robot_bags import START_NS, Lines
from tests.integration.robot_traffic import (
    BROADCASTERS,
    Traffic,
    image_fill,
    image_index,
    map_cells,
    odom_index,
    odom_x,
    write_traffic_bag,
)
from tests.reliability import Record
from tests.rrd import entity_rows

pytestmark = pytest.mark.integration

ROBOT = "tb"
PORT = 7447
BAD_LINK = LinkShape(delay_s=0.1, loss=0.1, rate_mbit=20)
NO_SHM = ("--no-multicast-scouting", "--cfg", "transport/shared_memory/enabled:false")
STOP_S = 120.0
"""Every process ends within this (a loaded 2-core machine; the replay takes ~20 s)."""
LATENCY_TOPICS = ("/odom", "/scan", "/camera/image_raw")


def host_command(link: Link, out: Path, *flags: str) -> list[str]:
    return link.in_pc(command("host_bridge.cli", "-l", f"tcp/{link.pc_ip}:{PORT}", *NO_SHM,
                              "--save", str(out), *flags))


def relay_command(link: Link, bag: Path, *flags: str) -> list[str]:
    return link.in_robot(command("robot_relay.cli", "--robot", ROBOT, "--bag", str(bag),
                                 "-e", f"tcp/{link.pc_ip}:{PORT}", *NO_SHM, *flags))


def arrival_order(path: Path, entity: str) -> list[int]:
    """The ros_time of each non-static row of ``entity`` in the order the host received them:
    by its receive_time timeline, stamped on arrival. (Not the order of the chunks in the file:
    Rerun's batcher holds the rows of ``rr.log`` a while, while ``send_columns`` chunks go out
    at once, so a run of one message can land in the file after a later run's columns.)"""
    arrivals: list[tuple[int, int]] = []
    for chunk in RrdReader(path).stream():
        if chunk.entity_path == entity and not chunk.is_static:
            batch = chunk.to_record_batch()
            arrivals += zip(batch.column("receive_time").cast(pa.int64()).to_pylist(),
                            batch.column("ros_time").cast(pa.int64()).to_pylist(), strict=True)
    return [ros_time for _, ros_time in sorted(arrivals)]


def scalars(rows: dict[str, list[dict[str, Any]]], entity: str) -> list[float]:
    return [row["Scalars:scalars"][0] for row in rows.get(entity, [])]


def summary_row(stderr: str, topic: str) -> dict[str, int]:
    """received / converted / gaps of ``topic`` in the host's closing summary table."""
    for line in stderr.splitlines():
        fields = line.split()
        if fields[:2] == [ROBOT, topic]:
            return {"received": int(fields[3]), "converted": int(fields[4]), "gaps": int(fields[7])}
    raise AssertionError(f"{topic} not in the host's summary:\n{stderr}")


def check_latched_once(rows: dict[str, list[dict[str, Any]]]) -> None:
    """Every /tf_static broadcaster's transform, the map and the model, each logged once. (The
    URDF's fixed joint writes base_link's relation too, with the same value, when it comes
    before /tf_static placed base_link.)"""
    for parent, child, xyz in BROADCASTERS:
        logged = rows[f"/{ROBOT}/tf_static/{child}"]
        assert all(row["static"] for row in logged)
        expected_rows = (1, 2) if child == "base_link" else (1,)
        assert len(logged) in expected_rows, (child, logged)
        for row in logged:
            assert row["Transform3D:parent_frame"] == [f"{ROBOT}/{parent}"]
            np.testing.assert_allclose(row["Transform3D:translation"][0], xyz, atol=1e-6)
    (grid,) = rows[f"/{ROBOT}/map"]
    assert grid["ros_time"] == START_NS
    assert grid["GridMap:data"] == [map_cells().astype(np.uint8).ravel().tolist()]
    assert len(rows[f"/{ROBOT}/robot_model/base_link/visual_0"]) == 1


def check_odometry(path: Path, rows: Sequence[dict[str, Any]], expected: range) -> None:
    """Every odometry message, once, in the order sent, with its own position."""
    assert [odom_index(t) for t in arrival_order(path, f"/{ROBOT}/odom")] == list(expected)
    for row in rows:
        assert row["Transform3D:translation"][0][0] == pytest.approx(
            odom_x(odom_index(row["ros_time"])), abs=1e-6)


def test_latched_and_reliable_survive_a_lossy_slow_link(tmp_path: Path, reliability: Record) -> None:
    traffic = Traffic(seconds=8.0)
    bag = write_traffic_bag(tmp_path / "traffic", traffic)
    out = tmp_path / "bad_link.rrd"
    with ExitStack() as stack:
        link = stack.enter_context(emulated_link(BAD_LINK))
        host = stack.enter_context(running(host_command(
            link, out, "--until-idle", "4", "--duration", str(STOP_S))))
        # --hold 5: the relay's session stays up while the link drains its send buffer (the
        # replay's last second sits there; see the report on tail loss at relay exit).
        relay = stack.enter_context(running(relay_command(
            link, bag, "--wait-for-host", "60", "--hold", "5")))
        host_lines, relay_lines = Lines(host), Lines(relay)
        sampler = Sampler(relay.pid)
        relay_lines.wait_for("robot tb: 6 topics", timeout=60)
        started = time.monotonic()
        relay_lines.wait_for("replay finished", timeout=STOP_S)
        replayed = time.monotonic()
        assert relay.wait(timeout=STOP_S) == 0, relay_lines.text
        sampler.stop()
        assert host.wait(timeout=STOP_S) == 0, host_lines.text
    assert link.counts is not None
    sent = link.counts["robot_to_pc"]
    rows = entity_rows(out)

    check_latched_once(rows)
    odom = [row for row in rows[f"/{ROBOT}/odom"] if not row["static"]]
    check_odometry(out, odom, traffic.odom())
    assert summary_row(host_lines.text, "/odom")["gaps"] == 0, host_lines.text + relay_lines.text
    assert set(scalars(rows, f"/_stats/{ROBOT}/odom/drops")) == {0.0}

    scans = rows[f"/{ROBOT}/scan"]
    assert 0 < len(scans) <= len(traffic.scan_indices())
    # Images: fewer than sent, and those that came are whole and recent (no backlog grows: the
    # relay drops what the link cannot take instead of queueing it).
    images = rows[f"/{ROBOT}/camera/image_raw"]
    sent_images = len(traffic.image_indices())
    assert 0 < len(images) < sent_images
    for row in images:
        pixels = np.asarray(row["Image:buffer"][0], np.uint8)
        assert pixels.size == 320 * 240 * 3
        assert set(np.unique(pixels).tolist()) == {image_fill(image_index(row["ros_time"]))}
    # Lost on the link (drops: wire gaps of closed periods) or replaced in the host's queue
    # while it was behind (host_drops): both show in /_stats, never more than were lost.
    lost = sent_images - len(images)
    image_drops = sum(scalars(rows, f"/_stats/{ROBOT}/camera/image_raw/drops")) + sum(
        scalars(rows, f"/_stats/{ROBOT}/camera/image_raw/host_drops"))
    assert 0 < image_drops <= lost
    gaps = summary_row(host_lines.text, "/camera/image_raw")["gaps"]
    assert gaps <= lost
    latency_s = max(scalars(rows, f"/_stats/{ROBOT}/camera/image_raw/latency_ms")) / 1000
    assert latency_s < 10.0
    # Medians of the per-second means (the first seconds, slow start through 10 % loss and the
    # latched burst, are slow for every topic). Measured: all three 1.5 s.
    median_s = {topic: statistics.median(scalars(rows, f"/_stats/{ROBOT}{topic}/latency_ms")) / 1000
                for topic in LATENCY_TOPICS}
    assert max(median_s.values()) < 10.0, median_s

    # The relay's memory: bounded, and not growing during the replay.
    assert sampler.samples, "no /proc sample of the relay"
    middle = started + (replayed - started) / 2
    first_half, second_half = sampler.peak_mb(started, middle), sampler.peak_mb(middle, replayed)
    peak = sampler.peak_mb()
    assert peak < 250.0
    assert second_half <= first_half + 25.0, (first_half, second_half)
    cpu = sampler.cpu_percent(started, replayed)
    assert cpu < 100.0

    reliability(
        "Bad links",
        f"relay and host in two network namespaces, link with {BAD_LINK.describe()} (TUN pair "
        "+ userspace wire: no netem here), Zenoh over TCP; an 8 s bag: /tf_static from 3 "
        "broadcasters, /robot_description, /map, 30 Hz reliable /odom, 10 Hz best-effort /scan, "
        "15 Hz 320x240 rgb8 images",
        tried=f"1 replay ({replayed - started:.0f} s through the link); {sent['forwarded']} "
              f"packets robot->PC, {sent['lost']} lost by the link",
        survived=f"latched 5/5, each once; /odom {len(odom)}/{len(traffic.odom())} in order; "
                 f"/scan {len(scans)}/{len(traffic.scan_indices())}; images {len(images)}/"
                 f"{sent_images}, intact, latency at most {latency_s:.1f} s; relay RSS peak "
                 f"{peak:.0f} MB ({first_half:.0f} -> {second_half:.0f} MB over the replay), CPU "
                 f"{cpu:.0f} % of a core; latency (median of per-second means) "
                 + ", ".join(f"{topic} {median_s[topic]:.2f} s" for topic in median_s)
                 + " (one TCP connection: small topics wait behind the images)",
        lost=f"{sent_images - len(images)} images (dropped by the relay under congestion, "
             f"{image_drops:.0f} shown in /_stats drops and host_drops, {gaps} gaps in the host "
             "summary); "
             "0 latched, 0 reliable",
    )
