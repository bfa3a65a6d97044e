"""A cycle counter readable inside numba kernels, for splitting a kernel's wall time.

numba's nopython mode has no clock. The near-light sweep kernel reads the
CPU's time-stamp counter (``llvm.readcyclecounter``: ``rdtsc`` on x86-64)
at the boundaries of its phases, and the caller turns the ratio of the
counts into a share of the kernel's wall time, measured outside with
``time.perf_counter``. Only ratios are used, so the counter's frequency
never matters (on x86-64 it is constant, not the core clock). Three reads
per frame cost nanoseconds.

Only on x86-64 (``rdtsc``: constant rate, readable by user code on Linux).
Elsewhere the counter is not read and :func:`cycle_counter` returns 0: LLVM
lowers ``llvm.readcyclecounter`` on aarch64 to ``PMCCNTR_EL0`` in older
releases (LLVM 14, numba 0.58's), which traps in user mode, and Linux ≥ 6.6
traps riscv64's ``rdcycle``. The split is then not measured (the share is 0).
"""

from __future__ import annotations

import platform
from collections.abc import Callable
from typing import Any, cast

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

#: whether :func:`cycle_counter` reads the CPU's counter here (x86-64 only)
COUNTER_AVAILABLE = platform.machine().lower() in ("x86_64", "amd64")


@intrinsic
def _cycle_counter(typingctx: Any) -> Any:
    """Typing and code generation of :func:`cycle_counter` (numba passes the typing context)."""
    signature = types.int64()

    def codegen(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        if not COUNTER_AVAILABLE:
            return ir.Constant(ir.IntType(64), 0)
        function_type = ir.FunctionType(ir.IntType(64), [])
        function = cgutils.get_or_insert_function(
            builder.module, function_type, "llvm.readcyclecounter"
        )
        return builder.call(function, [])

    return signature, codegen


#: ``cycle_counter()``: the CPU's cycle counter (int, ticks at a constant
#: rate; inside numba kernels only; 0 where not :data:`COUNTER_AVAILABLE`).
#: Differences of two reads on one thread are proportional to the wall time
#: between them.
cycle_counter = cast("Callable[[], int]", _cycle_counter)
