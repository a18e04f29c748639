"""Who imports whom, read from the source (AST), not by importing it.

- The host's modules import each other without a cycle, at module level, inside functions (how
  a module defers a heavy dependency) or under ``TYPE_CHECKING`` alike, and only from their own
  layer or the ones below it (:data:`LAYERS`).
- The robot side imports nothing from the host (ruff's banned-api rule TID251 says the same for
  the linter), and at module level only the standard library and its ``[relay]`` extra: it runs
  on a Pi with Python 3.10 and none of the host's packages.
- The host imports from the robot side only the modules in :data:`HOST_MAY_IMPORT`, each with
  its reason.
- The type table's module imports no converter at module level: the command line imports it
  and must start without them. Its ``Lazy("laser", "SPEC")`` rows count as imports of the
  converter module (``host_bridge.converters.laser``) made inside a function.
- Only ``host_bridge/core/rerun_private.py`` uses Rerun's private API (:data:`RERUN_PRIVATE_NAMES`).
"""

from __future__ import annotations

import ast
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("robot_relay", "host_bridge")

# robot_relay module -> (importers allowed, why the host needs it).
HOST_MAY_IMPORT: dict[str, tuple[str, str]] = {
    "robot_relay.wire": ("host_bridge", "the protocol both sides speak"),
    "robot_relay.session": ("host_bridge", "Zenoh flags and session opening, alike on both commands"),
    "robot_relay.sources.bag": ("host_bridge", "--bag reads bags with the source the relay replays"),
    "robot_relay.errors": (
        "host_bridge", "caught where the host calls the modules above: wire and graph errors "
        "become input problems (warned about under their own names), the others host errors "
        "(errors.relay_errors, inputs/bag.py); the host's command line catches HostError only",
    ),
    "robot_relay.configfile": (
        "host_bridge", "both config files load alike: line-numbered errors, topic-glob precedence",
    ),
    "robot_relay.files": ("host_bridge", "--package-path NAME=DIR is parsed alike on both commands"),
    "robot_relay.signals": (
        "host_bridge.cli", "SIGINT and SIGTERM stop both commands alike: the first cleanly, a second at once",
    ),
    "robot_relay.relay": ("host_bridge.demo", "the demo is a simulated robot: it runs a relay"),
    "robot_relay.heap": (
        "host_bridge.cli", "--bag: large chunks and messages reuse freed heap, as in the live relay",
    ),
    "robot_relay.policy": (
        "host_bridge.table.registry", "a row names the relay's traffic class of its type (TrafficClass), "
        "checked against the relay's own table",
    ),
    "robot_relay.sources.mcap": (
        "host_bridge", "--bag reads an indexed MCAP with the bulk reader the relay replays it with",
    ),
    "robot_relay.sources.sqlite": (
        "host_bridge.inputs.rows_ahead", "--bag hands the sqlite3 bulk reader the rows its own "
        "process fetched ahead",
    ),
    "robot_relay.sources.sqlite_rows": (
        "host_bridge.inputs.rows_ahead", "the rows' frames, as the process fetching them writes them",
    ),
}
# The host's layers, lowest first: a module imports from its own layer and the ones below only
# (at module level, inside functions and for type checking alike). A module is in the layer of
# the longest prefix naming it.
LAYERS: list[tuple[str, list[str]]] = [
    ("errors", ["host_bridge.errors"]),
    ("core: records, contract, decoding, frame names", ["host_bridge.core"]),
    ("converters", ["host_bridge.converters"]),
    ("slam", ["host_bridge.slam"]),
    ("the type table and the configuration", ["host_bridge.table"]),
    ("inputs", ["host_bridge.inputs"]),
    ("outputs", ["host_bridge.outputs"]),
    ("pipeline", ["host_bridge.pipeline"]),
    ("app", ["host_bridge", "host_bridge.app", "host_bridge.cli", "host_bridge.listing",
             "host_bridge.demo"]),
]
# The [relay] extra (pyproject.toml); rclpy and rosbags are imported inside the sources' functions.
RELAY_THIRD_PARTY = {"zenoh", "yaml", "jsonschema"}
# Robot-side modules of the [bag] extra (rosbags, which brings numpy), with what they import at
# module level beyond [relay]: the other robot modules import them inside functions only, so a
# relay installed without [bag] never loads them (the sqlite3 bulk reader hands on the MCAP one's runs).
# sqlite.py: rosbags too, whose sqlite3 reader it opens without counting rows; mcap_stream.py:
# rosbags' connections and zstandard (in [bag] for it); rosbag2.py:
# rosbags' reader and the YAML parser it reads metadata.yaml with.
BAG_MODULES = {
    "robot_relay.sources.mcap": {"numpy"}, "robot_relay.sources.sqlite": {"numpy", "rosbags"},
    "robot_relay.sources.mcap_stream": {"rosbags", "zstandard"},
    "robot_relay.sources.rosbag2": {"rosbags", "ruamel"},
}


@dataclass(frozen=True, slots=True)
class Import:
    importer: str
    imported: str
    line: int
    when: Literal["module", "function", "typing"]
    """``module``: runs when the importer is imported; ``function``: when a function of it is
    called; ``typing``: never (under ``if TYPE_CHECKING:``)."""

    @property
    def module_level(self) -> bool:
        return self.when == "module"


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def is_module(name: str) -> bool:
    path = ROOT.joinpath(*name.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def imported_modules(node: ast.Import | ast.ImportFrom, importer: str, package: bool) -> list[str]:
    """Full module names an import statement loads: ``from a.b import c`` is ``a.b.c`` when that
    is a module of ours, else ``a.b``."""
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names]
    base = node.module or ""
    if node.level:
        parent = importer.split(".")[: len(importer.split(".")) - node.level + package]
        base = ".".join([*parent, *([base] if base else [])])
    submodules = [f"{base}.{a.name}" for a in node.names if is_module(f"{base}.{a.name}")]
    return submodules or [base]


def lazy_converter(node: ast.AST) -> ast.Call | None:
    """A ``Lazy("module", "NAME")`` of the type table, which imports the converter module on
    first use (:func:`lazy_module`), else None."""
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "Lazy":
        return node
    return None


def lazy_module(call: ast.Call) -> str:
    module = call.args[0].value if call.args and isinstance(call.args[0], ast.Constant) else None
    assert isinstance(module, str), ast.unparse(call)  # a name the scan can read
    return f"host_bridge.converters.{module}"


def imports_of(path: Path) -> list[Import]:
    importer = module_name(path)
    package = path.name == "__init__.py"
    found: list[Import] = []

    def visit(node: ast.AST, when: Literal["module", "function", "typing"]) -> None:
        for child in ast.iter_child_nodes(node):
            inner = when
            if isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                inner = "typing"
            elif when == "module" and isinstance(
                child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)
            ):
                inner = "function"
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                found.extend(
                    Import(importer, name, child.lineno, when)
                    for name in imported_modules(child, importer, package)
                )
            elif lazy := lazy_converter(child):
                # The type table's Lazy("laser", "SPEC") imports converters.laser when called.
                found.append(Import(importer, lazy_module(lazy), lazy.lineno, "function"))
            visit(child, inner)

    visit(ast.parse(path.read_text(), str(path)), "module")
    return found


ALL_IMPORTS = [i for pkg in PACKAGES for path in sorted((ROOT / pkg).rglob("*.py"))
               for i in imports_of(path)]


def where(i: Import) -> str:
    return f"{i.importer.replace('.', '/')}.py:{i.line}: {i.imported}"


def in_package(name: str, package: str) -> bool:
    return name == package or name.startswith(package + ".")


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (or a self-import), by
    Tarjan's algorithm."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def connect(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for nxt in sorted(edges.get(node, ())):
            if nxt not in index:
                connect(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                component.append(member)
                if member == node:
                    break
            if len(component) > 1 or node in edges.get(node, ()):
                found.append(sorted(component))

    for node in sorted(edges):
        if node not in index:
            connect(node)
    return found


def test_the_imports_are_found() -> None:
    """The scan itself: known imports of each kind are seen as what they are."""
    seen = {(i.importer, i.imported, i.when) for i in ALL_IMPORTS}
    assert ("host_bridge.outputs.blueprint", "host_bridge.table.registry", "module") in seen
    assert ("host_bridge.table.registry", "host_bridge.converters.laser", "function") in seen
    assert ("host_bridge.outputs.stats", "host_bridge.outputs.sink", "typing") in seen
    assert ("host_bridge.pipeline.dispatch", "robot_relay.wire", "module") in seen


def host_graph(*when: str) -> dict[str, set[str]]:
    edges: dict[str, set[str]] = {}
    for i in ALL_IMPORTS:
        if i.when in when and in_package(i.importer, "host_bridge") and in_package(
            i.imported, "host_bridge"
        ):
            edges.setdefault(i.importer, set()).add(i.imported)
    return edges


def test_host_modules_import_each_other_without_a_cycle() -> None:
    assert cycles(host_graph("module", "function", "typing")) == []


def layer_of(module: str) -> int:
    """Index in :data:`LAYERS` of the longest prefix naming ``module``."""
    ranked = [(len(prefix), index) for index, (_, prefixes) in enumerate(LAYERS)
              for prefix in prefixes if in_package(module, prefix)]
    assert ranked, f"{module} is in no layer of LAYERS; add it to one"
    return max(ranked)[1]


def test_host_modules_import_only_their_layer_and_the_ones_below() -> None:
    upward = [
        f"{where(i)} ({LAYERS[layer_of(i.importer)][0]} -> {LAYERS[layer_of(i.imported)][0]})"
        for i in ALL_IMPORTS
        if in_package(i.importer, "host_bridge") and in_package(i.imported, "host_bridge")
        and layer_of(i.imported) > layer_of(i.importer)
    ]
    assert upward == []


def test_the_layer_check_sees_an_upward_import() -> None:
    assert layer_of("host_bridge.converters.laser") > layer_of("host_bridge.core.contract")
    assert layer_of("host_bridge.pipeline.dispatch") > layer_of("host_bridge.outputs.sink")


def test_cycle_finder_finds_a_cycle() -> None:
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"a"}}) == [["a"]]


def test_robot_side_imports_nothing_of_the_host() -> None:
    relay = [i for i in ALL_IMPORTS if in_package(i.importer, "robot_relay")]
    assert [where(i) for i in relay if in_package(i.imported, "host_bridge")] == []


def test_robot_side_imports_only_its_extra_at_module_level() -> None:
    relay = [i for i in ALL_IMPORTS if in_package(i.importer, "robot_relay") and i.module_level]
    others = [
        where(i) for i in relay
        if i.imported.split(".")[0] not in {
            *sys.stdlib_module_names, *RELAY_THIRD_PARTY, "robot_relay", *BAG_MODULES.get(i.importer, ())
        }
    ]
    assert others == []
    # ... and the [bag] modules are loaded at module level by none but each other.
    assert [where(i) for i in relay if i.imported in BAG_MODULES and i.importer not in BAG_MODULES] == []


def test_host_imports_only_the_robot_modules_it_is_allowed() -> None:
    host = [i for i in ALL_IMPORTS if in_package(i.importer, "host_bridge")]
    outside = [
        where(i) for i in host
        if in_package(i.imported, "robot_relay")
        and not (i.imported in HOST_MAY_IMPORT
                 and in_package(i.importer, HOST_MAY_IMPORT[i.imported][0]))
    ]
    assert outside == []
    used = {i.imported for i in host if in_package(i.imported, "robot_relay")}
    assert sorted(set(HOST_MAY_IMPORT) - used) == []  # the list holds nothing stale


def test_the_type_table_imports_no_converter_at_module_level() -> None:
    table = [i for i in ALL_IMPORTS if i.importer == "host_bridge.table.registry" and i.module_level]
    assert [where(i) for i in table if in_package(i.imported, "host_bridge.converters")] == []


# Rerun's private API: its native module, its private modules (``rerun._log``), and the private or
# undocumented attributes Swanky has used. Only RERUN_PRIVATE may use them (its docstring says why
# each, and tests/host_bridge/test_rerun_private.py checks them on the installed Rerun).
RERUN_PRIVATE = "host_bridge.core.rerun_private"
RERUN_PRIVATE_NAMES = frozenset({"to_native", "component_batch", "_offsets"})
CHECKED_FOR_RERUN = ("host_bridge", "robot_relay", "benchmarks", "scripts", "tests")


def rerun_private_uses(path: Path) -> list[str]:
    """Where ``path`` imports ``rerun_bindings`` or a private module of ``rerun``, reads an
    attribute of :data:`RERUN_PRIVATE_NAMES` or a private one of ``rr``/``rerun``."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and not node.level:
            names = [node.module or ""]
        private_import = any(
            name.split(".")[0] == "rerun_bindings"
            or (name.split(".")[0] == "rerun" and any(part.startswith("_") for part in name.split(".")))
            for name in names
        )
        private_attribute = isinstance(node, ast.Attribute) and (
            node.attr in RERUN_PRIVATE_NAMES
            or (node.attr.startswith("_") and not node.attr.endswith("__")
                and isinstance(node.value, ast.Name) and node.value.id in {"rr", "rerun"})
        )
        by_name = (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
                   and node.func.id in {"getattr", "setattr", "hasattr"}
                   and any(isinstance(arg, ast.Constant) and arg.value in RERUN_PRIVATE_NAMES
                           for arg in node.args))
        if private_import or private_attribute or by_name:
            where = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path
            found.append(f"{where}:{getattr(node, 'lineno', 0)}: {ast.unparse(node)[:80]}")
    return found


def test_only_rerun_private_uses_rerun_private_api() -> None:
    allowed = ROOT.joinpath(*RERUN_PRIVATE.split(".")).with_suffix(".py")
    uses = {path: rerun_private_uses(path) for folder in CHECKED_FOR_RERUN
            for path in sorted((ROOT / folder).rglob("*.py"))}
    assert uses.pop(allowed), "the scan no longer sees rerun_private.py's own private calls"
    assert [use for found in uses.values() for use in found] == []


def test_the_rerun_scan_sees_each_kind_of_private_use(tmp_path: Path) -> None:
    path = tmp_path / "probe.py"
    path.write_text(
        "import rerun_bindings\nfrom rerun._log import log\nimport rerun as rr\n"
        "a = stream.to_native()\nb = column.component_batch\nc = rr._send_columns\n"
        "d = getattr(column, '_offsets')\ne = rr.log\nf = rr.ComponentColumn\ng = rr.__version__\n"
    )
    assert sorted(use.split(": ", 1)[1] for use in rerun_private_uses(path)) == [
        "column.component_batch", "from rerun._log import log", "getattr(column, '_offsets')",
        "import rerun_bindings", "rr._send_columns", "stream.to_native",
    ]


def test_every_package_is_installed_by_a_non_editable_install() -> None:
    """pyproject.toml lists the packages setuptools installs: a folder missing there is missing
    from ``pip install .`` (the README's demo command), though an editable install finds it."""
    if sys.version_info < (3, 11):
        pytest.skip("reads pyproject.toml with Python 3.11's tomllib")
    else:
        import tomllib

        setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
        folders = {
            ".".join(init.parent.relative_to(ROOT).parts)
            for package in PACKAGES for init in (ROOT / package).rglob("__init__.py")
        }
        assert folders == set(setuptools["packages"]) - {"swanky_schemas"}
