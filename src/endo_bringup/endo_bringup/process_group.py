"""The graph's child processes: each with its own log file, all stopped in the end.

Used by ``endo-demo`` and ``endo-launch``. :class:`ProcessGroup` is a
context manager. Leaving it, by any path (success, an exception, Ctrl-C),
sends SIGINT to every child that still runs, waits for them together, and
kills (SIGKILL) those that have not exited after the grace period, so no
node outlives the run. On Linux every child also gets ``PR_SET_PDEATHSIG``
(SIGKILL), so that a ``kill -9`` of the parent, which runs no cleanup,
still takes its children with it instead of leaving them to PID 1.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import IO

#: ``echo(name, line)``: called with each line a child writes (newline stripped).
Echo = Callable[[str, str], None]

#: prctl(2) option: the signal a child gets when the thread that forked it dies.
PR_SET_PDEATHSIG = 1


def _die_with_parent(nice: int = 0) -> Callable[[], None] | None:
    """A ``preexec_fn`` giving the child SIGKILL when its parent dies (Linux; None elsewhere).

    libc is loaded here, in the parent, so the child only makes the call.
    The parent may die between the fork and the prctl: the child then
    already has another parent and exits at once. ``nice`` (> 0) is added
    to the child's niceness (``os.nice``) before it runs its program.
    """
    if not sys.platform.startswith("linux"):
        if nice <= 0:
            return None

        def renice() -> None:
            os.nice(nice)

        return renice
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    parent = os.getpid()

    def preexec() -> None:
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        if os.getppid() != parent:
            os._exit(1)
        if nice > 0:
            os.nice(nice)

    return preexec


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
        self._readers: dict[str, threading.Thread] = {}
        log_dir.mkdir(parents=True, exist_ok=True)

    def log_path(self, name: str) -> Path:
        """Where the output of child ``name`` goes."""
        return self.log_dir / f"{name}.log"

    def log(self, name: str) -> str:
        """Everything child ``name`` has written so far."""
        path = self.log_path(name)
        return path.read_text(errors="replace") if path.exists() else ""

    def start(
        self,
        name: str,
        argv: list[str],
        *,
        echo: Echo | None = None,
        new_session: bool = False,
        nice: int = 0,
    ) -> subprocess.Popen[bytes]:
        """Start ``argv`` as child ``name`` (again, when a child of that name has exited).

        Args:
            name: the child's name (its log file, its return code).
            argv: the command line.
            echo: also hand every line of its output to ``echo`` (from a
                reader thread), besides writing it to the log file. A restart
                appends to the log.
            new_session: start it in a session of its own, so that a terminal's
                Ctrl-C reaches only this process, which forwards it.
            nice: added to the child's niceness (0..19; lower CPU priority),
                for a process that must not take the CPU from the frames'
                path (the graph's recorder).
        """
        if not 0 <= nice <= 19:
            raise ValueError(f"nice must be in 0..19, got {nice}")
        previous = self.processes.get(name)
        if previous is not None and previous.poll() is None:
            raise RuntimeError(f"{name} is still running")
        self.return_codes.pop(name, None)
        mode = "ab" if previous is not None else "wb"
        log = self.log_path(name).open(mode)
        log.write(("$ " + " ".join(argv) + "\n").encode())
        log.flush()
        # The death signal follows the forking *thread*: children are started
        # from the thread that owns the group (the launcher's main thread).
        preexec = _die_with_parent(nice)
        if echo is None:
            with log:
                process = subprocess.Popen(
                    argv, env=self.env, stdout=log, stderr=subprocess.STDOUT,
                    start_new_session=new_session, preexec_fn=preexec,
                )  # fmt: skip
        else:
            process = subprocess.Popen(
                argv, env=self.env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                start_new_session=new_session, preexec_fn=preexec,
            )  # fmt: skip
            thread = threading.Thread(
                target=_copy_lines, args=(process, log, name, echo), daemon=True,
                name=f"log {name}",
            )  # fmt: skip
            thread.start()
            self._readers[name] = thread
        self.processes[name] = process
        return process

    def tail(self, name: str, lines: int = 10) -> list[str]:
        """The last ``lines`` lines child ``name`` wrote (its log file's end)."""
        reader = self._readers.get(name)
        if reader is not None:
            reader.join(timeout=1.0)  # the output of a child that exited, to its end
        return self.log(name).splitlines()[-lines:]

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


def _copy_lines(process: subprocess.Popen[bytes], log: IO[bytes], name: str, echo: Echo) -> None:
    """Copy a child's output to its log file and to ``echo``, line by line, until it closes."""
    assert process.stdout is not None
    with log:
        for raw in process.stdout:
            log.write(raw)
            log.flush()
            echo(name, raw.decode(errors="replace").rstrip("\n"))


def console_script(name: str) -> str:
    """Path of an installed console script: beside this Python first, else on PATH."""
    beside = Path(sys.executable).parent / name
    if beside.exists():
        return str(beside)
    found = shutil.which(name)
    if found is None:
        raise FileNotFoundError(f"{name} is not installed (pip install -e src/<package>)")
    return found
