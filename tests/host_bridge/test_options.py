"""Converter options: the records in host_bridge/options.py are the only defaults, the schema
names exactly their fields with compatible types, and a topic's configured values become them."""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from importlib.resources import files
from typing import Any

import pytest

from host_bridge.config import HostConfig
from host_bridge.errors import ConvertError
from host_bridge.options import (
    CONVERTER_OPTION,
    OPTIONS_BY_DEFINITION,
    GridOptions,
    GridUpdateOptions,
    ImageOptions,
    LaserScanOptions,
    PoseCovarianceOptions,
    fixed_defaults,
    options_from,
)
from host_bridge.registry import default_registry
from tests.host_bridge.sensor_test_support import make_ctx

SCHEMA = json.loads((files("swanky_schemas") / "host.schema.json").read_text())
DEFINITIONS = SCHEMA["$defs"]
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


def type_definitions() -> set[str]:
    """The $defs a type's settings refer to, and the two the config falls back to."""
    refs = {spec["$ref"].rsplit("/", 1)[-1] for spec in SCHEMA["properties"]["types"]["properties"].values()}
    return refs | {"plain", "generic"}


def test_every_schema_definition_of_a_type_has_an_options_record() -> None:
    assert set(OPTIONS_BY_DEFINITION) == type_definitions()


@pytest.mark.parametrize("definition", sorted(OPTIONS_BY_DEFINITION))
def test_schema_lists_exactly_the_record_fields_with_compatible_types(definition: str) -> None:
    record = OPTIONS_BY_DEFINITION[definition]
    properties = DEFINITIONS[definition]["properties"]
    schema_options = properties.get("options", {}).get("properties", {})
    hints = typing.get_type_hints(record)
    fields = {f.name: f for f in dataclasses.fields(record)}
    # The converter choice is the record's mode; every other field is an option.
    assert ("converter" in properties) == (CONVERTER_OPTION in fields)
    assert set(schema_options) == set(fields) - {CONVERTER_OPTION}
    for name, spec in schema_options.items():
        kind, optional = declared(hints[name])
        assert kind == python_type(spec), f"{definition}.{name}: {hints[name]} vs {resolved(spec)}"
        # None is the record saying "derived from the data"; only then may the field be None.
        assert optional == (fields[name].default is None), f"{definition}.{name}"
    if CONVERTER_OPTION in fields:
        assert hints[CONVERTER_OPTION] is str
        assert fields[CONVERTER_OPTION].default in properties["converter"]["enum"]


def test_the_schema_holds_no_default_copies() -> None:
    text = json.dumps(SCHEMA)
    assert '"default":' not in text


def test_the_built_in_layer_is_the_records_defaults() -> None:
    config = HostConfig.builtin(default_registry().types())
    walls = config.resolve("tb3", "/map", "nav_msgs/msg/OccupancyGrid").options
    assert walls == fixed_defaults(GridOptions)
    assert walls["wall_height"] == 0.5
    assert walls["wall_color"] == [170, 180, 200]
    assert "wall_thickness" not in walls  # derived from the grid's resolution
    assert fixed_defaults(PoseCovarianceOptions) == {"trail_length": 500, "axis_length": 0.3, "sigma": 1.0}


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
