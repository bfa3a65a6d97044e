"""ProcessGroup stops every child: politely with SIGINT, else with SIGKILL."""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import pytest

from endo_bringup.process_group import ProcessGroup

#: Exits 0 on SIGINT (after printing), like a node under run_node.
POLITE = (
    "import signal, sys, time\n"
    "signal.signal(signal.SIGINT, lambda *a: (print('interrupted', flush=True), sys.exit(0)))\n"
    "print('re' + 'ady', flush=True)\n"
    "time.sleep(60)\n"
)
#: Ignores SIGINT: must be killed.
STUBBORN = (
    "import signal, time\n"
    "signal.signal(signal.SIGINT, signal.SIG_IGN)\n"
    "print('re' + 'ady', flush=True)\n"
    "time.sleep(60)\n"
)


def _wait_ready(group: ProcessGroup, name: str) -> None:
    deadline = time.monotonic() + 10
    while "ready" not in group.log(name):
        assert time.monotonic() < deadline, group.log(name)
        time.sleep(0.02)


def test_stop_interrupts_then_kills(tmp_path: Path):
    with ProcessGroup(dict(os.environ), tmp_path, grace_s=1.0) as group:
        polite = group.start("polite", [sys.executable, "-c", POLITE])
        stubborn = group.start("stubborn", [sys.executable, "-c", STUBBORN])
        _wait_ready(group, "polite")
        _wait_ready(group, "stubborn")
        group.stop()
    assert polite.returncode == 0
    assert "interrupted" in group.log("polite")
    assert group.return_codes == {"polite": 0, "stubborn": None}  # None: killed
    assert stubborn.returncode == -9


def test_leaving_on_an_exception_stops_every_child(tmp_path: Path):
    env = dict(os.environ)
    with pytest.raises(RuntimeError), ProcessGroup(env, tmp_path, grace_s=1.0) as group:
        for name in ("a", "b"):
            group.start(name, [sys.executable, "-c", STUBBORN])
        raise RuntimeError("the demo failed half-way")
    assert all(p.poll() is not None for p in group.processes.values())
    assert group.log("a").startswith("$ ")  # the command line heads the log


def test_a_child_runs_at_the_niceness_asked(tmp_path: Path):
    script = "import os, time\nprint('re' + 'ady', os.nice(0), flush=True)\ntime.sleep(60)\n"
    own = os.nice(0)
    with ProcessGroup(dict(os.environ), tmp_path, grace_s=1.0) as group:
        niced = group.start("niced", [sys.executable, "-c", script], nice=7)
        plain = group.start("plain", [sys.executable, "-c", script])
        _wait_ready(group, "niced")
        _wait_ready(group, "plain")
        assert os.getpriority(os.PRIO_PROCESS, niced.pid) == min(own + 7, 19)
        assert os.getpriority(os.PRIO_PROCESS, plain.pid) == own
        with pytest.raises(ValueError, match=r"nice must be in 0\.\.19"):
            group.start("negative", [sys.executable, "-c", script], nice=-1)
    assert f"ready {min(own + 7, 19)}" in group.log("niced")
