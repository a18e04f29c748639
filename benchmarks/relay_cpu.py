"""CPU per message of the live relay against a bare rclpy raw subscriber of the same topics.

The small robot of ``tests/integration/ros_robot.py`` publishes (LaserScan 10 Hz, Odometry 30 Hz,
JointState 20 Hz, two /status publishers, a 640x480 rgb8 Image 15 Hz and a 50,000-point
PointCloud2 5 Hz from a second process) on a private ROS domain, localhost only. Then, one after
the other for the same time:

- baseline: a process with one rclpy node, ``raw=True`` subscriptions of the same topics with
  the relay's QoS, a callback that only counts, spun by rclpy's SingleThreadedExecutor (what the
  relay spins too);
- ``swanky-relay``, with a Zenoh subscriber in this process standing in for the host (so every
  topic is demanded), forwarding over loopback.

Each process's CPU (user + system: ``os.times()`` in the baseline, /proc for the relay) over the
measured window is divided by the messages it handled; the ratio relay / baseline is what the
relay adds. Needs the ``[ros-test]``
extra. Run: ``.venv/bin/python benchmarks/relay_cpu.py [--rounds 3] [--seconds 15]``.
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable
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
ROBOT = "bench"
Starter = Callable[..., "subprocess.Popen[str]"]


def bare_subscriber(warmup: float, seconds: float) -> None:
    """The baseline, run as its own process: prints the messages it received and the CPU
    seconds it used over ``seconds`` after ``warmup``."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions

    from robot_relay.sources.ros2 import message_class
    from robot_relay.stats import process_cpu_seconds

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("bare_subscriber")
    received = [0]

    def count_message(data: bytes, info: object) -> None:  # as the relay's, with message info
        received[0] += 1

    count: Callable[..., None] = count_message
    for topic, (msgtype, best_effort) in TOPICS.items():
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT if best_effort
                         else ReliabilityPolicy.RELIABLE)
        node.create_subscription(message_class(msgtype), topic, count, qos, raw=True)
    executor = SingleThreadedExecutor()
    executor.add_node(node)

    def spin_for(duration: float) -> None:
        ends = time.monotonic() + duration
        while time.monotonic() < ends:
            executor.spin_once(timeout_sec=0.1)

    spin_for(warmup)
    cpu, messages = process_cpu_seconds(), received[0]
    spin_for(seconds)
    print(received[0] - messages, process_cpu_seconds() - cpu, flush=True)
    executor.shutdown()
    node.destroy_node()
    rclpy.shutdown()


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def measure(proc: subprocess.Popen[str], warmup: float, seconds: float,
            count: Callable[[], int]) -> tuple[float, int]:
    """(CPU seconds of ``proc``, ``count()`` increase) over ``seconds`` after ``warmup``."""
    time.sleep(warmup)
    cpu, messages = cpu_seconds(proc.pid), count()
    time.sleep(seconds)
    return cpu_seconds(proc.pid) - cpu, count() - messages


Run = tuple[int, float]  # messages, CPU seconds


def run_bare(start: Starter, warmup: float, seconds: float) -> Run:
    bare = start(__file__, "--bare-subscriber", str(warmup), str(seconds))
    out, _ = bare.communicate(timeout=warmup + seconds + 60)
    messages, cpu = out.split()
    return int(messages), float(cpu)


def run_relay(start: Starter, warmup: float, seconds: float) -> Run:
    import zenoh

    from tests.integration.procs import free_port, open_loopback

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    relay = start("-m", "robot_relay.cli", "--robot", ROBOT, "-l", endpoint,
                  "--no-multicast-scouting", "--topics", *TOPICS)
    session = open_loopback("-e", endpoint)
    received = [0]
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        with lock:
            received[0] += 1

    subscriber = session.declare_subscriber(f"swanky/{ROBOT}/data/**", on_sample)
    try:
        cpu, messages = measure(relay, warmup, seconds, lambda: received[0])
    finally:
        relay.send_signal(signal.SIGTERM)
        relay.wait(timeout=30)
        subscriber.undeclare()
        session.close()
    return messages, cpu


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=15.0, help="measured time per run")
    parser.add_argument("--warmup", type=float, default=6.0, help="time before measuring")
    parser.add_argument("--rounds", type=int, default=3,
                        help="baseline then relay, this many times (the machine's load varies)")
    parser.add_argument("--bare-subscriber", type=float, nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.bare_subscriber is not None:
        bare_subscriber(*args.bare_subscriber)
        return 0

    sys.path.insert(0, str(ROOT))
    env = {**os.environ, "AMENT_PREFIX_PATH": sys.prefix, "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
           "ROS_DOMAIN_ID": str(1 + os.getpid() % 100), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
           "ROS_LOG_DIR": "/tmp/swanky_bench_ros_log", "PYTHONUNBUFFERED": "1", "PYTHONPATH": str(ROOT)}

    def start(*args: str) -> subprocess.Popen[str]:
        return subprocess.Popen([sys.executable, *args], stdout=subprocess.PIPE,
                                stderr=subprocess.DEVNULL, env=env, text=True)

    publishers = [start("-m", "tests.integration.ros_robot", role) for role in ("robot", "camera")]
    ratios = []
    try:
        time.sleep(3.0)
        for round_number in range(1, args.rounds + 1):
            (bare_messages, bare_cpu) = run_bare(start, args.warmup, args.seconds)
            (relay_messages, relay_cpu) = run_relay(start, args.warmup, args.seconds)
            bare_per = bare_cpu / bare_messages * 1e6
            relay_per = relay_cpu / relay_messages * 1e6
            ratios.append(relay_per / bare_per)
            print(f"round {round_number}: bare rclpy raw subscriber {bare_messages} msgs "
                  f"{bare_cpu:.2f} s CPU {bare_per:.0f} us/msg; swanky-relay {relay_messages} msgs "
                  f"{relay_cpu:.2f} s CPU {relay_per:.0f} us/msg; ratio {ratios[-1]:.2f}", flush=True)
    finally:
        for proc in publishers:
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=30)
    median = statistics.median(ratios)
    print(f"ratio relay / bare rclpy subscriber, CPU per message, median of {len(ratios)}: "
          f"{median:.2f} (the relay adds {(median - 1) * 100:+.0f} %)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
