"""The README's runnable shell blocks run as written on the sample bags.

A block is runnable when the line before its opening fence is
``<!-- runnable: timeout=SECONDS -->``. Every such block of README.md runs,
in the README's order, in one fresh directory holding a link to ``bags/``
(what a fresh clone has), each line as the user would type it (``bash -e``,
the virtual environment's executables first on PATH), under its timeout;
later blocks use what earlier ones wrote (the calibrations). A block passes
when every command exits 0 and, where a block writes a file the README names,
that file exists. Marker ``docs`` (``pytest -m docs`` runs only these).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
_BLOCK = re.compile(
    r"<!-- runnable: timeout=(?P<timeout>\d+) -->\n```bash\n(?P<body>.*?)\n```", re.S
)
_WRITES = re.compile(r"(?:-o|--record|--write-params)\s+(\S+)")

pytestmark = [pytest.mark.docs, pytest.mark.ros]


@dataclass(frozen=True)
class Block:
    """One runnable block: where it starts in the README, its timeout, its text."""

    line: int
    timeout_s: int
    body: str

    @property
    def writes(self) -> list[str]:
        """The files its commands are told to write."""
        return _WRITES.findall(self.body)


def runnable_blocks(text: str) -> list[Block]:
    """Every runnable block of ``text`` in order."""
    return [
        Block(text.count("\n", 0, m.start()) + 1, int(m["timeout"]), m["body"])
        for m in _BLOCK.finditer(text)
    ]


BLOCKS = runnable_blocks(README.read_text(encoding="utf-8"))


def test_the_readme_has_runnable_blocks_for_calibration_launch_and_parameters():
    bodies = "\n".join(b.body for b in BLOCKS)
    for command in ("endo-calibrate", "endo-handeye", "endo-launch replay", "--write-params"):
        assert command in bodies, command


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A fresh directory with ``bags/`` in it, as in a clone."""
    path = tmp_path_factory.mktemp("readme")
    (path / "bags").symlink_to(ROOT / "bags")
    return path


@pytest.mark.parametrize("block", BLOCKS, ids=[f"README.md:{b.line}" for b in BLOCKS])
def test_a_runnable_readme_block_runs_as_written(block: Block, workdir: Path):
    # A DDS domain of the README's own (this process's + 15, at most 101: see
    # conftest.py): `endo-launch` refuses to start a second graph in a domain where
    # it sees one, and a node of an earlier test still shutting down must not count.
    domain = (int(os.environ.get("ROS_DOMAIN_ID", "42")) + 15) % 102
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
               ROS_DOMAIN_ID=str(domain))  # fmt: skip
    result = subprocess.run(
        ["bash", "-e", "-o", "pipefail", "-c", block.body],
        cwd=workdir, env=env, capture_output=True, text=True, timeout=block.timeout_s,
        check=False,
    )  # fmt: skip
    assert result.returncode == 0, (
        f"README.md:{block.line} exited {result.returncode}:\n{block.body}\n"
        f"--- stdout ---\n{result.stdout[-4000:]}\n--- stderr ---\n{result.stderr[-4000:]}"
    )
    for name in block.writes:
        assert (workdir / name).is_file(), f"README.md:{block.line} did not write {name}"
