"""The solve's second thread for stages that numba's parallel loops do not split well.

numba's ``prange`` splits a loop across threads for each call; the small
per-pixel passes of a frame (0.03–0.4 ms each at solve_scale 0.5) gained
nothing from it on two cores and lost ~0.1 ms each beside OpenCV's own
workers (docs/sfs.md, "Speed"). With ``SfsOptions.threads`` ≥ 2 the solve
instead runs whole independent stages side by side: :func:`beside` starts one
on a second thread (one worker for the process, made on first use) while the
calling thread does another, each with numba on one thread.

That needs a thread-safe numba threading layer (OpenMP or TBB): numba's own
``workqueue`` layer aborts the process when two threads launch parallel
kernels at once ("Concurrent access has been detected"), whatever
``set_num_threads``. Where numba runs on ``workqueue`` (no libgomp or TBB,
or ``NUMBA_THREADING_LAYER=workqueue``) :func:`beside` runs the task on the
calling thread: the same result, without the overlap.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from typing import TypeVar

import numba

_T = TypeVar("_T")
_pool: ThreadPoolExecutor | None = None
_pool_lock = threading.Lock()
_threadsafe: bool | None = None  # whether numba's threading layer is (decided on first use)


def threading_layer_is_threadsafe() -> bool:
    """Whether two threads may run numba's parallel kernels at once (not ``workqueue``).

    Starts numba's threads to find out (numba picks its layer then), once per process.
    """
    global _threadsafe
    if _threadsafe is None:
        try:
            from numba.np.ufunc import parallel

            parallel._launch_threads()  # numba chooses its layer here
            _threadsafe = numba.threading_layer() != "workqueue"
        except Exception:  # no layer could be loaded, or numba's internals moved: be safe
            _threadsafe = False
    return _threadsafe


def _on_one_numba_thread(task: Callable[[], _T]) -> _T:
    numba.set_num_threads(1)  # numba's setting is per thread
    return task()


def beside(task: Callable[[], _T]) -> Future[_T]:
    """Start ``task()`` on the second thread; ``.result()`` waits for its value (or raises).

    Tasks run one after another in the order given. numba's kernels run on
    one thread within them; OpenCV's and numba's kernels release the GIL, so
    the task and the caller's own work overlap.
    """
    global _pool
    if not threading_layer_is_threadsafe():
        done: Future[_T] = Future()
        try:
            done.set_result(task())
        except Exception as error:  # .result() raises it, as the pool's future would
            done.set_exception(error)
        return done
    with _pool_lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="endo_sfs")
    return _pool.submit(_on_one_numba_thread, task)


@contextmanager
def numba_single_threaded() -> Iterator[None]:
    """Run the block with numba's parallel kernels on the calling thread alone."""
    previous = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        yield
    finally:
        numba.set_num_threads(previous)
