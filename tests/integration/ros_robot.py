"""Real ROS 2 nodes (rclpy) publishing like a small robot, for the live relay tests.

``python -m tests.integration.ros_robot robot`` runs until SIGTERM/SIGINT:

- ``/scan`` LaserScan 10 Hz, sensor-data QoS (best effort, depth 5);
- ``/odom`` Odometry 30 Hz, reliable, depth 10;
- ``/arm/joint_states`` JointState 20 Hz from the node ``/arm/arm_driver`` (a namespace);
- ``/robot_description`` (transient local, depth 1) published once at start;
- ``/status`` String 2 Hz from two nodes, one reliable and one best effort.

``... camera`` (another process, like a camera driver) until SIGTERM/SIGINT:

- ``/camera/image_raw`` Image 640x480 rgb8 15 Hz, reliable, depth 10;
- ``/points`` PointCloud2 of 50,000 points 5 Hz, reliable, depth 10.

``python -m tests.integration.ros_robot late SECONDS`` starts :data:`LATE_NODES` + 1 nodes, each
logging one line (so /rosout gains publishers mid-run), waits until it sees the relay's node,
then publishes ``/late_chatter`` at 10 Hz for SECONDS and exits.

Message ``i`` of a topic is stamped ``T0_NS + i * period`` and carries values derived from
``i`` (:func:`odom_values`, :func:`joint_position`, :func:`image_pixels`, :func:`first_point_x`),
so a test reading the host's recording knows exactly what each message held. Progress goes to
stderr as ``ros_robot: ...`` lines. rclpy is imported only when run, so tests can import the
constants without ROS installed.
"""

from __future__ import annotations

import math
import signal
import struct
import sys
import threading
import time
from typing import Any

import numpy as np
from numpy.typing import NDArray

T0_NS = 1_700_000_000_000_000_000
ODOM_HZ, SCAN_HZ, IMAGE_HZ, CLOUD_HZ, JOINT_HZ, STATUS_HZ = 30, 10, 15, 5, 20, 2
WIDTH, HEIGHT = 640, 480
CLOUD_POINTS = 50_000
JOINT = "arm_joint"
LATE_NODES = 10
URDF = """<?xml version="1.0"?>
<robot name="tiny">
  <link name="base_footprint"/>
  <link name="base_link"><visual><geometry><box size="0.3 0.2 0.1"/></geometry></visual></link>
  <link name="arm_link"><visual><geometry><box size="0.05 0.05 0.2"/></geometry></visual></link>
  <joint name="base_joint" type="fixed">
    <parent link="base_footprint"/><child link="base_link"/><origin xyz="0 0 0.05"/>
  </joint>
  <joint name="arm_joint" type="revolute">
    <parent link="base_link"/><child link="arm_link"/><origin xyz="0.1 0 0.1"/>
    <axis xyz="0 0 1"/><limit lower="-3.14" upper="3.14" effort="1" velocity="1"/>
  </joint>
</robot>
"""


def stamp_ns(index: int, hz: int) -> int:
    return T0_NS + index * (1_000_000_000 // hz)


def odom_values(index: int) -> tuple[float, float, float]:
    """(x, y, yaw) of odometry message ``index``."""
    return index * 0.001, -index * 0.002, index * 0.001


def joint_position(index: int) -> float:
    return math.remainder(index * 0.01, 2 * math.pi)


def image_pixels(index: int) -> NDArray[np.uint8]:
    """Row-major rgb8 bytes of frame ``index``: a fixed pattern, the first 8 bytes the index."""
    pixels = (np.arange(WIDTH * HEIGHT * 3, dtype=np.uint32) % 251).astype(np.uint8)
    pixels[:8] = np.frombuffer(struct.pack("<Q", index), np.uint8)
    return pixels


def cloud_points() -> NDArray[np.float32]:
    """x, y, z of every point: a 250 x 200 grid 1 m ahead, z from the column."""
    columns, rows = np.meshgrid(np.arange(250, dtype=np.float32), np.arange(200, dtype=np.float32))
    return np.stack([np.full(CLOUD_POINTS, 1.0, np.float32), columns.ravel() * 0.01,
                     rows.ravel() * 0.01], axis=1).astype(np.float32)


def first_point_x(index: int) -> float:
    """Cloud ``index``'s first point has this x (the others are :func:`cloud_points`)."""
    return float(index)


def say(text: str) -> None:
    print(f"ros_robot: {text}", file=sys.stderr, flush=True)


def _stamp(index: int, hz: int) -> Any:
    from builtin_interfaces.msg import Time

    sec, nanosec = divmod(stamp_ns(index, hz), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def _patched(template: bytes, index: int, hz: int, patches: list[tuple[int, bytes]]) -> bytes:
    """``template`` (CDR of a message with a Header first) with the stamp of ``index`` and
    ``patches`` written in: big messages are serialised once, not per publish."""
    data = bytearray(template)
    sec, nanosec = divmod(stamp_ns(index, hz), 1_000_000_000)
    data[4:12] = struct.pack("<iI", sec, nanosec)
    for offset, value in patches:
        data[offset:offset + len(value)] = value
    return bytes(data)


class Counter:
    def __init__(self) -> None:
        self.value = -1

    def next(self) -> int:
        self.value += 1
        return self.value


def robot(stop: threading.Event) -> None:
    import rclpy
    from nav_msgs.msg import Odometry
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import JointState, LaserScan
    from std_msgs.msg import String

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    main = rclpy.create_node("robot")
    arm = rclpy.create_node("arm_driver", namespace="/arm")
    status_a = rclpy.create_node("status_a")
    status_b = rclpy.create_node("status_b")
    reliable = QoSProfile(depth=10)
    latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)

    description = main.create_publisher(String, "/robot_description", latched)
    description.publish(String(data=URDF))
    main.get_logger().info("robot up")

    odom_pub = main.create_publisher(Odometry, "/odom", reliable)
    odom_count = Counter()

    def odom() -> None:
        i = odom_count.next()
        x, y, yaw = odom_values(i)
        msg = Odometry()
        msg.header.stamp = _stamp(i, ODOM_HZ)
        msg.header.frame_id = "odom"
        msg.child_frame_id = "base_footprint"
        msg.pose.pose.position.x, msg.pose.pose.position.y = x, y
        msg.pose.pose.orientation.z, msg.pose.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
        msg.twist.twist.linear.x = 0.5
        odom_pub.publish(msg)

    scan_pub = main.create_publisher(LaserScan, "/scan", qos_profile_sensor_data)
    scan_count = Counter()

    def scan() -> None:
        i = scan_count.next()
        msg = LaserScan(angle_min=-math.pi, angle_max=math.pi, angle_increment=2 * math.pi / 360,
                        range_min=0.1, range_max=10.0, ranges=[1.0 + (k % 10) * 0.1 for k in range(360)])
        msg.header.stamp = _stamp(i, SCAN_HZ)
        msg.header.frame_id = "base_scan"
        scan_pub.publish(msg)

    joint_pub = arm.create_publisher(JointState, "joint_states", reliable)
    joint_count = Counter()

    def joints() -> None:
        i = joint_count.next()
        msg = JointState(name=[JOINT], position=[joint_position(i)])
        msg.header.stamp = _stamp(i, JOINT_HZ)
        joint_pub.publish(msg)

    status_reliable = status_a.create_publisher(String, "/status", reliable)
    status_best_effort = status_b.create_publisher(
        String, "/status", QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT)
    )
    status_count = Counter()

    def status() -> None:
        i = status_count.next()
        status_reliable.publish(String(data=f"a {i}"))
        status_best_effort.publish(String(data=f"b {i}"))

    main.create_timer(1 / ODOM_HZ, odom)
    main.create_timer(1 / SCAN_HZ, scan)
    arm.create_timer(1 / JOINT_HZ, joints)
    status_a.create_timer(1 / STATUS_HZ, status)
    executor = SingleThreadedExecutor()
    for node in (main, arm, status_a, status_b):
        executor.add_node(node)
    say("publishing")
    while not stop.is_set():
        executor.spin_once(timeout_sec=0.1)
    say(f"published odom {odom_count.value + 1} joints {joint_count.value + 1}")
    executor.shutdown()
    for node in (main, arm, status_a, status_b):
        node.destroy_node()
    rclpy.shutdown()


def camera(stop: threading.Event) -> None:
    """The camera driver: its own process, as on a robot."""
    import rclpy
    from rclpy.qos import QoSProfile
    from rclpy.serialization import serialize_message
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import Image, PointCloud2, PointField

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    main = rclpy.create_node("camera")
    reliable = QoSProfile(depth=10)
    image_pub = main.create_publisher(Image, "/camera/image_raw", reliable)
    image = Image(height=HEIGHT, width=WIDTH, encoding="rgb8", step=WIDTH * 3,
                  data=image_pixels(0).tobytes())
    image.header.frame_id = "camera"
    image_template = serialize_message(image)
    pixels_at = image_template.index(bytes(image.data))
    image_count = Counter()

    def frame() -> None:
        i = image_count.next()
        image_pub.publish(_patched(image_template, i, IMAGE_HZ, [(pixels_at, struct.pack("<Q", i))]))

    cloud_pub = main.create_publisher(PointCloud2, "/points", reliable)
    cloud = PointCloud2(
        height=1, width=CLOUD_POINTS, is_bigendian=False, point_step=12, row_step=12 * CLOUD_POINTS,
        is_dense=True, data=cloud_points().tobytes(),
        fields=[PointField(name=n, offset=4 * k, datatype=PointField.FLOAT32, count=1)
                for k, n in enumerate("xyz")],
    )
    cloud.header.frame_id = "base_link"
    cloud_template = serialize_message(cloud)
    points_at = cloud_template.index(bytes(cloud.data))
    cloud_count = Counter()

    def points() -> None:
        i = cloud_count.next()
        cloud_pub.publish(_patched(cloud_template, i, CLOUD_HZ,
                                   [(points_at, struct.pack("<f", first_point_x(i)))]))

    main.create_timer(1 / IMAGE_HZ, frame)
    main.create_timer(1 / CLOUD_HZ, points)
    say("publishing")
    while not stop.is_set():
        rclpy.spin_once(main, timeout_sec=0.1)
    say(f"published image {image_count.value + 1} cloud {cloud_count.value + 1}")
    main.destroy_node()
    rclpy.shutdown()


def late(seconds: float, stop: threading.Event) -> None:
    import rclpy
    from rclpy.qos import QoSProfile
    from rclpy.signals import SignalHandlerOptions
    from std_msgs.msg import String

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("late")
    helpers = [rclpy.create_node(f"late_helper_{k}") for k in range(LATE_NODES)]
    for k, helper in enumerate(helpers):
        helper.get_logger().info(f"late helper {k} up")
    # The topic appears once this process's participant and the relay's know each other: how
    # long that takes is Fast DDS's participant discovery (its announcements come every 3 s).
    known = time.monotonic() + 30
    while "swanky_relay" not in node.get_node_names() and time.monotonic() < known:
        time.sleep(0.05)
    publisher = node.create_publisher(String, "/late_chatter", QoSProfile(depth=10))
    say(f"late first publish at {time.time_ns()}")
    ends = time.monotonic() + seconds
    i = 0
    while not stop.is_set() and time.monotonic() < ends:
        publisher.publish(String(data=f"late {i}"))
        i += 1
        rclpy.spin_once(node, timeout_sec=0.1)
    say(f"late published {i}, leaving")
    for helper in helpers:
        helper.destroy_node()
    node.destroy_node()
    rclpy.shutdown()


def main(argv: list[str]) -> int:
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    if argv[:1] == ["robot"]:
        robot(stop)
    elif argv[:1] == ["camera"]:
        camera(stop)
    elif argv[:1] == ["late"] and len(argv) == 2:
        late(float(argv[1]), stop)
    elif argv[:1] == ["laser"] and len(argv) == 2:
        from tests.integration.ros_laser_robot import drive

        drive(float(argv[1]), stop)
    else:
        print("usage: ros_robot.py robot | camera | late SECONDS | laser SECONDS", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
