"""Package roots that export their public API without importing it up front.

``from endo_calib import PhotometricCalibration`` should work, but importing
the root must stay cheap: a ROS-free user of ``endo_io.camera`` must not load
rclpy because ``endo_io``'s root also exports the replay node, and the
correction node must not load scipy because ``endo_calib``'s root also exports
the fit. So a root lists its exports once, as imports inside ``if
TYPE_CHECKING:`` (what type checkers and readers see), and calls
:func:`lazy_exports`, which reads that block from the root's own source and
imports each name's module on first access (PEP 562 module ``__getattr__``)::

    from typing import TYPE_CHECKING

    from endo_io.lazy_exports import lazy_exports

    if TYPE_CHECKING:
        from endo_calib.calibration import PhotometricCalibration

    __all__ = ["PhotometricCalibration"]
    __getattr__, __dir__ = lazy_exports(__name__)
"""

from __future__ import annotations

import ast
import importlib
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any


def type_checking_imports(source: str) -> dict[str, str]:
    """Names imported in a module's top-level ``if TYPE_CHECKING:`` blocks.

    Args:
        source: Python source of the module.

    Returns:
        Exported name (the alias, when one is given) → ``"module:attribute"``.
        Only absolute ``from X import Y`` imports count.
    """
    exports: dict[str, str] = {}
    for statement in ast.parse(source).body:
        if not (isinstance(statement, ast.If) and _is_type_checking(statement.test)):
            continue
        for node in statement.body:
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                for alias in node.names:
                    exports[alias.asname or alias.name] = f"{node.module}:{alias.name}"
    return exports


def _is_type_checking(test: ast.expr) -> bool:
    if isinstance(test, ast.Name):
        return test.id == "TYPE_CHECKING"
    return isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"


def lazy_exports(
    package: str,
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """Module ``__getattr__`` and ``__dir__`` for a package root's lazy exports.

    Args:
        package: the root's ``__name__``; its source must already be in
            ``sys.modules`` (true while its ``__init__`` runs).

    Returns:
        ``(__getattr__, __dir__)`` to assign at module level. ``__getattr__``
        imports the name's module on first access and caches the value in the
        root, so later accesses are plain attribute lookups.
    """
    module = sys.modules[package]
    origin = module.__file__
    exports = type_checking_imports(Path(origin).read_text(encoding="utf-8")) if origin else {}

    def __getattr__(name: str) -> Any:  # noqa: N807 - the PEP 562 hook's name
        target = exports.get(name)
        if target is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        module_name, attribute = target.split(":")
        if module_name == package:  # ``from <root> import <submodule>``
            value = importlib.import_module(f"{package}.{attribute}")
        else:
            value = getattr(importlib.import_module(module_name), attribute)
        setattr(module, name, value)
        return value

    def __dir__() -> list[str]:  # noqa: N807 - the PEP 562 hook's name
        return sorted(set(vars(module)) | set(exports))

    return __getattr__, __dir__
