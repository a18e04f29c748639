"""A real ROS 2 node (rclpy) driving the demo apartment's loop with a laser and drifting wheel
odometry, for the live SLAM test: ``python -m tests.integration.ros_robot laser SECONDS``.

It publishes what a TurtleBot's drivers publish and nothing more (no map, no SLAM): /scan
(LaserScan 5 Hz, 360 beams, sensor-data QoS), /odom (Odometry 30 Hz, reliable) with a 5 % scale
error and 2 deg/m heading drift, and /robot_description (transient local), whose fixed joint
places the laser on the base (the host reads the mount from it: the ros-jazzy wheels have no
tf2_msgs for a /tf_static),
from :func:`tests.host_bridge.slam.robot_logs.simulate`, in real time; each message stamped
with the simulated clock. Then it exits. Progress goes to stderr as ``ros_laser_robot: ...``.
"""

from __future__ import annotations

import math
import sys
import threading
import time

from tests.host_bridge.slam.robot_logs import LASER_XY, LASER_Z, LaserLog, simulate, timeline

URDF = f"""<?xml version="1.0"?>
<robot name="laser_bot">
  <link name="base_footprint"/>
  <link name="base_scan"><visual><geometry><cylinder radius="0.035" length="0.04"/></geometry></visual></link>
  <joint name="scan_joint" type="fixed">
    <parent link="base_footprint"/><child link="base_scan"/>
    <origin xyz="{LASER_XY[0]} {LASER_XY[1]} {LASER_Z}"/>
  </joint>
</robot>
"""


def say(text: str) -> None:
    print(f"ros_laser_robot: {text}", file=sys.stderr, flush=True)


def drive(seconds: float, stop: threading.Event) -> None:
    import rclpy
    from builtin_interfaces.msg import Time
    from nav_msgs.msg import Odometry
    from rclpy.qos import DurabilityPolicy, QoSProfile, qos_profile_sensor_data
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import LaserScan
    from std_msgs.msg import String

    run = simulate(LaserLog(seconds=seconds))
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("turtlebot_drivers")
    description = node.create_publisher(String, "/robot_description", QoSProfile(
        depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    odom_pub = node.create_publisher(Odometry, "/odom", QoSProfile(depth=10))
    scan_pub = node.create_publisher(LaserScan, "/scan", qos_profile_sensor_data)

    def stamp(ns: int) -> Time:
        sec, nanosec = divmod(ns, 1_000_000_000)
        return Time(sec=sec, nanosec=nanosec)

    description.publish(String(data=URDF))
    time.sleep(2.0)  # the relay discovers the topics before the robot moves
    say("publishing")
    started = time.monotonic()
    first = run.ticks[0].stamp_ns
    for sample in timeline(run):
        if stop.is_set():
            break
        delay = started + (sample.stamp_ns - first) / 1e9 - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        if sample.ranges is not None:
            scan = LaserScan(angle_min=run.angle_min, angle_max=run.angle_min + 359 * run.angle_increment,
                             angle_increment=run.angle_increment, scan_time=1.0 / run.log.scan_hz,
                             range_min=run.log.range_min, range_max=run.log.range_max,
                             ranges=sample.ranges.tolist())
            scan.header.stamp = stamp(sample.stamp_ns)
            scan.header.frame_id = "base_scan"
            scan_pub.publish(scan)
            continue
        x, y, yaw = (float(v) for v in sample.odom)
        odom = Odometry()
        odom.header.stamp = stamp(sample.stamp_ns)
        odom.header.frame_id, odom.child_frame_id = "odom", "base_footprint"
        odom.pose.pose.position.x, odom.pose.pose.position.y = x, y
        odom.pose.pose.orientation.z, odom.pose.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
        odom_pub.publish(odom)
    say("done")
    time.sleep(1.0)
    node.destroy_node()
    rclpy.shutdown()

