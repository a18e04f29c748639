"""Fleet capacity (issue 24): 25 demo robots' live traffic into one host on this machine, against
one robot's through the same pipeline, measured in the same run.

Each robot is the demo's simulated swanky_bot (``host_bridge/demo``: Imu, TF, odometry, joint
states, ground-truth pose and a step-time series at 30 Hz, LaserScan 360 rays at 5 Hz, a 160x120
RGB-D camera at 5 Hz: image, depth image, depth cloud and camera_info, battery at 1 Hz, rosout,
and the latched /tf_static, robot description and walls), its bag written by the demo's own
writer and replayed (looping, real time) by the demo's own relay (``demo.run.relay_bag``). The
robots' relays run in one process of their own, as they would on the robots: the host's figures
are the host's alone (the relays still share this machine's cores; the messages each robot
delivered, against the baseline's, show whether they kept real time).

The host is the live pipeline as ``swanky-host`` builds it (``app.open_input``: Zenoh, the
per-robot queues, ``/_stats``; the Dispatcher; a Rerun sink saving to /dev/null, so heavy topics
are converted on the robots' heavy threads in this process: the harder case for the small
topics, which share its GIL), listening on a loopback endpoint the relays connect to;
``--slam`` adds the demo's host-side SLAM per robot. Each phase, the baseline (one robot) then
the fleet, runs in a process of its own (its CPU time and peak RSS are its own): it waits until
every robot delivered, warms up ``--warmup`` s, then measures ``--seconds``:

- small-topic latency per robot: the relay's receive clock (stamped when it publishes) to the
  dispatcher having converted the message's run (each batch's runs one topic at a time, as the
  dispatcher does; as ``live_capacity.py``), p50 and p99 of each robot;
- drops by kind, small topics against heavy ones (the type table's lanes): messages the host's
  queues dropped (a full queue; a heavy message replaced by a newer one while the host is behind,
  ``inputs/queues.py``) and messages lost between relay and host (wire sequence gaps);
- heavy messages converted per robot: the fewest and the most over the robots (fair thinning
  keeps them close, no robot starved);
- host CPU: the phase's process time over the window's wall time (cores), per robot, and per
  message converted (the turns of ``inputs/queues.py`` make a busy host convert longer runs,
  which cost less per message);
- host peak RSS: the phase process's VmHWM.

Targets: no small-topic message dropped (TF, odometry, joints, IMU, logs, latched topics: the
issue's "no drop of non-sensor data"); every robot's small-topic p99 <= 100 ms (three periods of
its 30 Hz topics, half the time between two of its scans: the viewer's frames and TF lookups
stay current); every robot converts heavy messages.

The bags took 45-52 s to simulate on this shared 2-core machine (load 8 to 13), each phase
30-45 s; a phase's process ends right after its window, without draining what its queues hold.

    .venv/bin/python benchmarks/fleet.py [--robots 25] [--seconds 15] [--warmup 5] [--slam]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NoReturn

import numpy as np
import numpy.typing as npt

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from live_capacity import received_ns  # noqa: E402  (beside this script)

from host_bridge.app import HostOptions, open_input  # noqa: E402
from host_bridge.core.destinations import SinkOptions  # noqa: E402
from host_bridge.demo.run import (  # noqa: E402
    DEMO_ROBOT,
    demo_robot_names,
    free_loopback_port,
    relay_bag,
    write_bags,
)
from host_bridge.inputs.base import InputItem, InputProblem, MessageRun  # noqa: E402
from host_bridge.inputs.live import LiveInput  # noqa: E402
from host_bridge.inputs.queues import HeavyTopicsThinnedError  # noqa: E402
from host_bridge.outputs.sink import RerunSink  # noqa: E402
from host_bridge.pipeline.dispatch import Dispatcher  # noqa: E402
from host_bridge.table.registry import Lane, Registry, default_registry  # noqa: E402
from robot_relay.session import ZenohOptions  # noqa: E402
from robot_relay.wire import RawMessage  # noqa: E402

# python -m benchmarks gives each script this many seconds at most.
BUDGET_SECONDS = 180

P99_TARGET_MS = 100.0
BAG_MARGIN_S = 5.0  # the bags loop; a little more than the phase needs spares the loop's jump
JOIN_TIMEOUT_S = 90.0  # every robot delivering: a loaded 2-core machine starts 25 relays slowly
KINDS = ("small", "heavy")


@dataclass(frozen=True, slots=True)
class RobotFigures:
    """One robot over the measured window."""

    robot: str
    small_p50_ms: float
    small_p99_ms: float
    small_timed: int
    arrived: dict[str, int]
    """Messages that reached the host, per kind: converted or dropped in its queues."""
    converted: dict[str, int]
    queue_drops: dict[str, int]
    link_drops: dict[str, int]


@dataclass(frozen=True, slots=True)
class Phase:
    robots: int
    seconds: float
    host_cpu_s: float
    relays_cpu_s: float
    peak_rss_mb: float
    small_pooled_p50_ms: float
    small_pooled_p99_ms: float
    small_entered_p50_ms: float
    small_entered_p99_ms: float
    small_per_batch: float
    """Small messages a robot's thread handed over per batch, on average."""
    figures: list[RobotFigures]
    thinned_said: int


class FleetTiming:
    """The dispatcher's ``take`` one topic's run at a time, timing each small message from its
    publication by the relay to its run converted, per robot."""

    def __init__(self, dispatcher: Dispatcher, registry: Registry) -> None:
        self.dispatcher = dispatcher
        self.registry = registry
        self.small_ms: dict[str, list[npt.NDArray[np.float64]]] = {}
        self.entered_ms: list[npt.NDArray[np.float64]] = []
        self.small_batches = 0
        """Batches of small messages handed over while measuring (their runs in small_ms)."""
        self.seen: set[str] = set()
        self.thinned_said = 0
        self.measuring = False
        self._lock = threading.Lock()

    def __call__(self, batch: Sequence[InputItem]) -> None:
        runs: dict[str, list[InputItem]] = {}
        entered_ns = time.time_ns()
        timed_small = False
        for item in batch:
            if isinstance(item, InputProblem) and isinstance(item.error, HeavyTopicsThinnedError):
                self.thinned_said += 1
            runs.setdefault(getattr(item, "topic", ""), []).append(item)
        for run in runs.values():
            self.dispatcher.take(run)
            converted_ns = time.time_ns()
            first = next((i for i in run if isinstance(i, RawMessage | MessageRun)), None)
            if first is None:
                continue
            if first.robot not in self.seen:
                with self._lock:
                    self.seen.add(first.robot)
            if not self.measuring or self.registry.row(first.msgtype, first.topic).lane is not Lane.SMALL:
                continue
            received = received_ns(run)
            with self._lock:
                self.small_batches += not timed_small
                timed_small = True
                self.small_ms.setdefault(first.robot, []).append((converted_ns - received) / 1e6)
                self.entered_ms.append((entered_ns - received) / 1e6)

    def start_measuring(self) -> None:
        with self._lock:
            self.small_ms.clear()
            self.entered_ms.clear()
            self.small_batches = 0
            self.measuring = True

    def stop_measuring(self) -> tuple[dict[str, npt.NDArray[np.float64]], npt.NDArray[np.float64]]:
        """Per robot, its small messages' publish -> converted; pooled, publish -> the worker
        handing their batch to the dispatcher (what waiting in Zenoh and the queues costs)."""
        with self._lock:
            self.measuring = False
            return ({robot: np.concatenate(parts) for robot, parts in self.small_ms.items()},
                    np.concatenate(self.entered_ms or [np.array([np.nan])]))


def process_cpu_s(pid: int) -> float:
    """utime + stime of process ``pid`` (/proc/<pid>/stat), in seconds."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def peak_rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


Counts = dict[tuple[str, str], tuple[int, int, int]]
"""(robot, topic) -> (received by the dispatcher, converted, sequence gaps)."""


def counter_snapshot(dispatcher: Dispatcher) -> tuple[Counts, dict[tuple[str, str], str]]:
    counts, types = {}, {}
    for key, counters in list(dispatcher.counters.items()):
        counts[key] = (counters.received, counters.converted, counters.sequence_gaps)
        types[key] = counters.msgtype
    return counts, types


def robot_figures(
    robot: str, small_ms: npt.NDArray[np.float64] | None, *, kinds: dict[tuple[str, str], str],
    before: Counts, after: Counts, drops_before: dict[tuple[str, str], int],
    drops_after: dict[tuple[str, str], int],
) -> RobotFigures:
    arrived, converted, queue_drops, link_drops = (dict.fromkeys(KINDS, 0) for _ in range(4))
    for key, (received, done, gaps) in after.items():
        if key[0] != robot:
            continue
        kind = kinds[key]
        received0, done0, gaps0 = before.get(key, (0, 0, 0))
        dropped = drops_after.get(key, 0) - drops_before.get(key, 0)
        arrived[kind] += received - received0 + dropped
        converted[kind] += done - done0
        queue_drops[kind] += dropped
        link_drops[kind] += gaps - gaps0
    timed = small_ms if small_ms is not None and len(small_ms) else np.array([np.nan])
    return RobotFigures(
        robot, float(np.percentile(timed, 50)), float(np.percentile(timed, 99)),
        0 if small_ms is None else len(small_ms), arrived, converted, queue_drops, link_drops)


def start_relays(robots: list[str], bags: Path, endpoint: str) -> subprocess.Popen[str]:
    """The relays' process; what it says goes to ``relays.log`` beside the bags (a pipe nobody
    reads while the phase runs could fill and stop it)."""
    with (bags / "relays.log").open("a") as log:
        return subprocess.Popen(
            [sys.executable, __file__, "--relay-fleet", endpoint, "--bags", str(bags),
             "--robots", str(len(robots))],
            stdout=subprocess.DEVNULL, stderr=log, text=True)


def stop_relays(relays: subprocess.Popen[str]) -> None:
    if relays.poll() is None:
        relays.send_signal(signal.SIGTERM)
    try:
        relays.wait(timeout=30)
    except subprocess.TimeoutExpired:
        relays.kill()
        relays.wait(timeout=10)


def run_phase(
    count: int, bags: Path, *, warmup: float, seconds: float, slam: bool,
    publish: Callable[[Phase], None],
) -> None:
    """One host, ``count`` robots' relays (another process) into it; the figures of the
    ``seconds`` after every robot delivered and ``warmup`` passed go to ``publish`` once the
    relays have stopped, before the host drains its queues (seconds of backlog when it does not
    keep up: nothing after the window is measured)."""
    robots = demo_robot_names(str(count))
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    registry = default_registry()
    with ExitStack() as closing:
        sink = RerunSink(SinkOptions(save=Path("/dev/null")))
        closing.callback(sink.close)
        dispatcher = Dispatcher(sink, registry=registry)
        closing.callback(dispatcher.close)
        if slam:
            from host_bridge.slam.feeder import SlamTap
            from host_bridge.table.config import HostConfig

            config = HostConfig.builtin(registry)
            slam_tap = SlamTap(dispatcher, lambda robot: config.slam_settings(robot, True),
                               lossless=False)
            closing.callback(slam_tap.close)
            dispatcher.add_tap(slam_tap)
        options = HostOptions(zenoh=ZenohOptions(listen=(endpoint,), multicast_scouting=False),
                              robots=f"{DEMO_ROBOT}$*", rmw_zenoh=False)
        live = open_input(options, dispatcher, demo=None, robot_files=None,
                          stop=threading.Event(), closing=closing)
        assert isinstance(live, LiveInput)
        timing = FleetTiming(dispatcher, registry)
        live.start(timing)
        relays = start_relays(robots, bags, endpoint)
        closing.callback(stop_relays, relays)
        deadline = time.monotonic() + JOIN_TIMEOUT_S
        while len(timing.seen) < count:
            if relays.poll() is not None or time.monotonic() > deadline:
                msg = (f"{len(timing.seen)} of {count} robots delivered within {JOIN_TIMEOUT_S:.0f} s"
                       f"; relays' process: {relays.poll()}, said: "
                       f"{(bags / 'relays.log').read_text()[-2000:]}")
                raise RuntimeError(msg)
            time.sleep(0.1)
        time.sleep(warmup)
        counts_before, _ = counter_snapshot(dispatcher)
        drops_before = live.queues.dropped
        relays_before = process_cpu_s(relays.pid)
        timing.start_measuring()
        cpu_before, wall_before = time.process_time(), time.perf_counter()
        time.sleep(seconds)
        small_ms, entered_ms = timing.stop_measuring()
        host_cpu = time.process_time() - cpu_before
        wall = time.perf_counter() - wall_before
        relays_cpu = process_cpu_s(relays.pid) - relays_before
        counts_after, types = counter_snapshot(dispatcher)
        drops_after = live.queues.dropped
        stop_relays(relays)
        kinds = {key: "small" if registry.row(msgtype, key[1]).lane is Lane.SMALL else "heavy"
                 for key, msgtype in types.items()}
        pooled = np.concatenate(list(small_ms.values())) if small_ms else np.array([np.nan])
        publish(Phase(
            count, wall, host_cpu, relays_cpu, peak_rss_mb(),
            float(np.percentile(pooled, 50)), float(np.percentile(pooled, 99)),
            float(np.percentile(entered_ms, 50)), float(np.percentile(entered_ms, 99)),
            len(pooled) / max(timing.small_batches, 1),
            [robot_figures(robot, small_ms.get(robot), kinds=kinds, before=counts_before,
                           after=counts_after, drops_before=drops_before, drops_after=drops_after)
             for robot in robots],
            timing.thinned_said))


def publish_and_exit(phase: Phase) -> NoReturn:
    """The phase's figures to the parent (stdout), then this process ends at once."""
    print(json.dumps(asdict(phase)), flush=True)
    os._exit(0)


def relay_fleet(endpoint: str, bags: Path, count: int) -> int:
    """The robots' side: one demo relay per robot, threads of this process, until SIGTERM."""
    stop, failed = threading.Event(), threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    relays = [threading.Thread(target=relay_bag, args=(bags / robot, robot, endpoint, stop, failed),
                               name=f"relay-{robot}", daemon=True)
              for robot in demo_robot_names(str(count))]
    for relay in relays:
        relay.start()
    while not stop.wait(0.2):
        if failed.is_set():
            return 1
    for relay in relays:
        relay.join(timeout=5.0)
    return 0


def measured_phase(count: int, bags: Path, args: argparse.Namespace) -> Phase:
    """``count`` robots' phase in a process of its own."""
    command = [sys.executable, __file__, "--phase", str(count), "--bags", str(bags),
               "--seconds", str(args.seconds), "--warmup", str(args.warmup)]
    if args.slam:
        command.append("--slam")
    done = subprocess.run(command, capture_output=True, text=True, check=False,
                          timeout=BUDGET_SECONDS)
    if done.returncode != 0:
        msg = f"the {count}-robot phase failed ({done.returncode}): {done.stderr[-3000:]}"
        raise RuntimeError(msg)
    found = json.loads(done.stdout.strip().splitlines()[-1])
    found["figures"] = [RobotFigures(**figures) for figures in found["figures"]]
    return Phase(**found)


def per_second(phase: Phase, kind: str, what: str) -> float:
    """Messages of ``kind`` per robot and second: ``what`` is a RobotFigures count field."""
    counts: list[dict[str, int]] = [getattr(f, what) for f in phase.figures]
    return sum(count[kind] for count in counts) / phase.seconds / phase.robots


def cpu_per_message_ms(phase: Phase) -> float:
    converted = sum(sum(f.converted.values()) for f in phase.figures)
    return phase.host_cpu_s / max(converted, 1) * 1e3


def report(base: Phase, fleet: Phase) -> None:
    """Print the figures, each target's verdict with them."""
    for phase in (base, fleet):
        name = "baseline" if phase is base else "fleet"
        print(f"{name}, {phase.robots} robot{'s' if phase.robots > 1 else ''}, {phase.seconds:.1f} s: "
              f"arrived per robot {per_second(phase, 'small', 'arrived'):.1f} small + "
              f"{per_second(phase, 'heavy', 'arrived'):.1f} heavy msg/s; "
              f"host CPU {phase.host_cpu_s / phase.seconds:.2f} cores "
              f"({phase.host_cpu_s / phase.seconds / phase.robots * 100:.1f} % of a core per robot, "
              f"{cpu_per_message_ms(phase):.3f} ms per message converted, "
              f"{phase.small_per_batch:.1f} small messages per batch), "
              f"relays' process {phase.relays_cpu_s / phase.seconds:.2f} cores; "
              f"host peak RSS {phase.peak_rss_mb:.0f} MB", flush=True)
    print(f"  {'robot':<8}{'small/s':>8}{'p50 ms':>8}{'p99 ms':>8}{'small drops':>12}"
          f"{'heavy/s':>8}{'converted':>10}{'replaced':>9}{'link gaps':>10}")
    for f in fleet.figures:
        print(f"  {f.robot:<8}{f.arrived['small'] / fleet.seconds:>8.1f}{f.small_p50_ms:>8.2f}"
              f"{f.small_p99_ms:>8.2f}{f.queue_drops['small']:>12}"
              f"{f.arrived['heavy'] / fleet.seconds:>8.1f}{f.converted['heavy']:>10}"
              f"{f.queue_drops['heavy']:>9}{sum(f.link_drops.values()):>10}")
    kept = per_second(fleet, "small", "arrived") / per_second(base, "small", "arrived")
    print(f"small messages arrived per robot per second, fleet / baseline: {kept:.2f} "
          "(below 1: the relays' process, on the same cores, fell behind real time)")
    worst = max(fleet.figures, key=lambda f: f.small_p99_ms)
    base_p99 = base.figures[0].small_p99_ms
    p99_met = worst.small_p99_ms <= P99_TARGET_MS
    print(f"small topics publish -> converted, p50 / p99 ms: baseline {base.small_pooled_p50_ms:.2f} / "
          f"{base_p99:.2f}; fleet pooled {fleet.small_pooled_p50_ms:.2f} / "
          f"{fleet.small_pooled_p99_ms:.2f}, worst robot ({worst.robot}) p99 {worst.small_p99_ms:.2f}; "
          f"ratio worst fleet p99 / baseline p99 {worst.small_p99_ms / base_p99:.1f} "
          f"(target every robot's p99 <= {P99_TARGET_MS:g} ms: {'met' if p99_met else 'MISSED'}); "
          f"of which publish -> pipeline entry: baseline {base.small_entered_p50_ms:.2f} / "
          f"{base.small_entered_p99_ms:.2f}, fleet {fleet.small_entered_p50_ms:.2f} / "
          f"{fleet.small_entered_p99_ms:.2f}")
    small_lost = sum(f.queue_drops["small"] + f.link_drops["small"] for f in fleet.figures)
    heavy_replaced = sum(f.queue_drops["heavy"] for f in fleet.figures)
    heavy_lost = sum(f.link_drops["heavy"] for f in fleet.figures)
    print(f"drops in the fleet: small {small_lost} (target 0: {'met' if not small_lost else 'MISSED'}); "
          f"heavy {heavy_replaced} replaced by newer ones in the host's queues "
          f"(baseline {base.figures[0].queue_drops['heavy']}), {heavy_lost} lost on the link; "
          f"the host said it thins heavy topics {fleet.thinned_said} time(s)")
    heavy = sorted(f.converted["heavy"] for f in fleet.figures)
    arrived = sum(f.arrived["heavy"] for f in fleet.figures)
    fair = heavy[0] > 0
    print(f"heavy messages converted per robot: fewest {heavy[0]}, most {heavy[-1]} "
          f"({sum(heavy)} of {arrived} arrived; baseline robot {base.figures[0].converted['heavy']}); "
          f"every robot converts some: {'met' if fair else 'MISSED'}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", type=int, default=25, help="the fleet (default %(default)s)")
    parser.add_argument("--seconds", type=float, default=15.0, help="measured per phase")
    parser.add_argument("--warmup", type=float, default=5.0, help="after every robot delivered")
    parser.add_argument("--slam", action="store_true", help="host-side SLAM per robot, as the demo")
    parser.add_argument("--phase", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--relay-fleet", metavar="ENDPOINT", help=argparse.SUPPRESS)
    parser.add_argument("--bags", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.relay_fleet is not None:
        return relay_fleet(args.relay_fleet, args.bags, args.robots)
    if args.phase is not None:
        run_phase(args.phase, args.bags, warmup=args.warmup, seconds=args.seconds, slam=args.slam,
                  publish=publish_and_exit)
        return 1  # publish_and_exit did not exit: the phase failed
    with tempfile.TemporaryDirectory(prefix="swanky-fleet-") as tmp:
        started = time.perf_counter()
        seconds = args.warmup + args.seconds + BAG_MARGIN_S
        written = write_bags(Path(tmp), demo_robot_names(str(args.robots)), seconds, threading.Event())
        assert written is not None
        print(f"{args.robots} demo robots' bags of {seconds:g} s written in "
              f"{time.perf_counter() - started:.1f} s; host saving to /dev/null"
              + (", SLAM per robot" if args.slam else ""), flush=True)
        base = measured_phase(1, Path(tmp), args)
        print(f"baseline measured: {base.figures[0].small_p50_ms:.2f} / "
              f"{base.figures[0].small_p99_ms:.2f} ms small-topic p50 / p99", flush=True)
        fleet = measured_phase(args.robots, Path(tmp), args)
    report(base, fleet)
    return 0


if __name__ == "__main__":
    sys.exit(main())
