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


class TypeChangeError(HostError):
    """A topic's messages came with another type than before (a robot's node migrated, Twist to
    TwistStamped, or a sender lies): the topic is converted as the new type from then on."""


class TypeMismatchError(HostError):
    """A sample claims another type than its relay's catalog announced for its topic: refused,
    so it cannot change how the topic's real messages are converted."""


class GraphError(HostError):
    """An rmw_zenoh key, liveliness token or attachment is not in a form rmw_zenoh produces."""


class NoClockError(HostError):
    """A relay does not answer the clock query (older than the host, or its answer is not a
    clock reading): its receive times stay on its own clock."""


class ClockOffsetError(HostError):
    """A relay's clock is more than a second off the PC's (a Raspberry Pi without a real-time
    clock or NTP); its receive times are corrected, its header stamps are not."""


class RegistryError(HostError):
    """The converter registry was assembled wrongly (a type registered twice)."""


class InputError(HostError):
    """An input (bag path, Zenoh endpoint) cannot be opened."""


class ConfigError(HostError):
    """The host configuration or command line is wrong."""


class SinkError(HostError):
    """The Rerun sink cannot be set up (viewer not spawnable, bad address)."""


class SlamError(HostError):
    """A message SLAM cannot use (too few ranges, no odometry, stamps going back); each kind
    is warned about once per robot and topic (host_bridge/slam/feeder.py)."""


class SparseScanError(SlamError):
    """A scan with too few valid ranges to match or map."""


class StampBackwardsError(SlamError):
    """A scan stamped no later than one already mapped."""


class NoOdometryError(SlamError):
    """A robot sends no odometry: SLAM matches scans alone."""


class NoLaserTransformError(SlamError):
    """Nothing places the laser frame on the robot's base."""


class OdometryJumpError(SlamError):
    """Odometry reset or jumped: a new trajectory segment starts."""


class SlamBehindError(SlamError):
    """Live scans skipped because SLAM runs slower than they come."""


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
