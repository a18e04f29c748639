"""The demo robot's topics as real CDR from the ROS 2 Humble definitions, with the frames,
rates and QoS a real robot offers: :func:`simulate` gives every message of a run in time order.

Everything is a pure function of time and start position (no randomness, no clock), so two runs
give the same bytes. The URDF goes out on /robot_description and its fixed joints on
/tf_static, its wheel joints on /tf, as robot_state_publisher would. /odom and /tf's
odom -> base_footprint are the drifting wheel odometry; the truth, which a real robot cannot
publish, goes out for the viewer and the tests on /ground_truth/pose and /ground_truth/walls.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection, Iterator, Sequence
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
from numpy.typing import NDArray
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from host_bridge.converters.urdf.kinematics import joint_motion
from host_bridge.core.options import GridOptions
from host_bridge.core.state import JointModel
from host_bridge.demo.driver import LOGGER_NAME, Driver, Step
from host_bridge.demo.robot import (
    BASE_FOOTPRINT_FRAME,
    BASE_LINK_FRAME,
    CAMERA_FRAME,
    IMU_FRAME,
    MAP_FRAME,
    ODOM_FRAME,
    ODOM_SCALE_ERROR,
    SCAN_FRAME,
    TICK_HZ,
    WHEEL_JOINTS,
    odometry_track,
    robot_description,
    urdf_joints,
)
from host_bridge.demo.sensors import (
    BATTERY_CAPACITY_AH,
    BATTERY_EMPTY_V,
    BATTERY_FULL_V,
    CAMERA_HEIGHT,
    CAMERA_HZ,
    CAMERA_WIDTH,
    CLOUD_DTYPE,
    RANGE_MAX,
    RANGE_MIN,
    SCAN_ANGLES,
    SCAN_HZ,
    SCAN_INCREMENT,
    SCAN_INTENSITY,
    SCAN_RAYS,
    battery_fraction,
    camera_matrix,
    depth_cloud,
    imu_acceleration,
)
from host_bridge.demo.world import WALLS

Xyzw = tuple[float, float, float, float]

DEFAULT_START_NS = 1_700_000_000_000_000_000

# diff_drive_controller's default diagonals (x y z roll pitch yaw), constant as that driver's
# are: they do not grow with the drift, which a real driver does not know either.
_COVARIANCE = np.diag([0.001, 0.001, 0.001, 0.001, 0.001, 0.01]).ravel()


@dataclass(frozen=True, slots=True)
class SimMessage:
    """One serialized message as a recorder would see it."""

    topic: str
    msgtype: str
    log_ns: int
    data: bytes


@cache
def typestore() -> Typestore:
    return get_typestore(Stores.ROS2_HUMBLE)


class MessageBuilder:
    """Message constructors bound to the typestore; every stamp is the log time."""

    def __init__(self, store: Typestore) -> None:
        self.t = store.types

    def time(self, stamp_ns: int) -> Any:
        sec, nanosec = divmod(stamp_ns, 1_000_000_000)
        return self.t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)

    def header(self, stamp_ns: int, frame_id: str) -> Any:
        return self.t["std_msgs/msg/Header"](stamp=self.time(stamp_ns), frame_id=frame_id)

    def vector(self, xyz: Sequence[float]) -> Any:
        return self.t["geometry_msgs/msg/Vector3"](x=xyz[0], y=xyz[1], z=xyz[2])

    def quaternion(self, xyzw: Sequence[float]) -> Any:
        x, y, z, w = xyzw
        return self.t["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)

    def pose(self, xyz: Sequence[float], xyzw: Sequence[float] = (0.0, 0.0, 0.0, 1.0)) -> Any:
        position = self.t["geometry_msgs/msg/Point"](x=xyz[0], y=xyz[1], z=xyz[2])
        return self.t["geometry_msgs/msg/Pose"](position=position, orientation=self.quaternion(xyzw))

    def transform(
        self,
        stamp_ns: int,
        parent: str,
        child: str,
        xyz: Sequence[float],
        xyzw: Sequence[float] = (0.0, 0.0, 0.0, 1.0),
    ) -> Any:
        return self.t["geometry_msgs/msg/TransformStamped"](
            header=self.header(stamp_ns, parent),
            child_frame_id=child,
            transform=self.t["geometry_msgs/msg/Transform"](
                translation=self.vector(xyz), rotation=self.quaternion(xyzw)
            ),
        )

    def tf(self, transforms: list[Any]) -> Any:
        return self.t["tf2_msgs/msg/TFMessage"](transforms=transforms)

    def image(self, stamp_ns: int, frame_id: str, encoding: str, pixels: NDArray[Any]) -> Any:
        height, width = pixels.shape[:2]
        data = np.ascontiguousarray(pixels).reshape(-1).view(np.uint8)
        return self.t["sensor_msgs/msg/Image"](
            header=self.header(stamp_ns, frame_id),
            height=height,
            width=width,
            encoding=encoding,
            is_bigendian=0,
            step=len(data) // height,
            data=data,
        )


def _yaw_quaternion(yaw: float) -> Xyzw:
    return (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))


def _joint_transform(b: MessageBuilder, stamp_ns: int, joint: JointModel, value: float) -> Any:
    """Parent link -> child link at joint ``value``, as robot_state_publisher computes it."""
    translations, quaternions = joint_motion(joint, np.array([value]))
    return b.transform(stamp_ns, joint.parent, joint.child, translations[0], quaternions[0])


def _build_tf_static(b: MessageBuilder, step: Step) -> Any:
    return b.tf([
        _joint_transform(b, step.stamp_ns, j, 0.0) for j in urdf_joints().values() if j.type == "fixed"
    ])


def _build_robot_description(b: MessageBuilder, _step: Step) -> Any:
    return b.t["std_msgs/msg/String"](data=robot_description())


def _build_tf(b: MessageBuilder, step: Step) -> Any:
    odom = step.odom
    body = b.transform(
        step.stamp_ns, ODOM_FRAME, BASE_FOOTPRINT_FRAME, (odom.x, odom.y, 0.0),
        _yaw_quaternion(odom.yaw),
    )
    joints = urdf_joints()
    wheels = [
        _joint_transform(b, step.stamp_ns, j, angle)
        for j, angle in zip((joints[n] for n in WHEEL_JOINTS), step.state.wheel_angles, strict=True)
    ]
    return b.tf([body, *wheels])


def _build_odom(b: MessageBuilder, step: Step) -> Any:
    t, state, odom = b.t, step.state, step.odom
    # The speed as the (mis-scaled) wheels read it; the turn rate is the commanded one.
    twist = t["geometry_msgs/msg/Twist"](
        linear=b.vector(((1.0 + ODOM_SCALE_ERROR) * state.v, 0.0, 0.0)),
        angular=b.vector((0.0, 0.0, state.w)),
    )
    return t["nav_msgs/msg/Odometry"](
        header=b.header(step.stamp_ns, ODOM_FRAME),
        child_frame_id=BASE_FOOTPRINT_FRAME,
        pose=t["geometry_msgs/msg/PoseWithCovariance"](
            pose=b.pose((odom.x, odom.y, 0.0), _yaw_quaternion(odom.yaw)), covariance=_COVARIANCE
        ),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=_COVARIANCE),
    )


def _build_ground_truth_pose(b: MessageBuilder, step: Step) -> Any:
    state = step.state
    return b.t["geometry_msgs/msg/PoseStamped"](
        header=b.header(step.stamp_ns, MAP_FRAME),
        pose=b.pose((state.x, state.y, 0.0), _yaw_quaternion(state.yaw)),
    )


GROUND_TRUTH_WALLS_Z = GridOptions().wall_height + 0.02
"""Just above the walls the host raises on a map (``wall_height``), so the true walls show on
top of those of the map the host builds rather than hidden inside them."""
GROUND_TRUTH_WALLS_WIDTH = 0.03  # m
GROUND_TRUTH_WALLS_RGBA = (0.1, 0.85, 0.3, 1.0)  # green, apart from the map's grey-blue walls


def _build_ground_truth_walls(b: MessageBuilder, step: Step) -> Any:
    """demo/world.py's WALLS as one LINE_LIST marker: a line per wall segment."""
    t = b.t
    marker: Any = t["visualization_msgs/msg/Marker"]  # its class holds the type constants
    point = t["geometry_msgs/msg/Point"]
    return marker(
        header=b.header(step.stamp_ns, MAP_FRAME),
        ns="walls",
        id=0,
        type=marker.LINE_LIST,
        action=marker.ADD,
        pose=b.pose((0.0, 0.0, 0.0)),
        scale=b.vector((GROUND_TRUTH_WALLS_WIDTH, 0.0, 0.0)),
        color=t["std_msgs/msg/ColorRGBA"](**dict(zip("rgba", GROUND_TRUTH_WALLS_RGBA, strict=True))),
        lifetime=t["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),  # for ever
        frame_locked=False,
        points=[point(x=x, y=y, z=GROUND_TRUTH_WALLS_Z) for x, y in WALLS.reshape(-1, 2).tolist()],
        colors=[],
        texture_resource="",
        texture=t["sensor_msgs/msg/CompressedImage"](
            header=b.header(0, ""), format="", data=np.zeros(0, dtype=np.uint8)
        ),
        uv_coordinates=[],
        text="",
        mesh_resource="",
        mesh_file=t["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, dtype=np.uint8)),
        mesh_use_embedded_materials=False,
    )


def _build_joint_states(b: MessageBuilder, step: Step) -> Any:
    return b.t["sensor_msgs/msg/JointState"](
        header=b.header(step.stamp_ns, BASE_LINK_FRAME),
        name=list(WHEEL_JOINTS),
        position=np.array(step.state.wheel_angles, dtype=np.float64),
        velocity=np.array(step.state.wheel_rates, dtype=np.float64),
        effort=np.zeros(0, dtype=np.float64),
    )


_IMU_COVARIANCE = np.diag([1e-4, 1e-4, 1e-4]).ravel()


def _build_imu(b: MessageBuilder, step: Step) -> Any:
    state = step.state
    return b.t["sensor_msgs/msg/Imu"](
        header=b.header(step.stamp_ns, IMU_FRAME),
        orientation=b.quaternion(_yaw_quaternion(state.yaw)),
        orientation_covariance=_IMU_COVARIANCE,
        angular_velocity=b.vector((0.0, 0.0, state.w)),
        angular_velocity_covariance=_IMU_COVARIANCE,
        linear_acceleration=b.vector(imu_acceleration(state, step.acceleration)),
        linear_acceleration_covariance=_IMU_COVARIANCE,
    )


def _build_scan(b: MessageBuilder, step: Step) -> Any:
    return b.t["sensor_msgs/msg/LaserScan"](
        header=b.header(step.stamp_ns, SCAN_FRAME),
        angle_min=0.0,
        angle_max=float(SCAN_ANGLES[-1]),
        angle_increment=SCAN_INCREMENT,
        # All rays are cast from one pose, so there is no per-ray delay for a consumer to undo.
        time_increment=0.0,
        scan_time=1.0 / SCAN_HZ,
        range_min=RANGE_MIN,
        range_max=RANGE_MAX,
        ranges=step.scan,
        intensities=np.full(SCAN_RAYS, SCAN_INTENSITY, dtype=np.float32),
    )


def _build_image(b: MessageBuilder, step: Step) -> Any:
    return b.image(step.stamp_ns, CAMERA_FRAME, "rgb8", step.camera.rgb)


def _build_depth(b: MessageBuilder, step: Step) -> Any:
    return b.image(step.stamp_ns, CAMERA_FRAME, "16UC1", step.camera.depth_mm)


def _build_camera_info(b: MessageBuilder, step: Step) -> Any:
    k = camera_matrix()
    return b.t["sensor_msgs/msg/CameraInfo"](
        header=b.header(step.stamp_ns, CAMERA_FRAME),
        height=CAMERA_HEIGHT,
        width=CAMERA_WIDTH,
        distortion_model="plumb_bob",
        d=np.zeros(5, dtype=np.float64),
        k=k.ravel(),
        r=np.eye(3).ravel(),
        p=np.hstack([k, np.zeros((3, 1))]).ravel(),
        binning_x=0,
        binning_y=0,
        roi=b.t["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        ),
    )


_CLOUD_FIELDS = ("x", "y", "z", "rgb")  # CLOUD_DTYPE's, each a 4-byte word declared FLOAT32
_FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32


def _build_points(b: MessageBuilder, step: Step) -> Any:
    cloud = depth_cloud(step.camera)
    point = b.t["sensor_msgs/msg/PointField"]
    return b.t["sensor_msgs/msg/PointCloud2"](
        header=b.header(step.stamp_ns, CAMERA_FRAME),
        height=cloud.shape[0],
        width=cloud.shape[1],
        fields=[
            point(name=name, offset=4 * index, datatype=_FLOAT32, count=1)
            for index, name in enumerate(_CLOUD_FIELDS)
        ],
        is_bigendian=False,
        point_step=CLOUD_DTYPE.itemsize,
        row_step=CLOUD_DTYPE.itemsize * cloud.shape[1],
        data=cloud.reshape(-1).view(np.uint8),
        is_dense=bool(np.isfinite(cloud["z"]).all()),
    )


POWER_SUPPLY_STATUS_DISCHARGING = 2
POWER_SUPPLY_HEALTH_GOOD = 1
POWER_SUPPLY_TECHNOLOGY_LIPO = 4


def _build_battery(b: MessageBuilder, step: Step) -> Any:
    elapsed = step.tick / TICK_HZ
    fraction = battery_fraction(step.state, elapsed)
    return b.t["sensor_msgs/msg/BatteryState"](
        header=b.header(step.stamp_ns, BASE_LINK_FRAME),
        voltage=BATTERY_EMPTY_V + (BATTERY_FULL_V - BATTERY_EMPTY_V) * fraction,
        temperature=28.0 + 2.0 * (1.0 - fraction),
        current=-(0.35 + 1.2 * abs(step.state.v)),  # negative: discharging
        charge=BATTERY_CAPACITY_AH * fraction,
        capacity=BATTERY_CAPACITY_AH,
        design_capacity=BATTERY_CAPACITY_AH,
        percentage=fraction,
        power_supply_status=POWER_SUPPLY_STATUS_DISCHARGING,
        power_supply_health=POWER_SUPPLY_HEALTH_GOOD,
        power_supply_technology=POWER_SUPPLY_TECHNOLOGY_LIPO,
        present=True,
        cell_voltage=np.zeros(0, dtype=np.float32),
        cell_temperature=np.zeros(0, dtype=np.float32),
        location="base",
        serial_number="SIM-0001",
    )


def _build_rosout(b: MessageBuilder, step: Step) -> Any:
    line = step.log
    assert line is not None
    return b.t["rcl_interfaces/msg/Log"](
        stamp=b.time(step.stamp_ns),
        level=line.level,
        name=LOGGER_NAME,
        msg=line.text,
        file="host_bridge/demo/driver.py",
        function=line.function,
        line=0,
    )


def _build_step_timer(b: MessageBuilder, step: Step) -> Any:
    return b.t["std_msgs/msg/Float32"](data=step.step_ms)


def _always(_step: Step) -> bool:
    return True


@dataclass(frozen=True, slots=True)
class TopicSpec:
    """One simulated topic: published on the ticks where ``due`` holds, every ``every`` ticks,
    or once at the start if ``every`` is None; ``latched`` topics are offered transient_local."""

    topic: str
    msgtype: str
    every: int | None
    build: Callable[[MessageBuilder, Step], Any]
    latched: bool = False
    due: Callable[[Step], bool] = _always


_SCAN_EVERY = TICK_HZ // SCAN_HZ
_CAMERA_EVERY = TICK_HZ // CAMERA_HZ
STEP_TIMER_TOPIC = "/instrumentation/timer/sim_step"
GROUND_TRUTH_POSE_TOPIC = "/ground_truth/pose"
GROUND_TRUTH_WALLS_TOPIC = "/ground_truth/walls"

TOPICS: tuple[TopicSpec, ...] = (
    TopicSpec("/tf_static", "tf2_msgs/msg/TFMessage", None, _build_tf_static, latched=True),
    TopicSpec("/robot_description", "std_msgs/msg/String", None, _build_robot_description,
              latched=True),
    TopicSpec("/tf", "tf2_msgs/msg/TFMessage", 1, _build_tf),
    TopicSpec("/odom", "nav_msgs/msg/Odometry", 1, _build_odom),
    TopicSpec(GROUND_TRUTH_POSE_TOPIC, "geometry_msgs/msg/PoseStamped", 1, _build_ground_truth_pose),
    TopicSpec(GROUND_TRUTH_WALLS_TOPIC, "visualization_msgs/msg/Marker", None,
              _build_ground_truth_walls, latched=True),
    TopicSpec("/joint_states", "sensor_msgs/msg/JointState", 1, _build_joint_states),
    TopicSpec("/imu", "sensor_msgs/msg/Imu", 1, _build_imu),
    TopicSpec(STEP_TIMER_TOPIC, "std_msgs/msg/Float32", 1, _build_step_timer),
    TopicSpec("/scan", "sensor_msgs/msg/LaserScan", _SCAN_EVERY, _build_scan),
    TopicSpec("/camera/camera_info", "sensor_msgs/msg/CameraInfo", _CAMERA_EVERY, _build_camera_info),
    TopicSpec("/camera/image_raw", "sensor_msgs/msg/Image", _CAMERA_EVERY, _build_image),
    TopicSpec("/camera/depth/image_raw", "sensor_msgs/msg/Image", _CAMERA_EVERY, _build_depth),
    TopicSpec("/camera/depth/points", "sensor_msgs/msg/PointCloud2", _CAMERA_EVERY, _build_points),
    TopicSpec("/battery_state", "sensor_msgs/msg/BatteryState", TICK_HZ, _build_battery),
    TopicSpec("/rosout", "rcl_interfaces/msg/Log", 1, _build_rosout,
              due=lambda step: step.log is not None),
)


def tick_stamp_ns(tick: int, start_ns: int = DEFAULT_START_NS) -> int:
    """The stamp (and log time) of a run's messages of ``tick``, the index of
    :func:`~host_bridge.demo.robot.odometry_track`'s items."""
    return start_ns + tick * 1_000_000_000 // TICK_HZ


def simulate(
    duration_s: float = 20.0,
    *,
    start_ns: int = DEFAULT_START_NS,
    route_offset: float = 0.0,
    topics: Collection[str] | None = None,
) -> Iterator[SimMessage]:
    """Every message of a ``duration_s`` run in time order; header stamps equal log times.
    ``route_offset`` (metres along the loop) is where the robot starts: a fleet spreads out.
    ``topics`` limits the run to those topics (and their cost)."""
    store = typestore()
    builder = MessageBuilder(store)
    driver = Driver()
    wanted = [spec for spec in TOPICS if topics is None or spec.topic in topics]
    for tick, (state, odom) in enumerate(odometry_track(duration_s, route_offset)):
        stamp_ns = tick_stamp_ns(tick, start_ns)
        step = driver.step(tick, stamp_ns, state, odom)
        for spec in wanted:
            periodic = tick == 0 if spec.every is None else tick % spec.every == 0
            if periodic and spec.due(step):
                msg = spec.build(builder, step)
                data = bytes(store.serialize_cdr(msg, spec.msgtype))
                yield SimMessage(spec.topic, spec.msgtype, stamp_ns, data)


