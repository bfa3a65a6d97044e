"""The whole tree is ruff clean and each package's code mypy clean (docs/CONTRIBUTING.md)."""

from __future__ import annotations

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


def test_mypy_reports_nothing():
    """The settings are pyproject.toml's [tool.mypy]; the paths are `make lint`'s."""
    mypy = Path(sys.executable).parent / "mypy"
    packages = sorted(p.parent for p in (ROOT / "src").glob("*/package.xml"))
    code = [str((p / p.name).relative_to(ROOT)) for p in packages]
    assert len(code) >= 7
    result = subprocess.run(
        [str(mypy), *code], cwd=ROOT, capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, result.stdout[-4000:]
