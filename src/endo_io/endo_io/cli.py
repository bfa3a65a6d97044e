"""The command-line tools' one way to fail on bad input: one line, exit code 2.

Every endo3d console script wraps its ``main`` in :func:`exit_on_error`. An
:class:`~endo_io.errors.Endo3dError` (or another exception class the tool
names, e.g. ``OSError`` for a file it cannot write) then ends the program
with one line on stderr, ``<program>: <ErrorClass>: <message>``, and exit code
:data:`EXIT_BAD_INPUT`, never a traceback. argparse's own usage errors exit
with 2 as well, so a script has one failure code for "the input was wrong".
A tool whose lines follow argparse's ``<program>: error: <message>`` form
(``endo-replay``, ``endo-record``) passes ``label="error"``.

A tool never replaces a file the user already has unless told to:
:func:`refuse_existing` is its one check, before any work is done.

>>> @exit_on_error("endo-calibrate")
... def main(argv: Sequence[str] | None = None) -> int:
...     run(build_parser().parse_args(argv))
...     return 0
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from pathlib import Path
from typing import ParamSpec

from endo_io.errors import Endo3dError, OutputExistsError

#: Exit code of a command-line tool given bad input (argparse uses it too).
EXIT_BAD_INPUT = 2

_P = ParamSpec("_P")


def report_error(program: str, error: BaseException, *, label: str | None = None) -> int:
    """Print ``<program>: <label>: <message>`` on stderr; return :data:`EXIT_BAD_INPUT`.

    Args:
        program: the executable's name.
        error: what went wrong; its message is the end of the line.
        label: the word before the message; default the exception's class
            name (``BagNotFoundError``), which names the cause.
    """
    print(f"{program}: {label or type(error).__name__}: {error}", file=sys.stderr, flush=True)
    return EXIT_BAD_INPUT


def refuse_existing(*paths: Path, overwrite: bool) -> None:
    """Refuse to replace a file the user has, unless ``overwrite`` (the tool's ``--overwrite``).

    Called before the tool does any work, so that a refusal costs nothing.

    Args:
        paths: the files the tool will write (an output and its side files).
        overwrite: the user asked for existing files to be replaced.

    Raises:
        OutputExistsError: ``<path> exists; --overwrite replaces it``, naming
            the first of ``paths`` that exists.
    """
    if overwrite:
        return
    for path in paths:
        if path.exists():
            raise OutputExistsError(f"{path} exists; --overwrite replaces it")


def exit_on_error(
    program: str,
    *,
    errors: tuple[type[BaseException], ...] = (Endo3dError,),
    label: str | None = None,
) -> Callable[[Callable[_P, int]], Callable[_P, int]]:
    """Decorate a console script's ``main``: ``errors`` become one line and exit code 2.

    Args:
        program: the executable's name, the first word of the line.
        errors: the exception classes that mean bad input (default
            :class:`~endo_io.errors.Endo3dError`, the base of every endo3d
            error); anything else is a bug and keeps its traceback.
        label: as for :func:`report_error`.

    Returns:
        A decorator; the decorated ``main`` returns its own exit code, or
        :data:`EXIT_BAD_INPUT` after printing the line.
    """

    def decorate(main: Callable[_P, int]) -> Callable[_P, int]:
        @functools.wraps(main)
        def guarded(*args: _P.args, **kwargs: _P.kwargs) -> int:
            try:
                return main(*args, **kwargs)
            except errors as error:
                return report_error(program, error, label=label)

        return guarded

    return decorate
