"""A live ``--save`` that Rerun's own tools accept: a 30-minute recording replayed at 300x by a
relay into a host that starts a new file every second, and saves stopped by SIGINT and by
SIGTERM while data flows. Every file passes ``rerun rrd verify`` and opens with
``RrdReader(path).store()``; together they hold each message the host converted once. The
host's memory over a long save: benchmarks/soak.py."""

from __future__ import annotations

import itertools
import signal
import time
from pathlib import Path

import pytest
from rerun.chunk import RrdReader

from host_bridge.outputs.sink import split_path
from tests.integration.procs import command, free_port, running, wait_listening
from tests.integration.robot_bags import Lines
from tests.integration.robot_traffic import ODOM_HZ, SCAN_HZ, Traffic, write_traffic_bag
from tests.integration.test_bad_links import NO_SHM
from tests.integration.test_host_stop import STARTUP_S, STOP_WITHIN_S, converted, stop_and_wait
from tests.reliability import Record
from tests.rrd import entity_rows, verify

pytestmark = pytest.mark.integration

ROBOT = "rec"
TRAIL = 20
SPLIT_S = 1.0
IDLE_S = 8.0
"""The host stops once no data came for this long (the relay starts after it listens)."""
RECORDING_S = 1800.0
RATE = 300
"""30 minutes in 6 s (at 60x the test took twice as long, mostly the replay). What the host
cannot convert it drops and counts (a third to a half on the loaded 2-core machine, at 60x as at
this); the files hold the rest, once."""
STOPPED_S = 300.0
STOPPED_RATE = 20
DONE_S = 120.0
"""Every process ends within this on a loaded 2-core machine (the long replay takes 6 s)."""


def relay_command(bag: Path, port: int, rate: int) -> list[str]:
    return command("robot_relay.cli", "--robot", ROBOT, "--bag", str(bag), "--rate", str(rate),
                   "-e", f"tcp/127.0.0.1:{port}", *NO_SHM, "--wait-for-host", str(STARTUP_S))


def host_command(port: int, out: Path, *flags: str) -> list[str]:
    """The host saving to ``out``, with odometry trails of TRAIL points: ``rerun rrd verify``
    spent nearly all its time on the default's rows of 500 (10 s of 10 s for 1130 rows)."""
    config = out.parent / "host.yaml"
    config.write_text(f"topics:\n  /odom:\n    options: {{trail_length: {TRAIL}}}\n")
    return command("host_bridge.cli", "-l", f"tcp/127.0.0.1:{port}", *NO_SHM, "--no-rmw-zenoh",
                   "--robots", ROBOT, "--save", str(out), "--save-split", str(SPLIT_S),
                   "--config", str(config), *flags)


def statics(path: Path) -> set[str]:
    """The entities of the recording's static chunks in ``path`` (Rerun's properties aside)."""
    return {chunk.entity_path for chunk in RrdReader(path).store().stream()
            if chunk.is_static and chunk.entity_path != "/__properties"}


def saved_files(out: Path) -> list[Path]:
    """The files of a split ``--save out``, in order: out.rrd itself has become out_0.rrd."""
    files = sorted(out.parent.glob(f"{out.stem}_*{out.suffix}"), key=lambda p: int(p.stem.rsplit("_", 1)[1]))
    assert files == [split_path(out, i) for i in range(len(files))]
    assert not out.exists()
    return files


def check_saved(out: Path, summary: str) -> tuple[list[Path], dict[str, int], float]:
    """Every file passes Rerun's checks and holds the static data (model, /tf_static) logged
    before it; together they hold every /odom and /scan message the host's summary says it
    converted, once. The files, the rows of each topic and the seconds from the first row's
    receive_time to the last."""
    files = saved_files(out)
    verify(*files)
    counts = {}
    received: list[int] = []
    for topic in ("/odom", "/scan"):
        entity = f"/{ROBOT}{topic}"
        rows = [row for path in files for row in entity_rows(path, entity).get(entity, [])]
        stamps = sorted(row["ros_time"] for row in rows)
        assert len(set(stamps)) == len(stamps) == converted(summary, ROBOT, topic) > 0, topic
        counts[topic] = len(rows)
        received.extend(row["receive_time"] for row in rows)
    held = [statics(path) for path in files]  # each opens alone with the robot's static data
    assert all(before <= after for before, after in itertools.pairwise(held))
    assert {f"/{ROBOT}/tf_static/base_scan", f"/{ROBOT}/robot_model/base_link/visual_0"} <= held[-1]
    return files, counts, (max(received) - min(received)) / 1e9


def test_a_30_minute_recording_replayed_fast_is_split_into_files_rerun_accepts(
    tmp_path: Path, reliability: Record,
) -> None:
    traffic = Traffic(RECORDING_S, image_size=(0, 0))
    bag = write_traffic_bag(tmp_path / "traffic", traffic)
    out = tmp_path / "out.rrd"
    port = free_port()
    with running(host_command(port, out, "--until-idle", str(IDLE_S))) as host:
        lines = Lines(host)
        wait_listening(port, STARTUP_S, "the host")
        started = time.monotonic()
        with running(relay_command(bag, port, RATE)) as relay:
            assert relay.wait(timeout=DONE_S) == 0
        replay_s = time.monotonic() - started
        assert host.wait(timeout=DONE_S) == 0, lines.text
    assert "Traceback" not in lines.text
    files, counts, data_s = check_saved(out, lines.text)
    # A file ends SPLIT_S seconds after its first data. Less one: the data's receive times are
    # the robot's, and the host's lag behind them, which decides when it logs, changes over the run.
    assert len(files) >= max(2, data_s // SPLIT_S - 1)
    sent = {"/odom": len(traffic.odom()), "/scan": len(traffic.scan_indices())}
    assert sent == {"/odom": RECORDING_S * ODOM_HZ, "/scan": RECORDING_S * SCAN_HZ}
    reliability(
        "Saved files", f"live --save of a {RECORDING_S / 60:.0f}-minute recording (30 Hz /odom, "
        f"10 Hz /scan, latched model, /tf_static and map) replayed at {RATE}x by a relay into the "
        f"host (loopback), --save-split {SPLIT_S:g}",
        tried=f"1 recording, {sum(sent.values())} messages in {replay_s:.0f} s",
        survived=f"{len(files)} files, each passing `rerun rrd verify`, opening with "
                 "RrdReader(path).store() and holding the model and /tf_static; /odom "
                 f"{counts['/odom']}/{sent['/odom']} and /scan {counts['/scan']}/{sent['/scan']}, "
                 "every converted message once",
        lost=f"{sent['/odom'] - counts['/odom']} /odom and {sent['/scan'] - counts['/scan']} /scan "
             "(dropped by the host's queue when behind, counted in its summary)",
    )


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_live_save_stopped_by_a_signal_is_files_rerun_accepts(
    tmp_path: Path, reliability: Record, signum: int,
) -> None:
    """Stopped while a relay streams into it, after its first split: the file being written
    is closed with its footer too."""
    bag = write_traffic_bag(tmp_path / "traffic", Traffic(STOPPED_S, image_size=(0, 0)))
    out = tmp_path / "out.rrd"
    port = free_port()
    with running(host_command(port, out)) as host:
        lines = Lines(host)
        wait_listening(port, STARTUP_S, "the host")
        with running(relay_command(bag, port, STOPPED_RATE)) as relay:
            lines.wait_for(f"saved {split_path(out, 0)}; the recording goes on in", timeout=STARTUP_S)
            time.sleep(SPLIT_S / 2)  # mid-file
            assert relay.poll() is None  # data still flows
            took = stop_and_wait(host, signum)
    assert (host.returncode, "Traceback" in lines.text) == (0, False), lines.text
    assert took < STOP_WITHIN_S
    files, counts, _ = check_saved(out, lines.text)
    name = signal.Signals(signum).name
    reliability(
        "Saved files", f"live --save stopped by {name} mid-file while a relay streamed 30 Hz "
        f"/odom and 10 Hz /scan at {STOPPED_RATE}x into the host (loopback), --save-split {SPLIT_S:g}",
        tried=f"1 {name}",
        survived=f"exit 0 in {took:.1f} s; {len(files)} files, each passing `rerun rrd verify` "
                 f"and opening with RrdReader(path).store(); /odom {counts['/odom']} and /scan "
                 f"{counts['/scan']} rows, each converted message once",
        lost="0 converted messages (the rest of the replay was not sent)",
    )
