"""ShadingPool with workers started early: taken over, fed at once by map(), results in order."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from endo_process.inputs import InputTopics, first_camera, open_recording
from endo_process.parallel import ShadingPool, StageConfig
from endo_process.settings import load_settings
from endo_process.shading import RawFrame
from endo_process.worker_start import start_workers

BAGS = Path(__file__).resolve().parents[3] / "bags"
FRAMES = 20


def _frames(pulled: list[int]) -> Iterator[RawFrame]:
    """Dark mono8 frames of the phantom's camera (no usable pixels: quick to shade)."""
    camera = first_camera(open_recording(BAGS / "phantom_colon.mcap", InputTopics(), None))
    assert camera is not None
    for index in range(FRAMES):
        pulled.append(index)
        raw = np.zeros((camera.height, camera.width), np.uint8)
        yield RawFrame(index, 10**9 + index * 33_333_333, "optical", raw, "mono8", camera)


def test_workers_get_the_first_frames_at_once_and_results_come_in_order(
    calibrations: tuple[Path, Path],
) -> None:
    settings = load_settings(None)
    config = StageConfig(calibrations[0], settings.channel, settings.sfs,
                         settings.mask_extrapolated)  # fmt: skip
    camera = first_camera(open_recording(BAGS / "phantom_colon.mcap", InputTopics(), None))
    started = start_workers(2)  # as endo-process does, before its own imports
    with ShadingPool(config, jobs=2, camera=camera, workers=started) as pool:
        assert started.taken and pool._workers == started.processes
        pulled: list[int] = []
        results = pool.map(_frames(pulled))
        # Sent before the first result is asked for: the workers start on them
        # while the caller goes on setting up.
        assert pulled == list(range(pool.depth)) and pool.depth < FRAMES
        shaded = list(results)
    assert [frame.index for frame in shaded] == list(range(FRAMES)) == pulled
    assert all(frame.depth_relative is not None for frame in shaded)
    assert all(frame.dropped is not None and frame.dropped[0] == "NoValidPixelsError"
               for frame in shaded)  # fmt: skip
    with ShadingPool(config, jobs=1) as pool:
        pulled = []
        results = pool.map(_frames(pulled))
        assert pulled == []  # one job: nothing runs before the loop asks
        assert next(results).index == 0 and pulled == [0]


def test_workers_no_run_took_are_stopped() -> None:
    started = start_workers(2)
    started.close()
    assert all(process.exitcode is not None for process in started.processes)
    started.close()  # again: nothing left to do


def test_shared_memory_over_the_file_size_limit_is_one_line() -> None:
    # A file size limit applies to /dev/shm: Python 3.11's SharedMemory then unregistered
    # the segment before registering it, and the resource tracker printed a KeyError
    # traceback beside endo-process's line (the hostile user's ulimit -f, --jobs 2).
    script = (
        "import resource, signal\n"
        "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (6_000_000, resource.RLIM_INFINITY))\n"
        "from endo_process.errors import WorkerError\n"
        "from endo_process.worker import SlotRing\n"
        "SlotRing(640 * 480, 2).close()  # 4.9 MB: fits\n"
        "try:\n"
        "    SlotRing(640 * 480, 8)\n"
        "except WorkerError as error:\n"
        "    print(error)\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 0, result.stderr
    assert "cannot create 19.7 MB of shared memory" in result.stdout
    assert "over the file size limit" in result.stdout
    assert "Traceback" not in result.stderr and "KeyError" not in result.stderr, result.stderr
