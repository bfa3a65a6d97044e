"""Row-band parallelism for the simulator's numba kernels.

Every per-pixel kernel here is compiled with ``nogil=True`` and takes a row
range ``[row_start, row_stop)``; :func:`run_in_bands` splits the image into
one band per worker and runs the bands on a thread pool, so the kernels use
all cores without numba's ``parallel=True`` (whose compilation takes many
seconds per kernel). Each pixel is computed independently, so the result is
bit-identical for any number of workers.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

#: Worker threads (one per core; ENDO_SIM_THREADS overrides).
WORKERS = max(1, int(os.environ.get("ENDO_SIM_THREADS", os.cpu_count() or 1)))

#: Bands per worker thread (dynamic load balancing).
BANDS_PER_WORKER = 8

_pool: ThreadPoolExecutor | None = None


def _executor() -> ThreadPoolExecutor:
    global _pool
    if _pool is None:
        _pool = ThreadPoolExecutor(max_workers=WORKERS, thread_name_prefix="endo_sim")
    return _pool


def set_workers(count: int) -> None:
    """Use ``count`` worker threads from now on (benchmarks compare 1 and 2)."""
    global WORKERS, _pool
    if count < 1:
        raise ValueError(f"need at least one worker, got {count}")
    if _pool is not None:
        _pool.shutdown()
        _pool = None
    WORKERS = int(count)


def run_in_bands(kernel: Callable[..., Any], rows: int, *args: Any) -> None:
    """Call ``kernel(*args, row_start, row_stop)`` over ``rows`` rows split in bands.

    The kernel must be a ``nogil`` numba function writing its results into
    arrays passed in ``args``; bands are disjoint, so no two calls write the
    same element.
    """
    bands = BANDS_PER_WORKER * WORKERS
    if WORKERS == 1 or rows < bands:
        kernel(*args, 0, rows)
        return
    # Many bands handed out as workers come free balance the load (the
    # lumen's centre costs more per pixel than its walls).
    bounds = [round(rows * k / bands) for k in range(bands + 1)]
    futures = [_executor().submit(kernel, *args, bounds[k], bounds[k + 1]) for k in range(bands)]
    for future in futures:
        future.result()
