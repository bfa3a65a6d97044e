"""SIGINT under ``run_node``: the context shuts down, nothing raises inside the node.

Python's default SIGINT handler raises KeyboardInterrupt at whatever bytecode
runs; one landing in the MCAP writer between a chunk's ``os.write`` and its
byte count left a recording no reader opened (session recdiag). Every node
started by :func:`endo_io.process.run_node` now only shuts its context down:
the callback the signal lands in finishes, and ``close()`` runs whole.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time

import pytest
import rclpy
from rclpy.node import Node

from endo_io.process import run_node

#: How long a test waits for a shutdown before it gives up (a deadline, not a timing).
DEADLINE_S = 10.0


class InterruptedNode(Node):
    """A node whose timer callback and ``close()`` each raise SIGINT part way.

    ``events`` records what ran; "gave up" means SIGINT did not end spin().
    """

    rclpy_handler = "installed"

    def __init__(self) -> None:
        super().__init__("sigint_under_test")
        self.events: list[str] = []
        self.exit_code = 0
        if self.rclpy_handler == "overridden":
            # the kernel calls Python's handler alone, as in the CI worker where
            # rclpy's never shut the context down (earlier tests' state)
            signal.signal(signal.SIGINT, signal.getsignal(signal.SIGINT))
        self.create_timer(0.01, self._tick)
        self._deadline = time.monotonic() + DEADLINE_S

    def _tick(self) -> None:
        if time.monotonic() > self._deadline:
            self.events.append("gave up")
            rclpy.try_shutdown()
            return
        if self.events:
            return
        self.events.append("callback began")
        signal.raise_signal(signal.SIGINT)  # raised KeyboardInterrupt here before
        self.events.append("callback ended")

    def close(self) -> None:
        self.events.append("close began")
        signal.raise_signal(signal.SIGINT)  # a second SIGINT while closing
        self.events.append("close ended")


@pytest.mark.ros
@pytest.mark.parametrize("rclpy_handler", ["installed", "overridden"])
def test_sigint_in_a_callback_lets_it_finish_and_the_node_close(monkeypatch, rclpy_handler):
    monkeypatch.setattr(InterruptedNode, "rclpy_handler", rclpy_handler)
    previous = signal.getsignal(signal.SIGINT)
    nodes: list[InterruptedNode] = []

    def factory() -> InterruptedNode:
        nodes.append(InterruptedNode())
        return nodes[-1]

    try:
        code = run_node(factory, ["interrupted-node"])
    except KeyboardInterrupt:
        pytest.fail(f"a KeyboardInterrupt escaped run_node after {nodes[0].events}")
    assert code == 0
    assert nodes[0].events == ["callback began", "callback ended", "close began", "close ended"]
    assert not rclpy.ok()
    assert signal.getsignal(signal.SIGINT) is previous  # run_node's handler is gone


@pytest.mark.ros
def test_a_second_sigint_abandons_a_start_up_and_a_first_does_not():
    # A node whose creation is slow (the SFS node compiling its kernels): the
    # first SIGINT shuts the context down and lets it go on; a second one ends it.
    # Between the two only Python runs (no rclpy call that the first SIGINT's
    # shutdown could fail), so nothing but the second SIGINT can stop it there.
    created = []

    class SlowStart(Node):
        def __init__(self) -> None:
            super().__init__("slow_start_under_test")
            signal.raise_signal(signal.SIGINT)
            created.append("after the first")
            sum(range(1000))  # the compile's pure Python / numba work
            signal.raise_signal(signal.SIGINT)
            created.append("after the second")

    try:
        code = run_node(SlowStart, ["slow-start"])
    except KeyboardInterrupt:
        pytest.fail(f"a KeyboardInterrupt escaped run_node after {created}")
    assert code == 0
    assert created == ["after the first"]  # the second SIGINT ended the start-up
    assert not rclpy.ok()


CHILD = textwrap.dedent(
    """
    import sys, time
    import rclpy
    from rclpy.node import Node
    from endo_io.process import run_node

    class Busy(Node):
        def __init__(self):
            super().__init__("busy_under_test")
            self.create_timer(0.01, self._work)
            self.done = False

        def _work(self):
            if self.done:
                return
            self.done = True
            print("busy", flush=True)
            deadline = time.monotonic() + 10.0
            while rclpy.ok() and time.monotonic() < deadline:  # Python bytecode all along
                sum(range(1000))
            print("callback finished" if not rclpy.ok() else "gave up", flush=True)

        def close(self):
            print("closed", flush=True)

    sys.exit(run_node(Busy, ["busy"]))
    """
)


@pytest.mark.ros
def test_sigint_to_a_node_process_busy_in_a_callback_ends_it_cleanly(child_lines):
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    # Fast DDS's own log lines go to stdout too (a shared-memory port warning
    # came first once under a full suite's load, and the test then waited on
    # stderr for 300 s): the child's lines are looked for among them.
    assert child.stdout is not None and child.stderr is not None
    lines = child_lines(child.stdout)
    try:
        busy = lines.until(lambda line: line == "busy", 60.0)
        assert busy, f"no 'busy' line within 60 s; stdout so far: {lines.seen}"
        child.send_signal(signal.SIGINT)  # lands in the callback's loop
        child.wait(DEADLINE_S + 20)
        err = child.stderr.read()
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    assert child.returncode == 0, err
    ours = {"busy", "callback finished", "gave up", "closed"}
    out = lines.rest(10.0)
    assert [line for line in out if line in ours] == ["busy", "callback finished", "closed"], out
    assert "Traceback" not in err and "KeyboardInterrupt" not in err
