"""Writing a benchmark's results into docs/benchmarks.md, one section per bench.

Imported by the bench scripts as a sibling module (``python bench/bench_x.py``
puts bench/ first on ``sys.path``).
"""

from __future__ import annotations

from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parents[1] / "docs" / "benchmarks.md"


def replace_section(section: str, title: str, path: Path = BENCHMARKS) -> None:
    """Put ``section`` (starting with the heading ``title``) in place of that section of ``path``.

    The file is re-read right before editing, because other benches write to
    it too; a section not there yet is appended.
    """
    text = path.read_text(encoding="utf-8") if path.exists() else "# Benchmarks\n"
    if title in text:
        start = text.index(title)
        following = text.find("\n## ", start + len(title))
        end = len(text) if following < 0 else following + 1
        text = text[:start] + section + ("\n" + text[end:] if following >= 0 else "")
    else:
        text = text.rstrip("\n") + "\n\n" + section
    path.write_text(text, encoding="utf-8")
