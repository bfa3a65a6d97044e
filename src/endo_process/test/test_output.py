"""The output's writer thread: calls reach the bag in order, and a writer error is raised."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from endo_io.bag import BagError, BagReader, BagWriter, deserialize
from endo_io.image import image_to_array
from endo_process.output import WRITE_QUEUE_CALLS, OutputBag


def test_writes_arrive_in_order_and_a_writer_error_is_raised(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    output = OutputBag(tmp_path / "ok.mcap", "lz4")
    frames = [np.full((4, 5), k, np.float32) for k in range(3 * WRITE_QUEUE_CALLS)]
    for k, frame in enumerate(frames):
        output.write_image("/depth", frame, "32FC1", 1_000 + k, "optical")
    output.close()
    output.close()  # idempotent
    with BagReader(tmp_path / "ok.mcap") as reader:
        read = [image_to_array(deserialize(m)) for m in reader.messages(["/depth"])]
    assert len(read) == len(frames)
    assert all(np.array_equal(a, b) for a, b in zip(read, frames, strict=True))

    def full_disk(self: BagWriter, *args: object) -> None:
        raise BagError("no space left on device")

    failing = OutputBag(tmp_path / "fail.mcap", "lz4")
    monkeypatch.setattr(BagWriter, "write", full_disk)
    with pytest.raises(BagError, match="no space"):
        for k in range(3 * WRITE_QUEUE_CALLS):  # raised by a later call, once the thread met it
            failing.write_image("/depth", frames[0], "32FC1", 1_000 + k, "optical")
        failing.close()
    failing.close()  # the file closed; the error was raised already
