"""The relay's read-only file server: what it serves and everything it refuses."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from robot_relay.errors import ConfigError, RelayError
from robot_relay.files import (
    FileAccessError,
    FileServer,
    package_roots,
    parse_package_path,
    serve,
    serve_files,
    urdf_package_names,
)
from robot_relay.wire import RawMessage, files_key

MESH = bytes(range(256)) * 40


@pytest.fixture
def root(tmp_path: Path) -> Path:
    """``<tmp>/install/share/robot_description`` with one mesh; a secret lies outside it."""
    package = tmp_path / "install" / "share" / "robot_description"
    (package / "meshes").mkdir(parents=True)
    (package / "meshes" / "base.stl").write_bytes(MESH)
    (tmp_path / "secret.txt").write_text("password")
    return package


@pytest.fixture
def server(root: Path) -> FileServer:
    return FileServer({"robot_description": root}, max_bytes=1 << 20)


def refused(server: FileServer, request: str) -> str:
    with pytest.raises(FileAccessError) as caught:
        server.read(request)
    assert isinstance(caught.value, RelayError)
    return caught.value.reason


@pytest.mark.parametrize(
    "request_form",
    [
        "package://robot_description/meshes/base.stl",
        "robot_description/meshes/base.stl",
        "robot_description/./meshes//base.stl",
        "{root}/meshes/base.stl",
        "file://{root}/meshes/base.stl",
    ],
)
def test_serves_a_file_inside_a_root_byte_for_byte(server: FileServer, root: Path, request_form: str) -> None:
    request = request_form.format(root=root)
    assert server.read(request) == MESH
    assert server.resolve(request) == (root / "meshes" / "base.stl").resolve()


@pytest.mark.parametrize(
    "request_text",
    [
        "robot_description/../../../secret.txt",
        "package://robot_description/meshes/../../../../secret.txt",
        "robot_description/meshes/../meshes/base.stl",
        "{root}/../../../secret.txt",
    ],
)
def test_refuses_dotdot(server: FileServer, root: Path, request_text: str) -> None:
    assert refused(server, request_text.format(root=root)) == "traversal"


def test_refuses_absolute_paths_outside_the_roots(server: FileServer, tmp_path: Path) -> None:
    assert refused(server, str(tmp_path / "secret.txt")) == "outside_roots"
    assert refused(server, f"file://{tmp_path}/secret.txt") == "outside_roots"
    assert refused(server, "/etc/passwd") == "outside_roots"


def test_refuses_symlinks_that_lead_out(server: FileServer, root: Path, tmp_path: Path) -> None:
    (root / "meshes" / "leak.stl").symlink_to(tmp_path / "secret.txt")
    (root / "outside").symlink_to(tmp_path, target_is_directory=True)
    assert refused(server, "robot_description/meshes/leak.stl") == "symlink_escape"
    assert refused(server, "robot_description/outside/secret.txt") == "symlink_escape"
    assert refused(server, f"{root}/meshes/leak.stl") == "symlink_escape"
    # A symlink that stays inside the root is fine.
    (root / "meshes" / "alias.stl").symlink_to(root / "meshes" / "base.stl")
    assert server.read("robot_description/meshes/alias.stl") == MESH


def test_refuses_files_over_the_limit(root: Path) -> None:
    exact = FileServer({"robot_description": root}, max_bytes=len(MESH))
    assert exact.read("robot_description/meshes/base.stl") == MESH
    small = FileServer({"robot_description": root}, max_bytes=len(MESH) - 1)
    with pytest.raises(FileAccessError, match=f"{len(MESH)} bytes") as caught:
        small.read("robot_description/meshes/base.stl")
    assert caught.value.reason == "too_large"


def test_refuses_unknown_packages_missing_files_and_bad_requests(server: FileServer) -> None:
    assert refused(server, "other_pkg/meshes/base.stl") == "unknown_package"
    assert refused(server, "robot_description/meshes/none.stl") == "not_found"
    assert refused(server, "robot_description/meshes") == "not_found"
    assert refused(server, "robot_description") == "bad_request"
    assert refused(server, "robot_description/a\0b") == "bad_request"


def test_bad_configuration(root: Path) -> None:
    with pytest.raises(ConfigError):
        FileServer({"robot_description": root}, max_bytes=0)
    with pytest.raises(ConfigError):
        FileServer({"a/b": root}, max_bytes=10)


def test_package_roots_first_prefix_wins(tmp_path: Path) -> None:
    overlay, underlay = tmp_path / "overlay", tmp_path / "underlay"
    for prefix in (overlay, underlay):
        (prefix / "share" / "both").mkdir(parents=True)
    (underlay / "share" / "under_only").mkdir(parents=True)
    roots = package_roots(["both", "under_only", "nowhere"], [overlay, underlay])
    assert roots == {
        "both": overlay / "share" / "both",
        "under_only": underlay / "share" / "under_only",
    }


def test_package_names_from_a_urdf() -> None:
    urdf = """<robot name="r">
      <link name="a"><visual><geometry>
        <mesh filename="package://tb3_description/meshes/a.stl"/></geometry></visual></link>
      <link name="b"><visual><geometry>
        <mesh filename="file:///opt/ros/humble/share/lidar_description/meshes/b.dae"/>
      </geometry></visual></link>
    </robot>"""
    assert urdf_package_names(urdf) == {"tb3_description", "lidar_description"}


def test_module_needs_only_the_standard_library() -> None:
    heavy = ("numpy", "rerun", "cv2", "trimesh", "host_bridge", "zenoh")
    code = f"import sys, robot_relay.files; print([m for m in {heavy!r} if m in sys.modules])"
    repo = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": str(repo)}
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)
    assert result.stdout.strip() == "[]"


def test_serve_over_zenoh(server: FileServer) -> None:
    zenoh = pytest.importorskip("zenoh")
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
    with zenoh.open(config) as session:
        queryable = serve(session, "tb1", server)
        ok = list(session.get(files_key("tb1", "robot_description", "meshes/base.stl"), timeout=5))
        assert len(ok) == 1
        assert ok[0].ok is not None
        assert ok[0].ok.payload.to_bytes() == MESH
        bad = list(session.get(files_key("tb1", "robot_description", "nope.stl"), timeout=5))
        assert len(bad) == 1
        assert bad[0].err is not None
        assert bad[0].err.payload.to_string().startswith("not_found:")
        queryable.undeclare()


def test_package_path_option(tmp_path: Path) -> None:
    assert parse_package_path(f"pkg={tmp_path}") == ("pkg", tmp_path)
    with pytest.raises(ConfigError) as missing:
        parse_package_path(f"pkg={tmp_path}/no/such")
    assert str(missing.value) == (
        f"--package-path pkg={tmp_path}/no/such: {tmp_path}/no/such is not a directory "
        "(nothing is there)"
    )
    for bad in ("pkg", "=dir", "pkg=", "a/b=dir", "..=dir"):
        with pytest.raises(ConfigError, match="NAME=DIR"):
            parse_package_path(bad)


def test_added_roots_never_replace_a_served_package(root: Path, tmp_path: Path) -> None:
    server = FileServer({"robot_description": root}, max_bytes=1 << 20)
    other = tmp_path / "other"
    (other / "meshes").mkdir(parents=True)
    (other / "meshes" / "base.stl").write_bytes(b"other")
    assert server.add_roots({"robot_description": other, "extra": other}) == ["extra"]
    assert server.read("robot_description/meshes/base.stl") == MESH
    assert server.read("extra/meshes/base.stl") == b"other"
    with pytest.raises(ConfigError):
        server.add_roots({"a/b": other})


def string_cdr(text: str) -> bytes:
    """std_msgs/String as ROS serialises it: header, length with the NUL, bytes, NUL."""
    data = text.encode("utf-8") + b"\0"
    return b"\x00\x01\x00\x00" + len(data).to_bytes(4, "little") + data


@pytest.fixture
def session() -> Iterator[Any]:
    zenoh = pytest.importorskip("zenoh")
    config = zenoh.Config()
    config.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(config) as opened:
        yield opened


def test_served_packages_grow_with_the_urdfs_forwarded(session: Any, root: Path, tmp_path: Path) -> None:
    prefix = {"AMENT_PREFIX_PATH": str(tmp_path / "install")}
    service = serve_files(session, "tb1", [], environ=prefix)
    key = files_key("tb1", "robot_description", "meshes/base.stl")
    try:
        (before,) = session.get(key, timeout=5)
        assert before.err.payload.to_string().startswith("unknown_package:")
        urdf = '<robot name="r"><link name="a"><visual><geometry><mesh filename=' \
               '"package://robot_description/meshes/base.stl"/></geometry></visual></link></robot>'
        messages = [
            RawMessage("tb1", "/chatter", "std_msgs/msg/String", string_cdr(urdf)),
            RawMessage("tb1", "/tb1/robot_description", "std_msgs/msg/String", string_cdr(urdf)),
        ]
        # Passed on unchanged; only the robot description teaches the server a package.
        watched = service.watch(messages)
        assert next(watched) is messages[0]
        assert service.server.packages == []
        assert next(watched) is messages[1]
        assert service.server.packages == ["robot_description"]
        (after,) = session.get(key, timeout=5)
        assert after.ok.payload.to_bytes() == MESH
    finally:
        service.close()


def test_explicit_package_paths_are_served_and_checked(session: Any, root: Path, tmp_path: Path) -> None:
    service = serve_files(session, "tb1", [f"robot_description={root}"], environ={})
    try:
        (reply,) = session.get(files_key("tb1", "robot_description", "meshes/base.stl"), timeout=5)
        assert reply.ok.payload.to_bytes() == MESH
    finally:
        service.close()
    with pytest.raises(ConfigError, match="not a directory"):
        serve_files(session, "tb1", [f"robot_description={tmp_path / 'nowhere'}"], environ={})
