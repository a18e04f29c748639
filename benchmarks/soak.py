"""Soak: a relay replaying a robot's traffic in a loop at 10x speed into a host, for 30 minutes
(issue 14), sampling both processes' resident memory once a second.

The traffic is tests/integration/robot_traffic.py's bag (latched /tf_static, /robot_description
and /map; 30 Hz /odom, 10 Hz /scan, 15 Hz 160x120 rgb8 images: 10x that is 550 messages and
5.9 MB a second), looped by ``swanky-relay --bag --loop --rate 10`` on loopback into
``swanky-host --save /dev/null`` (everything is converted and encoded; nothing fills the disk).
Printed: each side's peak RSS in the first and in the last window (5 minutes, or a third of a
shorter run) and last / first, the figure that says "flat" (1.00) or "growing"; the host's
converted count from its closing summary.

Opt-in (``OPT_IN``): 30 minutes is more than ``python -m benchmarks`` spends on its whole run.
Run it by name, with a deadline that fits it: ``.venv/bin/python -m benchmarks soak --deadline
2200``, or ``.venv/bin/python benchmarks/soak.py --minutes 3``.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # run as a script: the project's packages and tests' helpers
    sys.path.insert(0, str(ROOT))

from tests.integration.proc_sampler import Sampler  # noqa: E402
from tests.integration.procs import free_port  # noqa: E402
from tests.integration.robot_traffic import Traffic, write_traffic_bag  # noqa: E402

OPT_IN = True
BUDGET_SECONDS = 2100
SPEED = 10
WINDOW_S = 300.0
BAG_SECONDS = 20.0


def start(module: str, *args: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen([sys.executable, "-m", module, *args], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})


def stop(proc: subprocess.Popen[bytes]) -> str:
    """SIGTERM, then its stderr (the host's summary)."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        _, err = proc.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate(timeout=30)
    return err.decode(errors="replace")


def converted_total(summary: str) -> str:
    for line in summary.splitlines():
        if line.startswith("total "):
            return line.split()[4]
    return "?"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=float, default=30.0, help="soak length (default 30)")
    args = parser.parse_args()
    seconds = args.minutes * 60
    window = min(WINDOW_S, seconds / 3)
    with tempfile.TemporaryDirectory() as tmp:
        bag = write_traffic_bag(Path(tmp) / "traffic", Traffic(BAG_SECONDS, image_size=(160, 120)))
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        zenoh = ("--no-multicast-scouting",)
        host = start("host_bridge.cli", "-l", endpoint, *zenoh, "--save", os.devnull)
        relay = start("robot_relay.cli", "--robot", "soak", "--bag", str(bag), "--loop", "--rate",
                      str(SPEED), "-e", endpoint, *zenoh, "--wait-for-host", "60")
        samplers = {"relay": Sampler(relay.pid, 1.0), "host": Sampler(host.pid, 1.0)}
        began = time.monotonic()
        try:
            while time.monotonic() - began < seconds:
                if relay.poll() is not None or host.poll() is not None:
                    print(f"a process ended early: relay {relay.poll()}, host {host.poll()}")
                    return 1
                time.sleep(1.0)
        finally:
            ended = time.monotonic()
            relay_err = stop(relay)
            host_err = stop(host)
    print(f"soak: {args.minutes:g} min, bag looped at {SPEED}x, windows of {window / 60:.1f} min; "
          f"host converted {converted_total(host_err)} messages")
    print(f"{'process':<8} {'first window peak MB':>21} {'last window peak MB':>20} "
          f"{'last/first':>10} {'CPU %':>6}")
    for name, sampler in samplers.items():
        first = sampler.peak_mb(began, began + window)
        last = sampler.peak_mb(ended - window, ended)
        cpu = sampler.cpu_percent(began, ended)
        print(f"{name:<8} {first:>21.1f} {last:>20.1f} {last / first if first else 0:>10.2f} "
              f"{cpu:>6.0f}")
    if "Traceback" in relay_err + host_err:
        print(relay_err[-2000:] + host_err[-2000:])
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
