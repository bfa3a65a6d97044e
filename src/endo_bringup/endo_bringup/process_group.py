"""The demo's child processes: each with its own log file, all stopped in the end.

:class:`ProcessGroup` is a context manager. Leaving it, by any path
(success, an exception, Ctrl-C), sends SIGINT to every child that still runs,
waits for them together, and kills (SIGKILL) those that have not exited
after the grace period, so no node outlives the demo.
"""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import TracebackType


class ProcessGroup:
    """Named child processes started with ``subprocess.Popen``.

    env: the environment of every child; log_dir: each child's stdout and
    stderr go to ``log_dir/<name>.log``.
    """

    def __init__(self, env: dict[str, str], log_dir: Path, grace_s: float = 10.0) -> None:
        self.env = env
        self.log_dir = log_dir
        self.grace_s = grace_s
        self.processes: dict[str, subprocess.Popen[bytes]] = {}
        self.return_codes: dict[str, int | None] = {}
        log_dir.mkdir(parents=True, exist_ok=True)

    def log_path(self, name: str) -> Path:
        """Where the output of child ``name`` goes."""
        return self.log_dir / f"{name}.log"

    def log(self, name: str) -> str:
        """Everything child ``name`` has written so far."""
        path = self.log_path(name)
        return path.read_text(errors="replace") if path.exists() else ""

    def start(self, name: str, argv: list[str]) -> subprocess.Popen[bytes]:
        """Start ``argv`` as child ``name``."""
        with self.log_path(name).open("wb") as log:
            log.write(("$ " + " ".join(argv) + "\n").encode())
            log.flush()
            process = subprocess.Popen(argv, env=self.env, stdout=log, stderr=subprocess.STDOUT)
        self.processes[name] = process
        return process

    def running(self, name: str) -> bool:
        """True while child ``name`` has not exited."""
        return self.processes[name].poll() is None

    def stop(self, names: list[str] | None = None, timeout_s: float | None = None) -> None:
        """SIGINT the named children (all by default) and wait; SIGKILL after the timeout.

        Return codes are kept in ``return_codes`` (None for a child that had to
        be killed).
        """
        chosen = list(self.processes) if names is None else names
        timeout = self.grace_s if timeout_s is None else timeout_s
        for name in chosen:
            process = self.processes[name]
            if process.poll() is None:
                process.send_signal(signal.SIGINT)
        deadline = time.monotonic() + timeout
        for name in chosen:
            process = self.processes[name]
            try:
                code: int | None = process.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
                code = None
            self.return_codes.setdefault(name, code)

    def __enter__(self) -> ProcessGroup:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        try:
            self.stop()
        finally:
            # Even if waiting was interrupted (a second Ctrl-C), kill what is left.
            for process in self.processes.values():
                if process.poll() is None:
                    process.kill()
                    process.wait()


def console_script(name: str) -> str:
    """Path of an installed console script: beside this Python first, else on PATH."""
    beside = Path(sys.executable).parent / name
    if beside.exists():
        return str(beside)
    found = shutil.which(name)
    if found is None:
        raise FileNotFoundError(f"{name} is not installed (pip install -e src/<package>)")
    return found
