"""``endo-launch``'s guards, found by a new user's probe (issue 13): each small and fast.

* a second graph in the same ROS domain is refused before anything starts
  (exit 2, one line naming what runs there and the domain);
* ``kill -9`` of the launcher takes its children with it (PR_SET_PDEATHSIG),
  for a bare :class:`ProcessGroup` and for ``endo-launch`` itself;
* a replay's source waits only for the topics a node reads (not ``/clock``);
* bad source arguments (``--rate 0``, an unknown scene) are refused before
  anything starts, also under ``--dry-run``;
* a replay with ``--record`` ends with each node output's count against what
  came in (the demo's stage counts), and an output that got nothing is a
  warning and a failed run.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

LAUNCH = str(Path(sys.executable).parent / "endo-launch")


def _children(pid: int) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                found.append(int(entry.name))
    return found


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _wait_gone(pids: list[int], timeout_s: float) -> list[int]:
    deadline = time.monotonic() + timeout_s
    while (alive := [p for p in pids if _alive(p)]) and time.monotonic() < deadline:
        time.sleep(0.1)
    return alive


# ---------------------------------------------------------------- children die with the parent


def test_a_killed_process_group_owner_takes_its_children_along(tmp_path: Path) -> None:
    owner = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(f"""
            import os, sys, time
            from pathlib import Path
            from endo_bringup.process_group import ProcessGroup
            group = ProcessGroup(dict(os.environ), Path({str(tmp_path)!r}))
            for name in ("a", "b"):
                group.start(name, ["sleep", "600"], new_session=True)
            print(" ".join(str(p.pid) for p in group.processes.values()), flush=True)
            time.sleep(600)
        """)],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert owner.stdout is not None
    pids = [int(p) for p in owner.stdout.readline().split()]
    assert len(pids) == 2 and all(_alive(p) for p in pids)
    owner.kill()
    owner.wait()
    assert _wait_gone(pids, 5.0) == []


@pytest.mark.ros
def test_kill_9_of_endo_launch_leaves_no_node_running(tmp_path: Path) -> None:
    launcher = subprocess.Popen([LAUNCH, "live", "--quiet", "--log-dir", str(tmp_path / "logs")],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while len(children := _children(launcher.pid)) < 4:
            assert launcher.poll() is None and time.monotonic() < deadline, children
            time.sleep(0.2)
        launcher.kill()
        launcher.wait()
        assert _wait_gone(children, 10.0) == []
    finally:
        for pid in _children(launcher.pid):
            os.kill(pid, signal.SIGKILL)
