"""Errors of the PC side; each message says what was wrong, where, and what to do."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from robot_relay.errors import RelayError


class HostError(Exception):
    """Base of every error the host raises on purpose."""


class DecodeError(HostError):
    """A payload does not deserialize with its type definition (truncated CDR, wrong type)."""


class UnknownTypeError(HostError):
    """No definition is known for a message type."""


class ConvertError(HostError):
    """A decoded message cannot be converted (unsupported encoding, inconsistent sizes)."""


class PartialConvertError(ConvertError):
    """Part of a message converted (e.g. a model with one missing mesh): ``items`` are logged,
    then the error is reported."""

    def __init__(self, message: str, items: list[Any]) -> None:
        super().__init__(message)
        self.items = items


class MissingResourceError(ConvertError):
    """A file a robot model names (``package://``, ``file://``, a path) is nowhere to be found.

    The parts are kept apart so a model with many missing meshes can say where it looked and
    which ``--package-path`` would help once, not once per mesh."""

    def __init__(self, uri: str, searched: str, package: str | None) -> None:
        self.uri = uri
        self.searched = searched
        self.package = package
        hint = "" if package is None else f"; pass --package-path {package}=DIR"
        super().__init__(f"{uri} not found ({searched}){hint}")


class RegistryError(HostError):
    """The converter registry was assembled wrongly (a type registered twice)."""


class InputError(HostError):
    """An input (bag path, Zenoh endpoint) cannot be opened."""


class ConfigError(HostError):
    """The host configuration or command line is wrong."""


class SinkError(HostError):
    """The Rerun sink cannot be set up (viewer not spawnable, bad address)."""


class RecorderError(HostError):
    """The --record-mcap file cannot be written."""


@contextmanager
def relay_errors() -> Iterator[None]:
    """Around the host's calls into the relay's shared code (the Zenoh session, robot names,
    config files): the relay's error becomes the host's ConfigError, word for word, so the
    host's command line catches its own errors only."""
    try:
        yield
    except RelayError as err:
        raise ConfigError(str(err)) from err
