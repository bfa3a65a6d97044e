"""Stamps, QoS presets and the /diagnostics drop counter."""

from __future__ import annotations

import time

import pytest
import rclpy
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
from std_msgs.msg import Float32

from endo_io.diagnostics import InputHealth
from endo_io.errors import Endo3dError, ImageEncodingError
from endo_io.qos import SENSOR_DATA_QOS, create_reliable_publisher, reliable_qos
from endo_io.stamp import ns_to_stamp, stamp_to_ns


def test_stamp_round_trip_is_exact_for_large_epoch_times():
    ns = 1_763_800_000_123_456_789
    stamp = ns_to_stamp(ns)
    assert (stamp.sec, stamp.nanosec) == (1_763_800_000, 123_456_789)
    assert stamp_to_ns(stamp) == ns
    assert stamp_to_ns(Time(sec=3, nanosec=5)) == 3_000_000_005
    with pytest.raises(ValueError, match="non-negative"):
        ns_to_stamp(-1)


def test_qos_presets_follow_rep_2003():
    assert SENSOR_DATA_QOS.reliability == ReliabilityPolicy.BEST_EFFORT
    assert SENSOR_DATA_QOS.depth == 5
    profile = reliable_qos(7)
    assert profile.reliability == ReliabilityPolicy.RELIABLE
    assert profile.depth == 7
    assert profile.durability == DurabilityPolicy.VOLATILE
    assert reliable_qos(latched=True).durability == DurabilityPolicy.TRANSIENT_LOCAL


@pytest.fixture
def node():
    rclpy.init()
    node = Node("health_under_test")
    yield node
    node.destroy_node()
    rclpy.shutdown()


def test_publisher_qos_can_be_overridden_by_parameter():
    rclpy.init()
    try:
        node = Node(
            "qos_override_under_test",
            parameter_overrides=[
                rclpy.parameter.Parameter(
                    "qos_overrides./out.publisher.reliability",
                    value="best_effort",
                )
            ],
        )
        publisher = create_reliable_publisher(node, Float32, "/out", depth=3)
        assert publisher.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
        assert publisher.qos_profile.depth == 3
        node.destroy_node()
    finally:
        rclpy.shutdown()


def test_guard_drops_bad_messages_counts_them_and_keeps_going(node):
    health = InputHealth(node, "image input", period_s=0.05)
    seen: list[int] = []

    @health.guard
    def callback(value: int) -> int:
        if value == 1:
            raise ImageEncodingError("image encoding 'yuv422' is not supported")
        if value == 2:
            raise ZeroDivisionError("division by zero")
        seen.append(value)
        return value

    assert [callback(v) for v in (0, 1, 2, 3, 1)] == [0, None, None, 3, None]
    assert seen == [0, 3]
    assert health.processed == 2
    assert health.dropped == {"ImageEncodingError": 2, "ZeroDivisionError": 1}
    status = health.status()
    assert status.level == DiagnosticStatus.WARN
    assert status.name == "health_under_test: image input"
    values = {kv.key: kv.value for kv in status.values}
    assert values["processed"] == "2"
    assert values["dropped"] == "3"
    assert values["dropped.ImageEncodingError"] == "2"
    assert "yuv422" in status.message or "division" in status.message
    assert issubclass(ImageEncodingError, Endo3dError)


def test_status_is_published_on_diagnostics(node):
    health = InputHealth(node, "input", period_s=0.05)
    health.ok()
    health.set_value("latency_ms", 3.5)
    received: list[DiagnosticArray] = []
    node.create_subscription(DiagnosticArray, "/diagnostics", received.append, 10)
    deadline = time.monotonic() + 10.0
    while not received and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
    assert received, "no /diagnostics message within 10 s"
    status = received[-1].status[0]
    assert status.level == DiagnosticStatus.OK
    values = {kv.key: kv.value for kv in status.values}
    assert values["processed"] == "1"
    assert values["latency_ms"] == "3.5"


def test_run_node_help_lists_declared_parameters_and_exits(capsys):
    from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor

    from endo_io.process import run_node

    class GainNode(Node):
        def __init__(self) -> None:
            super().__init__("gain_under_test")
            self.declare_parameter(
                "gain",
                2.0,
                ParameterDescriptor(
                    description="multiplies every pixel",
                    floating_point_range=[FloatingPointRange(from_value=0.0, to_value=8.0)],
                ),
            )

    assert run_node(GainNode, ["gain-node", "--help"]) == 0
    out = capsys.readouterr().out
    assert "usage: gain-node [--ros-args" in out
    assert "gain (default 2.0 [0.0, 8.0]): multiplies every pixel" in out
    assert not rclpy.ok()  # the help path leaves no context running


def test_run_node_takes_a_shutdown_inside_spin_for_the_shutdown_it_is(monkeypatch):
    # SIGINT's handler shut the context down while spin() built its next wait
    # set: rclpy raised RCLError, the bridge printed a traceback and exited 1
    # (CI). The race is reproduced here by a spin that does the same.
    import endo_io.process as process

    def spin_into_a_shutdown(self):
        rclpy.try_shutdown()
        raise RuntimeError("failed to initialize wait set: the given context is not valid")

    closed = []

    class ClosingNode(Node):
        exit_code = 0

        def __init__(self) -> None:
            super().__init__("closing_under_test")

        def close(self) -> None:
            closed.append(True)

    monkeypatch.setattr(process.SingleThreadedExecutor, "spin", spin_into_a_shutdown)
    assert process.run_node(ClosingNode, ["closing-node"]) == 0
    assert closed == [True] and not rclpy.ok()

    def spin_into_a_real_error(self):
        raise RuntimeError("a bug while the context is valid")

    monkeypatch.setattr(process.SingleThreadedExecutor, "spin", spin_into_a_real_error)
    with pytest.raises(RuntimeError, match="a bug"):
        process.run_node(ClosingNode, ["closing-node"])
    assert closed == [True, True] and not rclpy.ok()


@pytest.mark.parametrize(("arguments", "reason"), [
    (["--params-file", "{broken}"], "Couldn't parse params file: '--params-file {broken}'. "
     "Error: Sequences can only be values and not keys in params. Error at line 1"),
    (["-r", "bad remap"], "Couldn't parse remap rule: '-r bad remap'. Error: Expected lexeme "
     "type (19) not found, search ended at index 3"),
])  # fmt: skip
def test_ros_arguments_rcl_refuses_are_one_line_and_exit_2(arguments, reason, tmp_path, capsys):
    # `endo-sfs --ros-args --params-file bad.yaml` was an RCLError traceback from rclpy.init.
    from endo_io.process import run_node

    broken = tmp_path / "broken.yaml"
    broken.write_text("a: [1, 2\n")
    argv = [a.format(broken=broken) for a in arguments]
    assert run_node(Node, ["some-node", "--ros-args", *argv]) == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert error == (
        "some-node: cannot start with these ROS arguments: failed to initialize rcl: "
        + reason.format(broken=broken)
    )
    assert not rclpy.ok()


@pytest.mark.timeout(30)
def test_a_sigint_before_rclpy_init_stops_the_node(monkeypatch):
    # `endo-record --all -o x.mcap & sleep 0.15; kill -INT $!`: the SIGINT came while the
    # process set up its transport, before rclpy.init; the shutdown it asked for found no
    # context, and the recorder then ran until a second SIGINT.
    import os
    import signal
    import time

    import endo_io.process as process

    def interrupted_set_up() -> None:
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.5)  # the watcher thread tries its shutdown now, before rclpy.init

    monkeypatch.setattr(process, "prepare_transport", interrupted_set_up)
    # Before, the node was created and spun until the timeout.
    assert process.run_node(lambda: Node("sigint_under_test"), ["some-node"]) == 0
    assert not rclpy.ok()
