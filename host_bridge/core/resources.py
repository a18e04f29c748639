"""Find the files a robot model names (``package://``, ``file://``, plain paths) on the PC.

A URDF from a robot names meshes by ROS package or by the robot's own absolute paths; neither
means anything on the PC until it is mapped. The order is: an explicit ``--package-path
NAME=DIR``, then search paths laid out like ``ROS_PACKAGE_PATH`` (``<dir>/<pkg>``) or like an
ament prefix (``<dir>/share/<pkg>``), then ``fetch``, which asks the robot's file server
(robot_relay/files.py; host_bridge/inputs/robot_files.py on this side). A robot-side absolute path
``.../share/<pkg>/<rest>`` (what xacro's ``$(find-pkg-share ...)`` produces) is retried as
``package://<pkg>/<rest>`` when the path does not exist here, so those URDFs resolve the same way.

One resolver serves every robot; :meth:`ResourceResolver.for_robot` binds the fetch to the robot
whose model is being loaded.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path, PurePosixPath
from urllib.parse import unquote

from host_bridge.errors import ConvertError, MissingResourceError, relay_errors
from robot_relay import files

Fetch = Callable[[str], bytes | None]
"""Asks the robot for a ``package://`` URI; returns None when the robot cannot serve it, or
raises ConvertError saying why (refused, no answer)."""
RobotFetch = Callable[[str, str], bytes | None]
"""A :data:`Fetch` for any robot: ``(robot, uri)``."""

PACKAGE_SCHEME = "package://"
FILE_SCHEME = "file://"


def parse_package_path(option: str) -> tuple[str, Path]:
    """Split a ``--package-path NAME=DIR`` option into the package name and its directory
    (the relay's option, spelt and checked the same way)."""
    with relay_errors():
        return files.parse_package_path(option)


def split_package_uri(uri: str) -> tuple[str, str]:
    """``package://pkg/a/b.stl`` -> ``("pkg", "a/b.stl")``."""
    package, _, relpath = uri[len(PACKAGE_SCHEME) :].partition("/")
    if not package or not relpath:
        msg = f"{uri!r} is not package://<package>/<path>"
        raise ConvertError(msg)
    return package, relpath


def package_uri_of_share_path(path: PurePosixPath) -> str | None:
    """``/opt/ros/humble/share/pkg/meshes/a.stl`` -> ``package://pkg/meshes/a.stl``."""
    parts = path.parts
    for i in range(len(parts) - 3, 0, -1):
        if parts[i] == "share":
            return PACKAGE_SCHEME + "/".join(parts[i + 1 :])
    return None


class ResourceResolver:
    """Reads the bytes behind a resource URI from local directories, else from the robot."""

    def __init__(
        self,
        package_paths: Mapping[str, Path] | None = None,
        search_paths: Sequence[Path] = (),
        fetch: Fetch | None = None,
        robot_fetch: RobotFetch | None = None,
    ) -> None:
        self._package_paths = dict(package_paths or {})
        self._search_paths = tuple(search_paths)
        self._fetch = fetch
        self._robot_fetch = robot_fetch

    @classmethod
    def from_env(
        cls, environ: Mapping[str, str] | None = None, fetch: Fetch | None = None
    ) -> ResourceResolver:
        """Search ``ROS_PACKAGE_PATH`` then ``AMENT_PREFIX_PATH``, as a sourced ROS shell would."""
        env = os.environ if environ is None else environ
        dirs = [
            Path(entry)
            for var in ("ROS_PACKAGE_PATH", "AMENT_PREFIX_PATH")
            for entry in env.get(var, "").split(os.pathsep)
            if entry
        ]
        return cls(search_paths=dirs, fetch=fetch)

    @property
    def search_paths(self) -> tuple[Path, ...]:
        return self._search_paths

    def for_robot(self, robot: str) -> ResourceResolver:
        """This resolver, fetching what is missing here from ``robot`` (if robots are asked)."""
        if self._robot_fetch is None:
            return self
        robot_fetch = self._robot_fetch

        def fetch(uri: str) -> bytes | None:
            return robot_fetch(robot, uri)

        return ResourceResolver(self._package_paths, self._search_paths, fetch=fetch)

    def package_dir(self, package: str) -> Path | None:
        explicit = self._package_paths.get(package)
        if explicit is not None:
            return explicit
        for directory in self._search_paths:
            for candidate in (directory / package, directory / "share" / package):
                if candidate.is_dir():
                    return candidate
            if directory.name == package and directory.is_dir():
                return directory
        return None

    def locate(self, uri: str, base: Path | None = None) -> Path | None:
        """Local file behind ``uri``, or None; ``base`` anchors relative paths (the URDF's dir)."""
        if uri.startswith(PACKAGE_SCHEME):
            package, relpath = split_package_uri(uri)
            root = self.package_dir(package)
            path = None if root is None else root / relpath
            return path if path is not None and path.is_file() else None
        path = self._local_path(uri, base)
        if path.is_file():
            return path
        package_uri = package_uri_of_share_path(PurePosixPath(path.as_posix()))
        return None if package_uri is None else self.locate(package_uri)

    def read(self, uri: str, base: Path | None = None) -> bytes:
        path = self.locate(uri, base)
        if path is not None:
            try:
                return path.read_bytes()
            except OSError as err:
                msg = f"{uri}: found at {path} but cannot read it ({err})"
                raise ConvertError(msg) from err
        package_uri = self._as_package_uri(uri, base)
        refusal = None
        if package_uri is not None and self._fetch is not None:
            try:
                data = self._fetch(package_uri)
            except ConvertError as err:
                data, refusal = None, str(err)
            if data is not None:
                return data
        raise self._not_found(uri, package_uri, refusal)

    def _local_path(self, uri: str, base: Path | None) -> Path:
        if uri.startswith(FILE_SCHEME):
            return Path(unquote(uri[len(FILE_SCHEME) :]))
        if "://" in uri:
            msg = f"{uri}: only package://, file:// and plain paths are supported"
            raise ConvertError(msg)
        path = Path(uri)
        return path if path.is_absolute() or base is None else base / path

    def _as_package_uri(self, uri: str, base: Path | None) -> str | None:
        if uri.startswith(PACKAGE_SCHEME):
            return uri
        return package_uri_of_share_path(PurePosixPath(self._local_path(uri, base).as_posix()))

    def _not_found(
        self, uri: str, package_uri: str | None, refusal: str | None
    ) -> MissingResourceError:
        tried = [f"--package-path {name}={path}" for name, path in self._package_paths.items()]
        tried += [f"search path {path}" for path in self._search_paths]
        where = ", ".join(tried) or "no --package-path and no ROS_PACKAGE_PATH/AMENT_PREFIX_PATH"
        if self._fetch is None or package_uri is None:
            robot = "no robot file server to ask"
        else:
            robot = refusal or "the robot did not serve it"
        package = None if package_uri is None else split_package_uri(package_uri)[0]
        return MissingResourceError(uri, f"{where}; {robot}", package)
