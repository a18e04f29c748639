"""A robot's 3D view reaches everything it holds: its target frame exists (map, else odom, else the
model's root) and every entity under the robot has a transform path to it, computed from the
transforms a real conversion wrote into the .rrd, as Rerun resolves them (named relations,
implicit ``tf#/<entity path>`` frames under their parent path, the view's target from its
blueprint or else the frame of its origin entity).

The data is the kind users bring (tests/host_bridge/user_robot.py): their own URDF with absolute
``file://`` meshes, Collada, mimic joints and no /joint_states; ``--urdf`` over a bag with TF
and its own /robot_description; a bag with no TF at all.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader

from host_bridge.cli import main as host_main
from host_bridge.converters.urdf.kinematics import robot_model
from host_bridge.core.contract import ColumnsItem, LogItem, repeated_texts
from host_bridge.core.frames import RobotFrames, frames_logged
from host_bridge.core.state import RobotState
from tests.host_bridge.user_robot import (
    FINGER_RIGHT_XYZ,
    MIMIC_MULTIPLIER,
    MIMIC_OFFSET,
    BagContent,
    user_urdf,
    write_bag,
    write_meshes,
    write_user_robot,
)

ROBOT = "robot"
ORIGIN = f"/{ROBOT}"


@dataclass
class Recording:
    """What a saved recording says about frames."""

    # Entity path -> its frame: the CoordinateFrame logged on it, else its implicit frame.
    entity_frames: dict[str, str] = field(default_factory=dict)
    # (child, parent) of every relation, and of the static ones only (what holds at any time).
    relations: set[tuple[str, str]] = field(default_factory=set)
    static_relations: set[tuple[str, str]] = field(default_factory=set)
    # Transform3D rows per entity: (static, translation or None, child frame or None).
    transforms: dict[str, list[tuple[bool, Any, str | None]]] = field(
        default_factory=lambda: defaultdict(list)
    )
    # Component columns logged per entity.
    components: dict[str, set[str]] = field(default_factory=lambda: defaultdict(set))
    # The robot's 3D view: origin, the target frame its blueprint names (None: unnamed), and
    # its contents queries.
    view_origin: str | None = None
    view_target: str | None = None
    view_contents: list[str] = field(default_factory=list)

    def target(self) -> str:
        """The view's target as the viewer picks it: the blueprint's, else the origin's frame."""
        assert self.view_origin is not None
        return self.view_target or self.entity_frames.get(self.view_origin, f"tf#{self.view_origin}")

    def in_view(self, entity: str) -> bool:
        """Whether the view's queries (``+ path/**``, ``- path/**``, ``$origin``) take ``entity``."""
        assert self.view_origin is not None
        included = excluded = False
        for query in self.view_contents:
            sign, _, pattern = query.partition(" ") if query[0] in "+-" else ("+", "", query)
            pattern = pattern.replace("$origin", self.view_origin)
            root = pattern.removesuffix("/**")
            matches = entity == root or (pattern.endswith("/**") and entity.startswith(root + "/"))
            included |= matches and sign == "+"
            excluded |= matches and sign == "-"
        return included and not excluded

    def pictures_without_pinhole(self) -> list[str]:
        """2D content in the 3D view under no pinhole: red errors in a 3D view."""
        pinholes = [e for e, names in self.components.items() if "Pinhole:image_from_camera" in names]
        return sorted(
            entity for entity, names in self.components.items()
            if names & {"Image:buffer", "EncodedImage:blob", "VideoStream:sample"}
            and self.in_view(entity)
            and not any(entity == p or entity.startswith(p + "/") for p in pinholes)
        )

    def unreachable(self, target: str, *, static_only: bool = False) -> dict[str, str]:
        """Entities under the robot whose frame has no path to ``target``, with that frame."""
        relations = self.static_relations if static_only else self.relations
        neighbours: dict[str, set[str]] = defaultdict(set)
        frames = set(self.entity_frames.values()) | {f for r in relations for f in r} | {target}
        for child, parent in relations:
            neighbours[child].add(parent)
            neighbours[parent].add(child)
        placed = {child for child, _ in relations}
        for frame in frames:
            # An implicit frame hangs from its parent path's, unless a relation names its parent.
            implicit = frame
            while implicit.startswith("tf#/") and implicit != "tf#/" and implicit not in placed:
                parent = "tf#" + (implicit[3:].rsplit("/", 1)[0] or "/")
                neighbours[implicit].add(parent)
                neighbours[parent].add(implicit)
                implicit = parent
        reached, todo = {target}, [target]
        while todo:
            for nxt in neighbours[todo.pop()] - reached:
                reached.add(nxt)
                todo.append(nxt)
        return {
            path: frame for path, frame in self.entity_frames.items()
            if (path == ORIGIN or path.startswith(f"{ORIGIN}/")) and frame not in reached
        }


def column(batch: Any, name: str) -> list[Any] | None:
    return batch.column(name).to_pylist() if name in batch.schema.names else None


def read_recording(path: Path) -> Recording:
    reader = RrdReader(path)
    found = Recording()
    for chunk in reader.stream():
        batch = chunk.to_record_batch()
        entity = chunk.entity_path
        found.entity_frames.setdefault(entity, f"tf#{entity}")
        found.components[entity].update(batch.schema.names)
        frames = column(batch, "CoordinateFrame:frame")
        if frames:
            found.entity_frames[entity] = [f for f in frames if f][-1][0]
        parents = column(batch, "Transform3D:parent_frame")
        if parents is None:
            continue
        children = column(batch, "Transform3D:child_frame") or [None] * len(parents)
        translations = column(batch, "Transform3D:translation") or [None] * len(parents)
        for parent, child, translation in zip(parents, children, translations, strict=True):
            child_frame = child[0] if child else f"tf#{entity}"
            found.transforms[entity].append(
                (chunk.is_static, translation[0] if translation else None, child[0] if child else None)
            )
            if parent:
                found.relations.add((child_frame, parent[0]))
                if chunk.is_static:
                    found.static_relations.add((child_frame, parent[0]))
    for store in reader.blueprints():  # the last one sent is the layout the viewer shows
        views: dict[str, dict[str, Any]] = defaultdict(dict)
        for chunk in reader.stream(store=store):
            view_path = "/".join(chunk.entity_path.split("/")[:3])  # /view/<id>
            batch = chunk.to_record_batch()
            for name in ("ViewBlueprint:display_name", "ViewBlueprint:space_origin",
                         "SpatialInformation:target_frame", "ViewContents:query"):
                values = column(batch, name)
                if values:
                    views[view_path][name] = values[-1]
        for view in views.values():
            if view.get("ViewBlueprint:display_name") == [f"{ROBOT} 3D"]:
                found.view_origin = view["ViewBlueprint:space_origin"][0]
                found.view_target = view.get("SpatialInformation:target_frame", [None])[0]
                found.view_contents = view["ViewContents:query"]
    return found


def convert(tmp_path: Path, content: BagContent, *extra: str) -> Recording:
    bag = write_bag(tmp_path / "bag", content)
    out = tmp_path / "out.rrd"
    assert host_main(["--bag", str(bag), "--robot", ROBOT, "--save", str(out), *extra]) == 0
    return read_recording(out)


def placed_at_root(recording: Recording) -> set[str]:
    return {child for child, parent in recording.static_relations if parent == f"tf#{ORIGIN}"}


def visual_links(recording: Recording) -> list[str]:
    return sorted(p.split("/")[3] for p in recording.entity_frames if p.endswith("/visual_0"))


def test_model_without_joint_states_is_one_tree_from_its_root(tmp_path: Path) -> None:
    """The user's URDF (file:// Collada, mimic joints) arrives, no /joint_states ever does: the
    view looks from the model's root and reaches every link, at every time."""
    meshes = write_meshes(tmp_path / "meshes")
    recording = convert(tmp_path, BagContent(description=user_urdf(meshes)))

    assert recording.view_origin == ORIGIN
    assert recording.view_target is None  # the data names it, see host_bridge/core/frames.py
    assert recording.target() == f"{ROBOT}/base_footprint"
    assert visual_links(recording) == ["base_link", "finger_left", "finger_right", "upper_arm", "wheel"]
    assert recording.entity_frames[f"{ORIGIN}/scan"] == f"{ROBOT}/base_link"
    assert recording.unreachable(recording.target()) == {}
    assert recording.unreachable(recording.target(), static_only=True) == {}
    # Through the model's own joints (movable ones at zero), not by being put at the root.
    assert placed_at_root(recording) == {f"{ROBOT}/base_footprint"}


def test_urdf_file_over_a_bag_with_tf_looks_from_odom_and_draws_one_model(tmp_path: Path) -> None:
    """--urdf replaces the bag's own /robot_description (other link names here), the bag's
    odom -> base_footprint carries the model, /joint_states moves the finger and its mimic."""
    urdf = write_user_robot(tmp_path / "mine")
    bag_model = user_urdf(tmp_path / "mine" / "meshes", name="bag_bot", prefix="bag_")
    content = BagContent(description=bag_model, odom_tf=True, joint_states=True)
    recording = convert(tmp_path, content, "--urdf", str(urdf))

    assert visual_links(recording) == ["base_link", "finger_left", "finger_right", "upper_arm", "wheel"]
    assert recording.target() == f"{ROBOT}/odom"
    assert (f"{ROBOT}/base_footprint", f"{ROBOT}/odom") in recording.relations
    assert recording.unreachable(recording.target()) == {}
    assert recording.unreachable(recording.target(), static_only=True) == {}
    # Both roots, until /tf places base_footprint under odom from its first stamp on.
    assert placed_at_root(recording) == {f"{ROBOT}/base_footprint", f"{ROBOT}/odom"}
    # Before the first joint state the mimic finger stands at its offset (static); the joint
    # states then move it from a temporal entity: -1 * 0.02 + 0.01 along y.
    static_pose = recording.transforms[f"{ORIGIN}/tf_static/finger_right"]
    assert [(s, c) for s, _, c in static_pose] == [(True, f"{ROBOT}/finger_right")]
    np.testing.assert_allclose(static_pose[0][1], np.add(FINGER_RIGHT_XYZ, [0, MIMIC_OFFSET, 0]),
                               atol=1e-6)
    moved = recording.transforms[f"{ORIGIN}/robot_model/joints/finger_right_joint"]
    assert len(moved) == 10
    assert not any(static for static, _, _ in moved)
    np.testing.assert_allclose(
        moved[-1][1], np.add(FINGER_RIGHT_XYZ, [0, MIMIC_MULTIPLIER * 0.02 + MIMIC_OFFSET, 0]),
        atol=1e-6,
    )


def test_bag_without_any_tf_has_every_frame_reachable(tmp_path: Path) -> None:
    """No TF, no model: a scan in ``laser`` and an IMU in ``imu_link`` that nothing relates.
    Both are drawn at the robot's root instead of showing red errors."""
    recording = convert(tmp_path, BagContent(scan_frame="laser", imu_frame="imu_link"))

    assert recording.entity_frames[f"{ORIGIN}/scan"] == f"{ROBOT}/laser"
    assert recording.view_target is None
    # No map, odom or model to look from: the viewer's own choice, the root every frame is in.
    assert recording.target() == f"tf#{ORIGIN}"
    assert recording.unreachable("tf#/") == {}
    assert {(f"{ROBOT}/laser", f"tf#{ORIGIN}"), (f"{ROBOT}/imu_link", f"tf#{ORIGIN}")} <= (
        recording.static_relations)


@pytest.mark.parametrize(
    ("bag", "target"),
    [
        # No TF at all: a real Hokuyo scan in "laser"; the viewer's own target.
        ("hokuyo_scan_ccny/laser_scan_matcher_demo.bag", f"tf#{ORIGIN}"),
        # Empty frame ids everywhere, a grid with resolution 0.
        ("ros_numpy_msgs_synthetic/ros_numpy_test.bag", f"tf#{ORIGIN}"),
        # odom -> base_footprint on /tf, base_footprint -> base_link on /tf_static.
        ("tf_nav2_sim_evo/tf_example.bag", f"{ROBOT}/odom"),
    ],
)
def test_real_bags_reach_every_entity(shared_data: Path, tmp_path: Path, bag: str, target: str) -> None:
    out = tmp_path / "real.rrd"
    assert host_main(["--bag", str(shared_data / bag), "--robot", ROBOT, "--save", str(out)]) == 0
    recording = read_recording(out)
    assert recording.target() == target
    assert len(recording.entity_frames) > 2
    assert recording.unreachable(target) == {}
    assert recording.pictures_without_pinhole() == []


# --- RobotFrames itself ---------------------------------------------------------------------------


def relation(parent: str, child: str) -> LogItem:
    return LogItem("/r/tf", (rr.Transform3D(parent_frame=parent, child_frame=child),))


def drawn_in(path: str, frame: str) -> LogItem:
    return LogItem(path, (rr.CoordinateFrame(frame), rr.Points3D([[0, 0, 0]])))


def logged(items: list[LogItem]) -> list[tuple[str, str, str]]:
    """(entity, parent, child) of placements and ("/r", "frame", target) of the target."""
    found = []
    for item in items:
        (archetype,) = item.archetypes
        assert item.static
        if isinstance(archetype, rr.CoordinateFrame):
            found.append((item.path, "frame", archetype.frame.as_arrow_array().to_pylist()[0]))  # type: ignore[union-attr]
        else:
            assert isinstance(archetype, rr.Transform3D)
            found.append((item.path, archetype.parent_frame.as_arrow_array().to_pylist()[0],  # type: ignore[union-attr]
                          archetype.child_frame.as_arrow_array().to_pylist()[0]))  # type: ignore[union-attr]
    return found


def test_unplaced_frames_go_to_the_robot_root_and_the_target_prefers_map() -> None:
    frames = RobotFrames("r")
    state = RobotState()
    assert logged(frames.observe([drawn_in("/r/scan", "r/laser")], state)) == [
        ("/r/tf_static/laser", "tf#/r", "r/laser")]
    assert frames.observe([drawn_in("/r/scan", "r/laser")], state) == []  # nothing new
    # odom appears with a child: odom is placed and becomes the target; laser keeps its place
    # until something names its parent.
    assert logged(frames.observe([relation("r/odom", "r/base_link")], state)) == [
        ("/r/tf_static/odom", "tf#/r", "r/odom"), ("/r", "frame", "r/odom")]
    assert logged(frames.observe([relation("r/map", "r/odom")], state)) == [
        ("/r/tf_static/map", "tf#/r", "r/map"), ("/r", "frame", "r/map")]
    assert frames.unplaced() == ["laser"]  # map is the target, odom has its parent now
    assert frames.observe([relation("r/base_link", "r/laser")], state) == []
    assert frames.unplaced() == []


def test_an_entity_hung_from_a_frame_places_that_frame_and_the_model_root_is_a_target() -> None:
    frames = RobotFrames("r")
    # The IMU's orientation: a transform with a parent frame and the entity's own as child.
    orientation = LogItem("/r/imu/orientation", (rr.Transform3D(parent_frame="r/imu_link"),))
    state = RobotState()
    assert logged(frames.observe([orientation], state)) == [
        ("/r/tf_static/imu_link", "tf#/r", "r/imu_link")]
    state.model = robot_model("m", [], root="base_footprint")
    assert logged(frames.observe([], state)) == [("/r", "frame", "r/base_footprint")]
    # Another robot's frames are its own business.
    assert frames.observe([drawn_in("/r/x", "r2/laser"), drawn_in("/r/y", "tf#/r/y")], state) == []


def test_frames_of_a_column_run_are_read_from_its_bytes() -> None:
    """A run of 3,000 TF rows over three relations (names of equal and of different sizes, one
    a prefix of another, non-ASCII) and 100 Imu rows with one parent: exactly those relations,
    from Arrow columns made by repeated_texts as the converters make them."""
    names = ["r/map", "r/odom", "r/odom", "r/base_link", "r/base_link", "r/bäse_link_2"]
    rows = np.arange(3000) % 3
    tf = ColumnsItem("/r/tf", list(rr.Transform3D.columns(
        translation=np.zeros((3000, 3)),
        parent_frame=repeated_texts(names[0::2], rows),
        child_frame=repeated_texts(names[1::2], rows),
    )), {"ros_time": np.arange(3000, dtype=np.int64)})
    imu = ColumnsItem("/r/imu/orientation", list(rr.Transform3D.columns(
        quaternion=np.tile([0.0, 0.0, 0.0, 1.0], (100, 1)),
        parent_frame=repeated_texts(["r/imu"], 100),
    )), {"ros_time": np.arange(100, dtype=np.int64)})
    assert frames_logged([tf, imu]) == ({
        ("r/odom", "r/map"), ("r/base_link", "r/odom"), ("r/bäse_link_2", "r/base_link"),
        ("tf#/r/imu/orientation", "r/imu")}, set())
    # The same relations in no repeating order (each row's bytes compared), and one period
    # cut short: found all the same.
    for order in (np.r_[np.zeros(50), np.ones(60), np.arange(91) % 3, np.full(40, 2)], rows[:-1]):
        shuffled = ColumnsItem("/r/tf", list(rr.Transform3D.columns(
            translation=np.zeros((len(order), 3)),
            parent_frame=repeated_texts(names[0::2], order.astype(np.intp)),
            child_frame=repeated_texts(names[1::2], order.astype(np.intp)),
        )), {"ros_time": np.arange(len(order), dtype=np.int64)})
        assert frames_logged([shuffled])[0] == {
            ("r/odom", "r/map"), ("r/base_link", "r/odom"), ("r/bäse_link_2", "r/base_link")}
    assert repeated_texts(["ab", "", "déf"], np.array([2, 0, 1, 0])).to_pylist() == [
        "déf", "ab", "", "ab"]
    assert repeated_texts(["ab", "c"], 2).to_pylist() == ["ab", "c", "ab", "c"]
    assert repeated_texts(["ab", "c"], 100).to_pylist() == ["ab", "c"] * 100
    assert repeated_texts(["é"], 40).to_pylist() == ["é"] * 40
    backwards = (np.arange(99) % 3)[::-1]
    assert repeated_texts(["ab", "", "déf"], backwards).to_pylist() == [
        ["ab", "", "déf"][row] for row in backwards]
