"""The robot model: /robot_description (std_msgs/String, latched) or ``--urdf PATH`` -> Rerun.

Why not ``rr.urdf`` (rerun 0.41)? ``UrdfTree`` loads only from a file path, finds
``package://`` files only through ROS_PACKAGE_PATH/AMENT_PREFIX_PATH (no callback, so neither
``--package-path`` nor the robot's file server can help), drops a missing mesh with a log line,
and writes chunks straight into a recording instead of returning archetypes; it also logs every
joint, movable ones at zero, as static transforms on one ``/tf_static`` entity, which would
collide with /tf and with the joint states. So: yourdfpy parses, trimesh loads meshes (STL, OBJ,
DAE, glTF, PLY...), and this module returns LogItems.

Entity and frame scheme (the one Rerun's own URDF importer uses): each visual ``i`` of link
``L`` is the entity ``/<robot>/robot_model/<L>/visual_<i>`` with ``CoordinateFrame(<robot>/L)``,
so it moves with the named link frame whoever drives it (/tf, /tf_static, joint states), and an
``InstancePoses3D`` holding the visual's ``<origin>`` relative to that frame. The pose stays an
instance pose rather than a Transform3D so the frame graph holds only the robot's real frames.
Mesh scale is applied to the vertices, so positions are metres as in trimesh's own load times
the scale. Fixed joints are static ``Transform3D(parent_frame, child_frame)`` on the entity
/tf_static uses for that child frame (``/<robot>/tf_static/<child>``, see
:func:`host_bridge.converters.tf.static_transform_path`), so a fixed joint robot_state_publisher
also broadcasts sits on one entity, as Rerun requires; movable joints are left to joints.py or /tf (a static
transform would hide their later motion). Everything carries the robot prefix, so two robots
with one URDF do not collide.

Visuals that cannot be loaded (missing mesh, broken file) are collected: the rest of the model
is logged and one PartialConvertError names every missing URI and its link.
"""

from __future__ import annotations

import io
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Mapping
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np
import numpy.typing as npt
import rerun as rr
import trimesh
import yourdfpy

from host_bridge.converters.joints import (
    ROBOT_MODEL_KEY,
    JointModel,
    MimicModel,
    RobotModel,
    joint_transform,
    link_frame,
    pose_of_matrix,
    robot_model,
    tf_carries,
)
from host_bridge.converters.tf import static_transform_path
from host_bridge.errors import ConvertError, PartialConvertError
from host_bridge.registry import ConvertContext, ConverterSpec, LogEntry, LogItem
from host_bridge.resources import ResourceResolver

RESOLVER_KEY = "resolver"

VisualArchetype = rr.Mesh3D | rr.Boxes3D | rr.Cylinders3D | rr.Ellipsoids3D


def convert(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    return model_items(msg.data, ctx, source=ctx.topic)


def model_items_from_file(path: Path, ctx: ConvertContext) -> list[LogEntry]:
    """The ``--urdf PATH`` form; relative mesh paths are taken from the URDF's directory."""
    try:
        xml = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        msg = f"cannot read URDF {path}: {err}; check the --urdf path"
        raise ConvertError(msg) from err
    return model_items(xml, ctx, source=str(path), base=Path(path).parent)


def robot_kinematics(xml: str, source: str) -> RobotModel:
    """The joint table of a URDF without its visuals; the demo robot places its frames and
    sensors from it, so what it publishes and what the host draws come from one parser."""
    return _kinematics(_parse(xml, source).robot, source)


def model_items(xml: str, ctx: ConvertContext, source: str, base: Path | None = None) -> list[LogEntry]:
    """Log items of the whole model; also stores its kinematics for joints.py."""
    urdf = _parse(xml, source)
    model = _kinematics(urdf.robot, source)
    ctx.robot_state[ROBOT_MODEL_KEY] = model
    resolver = ctx.robot_state.get(RESOLVER_KEY)
    if not isinstance(resolver, ResourceResolver):
        resolver = ResourceResolver.from_env()
    resolver = resolver.for_robot(ctx.robot)
    colors = {m.name: m.color.rgba for m in urdf.robot.materials if m.name and m.color}

    items: list[LogEntry] = []
    errors: list[str] = []
    for link, index, visual in _visuals(urdf.robot):
        try:
            geometry = _geometry(visual, colors, resolver, base)
        except ConvertError as err:
            errors.append(f"link {link!r} visual {index}: {err}")
            continue
        translation, quaternion = pose_of_matrix(_origin(visual.origin))
        path = f"/{ctx.robot}/robot_model/{rr.escape_entity_path_part(link)}/visual_{index}"
        archetypes = (
            rr.CoordinateFrame(link_frame(ctx, link)),
            rr.InstancePoses3D(translations=[translation], quaternions=[quaternion]),
            geometry,
        )
        items.append(LogItem(path, archetypes, static=True))
    items += [
        LogItem(
            static_transform_path(ctx.robot, ctx.robot_state, joint.child),
            (joint_transform(ctx, joint, 0.0),),
            static=True,
        )
        for joint in model.joints.values()
        if joint.type == "fixed" and not tf_carries(ctx, joint.child)
    ]
    if errors:
        msg = (
            f"{source}: {len(errors)} visual(s) of robot model {model.name!r} are missing, the "
            f"rest is shown: {'; '.join(errors)}"
        )
        raise PartialConvertError(msg, items)
    return items


def _parse(xml: str, source: str) -> yourdfpy.URDF:
    data = xml.encode("utf-8")
    try:
        # yourdfpy falls back to a "recover" parser that silently drops broken XML; refuse it.
        root = ET.fromstring(data)
    except ET.ParseError as err:
        msg = f"{source}: the robot description is not well-formed XML ({err})"
        raise ConvertError(msg) from err
    if root.tag != "robot":
        msg = f"{source}: the robot description's root element is <{root.tag}>, not <robot>"
        raise ConvertError(msg)
    try:
        return yourdfpy.URDF.load(io.BytesIO(data), build_scene_graph=False, load_meshes=False)
    except (AttributeError, KeyError, ValueError, TypeError) as err:
        # yourdfpy reports a missing required element as whatever failed while reading it.
        msg = f"{source}: the robot description is not a valid URDF ({type(err).__name__}: {err})"
        raise ConvertError(msg) from err


def _origin(matrix: npt.NDArray[np.float64] | None) -> npt.NDArray[np.float64]:
    return np.eye(4) if matrix is None else np.asarray(matrix, dtype=np.float64)


def _kinematics(robot: yourdfpy.Robot, source: str) -> RobotModel:
    joints = []
    for joint in robot.joints:
        axis = np.asarray(joint.axis if joint.axis is not None else (1.0, 0.0, 0.0), np.float64)
        norm = float(np.linalg.norm(axis))
        if joint.type in ("revolute", "continuous", "prismatic") and norm == 0.0:
            msg = f"{source}: joint {joint.name!r} has a zero <axis>; give a unit vector"
            raise ConvertError(msg)
        origin = _origin(joint.origin)
        translation, quaternion = pose_of_matrix(origin)
        mimic = joint.mimic
        joints.append(
            JointModel(
                name=joint.name,
                type=joint.type,
                parent=joint.parent,
                child=joint.child,
                translation=translation,
                rotation=origin[:3, :3].copy(),
                quaternion=quaternion,
                axis=axis / norm if norm else axis,
                mimic=None
                if mimic is None
                else MimicModel(mimic.joint, float(mimic.multiplier), float(mimic.offset)),
            )
        )
    return robot_model(robot.name, joints)


def _visuals(robot: yourdfpy.Robot) -> Iterator[tuple[str, int, yourdfpy.Visual]]:
    for link in robot.links:
        for index, visual in enumerate(link.visuals):
            yield link.name, index, visual


def _rgba8(rgba: Any) -> npt.NDArray[np.uint8]:
    return np.clip(np.round(np.asarray(rgba, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)


def _urdf_color(visual: yourdfpy.Visual, colors: Mapping[str, Any]) -> npt.NDArray[np.uint8] | None:
    material = visual.material
    if material is None:
        return None
    if material.color is not None:
        return _rgba8(material.color.rgba)
    rgba = colors.get(material.name or "")
    return None if rgba is None else _rgba8(rgba)


def _geometry(
    visual: yourdfpy.Visual,
    colors: Mapping[str, Any],
    resolver: ResourceResolver,
    base: Path | None,
) -> VisualArchetype:
    geometry = visual.geometry
    color = _urdf_color(visual, colors)
    solid = rr.components.FillMode.Solid
    color_list = None if color is None else [color]
    if geometry is not None:
        if geometry.mesh is not None:
            return _mesh(geometry.mesh, color, resolver, base)
        if geometry.box is not None:
            half_sizes = [np.asarray(geometry.box.size, np.float64) / 2.0]
            return rr.Boxes3D(half_sizes=half_sizes, colors=color_list, fill_mode=solid)
        if geometry.cylinder is not None:
            cylinder = geometry.cylinder
            return rr.Cylinders3D(
                lengths=[cylinder.length],
                radii=[cylinder.radius],
                colors=color_list,
                fill_mode=solid,
            )
        if geometry.sphere is not None:
            radius = geometry.sphere.radius
            return rr.Ellipsoids3D(half_sizes=[[radius] * 3], colors=color_list, fill_mode=solid)
    msg = "the visual has no <geometry> (mesh, box, cylinder or sphere)"
    raise ConvertError(msg)


class _SiblingFiles(Mapping[str, bytes]):
    """trimesh's view of the files next to a mesh (OBJ .mtl, textures), read via the resolver."""

    def __init__(self, resolver: ResourceResolver, uri: str, base: Path | None) -> None:
        self._resolver = resolver
        self._directory = uri.rsplit("/", 1)[0] if "/" in uri else ""
        self._base = base

    def __getitem__(self, name: str) -> bytes:
        uri = f"{self._directory}/{name}" if self._directory else name
        try:
            return self._resolver.read(uri, self._base)
        except ConvertError as err:
            raise KeyError(name) from err

    def __iter__(self) -> Iterator[str]:
        return iter(())

    def __len__(self) -> int:
        return 0


def _mesh(
    mesh: yourdfpy.Mesh,
    color: npt.NDArray[np.uint8] | None,
    resolver: ResourceResolver,
    base: Path | None,
) -> rr.Mesh3D:
    uri = mesh.filename
    data = resolver.read(uri, base)
    file_type = PurePosixPath(uri).suffix.lstrip(".").lower()
    try:
        loaded = trimesh.load(
            io.BytesIO(data),
            file_type=file_type,
            force="mesh",
            resolver=_SiblingFiles(resolver, uri, base),
        )
    except Exception as err:
        # trimesh's loaders raise whatever their parser hits on a corrupt or unknown file; one
        # broken mesh must cost one visual, not the robot.
        kind = file_type or "a mesh"
        msg = f"{uri}: trimesh cannot load it as {kind} ({type(err).__name__}: {err})"
        raise ConvertError(msg) from err
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        msg = f"{uri}: the file holds no triangles"
        raise ConvertError(msg)
    return _mesh3d(loaded, _scale(mesh.scale), color)


def _scale(scale: float | npt.ArrayLike | None) -> npt.NDArray[np.float64]:
    return np.broadcast_to(np.asarray(1.0 if scale is None else scale, np.float64), (3,))


def _mesh3d(
    mesh: trimesh.Trimesh, scale: npt.NDArray[np.float64], color: npt.NDArray[np.uint8] | None
) -> rr.Mesh3D:
    """Mesh3D of ``mesh`` scaled; the mesh's own colours win over the URDF material, as in RViz."""
    positions = np.asarray(mesh.vertices, np.float64) * scale
    normals = np.asarray(mesh.vertex_normals, np.float64) / scale
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    triangles = np.asarray(mesh.faces, np.uint32)
    if np.prod(scale) < 0:
        # A mirroring scale turns the faces inside out; flip the winding back.
        triangles = triangles[:, ::-1]
    vertex_colors = None
    texcoords = None
    texture = None
    albedo = color
    visual: Any = mesh.visual
    if visual.kind in ("vertex", "face"):
        vertex_colors = np.asarray(visual.vertex_colors, np.uint8)
    elif visual.kind == "texture":
        material = visual.material
        image = getattr(material, "image", None) or getattr(material, "baseColorTexture", None)
        if image is not None and visual.uv is not None and len(visual.uv) == len(positions):
            # trimesh's uv origin is the bottom-left corner, Rerun's the top-left one.
            uv = np.asarray(visual.uv, np.float32)
            texcoords = np.column_stack([uv[:, 0], 1.0 - uv[:, 1]])
            texture = np.asarray(image.convert("RGBA"))
            albedo = None
        elif getattr(material, "main_color", None) is not None:
            albedo = np.asarray(material.main_color, np.uint8)
    return rr.Mesh3D(
        vertex_positions=positions.astype(np.float32),
        vertex_normals=normals.astype(np.float32),
        triangle_indices=triangles,
        vertex_colors=vertex_colors,
        vertex_texcoords=texcoords,
        albedo_texture=texture,
        albedo_factor=albedo,
    )


def is_robot_description(topic: str) -> bool:
    """``/robot_description`` or a namespaced one (``/tb1/robot_description``)."""
    return topic.rstrip("/").split("/")[-1] == "robot_description"


# Keyed by topic, not type: std_msgs/String carries plain text everywhere else, so the
# dispatcher picks this for topics where is_robot_description() holds.
SPEC = ConverterSpec(convert=convert)
