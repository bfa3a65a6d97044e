"""launch/endo3d.launch.py agrees with the node table, read without ROS's launch packages.

The pip environment has neither ``launch`` nor ``launch_ros``, so the file is
parsed (``ast``), not run: it must start exactly the nodes of
:data:`endo_bringup.graph.NODES` (package, executable, node name, in order),
give each the ``params_file`` argument as its parameter file and the
namespace, and remap every topic the node uses: the drivers' inputs onto the
``image_topic`` / ``camera_info_topic`` / ``tracker_topic`` arguments, every
other topic into the namespace. Its default parameter file is the shipped
one, from the repository's ``launch/`` and from the package's alike, and
colcon installs both files into ``share/endo_bringup``.
"""

from __future__ import annotations

import ast
import importlib.util
from pathlib import Path

import pytest

from endo_bringup.graph import NODES
from endo_io import topics

ROOT = Path(__file__).resolve().parents[1]
LAUNCH_FILE = ROOT / "launch" / "endo3d.launch.py"
PACKAGE_LAUNCH_FILE = ROOT / "src" / "endo_bringup" / "launch" / "endo3d.launch.py"
#: The drivers' topics and the launch argument each is remapped onto.
INPUTS = {
    topics.IMAGE_RAW: "image_raw",
    topics.CAMERA_INFO: "camera_info",
    topics.TRACKER_POSE: "tracker_pose",
}
ARGUMENTS = {
    "params_file", "namespace", "image_topic", "camera_info_topic", "tracker_topic", "respawn"
}


def _calls(tree: ast.AST, name: str) -> list[ast.Call]:
    return [
        node for node in ast.walk(tree)
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == name
    ]  # fmt: skip


def _keyword(call: ast.Call, name: str) -> ast.expr:
    return next(k.value for k in call.keywords if k.arg == name)


def _launch_configurations(tree: ast.AST) -> dict[str, str]:
    """Local name -> launch argument, for ``x = LaunchConfiguration("arg")``."""
    found = {}
    for node in ast.walk(tree):
        if (isinstance(node, ast.Assign) and isinstance(node.value, ast.Call)
                and isinstance(node.value.func, ast.Name)
                and node.value.func.id == "LaunchConfiguration"):  # fmt: skip
            found[node.targets[0].id] = ast.literal_eval(node.value.args[0])  # type: ignore[attr-defined]
    return found


def test_the_repository_launch_file_is_the_packages():
    assert LAUNCH_FILE.resolve() == PACKAGE_LAUNCH_FILE
    assert (ROOT / "config" / "endo3d.yaml").resolve() == (
        ROOT / "src" / "endo_bringup" / "config" / "endo3d.yaml"
    )


def test_the_launch_file_starts_the_tables_nodes_with_the_params_file_and_remaps():
    tree = ast.parse(LAUNCH_FILE.read_text())
    declared = {ast.literal_eval(c.args[0]) for c in _calls(tree, "DeclareLaunchArgument")}
    assert declared == ARGUMENTS
    configurations = _launch_configurations(tree)
    assert configurations["params_file"] == "params_file"
    assert configurations["namespace"] == "namespace"
    for local, argument in (("image_raw", "image_topic"), ("camera_info", "camera_info_topic"),
                            ("tracker_pose", "tracker_topic")):  # fmt: skip
        assert configurations[local] == argument
    nodes = _calls(tree, "Node")
    assert len(nodes) == len(NODES)
    for call, row in zip(nodes, NODES, strict=True):
        assert ast.literal_eval(_keyword(call, "package")) == row.package
        assert ast.literal_eval(_keyword(call, "executable")) == row.executable
        assert ast.literal_eval(_keyword(call, "name")) == row.node_name
        parameters = _keyword(call, "parameters")
        assert isinstance(parameters, ast.List)
        assert [ast.unparse(e) for e in parameters.elts] == ["params_file"]
        assert ast.unparse(_keyword(call, "namespace")) == "namespace"
        remaps = _keyword(call, "remappings")
        assert isinstance(remaps, ast.List)
        rules = {}
        for pair in remaps.elts:
            assert isinstance(pair, ast.Tuple)
            rules[ast.literal_eval(pair.elts[0])] = ast.unparse(pair.elts[1])
        assert set(rules) == {*row.subscribes, *row.publishes}, row.name
        for topic, target in rules.items():
            expected = INPUTS.get(topic, f"graph({topic!r})")
            assert target.replace('"', "'") == expected, (row.name, topic, target)


def test_the_default_parameter_file_is_the_shipped_one():
    tree = ast.parse(LAUNCH_FILE.read_text())
    default = next(
        n for n in ast.walk(tree)
        if isinstance(n, ast.Assign) and getattr(n.targets[0], "id", "") == "DEFAULT_PARAMS"
    )  # fmt: skip
    text = ast.unparse(default.value)
    assert text == "str(Path(__file__).absolute().parent.parent / 'config' / 'endo3d.yaml')"
    for launch_dir in (LAUNCH_FILE.parent, PACKAGE_LAUNCH_FILE.parent):
        assert (launch_dir.parent / "config" / "endo3d.yaml").is_file()


def test_setup_py_installs_the_launch_file_and_the_parameter_file():
    text = (ROOT / "src" / "endo_bringup" / "setup.py").read_text()
    assert '"/launch", ["launch/endo3d.launch.py"]' in text
    assert '"/config", ["config/endo3d.yaml"]' in text


@pytest.mark.skipif(
    importlib.util.find_spec("launch_ros") is None,
    reason="launch_ros is not installed (pip-only environment); the structure tests above cover it",
)
def test_the_launch_description_builds_where_launch_ros_is_installed():  # pragma: no cover
    spec = importlib.util.spec_from_file_location("endo3d_launch", LAUNCH_FILE)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    description = module.generate_launch_description()
    assert len(description.entities) == len(ARGUMENTS) + len(NODES)
