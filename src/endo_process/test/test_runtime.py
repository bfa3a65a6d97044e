"""endo_process.runtime: freed frame-sized arrays are reused, not faulted in again."""

from __future__ import annotations

import subprocess
import sys

CHURN = """
import resource, sys
import numpy as np
from endo_process.runtime import reuse_freed_memory
if sys.argv[1] == "tuned":
    assert reuse_freed_memory()
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
np.ones((480, 640), np.float32) * 2  # numpy's own first-use allocations
start = faults()
for _ in range(100):  # a frame's worth of fresh 1.2 MB arrays, freed at once
    image = np.ones((480, 640), np.float32)
    depth = np.sqrt(image * 2)
    del image, depth
print(faults() - start)
"""


def faults(mode: str) -> int:
    done = subprocess.run([sys.executable, "-c", CHURN, mode], capture_output=True, text=True,
                          check=True, timeout=120)  # fmt: skip
    return int(done.stdout.strip())


def test_frame_arrays_reuse_the_freed_heap() -> None:
    # 200 arrays of 300 pages each: glibc's default maps (or trims) and faults most of them
    # in afresh; kept in the heap, the pages are touched once.
    default, tuned = faults("default"), faults("tuned")
    assert default > 20_000, default
    assert tuned < 2_000, tuned
