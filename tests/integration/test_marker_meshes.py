"""``package://`` marker meshes on a real host: found through ``--package-path`` when converting a
bag, and fetched from the robot's relay (its own ``--package-path``) when live, the way the
robot model's meshes are. Until the converters' state was typed, the marker converter read a
resolver under a key the host never set, so such markers failed on every real host.

One bag (rosbags' Writer) holds a MarkerArray whose MESH_RESOURCE marker names
``package://mypkg/meshes/x.stl``, an STL written here; the tests read the .rrd the host saved.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh

from host_bridge.cli import main as host_main
from host_bridge.converters import markers
from tests.host_bridge.converters.test_markers import marker
from tests.host_bridge.sensor_test_support import msg
from tests.integration.procs import command, free_port, running
from tests.integration.robot_bags import Entry, Lines, write_bag
from tests.rrd import entity_rows

pytestmark = pytest.mark.integration

PACKAGE = "mypkg"
URI = f"package://{PACKAGE}/meshes/x.stl"
MARKERS = "visualization_msgs/msg/MarkerArray"
ENTITY = "/markers/ns/7"  # under the robot: <topic>/<ns>/<id>


@dataclass(frozen=True, slots=True)
class Recorded:
    bag: Path
    package: Path
    stl: bytes


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Recorded:
    tmp = tmp_path_factory.mktemp("marker_meshes")
    package = tmp / PACKAGE
    (package / "meshes").mkdir(parents=True)
    stl = trimesh.creation.box(extents=(0.1, 0.2, 0.3)).export(file_type="stl")
    (package / "meshes" / "x.stl").write_bytes(stl)
    mesh = marker(markers.MESH_RESOURCE, marker_id=7, mesh_resource=URI, scale=(2.0, 2.0, 2.0))
    array = msg(MARKERS, markers=[mesh])
    bag = write_bag(tmp / "bag", [Entry("/markers", MARKERS, offset_ns, array)
                                  for offset_ns in (100_000_000, 200_000_000)])
    return Recorded(bag, package, stl)


def assert_mesh_is_the_stl(rows: list[dict[str, Any]], stl: bytes) -> None:
    """Every marker row carries the STL's bytes, as the viewer gets them: what it draws has the
    STL's vertices and triangles."""
    assert len(rows) == 2
    for row in rows:
        assert row["Asset3D:media_type"] == ["model/stl"]
        blob = bytes(row["Asset3D:blob"][0])
        assert blob == stl
        drawn = trimesh.load_mesh(io.BytesIO(blob), file_type="stl")
        written = trimesh.load_mesh(io.BytesIO(stl), file_type="stl")
        np.testing.assert_array_equal(drawn.vertices, written.vertices)
        assert len(drawn.faces) == 12  # a box
        assert row["InstancePoses3D:scales"] == [[2.0, 2.0, 2.0]]


def warnings(rows: dict[str, list[dict[str, Any]]]) -> list[str]:
    return [text for row in rows.get("/_swanky/warnings", []) for text in row.get("TextLog:text") or []]


@pytest.fixture
def no_ros_paths(monkeypatch: pytest.MonkeyPatch) -> None:
    """The host finds the package only where the test says."""
    for variable in ("ROS_PACKAGE_PATH", "AMENT_PREFIX_PATH"):
        monkeypatch.delenv(variable, raising=False)


@pytest.mark.usefixtures("no_ros_paths")
def test_bag_conversion_reads_the_mesh_through_package_path(recorded: Recorded, tmp_path: Path) -> None:
    out = tmp_path / "bag.rrd"
    assert host_main(["--bag", str(recorded.bag), "--robot", "bot", "--package-path",
                      f"{PACKAGE}={recorded.package}", "--save", str(out)]) == 0
    rows = entity_rows(out)
    assert_mesh_is_the_stl(rows[f"/bot{ENTITY}"], recorded.stl)
    assert warnings(rows) == []


@pytest.mark.usefixtures("no_ros_paths")
def test_without_the_package_the_marker_is_one_warning_naming_the_flag(
    recorded: Recorded, tmp_path: Path
) -> None:
    out = tmp_path / "missing.rrd"
    assert host_main(["--bag", str(recorded.bag), "--robot", "bot", "--save", str(out)]) == 0
    rows = entity_rows(out)
    assert f"/bot{ENTITY}" not in rows
    [warning] = warnings(rows)
    assert warning.startswith(f"[bot] /markers: marker ns='ns' id=7: {URI} not found (")
    assert f"pass --package-path {PACKAGE}=DIR" in warning


@pytest.mark.usefixtures("no_ros_paths")
def test_live_host_fetches_the_mesh_from_the_robots_relay(recorded: Recorded, tmp_path: Path) -> None:
    port = free_port()
    out = tmp_path / "live.rrd"
    with running(command(
        "robot_relay.cli", "--robot", "bot", "--bag", str(recorded.bag), "--rate", "1",
        "--package-path", f"{PACKAGE}={recorded.package}", "--wait-for-host", "60", "--hold", "inf",
        "-l", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting",
    )) as relay:
        lines = Lines(relay)
        lines.wait_for("topics from", timeout=60)
        assert host_main(["-e", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting", "--save", str(out),
                          "--until-idle", "3", "--duration", "60"]) == 0
        lines.wait_for("replay finished", timeout=30)
    rows = entity_rows(out)
    assert_mesh_is_the_stl(rows[f"/bot{ENTITY}"], recorded.stl)
    assert warnings(rows) == []
    assert "Traceback" not in lines.text
