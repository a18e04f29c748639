"""Errors of the robot side; each message says what was wrong, where, and what to do."""

from __future__ import annotations


class RelayError(Exception):
    """Base of every error the relay raises on purpose."""


class WireError(RelayError):
    """A sample or catalog does not follow schemas/wire.md."""


class SourceError(RelayError):
    """A ROS source (bag, rclpy) cannot be opened or read."""


class ConfigError(RelayError):
    """The relay configuration or command line is wrong."""
