"""Soak: a relay replaying a robot's traffic in a loop at 10x speed into a host, for 30 minutes
(issue 14), sampling both processes' resident memory once a second.

The traffic is tests/integration/robot_traffic.py's bag (latched /tf_static, /robot_description
and /map; 30 Hz /odom, 10 Hz /scan, 15 Hz 160x120 rgb8 images: 10x that is 550 messages and
5.9 MB a second), looped by ``swanky-relay --bag --loop --rate 10`` on loopback into
``swanky-host --save soak.rrd`` in a temporary directory (deleted afterwards), which goes on in a
new file every ``--save-split`` seconds (default 120; Rerun holds a file's index of its chunks in
memory until the file closes, host_bridge/outputs/sink.py ``SavedFile``). Printed: each side's peak RSS
in the first and in the last window (5 minutes, or a third of a shorter run) and last / first,
the figure that says "flat" (1.00) or "growing" (target: the host's within 10 %); the host's
converted count from its closing summary; the files saved and ``rerun rrd verify`` of every one
(about 10 s of CPU a 2-minute file, most of it on the odometry trail's rows of 500 points).

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

from host_bridge.outputs.sink import split_path  # noqa: E402
from tests.integration.proc_sampler import Sampler  # noqa: E402
from tests.integration.procs import free_port, rerun_binary  # noqa: E402
from tests.integration.robot_traffic import Traffic, write_traffic_bag  # noqa: E402

OPT_IN = True
BUDGET_SECONDS = 2100
SPEED = 10
WINDOW_S = 300.0
BAG_SECONDS = 20.0
FLAT = 1.10


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


def saved_files(out: Path) -> list[Path]:
    """``out`` if the host never split it, else its files in order."""
    if out.exists():
        return [out]
    files: list[Path] = []
    while split_path(out, len(files)).exists():
        files.append(split_path(out, len(files)))
    return files


def check_files(files: list[Path]) -> bool:
    """Print what ``rerun rrd verify`` says of the saved files; True if it takes them all."""
    started = time.monotonic()
    verify = subprocess.run([str(rerun_binary()), "rrd", "verify", *map(str, files)],
                            capture_output=True, text=True, check=False)
    size_mb = sum(path.stat().st_size for path in files) / 1e6
    print(f"host saved {len(files)} files ({size_mb:.0f} MB); rerun rrd verify of all: "
          f"{'ok' if verify.returncode == 0 else 'FAILED'} in {time.monotonic() - started:.0f} s")
    if verify.returncode != 0:
        print(verify.stdout[-2000:] + verify.stderr[-2000:])
    return verify.returncode == 0


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
        out = Path(tmp) / "soak.rrd"
        host = start("host_bridge.cli", "-l", endpoint, *zenoh, "--save", str(out))
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
        files_ok = check_files(saved_files(out))
    print(f"soak: {args.minutes:g} min, bag looped at {SPEED}x, windows of {window / 60:.1f} min; "
          f"host converted {converted_total(host_err)} messages")
    print(f"{'process':<8} {'first window peak MB':>21} {'last window peak MB':>20} "
          f"{'last/first':>10} {'CPU %':>6}")
    ratios = {}
    for name, sampler in samplers.items():
        first = sampler.peak_mb(began, began + window)
        last = sampler.peak_mb(ended - window, ended)
        cpu = sampler.cpu_percent(began, ended)
        ratios[name] = last / first if first else 0
        print(f"{name:<8} {first:>21.1f} {last:>20.1f} {ratios[name]:>10.2f} {cpu:>6.0f}")
    verdict = "flat" if ratios["host"] <= FLAT else "GROWING"
    print(f"host last/first {ratios['host']:.2f} (target <= {FLAT:.2f}): {verdict}")
    if "Traceback" in relay_err + host_err:
        print(relay_err[-2000:] + host_err[-2000:])
        return 1
    return 0 if files_ok else 1


if __name__ == "__main__":
    sys.exit(main())
