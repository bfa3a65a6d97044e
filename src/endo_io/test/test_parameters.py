"""endo_io.parameters: one table declares, validates and applies a node's parameters."""

from __future__ import annotations

import re

import pytest
import rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter

from endo_io.errors import Endo3dError, ParameterValidationError
from endo_io.parameters import NodeParameters, ParameterSpec
from endo_io.process import describe_parameters, run_node

pytestmark = pytest.mark.ros

TABLE = (
    ParameterSpec("gain", 2.0, "multiplies every pixel", range=(0.0, 8.0)),
    ParameterSpec("taps", 3, "filter length, pixels", range=(1, 9)),
    ParameterSpec("mode", "fast", "how to filter", choices=("fast", "exact")),
    ParameterSpec("label", "scope", "name in diagnostics"),
    ParameterSpec("enabled", True, "filter at all"),
    ParameterSpec("matrix", [1.0, 0.0], "two numbers", range=(-5.0, 5.0)),
    ParameterSpec("queue", 4, "fixed at start-up", range=(1, 10), read_only=True),
)


class FilterNode(Node):
    """A node with the table above; 'gain' above 'taps' is refused by its apply callback."""

    def __init__(self, **kwargs: object) -> None:
        super().__init__("filter_under_test", **kwargs)  # type: ignore[arg-type]
        self.parameters = NodeParameters(self, TABLE)
        self.applied: list[dict[str, object]] = []
        self.parameters.on_change(self._apply)

    def _apply(self, changes, values) -> None:
        if values["gain"] > values["taps"]:
            raise Endo3dError(f"gain {values['gain']} must not exceed taps {values['taps']}")
        self.applied.append(dict(changes))


@pytest.fixture
def context():
    rclpy.init()
    yield
    rclpy.shutdown()


def _node(**overrides: object) -> FilterNode:
    return FilterNode(
        parameter_overrides=[Parameter(name, value=value) for name, value in overrides.items()]
    )


def test_start_up_values_are_converted_and_checked(context):
    node = _node(gain=1, matrix=[1, 2], label=7)
    assert node.parameters["gain"] == 1.0 and isinstance(node.parameters["gain"], float)
    assert node.get_parameter("gain").type_ == Parameter.Type.DOUBLE
    assert node.parameters["matrix"] == [1.0, 2.0]
    assert node.get_parameter("matrix").type_ == Parameter.Type.DOUBLE_ARRAY
    assert node.parameters["label"] == "7"
    descriptor = node.describe_parameter("gain")
    assert descriptor.floating_point_range[0].to_value == 8.0 and not descriptor.dynamic_typing
    assert node.describe_parameter("mode").additional_constraints == "one of: fast, exact"
    assert node.describe_parameter("queue").read_only
    node.destroy_node()


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"gain": 9.5}, "parameter gain: 9.5 is out of range [0, 8]"),
        ({"gain": "high"}, "parameter gain: expected a number, got 'high'"),
        ({"taps": 2.5}, "parameter taps: expected an integer, got 2.5"),
        ({"mode": "slow"}, "parameter mode: 'slow' is not one of fast, exact"),
        ({"enabled": 1}, "parameter enabled: expected true or false, got 1"),
        ({"matrix": [1.0, 6.0]}, "parameter matrix: [1.0, 6.0] is out of range [-5, 5]"),
    ],
)
def test_a_bad_start_up_value_raises_one_line_naming_it(context, overrides, message):
    with pytest.raises(ParameterValidationError, match=f"^{re.escape(message)}$"):
        _node(**overrides)


def test_run_time_changes_are_converted_validated_and_applied(context):
    node = _node()
    # An integer for a double is taken as that double.
    assert node.set_parameters([Parameter("gain", value=3)])[0].successful
    assert node.parameters["gain"] == 3.0 and node.get_parameter("gain").value == 3.0
    assert node.applied == [{"gain": 3.0}]
    refused = {
        "gain": Parameter("gain", value=8.5),
        "mode": Parameter("mode", value="slow"),
        "queue": Parameter("queue", value=5),
        "apply": Parameter("gain", value=4.0),  # above taps: the node's own rule
    }
    refused_taps = node.set_parameters([Parameter("taps", value=2)])[0]
    assert not refused_taps.successful and "must not exceed taps 2" in refused_taps.reason
    for key, parameter in refused.items():
        result = node.set_parameters([parameter])[0]
        assert not result.successful, key
        assert result.reason
    assert "one of fast, exact" in node.set_parameters(
        [Parameter("mode", value="slow")]
    )[0].reason
    assert "read-only" in node.set_parameters([Parameter("queue", value=5)])[0].reason
    # Nothing refused changed anything.
    assert node.parameters.values() == {**{s.name: s.default for s in TABLE}, "gain": 3.0}
    assert node.get_parameter("mode").value == "fast" and node.get_parameter("taps").value == 3
    assert node.applied == [{"gain": 3.0}]
    # Several at once are applied together, checked against each other.
    assert node.set_parameters_atomically(
        [Parameter("taps", value=8), Parameter("gain", value=6)]
    ).successful
    assert node.applied[-1] == {"taps": 8, "gain": 6.0}
    node.destroy_node()


def test_parameters_outside_the_table_are_left_to_rclpy(context):
    from std_msgs.msg import Float32

    from endo_io.qos import create_reliable_publisher

    node = _node()
    create_reliable_publisher(node, Float32, "/filtered")  # declares qos_overrides.* parameters
    assert node.applied == []
    node.destroy_node()


def test_help_shows_ranges_choices_and_read_only(capsys):
    assert run_node(FilterNode, ["filter", "--help"]) == 0
    out = capsys.readouterr().out
    assert "gain (default 2.0 [0.0, 8.0]): multiplies every pixel" in out
    assert "mode (default 'fast', one of: fast, exact): how to filter" in out
    assert "queue (default 4 [1, 10], read-only): fixed at start-up" in out


def test_run_node_turns_a_bad_value_into_one_line_and_exit_code_2(capsys):
    code = run_node(FilterNode, ["filter", "--ros-args", "-p", "mode:=slow"])
    assert code == 2
    err = capsys.readouterr().err
    assert err == "filter: parameter mode: 'slow' is not one of fast, exact\n"
    assert not rclpy.ok()


def test_a_table_whose_default_is_invalid_is_a_programming_error():
    with pytest.raises(ParameterValidationError):
        ParameterSpec("gain", 9.0, "too high a default", range=(0.0, 8.0))
    with pytest.raises(ValueError, match="range needs a number"):
        ParameterSpec("mode", "fast", "a string", range=(0.0, 1.0))


def test_describe_parameters_lists_only_the_table(context):
    node = _node()
    text = describe_parameters(node)
    assert text.count("\n") == len(TABLE) - 1 and "use_sim_time" not in text
    node.destroy_node()


def test_a_near_miss_of_a_parameter_name_is_refused_naming_the_right_one(context):
    with pytest.raises(ParameterValidationError) as caught:
        _node(gian=1.5)
    message = str(caught.value)
    assert "\n" not in message
    assert message == "parameter gian: filter_under_test has no such parameter (did you mean gain?)"


def test_a_foreign_parameter_is_ignored_with_one_warning(context, capfd):
    # A '/**' section shared by every node carries other nodes' parameters.
    node = _node(solve_scale=0.5, gain=1.0)
    assert node.parameters["gain"] == 1.0
    assert not node.has_parameter("solve_scale")
    warnings = [line for line in capfd.readouterr().err.splitlines() if "ignoring" in line]
    assert len(warnings) == 1 and "solve_scale" in warnings[0]
    node.destroy_node()


def test_run_node_turns_a_typo_into_one_line_and_exit_code_2(capsys):
    code = run_node(FilterNode, ["filter", "--ros-args", "-p", "tapz:=3"])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "tapz" in err[0] and "did you mean taps?" in err[0]


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"gain": 9.5}, "parameter gain: 9.5 is out of range [0, 8]"),
        ({"mode": "slow"}, "parameter mode: 'slow' is not one of fast, exact"),
        ({"gian": 1.5}, "parameter gian: filter_under_test has no such parameter "
                        "(did you mean gain?)"),
    ],
)
def test_start_values_are_checked_without_a_node_as_the_node_checks_them(
    context, overrides, message
):
    # endo-launch checks every node's configuration before starting anything.
    from endo_io.parameters import check_start_values

    with pytest.raises(ParameterValidationError, match=f"^{re.escape(message)}$"):
        _node(**overrides)
    with pytest.raises(ParameterValidationError, match=f"^{re.escape(message)}$"):
        check_start_values(TABLE, overrides, "filter_under_test")
    values = check_start_values(TABLE, {"gain": 1, "solve_scale": 0.5, "use_sim_time": True},
                                "filter_under_test")  # fmt: skip
    assert values["gain"] == 1.0 and isinstance(values["gain"], float) and values["taps"] == 3


def test_file_overrides_apply_the_sections_rcl_applies_to_the_node():
    from endo_io.parameters import file_overrides

    document = {
        "/**": {"ros__parameters": {"a": 1, "b": 1}},
        "/**/filter": {"ros__parameters": {"b": 2, "qos": {"depth": 5}}},
        "filter": {"ros__parameters": {"c": 3}},
        "/rig1/filter": {"ros__parameters": {"d": 4}},
        "/*/filter": {"ros__parameters": {"e": 5}},
        "other": {"ros__parameters": {"f": 6}},
    }
    assert file_overrides(document, "filter") == {"a": 1, "b": 2, "qos.depth": 5, "c": 3}
    assert file_overrides(document, "filter", "/rig1") == {
        "a": 1, "b": 2, "qos.depth": 5, "d": 4, "e": 5
    }
    assert file_overrides("just a string", "filter") == {}


def test_sections_for_no_node_are_listed_and_a_misspelt_node_refused():
    from endo_io.errors import ParameterValidationError
    from endo_io.parameters import section_applies, sections_for_no_node

    fqns = ["/sfs", "/flow"]
    assert [section_applies(key, "/sfs") for key in ("/**", "/**/sfs", "sfs", "/sfs", "/*")] == [
        True] * 5
    assert not section_applies("/rig1/sfs", "/sfs") and section_applies("/rig1/sfs", "/rig1/sfs")
    document = {
        "/**": {"ros__parameters": {}},
        "/**/sfs": {"ros__parameters": {}},
        "/rig1/sfs": {"ros__parameters": {}},  # another namespace's
        "v4l2_camera": {"ros__parameters": {}},  # the camera driver's, in a shared file
    }
    assert sections_for_no_node(document, fqns) == ["/rig1/sfs", "v4l2_camera"]
    assert sections_for_no_node(document, ["/rig1/sfs", "/rig1/flow"]) == ["v4l2_camera"]
    assert sections_for_no_node("just a string", fqns) == []
    # rcl ignores these without a word; a near miss of a node's name is a typo
    for key, node in (("/**/sfss", "sfs"), ("flw", "flow"), ("/rig1/folw", "flow")):
        with pytest.raises(ParameterValidationError) as caught:
            sections_for_no_node({key: {"ros__parameters": {}}}, fqns)
        assert str(caught.value) == (
            f"section {key} of the parameter file applies to no node (did you mean {node}?)")
