"""The robot model's kinematics, without Rerun or a converter's context: the joint table of a
URDF (:class:`~host_bridge.core.state.RobotModel`) and the motion of its joints. The URDF converter
(description.py), the joint-state converter (joints.py) and the demo robot share it.

The table stays one tree per root whatever the file says: a joint naming a link no ``<link>``
defines, giving a link a second parent, or closing a loop (a link its own ancestor) is left
out, so the frames stay one tree per root; several root links are kept, the largest tree being
the model's root; non-finite origins are taken as identity, a zero or non-finite axis makes its
joint fixed, and mimic rules that point at themselves, in a loop or at a missing joint are
ignored. Each is returned as a problem, for the converter's one warning.

A movable joint's transform is its origin times its motion at a value (the relation
robot_state_publisher puts on /tf); mimic joints follow their driver
(``multiplier * driver + offset``); until a joint state arrives the model stands at
:func:`zero_positions`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from host_bridge.converters.urdf.parse import listed, parse
from host_bridge.core.state import JointModel, MimicModel, RobotModel

if TYPE_CHECKING:
    import yourdfpy  # imported by parse.py where a model is built: it takes about a second

MOVABLE_TYPES = frozenset({"revolute", "continuous", "prismatic"})

_JOINT_TYPES = frozenset({"fixed", "revolute", "continuous", "prismatic", "floating", "planar"})

FloatArray = npt.NDArray[np.float64]


def robot_kinematics(xml: str, source: str) -> RobotModel:
    """The joint table of a URDF without its visuals; the demo robot places its frames and
    sensors from it, so what it publishes and what the host draws come from one parser."""
    urdf, _ = parse(xml, source)
    return kinematics_of(urdf.robot)[0]


def origin_matrix(matrix: npt.NDArray[np.float64] | None) -> npt.NDArray[np.float64]:
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


def kinematics_of(robot: yourdfpy.Robot) -> tuple[RobotModel, list[str]]:
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
        problems.insert(0, f"joints not drawn: {listed(left_out)}")
    problems += _drop_bad_mimics(joints)
    roots = [link for link in links if link not in placed_by]
    # Several roots (urdfdom refuses them): the largest tree is the model's, the others are
    # drawn at the robot's root (frames.py places every unplaced frame there).
    root = max(roots, key=lambda link: trees.size[trees.find(link)]) if roots else None
    if len(roots) > 1:
        others = [link for link in roots if link != root]
        problems.append(
            f"{len(roots)} root links (a URDF has one): {root!r} is the model's root, "
            f"{listed([repr(link) for link in others])} drawn at the robot's root"
        )
    return robot_model(robot.name, joints.values(), root=root), problems


def _finite(*values: float | None) -> bool:
    return all(value is None or np.isfinite(value) for value in values)


def _joint_model(joint: yourdfpy.Joint) -> tuple[JointModel, list[str]]:
    """The joint as drawn; what of it was not finite or not URDF is said and made harmless."""
    problems = []
    name = joint.name
    origin = origin_matrix(joint.origin)
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


def pose_of_matrix(matrix: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Translation and unit quaternion (x, y, z, w) of a 4x4 rigid transform."""
    r = matrix[:3, :3]
    # Shepperd: take the square root of the largest of 4w², 4x², 4y², 4z² for stability.
    diagonal = np.array([np.trace(r), r[0, 0], r[1, 1], r[2, 2]])
    k = int(np.argmax(diagonal))
    if k == 0:
        w = 0.5 * np.sqrt(1.0 + diagonal[0])
        q = [
            (r[2, 1] - r[1, 2]) / (4 * w),
            (r[0, 2] - r[2, 0]) / (4 * w),
            (r[1, 0] - r[0, 1]) / (4 * w),
            w,
        ]
    else:
        i, j, m = k - 1, k % 3, (k + 1) % 3
        v = 0.5 * np.sqrt(1.0 + r[i, i] - r[j, j] - r[m, m])
        q = [0.0, 0.0, 0.0, (r[m, j] - r[j, m]) / (4 * v)]
        q[i] = v
        q[j] = (r[j, i] + r[i, j]) / (4 * v)
        q[m] = (r[m, i] + r[i, m]) / (4 * v)
    quaternion = np.asarray(q, dtype=np.float64)
    return np.asarray(matrix[:3, 3], dtype=np.float64), quaternion / np.linalg.norm(quaternion)


def robot_model(name: str, joints: Iterable[JointModel], root: str | None = None) -> RobotModel:
    table = {joint.name: joint for joint in joints}
    return RobotModel(name=name, joints=table, mimic_order=_mimic_order(table), root=root)


def _mimic_order(joints: Mapping[str, JointModel]) -> tuple[str, ...]:
    """Mimic joints with each driver before the joints that follow it (mimic chains). A loop
    is followed once round. Iterative: a chain of thousands of mimic joints listed followers
    first exceeded Python's recursion limit and lost the whole model."""
    order: list[str] = []
    placed: set[str] = set()
    for start in joints:
        chain: dict[str, None] = {}  # ordered: ``start`` and the mimic drivers it follows
        name = start
        while name in joints and name not in placed and name not in chain:
            mimic = joints[name].mimic
            if mimic is None:
                break
            chain[name] = None
            name = mimic.joint
        for follower in reversed(chain):
            placed.add(follower)
            order.append(follower)
    return tuple(order)


def joint_motion(joint: JointModel, values: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Translations (n, 3) and quaternions (n, 4, xyzw) of parent -> child at ``values``."""
    count = len(values)
    translations = np.tile(joint.translation, (count, 1))
    quaternions = np.tile(joint.quaternion, (count, 1))
    if joint.type == "prismatic":
        translations += values[:, None] * (joint.rotation @ joint.axis)
    elif joint.type in ("revolute", "continuous"):
        half = values / 2.0
        motion = np.column_stack([np.outer(np.sin(half), joint.axis), np.cos(half)])
        quaternions = _quaternion_product(quaternions, motion)
    return translations, quaternions


def _quaternion_product(a: FloatArray, b: FloatArray) -> FloatArray:
    """Row-wise Hamilton product of (n, 4) xyzw quaternions."""
    ax, ay, az, aw = a.T
    bx, by, bz, bw = b.T
    return np.column_stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ]
    )


def follow_drivers(model: RobotModel, values: dict[str, float]) -> None:
    """Set each mimic joint whose driver is in ``values`` to ``multiplier * driver + offset``."""
    for name in model.mimic_order:
        mimic = model.joints[name].mimic
        if mimic is not None and mimic.joint in values:
            values[name] = mimic.multiplier * values[mimic.joint] + mimic.offset


def zero_positions(model: RobotModel) -> dict[str, float]:
    """Every joint at 0 and mimic joints where a driver at 0 puts them (their offset): the pose
    RViz and Rerun's URDF loader show until the first joint state."""
    values = dict.fromkeys(model.joints, 0.0)
    follow_drivers(model, values)
    return values
