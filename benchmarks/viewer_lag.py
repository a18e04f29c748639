"""How far behind a real viewer is with a fleet of demo robots (issue 24, target: under 1 s with
10 robots): ``swanky-host --demo --robots N --rerun-addr URL`` into Rerun's native viewer with
software GL, against the same host in the same run with its pacing held.

- baseline: host_bridge.pipeline.thinning.BEHIND_S set to infinity before the host starts: the viewers'
  stream flushed every 0.2 s, every heavy message sent (what the host did before issue 24, but
  for its pacer's waits, which held the robots back);
- paced: the host as shipped (thinning.py: heavy topics latest-only at an adapted interval,
  longer batches for a viewer slow to take them in).

The viewer: ``rerun --headless`` (the native viewer drawing offscreen, Mesa's lavapipe on a
machine without a GPU) by default, or ``--viewer xvfb``: the native viewer in a window of an
Xvfb server this script starts (1280x800), drawing with llvmpipe too. Each phase gets a fresh
viewer and a fresh host, which writes the demo's bags first (a minute and more on a loaded
2-core machine; not measured).

Measured once every robot has joined and WARM_UP_S more have passed, until the host stops:

- the host's own ``/_stats/host/viewer_lag_ms`` (its ``-v`` log line each second: the most the
  viewer was behind in that second, a flush's round trip into the viewer plus the period its
  rows waited; viewer_lag.py);
- independently, the viewer's answer time: this script asks the viewer its state
  (``rerun.experimental.ViewerClient.get_state``) every 0.5 s; the request reaches it behind
  whatever it has not taken in yet, so the answer time is its own backlog plus a frame.

Printed per phase: median, p95 and max of each, the share of the host's seconds under 1 s, the
heavy messages the viewer was not sent; then the ratio paced / baseline of the host's p95 and
the verdict against the target. Opt-in (``python -m benchmarks viewer_lag``): two phases of a
10-robot demo take 6-9 minutes here.

    .venv/bin/python benchmarks/viewer_lag.py [--robots 10] [--seconds 60] [--viewer headless]
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.integration.procs import free_port, listening, rerun_binary  # noqa: E402

OPT_IN = True
BUDGET_SECONDS = 900
WARM_UP_S = 15.0
"""After the last robot joined: the viewer lays out the robots' views, the pace settles."""
JOIN_TIMEOUT_S = 300.0
ASK_EVERY_S = 0.5
TARGET_S = 1.0
XVFB_SCREEN = "1280x800x24"
HELD = "import host_bridge.pipeline.thinning as t; t.BEHIND_S = float('inf'); "
HOST = "import sys; from host_bridge.cli import main; sys.exit(main(sys.argv[1:]))"
LAG_LINE = re.compile(r"viewer lag: (\d+) ms at most in the last second")
THINNED_LINE = re.compile(r"^\[(\S+)\] (\S+): (\d+)$", re.M)


@dataclass(frozen=True, slots=True)
class Phase:
    name: str
    host_lag_ms: list[int]
    answers_s: list[float]
    not_sent: int


def figures(values: Sequence[float]) -> str:
    if not values:
        return "none"
    ordered = sorted(values)
    p95 = ordered[min(len(ordered) - 1, round(0.95 * (len(ordered) - 1)))]
    return f"median {statistics.median(ordered):.2f} p95 {p95:.2f} max {ordered[-1]:.2f}"


def p95(values: Sequence[float]) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(0.95 * (len(ordered) - 1)))]


@contextmanager
def xvfb() -> Iterator[str]:
    """An Xvfb server of its own: its DISPLAY."""
    display = f":{50 + os.getpid() % 40}"
    server = subprocess.Popen(["Xvfb", display, "-screen", "0", XVFB_SCREEN],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        time.sleep(1.0)
        if server.poll() is not None:
            sys.exit(f"Xvfb {display} did not start (apt-get install xvfb)")
        yield display
    finally:
        server.terminate()
        server.wait(timeout=10)


@contextmanager
def viewer(kind: str, display: str | None) -> Iterator[str]:
    """A native viewer with software GL, killed on leaving: its URL."""
    port = free_port()
    args = [str(rerun_binary()), "--port", str(port)]
    env = dict(os.environ, XDG_RUNTIME_DIR=tempfile.gettempdir())
    if kind == "headless":
        args.append("--headless")
    else:
        assert display is not None
        env["DISPLAY"] = display
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    try:
        deadline = time.monotonic() + 60
        while not listening(port):
            if proc.poll() is not None or time.monotonic() > deadline:
                sys.exit(f"rerun {' '.join(args[1:])} did not start (a Vulkan adapter: apt-get "
                         "install mesa-vulkan-drivers)")
            time.sleep(0.2)
        yield f"rerun+http://127.0.0.1:{port}/proxy"
    finally:
        proc.kill()
        proc.wait(timeout=10)


def ask_until(url: str, stop: threading.Event, answers: list[float]) -> None:
    """The viewer's answer time, every ASK_EVERY_S until ``stop``."""
    from rerun.experimental import ViewerClient

    client = ViewerClient(url)
    while not stop.wait(ASK_EVERY_S):
        started = time.monotonic()
        try:
            client.get_state()
        except TimeoutError:
            pass  # 15 s and more behind: counted as what it waited
        except (ConnectionError, RuntimeError):
            return
        answers.append(time.monotonic() - started)


def run_phase(name: str, held: bool, args: argparse.Namespace, display: str | None, log: Path) -> Phase:
    with viewer(args.viewer, display) as url, log.open("w") as stderr:
        host = subprocess.Popen(
            [sys.executable, "-c", (HELD if held else "") + HOST, "-v", "--demo", "--robots",
             str(args.robots), "--rerun-addr", url, "--duration", str(args.seconds)],
            stdout=subprocess.DEVNULL, stderr=stderr, cwd=ROOT, start_new_session=True)
        try:
            deadline = time.monotonic() + JOIN_TIMEOUT_S
            while log.read_text().count(" joined (") < args.robots:
                if host.poll() is not None or time.monotonic() > deadline:
                    sys.exit(f"{name}: the robots did not all join; see {log}")
                time.sleep(0.5)
            time.sleep(WARM_UP_S)
            skipped = len(LAG_LINE.findall(log.read_text()))
            stop, answers = threading.Event(), list[float]()
            asking = threading.Thread(target=ask_until, args=(url, stop, answers), daemon=True)
            asking.start()
            host.wait(timeout=args.seconds + JOIN_TIMEOUT_S)
            stop.set()
        finally:
            if host.poll() is None:
                os.killpg(host.pid, signal.SIGKILL)
                host.wait()
    text = log.read_text()
    return Phase(name, [int(ms) for ms in LAG_LINE.findall(text)[skipped:]], answers,
                 sum(int(count) for _, _, count in THINNED_LINE.findall(text)))


def report(phase: Phase) -> None:
    lag = phase.host_lag_ms
    under = sum(ms < TARGET_S * 1000 for ms in lag) / len(lag) if lag else 0.0
    print(f"{phase.name}: host viewer_lag_ms over {len(lag)} s: {figures([ms / 1000 for ms in lag])} s, "
          f"{under:.0%} of seconds under {TARGET_S:.0f} s; viewer answers ({len(phase.answers_s)}): "
          f"{figures(phase.answers_s)} s; heavy messages not sent to it: {phase.not_sent}", flush=True)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--robots", type=int, default=10)
    parser.add_argument("--seconds", type=float, default=60.0, help="each host's --duration")
    parser.add_argument("--viewer", choices=("headless", "xvfb"), default="headless")
    parser.add_argument("--keep", type=Path, help="keep the hosts' logs in this directory")
    args = parser.parse_args(argv)
    with ExitStack() as stack:
        logs = args.keep or Path(stack.enter_context(tempfile.TemporaryDirectory()))
        logs.mkdir(parents=True, exist_ok=True)
        display = stack.enter_context(xvfb()) if args.viewer == "xvfb" else None
        print(f"{args.robots} demo robots into rerun ({args.viewer}, software GL), "
              f"{args.seconds:.0f} s each, measured after {WARM_UP_S:.0f} s", flush=True)
        base = run_phase("baseline (pace held)", True, args, display, logs / "baseline.log")
        report(base)
        paced = run_phase("paced", False, args, display, logs / "paced.log")
        report(paced)
    if not base.host_lag_ms or not paced.host_lag_ms:
        print("no lag measured")
        return 1
    ratio = p95(paced.host_lag_ms) / p95(base.host_lag_ms)
    verdict = "met" if p95(paced.host_lag_ms) < TARGET_S * 1000 else "missed"
    print(f"host viewer_lag_ms p95 paced / baseline: {ratio:.2f}; target p95 under {TARGET_S:.0f} s "
          f"with {args.robots} robots: {verdict} ({p95(paced.host_lag_ms) / 1000:.2f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
