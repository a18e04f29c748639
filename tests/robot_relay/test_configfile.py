"""The shared YAML + JSON Schema loader: every mistake names file, line and key."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest

from robot_relay.configfile import ConfigDocument, check_topic_glob, first_match, key_text
from robot_relay.errors import ConfigError

SCHEMA: dict[str, Any] = {
    "type": "object",
    "additionalProperties": False,
    "properties": {
        "robot": {"type": "string"},
        "topics": {
            "type": "object",
            "propertyNames": {"format": "topic-glob"},
            "additionalProperties": {
                "type": "object",
                "additionalProperties": False,
                "properties": {"max_rate": {"type": "number", "exclusiveMinimum": 0}},
            },
        },
    },
}


def problems(tmp_path: Path, text: str) -> list[str]:
    path = tmp_path / "relay.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as caught:
        ConfigDocument.parse(path).check(SCHEMA)
    return [line.removeprefix(f"{path}:") for line in str(caught.value).splitlines()]


def test_each_mistake_names_line_and_key(tmp_path: Path) -> None:
    text = "robot: tb3\ntopics:\n  /scan:\n    max_rate: fast\n    colour: red\n  scan*:\n    max_rate: 2\n"
    assert problems(tmp_path, text) == [
        "4: topics./scan.max_rate: 'fast' is not of type 'number'",
        "5: topics./scan.colour: unknown key (expected one of: max_rate)",
        "6: topics.scan*: topic glob 'scan*' must start with '/' or a wildcard",
    ]


def test_unknown_top_level_key_and_wrong_type(tmp_path: Path) -> None:
    assert problems(tmp_path, "robot: 3\nrobto: tb3\n") == [
        "1: robot: 3 is not of type 'string'",
        "2: robto: unknown key (expected one of: robot, topics)",
    ]


def test_broken_yaml_names_the_line(tmp_path: Path) -> None:
    path = tmp_path / "relay.yaml"
    path.write_text("topics:\n  /scan: {max_rate: 2\n")
    with pytest.raises(ConfigError, match=rf"^{re.escape(str(path))}:3: not valid YAML"):
        ConfigDocument.parse(path)


def test_missing_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"nope\.yaml: cannot read config file"):
        ConfigDocument.parse(tmp_path / "nope.yaml")


def test_empty_file_is_an_empty_mapping(tmp_path: Path) -> None:
    path = tmp_path / "empty.yaml"
    path.write_text("# nothing\n")
    document = ConfigDocument.parse(path)
    document.check(SCHEMA)
    assert document.data == {}
    assert str(document.error(("topics",), "x")) == f"{path}:1: topics: x"


@pytest.mark.parametrize(
    ("glob", "why"),
    [
        ("scan", "must start with"),
        ("/camera/[abc", "unclosed"),
        ("/a]b[", "unbalanced"),
        ("/a//b", "empty name segment"),
        ("/a b", "characters"),
    ],
)
def test_bad_globs(glob: str, why: str) -> None:
    with pytest.raises(ValueError, match=why):
        check_topic_glob(glob)


@pytest.mark.parametrize("glob", ["/scan", "/*", "*", "/camera/*/image_[rc]*", "/tb?/odom"])
def test_good_globs(glob: str) -> None:
    assert check_topic_glob(glob)


def test_most_specific_pattern_wins() -> None:
    patterns = ["*", "/camera/*", "/camera/depth/*", "/camera/depth/image_raw"]
    assert first_match(patterns, "/camera/depth/image_raw") == "/camera/depth/image_raw"
    assert first_match(patterns, "/camera/depth/points") == "/camera/depth/*"
    assert first_match(patterns, "/camera/rgb") == "/camera/*"
    assert first_match(patterns, "/scan") == "*"
    assert first_match(["/camera/*"], "/scan") is None


def test_key_text() -> None:
    assert key_text(()) == "(top level)"
    assert key_text(("topics", "/scan", "max_rate")) == "topics./scan.max_rate"
    assert key_text(("robots", 2, "name")) == "robots[2].name"
