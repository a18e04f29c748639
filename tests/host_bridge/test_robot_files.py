"""Meshes the PC lacks, fetched from the robot's relay (host_bridge/inputs/robot_files.py) through the
resource resolver, against the relay's real file server in one local Zenoh session."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import rerun as rr
import trimesh
import zenoh

from host_bridge.core.resources import ResourceResolver
from host_bridge.errors import ConvertError, PartialConvertError
from host_bridge.inputs.robot_files import RobotFiles
from robot_relay.files import serve_files
from tests.host_bridge.converters.test_urdf import (
    archetype,
    by_path,
    convert,
    description_ctx,
    mesh_urdf,
    values,
)

BOX = trimesh.creation.box(extents=[1.0, 2.0, 4.0]).export(file_type="stl")


@pytest.fixture
def session() -> Iterator[zenoh.Session]:
    config = zenoh.Config()
    config.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(config) as opened:
        yield opened


@pytest.fixture
def package(tmp_path: Path) -> Path:
    (tmp_path / "pkg" / "meshes").mkdir(parents=True)
    (tmp_path / "pkg" / "meshes" / "box.stl").write_bytes(BOX)
    return tmp_path / "pkg"


def test_fetches_from_the_robot_and_keeps_the_bytes(session: zenoh.Session, package: Path) -> None:
    service = serve_files(session, "tb1", [f"pkg={package}"], environ={})
    files = RobotFiles(timeout=5.0)
    files.attach(session)
    assert files.fetch("tb1", "package://pkg/meshes/box.stl") == BOX
    with pytest.raises(ConvertError, match=r"robot tb1 refused package://pkg/meshes/none.stl \(not_found:"):
        files.fetch("tb1", "package://pkg/meshes/none.stl")
    with pytest.raises(ConvertError, match=r"robot tb1 refused .*\(unknown_package:"):
        files.fetch("tb1", "package://other/meshes/box.stl")
    service.close()
    # Cached: the relay is gone, the bytes are not.
    assert files.fetch("tb1", "package://pkg/meshes/box.stl") == BOX


def test_a_silent_robot_is_named_and_not_asked_again_at_once(session: zenoh.Session) -> None:
    files = RobotFiles(timeout=0.5, quiet=60.0)
    with pytest.raises(ConvertError, match="cannot be asked"):
        files.fetch("tb9", "package://pkg/a.stl")  # no session attached: a bag, not a robot
    files.attach(session)
    with pytest.raises(ConvertError, match=r"no file server of robot tb9 answered for package://pkg/a\.stl"):
        files.fetch("tb9", "package://pkg/a.stl")
    with pytest.raises(ConvertError, match="did not answer a file request just before; not asked for"):
        files.fetch("tb9", "package://pkg/b.stl")
    with pytest.raises(ConvertError, match=r"cannot be asked for package://pkg//b\.stl"):
        files.fetch("tb8", "package://pkg//b.stl")  # not a valid key: empty chunk


def test_the_model_gets_each_robots_meshes_and_names_refusals(session: zenoh.Session, package: Path) -> None:
    service = serve_files(session, "tb1", [f"pkg={package}"], environ={})
    files = RobotFiles(timeout=1.0)
    files.attach(session)
    resolver = ResourceResolver(robot_fetch=files.fetch)
    xml = mesh_urdf(("package://pkg/meshes/box.stl", "1 1 1"), ("package://pkg/meshes/gone.stl", "1 1 1"))
    try:
        with pytest.raises(PartialConvertError) as caught:
            convert(xml, description_ctx("tb1", resolver))
    finally:
        service.close()
    message = str(caught.value)
    assert "robot model 'meshes': 1 of 2 visuals not drawn" in message
    assert "robot tb1 refused package://pkg/meshes/gone.stl (not_found:" in message
    mesh = archetype(by_path(caught.value.items)["/tb1/robot_model/l0/visual_0"], rr.Mesh3D)
    assert np.ptp(values(mesh.vertex_positions), axis=0).tolist() == [1.0, 2.0, 4.0]


def test_for_robot_binds_the_fetch_and_local_files_win(tmp_path: Path, package: Path) -> None:
    asked: list[tuple[str, str]] = []

    def robot_fetch(robot: str, uri: str) -> bytes:
        asked.append((robot, uri))
        return b"from " + robot.encode()

    resolver = ResourceResolver({"pkg": package}, robot_fetch=robot_fetch)
    assert resolver.for_robot("tb2").read("package://remote/a.stl") == b"from tb2"
    assert resolver.for_robot("tb1").read("package://pkg/meshes/box.stl") == BOX
    assert asked == [("tb2", "package://remote/a.stl")]
    plain = ResourceResolver()
    assert plain.for_robot("tb1") is plain
    with pytest.raises(ConvertError, match="no robot file server to ask"):
        plain.read("package://remote/a.stl")
