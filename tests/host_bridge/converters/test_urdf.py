"""Robot model: TurtleBot3 URDFs with their STL meshes, primitives, resolution, errors."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest
import rerun as rr
import trimesh
import trimesh.transformations as tra
from PIL import Image

from host_bridge.converters.urdf import description
from host_bridge.core.contract import ConvertContext, LogEntry, LogItem
from host_bridge.core.resources import ResourceResolver, parse_package_path
from host_bridge.core.state import RobotModel, RobotState
from host_bridge.errors import ConfigError, ConvertError, PartialConvertError
from tests.host_bridge.sensor_test_support import make_ctx
from tests.host_bridge.user_robot import (
    ARM_DARK,
    ARM_RED,
    FINGER_LEFT_XYZ,
    FINGER_RIGHT_XYZ,
    MIMIC_OFFSET,
    ROBOT_SHARE,
    SHOULDER_XYZ,
    Flat,
    Textured,
    collada,
    user_urdf,
    write_texture,
    write_user_robot,
)
from tests.host_bridge.user_robot import PACKAGE as USER_PACKAGE

PACKAGE = "turtlebot3_description"
MESHES = {
    "burger": {
        "base_link": "bases/burger_base.stl",
        "wheel_left_link": "wheels/left_tire.stl",
        "wheel_right_link": "wheels/right_tire.stl",
        "base_scan": "sensors/lds.stl",
    },
    "waffle_pi": {
        "base_link": "bases/waffle_pi_base.stl",
        "wheel_left_link": "wheels/left_tire.stl",
        "wheel_right_link": "wheels/right_tire.stl",
        "base_scan": "sensors/lds.stl",
    },
}


@pytest.fixture
def tb3(shared_data: Path) -> Path:
    """The directory holding the turtlebot3_description package (a ROS_PACKAGE_PATH entry)."""
    return shared_data / PACKAGE


def urdf_text(tb3: Path, model: str) -> str:
    return (tb3 / PACKAGE / "urdf" / f"turtlebot3_{model}.urdf").read_text()


def description_ctx(robot: str, resolver: ResourceResolver | None = None) -> ConvertContext:
    """/robot_description of ``robot``, its meshes found by ``resolver`` (else ROS's paths)
    bound to the robot, as the dispatcher binds it."""
    state = RobotState() if resolver is None else RobotState(resolver.for_robot(robot))
    return make_ctx("/robot_description", stamp_ns=0, robot=robot, robot_state=state)


def convert(xml: str, ctx: ConvertContext) -> list[LogEntry]:
    return description.convert(SimpleNamespace(data=xml), ctx)


def by_path(items: list[LogEntry]) -> dict[str, LogItem]:
    return {item.path: item for item in items if isinstance(item, LogItem)}


def archetype(item: LogItem, kind: type[Any]) -> Any:
    (found,) = [a for a in item.archetypes if isinstance(a, kind)]
    return found


def values(batch: Any) -> npt.NDArray[Any]:
    return np.asarray(batch.as_arrow_array().to_pylist())


def packed(rgba: list[int]) -> int:
    r, g, b, a = rgba
    return (r << 24) | (g << 16) | (b << 8) | a


def rotation(quaternion_xyzw: npt.NDArray[Any]) -> npt.NDArray[np.float64]:
    x, y, z, w = quaternion_xyzw
    matrix: npt.NDArray[np.float64] = tra.quaternion_matrix([w, x, y, z])  # type: ignore[no-untyped-call]
    return matrix[:3, :3]


def load_mesh(path: Path) -> trimesh.Trimesh:
    mesh = trimesh.load(path, force="mesh")
    assert isinstance(mesh, trimesh.Trimesh)
    return mesh


@pytest.mark.parametrize("model", ["burger", "waffle_pi"])
def test_turtlebot_meshes_match_trimesh_in_metres(tb3: Path, model: str) -> None:
    ctx = description_ctx("tb1", ResourceResolver(search_paths=[tb3]))
    items = by_path(convert(urdf_text(tb3, model), ctx))
    meshes = {path: item for path, item in items.items() if "/tf_static/" not in path}
    assert sorted(meshes) == sorted(f"/tb1/robot_model/{link}/visual_0" for link in MESHES[model])
    for link, relpath in MESHES[model].items():
        item = meshes[f"/tb1/robot_model/{link}/visual_0"]
        assert item.static
        reference = load_mesh(tb3 / PACKAGE / "meshes" / relpath)
        mesh = archetype(item, rr.Mesh3D)
        positions = values(mesh.vertex_positions)
        assert len(positions) == len(reference.vertices)
        assert len(values(mesh.triangle_indices)) == len(reference.faces)
        np.testing.assert_allclose(positions, reference.vertices * 0.001, rtol=1e-6, atol=1e-7)
        # A uniform scale leaves trimesh's normals as they are.
        np.testing.assert_allclose(values(mesh.vertex_normals), reference.vertex_normals, atol=1e-5)
        assert values(archetype(item, rr.CoordinateFrame).frame).tolist() == [f"tb1/{link}"]
    base = values(archetype(meshes["/tb1/robot_model/base_link/visual_0"], rr.Mesh3D).vertex_positions)
    base_extent = np.ptp(base, axis=0)
    expected_width = {"burger": 0.1375, "waffle_pi": 0.2655}[model]
    assert base_extent[0] == pytest.approx(expected_width, abs=1e-3)
    tire = values(archetype(meshes["/tb1/robot_model/wheel_left_link/visual_0"], rr.Mesh3D).vertex_positions)
    assert np.ptp(tire, axis=0) == pytest.approx([0.066, 0.0182, 0.066], abs=1e-4)


def test_visual_origin_and_material_colour(tb3: Path) -> None:
    ctx = description_ctx("tb1", ResourceResolver(search_paths=[tb3]))
    items = by_path(convert(urdf_text(tb3, "burger"), ctx))
    base = items["/tb1/robot_model/base_link/visual_0"]
    pose = archetype(base, rr.InstancePoses3D)
    np.testing.assert_allclose(values(pose.translations), [[-0.032, 0.0, 0.0]], atol=1e-7)
    np.testing.assert_allclose(values(pose.quaternions), [[0.0, 0.0, 0.0, 1.0]], atol=1e-7)
    # light_black is a named top-level material: 0.4 grey.
    assert values(archetype(base, rr.Mesh3D).albedo_factor).tolist() == [packed([102, 102, 102, 255])]
    wheel = archetype(items["/tb1/robot_model/wheel_left_link/visual_0"], rr.InstancePoses3D)
    (quaternion,) = values(wheel.quaternions)
    expected: npt.NDArray[np.float64] = tra.euler_matrix(1.57, 0, 0)  # type: ignore[no-untyped-call]
    np.testing.assert_allclose(rotation(quaternion), expected[:3, :3], atol=1e-6)


def test_every_joint_is_static_with_the_wheels_at_zero(tb3: Path) -> None:
    ctx = description_ctx("tb1", ResourceResolver(search_paths=[tb3]))
    items = by_path(convert(urdf_text(tb3, "burger"), ctx))
    # On the entity /tf_static uses for the child frame: one entity per relation (see tf.py).
    joints = sorted(path for path in items if "/tf_static/" in path)
    assert joints == [
        f"/tb1/tf_static/{child}"
        for child in ("base_link", "base_scan", "caster_back_link", "imu_link", "wheel_left_link",
                      "wheel_right_link")
    ]
    # Continuous wheel joints stand at 0 until /joint_states moves them: the joint origin.
    wheel = archetype(items["/tb1/tf_static/wheel_left_link"], rr.Transform3D)
    assert items["/tb1/tf_static/wheel_left_link"].static
    assert values(wheel.parent_frame).tolist() == ["tb1/base_link"]
    assert values(wheel.child_frame).tolist() == ["tb1/wheel_left_link"]
    np.testing.assert_allclose(values(wheel.translation), [[0.0, 0.08, 0.023]], atol=1e-7)
    expected: npt.NDArray[np.float64] = tra.euler_matrix(-1.57, 0, 0)  # type: ignore[no-untyped-call]
    np.testing.assert_allclose(rotation(values(wheel.quaternion)[0]), expected[:3, :3], atol=1e-6)
    scan = items["/tb1/tf_static/base_scan"]
    assert scan.static
    transform = archetype(scan, rr.Transform3D)
    assert values(transform.parent_frame).tolist() == ["tb1/base_link"]
    assert values(transform.child_frame).tolist() == ["tb1/base_scan"]
    np.testing.assert_allclose(values(transform.translation), [[-0.032, 0.0, 0.172]], atol=1e-7)
    model = ctx.robot_state.model
    assert isinstance(model, RobotModel)
    assert model.joints["wheel_left_joint"].type == "continuous"


def test_fixed_joint_already_on_tf_is_left_to_tf(tb3: Path) -> None:
    ctx = description_ctx("tb1", ResourceResolver(search_paths=[tb3]))
    ctx.robot_state.tf_children.update({"base_scan", "tb1/imu_link"})
    joints = sorted(path for path in by_path(convert(urdf_text(tb3, "burger"), ctx)) if "/tf_static/" in path)
    assert joints == [
        "/tb1/tf_static/base_link", "/tb1/tf_static/caster_back_link",
        "/tb1/tf_static/wheel_left_link", "/tb1/tf_static/wheel_right_link",
    ]


def test_missing_mesh_one_error_rest_logged(tb3: Path) -> None:
    missing = f"package://{PACKAGE}/meshes/sensors/no_such_lidar.stl"
    xml = urdf_text(tb3, "burger").replace(f"package://{PACKAGE}/meshes/sensors/lds.stl", missing)
    with pytest.raises(PartialConvertError) as caught:
        convert(xml, description_ctx("tb1", ResourceResolver(search_paths=[tb3])))
    message = str(caught.value)
    assert missing in message
    assert "'base_scan'" in message
    assert message.count("package://") == 1
    logged = by_path(caught.value.items)
    assert sorted(path for path in logged if "/tf_static/" not in path) == [
        "/tb1/robot_model/base_link/visual_0",
        "/tb1/robot_model/wheel_left_link/visual_0",
        "/tb1/robot_model/wheel_right_link/visual_0",
    ]
    assert "/tb1/tf_static/base_scan" in logged


def test_two_robots_never_share_paths_or_frames(tb3: Path) -> None:
    resolver = ResourceResolver(search_paths=[tb3])
    xml = urdf_text(tb3, "burger")
    tb1, tb2 = description_ctx("tb1", resolver), description_ctx("tb2", resolver)
    first, second = by_path(convert(xml, tb1)), by_path(convert(xml, tb2))
    assert all(path.startswith(("/tb1/robot_model/", "/tb1/tf_static/")) for path in first)
    assert all(path.startswith(("/tb2/robot_model/", "/tb2/tf_static/")) for path in second)
    assert {p.replace("/tb1/", "/tb2/", 1) for p in first} == set(second)
    frame = archetype(second["/tb2/robot_model/base_scan/visual_0"], rr.CoordinateFrame)
    assert values(frame.frame).tolist() == ["tb2/base_scan"]
    scan = archetype(second["/tb2/tf_static/base_scan"], rr.Transform3D)
    assert values(scan.parent_frame).tolist() == ["tb2/base_link"]
    assert tb1.robot_state.model is not tb2.robot_state.model


PRIMITIVES = """<?xml version="1.0" encoding="utf-8"?>
<robot name="shapes">
  <material name="blue"><color rgba="0 0 1 1"/></material>
  <link name="base">
    <visual>
      <origin xyz="1 2 3" rpy="0 0 1.5707963267948966"/>
      <geometry><box size="0.2 0.4 0.6"/></geometry>
      <material name="blue"/>
    </visual>
    <visual>
      <geometry><cylinder radius="0.05" length="0.3"/></geometry>
      <material name="inline"><color rgba="1 0.5 0 0.5"/></material>
    </visual>
  </link>
  <link name="head">
    <visual><geometry><sphere radius="0.1"/></geometry></visual>
  </link>
  <joint name="neck" type="fixed">
    <parent link="base"/><child link="head"/><origin xyz="0 0 0.5"/>
  </joint>
</robot>
"""


def test_primitives_colours_and_origins() -> None:
    items = by_path(convert(PRIMITIVES, description_ctx("bot", ResourceResolver())))
    box_item = items["/bot/robot_model/base/visual_0"]
    box = archetype(box_item, rr.Boxes3D)
    np.testing.assert_allclose(values(box.half_sizes), [[0.1, 0.2, 0.3]], atol=1e-7)
    assert values(box.colors).tolist() == [packed([0, 0, 255, 255])]
    assert values(box.fill_mode).tolist() == [rr.components.FillMode.Solid.value]
    pose = archetype(box_item, rr.InstancePoses3D)
    np.testing.assert_allclose(values(pose.translations), [[1.0, 2.0, 3.0]])
    np.testing.assert_allclose(values(pose.quaternions), [[0, 0, np.sqrt(0.5), np.sqrt(0.5)]], atol=1e-7)
    cylinder = archetype(items["/bot/robot_model/base/visual_1"], rr.Cylinders3D)
    np.testing.assert_allclose(values(cylinder.radii), [0.05])
    np.testing.assert_allclose(values(cylinder.lengths), [0.3])
    assert values(cylinder.colors).tolist() == [packed([255, 128, 0, 128])]
    sphere_item = items["/bot/robot_model/head/visual_0"]
    np.testing.assert_allclose(values(archetype(sphere_item, rr.Ellipsoids3D).half_sizes), [[0.1] * 3])
    assert values(archetype(sphere_item, rr.CoordinateFrame).frame).tolist() == ["bot/head"]
    neck = archetype(items["/bot/tf_static/head"], rr.Transform3D)
    np.testing.assert_allclose(values(neck.translation), [[0.0, 0.0, 0.5]])


def mesh_urdf(*meshes: tuple[str, str]) -> str:
    """One link per (filename, scale), each fixed to a bare root link (one root, as URDF has)."""
    links = "".join(
        f'<link name="l{i}"><visual><geometry><mesh filename="{name}" scale="{scale}"/>'
        f'</geometry></visual></link><joint name="j{i}" type="fixed"><parent link="base"/>'
        f'<child link="l{i}"/></joint>'
        for i, (name, scale) in enumerate(meshes)
    )
    return f'<robot name="meshes"><link name="base"/>{links}</robot>'


def write_box(path: Path) -> None:
    box = trimesh.creation.box(extents=[1.0, 2.0, 4.0])
    path.parent.mkdir(parents=True, exist_ok=True)
    box.export(path)


def mesh_of(items: dict[str, LogItem], link: str) -> Any:
    return archetype(items[f"/r/robot_model/{link}/visual_0"], rr.Mesh3D)


def test_file_form_relative_file_uri_and_formats(tmp_path: Path) -> None:
    write_box(tmp_path / "meshes" / "box.stl")
    write_box(tmp_path / "meshes" / "box.obj")
    write_box(tmp_path / "elsewhere" / "box.dae")
    urdf_file = tmp_path / "robot.urdf"
    urdf_file.write_text(
        mesh_urdf(
            ("meshes/box.stl", "0.5 0.5 0.5"),
            ("meshes/box.obj", "1 1 1"),
            (f"file://{tmp_path}/elsewhere/box.dae", "-1 1 1"),
        )
    )
    items = by_path(description.model_items_from_file(urdf_file, description_ctx("r", ResourceResolver())))
    stl = mesh_of(items, "l0")
    assert np.ptp(values(stl.vertex_positions), axis=0) == pytest.approx([0.5, 1.0, 2.0])
    for link, name in (("l1", "meshes/box.obj"), ("l2", "elsewhere/box.dae")):
        reference = load_mesh(tmp_path / name)
        assert len(values(mesh_of(items, link).vertex_positions)) == len(reference.vertices)
    # A mirroring scale flips the winding so faces stay outward.
    dae = mesh_of(items, "l2")
    reference = load_mesh(tmp_path / "elsewhere" / "box.dae")
    np.testing.assert_array_equal(values(dae.triangle_indices), reference.faces[:, ::-1])
    np.testing.assert_allclose(values(dae.vertex_positions)[:, 0], -reference.vertices[:, 0])


def test_unreadable_urdf_file_is_a_convert_error(tmp_path: Path) -> None:
    with pytest.raises(ConvertError, match="--urdf"):
        description.model_items_from_file(tmp_path / "absent.urdf", description_ctx("r"))


@pytest.mark.parametrize(
    ("xml", "match"),
    [
        ("", "not well-formed"),
        ("<robot name='x'><link name='a'>", "not well-formed"),
        ("<sdf version='1.6'/>", "not <robot>"),
        (
            "<robot name='x'><joint name='j' type='fixed'><child link='a'/></joint></robot>",
            "not a valid URDF",
        ),
    ],
)
def test_bad_descriptions_are_convert_errors(xml: str, match: str) -> None:
    with pytest.raises(ConvertError, match=match):
        convert(xml, description_ctx("r", ResourceResolver()))


def test_package_path_beats_search_paths_and_fetch_is_the_fallback(tmp_path: Path) -> None:
    box_bytes = trimesh.creation.box(extents=[1.0, 1.0, 1.0]).export(file_type="stl")
    write_box(tmp_path / "explicit" / "meshes" / "a.stl")
    write_box(tmp_path / "search" / "pkg" / "meshes" / "a.stl")
    asked: list[str] = []

    def fetch(uri: str) -> bytes | None:
        asked.append(uri)
        return box_bytes if uri == "package://remote_pkg/meshes/b.stl" else None

    resolver = ResourceResolver(
        package_paths=dict([parse_package_path(f"pkg={tmp_path / 'explicit'}")]),
        search_paths=[tmp_path / "search"],
        fetch=fetch,
    )
    assert resolver.locate("package://pkg/meshes/a.stl") == tmp_path / "explicit" / "meshes" / "a.stl"
    xml = mesh_urdf(("package://pkg/meshes/a.stl", "1 1 1"), ("package://remote_pkg/meshes/b.stl", "1 1 1"))
    items = by_path(convert(xml, description_ctx("r", resolver)))
    assert np.ptp(values(mesh_of(items, "l0").vertex_positions), axis=0) == pytest.approx([1, 2, 4])
    assert np.ptp(values(mesh_of(items, "l1").vertex_positions), axis=0) == pytest.approx([1, 1, 1])
    assert asked == ["package://remote_pkg/meshes/b.stl"]


def test_robot_share_paths_resolve_as_packages(tb3: Path) -> None:
    xml = urdf_text(tb3, "burger").replace(
        f"package://{PACKAGE}/", f"file:///opt/ros/humble/share/{PACKAGE}/"
    )
    items = by_path(convert(xml, description_ctx("tb1", ResourceResolver(search_paths=[tb3]))))
    assert len([path for path in items if "/visual_" in path]) == 4


def test_environment_is_the_default_resolver(tb3: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ROS_PACKAGE_PATH", str(tb3))
    monkeypatch.delenv("AMENT_PREFIX_PATH", raising=False)
    items = by_path(convert(urdf_text(tb3, "burger"), description_ctx("tb1")))
    assert len([path for path in items if "/visual_" in path]) == 4


def test_not_found_message_says_what_to_do(tmp_path: Path) -> None:
    resolver = ResourceResolver(search_paths=[tmp_path])
    with pytest.raises(ConvertError, match=r"--package-path foo=DIR") as caught:
        resolver.read("package://foo/meshes/x.stl")
    assert f"search path {tmp_path}" in str(caught.value)
    with pytest.raises(ConvertError, match="only package://"):
        resolver.read("http://example.com/x.stl")


def test_package_path_option_parsing(tmp_path: Path) -> None:
    assert parse_package_path(f"pkg={tmp_path}") == ("pkg", tmp_path)
    for bad in ("pkg", "=dir", "pkg=", "a/b=dir"):
        with pytest.raises(ConfigError):
            parse_package_path(bad)


OBJ = b"""mtllib {mtl}
v 0 0 0
v 1 0 0
v 0 1 0
vt 0 0
vt 1 0
vt 0 1
usemtl m
f 1/1 2/2 3/3
"""


def test_obj_materials_and_textures_come_through_the_resolver(tmp_path: Path) -> None:
    texture = tmp_path / "tex.png"
    pixels = np.array([[[255, 0, 0], [0, 255, 0]], [[0, 0, 255], [9, 9, 9]]], np.uint8)
    Image.fromarray(pixels).save(texture)
    served = {
        "package://remote/m/red.obj": OBJ.replace(b"{mtl}", b"red.mtl"),
        "package://remote/m/red.mtl": b"newmtl m\nKd 1 0 0\n",
        "package://remote/m/tex.obj": OBJ.replace(b"{mtl}", b"tex.mtl"),
        "package://remote/m/tex.mtl": b"newmtl m\nKd 1 1 1\nmap_Kd tex.png\n",
        "package://remote/m/tex.png": texture.read_bytes(),
    }
    resolver = ResourceResolver(fetch=served.get)
    xml = mesh_urdf(("package://remote/m/red.obj", "1 1 1"), ("package://remote/m/tex.obj", "1 1 1"))
    items = by_path(convert(xml, description_ctx("r", resolver)))
    red = mesh_of(items, "l0")
    assert values(red.albedo_factor).tolist() == [packed([255, 0, 0, 255])]
    assert red.albedo_texture_buffer is None
    textured = mesh_of(items, "l1")
    assert textured.albedo_factor is None
    # trimesh's uv origin is bottom-left, Rerun's top-left: v is flipped.
    np.testing.assert_allclose(values(textured.vertex_texcoords), [[0, 1], [1, 1], [0, 0]])
    assert values(textured.albedo_texture_buffer)[0][:4].tolist() == [255, 0, 0, 255]


# --- a user's own robot: absolute file:// meshes, Collada materials, mimic joints -----------------


def user_model(tmp_path: Path) -> tuple[dict[str, LogItem], ConvertContext]:
    ctx = description_ctx("r", ResourceResolver())
    return by_path(description.model_items_from_file(write_user_robot(tmp_path), ctx)), ctx


def test_user_model_stands_at_zero_with_the_mimic_finger_at_its_offset(tmp_path: Path) -> None:
    items, ctx = user_model(tmp_path)
    visuals = sorted(path for path in items if "/robot_model/" in path)
    assert visuals == [f"/r/robot_model/{link}/visual_0" for link in
                       ("base_link", "finger_left", "finger_right", "upper_arm", "wheel")]
    joints = {path.rsplit("/", 1)[1]: archetype(item, rr.Transform3D)
              for path, item in items.items() if "/tf_static/" in path}
    # Every link but the root has a relation, so the model is one tree from base_footprint.
    assert sorted(joints) == ["base_link", "finger_left", "finger_right", "upper_arm", "wheel"]
    assert {values(t.parent_frame)[0] for t in joints.values()} == {
        "r/base_footprint", "r/base_link", "r/upper_arm"}
    assert ctx.robot_state.model is not None
    assert ctx.robot_state.model.root == "base_footprint"
    np.testing.assert_allclose(values(joints["finger_left"].translation), [FINGER_LEFT_XYZ], atol=1e-7)
    # finger_right mimics finger_left at 0: -1 * 0 + 0.01 along its y axis.
    right = np.add(FINGER_RIGHT_XYZ, [0.0, MIMIC_OFFSET, 0.0])
    np.testing.assert_allclose(values(joints["finger_right"].translation), [right], atol=1e-7)
    # The revolute shoulder at 0 is its origin: 0.5 rad about z.
    np.testing.assert_allclose(values(joints["upper_arm"].translation), [SHOULDER_XYZ], atol=1e-7)
    np.testing.assert_allclose(values(joints["upper_arm"].quaternion),
                               [[0, 0, np.sin(0.25), np.cos(0.25)]], atol=1e-7)


def colours_by_triangle(mesh: Any) -> list[list[int]]:
    """The RGBA of each triangle's vertices, from vertex colours or the albedo texture."""
    triangles = values(mesh.triangle_indices)
    if mesh.albedo_texture_buffer is None:
        rgba = [[(c >> s) & 0xFF for s in (24, 16, 8, 0)] for c in values(mesh.vertex_colors)]
    else:
        layout = mesh.albedo_texture_format.as_arrow_array().to_pylist()[0]
        height, width = layout["height"], layout["width"]
        image = values(mesh.albedo_texture_buffer)[0].astype(np.uint8).reshape(height, width, 4)
        # Rerun samples with wrap-around, v from the top.
        rgba = [image[int(v % 1 * height), int(u % 1 * width)].tolist()
                for u, v in values(mesh.vertex_texcoords)]
    corner_colours = [[rgba[i] for i in triangle] for triangle in triangles]
    assert all(colours[0] == colours[1] == colours[2] for colours in corner_colours)
    return [colours[0] for colours in corner_colours]


def dae_mesh(tmp_path: Path, materials: list[Flat | Textured]) -> Any:
    (tmp_path / "part.dae").write_text(collada(materials))
    xml = mesh_urdf((f"file://{tmp_path}/part.dae", "1 1 1"))
    return mesh_of(by_path(convert(xml, description_ctx("r", ResourceResolver()))), "l0")


def test_multi_material_collada_keeps_each_diffuse_colour(tmp_path: Path) -> None:
    mesh = dae_mesh(tmp_path, [Flat(ARM_DARK), Flat(ARM_RED)])
    # The diffuse colours as written (64/255 once came out as 137/255), one per triangle.
    assert colours_by_triangle(mesh) == [[*ARM_DARK, 255], [*ARM_RED, 255]]
    assert mesh.albedo_factor is None  # would tint the vertex colours
    # The same colour as the one-material path logs it.
    single = dae_mesh(tmp_path, [Flat(ARM_DARK)])
    assert values(single.albedo_factor).tolist() == [packed([*ARM_DARK, 255])]


def test_textured_and_flat_collada_materials_keep_their_colours(tmp_path: Path) -> None:
    write_texture(tmp_path / "green.png", (10, 200, 30))
    mesh = dae_mesh(tmp_path, [Flat(ARM_DARK), Textured("green.png"), Flat(ARM_RED)])
    assert colours_by_triangle(mesh) == [[*ARM_DARK, 255], [10, 200, 30, 255], [*ARM_RED, 255]]
    # Triangle i of the file is at z = i: the parts stay in file order.
    np.testing.assert_allclose(values(mesh.vertex_positions)[:, 2], np.repeat([0, 1, 2], 3))


def test_gltf_base_colour_is_linear_and_made_srgb(tmp_path: Path) -> None:
    """glTF's baseColorFactor is linear (unlike Collada's diffuse): 0.2140 is sRGB 128/255."""
    linear = round(0.21404 * 255)
    parts = []
    for z, rgb in ((0.0, [linear, linear, linear]), (2.0, [255, 0, 0])):
        box = trimesh.creation.box(extents=[1, 1, 1])
        box.apply_translation([0, 0, z])
        material = trimesh.visual.material.PBRMaterial(baseColorFactor=[*rgb, 255])  # type: ignore[no-untyped-call]
        box.visual = trimesh.visual.TextureVisuals(material=material)  # type: ignore[no-untyped-call]
        parts.append(box)
    trimesh.Scene(parts).export(tmp_path / "two.glb")  # type: ignore[no-untyped-call]
    parts[0].export(tmp_path / "one.glb")
    xml = mesh_urdf((f"file://{tmp_path}/one.glb", "1 1 1"), (f"file://{tmp_path}/two.glb", "1 1 1"))
    items = by_path(convert(xml, description_ctx("r", ResourceResolver())))
    assert values(mesh_of(items, "l0").albedo_factor).tolist() == [packed([128, 128, 128, 255])]
    two = colours_by_triangle(mesh_of(items, "l1"))
    assert sorted({tuple(c) for c in two}) == [(128, 128, 128, 255), (255, 0, 0, 255)]


def test_missing_meshes_name_each_file_where_and_what_to_pass_once(tmp_path: Path) -> None:
    robot_meshes = f"file://{ROBOT_SHARE}/meshes"
    write_box(tmp_path / "here" / "box.stl")
    (tmp_path / "broken.stl").write_bytes(b"solid nothing\nendsolid\n")
    xml = mesh_urdf(
        (f"{robot_meshes}/base.dae", "1 1 1"),
        (f"{robot_meshes}/arm.dae", "1 1 1"),
        ("package://other_pkg/meshes/c.stl", "1 1 1"),
        (f"file://{tmp_path}/here/box.stl", "1 1 1"),
        (f"file://{tmp_path}/broken.stl", "1 1 1"),
    )
    search = [tmp_path / "ws_a", tmp_path / "ws_b"]
    with pytest.raises(PartialConvertError) as caught:
        convert(xml, description_ctx("r", ResourceResolver(search_paths=search)))
    message = str(caught.value)
    assert message == (
        "/robot_description: robot model 'meshes': 4 of 5 visuals not drawn: mesh files not "
        f"found: {robot_meshes}/: base.dae for link 'l0', arm.dae for link 'l1'; "
        "package://other_pkg/meshes/c.stl for link 'l2'; "
        f"looked in search path {search[0]}, search path {search[1]}; no robot file server to ask; "
        f"pass --package-path {USER_PACKAGE}=DIR --package-path other_pkg=DIR; "
        f"link 'l4': file://{tmp_path}/broken.stl: the file holds no triangles"
    )
    assert [path for path in by_path(caught.value.items) if "/visual_" in path] == [
        "/r/robot_model/l3/visual_0"]


def test_urdf_file_replaces_the_robot_description(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = write_user_robot(tmp_path)
    ctx = description_ctx("r", ResourceResolver())
    from_file = description.model_items_from_file(path, ctx)
    model = ctx.robot_state.model
    caplog.set_level("INFO", logger="swanky.host")
    other = user_urdf(tmp_path / "meshes", name="bag_bot", prefix="bag_")
    assert convert(other, ctx) == []
    assert convert(other, ctx) == []
    assert ctx.robot_state.model is model  # /joint_states keeps moving the file's model
    assert [r.getMessage() for r in caplog.records] == [
        f"[r] /robot_description: not drawn, the robot model is --urdf {path}"]
    assert len(from_file) == 10


def test_urdf_file_warning_names_the_file_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Through the command line: the --urdf file's missing mesh is one warning line that names
    the file once (it read ``robot.urdf: robot.urdf: ...``)."""
    from host_bridge.cli import main as host_main
    from tests.host_bridge.user_robot import BagContent, write_bag

    for variable in ("ROS_PACKAGE_PATH", "AMENT_PREFIX_PATH"):
        monkeypatch.delenv(variable, raising=False)
    path = write_user_robot(tmp_path)
    (tmp_path / "meshes" / "arm.dae").unlink()
    bag = write_bag(tmp_path / "bag", BagContent())
    with caplog.at_level("WARNING", logger="swanky.host"):
        assert host_main(["--bag", str(bag), "--urdf", str(path), "--save", str(tmp_path / "o.rrd")]) == 0
    (warning,) = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert warning == (
        f"[robot] {path}: robot model 'arm_bot': 1 of 5 visuals not drawn: mesh files not found: "
        f"file://{tmp_path}/meshes/arm.dae for link 'upper_arm'; looked in no --package-path "
        "and no ROS_PACKAGE_PATH/AMENT_PREFIX_PATH; no robot file server to ask "
        "(further PartialConvertErrors on this topic are counted, not shown)"
    )
