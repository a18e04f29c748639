"""Per-topic policy: built-ins, precedence, the keep-latest rate cap, relay.yaml and its errors."""

from __future__ import annotations

import sys
from itertools import pairwise
from pathlib import Path

import pytest

from robot_relay.cli import parse_args, relay_options
from robot_relay.config import DEFAULT_DENY, RelayConfig, load_relay_config
from robot_relay.errors import ConfigError
from robot_relay.policy import (
    DEFAULT_TRAFFIC,
    PRIORITIES,
    TRAFFIC,
    Policy,
    PolicyTable,
    RateLimiter,
)
from robot_relay.sources.take_loop import LATENCY_BUDGET_S
from robot_relay.wire import FLAG_LZ4, FLAG_ZSTD, QosProfile, compressor, decompress

REPO = Path(__file__).resolve().parents[2]
RELIABLE = QosProfile()
BEST_EFFORT = QosProfile(reliability="best_effort")
LATCHED = QosProfile(durability="transient_local", depth=1)


def test_builtin_defaults_put_tf_and_scans_first_and_images_last() -> None:
    table = PolicyTable()
    assert table.resolve("/tf", "tf2_msgs/msg/TFMessage", RELIABLE) == Policy(None, "data_high", "block")
    assert table.resolve("/tf_static", "tf2_msgs/msg/TFMessage", LATCHED) == Policy(
        None, "data_high", "block"
    )
    assert table.resolve("/scan", "sensor_msgs/msg/LaserScan", BEST_EFFORT) == Policy(
        None, "data_high", "drop"
    )
    assert table.resolve("/camera/image_raw", "sensor_msgs/msg/Image", RELIABLE) == Policy(
        None, "data_low", "drop"
    )
    assert table.resolve("/odom", "nav_msgs/msg/Odometry", RELIABLE) == Policy(None, "data", "block")
    assert table.resolve("/odom", "nav_msgs/msg/Odometry", BEST_EFFORT).congestion == "drop"
    assert table.resolve("/map", "nav_msgs/msg/OccupancyGrid", LATCHED).congestion == "block"


def test_builtins_never_drop_video_whatever_its_qos() -> None:
    """A lost video frame spoils the picture until the next keyframe: block, not drop."""
    table = PolicyTable()
    for qos in (RELIABLE, BEST_EFFORT):
        assert table.resolve("/camera/video", "foxglove_msgs/msg/CompressedVideo", qos) == Policy(
            None, "data_low", "block"
        )


def test_traffic_table_names_zenoh_priorities() -> None:
    assert {c.priority for c in TRAFFIC.values()} <= set(PRIORITIES)
    assert DEFAULT_TRAFFIC.priority in PRIORITIES


def test_exact_name_beats_specific_glob_beats_broad_glob_beats_defaults() -> None:
    table = PolicyTable(
        defaults={"compression": "lz4", "priority": "background"},
        topics={
            "*": {"max_rate": 30},
            "/camera/*": {"max_rate": 5, "priority": "data"},
            "/camera/*/image_raw": {"max_rate": 2},
            "/camera/front/image_raw": {"compression": "zstd"},
        },
    )
    image = "sensor_msgs/msg/Image"
    # Exact entry: its own key, the rest from defaults then built-ins (entries do not merge).
    assert table.resolve("/camera/front/image_raw", image, RELIABLE) == Policy(
        None, "background", "drop", "zstd"
    )
    assert table.resolve("/camera/rear/image_raw", image, RELIABLE) == Policy(2, "background", "drop", "lz4")
    assert table.resolve("/camera/rear/info", "sensor_msgs/msg/CameraInfo", RELIABLE) == Policy(
        5, "data", "drop", "lz4"
    )
    assert table.resolve("/odom", "nav_msgs/msg/Odometry", RELIABLE) == Policy(
        30, "background", "block", "lz4"
    )
    assert table.entry("/camera/rear/image_raw") == "/camera/*/image_raw"


def test_latched_topics_are_never_rate_capped() -> None:
    table = PolicyTable(topics={"*": {"max_rate": 1, "congestion": "drop"}})
    policy = table.resolve("/tf_static", "tf2_msgs/msg/TFMessage", LATCHED)
    assert policy.max_rate is None
    assert policy.congestion == "drop"  # an explicit choice is kept


def test_rate_limiter_keeps_the_newest_and_flushes_the_last_of_a_burst() -> None:
    limiter: RateLimiter[int] = RateLimiter(8.0)
    sent: list[tuple[float, int]] = []
    # 64 Hz for two seconds (items 0..127; binary fractions keep the times exact), flushing
    # exactly when due like the relay's flusher thread.
    arrivals = [i / 64 for i in range(128)]
    for i, now in enumerate(arrivals):
        due = limiter.due_at
        if due is not None and due <= now:
            item = limiter.take_due(due)
            assert item is not None
            sent.append((due, item))
        ready = limiter.offer(i, now)
        if ready is not None:
            sent.append((now, ready))
    due = limiter.due_at
    assert due == 2.0
    assert limiter.take_due(due - 0.001) is None  # not before its time
    assert limiter.take_due(due) == 127  # the last message of the burst is not lost
    sent.append((due, 127))
    assert limiter.due_at is None
    times = [t for t, _ in sent]
    assert [item for _, item in sent] == [0, *range(7, 128, 8)]
    # Nothing newer than a sent item had arrived before it went out; sends are 1/8 s apart.
    assert not any(i > item and t < sent_at for sent_at, item in sent for i, t in enumerate(arrivals))
    assert all(b - a >= 0.125 for a, b in pairwise(times))
    assert limiter.dropped == 128 - len(sent)


def test_rate_limiter_after_a_quiet_period_sends_at_once_and_a_late_flush_loses_to_newer() -> None:
    limiter: RateLimiter[str] = RateLimiter(2.0)
    assert limiter.offer("a", 0.0) == "a"
    assert limiter.offer("b", 0.1) is None
    assert limiter.due_at == pytest.approx(0.5)
    # The flush did not run in time; a newer message replaces the waiting one and goes out.
    assert limiter.offer("c", 0.7) == "c"
    assert limiter.due_at is None
    assert limiter.dropped == 1
    assert limiter.offer("d", 5.0) == "d"
    assert limiter.take_any() is None
    with pytest.raises(ValueError, match="max_rate must be > 0"):
        RateLimiter(0.0)


@pytest.mark.parametrize(("name", "flag"), [("lz4", FLAG_LZ4), ("zstd", FLAG_ZSTD)])
def test_compression_round_trips_bytes_exactly(name: str, flag: int) -> None:
    payload = b"\x00\x01\x00\x00" + bytes(range(256)) * 40 + b"\xff" * 3
    packed = compressor(name)(payload)
    assert len(packed) < len(payload) // 4
    assert decompress(packed, flag, "swanky/r/data/x") == payload


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "relay.yaml"
    path.write_text(text)
    return path


def config_errors(path: Path) -> list[str]:
    with pytest.raises(ConfigError) as caught:
        load_relay_config(path)
    return [line.removeprefix(f"{path}:") for line in str(caught.value).splitlines()]


def test_config_errors_name_file_line_and_key(tmp_path: Path) -> None:
    path = write(tmp_path, (
        "robot: tb3\n"
        "zenoh:\n"
        "  conect: [tcp/10.0.0.1:7447]\n"
        "topics:\n"
        "  deny: [scan]\n"
        "policy:\n"
        "  /camera/[ab:\n"
        "    max_rate: 5\n"
        "  /scan:\n"
        "    max_rate: fast\n"
        "    priority: urgent\n"
        "defaults:\n"
        "  compression: gzip\n"
    ))
    assert config_errors(path) == [
        "3: zenoh.conect: unknown key (expected one of: config, connect, listen, mode, "
        "multicast_scouting)",
        "5: topics.deny[0]: topic glob 'scan' must start with '/' or a wildcard",
        "7: policy./camera/[ab: topic glob '/camera/[ab' has an unclosed [",
        "10: policy./scan.max_rate: 'fast' is not of type 'number', 'null'",
        "11: policy./scan.priority: 'urgent' is not one of ['real_time', 'interactive_high', "
        "'interactive_low', 'data_high', 'data', 'data_low', 'background']",
        "13: defaults.compression: 'gzip' is not one of ['none', 'lz4', 'zstd']",
    ]


def test_rate_cap_of_zero_and_bad_robot_name_are_refused(tmp_path: Path) -> None:
    path = write(tmp_path, "robot: my robot\npolicy:\n  /scan: {max_rate: 0}\n")
    assert config_errors(path) == [
        "1: robot: 'my robot' does not match '^[A-Za-z0-9_-]+$'",
        "3: policy./scan.max_rate: 0 is less than or equal to the minimum of 0",
    ]


def test_missing_compression_package_is_named_at_start_up(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "zstandard", None)  # import zstandard -> ImportError
    path = write(tmp_path, "policy:\n  /camera/*:\n    compression: zstd\n")
    assert config_errors(path) == [
        "3: policy./camera/*.compression: zstd needs the Python package 'zstandard', which is not "
        "installed: pip install 'swanky[compression]' (or set compression: none)"
    ]


def test_deploy_example_is_valid_and_the_command_line_overrides_it() -> None:
    example = REPO / "deploy" / "relay.yaml"
    config = load_relay_config(example)
    assert config.robot == "tb3"
    assert config.mode == "client"
    assert config.connect == ("tcp/192.168.1.10:7447",)
    table = config.policies
    assert table.resolve("/camera/image_raw/compressed", "sensor_msgs/msg/CompressedImage",
                         BEST_EFFORT).max_rate == 5
    assert table.resolve("/scan", "sensor_msgs/msg/LaserScan", BEST_EFFORT).priority == "data_high"

    args = parse_args(["--config", str(example), "--robot", "pupper", "-e", "tcp/10.0.0.2:7447",
                       "--exclude", "/rosout"])
    options = relay_options(args, config)
    assert (options.robot, options.zenoh.connect, options.zenoh.mode) == (
        "pupper", ("tcp/10.0.0.2:7447",), "client"
    )
    assert options.exclude == ("/rosout",)
    assert options.topics == config.allow
    assert options.policies is table

    assert options.latency_budget == config.latency_budget == 0.1
    assert relay_options(parse_args(["--config", str(example), "--latency-budget", "0"]),
                         config).latency_budget == 0.0

    bare = relay_options(parse_args([]), RelayConfig())
    assert bare.latency_budget == LATENCY_BUDGET_S
    assert bare.topics == ("*",)
    assert bare.exclude == DEFAULT_DENY
    assert bare.robot  # the hostname


@pytest.mark.parametrize("text", ["-0.01", "50", "soon", "nan"])
def test_a_latency_budget_outside_0_to_1_s_is_refused_by_flag_and_by_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str,
) -> None:
    with pytest.raises(SystemExit) as exited:
        parse_args(["--latency-budget", text])
    assert exited.value.code == 2
    assert (f"argument --latency-budget: {text!r} is not a number of seconds from 0 to 1"
            in capsys.readouterr().err)
    if text in ("-0.01", "50"):
        relation = "less than the minimum of 0" if text.startswith("-") else "greater than the maximum of 1"
        assert config_errors(write(tmp_path, f"latency_budget: {text}\n")) == [
            f"1: latency_budget: {text} is {relation}"
        ]
