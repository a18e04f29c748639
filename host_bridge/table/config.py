"""The host's YAML configuration (``swanky-host --config host.yaml``): per topic its entity path,
whether it is shown, which alternative converter draws it, the converter's options, and restamping.

Precedence, lowest to highest, merged key by key (``options`` too, option by option):

1. the built-in defaults of the topic's type (the options record of its row in the type table,
   ``host_bridge/table/registry.py``),
2. ``defaults``,
3. matching ``types`` entries: type globs (``sensor_msgs/msg/*``) least specific first, then
   the exact type name,
4. matching ``topics`` entries: topic globs least specific first (more wildcards before fewer,
   shorter before longer, as :func:`robot_relay.configfile.first_match` ranks them), a
   robot-qualified key ``ROBOT_GLOB:/topic`` right after the same unqualified topic pattern,
   and the exact topic name last.

So an exact topic beats any glob, and a glob beats the type. The schema checks what it can; the
rest (glob syntax, placeholders, whether a converter or option exists *for this type*: its row's
options record says) is checked here and reads the same ``FILE:LINE: KEY: what`` way. A
``types`` entry naming one type is checked when the file loads; a glob meets its types only at
run time, so a misfit there is reported once (as a warning) and only the misfit key is ignored
for that topic.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import re
import string
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from host_bridge.core.options import CONVERTER_OPTION, converter_choices, fixed_defaults, option_names
from host_bridge.errors import ConfigError, relay_errors
from robot_relay.configfile import (
    ConfigDocument,
    KeyPath,
    check_topic_glob,
    first_match,
    load_config,
    schema,
    schema_validator,
)

if TYPE_CHECKING:
    from jsonschema.protocols import Validator

    from host_bridge.slam.settings import SlamSettings
    from host_bridge.table.registry import Registry

SCHEMA_NAME = "host"
DEFAULT_ENTITY_PATH = "/{robot}{topic}"
_PLACEHOLDERS = frozenset({"robot", "topic"})
# pkg/msg/Name with fnmatch wildcards; a [...] class must be closed and non-empty.
_TYPE_GLOB = re.compile(r"(?:[A-Za-z0-9_/*?]|\[!?[A-Za-z0-9_/]+\])+")
_ROBOT_GLOB = re.compile(r"[A-Za-z0-9_*?\[\]!-]+")
_WILDCARDS = re.compile(r"[*?\[]")


@dataclass(frozen=True, slots=True)
class TopicConfig:
    """What the host configuration says of one topic of one robot (of one type), every entry
    that applies merged: what the dispatcher does with it.

    ``options`` are what the converter reads (``ctx.options``); the ``converter`` choice is in
    them as ``mode``, the option the converters with alternatives already read. ``problems``
    are configuration misfits found while resolving, each reported only the first time.
    """

    entity_path: str
    enabled: bool = True
    converter: str | None = None
    options: Mapping[str, Any] = field(default_factory=dict)
    restamp: bool = False
    problems: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class _Layer:
    """One entry of the file (``("topics", "/scan")``) and its settings."""

    path: KeyPath
    settings: Mapping[str, Any]


@dataclass(frozen=True, slots=True)
class _TopicKey:
    """A ``topics`` key: a topic glob, optionally qualified by a robot glob (``tb3_*:/scan``)."""

    key: str
    robot: str | None
    topic: str

    @classmethod
    def parse(cls, key: str) -> _TopicKey:
        robot, sep, topic = key.partition(":")
        if not sep:
            return cls(key, None, key)
        if not _ROBOT_GLOB.fullmatch(robot):
            msg = f"robot glob {robot!r} before ':' may hold letters, digits, '_', '-' and wildcards only"
            raise ValueError(msg)
        return cls(key, robot, topic)

    def matches(self, robot: str, topic: str) -> bool:
        return fnmatch.fnmatchcase(topic, self.topic) and (
            self.robot is None or fnmatch.fnmatchcase(robot, self.robot)
        )


@dataclass(slots=True)
class _TypeRules:
    """What one type takes: its alternative converters, options and their defaults (its row's
    options record), and the schema that checks its option values (made when first needed)."""

    converters: tuple[str, ...]
    options: tuple[str, ...]
    defaults: Mapping[str, Any]
    schema: Mapping[str, Any]
    validator: Validator | None = None


def by_specificity(patterns: Iterable[str], name: str) -> list[str]:
    """The patterns matching ``name``, least specific first (the reverse of first_match's ranking)."""
    remaining = list(patterns)
    ranked: list[str] = []
    while (best := first_match(remaining, name)) is not None:
        ranked.append(best)
        remaining.remove(best)
    return ranked[::-1]


def _check_type_glob(text: str) -> None:
    if not _TYPE_GLOB.fullmatch(text):
        msg = f"type {text!r} must look like pkg/msg/Name, globs using * ? and closed [...] classes"
        raise ValueError(msg)


def _check_entity_path(text: str) -> None:
    try:
        parts = list(string.Formatter().parse(text))
    except ValueError as err:
        msg = f"entity path {text!r} has unbalanced braces ({err})"
        raise ValueError(msg) from None
    for _, name, spec, conv in parts:
        if name is not None and (name not in _PLACEHOLDERS or spec or conv):
            msg = f"entity path {text!r}: the only placeholders are {{robot}} and {{topic}}"
            raise ValueError(msg)


def _builtin_settings(record: type[Any]) -> dict[str, Any]:
    """The built-in layer of the types whose row names ``record``: its fixed defaults as a
    config file would write them (``converter`` and ``options``)."""
    option_defaults = fixed_defaults(record)
    settings: dict[str, Any] = {}
    if CONVERTER_OPTION in option_defaults:
        settings["converter"] = option_defaults.pop(CONVERTER_OPTION)
    if option_defaults:
        settings["options"] = option_defaults
    return settings


class HostConfig:
    """The loaded file (or none) and the per-(robot, topic, type) settings it resolves to."""

    def __init__(self, document: ConfigDocument | None, registry: Registry) -> None:
        self._schema = schema(SCHEMA_NAME)
        self._document = document
        self._registry = registry
        data: Mapping[str, Any] = document.data if document is not None else {}
        self._user = data
        self._defaults = _Layer(("defaults",), data.get("defaults", {}))
        self._types = {key: _Layer(("types", key), value) for key, value in data.get("types", {}).items()}
        self._topic_layers = {
            key: _Layer(("topics", key), value) for key, value in data.get("topics", {}).items()
        }
        self._topic_keys: list[_TopicKey] = []
        self._rules: dict[str, _TypeRules] = {}
        self._slam: Mapping[str, Any] = data.get("slam", {})
        self._cache: dict[tuple[str, str, str], TopicConfig] = {}
        self._reported: set[str] = set()
        self._check()

    @classmethod
    def load(cls, path: Path, registry: Registry) -> HostConfig:
        """Read and check ``path`` against ``registry``'s types; a mistake raises ConfigError
        naming file:line:key."""
        with relay_errors():  # the file is read and checked by the relay's shared loader
            document = load_config(path, SCHEMA_NAME)
        return cls(document, registry)

    @classmethod
    def builtin(cls, registry: Registry) -> HostConfig:
        """No file: every type's built-in defaults only."""
        return cls(None, registry)

    def _error(self, path: KeyPath, message: str) -> str:
        assert self._document is not None  # layers with problems come from a file
        return str(self._document.error(path, message))

    def _check(self) -> None:
        """What the schema cannot say, all mistakes at once as ConfigDocument.check reports them."""
        problems: list[str] = []
        for key, layer in self._types.items():
            try:
                _check_type_glob(key)
            except ValueError as err:
                problems.append(self._error(layer.path, str(err)))
                continue
            if not _WILDCARDS.search(key):
                problems.extend(self._fit(layer, key)[1])
        for key, layer in self._topic_layers.items():
            try:
                topic_key = _TopicKey.parse(key)
                check_topic_glob(topic_key.topic)
            except ValueError as err:
                problems.append(self._error(layer.path, str(err)))
                continue
            self._topic_keys.append(topic_key)
        for layer in (self._defaults, *self._types.values(), *self._topic_layers.values()):
            problems.extend(self._check_values(layer))
        problems.extend(self._check_slam())
        if problems:
            raise ConfigError("\n".join(problems))

    def _check_values(self, layer: _Layer) -> list[str]:
        """Type-independent checks of one entry: placeholders, and ranges the schema cannot order."""
        problems = []
        path = layer.settings.get("entity_path")
        if path is not None:
            try:
                _check_entity_path(path)
            except ValueError as err:
                problems.append(self._error((*layer.path, "entity_path"), str(err)))
        depth_range = layer.settings.get("options", {}).get("depth_range")
        if depth_range is not None and not depth_range[0] < depth_range[1]:
            where = (*layer.path, "options", "depth_range")
            problems.append(self._error(where, f"{depth_range} must be [min, max] with min < max (metres)"))
        return problems

    def _slam_layers(self, robot: str | None) -> list[tuple[KeyPath, Mapping[str, Any]]]:
        """The slam: block's settings for ``robot``, lowest precedence first: the block itself,
        then its ``robots`` globs matching the name, least specific first (all of them for None)."""
        base = {key: value for key, value in self._slam.items() if key != "robots"}
        robots: Mapping[str, Any] = self._slam.get("robots", {})
        keys = list(robots) if robot is None else by_specificity(robots, robot)
        return [(("slam",), base), *((("slam", "robots", key), robots[key]) for key in keys)]

    def _check_slam(self) -> list[str]:
        if not self._slam:  # the built-in settings hold, and the SLAM modules stay unimported
            return []
        from host_bridge.slam.settings import SlamSettings, settings_from

        problems = []
        for key in self._slam.get("robots", {}):
            if not _ROBOT_GLOB.fullmatch(key):
                text = "a robot glob may hold letters, digits, '_', '-' and wildcards only"
                problems.append(self._error(("slam", "robots", key), text))
        for path, values in self._slam_layers(None):
            settings = settings_from(values, SlamSettings(enabled=True))
            for problem in settings.check():
                name, _, text = problem.partition(": ")
                problems.append(self._error((*path, name), text))
        return problems

    def slam_configured(self) -> bool:
        """Whether the slam: block turns SLAM on for some robot."""
        return any(values.get("enabled") for _, values in self._slam_layers(None))

    def slam_settings(self, robot: str, enabled: bool = False) -> SlamSettings:
        """``robot``'s SLAM settings; ``enabled`` (--slam) turns it on unless the file says no."""
        from host_bridge.slam.settings import SlamSettings, settings_from

        settings = SlamSettings(enabled=enabled)
        for _, values in self._slam_layers(robot):
            settings = settings_from(values, settings)
        return settings

    def _type_rules(self, msgtype: str) -> _TypeRules:
        """What ``msgtype`` takes: its row's options record says which converters and options,
        the schema's description of the type which values (the settings of any type when the
        schema does not name it: ``test_options.py`` checks it names every type with options)."""
        rules = self._rules.get(msgtype)
        if rules is not None:
            return rules
        record = self._registry.row(msgtype).options
        named = self._schema["properties"]["types"]["properties"]
        value_schema = {"$defs": self._schema["$defs"], **named.get(msgtype, {"$ref": "#/$defs/settings"})}
        rules = self._rules[msgtype] = _TypeRules(
            converter_choices(record), option_names(record), _builtin_settings(record), value_schema
        )
        return rules

    def _fit(self, layer: _Layer, msgtype: str) -> tuple[dict[str, Any], list[str]]:
        """``layer``'s settings as ``msgtype`` takes them, and a message per key it does not."""
        rules = self._type_rules(msgtype)
        settings = dict(layer.settings)
        problems: list[str] = []
        converter = settings.get("converter")
        if converter is not None and converter not in rules.converters:
            choices = ", ".join(rules.converters) or "none, it has one converter"
            text = f"{msgtype} has no converter {converter!r} (alternatives: {choices})"
            problems.append(self._error((*layer.path, "converter"), text))
            del settings["converter"]
        if "options" in settings:
            from jsonschema.exceptions import best_match  # only where a config sets options

            options = dict(settings["options"])
            for name, value in settings["options"].items():
                if name not in rules.options:
                    known = ", ".join(sorted(rules.options)) or "none"
                    text = f"{msgtype} takes no option {name!r} (its options: {known})"
                    problems.append(self._error((*layer.path, "options", name), text))
                    del options[name]
                    continue
                if rules.validator is None:
                    rules.validator = schema_validator(rules.schema)
                error = best_match(rules.validator.iter_errors({"options": {name: value}}))
                if error is not None:
                    text = f"{error.message} for {msgtype}"
                    problems.append(self._error((*layer.path, *error.absolute_path), text))
                    del options[name]
            settings["options"] = options
        return settings, problems

    def _layers(self, robot: str, topic: str, msgtype: str) -> list[_Layer]:
        """Every entry that applies, lowest precedence first (see the module docstring)."""
        types = [self._types[key] for key in by_specificity(self._types, msgtype)]
        matching = [key for key in self._topic_keys if key.matches(robot, topic)]
        topic_rank = by_specificity({key.topic for key in matching}, topic)
        robot_rank = by_specificity({key.robot for key in matching if key.robot is not None}, robot)
        matching.sort(key=lambda k: (
            topic_rank.index(k.topic), -1 if k.robot is None else robot_rank.index(k.robot)
        ))
        return [self._defaults, *types, *(self._topic_layers[key.key] for key in matching)]

    def resolve(self, robot: str, topic: str, msgtype: str) -> TopicConfig:
        """The settings of one topic, merged from every applying entry (cached)."""
        key = (robot, topic, msgtype)
        settings = self._cache.get(key)
        if settings is None:
            settings = self._cache[key] = self._resolve(robot, topic, msgtype)
        return settings

    def _resolve(self, robot: str, topic: str, msgtype: str) -> TopicConfig:
        merged: dict[str, Any] = {}
        options: dict[str, Any] = {}
        problems: list[str] = []
        builtin = _Layer((), self._type_rules(msgtype).defaults)
        for layer in (builtin, *self._layers(robot, topic, msgtype)):
            settings, found = self._fit(layer, msgtype) if layer.path else (dict(layer.settings), [])
            problems.extend(p for p in found if p not in self._reported)
            self._reported.update(found)
            options.update(settings.pop("options", {}))
            merged.update(settings)
        converter = merged.get("converter")
        if converter is not None:
            options["mode"] = converter
        return TopicConfig(
            entity_path=merged.get("entity_path", DEFAULT_ENTITY_PATH).format(robot=robot, topic=topic),
            enabled=merged.get("enabled", True),
            converter=converter,
            options=options,
            restamp=merged.get("restamp", False),
            problems=tuple(problems),
        )

    def effective(self) -> dict[str, Any]:
        """The file merged over the built-in defaults: what ``--print-config`` shows."""
        defaults = {"entity_path": DEFAULT_ENTITY_PATH, "enabled": True, "restamp": False,
                    **self._user.get("defaults", {})}
        types: dict[str, Any] = {}
        for msgtype in self._registry.types():
            if self._type_rules(msgtype).defaults:
                types[msgtype] = dict(self._type_rules(msgtype).defaults)
        for msgtype, settings in self._user.get("types", {}).items():
            base = types.get(msgtype, {})
            types[msgtype] = {**base, **settings}
            if "options" in base and "options" in settings:
                types[msgtype]["options"] = {**base["options"], **settings["options"]}
        effective: dict[str, Any] = {"defaults": defaults, "types": types,
                                     "topics": dict(self._user.get("topics", {}))}
        if self._slam:
            from host_bridge.slam.settings import SlamSettings

            base = {key: value for key, value in self._slam.items() if key != "robots"}
            effective["slam"] = {**dataclasses.asdict(SlamSettings()), **base}
            if "robots" in self._slam:
                effective["slam"]["robots"] = dict(self._slam["robots"])
        return effective

    def dump(self) -> str:
        """``effective()`` as YAML, itself a valid host config file."""
        import yaml

        source = (
            f"{self._document.path} merged over the built-in defaults" if self._document is not None
            else "the built-in defaults (no --config file)"
        )
        header = f"# swanky-host effective configuration: {source}\n"
        # A family's defaults as a types entry would reach every type its glob matches.
        for row in self._registry.rows():
            builtin = _builtin_settings(row.options) if row.is_family else {}
            if builtin:
                flow = yaml.safe_dump(builtin, default_flow_style=True, width=1000).strip()
                header += f"# built in for the types matching {row.msgtype!r} (no row of their own): {flow}\n"
        return header + yaml.safe_dump(self.effective(), sort_keys=False, default_flow_style=False)
