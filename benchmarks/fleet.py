"""Fleet capacity (issue 24): 25 demo robots' live traffic into one host on this machine, against
one robot's through the same pipeline, measured in the same run; with ``--router``, the README's
two-PC recipe: the fleet through a Zenoh router into one host, then into two hosts sharing one
viewer.

Each robot is the demo's simulated swanky_bot (``host_bridge/demo``: Imu, TF, odometry, joint
states, ground-truth pose and a step-time series at 30 Hz, LaserScan 360 rays at 5 Hz, a 160x120
RGB-D camera at 5 Hz: image, depth image, depth cloud and camera_info, battery at 1 Hz, rosout,
and the latched /tf_static, robot description and walls), its bag written by the demo's own
writer and replayed (looping, real time) by the demo's own relays (``demo.relays.relay_bags``: a
Zenoh session and a Relay per robot, one thread pacing them all). The robots' relays run in one
process of their own, as they would on the robots: the host's figures are the host's alone (the
relays still share this machine's cores; the messages each robot delivered, converted, dropped
or still waiting in the host's queues, against the baseline's, show whether they kept real
time; what waits at the window's end is how far behind the host is).

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
  ``inputs/queues.py``) and messages lost between relay and host (wire sequence gaps less the
  host's own drops, which leave gaps too; read a moment apart, so a robot's figure can be a few
  messages off either way, even below 0);
- heavy messages converted per robot: the fewest and the most over the robots (fair thinning
  keeps them close, no robot starved);
- host CPU: the phase's process time over the window's wall time (cores), per robot, and per
  message converted (the turns of ``inputs/queues.py`` make a busy host convert longer runs,
  which cost less per message);
- host peak RSS: the phase process's VmHWM;
- the CPU (cores) over the window of the processes beside the host: the relays'.

Targets: no small-topic message dropped (TF, odometry, joints, IMU, logs, latched topics: the
issue's "no drop of non-sensor data"); every robot's small-topic p99 <= 100 ms (three periods of
its 30 Hz topics, half the time between two of its scans: the viewer's frames and TF lookups
stay current); every robot converts heavy messages.

``--router``: relays and hosts meet at the lab's router (``deploy/zenoh-router.json5`` on a
loopback port, a zenoh-python session in router mode in a process of its own: no zenohd here),
all of them its clients, as that file has robots connect (in Zenoh's default peer mode they learn
of each other through the router and connect directly, so the data would not pass it). The
robots are the README's two groups, east-1, west-1, east-2, ... (the same demo robots). Two
phases, each with its own Rerun viewer process without a window (``rerun --port N --save
FILE.rrd``, ``tests/integration/procs.saving_viewer``) that its hosts log to under the recording
id ``fleet``, as ``swanky-host --recording-id fleet --host-name east --rerun-addr`` does: the
layout it follows the topics with (shared with the other host: host_bridge/outputs/shared_layout.py),
how far behind the viewer is (``/_stats/host/<group>/viewer_lag_ms`` with two hosts) and heavy
topics thinned for a viewer behind; only their conversion stays on the host's threads (no
converter process), so the host's CPU is its process's:

- one host, ``--robots '*'``: the whole fleet;
- two hosts, ``--robots 'east-$*'`` and ``--robots 'west-$*'``, each a process of its own,
  measuring the same window (the parent tells both to go once both have every robot).

Printed per host the figures above (the router's and the viewer's CPU beside the relays'), then two
hosts against one: the worst robot's small-topic p99, the pooled p50s, host CPU in cores and per
message converted, small and heavy messages converted per robot and second, peak RSS, small
messages dropped, each as a ratio where one reads as one. Both hosts run on this machine's two
cores, so two hosts against one says what splitting the fleet over two processes buys (a GIL each)
and costs, not what a second PC's cores would add; with ``--pcs`` each host is pinned to a core of
its own (``os.sched_setaffinity``: the one host to core 0, the two to cores 0 and 1), as two PCs of
one core each would run them, and two hosts against one is what the second PC adds (the relays, the
router and the viewer, a lab's other machines, still run on either core). Then what each viewer
saved: its recordings (one: both hosts' data in ``fleet``), the blueprints the hosts sent (each
made the active one; each names every robot of both hosts once their topics were shared, so the
layout shown is the whole fleet's whichever host sent last), rows of each robot's ``/imu`` (every
robot present, none short), the entities outside every robot's paths (each host's own viewer lag)
and the hosts' warnings. After its window a host flushes what it logged to the viewer, then ends.

``--workers N`` (default 2): the fleet phase is ``swanky-host --workers N`` itself, as a user runs
it for a fleet (``host_bridge/workers.py``: this many processes, each converting its share of the
robots, and the main process routing their samples), saving to a file, with the same relays and
bags. Its figures are read from outside, as only the host's own files and output show them:
small-topic latency is the relay's receive clock to the row's Rerun row id (which begins with the
time the host logged it: converted, to the nanosecond of the dispatcher's figure above), for the
messages received in the window (each message once, however many entities it fills); messages
converted per robot and second likewise; drops (the host's queues) and sequence gaps per kind from
the summary each worker prints at its stop, over the whole run (none in the run is none in the
window); host CPU of the main process and the workers over the window, and their peak RSS each.
``--workers 1`` measures the one-process host in this process instead, with the figures above.

The bags took 14-86 s to simulate on this shared 2-core machine (load 3.5 to 20), each phase
30-45 s; a phase's process ends right after its window, without draining what its queues hold.

    .venv/bin/python benchmarks/fleet.py [--robots 25] [--seconds 15] [--warmup 5] [--slam]
        [--workers 2] [--router [--pcs]]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import IO, NoReturn

import numpy as np
import numpy.typing as npt
import pyarrow as pa

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from live_capacity import received_ns  # noqa: E402  (beside this script)

from host_bridge.app import HostOptions, open_input, start_layout  # noqa: E402
from host_bridge.core.contract import WARNINGS_PATH  # noqa: E402
from host_bridge.core.destinations import SinkOptions  # noqa: E402
from host_bridge.demo.relays import relay_bags  # noqa: E402
from host_bridge.demo.run import (  # noqa: E402
    DEMO_ROBOT,
    demo_robot_names,
    free_loopback_port,
    write_bags,
)
from host_bridge.inputs.base import InputItem, InputProblem, MessageRun  # noqa: E402
from host_bridge.inputs.live import LiveInput  # noqa: E402
from host_bridge.inputs.queues import HeavyTopicsThinnedError, RobotQueues  # noqa: E402
from host_bridge.outputs.sink import RerunSink  # noqa: E402
from host_bridge.pipeline.dispatch import Dispatcher  # noqa: E402
from host_bridge.table.registry import Lane, Registry, default_registry  # noqa: E402
from robot_relay.session import ZenohOptions  # noqa: E402
from robot_relay.wire import RawMessage  # noqa: E402
from tests.integration.procs import running, saving_viewer, stop  # noqa: E402
from tests.integration.router import router_command, wait_for_port  # noqa: E402
from tests.rrd import ROW_ID  # noqa: E402

# python -m benchmarks gives each script this many seconds at most.
BUDGET_SECONDS = 180

P99_TARGET_MS = 100.0
BAG_MARGIN_S = 5.0  # the bags loop; a little more than the phase needs spares the loop's jump
WORKERS_START_S = 10.0
"""More bag for ``--workers``: its robots join seconds after their relays start publishing (the
workers are processes of their own, each opening its session and sink)."""
JOIN_TIMEOUT_S = 90.0  # every robot delivering: a loaded 2-core machine starts 25 relays slowly
KINDS = ("small", "heavy")
ROUTER_CONFIG = ROOT / "deploy" / "zenoh-router.json5"
RECORDING_ID = "fleet"
GROUPS = {"all": "*", "east": "east-$*", "west": "west-$*"}
"""Through the router, each host's ``--robots``: one host takes every robot, or two hosts one
group each, as the README's two-PC recipe has it."""
VIEWER_TOPIC = "imu"
"""The small topic whose rows per robot the shared viewer's file is read for (30 Hz)."""


@dataclass(frozen=True, slots=True)
class RobotFigures:
    """One robot over the measured window."""

    robot: str
    small_p50_ms: float
    small_p99_ms: float
    small_timed: int
    arrived: dict[str, int]
    """Messages that reached the host, per kind: converted, dropped in its queues or waiting
    there."""
    converted: dict[str, int]
    queue_drops: dict[str, int]
    link_drops: dict[str, int]
    waiting: dict[str, int]
    """Messages waiting in the host's queues at the window's end, per kind."""


@dataclass(frozen=True, slots=True)
class Phase:
    host: str
    """The host's group: "all" (the only host), "east" or "west"."""
    robots: int
    seconds: float
    host_cpu_s: float
    others_cpu_s: dict[str, float]
    """CPU seconds over the window of the processes beside the host: the relays', and through
    the router the router's and the shared viewer's."""
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


def peak_rss_mb(pid: int | str = "self") -> float:
    """Process ``pid``'s peak resident set (VmHWM), in MB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


Counts = dict[tuple[str, str], tuple[int, int, int]]
"""(robot, topic) -> (received by the dispatcher, converted, messages lost between relay and
host)."""


def counter_snapshot(
    dispatcher: Dispatcher, queues: RobotQueues,
) -> tuple[Counts, dict[tuple[str, str], str]]:
    """The dispatcher's counters; the link's losses are its sequence gaps less the host's own
    drops, which leave gaps too (as the ``/_stats`` drops series counts them)."""
    counts, types = {}, {}
    for key, counters in list(dispatcher.counters.items()):
        host_dropped = queues.dropped_when_taken(key[0]).get(key[1], 0)
        counts[key] = (counters.received, counters.converted, counters.sequence_gaps - host_dropped)
        types[key] = counters.msgtype
    return counts, types


def robot_figures(
    robot: str, small_ms: npt.NDArray[np.float64] | None, *, kinds: dict[tuple[str, str], str],
    before: Counts, after: Counts, drops_before: dict[tuple[str, str], int],
    drops_after: dict[tuple[str, str], int], waiting_before: dict[str, tuple[int, int]],
    waiting_after: dict[str, tuple[int, int]],
) -> RobotFigures:
    arrived, converted, queue_drops, link_drops = (dict.fromkeys(KINDS, 0) for _ in range(4))
    waiting = dict(zip(KINDS, waiting_after.get(robot, (0, 0)), strict=True))
    for kind, waited in zip(KINDS, waiting_before.get(robot, (0, 0)), strict=True):
        arrived[kind] += waiting[kind] - waited
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
        0 if small_ms is None else len(small_ms), arrived, converted, queue_drops, link_drops,
        waiting)


def robot_names(count: int, *, router: bool) -> list[str]:
    """The demo's robots (sim, sim2, ...); through the router the README's two groups, east-1,
    west-1, east-2, ... (their bags the demo's, spread along its loop alike)."""
    if not router:
        return demo_robot_names(str(count))
    return [f"{('east', 'west')[i % 2]}-{i // 2 + 1}" for i in range(count)]


def group_robots(robots: list[str], group: str) -> list[str]:
    """The robots of ``robots`` a host of ``group`` (GROUPS) takes."""
    return robots if group == "all" else [robot for robot in robots if robot.startswith(f"{group}-")]


@dataclass(frozen=True, slots=True)
class ViaRouter:
    """A phase's host behind the router: the router's endpoint, the host's group and the viewer
    it shares with the other host."""

    router: str
    group: str
    viewer: str


def start_relays(count: int, bags: Path, endpoint: str, *, router: bool) -> subprocess.Popen[str]:
    """The relays' process; what it says goes to ``relays.log`` beside the bags (a pipe nobody
    reads while the phase runs could fill and stop it)."""
    with (bags / "relays.log").open("a") as log:
        return subprocess.Popen(
            [sys.executable, __file__, "--relay-fleet", endpoint, "--bags", str(bags),
             "--robots", str(count), *(["--router"] if router else [])],
            stdout=subprocess.DEVNULL, stderr=log, text=True)


def stop_process(process: subprocess.Popen[str]) -> None:
    """SIGTERM, then SIGKILL after 30 s."""
    stop(process, wait_s=30.0)


def run_phase(
    count: int, bags: Path, *, warmup: float, seconds: float, slam: bool,
    publish: Callable[[Phase], None], via: ViaRouter | None,
) -> None:
    """One host and its robots' relays (another process); the figures of the ``seconds`` after
    every robot delivered, the parent said go (a line on stdin: the processes beside the host
whose CPU over the window is measured too, names to pids) and ``warmup`` passed go to
    ``publish`` before the host drains its queues (seconds of backlog when it does not keep up:
    nothing after the window is measured).

    Without ``via`` the host listens on a loopback endpoint and starts the relays of ``count``
    robots itself, saving to /dev/null. With it, the host connects to the router as a client and
    takes its group of the ``count`` robots (whose relays the parent starts once the host said
    "opened"), logging to the shared viewer as ``swanky-host --recording-id fleet --rerun-addr``
    does (its layout; how far behind the viewer is, and heavy topics thinned for it when behind)
    but for the converter process (its heavy topics are converted on threads, as without the
    router: the host's CPU is this process's)."""
    robots = group_robots(robot_names(count, router=via is not None), "all" if via is None else via.group)
    registry = default_registry()
    with ExitStack() as closing:
        if via is None:
            endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
            zenoh = ZenohOptions(listen=(endpoint,), multicast_scouting=False)
            sink = RerunSink(SinkOptions(save=Path("/dev/null")))
        else:
            zenoh = ZenohOptions(mode="client", connect=(via.router,), multicast_scouting=False)
            sink = RerunSink(SinkOptions(connect=via.viewer, recording_id=RECORDING_ID), keep_up=True)
        closing.callback(sink.close)
        layout = None if via is None else start_layout(HostOptions(), sink)
        if layout is not None:
            closing.callback(layout.close)
        dispatcher = Dispatcher(sink, registry=registry,
                                on_new_topic=None if layout is None else layout.topic_seen)
        closing.callback(dispatcher.close)
        if sink.viewer_lag is not None:
            from host_bridge.pipeline.thinning import ViewerThinning, lag_path

            dispatcher.offload = ViewerThinning(dispatcher, sink, sink.viewer_lag,
                                                path=lag_path(None if via is None or via.group == "all"
                                                              else via.group))  # --host-name east
        if slam:
            from host_bridge.slam.feeder import SlamTap
            from host_bridge.table.config import HostConfig

            config = HostConfig.builtin(registry)
            slam_tap = SlamTap(dispatcher, lambda robot: config.slam_settings(robot, True),
                               lossless=False)
            closing.callback(slam_tap.close)
            dispatcher.add_tap(slam_tap)
        options = HostOptions(zenoh=zenoh, rmw_zenoh=False,
                              robots=f"{DEMO_ROBOT}$*" if via is None else GROUPS[via.group],
                              sink=SinkOptions(recording_id=None if via is None else RECORDING_ID))
        live = open_input(options, dispatcher, demo=None, robot_files=None,
                          stop=threading.Event(), closing=closing, layout=layout)
        assert isinstance(live, LiveInput)
        timing = FleetTiming(dispatcher, registry)
        live.start(timing)
        relays = None
        if via is None:
            relays = start_relays(count, bags, endpoint, router=False)
            closing.callback(stop_process, relays)
        print("opened", flush=True)
        deadline = time.monotonic() + JOIN_TIMEOUT_S
        while len(timing.seen) < len(robots):
            if (relays is not None and relays.poll() is not None) or time.monotonic() > deadline:
                msg = (f"{len(timing.seen)} of {len(robots)} robots delivered within "
                       f"{JOIN_TIMEOUT_S:.0f} s; relays said: {(bags / 'relays.log').read_text()[-2000:]}")
                raise RuntimeError(msg)
            time.sleep(0.1)
        print("joined", flush=True)
        # The parent's go: every host of the phase measures the same window.
        watched: dict[str, int] = json.loads(sys.stdin.readline())
        if relays is not None:
            watched["relays"] = relays.pid
        time.sleep(warmup)
        counts_before, _ = counter_snapshot(dispatcher, live.queues)
        drops_before = live.queues.dropped
        waiting_before = live.queues.waiting
        others_before = {name: process_cpu_s(pid) for name, pid in watched.items()}
        timing.start_measuring()
        cpu_before, wall_before = time.process_time(), time.perf_counter()
        time.sleep(seconds)
        small_ms, entered_ms = timing.stop_measuring()
        host_cpu = time.process_time() - cpu_before
        wall = time.perf_counter() - wall_before
        others_cpu = {name: process_cpu_s(pid) - others_before[name] for name, pid in watched.items()}
        counts_after, types = counter_snapshot(dispatcher, live.queues)
        drops_after = live.queues.dropped
        waiting_after = live.queues.waiting
        if relays is not None:
            stop_process(relays)
        if layout is not None:  # the viewer's file gets everything up to the window's end
            layout.close()
            sink.flush()
        kinds = {key: "small" if registry.row(msgtype, key[1]).lane is Lane.SMALL else "heavy"
                 for key, msgtype in types.items()}
        pooled = np.concatenate(list(small_ms.values())) if small_ms else np.array([np.nan])
        publish(Phase(
            "all" if via is None else via.group, len(robots), wall, host_cpu, others_cpu,
            peak_rss_mb(),
            float(np.percentile(pooled, 50)), float(np.percentile(pooled, 99)),
            float(np.percentile(entered_ms, 50)), float(np.percentile(entered_ms, 99)),
            len(pooled) / max(timing.small_batches, 1),
            [robot_figures(robot, small_ms.get(robot), kinds=kinds, before=counts_before,
                           after=counts_after, drops_before=drops_before, drops_after=drops_after,
                           waiting_before=waiting_before, waiting_after=waiting_after)
             for robot in robots],
            timing.thinned_said))


def publish_and_exit(phase: Phase) -> NoReturn:
    """The phase's figures to the parent (stdout), then this process ends at once."""
    print(json.dumps(asdict(phase)), flush=True)
    os._exit(0)


def relay_fleet(endpoint: str, bags: Path, count: int, *, router: bool) -> int:
    """The robots' side: the demo's relays (a Zenoh session each, one thread pacing them all),
    until SIGTERM; through the router each a Zenoh client of it, as deploy/zenoh-router.json5
    has robots."""
    stop, failed = threading.Event(), threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    robots = robot_names(count, router=router)
    relays = threading.Thread(
        target=relay_bags, args=({robot: bags / robot for robot in robots}, endpoint, stop, failed),
        kwargs={"mode": "client" if router else None, "host_wait_s": JOIN_TIMEOUT_S},
        name="relays", daemon=True)
    relays.start()
    while not stop.wait(0.2):
        if failed.is_set():
            return 1
    relays.join(timeout=30.0)
    return 0


@contextmanager
def running_router() -> Iterator[tuple[str, int]]:
    """The lab's router (deploy/zenoh-router.json5: no multicast scouting, two links a client,
    timestamps) on a loopback port instead of 7447, a process of its own (no zenohd here: a
    zenoh-python session in router mode): its endpoint and pid, until leaving."""
    port = free_loopback_port()
    with running(router_command(port, ROUTER_CONFIG)) as router:
        wait_for_port(port)
        yield f"tcp/127.0.0.1:{port}", router.pid


def expect_line(host: subprocess.Popen[str], stderr: IO[str], line: str) -> None:
    """Read the host's stdout up to ``line``; a host that ended first is an error naming why
    (its ``stderr``)."""
    assert host.stdout is not None
    while (said := host.stdout.readline()) != f"{line}\n":
        if not said:
            host.wait(timeout=30)
            raise RuntimeError(f"a host ended ({host.returncode}) before saying {line!r}: {tail(stderr)}")


def tail(stderr: IO[str]) -> str:
    stderr.seek(0)
    return stderr.read()[-3000:]


def measured_hosts(
    count: int, bags: Path, args: argparse.Namespace, hosts: Sequence[Sequence[str]],
    opened: Callable[[], dict[str, int]] = dict,
) -> list[Phase]:
    """One phase: a process per host (``hosts``: each one's extra flags), ``opened()`` once each
    host listens for its robots (the processes it started, whose CPU the hosts measure too);
    when every host has every robot, they are told to go at once."""
    command = [sys.executable, __file__, "--phase", str(count), "--bags", str(bags),
               "--seconds", str(args.seconds), "--warmup", str(args.warmup)]
    if args.slam:
        command.append("--slam")
    with ExitStack() as closing:
        processes = []
        for flags in hosts:
            said = closing.enter_context(tempfile.TemporaryFile("w+"))
            process = subprocess.Popen([*command, *flags], stdin=subprocess.PIPE,
                                       stdout=subprocess.PIPE, stderr=said, text=True)
            closing.callback(stop_process, process)
            processes.append((process, said))
        for process, said in processes:
            expect_line(process, said, "opened")
        watched = json.dumps(opened())
        for process, said in processes:
            expect_line(process, said, "joined")
        for process, _ in processes:
            assert process.stdin is not None
            process.stdin.write(f"{watched}\n")
            process.stdin.flush()
        phases = []
        for process, said in processes:
            out, _ = process.communicate(timeout=BUDGET_SECONDS)
            if process.returncode != 0:
                msg = f"a host of the {count}-robot phase failed ({process.returncode}): {tail(said)}"
                raise RuntimeError(msg)
            found = json.loads(out.strip().splitlines()[-1])
            found["figures"] = [RobotFigures(**figures) for figures in found["figures"]]
            phases.append(Phase(**found))
        return phases


@dataclass(frozen=True, slots=True)
class ViewerFindings:
    """What the viewer the hosts shared saved."""

    recordings: list[str]
    """Each recording's application and recording id."""
    blueprints: list[list[str]]
    """Each blueprint's robots (those its views name), in the order they were sent (their first
    row ids, which begin with the time they were logged at: the file keeps no order of stores)."""
    rows: dict[str, int]
    """Per robot, the rows of its VIEWER_TOPIC."""
    shared: dict[str, int]
    """Entities under no robot's paths (every host may write them): their rows."""
    warnings: list[str]
    """The hosts' warnings (WARNINGS_PATH)."""


def viewer_findings(rrd: Path, robots: list[str]) -> ViewerFindings:
    from rerun.chunk import RrdReader

    with warnings.catch_warnings():  # the viewer's --save file has no footer: read whole, as meant
        warnings.simplefilter("ignore")
        reader = RrdReader(rrd)
    named = "|".join(robots)
    blueprints = []
    for store in reader.blueprints():
        found: set[str] = set()
        first_row = b"\xff" * 16
        for chunk in reader.stream(store=store):
            batch = chunk.to_record_batch()
            found.update(chunk_robots(batch, named))
            first_row = min(first_row, *batch.column(ROW_ID).to_pylist())
        blueprints.append((first_row, sorted(found, key=robots.index)))
    rows = dict.fromkeys(robots, 0)
    shared: dict[str, int] = {}
    said = []
    for store in reader.recordings():
        for chunk in reader.stream(store=store):
            if chunk.entity_path == WARNINGS_PATH:
                batch = chunk.to_record_batch()
                said += [text for name in batch.schema.names if name.endswith(":text")
                         for texts in batch.column(name).to_pylist() for text in texts or ()]
            parts = chunk.entity_path.strip("/").split("/")
            robot = parts[1] if parts[0] == "_stats" and len(parts) > 1 else parts[0]
            if robot not in rows:
                shared[chunk.entity_path] = shared.get(chunk.entity_path, 0) + chunk.num_rows
            elif parts[0] == robot and parts[1:2] == [VIEWER_TOPIC] and not chunk.is_static:
                rows[robot] += chunk.num_rows
    return ViewerFindings([f"{s.application_id}/{s.recording_id}" for s in reader.recordings()],
                          [robots for _, robots in sorted(blueprints)], rows, shared, said)


def chunk_robots(batch: pa.RecordBatch, named: str) -> set[str]:
    """The robots a blueprint chunk names (an entity path, a view's origin or query)."""
    columns = zip(batch.schema.names, batch.columns, strict=True)
    text = json.dumps([column.to_pylist() for name, column in columns
                       if name != ROW_ID and not pa.types.is_timestamp(column.type)], default=str)
    return {found.group(1) for found in re.finditer(rf"/({named})\b", text)}


def router_phase(
    groups: Sequence[str], bags: Path, args: argparse.Namespace, router: tuple[str, int],
) -> tuple[list[Phase], ViewerFindings]:
    """The hosts of ``groups`` behind the router, logging to one saving viewer; the relays of
    every robot in a process of their own, started once the hosts listen."""
    endpoint, router_pid = router
    rrd = bags / f"viewer-{len(groups)}-hosts.rrd"
    with saving_viewer(rrd) as (viewer, viewer_process), ExitStack() as relays:

        def start() -> dict[str, int]:
            process = start_relays(args.robots, bags, endpoint, router=True)
            relays.callback(stop_process, process)
            return {"relays": process.pid, "router": router_pid, "viewer": viewer_process.pid}

        hosts = [["--router-at", endpoint, "--group", group, "--viewer", viewer,
              *(["--core", str(core)] if args.pcs else [])] for core, group in enumerate(groups)]
        phases = measured_hosts(args.robots, bags, args, hosts, opened=start)
    return phases, viewer_findings(rrd, robot_names(args.robots, router=True))


def per_second(phase: Phase, kind: str, what: str) -> float:
    """Messages of ``kind`` per robot and second: ``what`` is a RobotFigures count field."""
    counts: list[dict[str, int]] = [getattr(f, what) for f in phase.figures]
    return sum(count[kind] for count in counts) / phase.seconds / phase.robots


def cpu_per_message_ms(phase: Phase) -> float:
    converted = sum(sum(f.converted.values()) for f in phase.figures)
    return phase.host_cpu_s / max(converted, 1) * 1e3


def phase_line(name: str, phase: Phase) -> str:
    others = ", ".join(f"{who} {cpu / phase.seconds:.2f}"
                       for who, cpu in phase.others_cpu_s.items())
    return (f"{name}, {phase.robots} robot{'s' if phase.robots > 1 else ''}, {phase.seconds:.1f} s: "
            f"arrived per robot {per_second(phase, 'small', 'arrived'):.1f} small + "
            f"{per_second(phase, 'heavy', 'arrived'):.1f} heavy msg/s; "
            f"host CPU {phase.host_cpu_s / phase.seconds:.2f} cores "
            f"({phase.host_cpu_s / phase.seconds / phase.robots * 100:.1f} % of a core per robot, "
            f"{cpu_per_message_ms(phase):.3f} ms per message converted, "
            f"{phase.small_per_batch:.1f} small messages per batch); beside it: {others} cores; "
            f"host peak RSS {phase.peak_rss_mb:.0f} MB")


def robot_table(phase: Phase) -> None:
    print(f"  {'robot':<8}{'small/s':>8}{'p50 ms':>10}{'p99 ms':>10}{'small drops':>12}"
          f"{'heavy/s':>8}{'converted':>10}{'replaced':>9}{'link gaps':>10}")
    for f in phase.figures:
        print(f"  {f.robot:<8}{f.arrived['small'] / phase.seconds:>8.1f}{f.small_p50_ms:>10.1f}"
              f"{f.small_p99_ms:>10.1f}{f.queue_drops['small']:>12}"
              f"{f.arrived['heavy'] / phase.seconds:>8.1f}{f.converted['heavy']:>10}"
              f"{f.queue_drops['heavy']:>9}{sum(f.link_drops.values()):>10}")


def worst_robot(phases: Sequence[Phase]) -> RobotFigures:
    return max((f for phase in phases for f in phase.figures), key=lambda f: f.small_p99_ms)


def small_lost(phases: Sequence[Phase]) -> int:
    return sum(f.queue_drops["small"] + f.link_drops["small"] for phase in phases for f in phase.figures)


def report(base: Phase, fleet: Phase) -> None:
    """Print the figures, each target's verdict with them."""
    print(phase_line("baseline", base), flush=True)
    print(phase_line("fleet", fleet), flush=True)
    robot_table(fleet)
    kept = per_second(fleet, "small", "arrived") / per_second(base, "small", "arrived")
    print(f"small messages arrived per robot per second, fleet / baseline: {kept:.2f} "
          "(below 1: behind real time before the host's queues, in the relays' process on the same "
          "cores or in Zenoh's links to a host that reads them late)")
    waiting = sum(f.waiting["small"] for f in fleet.figures)
    behind_s = waiting / fleet.robots / per_second(base, "small", "arrived")
    print(f"small messages converted per robot per second: {per_second(fleet, 'small', 'converted'):.1f} "
          f"of {per_second(fleet, 'small', 'arrived'):.1f} arrived; {waiting} waiting in the host's "
          f"queues at the window's end ({behind_s:.1f} s of a robot's small messages: what the host "
          "is behind)")
    worst = worst_robot([fleet])
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
    lost = small_lost([fleet])
    heavy_replaced = sum(f.queue_drops["heavy"] for f in fleet.figures)
    heavy_lost = sum(f.link_drops["heavy"] for f in fleet.figures)
    print(f"drops in the fleet: small {lost} (target 0: {'met' if not lost else 'MISSED'}); "
          f"heavy {heavy_replaced} replaced by newer ones in the host's queues "
          f"(baseline {base.figures[0].queue_drops['heavy']}), {heavy_lost} lost on the link; "
          f"the host said it thins heavy topics {fleet.thinned_said} time(s)")
    heavy = sorted(f.converted["heavy"] for f in fleet.figures)
    arrived = sum(f.arrived["heavy"] for f in fleet.figures)
    fair = heavy[0] > 0
    print(f"heavy messages converted per robot: fewest {heavy[0]}, most {heavy[-1]} "
          f"({sum(heavy)} of {arrived} arrived; baseline robot {base.figures[0].converted['heavy']}); "
          f"every robot converts some: {'met' if fair else 'MISSED'}")


def report_router(one: Phase, two: list[Phase], seen: dict[int, ViewerFindings]) -> None:
    """Each host's figures, two hosts against one, and what the shared viewer saved."""
    for phase in (one, *two):
        print(phase_line(f"{'one host' if phase is one else 'two hosts'}, {phase.host}", phase), flush=True)
        robot_table(phase)
    worst_one, worst_two = worst_robot([one]), worst_robot(two)
    cpu_one = one.host_cpu_s / one.seconds
    cpu_two = sum(phase.host_cpu_s / phase.seconds for phase in two)
    per_message_two = sum(phase.host_cpu_s for phase in two) / max(
        sum(sum(f.converted.values()) for phase in two for f in phase.figures), 1) * 1e3
    small_one = per_second(one, "small", "converted")
    small_two = sum(per_second(phase, "small", "converted") * phase.robots for phase in two) / one.robots
    heavy_one = per_second(one, "heavy", "converted")
    heavy_two = sum(per_second(phase, "heavy", "converted") * phase.robots for phase in two) / one.robots
    print(f"two hosts / one host: worst robot's small-topic p99 {worst_two.small_p99_ms:.1f} "
          f"({worst_two.robot}) / {worst_one.small_p99_ms:.1f} ms ({worst_one.robot}) = "
          f"{worst_two.small_p99_ms / worst_one.small_p99_ms:.2f}; pooled p50 "
          f"{' + '.join(f'{p.small_pooled_p50_ms:.1f}' for p in two)} / {one.small_pooled_p50_ms:.1f} ms; "
          f"host CPU {cpu_two:.2f} / {cpu_one:.2f} cores = {cpu_two / cpu_one:.2f}; CPU per message "
          f"converted {per_message_two:.3f} / {cpu_per_message_ms(one):.3f} ms = "
          f"{per_message_two / cpu_per_message_ms(one):.2f}; converted per robot per second: small "
          f"{small_two:.1f} / {small_one:.1f} = {small_two / small_one:.2f}, heavy {heavy_two:.2f} / "
          f"{heavy_one:.2f}; peak RSS {' + '.join(f'{p.peak_rss_mb:.0f}' for p in two)} / "
          f"{one.peak_rss_mb:.0f} MB; small messages dropped {small_lost(two)} / {small_lost([one])}")
    for hosts, found in seen.items():
        groups = {group: group_robots(list(found.rows), group) for group in ("east", "west")}
        rows = "; ".join(f"{group} {min(found.rows[r] for r in robots)}-{max(found.rows[r] for r in robots)}"
                         for group, robots in groups.items() if robots)
        present = sum(1 for count in found.rows.values() if count)
        print(f"viewer shared by {hosts} host{'s' if hosts > 1 else ''}: {len(found.recordings)} "
              f"recording(s) ({', '.join(found.recordings)}); robots with /{VIEWER_TOPIC} rows "
              f"{present} of {len(found.rows)} (rows per robot, fewest-most: {rows}); "
              f"{len(found.blueprints)} blueprint(s) sent, each made the active one, naming "
              + ", ".join(f"{len(robots)} robot(s)" + (f" ({robots[0]}...)" if robots else "")
                          for robots in found.blueprints)
              + f" (the last, the layout shown at the end: {len(found.blueprints[-1])} of "
              f"{len(found.rows)} robots); entities outside every robot's (rows): "
              + ", ".join(f"{path} {rows}" for path, rows in sorted(found.shared.items()))
              + "".join(f"\n  warning: {text}" for text in found.warnings))


@dataclass(frozen=True, slots=True)
class WorkerRobot:
    """One robot of the ``--workers`` phase."""

    robot: str
    converted: dict[str, int]
    """Messages received in the window and converted, per kind."""
    small_p50_ms: float
    small_p99_ms: float
    dropped: dict[str, int]
    """Dropped in the host's queues over the whole run, per kind (the workers' summaries)."""
    gaps: dict[str, int]
    """Sequence gaps over the whole run, per kind: the host's own drops leave gaps too."""


@dataclass(frozen=True, slots=True)
class WorkersPhase:
    workers: int
    seconds: float
    host_cpu_s: list[float]
    """CPU over the window of the main process, then of each of its children (the workers and
    multiprocessing's resource tracker)."""
    relays_cpu_s: float
    peak_rss_mb: list[float]
    """The main process's, then each worker's."""
    small_pooled_p50_ms: float
    small_pooled_p99_ms: float
    robots: list[WorkerRobot]
    thinned_said: int


SUMMARY_COLUMNS = ("robot", "topic", "type", "received", "converted", "dropped", "warnings", "gaps",
                   "ms/msg")
"""The header of the table a host prints at its stop (host_bridge/core/counters.py)."""


def summary_rows(said: str, robots: set[str]) -> dict[tuple[str, str], tuple[str, int, int]]:
    """(robot, topic) -> (type, dropped, gaps) from the workers' summaries in their output."""
    rows = {}
    for line in said.splitlines():
        fields = line.split()
        if len(fields) == len(SUMMARY_COLUMNS) and fields[0] in robots and fields[1].startswith("/"):
            rows[fields[0], fields[1]] = (fields[2], int(fields[5]), int(fields[7]))
    return rows


def topic_of(entity: str, topics: Sequence[str]) -> str | None:
    """The topic whose rows ``entity`` (without its robot) holds: the longest that is it or a
    parent of it (/imu for /imu/orientation)."""
    found = [topic for topic in topics if entity == topic or entity.startswith(f"{topic}/")]
    return max(found, key=len, default=None)


def logged_ms(
    files: Sequence[Path], topics: dict[str, list[str]], window: tuple[int, int],
) -> dict[tuple[str, str], list[float]]:
    """Per (robot, topic), each message received in ``window`` (ns): receive -> logged in ms.
    A message is its receive time and header stamp; of its rows (an Imu fills three entities,
    a TF message one row per transform) the last logged counts, when all of it was."""
    from rerun.chunk import RrdReader

    logged: dict[tuple[str, str], dict[tuple[int, int], int]] = {}
    for path in files:
        for chunk in RrdReader(path).stream():
            robot, _, rest = chunk.entity_path.strip("/").partition("/")
            topic = None if chunk.is_static or robot not in topics else topic_of(f"/{rest}", topics[robot])
            if topic is None:
                continue
            batch = chunk.to_record_batch()
            if "receive_time" not in batch.schema.names:
                continue
            received = batch.column("receive_time").cast(pa.int64()).to_numpy(zero_copy_only=False)
            stamp_name = next((n for n in ("ros_time", "log_time") if n in batch.schema.names), None)
            stamps = (np.zeros(len(received), np.int64) if stamp_name is None else
                      batch.column(stamp_name).cast(pa.int64()).fill_null(0).to_numpy(zero_copy_only=False))
            row_ids = batch.column(ROW_ID)
            # A row id begins with the time it was logged at, in ns since the epoch, big endian.
            words = np.frombuffer(row_ids.buffers()[1], dtype=">u8")
            logged_ns = words[2 * row_ids.offset:2 * (row_ids.offset + len(row_ids)):2].astype(np.int64)
            rows = logged.setdefault((robot, topic), {})
            for receive_ns, stamp_ns, at_ns in zip(received, stamps, logged_ns, strict=True):
                if window[0] <= receive_ns < window[1]:
                    key = (int(receive_ns), int(stamp_ns))
                    rows[key] = max(rows.get(key, 0), int(at_ns))
    return {key: [(at - receive_ns) / 1e6 for (receive_ns, _), at in rows.items()]
            for key, rows in logged.items()}


def process_tree(pid: int) -> list[int]:
    """``pid`` and its children (the workers), as /proc lists them."""
    children = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    return [pid, *map(int, children)]


def workers_phase(count: int, bags: Path, args: argparse.Namespace) -> WorkersPhase:
    """``swanky-host --workers N`` listening for ``count`` robots' relays; the window begins
    ``warmup`` s after every robot joined (its line in the host's output)."""
    robots = robot_names(count, router=False)
    port = free_loopback_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    said = bags / "host.log"
    host_command = [sys.executable, "-m", "host_bridge.cli", "--listen", endpoint,
                    "--no-multicast-scouting", "--no-rmw-zenoh", "--robots", f"{DEMO_ROBOT}$*",
                    "--workers", str(args.workers), "--save", str(bags / "fleet.rrd"),
                    "--slam" if args.slam else "--no-slam"]
    with ExitStack() as closing:
        host = closing.enter_context(running(host_command, output=said))
        wait_for_port(port, timeout=JOIN_TIMEOUT_S)
        relays = start_relays(count, bags, endpoint, router=False)
        closing.callback(stop_process, relays)
        deadline = time.monotonic() + JOIN_TIMEOUT_S
        while (joined := said.read_text().count(" joined (swanky relay)")) < count:
            if host.poll() is not None or relays.poll() is not None or time.monotonic() > deadline:
                msg = (f"{joined} of {count} robots joined swanky-host --workers {args.workers} "
                       f"within {JOIN_TIMEOUT_S:.0f} s; it said: {said.read_text()[-2000:]}")
                raise RuntimeError(msg)
            time.sleep(0.1)
        time.sleep(args.warmup)
        pids = process_tree(host.pid)
        cpu_before = [process_cpu_s(pid) for pid in pids]
        relays_before = process_cpu_s(relays.pid)
        window_ns = time.time_ns()
        time.sleep(args.seconds)
        window = (window_ns, time.time_ns())
        host_cpu = [process_cpu_s(pid) - before for pid, before in zip(pids, cpu_before, strict=True)]
        relays_cpu = process_cpu_s(relays.pid) - relays_before
        peak_rss = [peak_rss_mb(pid) for pid in pids]
        stop_process(relays)
        host.send_signal(signal.SIGINT)  # Ctrl-C: every worker finishes its file and summary
        if host.wait(timeout=BUDGET_SECONDS) != 0:
            msg = (f"swanky-host --workers {args.workers} ended with {host.returncode}: "
                   f"{said.read_text()[-3000:]}")
            raise RuntimeError(msg)
    output = said.read_text()
    summary = summary_rows(output, set(robots))
    registry = default_registry()
    kinds = {key: "small" if registry.row(msgtype, key[1]).lane is Lane.SMALL else "heavy"
             for key, (msgtype, _, _) in summary.items()}
    topics: dict[str, list[str]] = {}
    for robot, topic in summary:
        topics.setdefault(robot, []).append(topic)
    latencies = logged_ms(sorted(bags.glob("fleet*.rrd")), topics, window)
    figures = []
    for robot in robots:
        converted, dropped, gaps = (dict.fromkeys(KINDS, 0) for _ in range(3))
        small: list[float] = []
        for (name, topic), (_, topic_dropped, topic_gaps) in summary.items():
            if name != robot:
                continue
            kind = kinds[name, topic]
            dropped[kind] += topic_dropped
            gaps[kind] += topic_gaps
            logged = latencies.get((robot, topic), [])
            converted[kind] += len(logged)
            if kind == "small":
                small += logged
        timed = np.array(small or [np.nan])
        figures.append(WorkerRobot(robot, converted, float(np.percentile(timed, 50)),
                                   float(np.percentile(timed, 99)), dropped, gaps))
    pooled = np.array([ms for key, logged in latencies.items() if kinds.get(key) == "small"
                       for ms in logged] or [np.nan])
    return WorkersPhase(args.workers, (window[1] - window[0]) / 1e9, host_cpu, relays_cpu, peak_rss,
                        float(np.percentile(pooled, 50)), float(np.percentile(pooled, 99)), figures,
                        output.count("thinning now"))


def report_workers(base: Phase, fleet: WorkersPhase) -> None:
    """The ``--workers`` phase's figures, each target's verdict with them."""
    print(phase_line("baseline", base), flush=True)
    converted = sum(sum(f.converted.values()) for f in fleet.robots)
    host_cpu = sum(fleet.host_cpu_s)
    print(f"fleet through swanky-host --workers {fleet.workers}, {len(fleet.robots)} robots, "
          f"{fleet.seconds:.1f} s: host CPU {host_cpu / fleet.seconds:.2f} cores ("
          f"{' + '.join(f'{cpu / fleet.seconds:.2f}' for cpu in fleet.host_cpu_s)}: the main process, "
          f"then its children; {host_cpu / max(converted, 1) * 1e3:.3f} ms per message converted); "
          f"beside it: relays {fleet.relays_cpu_s / fleet.seconds:.2f} cores; peak RSS "
          f"{' + '.join(f'{mb:.0f}' for mb in fleet.peak_rss_mb)} MB (the same processes)")
    print(f"  {'robot':<8}{'small/s':>8}{'p50 ms':>10}{'p99 ms':>10}{'small drops':>12}"
          f"{'heavy/s':>8}{'replaced':>9}{'gaps':>6}")
    for f in fleet.robots:
        print(f"  {f.robot:<8}{f.converted['small'] / fleet.seconds:>8.1f}{f.small_p50_ms:>10.1f}"
              f"{f.small_p99_ms:>10.1f}{f.dropped['small']:>12}{f.converted['heavy'] / fleet.seconds:>8.1f}"
              f"{f.dropped['heavy']:>9}{sum(f.gaps.values()):>6}")
    small_rate = sum(f.converted["small"] for f in fleet.robots) / fleet.seconds / len(fleet.robots)
    base_rate = per_second(base, "small", "arrived")
    print(f"small messages received in the window and converted, per robot per second: "
          f"{small_rate:.1f}, against {base_rate:.1f} arriving for the baseline robot: "
          f"{small_rate / base_rate:.2f} (below 1: behind real time, in the relays or the host; "
          "not counted: messages whose rows are under another path than their topic's, such as "
          "camera_info's, under its camera's)")
    worst = max(fleet.robots, key=lambda f: f.small_p99_ms)
    base_p99 = base.figures[0].small_p99_ms
    print(f"small topics publish -> logged, p50 / p99 ms: baseline (publish -> converted) "
          f"{base.small_pooled_p50_ms:.2f} / {base_p99:.2f}; fleet pooled "
          f"{fleet.small_pooled_p50_ms:.2f} / {fleet.small_pooled_p99_ms:.2f}, worst robot "
          f"({worst.robot}) p99 {worst.small_p99_ms:.2f}; ratio worst fleet p99 / baseline p99 "
          f"{worst.small_p99_ms / base_p99:.1f} (target every robot's p99 <= {P99_TARGET_MS:g} ms: "
          f"{'met' if worst.small_p99_ms <= P99_TARGET_MS else 'MISSED'})")
    lost = sum(f.dropped["small"] for f in fleet.robots)
    gaps = sum(f.gaps["small"] for f in fleet.robots)
    print(f"drops over the whole run: small {lost} in the host's queues, {gaps} sequence gaps "
          f"(target 0: {'met' if not lost and not gaps else 'MISSED'}); heavy "
          f"{sum(f.dropped['heavy'] for f in fleet.robots)} replaced by newer ones; the workers said "
          f"they thin heavy topics {fleet.thinned_said} time(s)")
    heavy = sorted(f.converted["heavy"] for f in fleet.robots)
    print(f"heavy messages received in the window and converted per robot: fewest {heavy[0]}, most "
          f"{heavy[-1]} (baseline robot {base.figures[0].converted['heavy']}); every robot converts "
          f"some: {'met' if heavy[0] > 0 else 'MISSED'}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", type=int, default=25, help="the fleet (default %(default)s)")
    parser.add_argument("--seconds", type=float, default=15.0, help="measured per phase")
    parser.add_argument("--warmup", type=float, default=5.0, help="after every robot delivered")
    parser.add_argument("--slam", action="store_true", help="host-side SLAM per robot, as the demo")
    parser.add_argument("--workers", type=int, default=2,
                        help="the fleet through swanky-host --workers N (1: one process, measured "
                             "from inside; default %(default)s)")
    parser.add_argument("--router", action="store_true",
                        help="through a Zenoh router: one host for the fleet, then two (README)")
    parser.add_argument("--pcs", action="store_true",
                        help="with --router: each host on a core of its own, as if each were a PC")
    parser.add_argument("--phase", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--core", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--router-at", metavar="ENDPOINT", help=argparse.SUPPRESS)
    parser.add_argument("--group", choices=sorted(GROUPS), help=argparse.SUPPRESS)
    parser.add_argument("--viewer", help=argparse.SUPPRESS)
    parser.add_argument("--relay-fleet", metavar="ENDPOINT", help=argparse.SUPPRESS)
    parser.add_argument("--bags", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.pcs and not args.router:
        parser.error("--pcs needs --router: it places the router recipe's hosts")
    if args.relay_fleet is not None:
        return relay_fleet(args.relay_fleet, args.bags, args.robots, router=args.router)
    if args.phase is not None:
        if args.core is not None:  # before any thread starts: every thread of the host inherits it
            os.sched_setaffinity(0, {args.core})
        via = None if args.router_at is None else ViaRouter(args.router_at, args.group, args.viewer)
        run_phase(args.phase, args.bags, warmup=args.warmup, seconds=args.seconds, slam=args.slam,
                  publish=publish_and_exit, via=via)
        return 1  # publish_and_exit did not exit: the phase failed
    with tempfile.TemporaryDirectory(prefix="swanky-fleet-") as tmp:
        bags = Path(tmp)
        started = time.perf_counter()
        seconds = args.warmup + args.seconds + BAG_MARGIN_S + (WORKERS_START_S if args.workers > 1 else 0)
        robots = robot_names(args.robots, router=args.router)
        written = write_bags(bags, robots, seconds, threading.Event())
        assert written is not None
        print(f"{args.robots} demo robots' bags of {seconds:g} s written in "
              f"{time.perf_counter() - started:.1f} s; "
              + (f"through a Zenoh router ({ROUTER_CONFIG.name}), hosts logging to one Rerun "
                 f"viewer (rerun --port N --save FILE) under recording id {RECORDING_ID!r}"
                 if args.router else "host saving to /dev/null")
              + (", each host on a core of its own (--pcs)" if args.pcs else "")
              + (", SLAM per robot" if args.slam else ""), flush=True)
        if args.router:
            with running_router() as router:
                (one,), seen_one = router_phase(["all"], bags, args, router)
                print(f"one host measured: worst robot's small-topic p99 "
                      f"{worst_robot([one]).small_p99_ms:.2f} ms", flush=True)
                two, seen_two = router_phase(["east", "west"], bags, args, router)
            report_router(one, two, {1: seen_one, 2: seen_two})
            return 0
        (base,) = measured_hosts(1, bags, args, [[]])
        print(f"baseline measured: {base.figures[0].small_p50_ms:.2f} / "
              f"{base.figures[0].small_p99_ms:.2f} ms small-topic p50 / p99", flush=True)
        if args.workers > 1:
            workers = workers_phase(args.robots, bags, args)
        else:
            (fleet,) = measured_hosts(args.robots, bags, args, [[]])
    if args.workers > 1:
        report_workers(base, workers)
    else:
        report(base, fleet)
    return 0


if __name__ == "__main__":
    sys.exit(main())
