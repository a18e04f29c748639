"""A robot and a PC in two network namespaces joined by an emulated bad link.

This kernel has no ``netem`` qdisc (no delay, no loss in ``tc``), only ``tbf``. So the link is
two TUN devices, one in each namespace, and a small Python process (the "wire", run as
``python -m tests.integration.emulated_link``) that forwards the IP packets between them:

- each direction delays every packet by ``delay_s`` (a FIFO: order is kept, as on a cable) and
  drops each one with probability ``loss`` (a seeded random stream);
- the kernel's ``tbf`` on each TUN device's egress limits each direction to ``rate_mbit``;
- SIGUSR1 cuts the link (every packet is dropped, as when a robot leaves Wi-Fi range: no
  reset, no error, silence) and SIGUSR2 restores it.

A veth pair would join the namespaces too, but its packets never leave the kernel, so there is
nowhere to delay or lose them without netem. Through the TUN pair the kernel's own TCP sees real
loss, retransmits and backs off, as over a bad Wi-Fi link; the relay and the host run unchanged
(``ip netns exec``) and talk Zenoh over TCP to each other's namespace address.

SIGTERM stops the wire, which prints its per-direction packet counts as one JSON line. Its TUN
devices vanish with it; :func:`emulated_link` deletes the namespaces, whatever happened.
"""

from __future__ import annotations

import fcntl
import json
import os
import random
import select
import shutil
import signal
import struct
import subprocess
import sys
import time
from collections import deque
from collections.abc import Iterator, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from tests.integration.procs import command

TUNSETIFF = 0x400454CA
IFF_TUN = 0x0001
IFF_NO_PI = 0x1000
READY = "wire ready"
SUBNET = "10.231.{}.{}"


@dataclass(frozen=True, slots=True)
class LinkShape:
    """What the link does to each direction."""

    delay_s: float = 0.0
    """One-way delay, each direction (the round trip is twice this)."""
    loss: float = 0.0
    """Probability that a packet is lost, each direction."""
    rate_mbit: float | None = None
    """Each direction's rate (tbf); None: as fast as the wire process forwards."""

    def describe(self) -> str:
        parts = [f"{self.loss:.0%} packet loss and {self.delay_s * 1000:.0f} ms delay each way"]
        if self.rate_mbit is not None:
            parts.append(f"{self.rate_mbit:g} Mbit/s (tbf) each way")
        return ", ".join(parts)


@dataclass
class Link:
    """A running link: the namespaces' names and addresses, and the wire process."""

    robot_ns: str
    pc_ns: str
    robot_ip: str
    pc_ip: str
    shape: LinkShape
    wire: subprocess.Popen[str]
    counts: dict[str, Any] | None = None
    """The wire's packet counts per direction, once it stopped."""

    def in_robot(self, cmd: Sequence[str]) -> list[str]:
        return ["ip", "netns", "exec", self.robot_ns, *cmd]

    def in_pc(self, cmd: Sequence[str]) -> list[str]:
        return ["ip", "netns", "exec", self.pc_ns, *cmd]

    def cut(self) -> None:
        self.wire.send_signal(signal.SIGUSR1)

    def restore(self) -> None:
        self.wire.send_signal(signal.SIGUSR2)


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True, timeout=30)


def require_netns() -> None:
    """Skip (with the reason) where namespaces cannot be made: not root, no iproute2, no TUN."""
    if os.geteuid() != 0:
        pytest.skip("network namespaces need root (ip netns add); not root here")
    if shutil.which("ip") is None:
        pytest.skip("iproute2's ip command is not installed")
    if not Path("/dev/net/tun").exists():
        pytest.skip("no /dev/net/tun: the emulated link needs TUN devices")


@contextmanager
def emulated_link(shape: LinkShape) -> Iterator[Link]:
    """Two fresh namespaces joined by the wire; torn down (wire stopped, namespaces deleted)
    on the way out, also when the test failed."""
    require_netns()
    tag = f"{os.getpid() % 100000}{random.randrange(100):02d}"
    robot_ns, pc_ns = f"swanky-robot-{tag}", f"swanky-pc-{tag}"
    robot_dev, pc_dev = f"swkr{tag}", f"swkp{tag}"
    subnet = random.randrange(1, 250)
    robot_ip, pc_ip = SUBNET.format(subnet, 1), SUBNET.format(subnet, 2)
    with ExitStack() as cleanup:
        for ns in (robot_ns, pc_ns):
            _ip("netns", "add", ns)
            cleanup.callback(subprocess.run, ["ip", "netns", "delete", ns], capture_output=True,
                             timeout=30)
        wire = subprocess.Popen(
            command("tests.integration.emulated_link", robot_dev, pc_dev, str(shape.delay_s),
                    str(shape.loss)),
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        link = Link(robot_ns, pc_ns, robot_ip, pc_ip, shape, wire)
        cleanup.callback(_stop_wire, link)
        assert wire.stdout is not None
        line = wire.stdout.readline()
        assert line.strip() == READY, (line, wire.stderr.read() if wire.stderr else "")
        for ns, dev, mine, other in ((robot_ns, robot_dev, robot_ip, pc_ip),
                                     (pc_ns, pc_dev, pc_ip, robot_ip)):
            _ip("link", "set", dev, "netns", ns)
            _ip("-n", ns, "link", "set", "lo", "up")
            _ip("-n", ns, "addr", "add", mine, "peer", other, "dev", dev)
            _ip("-n", ns, "link", "set", dev, "up")
            if shape.rate_mbit is not None:
                # A burst of ten full packets; a queue of at most 200 ms at the rate.
                subprocess.run(["tc", "-n", ns, "qdisc", "add", "dev", dev, "root", "tbf", "rate",
                                f"{shape.rate_mbit}mbit", "burst", "15kb", "latency", "200ms"],
                               check=True, capture_output=True, timeout=30)
        yield link


def _stop_wire(link: Link) -> None:
    if link.wire.poll() is None:
        link.wire.send_signal(signal.SIGTERM)
        try:
            out, _ = link.wire.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            link.wire.kill()
            out, _ = link.wire.communicate(timeout=10)
        lines = out.strip().splitlines()
        if lines:
            link.counts = json.loads(lines[-1])


# -- the wire process --------------------------------------------------------------------------


def _open_tun(name: str) -> int:
    fd = os.open("/dev/net/tun", os.O_RDWR | os.O_NONBLOCK)
    fcntl.ioctl(fd, TUNSETIFF, struct.pack("16sH", name.encode(), IFF_TUN | IFF_NO_PI))
    return fd


@dataclass
class _Direction:
    source: int
    target: int
    queue: deque[tuple[float, bytes]]
    forwarded: int = 0
    lost: int = 0
    cut: int = 0
    resets: int = 0
    """TCP segments with RST forwarded (a connection torn down, its unsent data thrown away)."""


def _is_tcp_reset(packet: bytes) -> bool:
    """An IPv4 TCP segment with the RST flag."""
    if len(packet) < 20 or packet[0] >> 4 != 4 or packet[9] != 6:
        return False
    flags_at = (packet[0] & 0x0F) * 4 + 13
    return len(packet) > flags_at and bool(packet[flags_at] & 0x04)


def wire(robot_dev: str, pc_dev: str, delay_s: float, loss: float) -> None:
    """Forward packets between the two TUN devices until SIGTERM; print the counts."""
    robot, pc = _open_tun(robot_dev), _open_tun(pc_dev)
    directions = {
        "robot_to_pc": _Direction(robot, pc, deque()),
        "pc_to_robot": _Direction(pc, robot, deque()),
    }
    by_source = {d.source: d for d in directions.values()}
    chance = random.Random(14)  # the same loss pattern every run
    state = {"cut": False, "stop": False, "cuts": 0}

    def cut(*_: object) -> None:
        state["cut"] = True
        state["cuts"] += 1

    def restore(*_: object) -> None:
        state["cut"] = False

    def stop(*_: object) -> None:
        state["stop"] = True

    signal.signal(signal.SIGUSR1, cut)
    signal.signal(signal.SIGUSR2, restore)
    signal.signal(signal.SIGTERM, stop)
    print(READY, flush=True)
    while not state["stop"]:
        now = time.monotonic()
        due = [d.queue[0][0] for d in directions.values() if d.queue]
        timeout = min(0.05, max(0.0, min(due) - now)) if due else 0.05
        try:
            readable, _, _ = select.select([robot, pc], [], [], timeout)
        except InterruptedError:
            continue
        now = time.monotonic()
        for fd in readable:
            direction = by_source[fd]
            while True:
                try:
                    packet = os.read(fd, 65536)
                except (BlockingIOError, OSError):  # drained, or the device went down
                    break
                if state["cut"]:
                    direction.cut += 1
                elif chance.random() < loss:
                    direction.lost += 1
                else:
                    direction.queue.append((now + delay_s, packet))
        for direction in directions.values():
            while direction.queue and direction.queue[0][0] <= now:
                _, packet = direction.queue.popleft()
                try:
                    os.write(direction.target, packet)
                    direction.forwarded += 1
                    direction.resets += _is_tcp_reset(packet)
                except OSError:  # the far device is down: the packet is lost
                    direction.lost += 1
    counts: dict[str, Any] = {
        name: {"forwarded": d.forwarded, "lost": d.lost, "cut": d.cut, "resets": d.resets}
        for name, d in directions.items()
    }
    counts["cuts"] = state["cuts"]
    print(json.dumps(counts), flush=True)


if __name__ == "__main__":
    wire(sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4]))
