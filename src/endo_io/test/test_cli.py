"""endo_io.cli.exit_on_error: bad input is one line on stderr and exit code 2."""

from __future__ import annotations

from pathlib import Path

import pytest

from endo_io.cli import EXIT_BAD_INPUT, exit_on_error
from endo_io.errors import BagError, PoseError


@exit_on_error("endo-example")
def _main(argv: list[str]) -> int:
    if argv == ["pose"]:
        raise PoseError("quaternion contains NaN or infinity")
    if argv == ["bug"]:
        raise KeyError("not bad input: a bug")
    return len(argv)


@exit_on_error("endo-files", errors=(BagError, OSError), label="error")
def _files(path: str) -> int:
    with open(path, "rb"):  # noqa: PTH123
        return 0


def test_bad_input_is_one_line_and_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert EXIT_BAD_INPUT == 2
    assert _main(["pose"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err == "endo-example: PoseError: quaternion contains NaN or infinity\n"


def test_the_wrapped_exit_code_and_anything_else_pass_through(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert _main(["a", "b", "c"]) == 3
    with pytest.raises(KeyError):
        _main(["bug"])
    assert capsys.readouterr().err == ""
    assert _main.__name__ == "_main"


def test_named_classes_are_bad_input_too_and_the_label_can_be_argparses(
    tmp_path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert _files(str(tmp_path / "missing.bin")) == 2
    err = capsys.readouterr().err
    assert err.startswith("endo-files: error: ") and "missing.bin" in err
    assert len(err.splitlines()) == 1


def test_yaml_error_line_names_the_position_in_one_line() -> None:
    import yaml

    from endo_io.errors import yaml_error_line

    with pytest.raises(yaml.YAMLError) as raised:
        yaml.safe_load("a: b: c\n")
    assert yaml_error_line(raised.value) == "line 1, column 5: mapping values are not allowed here"
    assert yaml_error_line(OSError(21, "Is a directory")) == "[Errno 21] Is a directory"


def test_refuse_existing_names_the_first_existing_file(tmp_path: Path) -> None:
    from endo_io.cli import refuse_existing
    from endo_io.errors import OutputExistsError

    new, old = tmp_path / "new.yaml", tmp_path / "old.yaml"
    old.write_text("kept\n")
    refuse_existing(new, overwrite=False)
    refuse_existing(new, old, overwrite=True)
    with pytest.raises(OutputExistsError, match=r"old\.yaml exists; --overwrite replaces it$"):
        refuse_existing(new, old, overwrite=False)
    assert old.read_text() == "kept\n"
