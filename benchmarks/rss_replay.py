"""Host memory over a 10-minute robot replay at 10x speed: does the host's RSS stay flat?

The demo's simulated robot (lidar, RGB-D camera with its cloud, IMU, odometry, TF, joint states,
ground-truth pose and walls, battery, rosout) is recorded as a rosbag2 of ``--minutes`` (10) with
the demo's own writer (``host_bridge.demo.bag.write_demo_bag``), then replayed by
``swanky-relay --bag --rate 10`` over loopback Zenoh into ``swanky-host --save`` (a real .rrd in
a temporary directory, deleted afterwards), both with their default settings otherwise.

The host's VmRSS (``/proc/<pid>/status``) is sampled every ``--interval`` seconds while the
relay replays; the replay's wall time (relay start to exit) is split into as many equal parts
as the bag has minutes, so each part is about one bag minute. Printed: the peak RSS of every
bag minute, the baseline (the second minute's peak, measured in the same run: the first holds
the host's start, which imports each converter when its type first comes) and the ratio of the
last minute's peak to it (flat: within 10 %), the host's high-water mark (VmHWM) and its exit,
and from the host's closing table how many messages it dropped on arrival. A host that converts
slower than 10x (a loaded machine) drops its oldest messages from a bounded per-robot queue
(``host_bridge/inputs/queues.py``); while that queue fills, RSS grows with it up to the bound, so
read the per-minute peaks with the drops: growth that levels off with drops is the backlog, growth
without drops or without end is a leak. The bag takes 30-45 s to simulate, the replay 60 s.
Run: ``.venv/bin/python benchmarks/rss_replay.py [--minutes 10] [--rate 10]``.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # tests/ for the loopback helpers

from host_bridge.demo.bag import write_demo_bag
from tests.integration.procs import command, free_port, listening, stop

ROOT = Path(__file__).resolve().parent.parent
BUDGET_SECONDS = 170
ROBOT = "bench"
FLAT = 1.10  # last-minute peak within 10 % of the second minute's
HOST_READY_S = 60.0
IDLE_S = 5.0  # the host stops once no data came for this long after the replay


def status_kib(pid: int, field: str) -> int | None:
    """A ``VmRSS``/``VmHWM`` line of /proc/<pid>/status in KiB; None once the process is gone."""
    try:
        lines = Path(f"/proc/{pid}/status").read_text().splitlines()
    except (FileNotFoundError, ProcessLookupError):
        return None
    for line in lines:
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return None


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=int, default=10, help="bag length (default %(default)s)")
    parser.add_argument("--rate", type=float, default=10.0, help="replay speed (default %(default)s)")
    parser.add_argument("--interval", type=float, default=0.5, help="seconds between RSS samples")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory(prefix="swanky-rss-") as tmp:
        started = time.perf_counter()
        bag = write_demo_bag(Path(tmp) / "demo", args.minutes * 60.0)
        size_mb = sum(f.stat().st_size for f in bag.rglob("*") if f.is_file()) / 1e6
        print(f"demo bag: {args.minutes} min, {size_mb:.0f} MB, written in "
              f"{time.perf_counter() - started:.1f} s", flush=True)
        port = free_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        host_log = Path(tmp) / "host.log"  # a file: a full pipe would block the host
        with host_log.open("wb") as log_file:  # the host keeps its own copy of the file
            host = subprocess.Popen(
                command("host_bridge.cli", "-l", endpoint, "--no-multicast-scouting", "--no-rmw-zenoh",
                        "--robots", ROBOT, "--save", str(Path(tmp) / "replay.rrd"),
                        "--until-idle", str(IDLE_S)),
                cwd=ROOT, stdout=subprocess.DEVNULL, stderr=log_file)
        relay: subprocess.Popen[bytes] | None = None
        try:
            deadline = time.monotonic() + HOST_READY_S
            while not listening(port):
                if host.poll() is not None or time.monotonic() > deadline:
                    print(f"the host did not listen on {endpoint} (exit {host.poll()})")
                    return 1
                time.sleep(0.2)
            relay = subprocess.Popen(
                command("robot_relay.cli", "--robot", ROBOT, "--bag", str(bag), "--rate",
                        str(args.rate), "-e", endpoint, "--no-multicast-scouting",
                        "--wait-for-host", str(HOST_READY_S)),
                cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            replay_started = time.monotonic()
            samples: list[tuple[float, int]] = []
            while relay.poll() is None:
                rss = status_kib(host.pid, "VmRSS")
                if rss is None:
                    break
                samples.append((time.monotonic() - replay_started, rss))
                time.sleep(args.interval)
            replay_s = time.monotonic() - replay_started
            high_water = status_kib(host.pid, "VmHWM")
            relay_exit = relay.wait(timeout=30)
            try:
                host_exit = host.wait(timeout=IDLE_S + 30)
            except subprocess.TimeoutExpired:
                host_exit = stop(host, wait_s=15.0)
        finally:
            if relay is not None:
                stop(relay, wait_s=15.0)
            stop(host, wait_s=15.0)
        errors = host_log.read_text(errors="replace")
        files = sorted(Path(tmp).glob("replay*.rrd"))
        sizes_mb = [f.stat().st_size / 1e6 for f in files]

    part = replay_s / args.minutes
    peaks = []
    for minute in range(args.minutes):
        in_minute = [rss for at, rss in samples if minute * part <= at < (minute + 1) * part]
        peaks.append(max(in_minute) if in_minute else 0)
    print(f"replay at {args.rate:g}x: {replay_s:.1f} s wall, {len(samples)} RSS samples of the "
          f"host every {args.interval:g} s; relay exit {relay_exit}, host exit {host_exit}")
    print(f"--save wrote {len(files)} file(s), MB: "
          + ", ".join(f"{size:.0f}" for size in sizes_mb))
    print("host peak RSS per bag minute (MB): "
          + ", ".join(f"{peak / 1024:.0f}" for peak in peaks))
    if not all(peaks):
        print("some bag minutes have no sample: the host stopped early")
        print(errors[-1500:])
        return 1
    # The host's closing table: "total  N topics  received converted dropped ...".
    total = re.search(r"^total\s+\d+ topics\s+(\d+)\s+(\d+)\s+(\d+)", errors, re.MULTILINE)
    # Its drop summary: "[robot] /topic: N dropped (why)", queue full or replaced by a newer one.
    queue_drops = sum(int(n) for n in re.findall(r"^\[.*\] \S+: (\d+) dropped \(", errors,
                                                  re.MULTILINE))
    if total is not None:
        print(f"host received {total[1]} messages, converted {total[2]}; {queue_drops} dropped on "
              "arrival because it fell behind (its per-robot queue full, or a heavy message "
              "replaced by a newer one: while that queue fills, RSS grows with it, up to its bound)")
    ratio = peaks[-1] / peaks[1]
    verdict = "flat" if ratio <= FLAT else "GROWING"
    print(f"baseline (second-minute peak) {peaks[1] / 1024:.0f} MB, last-minute peak "
          f"{peaks[-1] / 1024:.0f} MB: ratio last/second {ratio:.3f} (last/first: "
          f"{peaks[-1] / peaks[0]:.3f}); high-water mark {(high_water or 0) / 1024:.0f} MB; "
          f"target ratio <= {FLAT:.2f}: {verdict}", flush=True)
    return 0 if host_exit == 0 and relay_exit == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
