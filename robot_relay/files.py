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

What a relay serves (:func:`serve_files`): the ``--package-path NAME=DIR`` packages, plus the
packages named by every /robot_description the relay forwards (live or from a bag) that are
found under AMENT_PREFIX_PATH. The URDF is not decoded: its CDR payload is scanned for
``package://`` names, before it is published, so a host that asks right away is answered.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING
from urllib.parse import unquote

from robot_relay.errors import ConfigError, RelayError
from robot_relay.wire import RawMessage, files_prefix, files_selector

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger("swanky.relay")

PACKAGE_SCHEME = "package://"
DEFAULT_MAX_BYTES = 64 << 20
"""Larger than any robot mesh we know of; a bigger file is refused rather than sent."""
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


def urdf_package_names(urdf: str) -> set[str]:
    """Packages a URDF names: ``package://<pkg>/`` and ``file://.../share/<pkg>/`` URIs."""
    return set(_PACKAGE_URI.findall(urdf)) | set(_SHARE_PATH.findall(urdf))


def parse_package_path(option: str) -> tuple[str, Path]:
    """Split a ``--package-path NAME=DIR`` option (the host's spelling) into name and directory,
    which must exist: a typo would otherwise only show later as meshes not found."""
    name, sep, directory = option.partition("=")
    if not sep or not name or not directory or "/" in name or name in (".", ".."):
        msg = (
            f"--package-path {option!r} is not NAME=DIR: give the ROS package name, '=', and "
            "the directory holding that package's files (the one with package.xml)"
        )
        raise ConfigError(msg)
    path = Path(directory).expanduser()
    if not path.is_dir():
        nothing = "" if path.exists() else " (nothing is there)"
        msg = f"--package-path {option}: {path} is not a directory{nothing}"
        raise ConfigError(msg)
    return name, path


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
        self._roots: dict[str, Path] = {}
        self._real_roots: dict[str, Path] = {}
        self._max_bytes = max_bytes
        self.add_roots(roots)

    def add_roots(self, roots: Mapping[str, Path]) -> list[str]:
        """Serve more packages (a URDF named them); a package already served keeps its root.

        Returns the packages added. Requests run on Zenoh's threads meanwhile, so the tables
        are replaced, never changed in place, and the resolved one first: a package is never
        seen in ``_roots`` without its entry in ``_real_roots``.
        """
        new = {package: root for package, root in roots.items() if package not in self._roots}
        for package in new:
            if not package or "/" in package or package in (".", ".."):
                msg = f"file server package name {package!r} is not a ROS package name"
                raise ConfigError(msg)
        # Lexical roots to recognise absolute requests; resolved roots to check real paths.
        lexical = {package: Path(os.path.abspath(root)) for package, root in new.items()}
        self._real_roots = {**self._real_roots, **{p: r.resolve() for p, r in lexical.items()}}
        self._roots = {**self._roots, **lexical}
        return sorted(new)

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

    return session.declare_queryable(files_selector(robot), on_query)


def is_robot_description(raw: RawMessage) -> bool:
    """``/robot_description`` or a namespaced one (``/tb1/robot_description``), as a String."""
    return raw.msgtype == "std_msgs/msg/String" and raw.topic.rsplit("/", 1)[-1] == "robot_description"


class FileService:
    """One relay's file server: a :class:`FileServer` answering on Zenoh whose packages grow
    with the URDFs the relay forwards (:meth:`watch`)."""

    def __init__(
        self, session: zenoh.Session, robot: str, server: FileServer, prefixes: Sequence[Path]
    ) -> None:
        self.server = server
        self._prefixes = tuple(prefixes)
        self._unfound: set[str] = set()
        self._queryable = serve(session, robot, server)

    def learn(self, raw: RawMessage) -> None:
        """Serve the packages a /robot_description names, when AMENT_PREFIX_PATH has them."""
        if not is_robot_description(raw):
            return
        # Package names are ASCII inside the CDR string; nothing else of it is looked at.
        names = urdf_package_names(bytes(raw.data).decode("utf-8", errors="replace"))
        added = self.server.add_roots(package_roots(names - set(self.server.packages), self._prefixes))
        if added:
            log.info("%s names packages %s: serving their files", raw.topic, ", ".join(added))
        missing = sorted(names - set(self.server.packages) - self._unfound)
        if missing:
            self._unfound.update(missing)  # a re-sent or looped description says it once
            log.warning(
                "%s names packages %s, which are neither a --package-path nor under "
                "AMENT_PREFIX_PATH: hosts cannot fetch their meshes from this robot",
                raw.topic, ", ".join(missing),
            )

    def watch(self, messages: Iterable[RawMessage]) -> Iterator[RawMessage]:
        """``messages`` unchanged, each learnt from before it is passed on (and published)."""
        for raw in messages:
            self.learn(raw)
            yield raw

    def close(self) -> None:
        self._queryable.undeclare()


def serve_files(
    session: zenoh.Session,
    robot: str,
    package_paths: Sequence[str],
    environ: Mapping[str, str] | None = None,
    max_bytes: int = DEFAULT_MAX_BYTES,
) -> FileService:
    """Start answering ``swanky/<robot>/files/**`` for the ``--package-path NAME=DIR`` options."""
    explicit = dict(parse_package_path(option) for option in package_paths)
    return FileService(session, robot, FileServer(explicit, max_bytes), ament_prefix_paths(environ))
