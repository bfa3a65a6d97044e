"""The whole tree is ruff clean and writes one docstring convention (docs/CONTRIBUTING.md).

mypy over each package's code is `make lint`'s (CI runs it after `make test`,
`.ci/run`): from a clean clone it takes ~25 s of the suite's ten minutes.
"""

from __future__ import annotations

import itertools
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_ruff_reports_nothing():
    ruff = Path(sys.executable).parent / "ruff"
    result = subprocess.run(
        [str(ruff), "check", "--no-cache", "src", "tests", "bench", "conftest.py"],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 0, result.stdout[-4000:]


def test_docstrings_use_one_convention():
    """Google sections only: ruff's google convention does not flag numpydoc underlines."""
    underlined = []
    for path in sorted(ROOT.glob("*/**/*.py")):
        if ".venv" in path.parts or "build" in path.parts:
            continue
        lines = path.read_text(encoding="utf-8").splitlines()
        for number, (line, below) in enumerate(itertools.pairwise(lines), start=1):
            if line.strip() in ("Parameters", "Returns", "Raises", "Attributes", "Notes") and (
                below.strip() and set(below.strip()) == {"-"}
            ):
                underlined.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()}")
    assert underlined == [], "numpydoc sections; write them Google style:\n" + "\n".join(underlined)
