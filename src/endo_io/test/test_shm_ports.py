"""endo_io.shm_ports: a node whose shared-memory port Fast DDS lost is found and brought back.

The race itself (a CPU-starved listener's port removed and recreated by name,
eProsima/Fast-DDS#5469) is chance; its outcome is not: the port's file names
another segment than the one the node receives on. The tests below make that
outcome directly (the node's port files removed by name) and check that a
node left so hears nothing (the control), and that ``run_node`` with
``restart_on_lost_port`` finds it, says so in one line and hears again.
"""

from __future__ import annotations

import fcntl
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import TYPE_CHECKING

import pytest
import rclpy
from std_msgs.msg import String

from endo_io import process, shm_ports
from endo_io.process import prepare_transport
from endo_io.shm_ports import (
    LostPort,
    SharedMemoryPortLostError,
    SharedMemoryPortWatch,
    fd_targets,
    held_ports,
    lost_ports,
    mapped_port_inodes,
)

if TYPE_CHECKING:  # the fixture's class (the repository's conftest.py), for its annotation
    from conftest import ChildLines

MAPS = textwrap.dedent(
    """\
    7f0000000000-7f0004000000 rw-s 00000000 00:1a 285080 /dev/shm/fastrtps_port23169 (deleted)
    7f0004000000-7f0004100000 rw-s 00000000 00:1a 285090 /dev/shm/fastrtps_port7000
    7f0004100000-7f0004200000 rw-s 00000000 00:1a 285095 /dev/shm/fastrtps_3fcc2cdb8dd314c7
    7f0004200000-7f0004300000 r-xp 00000000 08:01 1234 /usr/lib/libc.so.6
    7f0004300000-7f0004400000 rw-p 00000000 00:00 0
    """
)


def test_the_ports_held_and_mapped_are_read_from_the_process_tables():
    targets = ["/dev/shm/fastrtps_port23169_el", "/dev/shm/fastrtps_port7000_el",
               "/dev/shm/fastrtps_3fcc2cdb8dd314c7_el", "/tmp/fastrtps_port1_el", "pipe:[42]"]
    assert held_ports(targets) == {23169, 7000}
    assert mapped_port_inodes(MAPS) == {23169: {285080}, 7000: {285090}}


def test_a_held_port_is_lost_when_its_name_points_elsewhere_or_nowhere():
    mapped = {23169: {285080}, 7000: {285090}}
    # 7000's name is still the segment mapped; 23169's is another one
    lost = lost_ports({23169, 7000}, mapped, {23169: 999, 7000: 285090}.get)
    assert lost == [LostPort(23169, frozenset({285080}), 999)]
    assert "another segment (inode 999)" in lost[0].describe()
    # no file carries the name at all (removed, not yet recreated)
    lost = lost_ports({23169}, mapped, lambda port: None)
    assert [port.port for port in lost] == [23169]
    assert "no file carries its name" in lost[0].describe()
    # a port held but not mapped (being opened) is not judged
    assert lost_ports({23171}, mapped, lambda port: None) == []


def test_the_watch_raises_only_for_a_port_lost_at_every_check_for_the_confirmation_time():
    # a port being regenerated, or healing once its listener runs again, is lost
    # for an instant or a few seconds: not enough
    now = [0.0]
    answers: list[list[LostPort]] = []
    watch = SharedMemoryPortWatch(lambda: answers.pop(0), confirm_s=5.0, clock=lambda: now[0])

    def check_at(seconds: float, *lost: LostPort) -> None:
        now[0] = seconds
        answers.append(list(lost))
        watch.check()

    check_at(0.0, LostPort(1, frozenset({5}), None))
    check_at(2.0, LostPort(1, frozenset({5}), 6))
    check_at(4.0)  # healed: the next loss starts over
    check_at(6.0, LostPort(1, frozenset({5}), 7))
    check_at(8.0, LostPort(1, frozenset({5}), 8))  # its name moves on: still lost
    check_at(10.0, LostPort(1, frozenset({5}), None), LostPort(3, frozenset({9}), None))
    with pytest.raises(SharedMemoryPortLostError) as raised:
        check_at(11.0, LostPort(1, frozenset({5}), 8), LostPort(3, frozenset({9}), None))
    assert "port 1 " in str(raised.value) and "port 3 " not in str(raised.value)
    assert raised.value.ports == (1, 3)  # every port lost now is to be avoided


def test_a_reserved_port_is_busy_to_anyone_who_tries_its_lock(tmp_path, monkeypatch):
    monkeypatch.setattr(shm_ports, "SHM_DIR", tmp_path)
    reserved: list[int] = []
    monkeypatch.setattr(shm_ports, "_reserved", reserved)  # this process's own stay untouched
    try:
        assert shm_ports.reserve_ports([31001]) == [31001]
        descriptor = os.open(tmp_path / "fastrtps_port31001_el", os.O_RDWR)
        try:
            with pytest.raises(BlockingIOError):  # what Fast DDS meets: the port is taken
                fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        finally:
            os.close(descriptor)
        # a lock someone else holds (here: the same file opened again) is left to them
        assert shm_ports.reserve_ports([31001]) == []
    finally:
        for descriptor in reserved:
            os.close(descriptor)


LISTENER = textwrap.dedent(
    """
    import sys
    from rclpy.node import Node
    from std_msgs.msg import String
    from endo_io.process import run_node

    class Listener(Node):
        def __init__(self):
            super().__init__("lost_port_listener")
            self.create_subscription(String, "/lost_port_probe", self._got, 10)
            print("ready", flush=True)

        def _got(self, msg):
            print("got " + msg.data, flush=True)

    sys.exit(run_node(Listener, ["listener"], restart_on_lost_port=sys.argv[1] == "restart"))
    """
)


def _listen_after_losing_its_ports(child_lines: type[ChildLines], mode: str, seconds: float,
                                   enough: int | None = None) -> tuple[list[str], str]:
    """Start a listener node, remove its port files by name, publish from a new participant.

    Publishes for ``seconds``, or until the listener heard ``enough`` messages.
    Returns the listener's lines ("ready", "got N"; Fast DDS's own log lines
    left out) and its stderr; the listener must end cleanly on SIGINT.
    """
    child = subprocess.Popen([sys.executable, "-c", LISTENER, mode], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True,
                             env=dict(os.environ, PYTHONUNBUFFERED="1"))
    assert child.stdout is not None and child.stderr is not None
    output = child_lines(child.stdout)

    def ours() -> list[str]:
        return [line for line in output.seen if line == "ready" or line.startswith("got ")]

    context = rclpy.Context()
    try:
        deadline = time.monotonic() + 60.0
        held: set[int] = set()
        while not held and time.monotonic() < deadline:  # its participant is up
            time.sleep(0.2)
            held = held_ports(fd_targets(Path(f"/proc/{child.pid}/fd")))
        assert held, "the listener holds no shared-memory port"
        for port in held:  # what the race leaves: the names no longer its segments
            (shm_ports.SHM_DIR / f"fastrtps_port{port}").unlink(missing_ok=True)
        prepare_transport()
        rclpy.init(context=context)
        node = rclpy.create_node("lost_port_talker", context=context)
        publisher = node.create_publisher(String, "/lost_port_probe", 10)
        end = time.monotonic() + seconds
        count = 0
        while time.monotonic() < end and (
                enough is None or sum(line.startswith("got ") for line in ours()) < enough):
            publisher.publish(String(data=str(count)))
            count += 1
            output.until(lambda line: False, 0.05)  # take what came meanwhile
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
        if child.poll() is None:
            child.send_signal(signal.SIGINT)
        try:
            child.wait(20)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()
        err = child.stderr.read()
    output.rest(5.0)
    assert child.returncode == 0, err
    assert "Traceback" not in err, err
    return ours(), err


@pytest.mark.ros
def test_a_node_whose_ports_were_taken_hears_nothing_and_says_so(child_lines):
    lines, err = _listen_after_losing_its_ports(child_lines, "log", 12.0)
    assert not any(line.startswith("got ") for line in lines), lines
    lost = [line for line in err.splitlines() if "was taken from this node" in line]
    assert len(lost) == 1 and "[ERROR]" in lost[0], err
    assert "restart this node to be reachable again" in lost[0]


@pytest.mark.ros
def test_run_node_restarts_a_node_whose_ports_were_taken_and_it_hears_again(child_lines):
    lines, err = _listen_after_losing_its_ports(child_lines, "restart", 30.0, enough=20)
    restarts = [line for line in err.splitlines()
                if "restarting the node's DDS participant" in line]
    assert len(restarts) == 1, err
    assert lines.count("ready") == 2, lines  # the node was created again, once
    got = [line for line in lines if line.startswith("got ")]
    assert len(got) >= 20, (lines, err)
    assert lines.index("ready", 1) < lines.index(got[0])  # heard by the new node


def test_run_node_restarts_at_most_three_times_a_minute_then_only_logs(monkeypatch, capsys):
    calls: list[bool] = []

    def run_once(factory, argv, sigint, restart: bool) -> int:
        calls.append(restart)
        if restart:
            raise SharedMemoryPortLostError("shared-memory port 7 was taken", (7,))
        return 0  # without restarts the loss is only logged, and the node runs to its end

    monkeypatch.setattr(process, "_run_node", run_once)
    monkeypatch.setattr(process, "reserve_ports", lambda ports: [])
    assert process.run_node(lambda: None, ["node-under-test"], restart_on_lost_port=True) == 0
    assert calls == [True, True, True, False]
    err = capsys.readouterr().err
    assert err.count("restarting the node's DDS participant (port 7 could not be held") == 3
    assert "3 restarts within 60 s for a lost shared-memory port: no more restarts" in err
