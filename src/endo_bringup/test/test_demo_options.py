"""endo-demo refuses options no run can use, in one line, before anything starts."""

from __future__ import annotations

from pathlib import Path

import pytest

from endo_bringup.demo import main
from endo_io.bag import BagWriter


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--rate", "0"], "--rate must be a playback speed > 0, got 0"),
        (["--graph-rate", "-1"], "--graph-rate must be a playback speed > 0, got -1"),
        (["--rate", "nan"], "--rate must be a playback speed > 0, got nan"),
        (["--solve-scale", "5"], "--solve-scale must be in [0.1, 1], got 5"),
        (["--solve-scale", "0"], "--solve-scale must be in [0.1, 1], got 0"),
    ],
)
def test_bad_options_are_one_line_and_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], arguments: list[str], message: str
) -> None:
    out = tmp_path / "out"
    assert main([*arguments, "--output-dir", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    assert not out.exists()  # nothing started, nothing written


def test_a_bag_with_nothing_to_play_is_one_line_and_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    empty = tmp_path / "empty.mcap"
    with BagWriter(empty):
        pass
    out = tmp_path / "out"
    assert main(["--bag", str(empty), "--round-trip-only", "--output-dir", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{empty}: no topic to play here" in err[0], err
    assert not (out / "round_trip.mcap").exists()  # no recorder started
