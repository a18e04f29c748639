"""The relay's YAML file (``--config relay.yaml``, schemas/relay.schema.json); the command line
overrides it key by key (robot_relay.cli)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from robot_relay.configfile import ConfigDocument, KeyPath, load_config
from robot_relay.policy import PolicyTable
from robot_relay.wire import COMPRESSION_PACKAGES, compressor

DEFAULT_ALLOW = ("*",)
# Hidden topics (a name segment starting with '_', e.g. action internals) stay out unless
# asked for, as with `ros2 bag record` without --include-hidden-topics, and so does
# /parameter_events (every node's parameter chatter); a topic named exactly in `allow` (or
# --topics) is forwarded all the same.
DEFAULT_DENY = ("*/_*", "/parameter_events")


@dataclass(frozen=True, slots=True)
class RelayConfig:
    robot: str | None = None
    mode: str | None = None
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    zenoh_config: Path | None = None
    multicast_scouting: bool | None = None
    allow: tuple[str, ...] = DEFAULT_ALLOW
    deny: tuple[str, ...] = DEFAULT_DENY
    policies: PolicyTable = field(default_factory=PolicyTable)
    latency_budget: float | None = None


def _compressions(data: dict[str, Any]) -> Iterator[tuple[KeyPath, str]]:
    if "compression" in data.get("defaults", {}):
        yield ("defaults", "compression"), data["defaults"]["compression"]
    for glob, entry in data.get("policy", {}).items():
        if "compression" in entry:
            yield ("policy", glob, "compression"), entry["compression"]


def _check_compressions(document: ConfigDocument) -> None:
    """Fail at start-up, not when a topic appears, if a compression's package is missing."""
    for path, name in _compressions(document.data):
        if name == "none":
            continue
        try:
            compressor(name)
        except ImportError as err:
            raise document.error(
                path, f"{name} needs the Python package {COMPRESSION_PACKAGES[name]!r}, which is "
                "not installed: pip install 'swanky[compression]' (or set compression: none)"
            ) from err


def load_relay_config(path: Path) -> RelayConfig:
    document = load_config(path, "relay")
    _check_compressions(document)
    data: dict[str, Any] = document.data
    zenoh = data.get("zenoh", {})
    topics = data.get("topics", {})
    zenoh_config = zenoh.get("config")
    return RelayConfig(
        robot=data.get("robot"),
        mode=zenoh.get("mode"),
        connect=tuple(zenoh.get("connect", ())),
        listen=tuple(zenoh.get("listen", ())),
        zenoh_config=None if zenoh_config is None else path.parent / zenoh_config,
        multicast_scouting=zenoh.get("multicast_scouting"),
        allow=tuple(topics.get("allow", DEFAULT_ALLOW)),
        deny=tuple(topics.get("deny", DEFAULT_DENY)),
        policies=PolicyTable(data.get("defaults", {}), data.get("policy", {})),
        latency_budget=data.get("latency_budget"),
    )
