"""The graph's ROS parameter file, generated from the nodes' own parameter tables.

``config/endo3d.yaml`` (``src/endo_bringup/config/endo3d.yaml``, installed to
``share/endo_bringup/config``; the repository's ``config/endo3d.yaml`` links
to it) is this module's output: one section per node of
:data:`endo_bringup.graph.NODES`, keyed ``/**/<node name>`` so that it applies
in any namespace, with every row of the node's ``PARAMETERS`` table
(:class:`endo_io.parameters.ParameterSpec`) at its default, its description,
range or choices as a comment above it. ``endo-launch`` and
``launch/endo3d.launch.py`` pass it to every node with ``--params-file``.

An empty list cannot be typed by ROS's YAML parser, so such a parameter is
written commented out (its default applies). Regenerate after changing a
table: ``python -m endo_bringup.params_file src/endo_bringup/config/endo3d.yaml``
(``endo-launch --write-params PATH`` writes the same file);
``tests/test_launch_config.py`` fails while the shipped file differs.
"""

from __future__ import annotations

import importlib
import sys
import textwrap
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml

from endo_bringup.graph import NODES, GraphProcess
from endo_io.parameters import ParameterSpec

HEADER = """\
# endo3d: the parameters of every node of the graph, at their defaults.
# Generated from the nodes' parameter tables by endo_bringup.params_file
# (`endo-launch --write-params PATH` writes this file); edit a copy and pass it
# to every node: `endo-launch live --params my.yaml`, `ros2 launch
# launch/endo3d.launch.py params_file:=my.yaml`, or one node:
# `endo-sfs --ros-args --params-file my.yaml`. Keys `/**/<node>` match the node
# in any namespace. Each node's `--help` lists the same parameters.
"""


def node_parameters(node: GraphProcess) -> tuple[ParameterSpec, ...]:
    """The parameter table of ``node``: ``PARAMETERS`` of its package's ``node`` module."""
    module = importlib.import_module(f"{node.package}.node")
    return tuple(module.PARAMETERS)


def _value(value: Any) -> str:
    text = yaml.safe_dump(value, default_flow_style=True, width=10_000, allow_unicode=True)
    return text.removesuffix("\n...\n").strip()


def _comment(spec: ParameterSpec) -> list[str]:
    text = spec.description
    if spec.constraints:
        text += f" ({spec.constraints})"
    if spec.read_only:
        text += " (read-only: fixed at start-up)"
    return textwrap.wrap(text, width=84, initial_indent="    # ", subsequent_indent="    # ")


def render(nodes: Sequence[GraphProcess] = NODES) -> str:
    """The parameter file's text for ``nodes``."""
    lines = [HEADER]
    for node in nodes:
        lines.append(f"# {node.executable} (package {node.package})")
        lines.append(f"/**/{node.node_name}:")
        lines.append("  ros__parameters:")
        for spec in node_parameters(node):
            lines += _comment(spec)
            entry = f"{spec.name}: {_value(spec.default)}"
            empty = isinstance(spec.default, list | tuple) and not spec.default
            lines.append(("    # " if empty else "    ") + entry)
        lines.append("")
    return "\n".join(lines)


def write(path: Path) -> Path:
    """Write :func:`render`'s text to ``path``."""
    path.write_text(render(), encoding="utf-8")
    return path


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m endo_bringup.params_file PATH``: write the parameter file."""
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) != 1:
        print("usage: python -m endo_bringup.params_file PATH", file=sys.stderr)
        return 2
    print(write(Path(args[0])))
    return 0


if __name__ == "__main__":
    sys.exit(main())
