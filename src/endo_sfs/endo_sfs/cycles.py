"""A cycle counter readable inside numba kernels, for splitting a kernel's wall time.

numba's nopython mode has no clock. The near-light sweep kernel reads the
CPU's time-stamp counter (``llvm.readcyclecounter``: ``rdtsc`` on x86-64)
at the boundaries of its phases, and the caller turns the ratio of the
counts into a share of the kernel's wall time, measured outside with
``time.perf_counter``. Only ratios are used, so the counter's frequency
never matters (on x86-64 it is constant, not the core clock). Three reads
per frame cost nanoseconds.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, cast

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic


@intrinsic
def _cycle_counter(typingctx: Any) -> Any:
    """Typing and code generation of :func:`cycle_counter` (numba passes the typing context)."""
    signature = types.int64()

    def codegen(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        function_type = ir.FunctionType(ir.IntType(64), [])
        function = cgutils.get_or_insert_function(
            builder.module, function_type, "llvm.readcyclecounter"
        )
        return builder.call(function, [])

    return signature, codegen


#: ``cycle_counter()``: the CPU's cycle counter (int, ticks at a constant
#: rate; inside numba kernels only). Differences of two reads on one thread
#: are proportional to the wall time between them.
cycle_counter = cast("Callable[[], int]", _cycle_counter)
