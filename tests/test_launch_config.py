"""config/endo3d.yaml: every node's parameters, generated from their tables, and it loads.

The shipped file must equal what :mod:`endo_bringup.params_file` renders from
the nodes' ``PARAMETERS`` tables today (so it cannot drift from the code), and
each node of the graph, created with ``--params-file`` in a namespace (as
``endo-launch --namespace`` and the launch file start it), must get every
parameter of its table at the file's value.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import rclpy
import yaml

from endo_bringup.graph import NODES
from endo_bringup.params_file import node_parameters, render

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "config" / "endo3d.yaml"


def test_the_shipped_parameter_file_is_the_generated_one():
    assert SHIPPED.read_text(encoding="utf-8") == render(), (
        "config/endo3d.yaml is out of date: "
        "python -m endo_bringup.params_file src/endo_bringup/config/endo3d.yaml"
    )


def test_every_parameter_of_every_node_is_in_the_file_with_its_description():
    text = SHIPPED.read_text(encoding="utf-8")
    document = yaml.safe_load(text)
    assert set(document) == {f"/**/{node.node_name}" for node in NODES}
    for node in NODES:
        values = document[f"/**/{node.node_name}"]["ros__parameters"]
        for spec in node_parameters(node):
            if isinstance(spec.default, list | tuple) and not spec.default:
                assert f"# {spec.name}: []" in text
                continue
            assert values[spec.name] == spec.default, spec.name
            assert spec.description.split()[0] in text
        assert len(values) >= len(node_parameters(node)) - 1


def _node_classes() -> dict[str, type]:
    from endo_calib.node import PhotometricCorrectionNode
    from endo_flow.node import FlowNode
    from endo_sfs.node import SfsNode
    from endo_tracker_bridge.node import TrackerBridgeNode

    return {
        "photometric_correction": PhotometricCorrectionNode,
        "sfs": SfsNode,
        "tracker_bridge": TrackerBridgeNode,
        "flow": FlowNode,
    }


@pytest.mark.ros
def test_every_node_loads_the_file_in_a_namespace_with_a_users_changes(tmp_path):
    document = yaml.safe_load(SHIPPED.read_text(encoding="utf-8"))
    changed = {"sfs": ("roughness", 0.3), "flow": ("max_tracks", 120),
               "tracker_bridge": ("max_speed_m_s", 1.5),
               "photometric_correction": ("channel", "luminance")}  # fmt: skip
    for name, (key, value) in changed.items():
        document[f"/**/{name}"]["ros__parameters"][key] = value
    users = tmp_path / "my.yaml"
    users.write_text(yaml.safe_dump(document))
    classes = _node_classes()
    context = rclpy.Context()
    rclpy.init(
        args=["test", "--ros-args", "--params-file", str(users), "-r", "__ns:=/rig1"],
        context=context,
    )
    try:
        for node_row in NODES:
            node = classes[node_row.node_name](context=context)
            try:
                assert node.get_fully_qualified_name() == f"/rig1/{node_row.node_name}"
                expected = document[f"/**/{node_row.node_name}"]["ros__parameters"]
                for spec in node_parameters(node_row):
                    got = node.get_parameter(spec.name).value
                    want = expected.get(spec.name, spec.default)
                    if isinstance(want, list | tuple):
                        assert list(got) == pytest.approx(list(want)), spec.name
                    else:
                        assert got == want, spec.name
                key, value = changed[node_row.node_name]
                assert node.get_parameter(key).value == value
            finally:
                close = getattr(node, "close", None)
                if callable(close):
                    close()
                node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


def test_endo_process_reads_the_same_file_with_a_users_changes(tmp_path):
    from endo_process.settings import load_settings

    document = yaml.safe_load(SHIPPED.read_text(encoding="utf-8"))
    document["/**/sfs"]["ros__parameters"]["roughness"] = 0.25
    document["/**/flow"]["ros__parameters"]["max_tracks"] = 77
    users = tmp_path / "my.yaml"
    users.write_text(yaml.safe_dump(document))
    settings = load_settings(users)
    assert settings.sfs["roughness"] == 0.25
    assert settings.flow["max_tracks"] == 77
    assert load_settings(SHIPPED).sfs == load_settings(None).sfs  # the defaults, unchanged
