"""Starting endo-process's shading workers before the caller loads its own modules.

A worker's start-up is mostly imports (numpy, numba, OpenCV, the solver and
the correction: ~0.6-0.7 CPU-s) and, at its first frame, loading the
solver's cached kernels (~0.3 CPU-s); the calling process's own imports
(rclpy, every node's module, flow, the bag writer) take ~2 s more before
:func:`endo_process.runner.process_bag` even starts. Started from here, the
workers import beside the caller instead of after it: this module imports
nothing heavy, so ``endo-process`` (and ``bench/bench_process.py``) can call
:func:`start_workers` first thing, and hand them to ``process_bag``, whose
:class:`endo_process.parallel.ShadingPool` sends each its set-up (the
calibration, the SFS parameters, its shared memory) as its first message.
"""

from __future__ import annotations

import multiprocessing
import signal
from dataclasses import dataclass, field
from multiprocessing.context import SpawnProcess
from typing import Any

from endo_process.runtime import reuse_freed_memory


@dataclass
class StartedWorkers:
    """Worker processes waiting for their set-up, each with its two queues.

    processes, inboxes, outboxes: one per worker, in worker order. Once a
    :class:`endo_process.parallel.ShadingPool` has taken them (``taken``),
    the pool stops them; :meth:`close` stops them otherwise.
    """

    processes: list[SpawnProcess] = field(default_factory=list)
    inboxes: list[Any] = field(default_factory=list)
    outboxes: list[Any] = field(default_factory=list)
    taken: bool = False

    def __len__(self) -> int:
        return len(self.processes)

    def close(self) -> None:
        """Stop workers no pool took (idempotent)."""
        if self.taken:
            return
        self.taken = True
        # Terminated, not asked: they hold nothing yet (no set-up, no shared
        # memory), and one still importing would answer only after its imports.
        for process in self.processes:
            process.terminate()
        for process in self.processes:
            process.join(timeout=5.0)
        for box in self.inboxes + self.outboxes:
            box.cancel_join_thread()
            box.close()


def _run(inbox: Any, outbox: Any) -> None:
    """Worker process entry: ignore SIGINT, import the shading modules, then serve."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides when to stop
    reuse_freed_memory()  # before the frames' arrays: endo_process.runtime
    from endo_process.worker import serve  # the heavy imports, beside the parent's

    serve(inbox, outbox)


def start_workers(count: int) -> StartedWorkers:
    """Spawn ``count`` worker processes that import the shading modules and wait.

    spawn, not fork: the parent may already run numba or tqdm threads.
    """
    context = multiprocessing.get_context("spawn")
    workers = StartedWorkers()
    try:
        for _ in range(count):
            inbox, outbox = context.Queue(), context.Queue()
            process = context.Process(target=_run, args=(inbox, outbox), daemon=True)
            process.start()
            workers.processes.append(process)
            workers.inboxes.append(inbox)
            workers.outboxes.append(outbox)
    except BaseException:
        workers.close()
        raise
    return workers
