"""The host configuration: precedence, file:line:key mistakes, --print-config, and the dispatcher
honouring enabled, entity_path, converter, options and restamp."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rerun as rr
import yaml
from rosbags.typesys import Stores, get_typestore

from host_bridge import cli
from host_bridge.core.contract import WARNINGS_PATH, LogEntry, LogItem
from host_bridge.core.destinations import SinkOptions
from host_bridge.core.schemas import base_typestore
from host_bridge.errors import ConfigError
from host_bridge.outputs.sink import RerunSink
from host_bridge.pipeline.dispatch import Dispatcher
from host_bridge.table.config import HostConfig, TopicConfig
from host_bridge.table.registry import default_registry
from robot_relay.wire import RawMessage
from tests.host_bridge.test_custom_types import costmap
from tests.rrd import entity_rows

REGISTRY = default_registry()
REPO = Path(__file__).resolve().parents[2]
STORE = get_typestore(Stores.ROS2_HUMBLE)
T = STORE.types
SCAN = "sensor_msgs/msg/LaserScan"
IMAGE = "sensor_msgs/msg/Image"
COSTMAP = "nav2_msgs/msg/Costmap"


def load(tmp_path: Path, text: str) -> HostConfig:
    path = tmp_path / "host.yaml"
    path.write_text(text)
    return HostConfig.load(path, REGISTRY)


def mistakes(tmp_path: Path, text: str) -> list[str]:
    """The error lines, each without the leading ``<path>:``."""
    with pytest.raises(ConfigError) as caught:
        load(tmp_path, text)
    prefix = f"{tmp_path / 'host.yaml'}:"
    lines = str(caught.value).splitlines()
    assert all(line.startswith(prefix) for line in lines), lines
    return [line.removeprefix(prefix) for line in lines]


# --- precedence -----------------------------------------------------------------------------------

PRECEDENCE = """\
defaults:
  restamp: true
types:
  sensor_msgs/msg/*:
    options: {colormap: viridis}
  sensor_msgs/msg/LaserScan:
    converter: rays
    options: {radius: 0.05, colormap: magma}
topics:
  /*:
    options: {color_by: intensity}
  /scan*:
    converter: both
    entity_path: /{robot}/lidars{topic}
  /scan_front:
    converter: points
    restamp: false
  pupper:/scan*:
    options: {radius: 0.07}
  /s*:
    options: {radius: 0.5}
"""


def test_exact_topic_beats_glob_beats_type_key_by_key(tmp_path: Path) -> None:
    config = load(tmp_path, PRECEDENCE)
    front = config.resolve("tb3", "/scan_front", SCAN)
    assert front == TopicConfig(
        entity_path="/tb3/lidars/scan_front",  # from the glob /scan*: the exact entry has none
        converter="points",  # exact topic > /scan* > type
        # built-in color_by range < /* intensity; type radius 0.05 < /s* 0.5; colormap: the
        # exact type's magma beats the type glob's viridis.
        options={"color_by": "intensity", "colormap": "magma", "radius": 0.5, "mode": "points"},
        restamp=False,  # exact topic > defaults
    )
    rear = config.resolve("tb3", "/scan_rear", SCAN)
    assert (rear.converter, rear.options["mode"], rear.restamp) == ("both", "both", True)
    # /scan* is more specific than /s* (same wildcards, longer), and pupper:/scan* comes right
    # after /scan*: so pupper's radius wins, tb3 keeps /s*'s.
    assert rear.options["radius"] == 0.5
    assert config.resolve("pupper", "/scan_rear", SCAN).options["radius"] == 0.07
    # A type with nothing but the type glob: its built-in defaults plus the glob.
    cloud = config.resolve("tb3", "/points", "sensor_msgs/msg/PointCloud2")
    assert cloud.options == {"colormap": "viridis"}
    assert cloud.entity_path == "/tb3/points"


def test_no_file_gives_the_built_in_defaults(tmp_path: Path) -> None:
    config = HostConfig.builtin(REGISTRY)
    assert config.resolve("tb3", "/scan", SCAN) == TopicConfig(
        entity_path="/tb3/scan", converter="points",
        options={"color_by": "range", "colormap": "turbo", "radius": 0.02, "mode": "points"},
    )
    assert config.resolve("tb3", "/speed", "std_msgs/msg/Float64") == TopicConfig("/tb3/speed")


# --- mistakes: each names file:line: key ---------------------------------------------------------


def test_unknown_key_wrong_type_and_bad_glob(tmp_path: Path) -> None:
    text = (
        "topics:\n"
        "  /scan:\n"
        "    enabeld: false\n"
        "  /camera/[abc:\n"
        "    enabled: yes please\n"
        "  scan*:\n"
        "    restamp: true\n"
        "types:\n"
        "  sensor_msgs/msg/Ima[ge:\n"
        "    enabled: false\n"
    )
    assert mistakes(tmp_path, text) == [
        "3: topics./scan.enabeld: unknown key (expected one of: converter, enabled, entity_path, "
        "options, restamp)",
        "5: topics./camera/[abc.enabled: 'yes please' is not of type 'boolean'",
    ]
    # Glob syntax is checked once the file fits the schema.
    text = text.replace("enabeld", "enabled").replace("yes please", "true")
    assert mistakes(tmp_path, text) == [
        "9: types.sensor_msgs/msg/Ima[ge: type 'sensor_msgs/msg/Ima[ge' must look like pkg/msg/Name, "
        "globs using * ? and closed [...] classes",
        "4: topics./camera/[abc: topic glob '/camera/[abc' has an unclosed [",
        "6: topics.scan*: topic glob 'scan*' must start with '/' or a wildcard",
    ]


def test_converter_and_options_that_do_not_fit_the_type(tmp_path: Path) -> None:
    text = (
        "types:\n"
        "  sensor_msgs/msg/LaserScan:\n"
        "    converter: depth\n"
        "  sensor_msgs/msg/Image:\n"
        "    options:\n"
        "      colormap: jet\n"
        "      radius: 0.1\n"
        "  sensor_msgs/msg/Imu:\n"
        "    converter: points\n"
    )
    assert mistakes(tmp_path, text) == [
        "3: types.sensor_msgs/msg/LaserScan.converter: 'depth' is not one of ['points', 'rays', 'both']",
        "6: types.sensor_msgs/msg/Image.options.colormap: 'jet' is not one of ['turbo', 'viridis', "
        "'plasma', 'inferno', 'magma', 'grayscale', 'gray', 'grey', 'cyantoyellow', 'spectral', "
        "'twilight', 'rvizmap', 'rvizcostmap', 'costmap']",
        "7: types.sensor_msgs/msg/Image.options.radius: unknown key (expected one of: colormap, "
        "depth_meter, depth_range)",
        "9: types.sensor_msgs/msg/Imu.converter: unknown key (expected one of: enabled, entity_path, "
        "options, restamp)",
    ]
    # The schema knows only types with options; the rest are checked against the registry.
    text = (
        "types:\n  sensor_msgs/msg/Temperature:\n    options: {sigma: 2}\n"
        "  my_msgs/msg/Thing:\n    converter: rays\n"
    )
    assert mistakes(tmp_path, text) == [
        "3: types.sensor_msgs/msg/Temperature.options.sigma: sensor_msgs/msg/Temperature takes no "
        "option 'sigma' (its options: none)",
        "5: types.my_msgs/msg/Thing.converter: my_msgs/msg/Thing has no converter 'rays' "
        "(alternatives: none, it has one converter)",
    ]


def test_values_the_schema_cannot_order(tmp_path: Path) -> None:
    text = (
        "defaults:\n"
        "  entity_path: /{robot}/{name}\n"
        "topics:\n"
        "  /depth:\n"
        "    options: {depth_range: [5, 0.5]}\n"
        "  tb 3:/scan:\n"
        "    enabled: false\n"
    )
    assert mistakes(tmp_path, text) == [
        "6: topics.tb 3:/scan: robot glob 'tb 3' before ':' may hold letters, digits, '_', '-' and "
        "wildcards only",
        "2: defaults.entity_path: entity path '/{robot}/{name}': the only placeholders are {robot} and "
        "{topic}",
        "5: topics./depth.options.depth_range: [5, 0.5] must be [min, max] with min < max (metres)",
    ]


def test_a_glob_that_misfits_a_type_is_reported_once_and_only_that_key_dropped(tmp_path: Path) -> None:
    config = load(tmp_path, "topics:\n  /front/*:\n    converter: rays\n    options: {colormap: jet}\n"
                  "    entity_path: /{robot}/front{topic}\n")
    problem = [
        f"{tmp_path / 'host.yaml'}:3: topics./front/*.converter: sensor_msgs/msg/Image has no "
        "converter 'rays' (alternatives: auto, depth, color)",
        f"{tmp_path / 'host.yaml'}:4: topics./front/*.options.colormap: 'jet' is not one of "
        "['turbo', 'viridis', 'plasma', 'inferno', 'magma', 'grayscale', 'gray', 'grey', "
        "'cyantoyellow', 'spectral', 'twilight', 'rvizmap', 'rvizcostmap', 'costmap'] for "
        "sensor_msgs/msg/Image",
    ]
    image = config.resolve("tb3", "/front/image", IMAGE)
    assert image == TopicConfig("/tb3/front/front/image", converter="auto", options={"mode": "auto"},
                                  problems=tuple(problem))
    assert config.resolve("tb3", "/front/other", IMAGE).problems == ()
    scan = config.resolve("tb3", "/front/scan", SCAN)
    assert (scan.converter, scan.options["colormap"], scan.problems) == ("rays", "jet", ())


# --- --print-config and the example ---------------------------------------------------------------


def test_print_config_shows_the_file_over_the_defaults(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "host.yaml"
    path.write_text(PRECEDENCE)
    assert cli.main(["--config", str(path), "--print-config"]) == 0
    printed = capsys.readouterr().out
    assert printed.startswith(f"# swanky-host effective configuration: {path} merged over")
    effective = yaml.safe_load(printed)
    assert effective["defaults"] == {"entity_path": "/{robot}{topic}", "enabled": True, "restamp": True}
    assert effective["types"][SCAN] == {
        "converter": "rays", "options": {"color_by": "range", "colormap": "magma", "radius": 0.05}
    }
    assert effective["types"][IMAGE] == {"converter": "auto"}
    assert effective["types"]["sensor_msgs/msg/Imu"]["options"]["acceleration_scale"] == 0.1
    assert effective["topics"]["pupper:/scan*"] == {"options": {"radius": 0.07}}
    # The printout is itself a valid configuration meaning the same.
    again = tmp_path / "again.yaml"
    again.write_text(printed)
    reloaded = HostConfig.load(again, REGISTRY)
    original = HostConfig.load(path, REGISTRY)
    for robot, topic, msgtype in [("tb3", "/scan_front", SCAN), ("pupper", "/scan", SCAN),
                                  ("tb3", "/cam", IMAGE)]:
        # (The /* glob's color_by misfits images: reported against each file's own line.)
        assert replace(reloaded.resolve(robot, topic, msgtype), problems=()) == replace(
            original.resolve(robot, topic, msgtype), problems=()
        )


def test_config_mistake_exits_2_naming_file_line_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "host.yaml"
    path.write_text("topics:\n  /scan:\n    converter: ray\n")
    assert cli.main(["--config", str(path), "--print-config"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err == (
        f"swanky-host: error: {path}:3: topics./scan.converter: 'ray' is not one of "
        "['auto', 'both', 'color', 'depth', 'points', 'rays']\n"
    )


def test_example_config_is_valid() -> None:
    config = HostConfig.load(REPO / "deploy" / "host.yaml", REGISTRY)
    assert config.resolve("pupper", "/scan", SCAN).converter == "rays"
    assert config.resolve("tb3", "/scan", SCAN).converter == "both"
    assert not config.resolve("tb3", "/diagnostics", "diagnostic_msgs/msg/DiagnosticArray").enabled
    imu = config.resolve("tb3", "/imu/data_raw", "sensor_msgs/msg/Imu")
    assert imu.entity_path == "/tb3/sensors/imu/data_raw"


# --- the dispatcher honours the settings ----------------------------------------------------------


class RecordingSink(RerunSink):
    """Keeps what would be logged, with the times it would be logged at."""

    def __init__(self) -> None:  # no Rerun recording: the entries are the result
        self.logged: list[tuple[LogEntry, dict[str, int]]] = []

    def log(self, entries: Sequence[LogEntry], times: Mapping[str, int]) -> None:
        self.logged.extend(
            (entry, dict(times if not isinstance(entry, LogItem) or entry.times is None else entry.times))
            for entry in entries
        )

    def close(self) -> None:
        pass

    def items(self, path: str) -> list[tuple[LogItem, dict[str, int]]]:
        return [(e, t) for e, t in self.logged if isinstance(e, LogItem) and e.path == path]

    def warnings(self) -> list[str]:
        """The texts logged under /_swanky/warnings, in order."""
        return [text for item, _ in self.items(WARNINGS_PATH)
                for a in item.archetypes if isinstance(a, rr.TextLog) and a.text is not None
                for text in a.text.as_arrow_array().to_pylist()]


def header(sec: int) -> Any:
    stamp = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=0)
    return T["std_msgs/msg/Header"](stamp=stamp, frame_id="cam")


def image_cdr(sec: int) -> bytes:
    msg = T[IMAGE](header=header(sec), height=2, width=3, encoding="mono8", is_bigendian=0, step=3,
                   data=np.arange(6, dtype=np.uint8))
    return bytes(STORE.serialize_cdr(msg, IMAGE))


def scan_cdr(sec: int) -> bytes:
    msg = T[SCAN](header=header(sec), angle_min=0.0, angle_max=np.pi / 2, angle_increment=np.pi / 2,
                  time_increment=0.0, scan_time=0.0, range_min=0.1, range_max=10.0,
                  ranges=np.array([1.0, 2.0], dtype=np.float32), intensities=np.zeros(0, np.float32))
    return bytes(STORE.serialize_cdr(msg, SCAN))


def test_dispatcher_applies_enabled_entity_path_converter_options_and_restamp(tmp_path: Path) -> None:
    config = load(tmp_path, (
        "topics:\n"
        "  /depth/*:\n"
        "    converter: depth\n"
        "    options: {depth_meter: 100, colormap: viridis}\n"
        "    entity_path: /{robot}/cams{topic}\n"
        "  /color:\n"
        "    enabled: false\n"
        "  /scan:\n"
        "    converter: rays\n"
        "    restamp: true\n"
    ))
    sink = RecordingSink()
    dispatcher = Dispatcher(sink, config=config, strict=True)
    dispatcher.dispatch([
        RawMessage("tb3", "/depth/image", IMAGE, image_cdr(5), receive_ns=7),
        RawMessage("tb3", "/color", IMAGE, image_cdr(5), receive_ns=7),
        RawMessage("tb3", "/color", IMAGE, b"not even CDR", receive_ns=8),
        RawMessage("tb3", "/scan", SCAN, scan_cdr(5), receive_ns=7_000_000_123, log_ns=9),
    ])
    # A mono8 image would be a grey Image; forced to depth with the topic's options.
    [(item, times)] = sink.items("/tb3/cams/depth/image")
    [depth] = item.archetypes
    assert isinstance(depth, rr.DepthImage)
    assert depth.meter is not None
    assert depth.meter.as_arrow_array().to_pylist() == [100.0]
    assert depth.colormap is not None
    assert depth.colormap.as_arrow_array().to_pylist() == [rr.components.Colormap.Viridis.value]
    assert times == {"ros_time": 5_000_000_000, "receive_time": 7}
    # Disabled: nothing logged, not even a warning for the bad payload; counted as skipped.
    assert not [e for e, _ in sink.logged if "/color" in e.path or e.path == "/_swanky/warnings"]
    counters = dispatcher.counters[("tb3", "/color")]
    assert (counters.received, counters.skipped, counters.converted, counters.dropped) == (2, 2, 0, 0)
    # Rays only, stamped with the receive time instead of the header's 5 s.
    [(rays, times)] = sink.items("/tb3/scan/rays")
    assert not sink.items("/tb3/scan")
    assert times == {"ros_time": 7_000_000_123, "receive_time": 7_000_000_123, "log_time": 9}
    strips = rays.archetypes[0].strips.as_arrow_array().to_pylist()  # type: ignore[attr-defined]
    assert np.allclose(strips, [[[0, 0, 0], [1, 0, 0]], [[0, 0, 0], [0, 2, 0]]], atol=1e-6)


def test_dispatcher_warns_once_about_a_misfit_glob_and_converts_anyway(tmp_path: Path) -> None:
    config = load(tmp_path, "topics:\n  /cam*:\n    converter: both\n")
    sink = RecordingSink()
    dispatcher = Dispatcher(sink, config=config)
    dispatcher.dispatch([RawMessage("tb3", t, IMAGE, image_cdr(1)) for t in ("/cam1", "/cam2", "/cam1")])
    warnings = [e for e, _ in sink.items("/_swanky/warnings")]
    assert [w.archetypes[0].text.as_arrow_array().to_pylist() for w in warnings] == [[  # type: ignore[attr-defined]
        f"[tb3] /cam1: {tmp_path / 'host.yaml'}:3: topics./cam*.converter: sensor_msgs/msg/Image has no "
        "converter 'both' (alternatives: auto, depth, color) (ignored for this topic) (further "
        "ConfigErrors on this topic are counted, not shown)"
    ]]
    assert [type(e.archetypes[0]) for e, _ in sink.items("/tb3/cam1")] == [rr.Image, rr.Image]
    assert dispatcher.counters[("tb3", "/cam2")].converted == 1
    with pytest.raises(ConfigError, match=r"topics\./cam\*\.converter"):
        Dispatcher(RecordingSink(), config=load(tmp_path, "topics:\n  /cam*:\n    converter: both\n"),
                   strict=True).dispatch([RawMessage("tb3", "/cam1", IMAGE, image_cdr(1))])


def costmap_grid(tmp_path: Path, config: HostConfig) -> dict[str, Any]:
    """The GridMap row a nav2 global costmap is logged as, through the dispatcher into a file."""
    out = tmp_path / "costmap.rrd"
    dispatcher = Dispatcher(RerunSink(SinkOptions(save=out)), config=config, strict=True)
    cdr = bytes(base_typestore().serialize_cdr(costmap([[0, 128], [254, 255]]), COSTMAP))
    dispatcher.dispatch([RawMessage("tb3", "/global_costmap/costmap_raw", COSTMAP, cdr, log_ns=3 * 10**9)])
    dispatcher.close()
    dispatcher.sink.close()
    assert dispatcher.counters[("tb3", "/global_costmap/costmap_raw")].converted == 1
    [row] = entity_rows(out, "/tb3/global_costmap/costmap_raw")["/tb3/global_costmap/costmap_raw"]
    return row


def test_a_costmap_takes_the_grid_drawing_options_its_converter_reads(tmp_path: Path) -> None:
    """Its row names the record the Costmap converter reads; before, the config checked the
    schema's list of types and refused opacity ("its options: none")."""
    drawn = costmap_grid(tmp_path, load(tmp_path, f"types:\n  {COSTMAP}:\n    options: {{opacity: 0.5}}\n"))
    assert drawn["GridMap:opacity"] == [0.5]
    assert drawn["GridMap:draw_order"] == [1.0]  # still derived: a global costmap over the map
    assert drawn["GridMap:colormap"] == [rr.components.Colormap.RvizCostmap.value]
    builtin = costmap_grid(tmp_path, HostConfig.builtin(REGISTRY))
    assert builtin["GridMap:opacity"] == [pytest.approx(0.7)]  # a costmap's own default
    assert builtin["GridMap:data"] == drawn["GridMap:data"]
    # A costmap has no walls, so no wall options.
    assert mistakes(tmp_path, f"types:\n  {COSTMAP}:\n    options: {{wall_height: 1}}\n") == [
        "3: types.nav2_msgs/msg/Costmap.options.wall_height: unknown key (expected one of: color_scheme, "
        "draw_order, opacity)"
    ]
