"""Every command-line tool's ``--help`` states each option's default.

A user reads ``endo-replay --help`` to learn how long ``--wait-for-subscribers``
waits before it plays anyway, or ``endo-handeye --help`` to learn which unit
``--pose-unit`` assumes; a default that only the code knows is a trap. An
option whose default is None, False or an empty list ("not given") needs no
statement; every other option's help must name its default: the word
"default" (with the value or what it means) or the value itself, as the
sim's ``(640)`` style does.
"""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Iterator
from typing import Any

import pytest

#: console script -> (module, function building its parser)
PARSERS = {
    "endo-bag": ("endo_io.bag_cli", "build_parser"),
    "endo-calibrate": ("endo_calib.cli", "build_parser"),
    "endo-camera": ("endo_io.camera_node", "build_parser"),
    "endo-demo": ("endo_bringup.demo", "build_parser"),
    "endo-doctor": ("endo_bringup.doctor", "_parser"),
    "endo-handeye": ("endo_tracker_bridge.handeye_cli", "build_parser"),
    "endo-launch": ("endo_bringup.launcher", "build_parser"),
    "endo-process": ("endo_process.cli", "build_parser"),
    "endo-record": ("endo_io.record_node", "build_parser"),
    "endo-replay": ("endo_io.replay_node", "build_parser"),
    "endo-sim": ("endo_sim.cli", "build_parser"),
}


def _options(parser: argparse.ArgumentParser, prog: str) -> Iterator[tuple[str, argparse.Action]]:
    """(command, action) of every option, subcommands included."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _options(sub, f"{prog} {name}")
        elif action.option_strings and action.help != argparse.SUPPRESS:
            yield prog, action


def _renderings(default: Any) -> list[str]:
    """How a help text may write ``default``."""
    if isinstance(default, bool):
        return ["(on)"] if default else ["(off)"]
    if isinstance(default, int | float):
        return [f"{default:g}"]
    if isinstance(default, tuple | list):
        return [" ".join(f"{v:g}" if isinstance(v, int | float) else str(v) for v in default)]
    return [str(default)]


def _undocumented(script: str) -> list[str]:
    module, function = PARSERS[script]
    parser = getattr(importlib.import_module(module), function)()
    missing = []
    for command, action in _options(parser, script):
        default = action.default
        if default is None or default is False or default == [] or default == argparse.SUPPRESS:
            continue
        if isinstance(action, argparse._HelpAction | argparse._VersionAction):
            continue
        text = (action.help or "") % {**vars(action), "prog": command}
        if "default" in text or any(r in text for r in _renderings(default)):
            continue
        missing.append(f"{command} {'/'.join(action.option_strings)} (default {default!r})")
    return missing


@pytest.mark.parametrize("script", sorted(PARSERS))
def test_every_default_is_stated_in_the_help(script: str) -> None:
    assert _undocumented(script) == []
