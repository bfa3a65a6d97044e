"""Correction + SFS over a whole recording, in order, on one or several cores.

Shape from shading is the cost of a run, and each frame's solve is seeded by
the previous frame's solution, so frames cannot simply be handed out one by
one. ``jobs`` counts processes, the calling one included:

* ``jobs`` == 1: everything runs in the calling process, as one chain (the
  SFS node's own ``threads`` parameter decides how many threads a solve uses).
* ``jobs`` == 2: one worker process corrects and solves every frame in order,
  one unbroken warm-started chain as with 1, while the calling process reads,
  runs the flow step and writes: a two-stage pipeline, one stage per core,
  and the same chain of solves as ``jobs`` == 1.
* ``jobs`` == N > 2: N − 1 workers; the recording is cut into chunks of
  ``chunk_frames`` consecutive frames, chunk ``c`` goes to worker
  ``c mod (N − 1)``, which solves its frames in order, warm-started within the
  chunk and cold at the chunk's first frame. The warm start only changes where
  the solver starts, not what it converges to, so the depth agrees with a
  single chain to the solver's tolerance (tested). For machines with more
  cores than two.

Workers solve with one thread each. Results come back in frame order.
Memory is bounded: at most ``workers × chunk_frames + workers`` frames are in
flight (:data:`PIPELINE_DEPTH` with one worker).

Why not two chunked workers on two cores: each worker pays its own start-up
(imports, loading the compiled kernels: about 1.5 s of CPU) and every chunk
starts cold, while the calling process needs a core of its own for the flow
step and the writing anyway (docs/benchmarks.md, "endo-process").
"""

from __future__ import annotations

import contextlib
import dataclasses
import multiprocessing
import queue
import signal
import time
import traceback
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from multiprocessing.context import SpawnProcess
from pathlib import Path
from typing import Any

from endo_calib.calibration import PhotometricCalibration
from endo_io.camera import CameraModel
from endo_process.errors import WorkerError
from endo_process.shading import RawFrame, ShadedFrame, ShadingStage
from endo_sfs.warm_up import warm_up_frame

#: Frames per chunk when the recording is split over worker processes.
DEFAULT_CHUNK_FRAMES = 32
#: Frames in flight with one worker (enough to even out the two stages' jitter).
PIPELINE_DEPTH = 8
#: Seconds between checks that a worker is still alive while waiting for it.
_POLL_S = 0.5


@dataclass(frozen=True)
class StageConfig:
    """What a worker needs to build its own :class:`ShadingStage` (picklable)."""

    calibration_path: Path
    channel: str
    sfs_parameters: dict[str, Any]
    mask_extrapolated: bool = False

    def build(self) -> ShadingStage:
        """Load the calibration and return a stage."""
        calibration = PhotometricCalibration.load(self.calibration_path)
        return ShadingStage(calibration, self.channel, self.sfs_parameters,
                            mask_extrapolated=self.mask_extrapolated)  # fmt: skip


def _worker(
    config: StageConfig, inbox: Any, outbox: Any, camera: CameraModel | None = None
) -> None:
    """Worker process body: frames in, shaded frames out, None ends it.

    With ``camera`` it first solves a synthetic frame of that camera
    (:func:`endo_sfs.warm_up.warm_up_frame`: the kernels loaded, the solve
    grids built), while the parent sets up; the first real frame then costs
    what any other does.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides when to stop
    try:
        stage = config.build()
        if camera is not None:
            warm_up_frame(camera, stage.options)
        cpu_start: float | None = None
        while (frame := inbox.get()) is not None:
            cpu_start = time.process_time() if cpu_start is None else cpu_start
            shaded = stage.process(frame)
            outbox.put(dataclasses.replace(shaded, worker_cpu_s=time.process_time() - cpu_start))
    except BaseException:  # reported to the parent, which raises WorkerError
        outbox.put(("error", traceback.format_exc(limit=4)))


class ShadingPool:
    """Ordered correction + SFS of a stream of frames.

    Args:
        config: calibration file, channel and SFS parameters.
        jobs: worker processes (1: in this process).
        chunk_frames: consecutive frames per chunk with ``jobs`` > 1.
        stage: with ``jobs`` == 1, an already built stage to use.
        warm_up_camera: with ``jobs`` > 1, the workers warm up for this camera
            as soon as they start (see :func:`_worker`); with ``jobs`` == 1 the
            caller warms up (:meth:`ShadingStage.warm_up`), when it suits it.
    """

    def __init__(
        self,
        config: StageConfig,
        jobs: int = 1,
        chunk_frames: int = DEFAULT_CHUNK_FRAMES,
        stage: ShadingStage | None = None,
        warm_up_camera: CameraModel | None = None,
    ) -> None:
        if jobs < 1 or chunk_frames < 1:
            raise ValueError("jobs and chunk_frames must be >= 1")
        self.jobs = jobs
        self.chunk_frames = chunk_frames
        #: Worker processes (0: in this process); with one, the chain is never cut.
        self.worker_count = jobs - 1
        self._stage: ShadingStage | None = None
        self._workers: list[SpawnProcess] = []
        self._inboxes: list[Any] = []
        self._outboxes: list[Any] = []
        if jobs == 1:
            self._stage = stage or config.build()
            return
        # spawn, not fork: the parent may already run numba or tqdm threads.
        context = multiprocessing.get_context("spawn")
        worker_config = StageConfig(
            config.calibration_path, config.channel, dict(config.sfs_parameters, threads=1),
            config.mask_extrapolated,
        )
        for _ in range(self.worker_count):
            inbox, outbox = context.Queue(), context.Queue()
            process = context.Process(
                target=_worker, args=(worker_config, inbox, outbox, warm_up_camera), daemon=True
            )
            process.start()
            self._workers.append(process)
            self._inboxes.append(inbox)
            self._outboxes.append(outbox)

    @property
    def chunked(self) -> bool:
        """Whether the recording is cut into chunks (more than one worker)."""
        return self.worker_count > 1

    def worker_of(self, index: int) -> int:
        """The worker that shades frame ``index`` (0 with one worker or none)."""
        return (index // self.chunk_frames) % self.worker_count if self.chunked else 0

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
            return item

    def map(self, frames: Iterable[RawFrame]) -> Iterator[ShadedFrame]:
        """Yield the shaded frames in the order of ``frames``.

        ``frames[k].index`` must be k (the chunking follows it); frames are
        pulled from the iterable only as far ahead as the workers need.
        """
        if self._stage is not None:
            for frame in frames:
                yield self._stage.process(frame)
            return
        if self.chunked:
            limit = self.worker_count * self.chunk_frames + self.worker_count
        else:
            limit = PIPELINE_DEPTH
        pending: deque[int] = deque()
        source = iter(frames)
        exhausted = False
        while True:
            while not exhausted and len(pending) < limit:
                next_frame = next(source, None)
                if next_frame is None:
                    exhausted = True
                    break
                frame = next_frame
                start = self.chunked and frame.index % self.chunk_frames == 0
                if start != frame.chunk_start:
                    frame = RawFrame(frame.index, frame.stamp_ns, frame.frame_id, frame.raw,
                                     frame.encoding, frame.camera, start)  # fmt: skip
                self._inboxes[self.worker_of(frame.index)].put(frame)
                pending.append(frame.index)
            if not pending:
                return
            yield self._receive(self.worker_of(pending.popleft()))

    def close(self) -> None:
        """Stop the workers (idempotent); frames still queued are abandoned."""
        for inbox in self._inboxes:
            with contextlib.suppress(OSError, ValueError):
                inbox.put(None)
        for process in self._workers:
            process.join(timeout=2.0)
            if process.is_alive():
                process.terminate()
                process.join(timeout=2.0)
        for box in self._inboxes + self._outboxes:
            box.cancel_join_thread()
            box.close()
        self._workers.clear()
        self._inboxes.clear()
        self._outboxes.clear()

    def __enter__(self) -> ShadingPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
