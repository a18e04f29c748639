"""A host whose output cannot keep up (issue 14): two robots on loopback, one ("flood")
replaying its odometry as fast as its relay can send, the other ("calm") at its real 30 Hz.

The host runs as ``python -m tests.integration.slow_host``: the real ``swanky-host`` with its
dispatcher slowed down for the flood robot only (SLOW_S per message),
as if its converters or its viewer were too slow for it: about ten times too slow (a relay sends
~1,400 messages a second here, the host takes 1 / SLOW_S); the ratio measured goes into the
table. Its per-robot queue holds QUEUE messages instead of 5,000, or the host would need 35 s at
exit to convert what it holds (a saved .rrd is complete). The host's memory must stay flat (its
per-robot queues are bounded), the messages it drops must be counted and shown, and the calm
robot must not notice.
"""

from __future__ import annotations

import time
from contextlib import ExitStack
from pathlib import Path

import pytest

from host_bridge.core.contract import TIMELINE_RECEIVE
from tests.integration.proc_sampler import Sampler
from tests.integration.procs import command, free_port, running
from tests.integration.robot_bags import Lines
from tests.integration.robot_traffic import Traffic, odom_index, write_traffic_bag
from tests.integration.test_bad_links import NO_SHM, arrival_order
from tests.reliability import Record
from tests.rrd import entity_rows

pytestmark = pytest.mark.integration

SLOW_S = 0.007
"""The flood robot's output time per message: at most 143 a second."""
QUEUE = 500
FLOOD_MESSAGES = 18_000
STARTUP_S = 90.0


def test_slow_output_drops_the_flooding_robots_oldest_and_spares_the_other(
    tmp_path: Path, reliability: Record,
) -> None:
    calm = Traffic(seconds=12.0, image_size=(0, 0), scans=False, latched=False)
    flood = Traffic(seconds=FLOOD_MESSAGES / 30, image_size=(0, 0), scans=False, latched=False)
    bags = {"calm": write_traffic_bag(tmp_path / "calm", calm),
            "flood": write_traffic_bag(tmp_path / "flood", flood)}
    port = free_port()
    out = tmp_path / "slow.rrd"
    endpoint = ("-e", f"tcp/127.0.0.1:{port}", *NO_SHM, "--wait-for-host", "60")
    with ExitStack() as stack:
        host = stack.enter_context(running(command(
            "tests.integration.slow_host", str(SLOW_S), "flood", str(QUEUE),
            "-l", f"tcp/127.0.0.1:{port}", *NO_SHM,
            "--save", str(out), "--until-idle", "4", "--duration", "180")))
        host_lines = Lines(host)
        sampler = Sampler(host.pid, period_s=0.1)
        relays = {
            robot: stack.enter_context(running(command(
                "robot_relay.cli", "--robot", robot, "--bag", str(bags[robot]),
                "--rate", "1" if robot == "calm" else "0", *endpoint)))
            for robot in ("calm", "flood")
        }
        relay_lines = {robot: Lines(proc) for robot, proc in relays.items()}
        relay_lines["flood"].wait_for("robot flood: 1 topics", timeout=STARTUP_S)
        started = time.monotonic()
        for robot, proc in relays.items():
            assert proc.wait(timeout=STARTUP_S) == 0, relay_lines[robot].text
            if robot == "flood":
                flooded = time.monotonic()
        assert host.wait(timeout=180) == 0, host_lines.text
        sampler.stop()
    rows = entity_rows(out)

    # The calm robot: every message, in order, on time.
    assert [odom_index(t) for t in arrival_order(out, "/calm/odom")] == list(calm.odom())
    calm_latency_ms = max(row["Scalars:scalars"][0] for row in rows["/_stats/calm/odom/latency_ms"])
    assert calm_latency_ms < 2000

    # The flood robot: the host kept what it could, dropped its oldest, said so.
    kept = arrival_order(out, "/flood/odom")
    assert 0 < len(kept) < FLOOD_MESSAGES
    assert kept == sorted(set(kept))
    dropped = FLOOD_MESSAGES - len(kept)
    assert f"[flood] /odom: {dropped} dropped (" in host_lines.text
    warning = ("[flood] /odom: the host converts this robot's messages slower than they arrive; "
               "dropping its oldest ones (counted in /_stats/flood/odom/host_drops")
    assert warning in host_lines.text
    warned = [row["TextLog:text"][0] for row in rows["/_swanky/warnings"]]
    assert [text for text in warned if "slower than they arrive" in text] == [
        f"{warning}, other robots unaffected) (further HostBehindErrors on this topic are "
        "counted, not shown)"
    ]
    # In Rerun: every one of them in /_stats/flood/odom/host_drops, none as a link drop.
    host_drops = {row[TIMELINE_RECEIVE]: row["Scalars:scalars"][0]
                  for row in rows["/_stats/flood/odom/host_drops"]}
    shown = sum(host_drops.values())
    assert shown == dropped
    # A closed period logs rate_hz too; the open one's drops are logged alone when the host stops
    # (all of them when the flood's kept messages all fall in its last second of receive time).
    closed_periods = {row[TIMELINE_RECEIVE] for row in rows.get("/_stats/flood/odom/rate_hz", [])}
    at_stop = sum(n for at, n in host_drops.items() if at not in closed_periods)
    link_drops = sum(row["Scalars:scalars"][0] for row in rows.get("/_stats/flood/odom/drops", []))
    assert link_drops == 0
    assert {row["Scalars:scalars"][0] for row in rows["/_stats/calm/odom/host_drops"]} == {0.0}
    flood_latency_ms = max((row["Scalars:scalars"][0]
                            for row in rows.get("/_stats/flood/odom/latency_ms", [])), default=0.0)
    sent_rate = FLOOD_MESSAGES / (flooded - started)

    # Flat memory: the queue is full within the first second; from then on the host's
    # resident memory must not grow with what keeps arriving.
    middle = started + (flooded - started) / 2
    first_half = sampler.peak_mb(started, middle)
    second_half = sampler.peak_mb(middle, flooded)
    assert second_half <= first_half + 30.0, (first_half, second_half)
    assert sampler.peak_mb() < 600.0

    reliability(
        "Slow consumer",
        "host output slower than one robot's data: 'flood' replays 18,000 odometry messages as "
        f"fast as its relay sends them, its messages take {SLOW_S * 1000:.0f} ms each on the "
        f"way out, its queue holds {QUEUE}; 'calm' sends 30 Hz odometry beside it (loopback)",
        tried=f"1 run: flood sent {sent_rate:.0f} msg/s, the host could take "
              f"{1 / SLOW_S:.0f}/s ({sent_rate * SLOW_S:.1f}x too slow)",
        survived=f"calm: {len(calm.odom())}/{len(calm.odom())} in order, latency at most "
                 f"{calm_latency_ms:.0f} ms; flood: {len(kept)} kept, in order (latency up to "
                 f"{flood_latency_ms / 1000:.1f} s in closed stats periods); host RSS {first_half:.0f} MB -> "
                 f"{second_half:.0f} MB (peak {sampler.peak_mb():.0f} MB)",
        lost=f"{dropped} flood messages, its oldest, counted in the host's drop summary and "
             "warned about once (stderr and /_swanky/warnings); "
             f"{shown:.0f}/{dropped} of them in /_stats/flood/odom/host_drops "
             f"({shown - at_stop:.0f} in closed periods, {at_stop:.0f} logged at stop), "
             f"{link_drops:.0f} as link drops; calm lost 0",
    )
