"""YAML configuration files checked against a JSON Schema; every mistake names file:line:key.

Shared by the relay (``relay.schema.json``) and the host (``host.schema.json``); both schemas
live in ``schemas/`` (installed as ``swanky_schemas``). PyYAML's node tree keeps the line of
every key, jsonschema finds the mistakes, and :class:`ConfigDocument` joins the two so a
message reads ``relay.yaml:7: topics./scan.max_rate: 'fast' is not of type 'number'``.
Checks a schema cannot express (a glob that is malformed, a value that contradicts another)
go through :meth:`ConfigDocument.error` so they read the same way.
"""

from __future__ import annotations

import fnmatch
import functools
import json
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from importlib.resources import files
from pathlib import Path
from typing import TYPE_CHECKING, Any

from robot_relay.errors import ConfigError

if TYPE_CHECKING:
    # yaml only where a file is read: swanky-host --bag without --config imports this module
    # for its topic globs, not yaml (20 ms of its imports at load 5).
    import yaml
    from jsonschema import FormatChecker, ValidationError
    from jsonschema.protocols import Validator

KeyPath = tuple[str | int, ...]

# A ROS topic name glob: absolute or starting with a wildcard, ROS name characters plus
# fnmatch's * ? [...] and no empty segment. fnmatch itself accepts anything, so typos like
# "scan" (relative) or "/camera/[abc" (unclosed class) would silently match nothing.
_GLOB_CHARS = re.compile(r"[A-Za-z0-9_/~{}*?\[\]!-]+")

def check_topic_glob(text: object) -> bool:
    """True for a usable topic glob; raises ValueError saying what is wrong otherwise."""
    if not isinstance(text, str):
        return True
    if not text or text[0] not in "/*?[":
        raise ValueError(f"topic glob {text!r} must start with '/' or a wildcard")
    if not _GLOB_CHARS.fullmatch(text):
        raise ValueError(f"topic glob {text!r} has characters a ROS topic name cannot hold")
    depth = 0
    for char in text:
        depth += char == "["
        depth -= char == "]"
        if depth not in (0, 1):
            raise ValueError(f"topic glob {text!r} has unbalanced [ ]")
    if depth:
        raise ValueError(f"topic glob {text!r} has an unclosed [")
    if "//" in text:
        raise ValueError(f"topic glob {text!r} has an empty name segment '//'")
    return True


def schema(name: str) -> dict[str, Any]:
    """The bundled JSON Schema ``schemas/<name>.schema.json``."""
    text = (files("swanky_schemas") / f"{name}.schema.json").read_text(encoding="utf-8")
    loaded: dict[str, Any] = json.loads(text)
    return loaded


def key_text(path: KeyPath) -> str:
    """``topics./scan.max_rate`` / ``robots[2].name``; ``(top level)`` for the root."""
    text = ""
    for part in path:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else part)
    return text or "(top level)"


@dataclass(frozen=True)
class ConfigDocument:
    """A parsed YAML file with the source line of every key and item."""

    path: Path
    data: Any
    root: yaml.Node | None

    @classmethod
    def parse(cls, path: Path, text: str | None = None) -> ConfigDocument:
        import yaml

        if text is None:
            try:
                text = path.read_text(encoding="utf-8")
            except OSError as err:
                msg = f"{path}: cannot read config file: {err.strerror or err}"
                raise ConfigError(msg) from err
        try:
            root = yaml.compose(text, Loader=yaml.SafeLoader)
            data = yaml.safe_load(text)
        except yaml.YAMLError as err:
            mark = getattr(err, "problem_mark", None)
            where = f"{path}:{mark.line + 1}" if mark is not None else str(path)
            problem = getattr(err, "problem", None) or str(err)
            msg = f"{where}: not valid YAML: {problem}"
            raise ConfigError(msg) from err
        return cls(path, {} if data is None else data, root)

    def line(self, path: KeyPath) -> int:
        """1-based line of the deepest node of ``path`` that exists (1 for an empty file)."""
        node = self.root
        line = node.start_mark.line + 1 if node is not None else 1
        for part in path:
            child = self._child(node, part)
            if child is None:
                break
            node, line = child
        return line

    @staticmethod
    def _child(node: yaml.Node | None, part: str | int) -> tuple[yaml.Node, int] | None:
        import yaml

        if isinstance(node, yaml.MappingNode):
            for key, value in node.value:
                if key.value == str(part):
                    return value, key.start_mark.line + 1
        elif isinstance(node, yaml.SequenceNode) and isinstance(part, int) and part < len(node.value):
            item = node.value[part]
            return item, item.start_mark.line + 1
        return None

    def error(self, path: KeyPath, message: str) -> ConfigError:
        """A ConfigError reading ``FILE:LINE: KEY: message``."""
        return ConfigError(f"{self.path}:{self.line(path)}: {key_text(path)}: {message}")

    def check(self, schema: Mapping[str, Any]) -> None:
        """Raise one ConfigError listing every schema violation, each as FILE:LINE: KEY: what."""
        validator = schema_validator(schema)
        problems = sorted(
            (self.line(path), key_text(path), message)
            for error in validator.iter_errors(self.data)
            for path, message in _explain(error)
        )
        if problems:
            raise ConfigError("\n".join(f"{self.path}:{line}: {key}: {what}" for line, key, what in problems))


@functools.cache
def _format_checker() -> FormatChecker:
    from jsonschema import FormatChecker

    checker = FormatChecker()
    checker.checks("topic-glob", raises=ValueError)(check_topic_glob)
    return checker


def schema_validator(schema: Mapping[str, Any]) -> Validator:
    """A JSON Schema 2020-12 validator knowing our formats (``topic-glob``). jsonschema is
    imported here, when a config file is read: it is the heaviest import of the relay's
    start-up (44-71 ms, also on a Raspberry Pi that reads no config)."""
    from jsonschema import Draft202012Validator

    return Draft202012Validator(schema, format_checker=_format_checker())


def _explain(error: ValidationError) -> Iterator[tuple[KeyPath, str]]:
    """Where and what, pointing at the offending key itself rather than its parent."""
    path: KeyPath = tuple(error.absolute_path)
    if error.validator == "additionalProperties" and isinstance(error.instance, Mapping):
        properties = error.schema.get("properties", {}) if isinstance(error.schema, Mapping) else {}
        allowed = sorted(properties)
        known = set(allowed)
        for key in error.instance:
            if key not in known:
                hint = f" (expected one of: {', '.join(allowed)})" if allowed else ""
                yield (*path, str(key)), f"unknown key{hint}"
        return
    if "propertyNames" in error.absolute_schema_path:
        # jsonschema reports a bad key at its parent object; the key is the instance.
        yield (*path, str(error.instance)), _message(error)
        return
    if error.validator in ("anyOf", "oneOf") and error.context:
        # The alternative that got deepest explains best (e.g. a misspelt key inside an object
        # rather than "is not of type 'string'").
        best = max(error.context, key=lambda sub: len(sub.absolute_path))
        yield from _explain(best)
        return
    yield path, _message(error)


def _message(error: ValidationError) -> str:
    """A format checker's own explanation where it gave one."""
    return str(error.cause) if error.validator == "format" and error.cause else error.message


def load_config(path: Path, schema_name: str) -> ConfigDocument:
    """Read and validate ``path`` against ``schemas/<schema_name>.schema.json``."""
    document = ConfigDocument.parse(path)
    document.check(schema(schema_name))
    return document


def first_match(patterns: Sequence[str], name: str) -> str | None:
    """The most specific glob of ``patterns`` matching ``name``: exact > fewest wildcards > longest."""

    matching = [p for p in patterns if fnmatch.fnmatchcase(name, p)]
    if not matching:
        return None
    return min(matching, key=lambda p: (p != name, sum(p.count(c) for c in "*?["), -len(p)))
