"""Test data of the kind users bring: a robot description of their own with absolute ``file://``
meshes (Collada with several materials, one of them textured; STL), mimic joints and no
/joint_states, and bags that carry it with or without TF.

Everything is written here, from numbers the tests then expect back.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from PIL import Image
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

STORE = get_typestore(Stores.ROS2_HUMBLE)
T = STORE.types

PACKAGE = "arm_bot_description"
# A package installed into a workspace on the robot: a path that does not exist on the PC.
ROBOT_SHARE = f"/home/robot/ws/install/{PACKAGE}/share/{PACKAGE}"
T0 = 1_700_000_000_000_000_000
STEP = 100_000_000


@dataclass(frozen=True, slots=True)
class Flat:
    """A Collada material of one diffuse colour, written as 0-255 values."""

    rgb: tuple[int, int, int]


@dataclass(frozen=True, slots=True)
class Textured:
    """A Collada material whose diffuse colour is an image next to the .dae file."""

    image: str


Material = Flat | Textured


def collada(materials: Sequence[Material]) -> str:
    """A .dae with one triangle per material, triangle ``i`` at z = i, each with texture
    coordinates (0,0) (1,0) (0,1)."""
    effects, mats, images, triangles, bindings = [], [], [], [], []
    positions: list[float] = []
    for i, material in enumerate(materials):
        positions += [0, 0, i, 1, 0, i, 0, 1, i]
        if isinstance(material, Flat):
            rgba = " ".join(f"{c / 255:.9f}" for c in material.rgb) + " 1"
            effects.append(
                f'<effect id="e{i}"><profile_COMMON><technique sid="common"><phong><diffuse>'
                f'<color sid="diffuse">{rgba}</color></diffuse></phong></technique>'
                "</profile_COMMON></effect>"
            )
        else:
            images.append(f'<image id="img{i}"><init_from>{material.image}</init_from></image>')
            effects.append(
                f'<effect id="e{i}"><profile_COMMON>'
                f'<newparam sid="s{i}"><surface type="2D"><init_from>img{i}</init_from></surface>'
                f'</newparam><newparam sid="p{i}"><sampler2D><source>s{i}</source></sampler2D>'
                f'</newparam><technique sid="common"><lambert><diffuse>'
                f'<texture texture="p{i}" texcoord="UVMap"/></diffuse></lambert></technique>'
                "</profile_COMMON></effect>"
            )
        mats.append(f'<material id="m{i}"><instance_effect url="#e{i}"/></material>')
        corners = " ".join(f"{3 * i + k} {k}" for k in range(3))
        triangles.append(
            f'<triangles material="sym{i}" count="1">'
            '<input semantic="VERTEX" source="#g-vtx" offset="0"/>'
            '<input semantic="TEXCOORD" source="#g-uv" offset="1" set="0"/>'
            f"<p>{corners}</p></triangles>"
        )
        bindings.append(
            f'<instance_material symbol="sym{i}" target="#m{i}">'
            '<bind_vertex_input semantic="UVMap" input_semantic="TEXCOORD" input_set="0"/>'
            "</instance_material>"
        )
    count = len(positions)
    return f"""<?xml version="1.0" encoding="utf-8"?>
<COLLADA xmlns="http://www.collada.org/2005/11/COLLADASchema" version="1.4.1">
  <asset><unit name="meter" meter="1"/><up_axis>Z_UP</up_axis></asset>
  <library_images>{"".join(images)}</library_images>
  <library_effects>{"".join(effects)}</library_effects>
  <library_materials>{"".join(mats)}</library_materials>
  <library_geometries><geometry id="g"><mesh>
    <source id="g-pos"><float_array id="g-pos-a" count="{count}">{" ".join(map(str, positions))}</float_array>
      <technique_common><accessor source="#g-pos-a" count="{count // 3}" stride="3">
        <param name="X" type="float"/><param name="Y" type="float"/><param name="Z" type="float"/>
      </accessor></technique_common></source>
    <source id="g-uv"><float_array id="g-uv-a" count="6">0 0 1 0 0 1</float_array>
      <technique_common><accessor source="#g-uv-a" count="3" stride="2">
        <param name="S" type="float"/><param name="T" type="float"/>
      </accessor></technique_common></source>
    <vertices id="g-vtx"><input semantic="POSITION" source="#g-pos"/></vertices>
    {"".join(triangles)}
  </mesh></geometry></library_geometries>
  <library_visual_scenes><visual_scene id="scene"><node id="n">
    <instance_geometry url="#g"><bind_material><technique_common>{"".join(bindings)}
    </technique_common></bind_material></instance_geometry>
  </node></visual_scene></library_visual_scenes>
  <scene><instance_visual_scene url="#scene"/></scene>
</COLLADA>
"""


# The arm's two materials: the colours the issue names (64/255 came out as 137/255).
ARM_DARK = (64, 64, 64)
ARM_RED = (204, 26, 26)
# Joint origins of the model, parent -> child (x, y, z).
SHOULDER_XYZ = (0.0, 0.0, 0.05)
FINGER_LEFT_XYZ = (0.0, 0.05, 0.2)
FINGER_RIGHT_XYZ = (0.0, -0.05, 0.2)
MIMIC_MULTIPLIER = -1.0
MIMIC_OFFSET = 0.01


def user_urdf(meshes: Path, *, name: str = "arm_bot", prefix: str = "") -> str:
    """An arm on a base: ``base_footprint`` (root) -fixed- ``base_link`` -revolute ``shoulder``-
    ``upper_arm`` (two-material Collada) -prismatic- ``finger_left`` and a mimic ``finger_right``,
    and a continuous ``wheel``; meshes named by absolute ``file://`` URIs under ``meshes``."""
    p = prefix
    return f"""<?xml version="1.0"?>
<robot name="{name}">
  <material name="blue"><color rgba="0 0 1 1"/></material>
  <link name="{p}base_footprint"/>
  <link name="{p}base_link">
    <visual><geometry><mesh filename="file://{meshes}/base.stl"/></geometry><material name="blue"/></visual>
  </link>
  <link name="{p}upper_arm">
    <visual><geometry><mesh filename="file://{meshes}/arm.dae" scale="0.2 0.2 0.2"/></geometry></visual>
  </link>
  <link name="{p}finger_left"><visual><geometry><box size="0.02 0.02 0.1"/></geometry></visual></link>
  <link name="{p}finger_right"><visual><geometry><box size="0.02 0.02 0.1"/></geometry></visual></link>
  <link name="{p}wheel"><visual><geometry><cylinder radius="0.05" length="0.02"/></geometry></visual></link>
  <joint name="{p}base_joint" type="fixed">
    <parent link="{p}base_footprint"/><child link="{p}base_link"/><origin xyz="0 0 0.05"/>
  </joint>
  <joint name="{p}shoulder" type="revolute">
    <parent link="{p}base_link"/><child link="{p}upper_arm"/>
    <origin xyz="{" ".join(map(str, SHOULDER_XYZ))}" rpy="0 0 0.5"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/>
  </joint>
  <joint name="{p}finger_left_joint" type="prismatic">
    <parent link="{p}upper_arm"/><child link="{p}finger_left"/>
    <origin xyz="{" ".join(map(str, FINGER_LEFT_XYZ))}"/><axis xyz="0 1 0"/>
    <limit lower="0" upper="0.04" effort="1" velocity="1"/>
  </joint>
  <joint name="{p}finger_right_joint" type="prismatic">
    <parent link="{p}upper_arm"/><child link="{p}finger_right"/>
    <origin xyz="{" ".join(map(str, FINGER_RIGHT_XYZ))}"/><axis xyz="0 1 0"/>
    <limit lower="-0.04" upper="0" effort="1" velocity="1"/>
    <mimic joint="{p}finger_left_joint" multiplier="{MIMIC_MULTIPLIER}" offset="{MIMIC_OFFSET}"/>
  </joint>
  <joint name="{p}wheel_joint" type="continuous">
    <parent link="{p}base_link"/><child link="{p}wheel"/><origin xyz="0 0.17 -0.02"/><axis xyz="0 1 0"/>
  </joint>
</robot>
"""


def write_meshes(meshes: Path) -> Path:
    """The model's mesh files: ``base.stl`` (a box) and ``arm.dae`` (two materials)."""
    meshes.mkdir(parents=True, exist_ok=True)
    trimesh.creation.box(extents=[0.4, 0.3, 0.1]).export(meshes / "base.stl")
    (meshes / "arm.dae").write_text(collada([Flat(ARM_DARK), Flat(ARM_RED)]))
    return meshes


def write_texture(path: Path, rgb: tuple[int, int, int]) -> None:
    Image.fromarray(np.full((4, 4, 3), rgb, np.uint8)).save(path)


def write_user_robot(directory: Path, **urdf: str) -> Path:
    """``robot.urdf`` in ``directory`` with its meshes under ``directory/meshes``."""
    meshes = write_meshes(directory / "meshes")
    path = directory / "robot.urdf"
    path.write_text(user_urdf(meshes, **urdf))
    return path


@dataclass(frozen=True, slots=True)
class BagContent:
    """What a bag written by :func:`write_bag` holds (10 steps of 0.1 s from T0)."""

    description: str | None = None
    odom_tf: bool = False
    scan_frame: str | None = "base_link"
    imu_frame: str | None = None
    joint_states: bool = False


def _qos(durability: QosDurability) -> Qos:
    infinite = QosTime(sec=0x7FFFFFFF, nsec=0xFFFFFFFF)
    return Qos(
        history=QosHistory.UNKNOWN, depth=0, reliability=QosReliability.RELIABLE,
        durability=durability, deadline=infinite, lifespan=infinite,
        liveliness=QosLiveliness.AUTOMATIC, liveliness_lease_duration=infinite,
        avoid_ros_namespace_conventions=False,
    )


def _header(stamp: int, frame_id: str) -> Any:
    sec, nanosec = divmod(stamp, 1_000_000_000)
    time = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
    return T["std_msgs/msg/Header"](stamp=time, frame_id=frame_id)


def _vector(x: float, y: float, z: float) -> Any:
    return T["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)


def _messages(content: BagContent, stamp: int, step: int) -> list[tuple[str, str, Any]]:
    """(topic, type, message) of one step."""
    messages: list[tuple[str, str, Any]] = []
    if content.scan_frame is not None:
        messages.append(("/scan", "sensor_msgs/msg/LaserScan", T["sensor_msgs/msg/LaserScan"](
            header=_header(stamp, content.scan_frame), angle_min=-1.5, angle_max=1.5,
            angle_increment=0.1, time_increment=0.0, scan_time=0.1, range_min=0.1,
            range_max=10.0, ranges=np.full(31, 1.0, np.float32),
            intensities=np.zeros(0, np.float32),
        )))
    if content.imu_frame is not None:
        zero9 = np.zeros(9, np.float64)
        messages.append(("/imu", "sensor_msgs/msg/Imu", T["sensor_msgs/msg/Imu"](
            header=_header(stamp, content.imu_frame),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=zero9, angular_velocity=_vector(0.0, 0.0, 0.1),
            angular_velocity_covariance=zero9, linear_acceleration=_vector(0.0, 0.0, 9.81),
            linear_acceleration_covariance=zero9,
        )))
    if content.odom_tf:
        transform = T["geometry_msgs/msg/TransformStamped"](
            header=_header(stamp, "odom"), child_frame_id="base_footprint",
            transform=T["geometry_msgs/msg/Transform"](
                translation=_vector(0.1 * step, 0.0, 0.0),
                rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            ),
        )
        messages.append(("/tf", "tf2_msgs/msg/TFMessage", T["tf2_msgs/msg/TFMessage"](
            transforms=[transform]
        )))
    if content.joint_states:
        messages.append(("/joint_states", "sensor_msgs/msg/JointState", T["sensor_msgs/msg/JointState"](
            header=_header(stamp, ""), name=["finger_left_joint"], position=np.array([0.02]),
            velocity=np.zeros(0), effort=np.zeros(0),
        )))
    return messages


def write_bag(path: Path, content: BagContent) -> Path:
    """A rosbag2 (MCAP) of ``content``: /robot_description latched at T0, then 10 steps of 0.1 s
    of /scan, /imu, /tf ``odom -> base_footprint`` moving 0.1 m along x per step, and
    /joint_states holding ``finger_left_joint`` at 0.02 m."""
    with Writer(path, version=Writer.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP) as writer:
        connections: dict[str, Any] = {}

        def write(topic: str, msgtype: str, stamp: int, msg: Any, latched: bool = False) -> None:
            if topic not in connections:
                durability = QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE
                connections[topic] = writer.add_connection(
                    topic, msgtype, typestore=STORE, offered_qos_profiles=[_qos(durability)]
                )
            writer.write(connections[topic], stamp, STORE.serialize_cdr(msg, msgtype))

        if content.description is not None:
            write("/robot_description", "std_msgs/msg/String", T0,
                  T["std_msgs/msg/String"](data=content.description), latched=True)
        for step in range(10):
            stamp = T0 + (step + 1) * STEP
            for topic, msgtype, msg in _messages(content, stamp, step):
                write(topic, msgtype, stamp, msg)
    return path
