"""CPU per message of the live relay against a bare rclpy raw subscriber of the same topics,
for small messages and for large ones apart, and the relay's resident memory.

The small robot of ``tests/integration/ros_robot.py`` publishes (LaserScan 10 Hz, Odometry 30 Hz,
JointState 20 Hz, two /status publishers, a 640x480 rgb8 Image 15 Hz and a 50,000-point
PointCloud2 5 Hz from a second process) on a private ROS domain, localhost only. For the small
topics (scan, odom, joints, status: 0.1-6 KB) and then the large ones (image 0.9 MB, cloud 0.8
MB), three processes receive the same messages at the same time:

- baseline: one rclpy node, ``raw=True`` subscriptions of those topics with the relay's QoS, a
  callback that only counts, spun by rclpy's SingleThreadedExecutor;
- ``swanky-relay --topics ...`` as installed (its default ``--latency-budget``, 0.1 s), with a
  Zenoh subscriber in this process standing in for the host (so every topic is demanded),
  forwarding over loopback;
  the stand-in host is a remote one by default (``--host remote``: its session without Zenoh's
  shared memory, as a PC's across the network is, so none is negotiated: on a robot the host is
  always on another machine); ``--host local`` lets Zenoh use shared memory, as a host on the
  robot's own machine (a simulation) would;
- the same with ``--latency-budget 0`` (every message forwarded the moment it is taken).

Each window (``--seconds``; ``--rounds`` of them per group, beginning ``--warmup`` seconds after
every process had every topic) reads each process's CPU (user + system, every thread's
``/proc/<pid>/task/*/schedstat``: nanoseconds, where /proc's stat counts 10 ms ticks) and its
message count (the baseline's on SIGUSR1, the relays' at this process's subscriber), and divides.
Measuring the three over the same window matters: this shared machine's speed drifted by half
between runs a minute apart, which made sequential runs' ratios swing by 0.2. The ratio relay /
baseline, median over the windows, is what the relay costs against the plainest rclpy
subscriber. Targets (issue 25): at most 0.5 for small messages, at most 1.0 for large ones
(their copies are the floor). The relays' VmRSS and VmHWM are read from /proc at the end. Needs
the ``[ros-test]`` extra. Run: ``.venv/bin/python benchmarks/relay_cpu.py [--rounds 4]
[--seconds 10]``.

Where the relay's CPU went (perf with software clock sampling, py-spy, cProfile of the take
thread, per-thread schedstat; this 2-core machine, shared):

- With rclpy's SingleThreadedExecutor, small messages: 82 % of the samples in the Python
  threads (libpython 52 %); in the executor thread about 40 % of its busy samples rebuilt the
  wait set and ran the Task machinery per message, 38 % published to Zenoh (mostly the syscalls
  that wake Zenoh's transmit thread). Fast DDS's receive thread 8 %, Zenoh's transmit thread 9 %.
  Large messages: 56 % in the kernel, mostly page faults on fresh 1 MB buffers (clear_page_erms,
  exc_page_fault, unmap_page_range), memmove 9 %. The idle relay used 11-15 ms of CPU a second
  (the main thread's 20 Hz poll, the graph thread's 5 Hz waits, the executor's 0.1 s spins).
- With the take loop (robot_relay/sources/take_loop.py, robot_relay/heap.py) and no latency
  budget, small messages: the Python threads 11.0 ms of CPU a second, Zenoh's transmit thread
  4.2, Fast DDS's receive thread 3.4, Zenoh's net thread 0.9 (64 messages a second, mostly each
  at its own instant). Nearly all of it is paid per wake-up, not per message: the take thread
  wakes, waits on rcl again, and Zenoh's transmit thread wakes to write, once per message.
- With a 0.05 s budget, in the same windows: Python 7.9, Zenoh's transmit thread 1.8, Fast
  DDS 2.8, Zenoh net 0.9 (the net thread is Zenoh's shared-memory handoff reactor, woken 10 times
  a second while a peer on the same machine negotiated shared memory: a remote host, ``--host
  remote``, has none). The idle relay (topics present, no host) uses 1.6 ms a second, a third
  of it the graph thread's re-reading of the ROS graph every second.
- What a turn costs (scratch, in one process, a Zenoh subscriber without shared memory, turns 50
  ms apart): the thread's sleep 70-80 us of its CPU, the first Zenoh put after it about 80 (it
  wakes Zenoh's transmit thread), each further put of the turn 2; the relay's Python path on top
  about 60 us for a turn's first message and 7 for each further one. Hence the 0.1 s default:
  0.35-0.37 of the bare subscriber against 0.52-0.55 with 0.05 s (remote host, 5 windows).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import os
import select
import signal
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TOPICS = {  # topic -> (type, best effort)
    "/scan": ("sensor_msgs/msg/LaserScan", True),
    "/odom": ("nav_msgs/msg/Odometry", False),
    "/arm/joint_states": ("sensor_msgs/msg/JointState", False),
    "/status": ("std_msgs/msg/String", True),
    "/camera/image_raw": ("sensor_msgs/msg/Image", False),
    "/points": ("sensor_msgs/msg/PointCloud2", False),
}
GROUPS = {  # name -> (topics, target: the highest ratio relay / baseline allowed)
    "small": (("/scan", "/odom", "/arm/joint_states", "/status"), 0.5),
    "large": (("/camera/image_raw", "/points"), 1.0),
}
RELAYS = {  # name -> the relay's extra flags
    "swanky-relay": (),
    "swanky-relay --latency-budget 0": ("--latency-budget", "0"),
}
ROBOT = "bench"
HOSTS = {  # --host -> (the stand-in host's Zenoh flags, what it stands for)
    # Shared memory needs both ends on one machine: a host on the robot's network never has it.
    "remote": (("--cfg", "transport/shared_memory/enabled:false"),
               "no shared memory, as across a network"),
    "local": ((), "shared memory, as on the robot's own machine"),
}
STARTUP_TIMEOUT_S = 60.0
Starter = Callable[..., "subprocess.Popen[str]"]


def bare_subscriber(topics: Sequence[str]) -> None:
    """The baseline, run as its own process until killed: prints "ready" once every topic
    delivered, then its count of messages whenever SIGUSR1 asks."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions

    from robot_relay.sources.ros2 import message_class

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("bare_subscriber")
    received = dict.fromkeys(topics, 0)

    def counter(topic: str) -> Callable[..., None]:
        def count_message(data: bytes, info: object) -> None:  # as the relay's, with message info
            received[topic] += 1

        return count_message

    for topic in topics:
        msgtype, best_effort = TOPICS[topic]
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT if best_effort
                         else ReliabilityPolicy.RELIABLE)
        node.create_subscription(message_class(msgtype), topic, counter(topic), qos, raw=True)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    # Handled on this thread once spin_once returns (within its 0.1 s): nothing runs per message.
    signal.signal(signal.SIGUSR1, lambda *_: print(sum(received.values()), flush=True))
    while not all(received.values()):
        executor.spin_once(timeout_sec=0.1)
    print("ready", flush=True)
    while True:
        executor.spin_once(timeout_sec=0.1)


def cpu_seconds(pid: int) -> float:
    """User + system CPU of ``pid``, in /proc's 10 ms ticks (the threads that ended included)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def thread_cpu_seconds(pid: int) -> float:
    """CPU of ``pid``'s threads to the nanosecond (schedstat); a thread that ended meanwhile is
    missing, so only for processes whose threads last (these do, while measured)."""
    total = 0
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            total += int((task / "schedstat").read_text().split()[0])
        except (OSError, IndexError):  # the thread ended just now
            continue
    return total / 1e9


def memory_mb(pid: int) -> tuple[float, float]:
    """(VmRSS, VmHWM) of ``pid`` in MB."""
    fields = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines())
    rss, peak = (int(fields[key].split()[0]) / 1024 for key in ("VmRSS", "VmHWM"))
    return rss, peak


def read_line(proc: subprocess.Popen[str], timeout: float, what: str) -> str:
    assert proc.stdout is not None
    ready, _, _ = select.select([proc.stdout], [], [], timeout)
    line = proc.stdout.readline() if ready else ""
    if not line:
        raise RuntimeError(f"the bare subscriber gave no {what} within {timeout:.0f} s "
                           f"(exit code {proc.poll()})")
    return line.strip()


@dataclass
class Receiver:
    """One process receiving the group's messages and how to count them."""

    name: str
    proc: subprocess.Popen[str]
    count: Callable[[], int]


@dataclass(frozen=True, slots=True)
class Window:
    messages: dict[str, int]
    cpu_s: dict[str, float]

    def us_per_message(self, name: str) -> float:
        return self.cpu_s[name] / self.messages[name] * 1e6


def total(counts: dict[str, int]) -> int:
    return sum(counts.values())


def start_bare(start: Starter, topics: Sequence[str]) -> Receiver:
    bare = start(__file__, "--bare-subscriber", *topics)

    def count() -> int:
        bare.send_signal(signal.SIGUSR1)
        return int(read_line(bare, 10.0, "count"))

    return Receiver("bare rclpy subscriber", bare, count)


def measure_group(
    start: Starter, topics: Sequence[str], warmup: float, seconds: float, windows: int, *,
    host_flags: Sequence[str],
) -> tuple[list[Window], dict[str, tuple[float, float]]]:
    """The baseline and both relays over the same ``windows``, each relay forwarding to a
    stand-in host opened with ``host_flags``; each relay's (VmRSS, VmHWM)."""
    import zenoh

    from robot_relay.wire import data_key
    from tests.integration.procs import free_port, open_loopback

    with contextlib.ExitStack() as stack:
        bare = start_bare(start, topics)
        stack.callback(bare.proc.wait, 30)
        stack.callback(bare.proc.kill)
        receivers = [bare]
        counts: dict[str, dict[str, int]] = {}
        lock = threading.Lock()
        for name, flags in RELAYS.items():
            endpoint = f"tcp/127.0.0.1:{free_port()}"
            relay = start("-m", "robot_relay.cli", "--robot", ROBOT, "-l", endpoint,
                          "--no-multicast-scouting", "--topics", *topics, *flags)
            stack.callback(relay.wait, 30)
            stack.callback(relay.send_signal, signal.SIGTERM)
            session = open_loopback("-e", endpoint, *host_flags)
            stack.callback(session.close)
            received = counts[name] = {data_key(ROBOT, topic): 0 for topic in topics}

            def on_sample(sample: zenoh.Sample, received: dict[str, int] = received) -> None:
                with lock:
                    received[str(sample.key_expr)] += 1

            subscriber = session.declare_subscriber(f"swanky/{ROBOT}/data/**", on_sample)
            stack.callback(subscriber.undeclare)
            receivers.append(Receiver(name, relay, functools.partial(total, received)))
        if read_line(bare.proc, STARTUP_TIMEOUT_S, "ready line") != "ready":
            raise RuntimeError("the bare subscriber did not say ready")
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while not all(all(received.values()) for received in counts.values()):
            if time.monotonic() > deadline:
                raise RuntimeError(f"a relay forwarded no message of some topic within "
                                   f"{STARTUP_TIMEOUT_S:.0f} s: {counts}")
            time.sleep(0.1)
        time.sleep(warmup)

        def reading() -> tuple[dict[str, int], dict[str, float]]:
            return ({r.name: r.count() for r in receivers},
                    {r.name: thread_cpu_seconds(r.proc.pid) for r in receivers})

        results = []
        before = reading()
        for _ in range(windows):
            time.sleep(seconds)
            after = reading()
            results.append(Window(
                {name: after[0][name] - before[0][name] for name in after[0]},
                {name: after[1][name] - before[1][name] for name in after[1]},
            ))
            before = after
        memory = {r.name: memory_mb(r.proc.pid) for r in receivers[1:]}
    return results, memory


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="measured time per window")
    parser.add_argument("--warmup", type=float, default=2.0,
                        help="time before measuring, once every process had every topic")
    parser.add_argument("--rounds", type=int, default=4, help="windows per group")
    parser.add_argument("--host", choices=HOSTS, default="remote",
                        help="the stand-in host: on another machine, as on a robot (no shared "
                             "memory), or on this one (default %(default)s)")
    parser.add_argument("--domain-id", type=int, default=1 + os.getpid() % 100,
                        help="the private ROS_DOMAIN_ID of the run (default: from the process id)")
    parser.add_argument("--bare-subscriber", nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.bare_subscriber is not None:
        bare_subscriber(args.bare_subscriber)
        return 0

    sys.path.insert(0, str(ROOT))
    env = {**os.environ, "AMENT_PREFIX_PATH": sys.prefix, "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
           "ROS_DOMAIN_ID": str(args.domain_id), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
           "ROS_LOG_DIR": "/tmp/swanky_bench_ros_log", "PYTHONUNBUFFERED": "1", "PYTHONPATH": str(ROOT)}

    def start(*args: str) -> subprocess.Popen[str]:
        return subprocess.Popen([sys.executable, *args], stdout=subprocess.PIPE,
                                stderr=subprocess.DEVNULL, env=env, text=True)

    host_flags, host_kind = HOSTS[args.host]
    print(f"stand-in host: {args.host} ({host_kind})", flush=True)
    publishers = [start("-m", "tests.integration.ros_robot", role) for role in ("robot", "camera")]
    baseline = "bare rclpy subscriber"
    ratios: dict[tuple[str, str], list[float]] = {}
    memory: list[tuple[float, float]] = []
    try:
        time.sleep(3.0)
        for group, (topics, _) in GROUPS.items():
            windows, group_memory = measure_group(start, topics, args.warmup, args.seconds,
                                                  args.rounds, host_flags=host_flags)
            memory.extend(group_memory.values())
            for number, window in enumerate(windows, 1):
                bare = window.us_per_message(baseline)
                parts = [f"{baseline} {window.messages[baseline]} msgs {bare:.0f} us/msg"]
                for name in RELAYS:
                    ratio = window.us_per_message(name) / bare
                    ratios.setdefault((group, name), []).append(ratio)
                    parts.append(f"{name} {window.messages[name]} msgs "
                                 f"{window.us_per_message(name):.0f} us/msg, ratio {ratio:.2f}")
                print(f"{group} window {number}: " + "; ".join(parts), flush=True)
            for name, (rss, peak) in group_memory.items():
                print(f"{group}: {name} VmRSS {rss:.0f} MB, VmHWM {peak:.0f} MB", flush=True)
    finally:
        for proc in publishers:
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=30)
    for group, (topics, target) in GROUPS.items():
        for name in RELAYS:
            median = statistics.median(ratios[group, name])
            judged = name == "swanky-relay"
            verdict = ("met" if median <= target else f"missed by {median / target - 1:.0%}") if judged \
                else "for comparison, not judged"
            print(f"{group} messages ({', '.join(topics)}): {name} / bare rclpy subscriber, CPU per "
                  f"message, median of {len(ratios[group, name])}: {median:.2f} "
                  f"(target <= {target}: {verdict})")
    print(f"relay resident memory: VmRSS {max(m[0] for m in memory):.0f} MB at most, "
          f"VmHWM {max(m[1] for m in memory):.0f} MB at most")
    return 0


if __name__ == "__main__":
    sys.exit(main())
