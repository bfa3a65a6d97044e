"""Correction + SFS over a whole recording, in order, on one or several cores.

Shape from shading is the cost of a run, and each frame's solve is seeded by
an earlier frame's solution, so frames cannot simply be handed out one by
one to whoever is free. ``jobs`` counts the SFS chains:

* ``jobs`` == 1: everything runs in the calling process, as one chain (the
  SFS node's own ``threads`` parameter decides how many threads a solve uses).
* ``jobs`` == N ≥ 2: N worker processes correct and solve the frames in
  turn: frame k goes to worker k mod N (with ``chunk_frames`` C > 1: turns
  of C consecutive frames), and each worker warm-starts every frame from
  the last frame it solved itself, N frames back; the calling process reads,
  runs the flow step and writes meanwhile. Each worker's chain is fixed by
  the frame order alone, so a run gives the same result every time; the
  warm start changes where the solver starts, not the fixed point it stops
  at, so the depth agrees with one chain (``jobs`` == 1) to the solver's
  tolerance (tested). With C > 1 a worker starts each of its turns cold (its
  own last frame is C·(N − 1) + 1 frames back).

Why N workers beside the calling process (three processes on two cores with
the default 2), and why the warm start from N frames back: the calling
process's own work per frame (reading, poses, flow, writing: ~15 ms at
640×480) is about half the solve's (~25 ms on one thread at solve_scale
0.5), so one worker leaves the second core idle half the time, and the
solve from a warm start two frames old costs what it costs from the
previous frame (3.77 solves per node either way on the phantom; moving it
by the camera motion costs 5–9 ms more CPU and no fewer solves:
docs/benchmarks.md, "Pose-predicted warm start"). Measured:
docs/benchmarks.md, "endo-process".

Workers solve with one thread each. Results come back in frame order.
Memory is bounded: at most ``N × max(PIPELINE_DEPTH, C + 1)`` frames are
in flight. The shaded images come back through shared memory
(:class:`SlotRing`): a ring of slots per worker, each the size of one
frame's irradiance and relative depth, which the worker fills and the
calling process copies out; through the result queue they were pickled,
pushed through a pipe in 64 kB pieces and unpickled, ~2.4 MB per frame
at 640×480 (several ms of CPU on each side). A frame that does not fit a
slot (another image size, three channels) travels pickled as before.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import queue
from collections import deque
from collections.abc import Iterable, Iterator
from multiprocessing.context import SpawnProcess
from typing import Any

from endo_io.camera import CameraModel
from endo_process.errors import WorkerError
from endo_process.shading import RawFrame, ShadedFrame, ShadingStage
from endo_process.worker import SlotFrame, SlotRing, StageConfig
from endo_process.worker_start import StartedWorkers, start_workers

#: Consecutive frames per worker turn (1: frames dealt one at a time).
DEFAULT_CHUNK_FRAMES = 1
#: Frames in flight per worker at least (enough to even out the solves' and the caller's jitter).
PIPELINE_DEPTH = 8
#: Shared memory per worker for returning shaded frames, bytes at most (slots of one frame each).
SLOT_RING_BYTES = 64 * 2**20
#: Seconds between checks that a worker is still alive while waiting for it.
_POLL_S = 0.5


class ShadingPool:
    """Ordered correction + SFS of a stream of frames.

    Args:
        config: calibration file, channel and SFS parameters.
        jobs: SFS chains (1: in this process; N ≥ 2: N worker processes).
        chunk_frames: consecutive frames per worker turn with ``jobs`` > 1.
        stage: with ``jobs`` == 1, an already built stage to use.
        camera: with ``jobs`` > 1, the recording's first camera: the
            workers' shared memory slots are sized for its images.
        warm_up: with ``jobs`` > 1 and ``camera``, the workers solve a
            synthetic frame of it first (see :func:`endo_process.worker.serve`); by default
            they start on the first real frames, which :meth:`map` sends
            at once. With ``jobs`` == 1 the caller warms up
            (:meth:`ShadingStage.warm_up`), when it suits it.
        workers: with ``jobs`` > 1, worker processes started earlier
            (:func:`endo_process.worker_start.start_workers`, ``jobs`` of
            them), which the pool takes over and stops; None: it starts
            its own.
    """

    def __init__(
        self,
        config: StageConfig,
        jobs: int = 1,
        chunk_frames: int = DEFAULT_CHUNK_FRAMES,
        stage: ShadingStage | None = None,
        camera: CameraModel | None = None,
        warm_up: bool = False,
        workers: StartedWorkers | None = None,
    ) -> None:
        if jobs < 1 or chunk_frames < 1:
            raise ValueError("jobs and chunk_frames must be >= 1")
        self.jobs = jobs
        self.chunk_frames = chunk_frames
        #: Worker processes (0: in this process).
        self.worker_count = jobs if jobs > 1 else 0
        #: Frames in flight at most.
        self.depth = self.worker_count * max(PIPELINE_DEPTH, chunk_frames + 1)
        self._stage: ShadingStage | None = None
        self._workers: list[SpawnProcess] = []
        self._inboxes: list[Any] = []
        self._outboxes: list[Any] = []
        self._rings: list[SlotRing] = []
        self._free: list[deque[int]] = []
        self._stopped = False
        if jobs == 1:
            self._stage = stage or config.build()
            return
        worker_config = StageConfig(
            config.calibration_path, config.channel, dict(config.sfs_parameters, threads=1),
            config.mask_extrapolated, config.output_encoding,
        )
        try:
            if workers is None or len(workers) != self.worker_count or workers.taken:
                workers = start_workers(self.worker_count)
            workers.taken = True  # this pool stops them
            self._workers = list(workers.processes)
            self._inboxes = list(workers.inboxes)
            self._outboxes = list(workers.outboxes)
            for inbox in self._inboxes:
                ring = None
                if camera is not None:
                    pixels = camera.width * camera.height
                    slots = max(2, min(math.ceil(self.depth / self.worker_count) + 1,
                                       SLOT_RING_BYTES // (8 * pixels)))  # fmt: skip
                    self._rings.append(SlotRing(pixels, slots))
                    self._free.append(deque(range(slots)))
                    ring = (self._rings[-1].name, pixels, slots)
                inbox.put((worker_config, camera if warm_up else None, ring))
        except BaseException:
            self.close()
            raise

    @property
    def chunked(self) -> bool:
        """Whether workers take turns of several frames (each turn starts cold)."""
        return self.worker_count > 1 and self.chunk_frames > 1

    def worker_of(self, index: int) -> int:
        """The worker that shades frame ``index`` (0 with one worker or none)."""
        return (index // self.chunk_frames) % self.worker_count if self.worker_count else 0

    def _receive(self, worker: int) -> ShadedFrame:
        while True:
            try:
                item = self._outboxes[worker].get(timeout=_POLL_S)
            except queue.Empty:
                if not self._workers[worker].is_alive():
                    raise WorkerError(
                        f"shading worker {worker} exited with code {self._workers[worker].exitcode}"
                    ) from None
                continue
            if isinstance(item, tuple):
                raise WorkerError(f"shading worker {worker} failed:\n{item[1]}")
            if isinstance(item, SlotFrame):
                return self._rings[worker].take(item)
            return item

    def _send(self, frame: RawFrame) -> int | None:
        """Queue ``frame`` for its worker with a free slot of its ring (if any); the slot."""
        worker = self.worker_of(frame.index)
        free = self._free[worker] if self._free else None
        slot = free.popleft() if free else None
        self._inboxes[worker].put((frame, slot))
        return slot

    def map(self, frames: Iterable[RawFrame]) -> Iterator[ShadedFrame]:
        """The shaded frames in the order of ``frames``.

        ``frames[k].index`` must be k (the dealing follows it); frames are
        pulled from the iterable only as far ahead as the workers need. With
        workers, the first frames (up to :attr:`depth`) are read and sent
        at once, in this call, so that the workers start on them while the
        caller goes on setting up; with one job nothing runs before the
        first result is asked for.
        """
        if self._stage is not None:
            stage = self._stage
            return (stage.process(frame) for frame in frames)
        pending: deque[tuple[int, int | None]] = deque()  # (frame index, its slot)
        source = iter(frames)
        exhausted = self._send_ahead(source, pending)
        return self._collect(source, pending, exhausted)

    def _send_ahead(
        self, source: Iterator[RawFrame], pending: deque[tuple[int, int | None]]
    ) -> bool:
        """Send frames from ``source`` until :attr:`depth` are in flight; whether it ran out."""
        while len(pending) < self.depth:
            frame = next(source, None)
            if frame is None:
                return True
            start = self.chunked and frame.index % self.chunk_frames == 0
            if start != frame.chunk_start:
                frame = dataclasses.replace(frame, chunk_start=start)
            pending.append((frame.index, self._send(frame)))
        return False

    def _collect(
        self, source: Iterator[RawFrame], pending: deque[tuple[int, int | None]], exhausted: bool
    ) -> Iterator[ShadedFrame]:
        """Receive the frames in flight in order, sending more as each comes back."""
        while True:
            if not exhausted:
                exhausted = self._send_ahead(source, pending)
            if not pending:
                return
            index, slot = pending.popleft()
            worker = self.worker_of(index)
            shaded = self._receive(worker)
            if slot is not None:  # copied out (or the frame came pickled): free again
                self._free[worker].append(slot)
            yield shaded

    def stop(self) -> None:
        """Tell the workers to exit once their queued frames are done, without waiting.

        A worker's exit (its interpreter's teardown) takes a few tenths of a
        second: the caller finishes its output meanwhile, then :meth:`close`.
        """
        if self._stopped:
            return
        self._stopped = True
        for inbox in self._inboxes:
            with contextlib.suppress(OSError, ValueError):
                inbox.put(None)

    def close(self) -> None:
        """Stop the workers and wait for them (idempotent); frames still queued are abandoned."""
        self.stop()
        for process in self._workers:
            process.join(timeout=2.0)
            if process.is_alive():
                process.terminate()
                process.join(timeout=2.0)
        for box in self._inboxes + self._outboxes:
            box.cancel_join_thread()
            box.close()
        for ring in self._rings:
            ring.close()
        self._workers.clear()
        self._inboxes.clear()
        self._outboxes.clear()
        self._rings.clear()
        self._free.clear()

    def __enter__(self) -> ShadingPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
