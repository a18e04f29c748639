"""The host's YAML configuration (``swanky-host --config host.yaml``): per topic its entity path,
whether it is shown, which alternative converter draws it, the converter's options, and restamping.

Precedence, lowest to highest, merged key by key (``options`` too, option by option):

1. the built-in defaults of the topic's type (its options record in ``host_bridge/options.py``),
2. ``defaults``,
3. matching ``types`` entries: type globs (``sensor_msgs/msg/*``) least specific first, then
   the exact type name,
4. matching ``topics`` entries: topic globs least specific first (more wildcards before fewer,
   shorter before longer, as :func:`robot_relay.configfile.first_match` ranks them), a
   robot-qualified key ``ROBOT_GLOB:/topic`` right after the same unqualified topic pattern,
   and the exact topic name last.

So an exact topic beats any glob, and a glob beats the type. The schema checks what it can; the
rest (glob syntax, placeholders, whether a converter or option exists *for this type*) is checked
here and reads the same ``FILE:LINE: KEY: what`` way. A ``types`` entry naming one type is checked
when the file loads; a glob meets its types only at run time, so a misfit there is reported once
(as a warning) and only the misfit key is ignored for that topic.
"""

from __future__ import annotations

import fnmatch
import re
import string
from collections.abc import Collection, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from host_bridge.errors import ConfigError, relay_errors
from host_bridge.options import CONVERTER_OPTION, OPTIONS_BY_DEFINITION, fixed_defaults
from robot_relay.configfile import (
    ConfigDocument,
    KeyPath,
    check_topic_glob,
    first_match,
    load_config,
    schema,
    schema_validator,
)

SCHEMA_NAME = "host"
DEFAULT_ENTITY_PATH = "/{robot}{topic}"
_PLACEHOLDERS = frozenset({"robot", "topic"})
# pkg/msg/Name with fnmatch wildcards; a [...] class must be closed and non-empty.
_TYPE_GLOB = re.compile(r"(?:[A-Za-z0-9_/*?]|\[!?[A-Za-z0-9_/]+\])+")
_ROBOT_GLOB = re.compile(r"[A-Za-z0-9_*?\[\]!-]+")
_WILDCARDS = re.compile(r"[*?\[]")


@dataclass(frozen=True, slots=True)
class TopicSettings:
    """What the dispatcher does with one topic of one robot.

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


@dataclass(frozen=True, slots=True)
class _TypeRules:
    """What one type takes: its alternative converters and options (the schema's), and the
    defaults of its options record."""

    converters: tuple[str, ...]
    options: Mapping[str, Mapping[str, Any]]
    defaults: Mapping[str, Any]


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


class HostConfig:
    """The loaded file (or none) and the per-(robot, topic, type) settings it resolves to."""

    def __init__(self, document: ConfigDocument | None, registered_types: Collection[str]) -> None:
        self._schema = schema(SCHEMA_NAME)
        self._document = document
        self._registered = frozenset(registered_types)
        data: Mapping[str, Any] = document.data if document is not None else {}
        self._user = data
        self._defaults = _Layer(("defaults",), data.get("defaults", {}))
        self._types = {key: _Layer(("types", key), value) for key, value in data.get("types", {}).items()}
        self._topic_layers = {
            key: _Layer(("topics", key), value) for key, value in data.get("topics", {}).items()
        }
        self._topic_keys: list[_TopicKey] = []
        self._rules: dict[str, _TypeRules] = {}
        self._cache: dict[tuple[str, str, str], TopicSettings] = {}
        self._reported: set[str] = set()
        self._check()

    @classmethod
    def load(cls, path: Path, registered_types: Collection[str]) -> HostConfig:
        """Read and check ``path``; a mistake raises ConfigError naming file:line:key."""
        with relay_errors():  # the file is read and checked by the relay's shared loader
            document = load_config(path, SCHEMA_NAME)
        return cls(document, registered_types)

    @classmethod
    def builtin(cls, registered_types: Collection[str]) -> HostConfig:
        """No file: every type's built-in defaults only."""
        return cls(None, registered_types)

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

    def _type_rules(self, msgtype: str) -> _TypeRules:
        """The schema's definition for ``msgtype``: its own, else ``plain`` (a converter without
        options) or ``generic`` (no converter registered)."""
        rules = self._rules.get(msgtype)
        if rules is not None:
            return rules
        ref = self._schema["properties"]["types"]["properties"].get(msgtype, {}).get("$ref")
        name = ref.rsplit("/", 1)[-1] if ref else ("plain" if msgtype in self._registered else "generic")
        properties = self._schema["$defs"][name]["properties"]
        converter = properties.get("converter", {})
        options: Mapping[str, Mapping[str, Any]] = properties.get("options", {}).get("properties", {})
        option_defaults = fixed_defaults(OPTIONS_BY_DEFINITION[name])
        defaults: dict[str, Any] = {}
        if CONVERTER_OPTION in option_defaults:
            defaults["converter"] = option_defaults.pop(CONVERTER_OPTION)
        if option_defaults:
            defaults["options"] = option_defaults
        rules = self._rules[msgtype] = _TypeRules(tuple(converter.get("enum", ())), options, defaults)
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
                where = (*layer.path, "options", name)
                spec = rules.options.get(name)
                if spec is None:
                    known = ", ".join(sorted(rules.options)) or "none"
                    text = f"{msgtype} takes no option {name!r} (its options: {known})"
                    problems.append(self._error(where, text))
                    del options[name]
                    continue
                validator = schema_validator({"$defs": self._schema["$defs"], **spec})
                error = best_match(validator.iter_errors(value))
                if error is not None:
                    text = f"{error.message} for {msgtype}"
                    problems.append(self._error((*where, *error.absolute_path), text))
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

    def resolve(self, robot: str, topic: str, msgtype: str) -> TopicSettings:
        """The settings of one topic, merged from every applying entry (cached)."""
        key = (robot, topic, msgtype)
        settings = self._cache.get(key)
        if settings is None:
            settings = self._cache[key] = self._resolve(robot, topic, msgtype)
        return settings

    def _resolve(self, robot: str, topic: str, msgtype: str) -> TopicSettings:
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
        return TopicSettings(
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
        for msgtype in self._schema["properties"]["types"]["properties"]:
            if self._type_rules(msgtype).defaults:
                types[msgtype] = dict(self._type_rules(msgtype).defaults)
        for msgtype, settings in self._user.get("types", {}).items():
            base = types.get(msgtype, {})
            types[msgtype] = {**base, **settings}
            if "options" in base and "options" in settings:
                types[msgtype]["options"] = {**base["options"], **settings["options"]}
        return {"defaults": defaults, "types": types, "topics": dict(self._user.get("topics", {}))}

    def dump(self) -> str:
        """``effective()`` as YAML, itself a valid host config file."""
        source = (
            f"{self._document.path} merged over the built-in defaults" if self._document is not None
            else "the built-in defaults (no --config file)"
        )
        header = f"# swanky-host effective configuration: {source}\n"
        return header + yaml.safe_dump(self.effective(), sort_keys=False, default_flow_style=False)
