"""Software prefetch for numba kernels that visit a grid in a data-dependent order.

The near-light solver visits its nodes in order of value (along level sets),
so consecutive nodes are far apart in memory and each visit would wait for
its stencil to come from main memory. Kernels that know the next nodes ahead
of time call :func:`prefetch` on them a few visits early, so the loads
overlap with the current node's arithmetic.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, cast

import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

_I32 = ir.IntType(32)
#: llvm.prefetch arguments: read (0), highest temporal locality (3), data cache (1).
_READ, _KEEP_IN_ALL_CACHES, _DATA_CACHE = 0, 3, 1


@intrinsic
def _prefetch(typingctx: Any, array: types.Array, flat_index: types.Integer) -> Any:
    """Typing and code generation of :func:`prefetch` (numba passes the typing context)."""
    if not isinstance(array, types.Array) or not isinstance(flat_index, types.Integer):
        return None
    signature = types.void(array, flat_index)

    def codegen(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        array_struct = context.make_array(sig.args[0])(context, builder, args[0])
        address = builder.gep(array_struct.data, [args[1]])
        byte_pointer = ir.IntType(8).as_pointer()
        function_type = ir.FunctionType(ir.VoidType(), [byte_pointer, _I32, _I32, _I32])
        function = cgutils.get_or_insert_function(
            builder.module, function_type, "llvm.prefetch.p0i8"
        )
        builder.call(
            function,
            [
                builder.bitcast(address, byte_pointer),
                ir.Constant(_I32, _READ),
                ir.Constant(_I32, _KEEP_IN_ALL_CACHES),
                ir.Constant(_I32, _DATA_CACHE),
            ],
        )
        return context.get_dummy_value()

    return signature, codegen


#: ``prefetch(array, flat_index)``: hint the CPU to load ``array.flat[flat_index]``
#: into cache (inside numba kernels only). array: a C-contiguous array; flat_index:
#: element offset from its start. No bounds check and no effect on results: a hint.
#: (The cast gives type checkers the signature kernels call, without numba's typing
#: context argument.)
prefetch = cast("Callable[[np.ndarray, int], None]", _prefetch)
