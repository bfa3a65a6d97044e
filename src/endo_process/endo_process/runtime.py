"""Process set-up for endo-process: the allocator keeps freed memory, BLAS on one thread.

**Freed memory reused** (:func:`reuse_freed_memory`).

Every frame allocates and frees dozens of arrays of 0.3–5 MB (images, depth,
clouds, the solver's grids). glibc's default serves blocks above its mmap
threshold (128 KiB, raised on the fly up to 32 MiB) from fresh ``mmap``
mappings and gives them back with ``munmap``, and trims the heap's top when
more than twice that is free: either way the next frame's arrays are fresh
pages, each zeroed by the kernel on its first touch (a minor page fault).
Over the 60 s render's 1800 frames that was ~1.2 million page faults in the
main process (docs/benchmarks.md, "endo-process", session 13). With the
thresholds fixed high, freed blocks stay in the heap and are reused.

The cost is memory held: up to :data:`TRIM_THRESHOLD` of free heap is kept
rather than returned (the 60 s render's peak resident set of the whole
command, its largest process, 844 MB before, 887 MB after).

**BLAS on one thread** (:func:`one_blas_thread`). numpy's OpenBLAS starts a
thread per core, and after each call its threads spin (``sched_yield``)
waiting for the next: ~5 % of the main process's CPU samples over the 60 s
render (``perf``), on the cores the solver needs. The frame loop's matrix
products are small (3×3 to a few hundred rows), below OpenBLAS's own
threshold for using more than one thread: one thread loses nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

#: glibc's mallopt parameter numbers (malloc.h).
M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD = -1, -2, -3
#: Blocks up to this size come from the heap, not from mmap (bytes).
MMAP_THRESHOLD = 128 << 20
#: Free memory at the heap's top kept rather than returned (bytes).
TRIM_THRESHOLD = 512 << 20
#: Extra bytes asked of the kernel whenever the heap grows.
TOP_PAD = 64 << 20


def reuse_freed_memory() -> bool:
    """Set this process's allocator to keep and reuse freed blocks; True when glibc took it.

    A process-wide setting: ``endo-process`` calls it first thing in its
    main process and in each shading worker. A C library without
    ``mallopt`` (not glibc) leaves it as it is (False).
    """
    name = ctypes.util.find_library("c")
    try:
        mallopt = ctypes.CDLL(name).mallopt
    except (OSError, AttributeError, TypeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    settings = ((M_MMAP_THRESHOLD, MMAP_THRESHOLD), (M_TRIM_THRESHOLD, TRIM_THRESHOLD),
                (M_TOP_PAD, TOP_PAD))  # fmt: skip
    return all(mallopt(option, value) == 1 for option, value in settings)


#: The environment variables of numpy's BLAS thread count (OpenBLAS, and OpenMP builds).
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")


def one_blas_thread() -> None:
    """BLAS on one thread in this process and in the processes it starts.

    Sets :data:`BLAS_THREAD_VARIABLES` to 1 unless the user set them; it
    takes effect only if called before numpy is first imported (its BLAS
    reads them when loaded), so ``endo-process`` calls it first thing.
    The shading workers, spawned after it, inherit the environment.
    """
    for name in BLAS_THREAD_VARIABLES:
        os.environ.setdefault(name, "1")
