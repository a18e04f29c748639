"""The slam: block of the host configuration: precedence per robot glob, mistakes named by
file:line:key, --print-config, and the schema describing exactly the engine's settings."""

from __future__ import annotations

import dataclasses
import json
from importlib.resources import files
from pathlib import Path

import pytest
import yaml

from host_bridge import cli
from host_bridge.slam.settings import FIELDS, SlamSettings
from tests.host_bridge.test_config import load, mistakes

SLAM = """\
slam:
  resolution: 0.1
  odometry: tf
  robots:
    "tb3_*": {scan: /base_scan, max_range: 8}
    tb3_2: {enabled: false}
"""


def test_robot_globs_override_the_block_and_the_exact_name_wins(tmp_path: Path) -> None:
    config = load(tmp_path, SLAM)
    assert not config.slam_configured()  # nothing says enabled: --slam turns it on
    tb3 = config.slam_settings("tb3_1", enabled=True)
    assert (tb3.enabled, tb3.scan, tb3.odometry, tb3.resolution, tb3.max_range) == (
        True, "/base_scan", "tf", 0.1, 8.0)
    assert isinstance(tb3.max_range, float)
    assert not config.slam_settings("tb3_2", enabled=True).enabled
    other = config.slam_settings("pupper", enabled=True)
    assert (other.scan, other.resolution) == ("/scan", 0.1)
    enabled = load(tmp_path, "slam: {enabled: true}\n")
    assert enabled.slam_configured()
    assert enabled.slam_settings("x").enabled


def test_mistakes_name_file_line_and_key(tmp_path: Path) -> None:
    found = mistakes(tmp_path, """\
slam:
  resolution: 0
  robots:
    "tb3 bad": {min_matched: 1.5}
""")
    assert any(line.startswith("2: slam.resolution:") for line in found), found
    assert any("slam.robots" in line and "1.5" in line for line in found), found
    found = mistakes(tmp_path, "slam:\n  map_fram: map\n")
    assert any("map_fram" in line for line in found), found


def test_print_config_shows_the_slam_block_over_its_defaults(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "host.yaml"
    path.write_text(SLAM)
    assert cli.main(["--config", str(path), "--print-config"]) == 0
    slam = yaml.safe_load(capsys.readouterr().out)["slam"]
    assert slam["resolution"] == 0.1
    assert slam["keyframe_distance"] == SlamSettings().keyframe_distance
    assert slam["robots"]["tb3_*"] == {"scan": "/base_scan", "max_range": 8}
    assert set(slam) == {*FIELDS, "robots"}


def test_the_schema_describes_every_setting_and_no_other() -> None:
    schema = json.loads((files("swanky_schemas") / "host.schema.json").read_text())
    described = schema["$defs"]["slam_settings"]["properties"]
    assert set(described) == {f.name for f in dataclasses.fields(SlamSettings)}
    assert all(spec.get("description") for spec in described.values())
    assert set(schema["properties"]["slam"]["properties"]) == {*described, "robots"}
