"""Converter options: each type's row in the table names its record (host_bridge/core/options.py),
the only place a default is written; the schema describes exactly that record's fields for the
type, --print-config shows its defaults, and a topic's configured values become it."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import types
import typing
from importlib.resources import files
from typing import Any

import pytest
import yaml

from host_bridge import cli
from host_bridge.core.options import (
    CONVERTER_OPTION,
    GridOptions,
    GridUpdateOptions,
    ImageOptions,
    LaserScanOptions,
    PoseCovarianceOptions,
    converter_choices,
    fixed_defaults,
    option_names,
    options_from,
)
from host_bridge.errors import ConvertError
from host_bridge.table.config import HostConfig
from host_bridge.table.registry import Row, default_registry
from tests.host_bridge.sensor_test_support import make_ctx

SCHEMA = json.loads((files("swanky_schemas") / "host.schema.json").read_text())
DEFINITIONS = SCHEMA["$defs"]
NAMED = SCHEMA["properties"]["types"]["properties"]
"""The types the schema describes one by one; type globs and other types get ``settings``."""
TABLE = default_registry()
TYPE_ROWS = {row.msgtype: row for row in TABLE.rows() if not row.is_family and row.topics is None}
"""One row per type spelt out (the table checks a type's rows take one options record)."""
# JSON schema type -> the Python type an option record declares for it.
JSON_TYPES: dict[str, type] = {"number": float, "integer": int, "boolean": bool, "string": str}


def resolved(spec: dict[str, Any]) -> dict[str, Any]:
    """``spec`` with its ``$ref`` (within $defs) followed, the referring keys on top."""
    ref = spec.get("$ref")
    if ref is None:
        return spec
    *_, section, name = ref.split("/")
    target = DEFINITIONS[name] if section == "$defs" else DEFINITIONS["any_options"]["properties"][name]
    return {**resolved(target), **{k: v for k, v in spec.items() if k != "$ref"}}


def python_type(spec: dict[str, Any]) -> Any:
    """The type a record field must have for a schema property (without None)."""
    spec = resolved(spec)
    if "enum" in spec:
        return str
    if spec["type"] == "array":
        item = JSON_TYPES[resolved(spec["items"])["type"]]
        assert spec["minItems"] == spec["maxItems"], "arrays of options have a fixed length"
        return types.GenericAlias(tuple, (item,) * spec["minItems"])
    return JSON_TYPES[spec["type"]]


def declared(hint: Any) -> tuple[Any, bool]:
    """(the type, whether None is allowed) of a record field's annotation."""
    if isinstance(hint, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        assert len(args) == 1, hint
        return args[0], True
    return hint, False


def check_fields(where: str, record: type[Any], schema_options: dict[str, Any]) -> None:
    """Each of ``schema_options`` is a field of ``record`` of a compatible type, None-able
    exactly when its default is None (the record saying "derived from the data")."""
    hints = typing.get_type_hints(record)
    fields = {f.name: f for f in dataclasses.fields(record)}
    for name, spec in schema_options.items():
        kind, optional = declared(hints[name])
        assert kind == python_type(spec), f"{where}.{name}: {hints[name]} vs {resolved(spec)}"
        assert optional == (fields[name].default is None), f"{where}.{name}"


@pytest.fixture(scope="module")
def printed() -> dict[str, Any]:
    """What ``swanky-host --print-config`` prints without a file, as YAML and its header."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert cli.main(["--print-config"]) == 0
    text = out.getvalue()
    header = [line for line in text.splitlines() if line.startswith("#")]
    return {"config": yaml.safe_load(text), "header": header}


@pytest.mark.parametrize("row", TYPE_ROWS.values(), ids=lambda row: row.msgtype)
def test_the_schema_and_print_config_show_each_row_s_options(row: Row, printed: dict[str, Any]) -> None:
    record, msgtype = row.options, row.msgtype
    names, choices = option_names(record), converter_choices(record)
    if names or choices:
        assert msgtype in NAMED, f"{msgtype} takes options: give it its settings in the schema's types"
        properties = resolved(NAMED[msgtype])["properties"]
        schema_options = properties.get("options", {}).get("properties", {})
        assert sorted(schema_options) == sorted(names), msgtype
        assert tuple(properties.get("converter", {}).get("enum", ())) == choices, msgtype
        check_fields(msgtype, record, schema_options)
    else:  # `settings`: the config refuses every converter and option of the type, naming it
        assert msgtype not in NAMED
    defaults = fixed_defaults(record)
    shown = printed["config"]["types"].get(msgtype, {})
    assert shown.get("converter") == defaults.pop(CONVERTER_OPTION, None), msgtype
    assert shown.get("options", {}) == defaults, msgtype


def test_the_schema_names_only_types_of_the_table() -> None:
    assert sorted(set(NAMED) - set(TYPE_ROWS)) == []


def test_globs_and_other_types_may_set_every_option_and_converter_of_the_table(
    printed: dict[str, Any],
) -> None:
    """``settings`` (type globs, topics, types the schema does not name: custom ones get the
    catch-all row's record) offers each row's options; the config checks them per type."""
    settings = DEFINITIONS["settings"]["properties"]
    offered = settings["options"]["properties"]
    assert sorted(offered) == sorted({name for row in TABLE.rows() for name in option_names(row.options)})
    assert sorted(settings["converter"]["enum"]) == sorted(
        {choice for row in TABLE.rows() for choice in converter_choices(row.options)}
    )
    for row in TABLE.rows():
        check_fields(row.msgtype, row.options, {name: offered[name] for name in option_names(row.options)})
    # A family's defaults cannot be a types entry (it would set them on every type its glob
    # matches): the header names them.
    families = [row for row in TABLE.rows() if row.is_family and fixed_defaults(row.options)]
    assert [row.msgtype for row in families] == ["*"]
    assert printed["header"][1] == "# built in for the types matching '*' (no row of their own): " \
        "{options: {max_array: 64}}"
    assert not any(row.msgtype in printed["config"]["types"] for row in families)


def test_the_schema_holds_no_default_copies() -> None:
    text = json.dumps(SCHEMA)
    assert '"default":' not in text


def test_the_built_in_layer_is_the_records_defaults() -> None:
    config = HostConfig.builtin(TABLE)
    walls = config.resolve("tb3", "/map", "nav_msgs/msg/OccupancyGrid").options
    assert walls == fixed_defaults(GridOptions)
    assert walls["wall_height"] == 0.5
    assert walls["wall_color"] == [170, 180, 200]
    assert "wall_thickness" not in walls  # derived from the grid's resolution
    assert fixed_defaults(PoseCovarianceOptions) == {
        "trail_length": 500, "trail_period": 0.1, "axis_length": 0.3, "sigma": 1.0}
    # A costmap is drawn as a grid and has no walls: nothing fixed, all derived from its topic.
    assert config.resolve("tb3", "/global_costmap/costmap_raw", "nav2_msgs/msg/Costmap").options == {}


def test_configured_values_become_the_record() -> None:
    # YAML integers where a number is declared become floats, lists tuples.
    options = options_from(GridUpdateOptions, {"wall_height": 1, "wall_color": [1, 2, 3], "hough_votes": 4,
                                               "walls": True, "grid_topic": "/map"})
    assert options == GridUpdateOptions(wall_height=1.0, wall_color=(1, 2, 3), hough_votes=4, walls=True,
                                        grid_topic="/map")
    assert isinstance(options.wall_height, float)
    assert options_from(ImageOptions, {"depth_range": [0, 5]}).depth_range == (0, 5)
    assert options_from(LaserScanOptions, {}) == LaserScanOptions()


def test_a_converter_asking_for_another_record_is_told_which_options_do_not_fit() -> None:
    ctx = make_ctx("/scan", {"radius": 0.1, "sigma": 2.0})
    with pytest.raises(ConvertError) as caught:
        ctx.options(LaserScanOptions)
    assert str(caught.value) == (
        "/scan: LaserScanOptions takes no option sigma (its options: mode, color_by, colormap, radius)"
    )
