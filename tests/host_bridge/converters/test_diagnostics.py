"""DiagnosticArray: escaped per-status entities, levels, text, and numeric values as scalars."""

from __future__ import annotations

from typing import Any

import rerun as rr

from host_bridge.converters.diagnostics import SPEC
from host_bridge.core.contract import LogItem
from tests.host_bridge.sensor_test_support import TYPES as T
from tests.host_bridge.sensor_test_support import header, make_ctx

CONVERT = SPEC.convert


def _status(level: int, name: str, message: str, values: dict[str, str] | None = None) -> Any:
    pairs = [T["diagnostic_msgs/msg/KeyValue"](key=k, value=v) for k, v in (values or {}).items()]
    return T["diagnostic_msgs/msg/DiagnosticStatus"](
        level=level, name=name, message=message, hardware_id="tb3", values=pairs,
    )


def _convert(*statuses: Any) -> dict[str, tuple[str, ...] | float]:
    """Entity path -> (text, level) for text logs, or the scalar value."""
    msg = T["diagnostic_msgs/msg/DiagnosticArray"](header=header(""), status=list(statuses))
    ctx = make_ctx("/diagnostics", stamp_ns=3, robot="tb3")
    out: dict[str, tuple[str, ...] | float] = {}
    for item in CONVERT(msg, ctx):
        assert isinstance(item, LogItem)
        assert item.path not in out
        (archetype,) = item.archetypes
        if isinstance(archetype, rr.TextLog):
            text, level = archetype.text, archetype.level
            assert text is not None
            assert level is not None
            out[item.path] = (
                text.as_arrow_array().to_pylist()[0], level.as_arrow_array().to_pylist()[0],
            )
        else:
            assert isinstance(archetype, rr.Scalars)
            assert archetype.scalars is not None
            out[item.path] = archetype.scalars.as_arrow_array().to_pylist()[0]
    return out


def test_status_names_are_escaped_into_one_entity_part_each() -> None:
    out = _convert(
        _status(0, "battery: Motor 1/2", "Nominal", {"voltage": "12.3", "state": "charging"}),
        _status(1, "/Robot/Lidar", "Frequency low"),
        _status(0, "  ", "no name"),
    )
    assert out == {
        r"/tb3/diagnostics/battery\:\ Motor\ 1\/2": (
            "Nominal | voltage=12.3, state=charging", "INFO",
        ),
        r"/tb3/diagnostics/battery\:\ Motor\ 1\/2/voltage": 12.3,
        r"/tb3/diagnostics/\/Robot\/Lidar": ("Frequency low", "WARN"),
        "/tb3/diagnostics/unnamed": ("no name", "INFO"),
    }


def test_levels_map_ok_warn_error_and_stale() -> None:
    out = _convert(
        _status(0, "a", "fine"),
        _status(1, "b", "hot"),
        _status(2, "c", "dead"),
        _status(3, "d", "no updates"),
    )
    assert out == {
        "/tb3/diagnostics/a": ("fine", "INFO"),
        "/tb3/diagnostics/b": ("hot", "WARN"),
        "/tb3/diagnostics/c": ("dead", "ERROR"),
        "/tb3/diagnostics/d": ("stale: no updates", "WARN"),
    }


def test_only_values_that_parse_as_numbers_become_scalars() -> None:
    out = _convert(
        _status(
            2, "motor", "Overcurrent",
            {"current A": " 7.25 ", "count": "-3", "sci": "1e3", "mode": "12 V", "ok": "True",
             "": "5"},
        ),
    )
    assert out == {
        "/tb3/diagnostics/motor": (
            "Overcurrent | current A= 7.25 , count=-3, sci=1e3, mode=12 V, ok=True, =5", "ERROR",
        ),
        r"/tb3/diagnostics/motor/current\ A": 7.25,
        "/tb3/diagnostics/motor/count": -3.0,
        "/tb3/diagnostics/motor/sci": 1000.0,
    }
