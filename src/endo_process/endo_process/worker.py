"""A shading worker process's side: its set-up, its shared memory slots, its loop.

:func:`serve` is what each worker of :class:`endo_process.parallel.ShadingPool`
runs (started by :func:`endo_process.worker_start.start_workers`): it takes
its set-up (:class:`StageConfig`, the shared memory of its :class:`SlotRing`)
as its first message, then corrects and solves the frames it is sent. Apart
from the pool's module, so that the light starter imports this one and the
pool imports both, without a cycle.
"""

from __future__ import annotations

import contextlib
import dataclasses
import resource
import time
import traceback
from dataclasses import dataclass
from multiprocessing.shared_memory import SharedMemory
from pathlib import Path
from typing import Any

import numpy as np

from endo_calib.calibration import PhotometricCalibration
from endo_io.camera import CameraModel
from endo_process.errors import WorkerError
from endo_process.shading import ShadedFrame, ShadingStage
from endo_sfs.warm_up import warm_up_frame


@dataclass(frozen=True)
class StageConfig:
    """What a worker needs to build its own :class:`ShadingStage` (picklable)."""

    calibration_path: Path
    channel: str
    sfs_parameters: dict[str, Any]
    mask_extrapolated: bool = False
    output_encoding: str = "16UC1"

    def build(self) -> ShadingStage:
        """Load the calibration and return a stage."""
        calibration = PhotometricCalibration.load(self.calibration_path)
        return ShadingStage(calibration, self.channel, self.sfs_parameters,
                            mask_extrapolated=self.mask_extrapolated,
                            output_encoding=self.output_encoding)  # fmt: skip


@dataclass(frozen=True)
class SlotFrame:
    """A shaded frame whose images wait in slot ``slot`` of its worker's ring.

    frame: the :class:`ShadedFrame` without its two images; irradiance,
    depth_relative: the (H, W) shapes they had (None: the image was None).
    """

    frame: ShadedFrame
    slot: int
    irradiance: tuple[int, int] | None
    depth_relative: tuple[int, int] | None


class SlotRing:
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

    Raises:
        WorkerError: the shared memory cannot be had (one line naming why).
    """

    def __init__(self, pixels: int, slots: int, name: str | None = None) -> None:
        self.pixels = pixels
        self.slots = slots
        size = max(1, 2 * pixels * slots) * 4
        # Python 3.11's SharedMemory, when it cannot size a new segment, unregisters it
        # from the resource tracker before registering it, and the tracker process
        # prints a KeyError traceback beside our line: a file size limit is checked first.
        limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
        if name is None and limit != resource.RLIM_INFINITY and size > limit:
            raise WorkerError(_no_shared_memory(size, "over the file size limit"))
        try:
            self.memory = SharedMemory(name=name, create=name is None,
                                       size=size if name is None else 0)  # fmt: skip
        except OSError as error:
            raise WorkerError(_no_shared_memory(size, str(error.strerror))) from None
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

    def put(self, slot: int, shaded: ShadedFrame) -> SlotFrame:
        """Copy ``shaded``'s two images into ``slot`` (both must :meth:`fit`); its message."""
        shapes: list[tuple[int, int] | None] = []
        for k, image in enumerate((shaded.irradiance, shaded.depth_relative)):
            if image is None:
                shapes.append(None)
                continue
            self._images[slot, k] = image.reshape(-1)
            shapes.append((int(image.shape[0]), int(image.shape[1])))
        bare = dataclasses.replace(shaded, irradiance=None, depth_relative=None)
        return SlotFrame(bare, slot, shapes[0], shapes[1])

    def take(self, item: SlotFrame) -> ShadedFrame:
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


def _no_shared_memory(size: int, why: str) -> str:
    """The one line for a ring of ``size`` bytes that cannot be had, and ``why``."""
    return (f"cannot create {size / 1e6:.1f} MB of shared memory for the --jobs workers "
            f"({why}; a file size limit, ulimit -f, applies to /dev/shm too): "
            "--jobs 1 needs none")


def serve(inbox: Any, outbox: Any) -> None:
    """Worker process body: its set-up, then (frame, slot) in, shaded frames out; None ends it.

    The first message is the set-up, (config, warm_up_camera, ring), or None
    (stop before starting). With ``warm_up_camera`` the worker first solves a
    synthetic frame of that camera (:func:`endo_sfs.warm_up.warm_up_frame`:
    the kernels loaded, the solve grids built). Without it (what
    :class:`ShadingPool` does by default) the first real frames, sent as soon
    as the pool is made, do that work: the synthetic frame's rendering and
    its two solves cost a worker 0.1-0.4 CPU-s on top, while the caller's own
    set-up and the other worker share the two cores. ``ring``: (name, pixels,
    slots) of the caller's :class:`SlotRing` for this worker; a frame that
    comes with a slot goes back through it when its images fit. Started by
    :func:`endo_process.worker_start.start_workers`.
    """
    slots = None
    try:
        if (setup := inbox.get()) is None:
            return
        config: StageConfig = setup[0]
        warm_up_camera: CameraModel | None = setup[1]
        ring: tuple[str, int, int] | None = setup[2]
        stage = config.build()
        if ring is not None:
            slots = SlotRing(ring[1], ring[2], name=ring[0])
        if warm_up_camera is not None:
            warm_up_frame(warm_up_camera, stage.options)
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
