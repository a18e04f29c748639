"""The robot model: /robot_description (std_msgs/String, latched) or ``--urdf PATH`` -> Rerun.

The converter of the package: parse.py reads the URDF, kinematics.py makes its joint table,
meshes.py its visuals' geometry; this module names their entities and frames and gathers what
was left out into one PartialConvertError.

Why not ``rr.urdf`` (rerun 0.41)? ``UrdfTree`` loads only from a file path, finds
``package://`` files only through ROS_PACKAGE_PATH/AMENT_PREFIX_PATH (no callback, so neither
``--package-path`` nor the robot's file server can help), drops a missing mesh with a log line,
and writes chunks straight into a recording instead of returning archetypes; it also logs every
joint, movable ones at zero, as static transforms on one ``/tf_static`` entity, which would
collide with /tf and with the joint states. So: yourdfpy parses, trimesh loads meshes (STL, OBJ,
DAE, glTF, PLY...), and this package returns LogItems.

Entity and frame scheme (the one Rerun's own URDF importer uses): each visual ``i`` of link
``L`` is the entity ``/<robot>/robot_model/<L>/visual_<i>`` with ``CoordinateFrame(<robot>/L)``,
so it moves with the named link frame whoever drives it (/tf, /tf_static, joint states), and an
``InstancePoses3D`` holding the visual's ``<origin>`` relative to that frame. The pose stays an
instance pose rather than a Transform3D so the frame graph holds only the robot's real frames.

Every joint is a static ``Transform3D(parent_frame, child_frame)`` on the entity /tf_static uses
for its child frame (``/<robot>/tf_static/<child>``, see
:func:`host_bridge.core.state.static_transform_path`), so a joint robot_state_publisher also
broadcasts sits on one entity, as Rerun requires. Movable joints stand at
:func:`~host_bridge.converters.urdf.kinematics.zero_positions` (mimic joints at their offset), as
in RViz and Rerun's own URDF loader: without them a model whose /joint_states never came falls
apart into trees the view cannot connect. Joint states (joints.py) and /tf move them later from
a temporal entity, which Rerun lets win over the static row from its first stamp on. Everything
carries the robot prefix, so two robots with one URDF do not collide.

``--urdf PATH`` replaces the robot's /robot_description: once a file model is logged, the topic's
models are not drawn (said once, at info level), so one robot never shows two models.

Visuals that cannot be loaded (missing mesh, broken file, a mesh over
:data:`~host_bridge.converters.urdf.meshes.MAX_MESH_BYTES`) are collected: the rest of the model
is logged and one PartialConvertError says which files are missing, where they were looked for
and what to pass, each once, with what parse.py and kinematics.py left out of a malformed
description.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt
import rerun as rr

from host_bridge.converters.joints import joint_transform, link_frame, tf_carries
from host_bridge.converters.urdf.kinematics import (
    kinematics_of,
    origin_matrix,
    pose_of_matrix,
    zero_positions,
)
from host_bridge.converters.urdf.meshes import missing_files, visual_geometry
from host_bridge.converters.urdf.parse import listed, parse
from host_bridge.core.contract import ConvertContext, LogEntry, LogItem, per_message
from host_bridge.core.state import static_transform_path
from host_bridge.errors import ConvertError, MissingResourceError, PartialConvertError

if TYPE_CHECKING:
    import yourdfpy  # imported by parse.py where a model is built: it takes about a second

log = logging.getLogger("swanky.host")


@dataclass(slots=True)
class _DescriptionTopic:
    """Per /robot_description topic: whether it was said that the --urdf file replaces it."""

    said_replaced: bool = False


def convert(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    model_file = ctx.robot_state.model_file
    if model_file is not None:
        said = ctx.state(_DescriptionTopic)
        if not said.said_replaced:
            said.said_replaced = True
            log.info(
                "[%s] %s: not drawn, the robot model is --urdf %s", ctx.robot, ctx.topic, model_file
            )
        return []
    return model_items(msg.data, ctx, source=ctx.topic)


def model_items_from_file(path: Path, ctx: ConvertContext) -> list[LogEntry]:
    """The ``--urdf PATH`` form; relative mesh paths are taken from the URDF's directory. From
    now on the robot's /robot_description is not drawn."""
    try:
        xml = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        msg = f"cannot read URDF {path}: {err}; check the --urdf path"
        raise ConvertError(msg) from err
    ctx.robot_state.model_file = path
    return model_items(xml, ctx, source=str(path), base=Path(path).parent)


def model_items(xml: str, ctx: ConvertContext, source: str, base: Path | None = None) -> list[LogEntry]:
    """Log items of the whole model; also stores its kinematics for joints.py."""
    urdf, problems = parse(xml, source)
    model, kinematic_problems = kinematics_of(urdf.robot)
    problems += kinematic_problems
    ctx.robot_state.model = model
    resolver = ctx.robot_state.resolver
    colors = {m.name: m.color.rgba for m in urdf.robot.materials if m.name and m.color}

    items: list[LogEntry] = []
    missing: list[tuple[str, MissingResourceError]] = []
    broken: list[str] = []
    visuals, link_problems = _visuals(urdf.robot)
    problems += link_problems
    for link, index, visual in visuals:
        try:
            _check_origin(visual.origin, "its <origin>")
            geometry = visual_geometry(visual, colors, resolver, base)
        except MissingResourceError as err:
            missing.append((_visual_name(link, index), err))
            continue
        except ConvertError as err:
            broken.append(f"{_visual_name(link, index)}: {err}")
            continue
        translation, quaternion = pose_of_matrix(origin_matrix(visual.origin))
        path = f"/{ctx.robot}/robot_model/{rr.escape_entity_path_part(link)}/visual_{index}"
        archetypes = (
            rr.CoordinateFrame(link_frame(ctx, link)),
            rr.InstancePoses3D(translations=[translation], quaternions=[quaternion]),
            geometry,
        )
        items.append(LogItem(path, archetypes, static=True))
    items += [
        LogItem(
            static_transform_path(ctx.robot, ctx.robot_state, model.joints[name].child),
            (joint_transform(ctx, model.joints[name], position),),
            static=True,
        )
        for name, position in zero_positions(model).items()
        if not tf_carries(ctx, model.joints[name].child)
    ]
    if missing or broken:
        problems.append(
            f"{len(missing) + len(broken)} of {len(visuals)} visuals not drawn: "
            + "; ".join([*missing_files(missing), *broken])
        )
    if problems:
        msg = f"{source}: robot model {model.name!r}: {'; '.join(problems)}"
        raise PartialConvertError(msg, items)
    return items


def _visual_name(link: str, index: int) -> str:
    return f"link {link!r}" if index == 0 else f"link {link!r} visual {index}"


def _visuals(
    robot: yourdfpy.Robot,
) -> tuple[list[tuple[str, int, yourdfpy.Visual]], list[str]]:
    """The visuals of each named link's first definition, and the links left out."""
    visuals = []
    seen: set[str] = set()
    left_out = []
    for link in robot.links:
        if not link.name.strip("/"):
            left_out.append(f"a <link> named {link.name!r} (a frame needs a name)")
            continue
        if link.name in seen:
            left_out.append(f"link {link.name!r} (defined twice; the first one is drawn)")
            continue
        seen.add(link.name)
        visuals += [(link.name, index, visual) for index, visual in enumerate(link.visuals)]
    problems = [f"links not drawn: {listed(left_out)}"] if left_out else []
    return visuals, problems


def _check_origin(origin: npt.NDArray[np.float64] | None, what: str) -> None:
    if origin is not None and not np.isfinite(origin).all():
        msg = f"{what} is not finite"
        raise ConvertError(msg)


# Routed by topic, not type: std_msgs/String carries plain text everywhere else, so the
# registry's row picks this for topics where its is_robot_description() holds.
SPEC = per_message(convert)
