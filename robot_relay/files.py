"""Read-only file server for the meshes a robot's URDF names (``package://<pkg>/<path>``).

The host cannot load a robot's meshes unless the PC has the robot's ROS packages; this serves
them from the robot, but only from allow-listed package roots: ``<ament prefix>/share/<pkg>`` of
the packages the URDF names (:func:`package_roots`). Nothing outside a root is ever read: no
``..`` in a request, no absolute path outside the roots, no symlink whose target leaves its root
(checked on the fully resolved path), and nothing above ``max_bytes``.

Zenoh key: ``swanky/<robot>/files/<package>/<path>``. A reply carries the file's bytes
(``application/octet-stream``); a refusal is a ``reply_err`` whose text starts with the reason
(``traversal:``, ``outside_roots:``, ``symlink_escape:``, ``too_large:``, ``unknown_package:``,
``not_found:``, ``bad_request:``, ``unreadable:``). Zenoh is imported only by :func:`serve`, so
the path checks run and test without it.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING
from urllib.parse import unquote

from robot_relay.errors import ConfigError, RelayError
from robot_relay.wire import PREFIX, check_robot_name

if TYPE_CHECKING:
    import zenoh

PACKAGE_SCHEME = "package://"
FILE_SCHEME = "file://"
_PACKAGE_URI = re.compile(r"package://([^/\"'\s<>]+)/")
_SHARE_PATH = re.compile(r"file://[^\"'\s<>]*/share/([^/\"'\s<>]+)/")


class FileAccessError(RelayError):
    """A file request was refused; ``reason`` is a stable word the reply starts with.

    Meant for robot_relay/errors.py; it lives here until it moves there.
    """

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


def files_key(robot: str, package: str, relpath: str) -> str:
    return f"{files_prefix(robot)}{package}/{relpath}"


def files_prefix(robot: str) -> str:
    return f"{PREFIX}/{check_robot_name(robot)}/files/"


def urdf_package_names(urdf: str) -> set[str]:
    """Packages a URDF names: ``package://<pkg>/`` and ``file://.../share/<pkg>/`` URIs."""
    return set(_PACKAGE_URI.findall(urdf)) | set(_SHARE_PATH.findall(urdf))


def ament_prefix_paths(environ: Mapping[str, str] | None = None) -> list[Path]:
    env = os.environ if environ is None else environ
    return [Path(entry) for entry in env.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if entry]


def package_roots(package_names: Iterable[str], prefixes: Sequence[Path]) -> dict[str, Path]:
    """``<prefix>/share/<pkg>`` for each package, from the first prefix that has it.

    AMENT_PREFIX_PATH lists overlays first, so the first hit is the package ROS itself would
    use. Packages found nowhere are left out; the server then answers ``unknown_package``.
    """
    roots: dict[str, Path] = {}
    for package in package_names:
        for prefix in prefixes:
            candidate = prefix / "share" / package
            if candidate.is_dir():
                roots[package] = candidate
                break
    return roots


class FileServer:
    """Maps a request to a file inside an allow-listed package root, or refuses it."""

    def __init__(self, roots: Mapping[str, Path], max_bytes: int) -> None:
        if max_bytes <= 0:
            msg = f"file server max_bytes must be positive, got {max_bytes}"
            raise ConfigError(msg)
        for package in roots:
            if not package or "/" in package or package in (".", ".."):
                msg = f"file server package name {package!r} is not a ROS package name"
                raise ConfigError(msg)
        # Lexical roots to recognise absolute requests; resolved roots to check real paths.
        self._roots = {package: Path(os.path.abspath(root)) for package, root in roots.items()}
        self._real_roots = {package: root.resolve() for package, root in self._roots.items()}
        self._max_bytes = max_bytes

    @property
    def packages(self) -> list[str]:
        return sorted(self._roots)

    def resolve(self, request: str) -> Path:
        """Real path of ``package://pkg/path``, ``pkg/path``, ``file:///abs`` or ``/abs``."""
        if "\0" in request:
            raise FileAccessError("bad_request", f"{request!r}: NUL byte in the request")
        if request.startswith(FILE_SCHEME):
            request = unquote(request[len(FILE_SCHEME) :])
        elif request.startswith(PACKAGE_SCHEME):
            request = request[len(PACKAGE_SCHEME) :]
        path = PurePosixPath(request)
        if ".." in path.parts:
            raise FileAccessError("traversal", f"{request!r}: '..' is not allowed in a request")
        package, candidate = self._absolute(path) if path.is_absolute() else self._in_package(request, path)
        real = candidate.resolve()
        if not real.is_relative_to(self._real_roots[package]):
            msg = f"{request!r}: a symlink leads out of package {package!r} (to {real})"
            raise FileAccessError("symlink_escape", msg)
        if not real.is_file():
            raise FileAccessError("not_found", f"{request!r}: no such file in package {package!r}")
        size = real.stat().st_size
        if size > self._max_bytes:
            msg = f"{request!r}: {size} bytes is over the file server limit of {self._max_bytes}"
            raise FileAccessError("too_large", msg)
        return real

    def read(self, request: str) -> bytes:
        path = self.resolve(request)
        try:
            with path.open("rb") as file:
                # Read one byte past the limit: the file may have grown since resolve().
                data = file.read(self._max_bytes + 1)
        except OSError as err:
            raise FileAccessError("unreadable", f"{request!r}: {err}") from err
        if len(data) > self._max_bytes:
            msg = f"{request!r}: over the file server limit of {self._max_bytes} bytes"
            raise FileAccessError("too_large", msg)
        return data

    def _in_package(self, request: str, path: PurePosixPath) -> tuple[str, Path]:
        if len(path.parts) < 2:
            msg = f"{request!r}: ask for <package>/<path to a file>"
            raise FileAccessError("bad_request", msg)
        package = path.parts[0]
        root = self._roots.get(package)
        if root is None:
            msg = f"{request!r}: package {package!r} is not served (served: {self.packages})"
            raise FileAccessError("unknown_package", msg)
        return package, root.joinpath(*path.parts[1:])

    def _absolute(self, path: PurePosixPath) -> tuple[str, Path]:
        for package, root in self._roots.items():
            if Path(path).is_relative_to(root):
                return package, Path(path)
        for package, root in self._real_roots.items():
            if Path(path).is_relative_to(root):
                return package, Path(path)
        msg = f"{str(path)!r}: outside the served package roots"
        raise FileAccessError("outside_roots", msg)


def serve(session: zenoh.Session, robot: str, server: FileServer) -> zenoh.Queryable[None]:
    """Answer ``swanky/<robot>/files/**`` from ``server``; undeclare the result to stop."""
    import zenoh

    prefix = files_prefix(robot)

    def on_query(query: zenoh.Query) -> None:
        key = str(query.key_expr)
        request = key[len(prefix) :]
        if "*" in request or "$" in request:
            query.reply_err("bad_request: ask for one file; wildcards are not served")
            return
        try:
            data = server.read(request)
        except FileAccessError as err:
            query.reply_err(f"{err.reason}: {err}")
            return
        query.reply(query.key_expr, data, encoding=zenoh.Encoding.APPLICATION_OCTET_STREAM)

    return session.declare_queryable(f"{prefix}**", on_query)
