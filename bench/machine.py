"""What machine a benchmark ran on, for the header line of its results.

Imported by the bench scripts as a sibling module (``python bench/bench_x.py``
puts bench/ first on ``sys.path``).
"""

from __future__ import annotations

import platform
import subprocess


def cpu_model() -> str:
    """The CPU's model name from ``lscpu``, else ``platform.processor()``, else "unknown"."""
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
        for line in out.splitlines():
            if line.startswith("Model name"):
                return line.split(":", 1)[1].strip()
    except (OSError, subprocess.CalledProcessError):
        pass
    return platform.processor() or "unknown"
