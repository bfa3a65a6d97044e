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
(:class:`_SlotRing`): a ring of slots per worker, each the size of one
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
import multiprocessing
import queue
import signal
import time
import traceback
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from multiprocessing.context import SpawnProcess
from multiprocessing.shared_memory import SharedMemory
from pathlib import Path
from typing import Any

import numpy as np

from endo_calib.calibration import PhotometricCalibration
from endo_io.camera import CameraModel
from endo_process.errors import WorkerError
from endo_process.shading import RawFrame, ShadedFrame, ShadingStage
from endo_sfs.warm_up import warm_up_frame

#: Consecutive frames per worker turn (1: frames dealt one at a time).
DEFAULT_CHUNK_FRAMES = 1
#: Frames in flight per worker at least (enough to even out the solves' and the caller's jitter).
PIPELINE_DEPTH = 8
#: Shared memory per worker for returning shaded frames, bytes at most (slots of one frame each).
SLOT_RING_BYTES = 64 * 2**20
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


@dataclass(frozen=True)
class _SlotFrame:
    """A shaded frame whose images wait in slot ``slot`` of its worker's ring.

    frame: the :class:`ShadedFrame` without its two images; irradiance,
    depth_relative: the (H, W) shapes they had (None: the image was None).
    """

    frame: ShadedFrame
    slot: int
    irradiance: tuple[int, int] | None
    depth_relative: tuple[int, int] | None


class _SlotRing:
    """Slots of shared memory, each holding one frame's two (H, W) float32 images.

    The calling process creates the ring (``name`` None) and unlinks it in
    :meth:`close`; a worker attaches to it by name. A slot is handed to a
    worker with the frame it is for, filled by the worker (:meth:`put`) and
    read back by the caller (:meth:`take`), which then hands it out again:
    no slot is written while it is read.

    Args:
        pixels: H × W of the frames the slots are sized for.
        slots: how many.
        name: the shared memory to attach to (a worker), or None (create it).
    """

    def __init__(self, pixels: int, slots: int, name: str | None = None) -> None:
        self.pixels = pixels
        self.slots = slots
        size = max(1, 2 * pixels * slots) * 4
        self.memory = SharedMemory(name=name, create=name is None, size=size if name is None else 0)
        self._owner = name is None
        self._images = np.ndarray((slots, 2, pixels), np.float32, buffer=self.memory.buf)

    @property
    def name(self) -> str:
        """The shared memory's name (for a worker to attach)."""
        return self.memory.name

    def fits(self, image: np.ndarray | None) -> bool:
        """Whether ``image`` can travel in a slot (None can: nothing to copy)."""
        return image is None or (
            image.ndim == 2 and image.size == self.pixels and image.dtype == np.float32
        )

    def put(self, slot: int, shaded: ShadedFrame) -> _SlotFrame:
        """Copy ``shaded``'s two images into ``slot`` (both must :meth:`fit`); its message."""
        shapes: list[tuple[int, int] | None] = []
        for k, image in enumerate((shaded.irradiance, shaded.depth_relative)):
            if image is None:
                shapes.append(None)
                continue
            self._images[slot, k] = image.reshape(-1)
            shapes.append((int(image.shape[0]), int(image.shape[1])))
        bare = dataclasses.replace(shaded, irradiance=None, depth_relative=None)
        return _SlotFrame(bare, slot, shapes[0], shapes[1])

    def take(self, item: _SlotFrame) -> ShadedFrame:
        """The shaded frame of ``item``, its images copied out of the slot."""
        images = [
            None if shape is None else self._images[item.slot, k].reshape(shape).copy()
            for k, shape in enumerate((item.irradiance, item.depth_relative))
        ]
        return dataclasses.replace(item.frame, irradiance=images[0], depth_relative=images[1])

    def close(self) -> None:
        """Detach (and, in the process that created it, unlink) the shared memory."""
        del self._images
        self.memory.close()
        if self._owner:
            with contextlib.suppress(FileNotFoundError):
                self.memory.unlink()


def _worker(
    config: StageConfig,
    inbox: Any,
    outbox: Any,
    camera: CameraModel | None = None,
    ring: tuple[str, int, int] | None = None,
) -> None:
    """Worker process body: (frame, slot) in, shaded frames out, None ends it.

    With ``camera`` it first solves a synthetic frame of that camera
    (:func:`endo_sfs.warm_up.warm_up_frame`: the kernels loaded, the solve
    grids built), while the parent sets up; the first real frame then costs
    what any other does. ``ring``: (name, pixels, slots) of the caller's
    :class:`_SlotRing` for this worker; a frame that comes with a slot goes
    back through it when its images fit.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides when to stop
    slots = None
    try:
        stage = config.build()
        if ring is not None:
            slots = _SlotRing(ring[1], ring[2], name=ring[0])
        if camera is not None:
            warm_up_frame(camera, stage.options)
        cpu_start: float | None = None
        while (item := inbox.get()) is not None:
            frame, slot = item
            cpu_start = time.process_time() if cpu_start is None else cpu_start
            shaded = stage.process(frame)
            # The CPU time is taken before the copy into the slot (or the
            # pickling), the last thing the worker does for the frame.
            shaded = dataclasses.replace(shaded, worker_cpu_s=time.process_time() - cpu_start)
            if (slots is not None and slot is not None and slots.fits(shaded.irradiance)
                    and slots.fits(shaded.depth_relative)):  # fmt: skip
                outbox.put(slots.put(slot, shaded))
            else:
                outbox.put(shaded)
    except BaseException:  # reported to the parent, which raises WorkerError
        outbox.put(("error", traceback.format_exc(limit=4)))
    finally:
        if slots is not None:
            slots.close()


class ShadingPool:
    """Ordered correction + SFS of a stream of frames.

    Args:
        config: calibration file, channel and SFS parameters.
        jobs: SFS chains (1: in this process; N ≥ 2: N worker processes).
        chunk_frames: consecutive frames per worker turn with ``jobs`` > 1.
        stage: with ``jobs`` == 1, an already built stage to use.
        warm_up_camera: with ``jobs`` > 1, the workers warm up for this camera
            as soon as they start (see :func:`_worker`), and their shared
            memory slots are sized for its images; with ``jobs`` == 1 the
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
        #: Worker processes (0: in this process).
        self.worker_count = jobs if jobs > 1 else 0
        #: Frames in flight at most.
        self.depth = self.worker_count * max(PIPELINE_DEPTH, chunk_frames + 1)
        self._stage: ShadingStage | None = None
        self._workers: list[SpawnProcess] = []
        self._inboxes: list[Any] = []
        self._outboxes: list[Any] = []
        self._rings: list[_SlotRing] = []
        self._free: list[deque[int]] = []
        if jobs == 1:
            self._stage = stage or config.build()
            return
        # spawn, not fork: the parent may already run numba or tqdm threads.
        context = multiprocessing.get_context("spawn")
        worker_config = StageConfig(
            config.calibration_path, config.channel, dict(config.sfs_parameters, threads=1),
            config.mask_extrapolated,
        )
        try:
            for _ in range(self.worker_count):
                ring = None
                if warm_up_camera is not None:
                    pixels = warm_up_camera.width * warm_up_camera.height
                    slots = max(2, min(math.ceil(self.depth / self.worker_count) + 1,
                                       SLOT_RING_BYTES // (8 * pixels)))  # fmt: skip
                    self._rings.append(_SlotRing(pixels, slots))
                    self._free.append(deque(range(slots)))
                    ring = (self._rings[-1].name, pixels, slots)
                inbox, outbox = context.Queue(), context.Queue()
                process = context.Process(
                    target=_worker, args=(worker_config, inbox, outbox, warm_up_camera, ring),
                    daemon=True,
                )
                process.start()
                self._workers.append(process)
                self._inboxes.append(inbox)
                self._outboxes.append(outbox)
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
            if isinstance(item, _SlotFrame):
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
        """Yield the shaded frames in the order of ``frames``.

        ``frames[k].index`` must be k (the dealing follows it); frames are
        pulled from the iterable only as far ahead as the workers need.
        """
        if self._stage is not None:
            for frame in frames:
                yield self._stage.process(frame)
            return
        pending: deque[tuple[int, int | None]] = deque()  # (frame index, its slot)
        source = iter(frames)
        exhausted = False
        while True:
            while not exhausted and len(pending) < self.depth:
                next_frame = next(source, None)
                if next_frame is None:
                    exhausted = True
                    break
                frame = next_frame
                start = self.chunked and frame.index % self.chunk_frames == 0
                if start != frame.chunk_start:
                    frame = dataclasses.replace(frame, chunk_start=start)
                pending.append((frame.index, self._send(frame)))
            if not pending:
                return
            index, slot = pending.popleft()
            worker = self.worker_of(index)
            shaded = self._receive(worker)
            if slot is not None:  # copied out (or the frame came pickled): free again
                self._free[worker].append(slot)
            yield shaded

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
