"""An rmw_zenoh robot without ROS, made with zenoh-ros2-sdk (an rmw_zenoh implementation written
independently of Swanky, from PyPI): ``python -m tests.integration.rmw_publisher PORT``.

Node ``/pupper/lidar`` publishes ``/pupper/scan`` in the Humble key form (TypeHashNotSupported)
and ``/tf`` in the Jazzy form (RIHS01 hash); node ``/power`` (no namespace) publishes
``/voltage``. Once the host subscribes, COUNT messages each, then the nodes leave.
"""

from __future__ import annotations

import math
import sys
import time

SCAN_RANGES = (1.0, 2.0, 3.0, 4.0)  # + i for message i
ANGLE_INCREMENT = math.pi / 2
TRANSLATION = (1.5, -2.0, 0.25)  # + (i, 0, 0) for message i
YAW = 0.5
STAMP_SEC = 1_700_000_000  # + i for message i
COUNT = 5


def main() -> None:
    import numpy as np
    from rosbags.typesys import Stores, get_typestore
    from zenoh_ros2_sdk import ROS2Publisher

    port = int(sys.argv[1])
    store = get_typestore(Stores.ROS2_HUMBLE)

    def publisher(topic: str, msgtype: str, namespace: str, node: str, humble: bool) -> ROS2Publisher:
        return ROS2Publisher(
            topic, msgtype, msg_definition=store.generate_msgdef(msgtype, ros_version=2)[0],
            node_name=node, namespace=namespace, domain_id=0, router_port=port,
            type_hash="TypeHashNotSupported" if humble else store.hash_rihs01(msgtype),
        )

    scan = publisher("/pupper/scan", "sensor_msgs/msg/LaserScan", "/pupper", "lidar", True)
    tf = publisher("/tf", "tf2_msgs/msg/TFMessage", "/pupper", "lidar", False)
    voltage = publisher("/voltage", "std_msgs/msg/Float32", "/", "power", False)
    types = scan.session_mgr.store.types
    deadline = time.monotonic() + 60
    pubs = (scan, tf, voltage)
    while not all(p.pub.matching_status.matching for p in pubs) and time.monotonic() < deadline:
        time.sleep(0.05)
    for i in range(COUNT):
        header = types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=STAMP_SEC + i, nanosec=0),
            frame_id="laser",
        )
        scan.publish(
            header=header, angle_min=0.0, angle_max=3 * ANGLE_INCREMENT,
            angle_increment=ANGLE_INCREMENT, time_increment=0.0, scan_time=0.1, range_min=0.1,
            range_max=10.0, ranges=np.array(SCAN_RANGES, dtype=np.float32) + i,
            intensities=np.array([], dtype=np.float32),
        )
        transform = types["geometry_msgs/msg/TransformStamped"](
            header=types["std_msgs/msg/Header"](stamp=header.stamp, frame_id="odom"),
            child_frame_id="base_link",
            transform=types["geometry_msgs/msg/Transform"](
                translation=types["geometry_msgs/msg/Vector3"](
                    x=TRANSLATION[0] + i, y=TRANSLATION[1], z=TRANSLATION[2]),
                rotation=types["geometry_msgs/msg/Quaternion"](
                    x=0.0, y=0.0, z=math.sin(YAW / 2), w=math.cos(YAW / 2)),
            ),
        )
        tf.publish(transforms=[transform])
        voltage.publish(data=12.0 + i)
        time.sleep(0.05)
    time.sleep(1.0)
    for pub in pubs:
        pub.close()
    time.sleep(1.0)
    scan.session_mgr.close()


if __name__ == "__main__":
    main()
