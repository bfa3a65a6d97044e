"""What the tree imports: declared in each package.xml, and free of import cycles.

Both tests read the sources (``ast``), without importing them:

* every import of a package's code is an ``exec_depend`` (or ``depend``) of
  its package.xml, and every import of its tests an exec or ``test_depend``:
  endo3d packages and ROS packages by their names, other Python packages by
  their rosdep keys (:data:`ROSDEP_KEYS`). Imports under ``if TYPE_CHECKING:``
  are not needed at run time and do not count here.
* the graph of imports between the tree's modules (src/<package>/<package>),
  counting every import wherever it stands (function bodies and
  ``TYPE_CHECKING`` blocks too: a circle drawn through those is still one
  concept split in two), has no cycle.
"""

from __future__ import annotations

import ast
import functools
import importlib.metadata
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from catkin_pkg.package import parse_package

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = sorted(p.parent.name for p in (ROOT / "src").glob("*/package.xml"))

#: rosdep key of each third-party Python import (the import's top-level name).
#: Keys of packages that are on PyPI only follow rosdep's ``-pip`` convention.
ROSDEP_KEYS = {
    "cv2": "python3-opencv",
    "foxglove": "python3-foxglove-sdk-pip",
    "hypothesis": "python3-hypothesis",
    "llvmlite": "python3-numba",  # numba's code generator, installed with it
    "lz4": "python3-lz4",
    "matplotlib": "python3-matplotlib",
    "mcap": "python3-mcap-pip",
    "mcap_ros2": "python3-mcap-ros2-support-pip",
    "numba": "python3-numba",
    "numpy": "python3-numpy",
    "pyigtl": "python3-pyigtl-pip",
    "pytest": "python3-pytest",
    "rosbags": "python3-rosbags-pip",
    "scipy": "python3-scipy",
    "sksurgerycore": "python3-scikit-surgerycore-pip",
    "sksurgerynditracker": "python3-scikit-surgerynditracker-pip",
    "tqdm": "python3-tqdm",
    "websockets": "python3-websockets",
    "yaml": "python3-yaml",
    "zstandard": "python3-zstandard",
}


@dataclass(frozen=True)
class Import:
    """One imported module name of a source file."""

    module: str  # absolute dotted name, as written (``from a.b import c`` gives a.b)
    names: tuple[str, ...]  # the names a ``from`` import takes (empty for ``import a.b``)
    type_checking: bool  # under ``if TYPE_CHECKING:``
    relative: bool  # ``from . import x``, ``from .m import x``
    line: int


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _imports(path: Path, module: str) -> Iterator[Import]:
    """Every import of one file; relative imports resolved against ``module``."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    package_parts = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]

    def walk(node: ast.AST, type_checking: bool) -> Iterator[Import]:
        for child in ast.iter_child_nodes(node):
            inside = type_checking or (isinstance(child, ast.If) and _is_type_checking(child.test))
            if isinstance(child, ast.Import):
                for alias in child.names:
                    yield Import(alias.name, (), type_checking, False, child.lineno)
            elif isinstance(child, ast.ImportFrom):
                names = tuple(alias.name for alias in child.names)
                if child.level:
                    base = package_parts[: len(package_parts) - child.level + 1]
                    target = ".".join([*base, *([child.module] if child.module else [])])
                else:
                    target = child.module or ""
                yield Import(target, names, type_checking, child.level > 0, child.lineno)
            if isinstance(child, ast.If) and _is_type_checking(child.test):
                for statement in child.body:
                    yield from walk(ast.Module(body=[statement], type_ignores=[]), True)
                for statement in child.orelse:
                    yield from walk(ast.Module(body=[statement], type_ignores=[]), type_checking)
            else:
                yield from walk(child, inside)

    yield from walk(tree, False)


def _modules(package: str) -> dict[str, Path]:
    """Dotted module name → file of every module of a package's code."""
    base = ROOT / "src" / package
    found = {}
    for path in sorted((base / package).rglob("*.py")):
        parts = list(path.relative_to(base).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        found[".".join(parts)] = path
    return found


@functools.cache
def _distributions() -> dict[str, list[str]]:
    return importlib.metadata.packages_distributions()


def _dependency(top: str) -> str | None:
    """The package.xml name of a top-level import, None for the standard library."""
    if top in sys.stdlib_module_names or top == "__future__":
        return None
    if top in PACKAGES:
        return top
    if top in ROSDEP_KEYS:
        return ROSDEP_KEYS[top]
    distributions = _distributions().get(top, [])
    if any(d.startswith("ros-") for d in distributions):
        return top  # a ROS package: its import name is its package name
    raise AssertionError(
        f"import {top!r} (distribution {distributions}) has no rosdep key: add it to ROSDEP_KEYS"
    )


@pytest.mark.parametrize("package", PACKAGES)
def test_every_import_is_declared_in_package_xml(package):
    manifest = parse_package(str(ROOT / "src" / package / "package.xml"))
    run_keys = {d.name for d in (*manifest.exec_depends, *manifest.build_export_depends)}
    test_keys = run_keys | {d.name for d in manifest.test_depends}
    missing = []
    sources = [(m, p, run_keys, "exec_depend") for m, p in _modules(package).items()]
    test_dir = ROOT / "src" / package / "test"
    for path in sorted(test_dir.rglob("*.py")) if test_dir.is_dir() else []:
        sources.append((f"{package}_test.{path.stem}", path, test_keys, "test_depend"))
    for module, path, declared, tag in sources:
        for imported in _imports(path, module):
            if imported.type_checking or imported.relative or not imported.module:
                continue  # relative: the package's own modules (or its test folder's)
            key = _dependency(imported.module.split(".")[0])
            if key is not None and key != package and key not in declared:
                where = f"{path.relative_to(ROOT)}:{imported.line}"
                missing.append(f"<{tag}>{key}</{tag}> (import {imported.module}, {where})")
    assert not missing, f"src/{package}/package.xml lacks:\n" + "\n".join(sorted(set(missing)))


def _import_graph() -> dict[str, set[str]]:
    """Module → the tree's modules it imports."""
    modules: dict[str, Path] = {}
    for package in PACKAGES:
        modules.update(_modules(package))
    graph: dict[str, set[str]] = {name: set() for name in modules}
    for name, path in modules.items():
        for imported in _imports(path, name):
            targets = [f"{imported.module}.{n}" for n in imported.names]
            targets = [t for t in targets if t in modules] or [imported.module]
            graph[name].update(t for t in targets if t in modules and t != name)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []
    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10 * len(graph)))

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for succ in sorted(graph[node]):
            if succ not in index:
                visit(succ)
                low[node] = min(low[node], low[succ])
            elif succ in on_stack:
                low[node] = min(low[node], index[succ])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return components


def test_the_import_graph_of_the_tree_has_no_cycle():
    graph = _import_graph()
    assert "endo_calib.fit" in graph and "endo_io.pose" in graph["endo_io"]
    cycles = _cycles(graph)
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_the_cycle_finder_sees_a_circle():
    graph = {"a.fit": {"a.calibration"}, "a.calibration": {"a.fit"}, "a.cli": {"a.fit"}}
    assert _cycles(graph) == [["a.calibration", "a.fit"]]
