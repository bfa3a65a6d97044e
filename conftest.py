"""Workspace-wide pytest settings.

DDS stays on loopback in every test, however pytest was started: `make test`
exports these already; a bare `pytest` run gets the same defaults here, before
any test imports rclpy.

With pytest-xdist (`make test` runs two workers), each worker gets a DDS
domain of its own: worker gwK the domain given plus 30·K, modulo 102 (gw0
keeps it), so that two tests running at once never see each other's nodes
(a test that refuses a second graph in its domain would otherwise meet the
other worker's). Domains stay at 101 or below: above, Fast DDS's ports
(7400 + 250·domain + ...) fall in Linux's ephemeral port range (32768+),
where any outgoing socket may hold one, and discovery fails now and then
(seen: a worker on domain 152 whose pairs of processes did not find each
other, twice in one run).
"""

from __future__ import annotations

import gc
import os
import queue
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO

import pytest

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("ROS_DOMAIN_ID", "42")
os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")

#: Added to the domain of xdist worker gwK, times K.
WORKER_DOMAIN_STEP = 30
#: Domains above this risk Linux's ephemeral ports (see the module docstring).
SAFE_DOMAINS = 102
_worker = os.environ.get("PYTEST_XDIST_WORKER", "")
if _worker.startswith("gw"):
    os.environ["ROS_DOMAIN_ID"] = str(
        (int(os.environ["ROS_DOMAIN_ID"]) + WORKER_DOMAIN_STEP * int(_worker[2:])) % SAFE_DOMAINS
    )


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Tests marked ``ros`` (separate processes over DDS) are run once more if they fail.

    DDS discovery between two freshly started processes on this loopback fails
    now and then (a pair that never matches, or matches one way only: 3 times
    in ~8 full runs on 2026-12-02, on varying tests, never twice in a row on
    one); a second run tells such a failure from a broken graph. pytest reports
    every rerun (``R`` and the summary's "rerun" count), so none goes unseen.
    """
    for item in items:
        if item.get_closest_marker("ros") is not None and item.get_closest_marker("flaky") is None:
            item.add_marker(pytest.mark.flaky(reruns=1))


@pytest.fixture(autouse=True)
def _free_the_test_nodes(request: pytest.FixtureRequest) -> Iterator[None]:
    """After a ``ros`` test, collect the rclpy nodes it left in reference cycles.

    A node that outlives ``rclpy.shutdown()`` keeps its DDS participant, so its
    topics stay announced on the worker's domain: a later ``endo-record --all``
    in the same worker recorded a topic of test_record_node.py's (seen once,
    2026-12-03). Nodes hold cycles (timers and callbacks bound to them), so
    they go only when the garbage collector runs; run it here.
    """
    yield
    if request.node.get_closest_marker("ros") is not None:
        gc.collect()


class ChildLines:
    """A child process's output lines, read by a thread, waited for with a timeout.

    ``select`` and a buffered ``readline`` do not mix: two lines that come in
    one read leave the second in Python's buffer, where ``select`` does not
    see it (a test then waited its whole timeout). Fast DDS prints its own
    log lines on stdout, so a child's lines are looked for among others.
    """

    def __init__(self, stream: IO[str]) -> None:
        self._lines: queue.Queue[str | None] = queue.Queue()
        self.seen: list[str] = []  # every line taken so far, in order
        threading.Thread(target=self._read, args=(stream,), daemon=True).start()

    def _read(self, stream: IO[str]) -> None:
        for line in stream:
            self._lines.put(line.rstrip("\n"))
        self._lines.put(None)  # the stream ended

    def until(self, wanted: Callable[[str], bool], timeout: float) -> str | None:
        """The first line ``wanted`` accepts within ``timeout`` seconds, or None."""
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            try:
                line = self._lines.get(timeout=left)
            except queue.Empty:
                return None
            if line is None:
                self._lines.put(None)  # so that later calls see the end too
                return None
            self.seen.append(line)
            if wanted(line):
                return line
        return None

    def rest(self, timeout: float) -> list[str]:
        """Every line until the stream ends (or ``timeout`` seconds pass), taken in ``seen``."""
        self.until(lambda line: False, timeout)
        return self.seen


@pytest.fixture
def child_lines() -> type[ChildLines]:
    """:class:`ChildLines`, to read a child process's stdout: ``child_lines(child.stdout)``."""
    return ChildLines


def _clean_zombie_shared_memory() -> str:
    """Remove Fast DDS shared-memory files whose owner process is gone; returns the tool's summary.

    A process killed with SIGKILL (the fault tests do it on purpose) leaves
    its ports and segments in /dev/shm: 1340 files, 2.6 GB of RAM-backed
    tmpfs, had piled up here after a day of runs. Fast DDS's own
    ``fastdds shm clean`` removes only the files whose lock no live process
    holds, so running graphs (of other users too) are not touched.
    """
    # The wheel's `fastdds` launcher runs whatever `python3` is on PATH; run its script here.
    tool = Path(sys.prefix) / "tools" / "fastdds" / "fastdds.py"
    if not tool.exists():
        return "fastdds shm clean: not installed in this environment, skipped"
    try:
        done = subprocess.run(
            [sys.executable, str(tool), "shm", "clean"], capture_output=True, text=True, timeout=60
        )
    except subprocess.TimeoutExpired:
        return "fastdds shm clean: timed out after 60 s"
    lines = [line.strip() for line in done.stdout.splitlines() if "zombie" in line]
    return "fastdds shm clean: " + (", ".join(lines) if lines else f"exit {done.returncode}")


def _is_xdist_worker() -> bool:
    return bool(os.environ.get("PYTEST_XDIST_WORKER"))


_shm_reports: list[str] = []


def pytest_sessionstart(session: pytest.Session) -> None:
    """Clear what earlier crashed runs left in /dev/shm before any node starts."""
    if not _is_xdist_worker():
        _shm_reports.append("before: " + _clean_zombie_shared_memory())


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """Clear what this run's SIGKILL tests left in /dev/shm."""
    if not _is_xdist_worker():
        _shm_reports.append("after: " + _clean_zombie_shared_memory())


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    """Say what the shared-memory clean-ups removed."""
    for report in _shm_reports:
        terminalreporter.write_line(report)
