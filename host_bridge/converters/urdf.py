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
the scale.

Every joint is a static ``Transform3D(parent_frame, child_frame)`` on the entity /tf_static uses
for its child frame (``/<robot>/tf_static/<child>``, see
:func:`host_bridge.state.static_transform_path`), so a joint robot_state_publisher also
broadcasts sits on one entity, as Rerun requires. Movable joints stand at
:func:`~host_bridge.converters.joints.zero_positions` (mimic joints at their offset), as in RViz
and Rerun's own URDF loader: without them a model whose /joint_states never came falls apart
into trees the view cannot connect. Joint states (joints.py) and /tf move them later from a
temporal entity, which Rerun lets win over the static row from its first stamp on. Everything
carries the robot prefix, so two robots with one URDF do not collide.

``--urdf PATH`` replaces the robot's /robot_description: once a file model is logged, the topic's
models are not drawn (said once, at info level), so one robot never shows two models.

Meshes: several materials in one file become per-vertex colours; trimesh would pack them into a
texture through glTF's linear colour rule, which makes a Collada or OBJ diffuse colour (written
as it should look, as RViz shows it) lighter. glTF's own base colour is linear and is turned into
sRGB, the space of Rerun's colours.

Visuals that cannot be loaded (missing mesh, broken file, a mesh over :data:`MAX_MESH_BYTES`)
are collected: the rest of the model is logged and one PartialConvertError says which files are
missing, where they were looked for and what to pass, each once.

A malformed description costs what is malformed, not the robot, and the same PartialConvertError
names it: XML cut short (a truncated string) keeps the elements complete before the error; an
element yourdfpy refuses (a joint without a parent, ``xyz="1 two 3"``) is left out; a joint
naming a link no ``<link>`` defines, giving a link a second parent, or closing a loop (a link
its own ancestor) is not drawn, so the frames stay one tree per root; several root links are
drawn, the largest tree being the model's root; non-finite origins are taken as identity, a
zero or non-finite axis makes its joint fixed, and mimic rules that point at themselves, in a
loop or at a missing joint are ignored. (urdfdom refuses such a model whole, so RViz draws
nothing; a viewer should show what it can and say what it left out.)
"""

from __future__ import annotations

import dataclasses
import io
import logging
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt
import rerun as rr

from host_bridge.contract import ConvertContext, LogEntry, LogItem, per_message
from host_bridge.converters.joints import (
    MOVABLE_TYPES,
    joint_transform,
    link_frame,
    pose_of_matrix,
    robot_model,
    tf_carries,
    zero_positions,
)
from host_bridge.errors import ConvertError, MissingResourceError, PartialConvertError
from host_bridge.resources import ResourceResolver
from host_bridge.state import JointModel, MimicModel, RobotModel, static_transform_path

if TYPE_CHECKING:
    # Imported where a model is built: trimesh (with scipy) and yourdfpy take about a second to
    # import, which every --bag run without a robot description paid.
    import trimesh
    import yourdfpy

log = logging.getLogger("swanky.host")

VisualArchetype = rr.Mesh3D | rr.Boxes3D | rr.Cylinders3D | rr.Ellipsoids3D

# glTF stores its base colour linear; trimesh's other loaders keep the colour as written.
_LINEAR_COLOUR_TYPES = frozenset({"gltf", "glb"})

MAX_MESH_BYTES = 64 << 20
"""The largest mesh file loaded (64 MiB, also the relay's file server limit). That is millions
of triangles already; a bigger file (an unreduced CAD export, a corrupt file full of zeros)
would hold the robot's converting thread for seconds and cost several times its size in
memory while trimesh parses it, for one visual. It is named, with its size, and not drawn."""

_JOINT_TYPES = frozenset({"fixed", "revolute", "continuous", "prismatic", "floating", "planar"})
# Problems of one kind listed in a warning before "and N more": a 10k-link model with every
# joint wrong must still give a warning one can read.
_LISTED_PROBLEMS = 10
# What yourdfpy raises on an element it cannot read (a missing attribute or child, a number
# that is not one): whatever failed while reading it.
_URDF_ERRORS = (AttributeError, KeyError, ValueError, TypeError, IndexError)


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


def robot_kinematics(xml: str, source: str) -> RobotModel:
    """The joint table of a URDF without its visuals; the demo robot places its frames and
    sensors from it, so what it publishes and what the host draws come from one parser."""
    urdf, _ = _parse(xml, source)
    return _kinematics(urdf.robot)[0]


def model_items(xml: str, ctx: ConvertContext, source: str, base: Path | None = None) -> list[LogEntry]:
    """Log items of the whole model; also stores its kinematics for joints.py."""
    urdf, problems = _parse(xml, source)
    model, kinematic_problems = _kinematics(urdf.robot)
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
            geometry = _geometry(visual, colors, resolver, base)
        except MissingResourceError as err:
            missing.append((_visual_name(link, index), err))
            continue
        except ConvertError as err:
            broken.append(f"{_visual_name(link, index)}: {err}")
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
            + "; ".join([*_missing_files(missing), *broken])
        )
    if problems:
        msg = f"{source}: robot model {model.name!r}: {'; '.join(problems)}"
        raise PartialConvertError(msg, items)
    return items


def _visual_name(link: str, index: int) -> str:
    return f"link {link!r}" if index == 0 else f"link {link!r} visual {index}"


def _missing_files(missing: Sequence[tuple[str, MissingResourceError]]) -> list[str]:
    """One clause per place looked in: the files by directory with the links that name them,
    where they were looked for, and each ``--package-path`` that would help, once."""
    by_search: dict[str, dict[str, list[tuple[str, str]]]] = {}
    for visual, err in missing:
        directory, _, name = err.uri.rpartition("/")
        by_search.setdefault(err.searched, {}).setdefault(directory, []).append((name, visual))
    clauses = []
    for searched, directories in by_search.items():
        listed = []
        for directory, files in directories.items():
            if len(files) == 1:
                name, visual = files[0]
                listed.append(f"{directory}/{name} for {visual}")
            else:
                names = ", ".join(f"{name} for {visual}" for name, visual in files)
                listed.append(f"{directory}/: {names}")
        clauses.append(f"mesh files not found: {'; '.join(listed)}; looked in {searched}")
    packages = sorted({err.package for _, err in missing if err.package is not None})
    if packages:
        clauses.append("pass " + " ".join(f"--package-path {p}=DIR" for p in packages))
    return clauses


def _parse(xml: str, source: str) -> tuple[yourdfpy.URDF, list[str]]:
    """The URDF, and what of it was left out: the elements after the point where the XML stops
    being well-formed, and the elements yourdfpy cannot read (each tried on its own)."""
    data = xml.encode("utf-8")
    root, problems = _well_formed_part(data, source)
    if root.get("name") is None:
        problems.append("the <robot> element has no name attribute")
        root.set("name", "")
    import yourdfpy

    def load(document: bytes) -> yourdfpy.URDF:
        # A non-finite rpy makes trimesh's sin/cos warn on stderr; _joint_model names it.
        with np.errstate(invalid="ignore"):
            return yourdfpy.URDF.load(
                io.BytesIO(document), build_scene_graph=False, load_meshes=False
            )

    try:
        return load(ET.tostring(root) if problems else data), problems
    except _URDF_ERRORS as err:
        # yourdfpy reports a missing required element as whatever failed while reading it.
        refusal = f"{type(err).__name__}: {err}"
    kept = ET.Element(root.tag, root.attrib)
    refused = []
    for element in root:
        alone = ET.Element(root.tag, root.attrib)
        alone.append(element)
        try:
            load(ET.tostring(alone))
        except _URDF_ERRORS as err:
            refused.append(f"{_element_name(element)} ({type(err).__name__}: {err})")
            continue
        kept.append(element)
    if kept.find("link") is None:
        msg = f"{source}: the robot description is not a valid URDF ({refusal})"
        raise ConvertError(msg)
    problems.append(f"not valid URDF, not drawn: {_listed(refused)}")
    try:
        return load(ET.tostring(kept)), problems
    except _URDF_ERRORS as err:
        msg = f"{source}: the robot description is not a valid URDF ({refusal})"
        raise ConvertError(msg) from err


def _well_formed_part(data: bytes, source: str) -> tuple[ET.Element, list[str]]:
    """The document's root element; for XML that is not well-formed (a description cut short,
    a stray byte) the root with the children that were complete before the error, and the
    problem. The stdlib parser, not yourdfpy's lxml one: that falls back to a "recover" mode
    that silently drops or mends what is broken."""
    parser: ET.XMLPullParser[ET.Element] = ET.XMLPullParser(events=("start", "end"))
    parser.feed(data)
    error: ET.ParseError | None = None
    try:
        parser.close()
    except ET.ParseError as err:
        error = err
    root: ET.Element | None = None
    complete: list[ET.Element] = []
    depth = 0
    try:
        for pair in parser.read_events():
            event, element = pair[0], pair[-1]
            if not isinstance(element, ET.Element):
                continue  # only namespace events carry something else; none were asked for
            if event == "start":
                root = element if root is None else root
                depth += 1
            else:
                depth -= 1
                if depth == 1:
                    complete.append(element)
    except ET.ParseError as err:
        error = err  # the first error, from feed(); close() then reports a later one
    if root is not None and root.tag != "robot":
        msg = f"{source}: the robot description's root element is <{root.tag}>, not <robot>"
        raise ConvertError(msg)
    if error is None and root is not None:
        return root, []
    if root is None or not complete:
        msg = f"{source}: the robot description is not well-formed XML ({error})"
        raise ConvertError(msg)
    salvaged = ET.Element(root.tag, root.attrib)
    salvaged.extend(complete)
    problem = (
        f"the description is not well-formed XML ({error}): only the {len(complete)} elements "
        "complete before that point are drawn"
    )
    return salvaged, [problem]


def _element_name(element: ET.Element) -> str:
    name = element.get("name")
    return f"<{element.tag}>" if name is None else f"<{element.tag} name={name!r}>"


def _listed(problems: Sequence[str]) -> str:
    shown = ", ".join(problems[:_LISTED_PROBLEMS])
    more = len(problems) - _LISTED_PROBLEMS
    return shown if more <= 0 else f"{shown} and {more} more"


def _origin(matrix: npt.NDArray[np.float64] | None) -> npt.NDArray[np.float64]:
    return np.eye(4) if matrix is None else np.asarray(matrix, dtype=np.float64)


class _Trees:
    """The trees the joints accepted so far make of the links (union-find with path halving and
    tree sizes): a joint whose parent is already in its child's tree closes a loop. Walking up
    from each joint instead would be quadratic in a 10k-link chain."""

    def __init__(self, links: Iterable[str]) -> None:
        self._up = {link: link for link in links}
        self.size = dict.fromkeys(self._up, 1)

    def find(self, link: str) -> str:
        up = self._up
        while up[link] != link:
            up[link] = up[up[link]]
            link = up[link]
        return link

    def join(self, a: str, b: str) -> None:
        a, b = self.find(a), self.find(b)
        if a == b:
            return
        if self.size[a] < self.size[b]:
            a, b = b, a
        self._up[b] = a
        self.size[a] += self.size[b]


def _link_names(robot: yourdfpy.Robot) -> list[str]:
    """The links a frame can be named after, once each, in file order."""
    return list(dict.fromkeys(link.name for link in robot.links if link.name.strip("/")))


def _kinematics(robot: yourdfpy.Robot) -> tuple[RobotModel, list[str]]:
    """The joint table, and the joints left out or changed, each said once: the rest of the
    model stays one tree per root whatever the file says."""
    links = _link_names(robot)
    defined = set(links)
    trees = _Trees(links)
    placed_by: dict[str, str] = {}  # child link -> the joint that places it
    joints: dict[str, JointModel] = {}
    left_out: list[str] = []
    problems: list[str] = []
    for joint in robot.joints:
        if joint.name in joints:
            left_out.append(f"joint {joint.name!r} (defined twice; the first one is drawn)")
            continue
        missing = [link for link in (joint.parent, joint.child) if link not in defined]
        if missing:
            names = " and ".join(repr(link) for link in missing)
            left_out.append(f"joint {joint.name!r} (no <link> defines {names})")
            continue
        if joint.parent == joint.child:
            left_out.append(f"joint {joint.name!r} (it makes link {joint.child!r} its own parent)")
            continue
        if joint.child in placed_by:
            left_out.append(
                f"joint {joint.name!r} (link {joint.child!r} already has parent joint "
                f"{placed_by[joint.child]!r})"
            )
            continue
        if trees.find(joint.parent) == trees.find(joint.child):
            left_out.append(f"joint {joint.name!r} (it makes link {joint.child!r} its own ancestor)")
            continue
        placed_by[joint.child] = joint.name
        trees.join(joint.parent, joint.child)
        model, joint_problems = _joint_model(joint)
        joints[joint.name] = model
        problems += joint_problems
    if left_out:
        problems.insert(0, f"joints not drawn: {_listed(left_out)}")
    problems += _drop_bad_mimics(joints)
    roots = [link for link in links if link not in placed_by]
    # Several roots (urdfdom refuses them): the largest tree is the model's, the others are
    # drawn at the robot's root (frames.py places every unplaced frame there).
    root = max(roots, key=lambda link: trees.size[trees.find(link)]) if roots else None
    if len(roots) > 1:
        others = [link for link in roots if link != root]
        problems.append(
            f"{len(roots)} root links (a URDF has one): {root!r} is the model's root, "
            f"{_listed([repr(link) for link in others])} drawn at the robot's root"
        )
    return robot_model(robot.name, joints.values(), root=root), problems


def _finite(*values: float | None) -> bool:
    return all(value is None or np.isfinite(value) for value in values)


def _joint_model(joint: yourdfpy.Joint) -> tuple[JointModel, list[str]]:
    """The joint as drawn; what of it was not finite or not URDF is said and made harmless."""
    problems = []
    name = joint.name
    origin = _origin(joint.origin)
    if not np.isfinite(origin).all():
        problems.append(f"joint {name!r}: its <origin> is not finite: taken as identity")
        origin = np.eye(4)
    kind = joint.type
    if kind not in _JOINT_TYPES:
        problems.append(f"joint {name!r}: type {kind!r} is not a URDF joint type: drawn as fixed")
        kind = "fixed"
    axis = np.asarray(joint.axis if joint.axis is not None else (1.0, 0.0, 0.0), np.float64)
    norm = float(np.linalg.norm(axis)) if np.isfinite(axis).all() else 0.0
    if kind in MOVABLE_TYPES and norm == 0.0:
        problems.append(
            f"joint {name!r}: its <axis> {axis.tolist()} is not a direction: drawn as fixed, "
            "its joint states are ignored"
        )
        kind = "fixed"
    limit = joint.limit
    if limit is not None and not _finite(limit.lower, limit.upper, limit.effort, limit.velocity):
        problems.append(
            f"joint {name!r}: its <limit> is not finite (lower={limit.lower}, "
            f"upper={limit.upper}, effort={limit.effort}, velocity={limit.velocity}): "
            "ignored, as every limit (joint states are drawn as given)"
        )
    mimic = joint.mimic
    if mimic is not None and not _finite(mimic.multiplier, mimic.offset):
        problems.append(f"joint {name!r}: its <mimic> multiplier or offset is not finite: ignored")
        mimic = None
    translation, quaternion = pose_of_matrix(origin)
    model = JointModel(
        name=name,
        type=kind,
        parent=joint.parent,
        child=joint.child,
        translation=translation,
        rotation=origin[:3, :3].copy(),
        quaternion=quaternion,
        axis=axis / norm if norm else np.array([1.0, 0.0, 0.0]),
        mimic=None
        if mimic is None
        else MimicModel(mimic.joint, float(mimic.multiplier), float(mimic.offset)),
    )
    return model, problems


def _drop_bad_mimics(joints: dict[str, JointModel]) -> list[str]:
    """Clear (in ``joints``) the mimic rules that cannot be followed: one naming a joint the
    model lacks, one naming its own joint, and the rules of joints that mimic each other in a
    loop; each is said once."""
    problems = []
    for joint in list(joints.values()):
        if joint.mimic is not None and joint.mimic.joint not in joints:
            problems.append(
                f"joint {joint.name!r} mimics joint {joint.mimic.joint!r}, which the model does "
                "not have: moves on its own"
            )
            joints[joint.name] = dataclasses.replace(joint, mimic=None)
    done: set[str] = set()
    for start in list(joints):
        chain: dict[str, None] = {}  # ordered: the drivers followed from ``start``
        name: str | None = start
        while name is not None and name not in done and name not in chain:
            chain[name] = None
            mimic = joints[name].mimic
            name = None if mimic is None else mimic.joint
        done.update(chain)
        if name is None or name not in chain:
            continue
        loop = list(chain)[list(chain).index(name) :]
        for member in loop:
            joints[member] = dataclasses.replace(joints[member], mimic=None)
        if len(loop) == 1:
            problems.append(f"joint {name!r} mimics itself: its <mimic> is ignored")
        else:
            cycle = " -> ".join(repr(member) for member in [*loop, name])
            problems.append(f"joints {cycle} mimic each other in a loop: their <mimic> is ignored")
    return problems


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
    problems = [f"links not drawn: {_listed(left_out)}"] if left_out else []
    return visuals, problems


def _check_origin(origin: npt.NDArray[np.float64] | None, what: str) -> None:
    if origin is not None and not np.isfinite(origin).all():
        msg = f"{what} is not finite"
        raise ConvertError(msg)


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
            _check_sizes("<box> size", geometry.box.size)
            half_sizes = [np.asarray(geometry.box.size, np.float64) / 2.0]
            return rr.Boxes3D(half_sizes=half_sizes, colors=color_list, fill_mode=solid)
        if geometry.cylinder is not None:
            cylinder = geometry.cylinder
            _check_sizes("<cylinder> length and radius", (cylinder.length, cylinder.radius))
            return rr.Cylinders3D(
                lengths=[cylinder.length],
                radii=[cylinder.radius],
                colors=color_list,
                fill_mode=solid,
            )
        if geometry.sphere is not None:
            radius = geometry.sphere.radius
            _check_sizes("<sphere> radius", (radius,))
            return rr.Ellipsoids3D(half_sizes=[[radius] * 3], colors=color_list, fill_mode=solid)
    msg = "the visual has no <geometry> (mesh, box, cylinder or sphere)"
    raise ConvertError(msg)


def _check_sizes(what: str, sizes: npt.ArrayLike) -> None:
    values = np.asarray(sizes, np.float64)
    if not (np.isfinite(values).all() and (values >= 0).all()):
        msg = f"its {what} {values.tolist()} is not finite and >= 0"
        raise ConvertError(msg)


def _read_mesh(uri: str, resolver: ResourceResolver, base: Path | None) -> bytes:
    """The file's bytes, unless it is over :data:`MAX_MESH_BYTES` (a local file is measured
    before it is read)."""
    path = resolver.locate(uri, base)
    size = path.stat().st_size if path is not None else None
    data = None
    if size is None or size <= MAX_MESH_BYTES:
        data = resolver.read(uri, base)
        size = len(data)
    if data is None or size > MAX_MESH_BYTES:
        msg = (
            f"{uri}: {size} bytes ({size / (1 << 20):.0f} MiB) is over the mesh size limit of "
            f"{MAX_MESH_BYTES >> 20} MiB (urdf.MAX_MESH_BYTES), not loaded; reduce the mesh "
            "(MeshLab, Blender's Decimate)"
        )
        raise ConvertError(msg)
    return data


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
    import trimesh

    uri = mesh.filename
    if not isinstance(uri, str) or not uri:
        msg = "its <mesh> has no filename"
        raise ConvertError(msg)
    scale = _scale(mesh.scale)
    if not np.isfinite(scale).all():
        msg = f"{uri}: its scale {scale.tolist()} is not finite"
        raise ConvertError(msg)
    data = _read_mesh(uri, resolver, base)
    file_type = PurePosixPath(uri).suffix.lstrip(".").lower()
    try:
        loaded = trimesh.load(
            io.BytesIO(data),
            file_type=file_type,
            force="scene",
            resolver=_SiblingFiles(resolver, uri, base),
        )
    except Exception as err:
        # trimesh's loaders raise whatever their parser hits on a corrupt or unknown file; one
        # broken mesh must cost one visual, not the robot.
        kind = file_type or "a mesh"
        msg = f"{uri}: trimesh cannot load it as {kind} ({type(err).__name__}: {err})"
        raise ConvertError(msg) from err
    linear = file_type in _LINEAR_COLOUR_TYPES
    scene = loaded if isinstance(loaded, trimesh.Scene) else trimesh.Scene(loaded)
    parts = [
        part for part in scene.dump() if isinstance(part, trimesh.Trimesh) and len(part.faces) > 0
    ]
    if not parts:
        msg = f"{uri}: the file holds no triangles"
        raise ConvertError(msg)
    if len(parts) == 1:
        return _mesh3d(parts[0], scale, color, linear)
    merged = trimesh.util.concatenate(_uniform_visuals(parts, linear))
    assert isinstance(merged, trimesh.Trimesh)  # concatenating meshes gives a mesh
    return _mesh3d(merged, scale, color, linear)


def _scale(scale: float | npt.ArrayLike | None) -> npt.NDArray[np.float64]:
    return np.broadcast_to(np.asarray(1.0 if scale is None else scale, np.float64), (3,))


def _texture_image(material: Any) -> Any:
    return getattr(material, "image", None) or getattr(material, "baseColorTexture", None)


def _base_colour(material: Any, linear: bool) -> npt.NDArray[np.uint8]:
    """The material's colour in sRGB, the space of Rerun's colours."""
    rgba = np.asarray(material.main_color, np.uint8)
    if not linear:
        return rgba
    import trimesh

    srgb = trimesh.visual.color.linear_to_srgb(rgba[:3] / 255.0)
    return np.append(np.round(np.asarray(srgb) * 255.0), rgba[3]).astype(np.uint8)


def _image_of(part: trimesh.Trimesh) -> Any:
    visual: Any = part.visual
    return _texture_image(visual.material) if visual.kind == "texture" else None


def _uniform_visuals(parts: Sequence[trimesh.Trimesh], linear: bool) -> list[trimesh.Trimesh]:
    """``parts`` with visuals trimesh concatenates without changing a colour.

    Concatenating parts of several materials packs them into one texture, and trimesh bakes an
    untextured material's colour there as glTF's linear base colour (made sRGB): a Collada
    diffuse of 64/255 came out as 137/255. So an untextured material becomes vertex colours of
    its base colour or, when another part has a texture, a small image of it (trimesh misplaces
    the one-pixel ones it makes itself); a textured one keeps just its image, the one texture a
    Mesh3D has (trimesh's packing fails on a mix of material kinds)."""
    import PIL.Image
    import trimesh

    textured = any(_image_of(part) is not None for part in parts)
    for part in parts:
        visual: Any = part.visual
        if visual.kind != "texture":
            continue
        image, uv = _image_of(part), visual.uv
        if image is None:
            colour = _base_colour(visual.material, linear)
            if not textured:
                part.visual = trimesh.visual.ColorVisuals(
                    part, vertex_colors=np.tile(colour, (len(part.vertices), 1))
                )
                continue
            image = PIL.Image.new("RGBA", (4, 4), tuple(int(c) for c in colour))
            uv = np.full((len(part.vertices), 2), 0.5)
        material = trimesh.visual.material.SimpleMaterial(image=image)  # type: ignore[no-untyped-call]
        part.visual = trimesh.visual.TextureVisuals(uv=uv, material=material)  # type: ignore[no-untyped-call]
    return list(parts)


def _mesh3d(
    mesh: trimesh.Trimesh,
    scale: npt.NDArray[np.float64],
    color: npt.NDArray[np.uint8] | None,
    linear: bool,
) -> rr.Mesh3D:
    """Mesh3D of ``mesh`` scaled; the mesh's own colours win over the URDF material, as in RViz
    (Rerun multiplies the albedo factor into vertex colours and textures, so it is left out)."""
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
        albedo = None
    elif visual.kind == "texture":
        material = visual.material
        image = _texture_image(material)
        if image is not None and visual.uv is not None and len(visual.uv) == len(positions):
            # trimesh's uv origin is the bottom-left corner, Rerun's the top-left one.
            uv = np.asarray(visual.uv, np.float32)
            texcoords = np.column_stack([uv[:, 0], 1.0 - uv[:, 1]])
            texture = np.asarray(image.convert("RGBA"))
            albedo = None
        elif getattr(material, "main_color", None) is not None:
            albedo = _base_colour(material, linear)
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


# Routed by topic, not type: std_msgs/String carries plain text everywhere else, so the
# registry's row picks this for topics where is_robot_description() holds.
SPEC = per_message(convert)
