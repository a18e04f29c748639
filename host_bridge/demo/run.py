"""``swanky-host --demo [--robots N]``: simulated robots through the real relay -> Zenoh -> host path.

The simulator (:mod:`host_bridge.demo.bag`) writes one real rosbag2 per robot; for each robot an
in-process relay replays its bag (looping, real time) over a loopback Zenoh link to this host,
exactly as ``swanky-relay --bag`` on that robot would (:mod:`host_bridge.demo.relays`: one
thread paces them all). Robots are named ``sim``, ``sim2``,
``sim3``...; they drive the same loop through the same apartment, spread evenly along it, each
with its own frames (``sim2/base_link``), drifting odometry and sensors.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import socket
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

from host_bridge.demo.bag import write_demo_bag
from host_bridge.demo.relays import relay_bags
from host_bridge.demo.robot import lap_length
from host_bridge.errors import ConfigError
from host_bridge.inputs.base import Deliver, Input
from robot_relay.session import ZenohOptions

log = logging.getLogger("swanky.demo")

DEMO_ROBOT = "sim"
DEMO_BAG_SECONDS = 60.0
"""About one lap: a replay that loops starts again close to where it ended."""
MAX_DEMO_ROBOTS = 25
"""The issue's fleet on one PC. No port or thread limit sets it (one endpoint, one Zenoh session
per robot, one thread pacing them all), what each robot costs does: its bag is simulated before
the demo starts (1.7-2.1 s of CPU and 25 MB of temporary disk per 40 s of bag; 25 robots' bags
took 158 s on this shared 2-core machine under a load of 15), and the host's memory grows
(``swanky-host --demo --robots 25 --duration 30 --save``: peak RSS 1.7 GB, SLAM on). A larger
fleet is one of relays, on a bigger PC."""
HOST_WAIT_SECONDS = 30.0
BAG_MARGIN_SECONDS = 10.0


def demo_bag_seconds(duration: float | None) -> float:
    """How much to simulate: with --duration no more than the demo needs, plus a margin. The
    relays start replaying only once the bags are written and the host listens, about when the
    host's clock starts; without the margin a replay that ran a little ahead reached the end of
    its bag and looped, sending the first messages (the model, the first readings) again."""
    if duration is None:
        return DEMO_BAG_SECONDS
    return min(DEMO_BAG_SECONDS, max(duration, 1.0) + BAG_MARGIN_SECONDS)


def demo_robot_names(robots: str) -> list[str]:
    """The robots of ``--demo --robots N``: ``sim`` alone by default, else sim, sim2, ... simN."""
    if robots == "*":  # --robots left at its live default
        return [DEMO_ROBOT]
    try:
        count = int(robots)
    except ValueError:
        count = 0
    if not 1 <= count <= MAX_DEMO_ROBOTS:
        msg = (
            f"--robots {robots!r}: with --demo it is the number of simulated robots, "
            f"1 to {MAX_DEMO_ROBOTS} (e.g. --demo --robots 3)"
        )
        raise ConfigError(msg)
    return [DEMO_ROBOT if i == 0 else f"{DEMO_ROBOT}{i + 1}" for i in range(count)]


@dataclass(frozen=True, slots=True)
class DemoPlan:
    """``--demo --robots N``: the simulated robots, and the private loopback endpoint their
    relays reach the host on."""

    robots: tuple[str, ...]
    endpoint: str
    robot_filter: str = f"{DEMO_ROBOT}$*"
    """The host's ``--robots``: sim, sim2, ... (a Zenoh chunk wildcard)."""

    def host_zenoh(self, zenoh: ZenohOptions) -> ZenohOptions:
        """The host's session: listening on the demo's endpoint too, and no multicast, so no
        other robot joins by accident."""
        return replace(zenoh, listen=(*zenoh.listen, self.endpoint), multicast_scouting=False)


def configure_demo(robots: str) -> DemoPlan:
    """Check ``--robots`` before anything opens, and pick the demo relays' endpoint."""
    return DemoPlan(tuple(demo_robot_names(robots)), f"tcp/127.0.0.1:{free_loopback_port()}")


def free_loopback_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _write_bag(job: tuple[Path, float, float], stop: threading.Event | None = None) -> Path:
    path, seconds, route_offset = job
    return write_demo_bag(path, seconds, route_offset=route_offset, stop=stop)


@contextmanager
def _ctrl_c_ignored() -> Iterator[None]:
    """Processes started meanwhile ignore Ctrl-C for good (SIG_IGN survives exec, and Python
    then installs no KeyboardInterrupt handler): it reaches the whole process group, and the
    host stops the demo itself by terminating them. A Ctrl-C in these few milliseconds of
    process starting is lost; the host's own handler is back right after. Main thread only."""
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def write_bags(
    directory: Path, robots: list[str], seconds: float, stop: threading.Event
) -> list[Path] | None:
    """One bag per robot, spread evenly along the loop; several are written in parallel
    processes (the simulation is CPU-bound Python) so a fleet starts about as fast as one.
    None if ``stop`` was set meanwhile: the writing processes are terminated, not waited for."""
    spacing = lap_length() / len(robots)
    jobs = [(directory / robot, seconds, i * spacing) for i, robot in enumerate(robots)]
    workers = min(len(jobs), os.cpu_count() or 1)
    if workers == 1:
        bags = [_write_bag(job, stop) for job in jobs]  # here, each cut short by a stop
        return None if stop.is_set() else bags
    context = multiprocessing.get_context("spawn")  # never fork a process running zenoh threads
    with _ctrl_c_ignored():  # the pool starts its processes right away
        pool = context.Pool(workers)
    with pool:  # leaving it terminates the processes
        written = pool.map_async(_write_bag, jobs)
        while not stop.is_set():
            if written.ready():
                return written.get()
            written.wait(0.1)
        return None


class DemoRelays:
    """The robots' side of ``--demo``: writes the bags, then replays each through a relay of its
    own to the host at the plan's endpoint (``mode`` "client": a router's, as ``--workers``
    runs it)."""

    def __init__(
        self, plan: DemoPlan, stop: threading.Event, duration: float | None, mode: str | None = None
    ) -> None:
        self.plan = plan
        self._stop = stop
        self._mode = mode
        self._seconds = demo_bag_seconds(duration)
        self._relay_stop = threading.Event()
        self._relays: threading.Thread | None = None
        self._bags = tempfile.TemporaryDirectory(prefix="swanky-demo-")

    def write(self) -> list[Path] | None:
        """The robots' bags, watching the host's stop (None once it is set)."""
        robots = list(self.plan.robots)
        log.info("demo: simulating %s for %.0f s", ", ".join(robots), self._seconds)
        started = time.monotonic()
        bags = write_bags(Path(self._bags.name), robots, self._seconds, self._stop)
        if bags is not None:
            log.info("demo: bags written in %.1f s; relaying them over %s",
                     time.monotonic() - started, self.plan.endpoint)
        return bags

    def start(self, bags: list[Path]) -> None:
        self._relays = threading.Thread(
            target=relay_bags,
            args=(dict(zip(self.plan.robots, bags, strict=True)), self.plan.endpoint,
                  self._relay_stop, self._stop),
            kwargs={"mode": self._mode, "host_wait_s": HOST_WAIT_SECONDS}, name="demo-relays",
            daemon=True,
        )
        self._relays.start()

    def close(self) -> None:
        self._relay_stop.set()
        if self._relays is not None:
            self._relays.join(timeout=5.0 + 0.2 * len(self.plan.robots))
        self._bags.cleanup()


class DemoInput:
    """The :class:`~host_bridge.inputs.base.Input` of ``--demo``: the robots' relays
    (:class:`DemoRelays`) and what ``live`` (the host's live input, listening on the plan's
    endpoint) receives from them."""

    def __init__(
        self, plan: DemoPlan, live: Input, stop: threading.Event, duration: float | None
    ) -> None:
        self.plan = plan
        self._live = live
        self._relays = DemoRelays(plan, stop, duration)

    @property
    def last_activity(self) -> float:
        return self._live.last_activity

    def start(self, deliver: Deliver) -> None:
        """Write the bags (watching the host's stop), then start the relays and the live input."""
        bags = self._relays.write()
        if bags is None:
            return
        self._relays.start(bags)
        self._live.start(deliver)

    def ended(self) -> bool:
        return self._live.ended()

    def close(self) -> None:
        self._live.close()
        self._relays.close()
