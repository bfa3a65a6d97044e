"""The progress bar of the command-line tools on stderr: count, rate, ETA (tqdm).

``endo-process`` and ``endo-sim render`` show one. It is drawn only when
stderr is a terminal and the user did not ask for quiet, so logs, pipes and
CI stay clean.
"""

from __future__ import annotations

import sys

from tqdm import tqdm


class Progress:
    """A frame counter bar; ``update`` takes the total done so far.

    Args:
        total: frames expected.
        enabled: False (``--quiet``) hides it; it is hidden anyway when
            stderr is not a TTY.
        description: the bar's label (the program's name).
    """

    def __init__(
        self, total: int, *, enabled: bool = True, description: str = "", unit: str = "frame"
    ) -> None:
        shown = enabled and sys.stderr.isatty()
        self._bar = tqdm(
            total=total, unit=unit, desc=description or None, file=sys.stderr,
            disable=not shown, dynamic_ncols=True, smoothing=0.1,
        )  # fmt: skip
        self._done = 0

    @property
    def shown(self) -> bool:
        """Whether the bar is drawn."""
        return not self._bar.disable

    def update(self, done: int) -> None:
        """Move the bar to ``done`` frames."""
        if done > self._done:
            self._bar.update(done - self._done)
            self._done = done

    def close(self) -> None:
        """Finish the bar (idempotent)."""
        self._bar.close()
