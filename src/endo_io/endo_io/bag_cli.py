"""``endo-bag``: pip-only bag tools (``info``, ``reindex``, ``recover``) without the ros2 CLI.

* ``endo-bag info BAG``: files, size, duration, start and end, message
  count, chunk compression, and per topic its type, count and frequency,
  as ``ros2 bag info`` prints them.
* ``endo-bag reindex DIR``: rewrite a bag directory's metadata.yaml from the
  MCAP files in it.
* ``endo-bag recover IN OUT``: write every intact message of a damaged or
  SIGKILLed bag into a new, complete file and say how many were kept and
  lost.

Exit status: 0 on success; 1 when ``info`` read a damaged bag (everything
before the damage is summarised); 2 when the options or the input are
unusable (one line on stderr, nothing written).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import NoReturn

from endo_io.bag.info import bag_info, format_bag_info
from endo_io.bag.repair import recover, reindex
from endo_io.bag.writer import COMPRESSIONS, OUTPUT_PATH_HELP
from endo_io.errors import Endo3dError

PROG = "endo-bag"


class _Parser(argparse.ArgumentParser):
    """Reports a usage error in one line (and exit status 2), not usage plus error."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {PROG} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    """The ``endo-bag`` command line."""
    parser = _Parser(
        prog=PROG, description="Inspect and repair rosbag2 MCAP bags without the ros2 CLI."
    )
    commands = parser.add_subparsers(
        dest="command", required=True, metavar="COMMAND", parser_class=_Parser
    )
    info = commands.add_parser("info", help="what a bag holds, as 'ros2 bag info' prints it")
    info.add_argument("bag", type=Path, help=".mcap file or rosbag2 directory")
    reindex_cmd = commands.add_parser(
        "reindex", help="rewrite a bag directory's metadata.yaml from its MCAP files"
    )
    reindex_cmd.add_argument("directory", type=Path, help="rosbag2 bag directory")
    recover_cmd = commands.add_parser(
        "recover", help="copy every intact message of a damaged bag into a new, complete one"
    )
    recover_cmd.add_argument("source", type=Path, help="damaged .mcap file or bag directory")
    recover_cmd.add_argument(
        "target", type=Path, help="the new bag, which must not exist; " + OUTPUT_PATH_HELP
    )
    recover_cmd.add_argument(
        "--compression",
        choices=COMPRESSIONS,
        default=None,
        help="chunk compression of the new file (default: the source's)",
    )
    return parser


def _error(text: str) -> int:
    print(f"{PROG}: error: {text}", file=sys.stderr)
    return 2


def _warn(lines: Sequence[str]) -> None:
    for line in lines:
        print(f"{PROG}: warning: {line}", file=sys.stderr)


def _info(options: argparse.Namespace) -> int:
    info = bag_info(options.bag)
    _warn(info.warnings)
    print(format_bag_info(info))
    if info.damage:
        print(f"{PROG}: damaged: {info.damage}", file=sys.stderr)
        return 1
    return 0


def _reindex(options: argparse.Namespace) -> int:
    report = reindex(options.directory)
    before = "none" if report.previous_count is None else str(report.previous_count)
    print(
        f"{PROG}: wrote {report.path}: {len(report.files)} file(s) "
        f"({', '.join(report.files)}), {report.message_count} messages "
        f"(the previous metadata.yaml counted {before})"
    )
    _warn([f"{text}; its intact messages are counted" for text in report.damage])
    return 0


def _recover(options: argparse.Namespace) -> int:
    report = recover(options.source, options.target, compression=options.compression)
    print(f"{PROG}: wrote {options.target} from {options.source}")
    for topic in sorted(report.kept):
        kept, counted = report.kept[topic], report.counted.get(topic, 0)
        lost = max(0, counted - kept)
        print(f"  {topic}: kept {kept}" + (f", lost {lost}" if lost else ""))
    print(
        f"  total: kept {report.kept_total} messages, lost {report.lost_total} that the "
        "source's indexes count" + ("" if report.damage else " (the source was intact)")
    )
    if report.damage:
        print(f"  damage: {report.damage}")
        if "ends inside a chunk record" in report.damage:
            print(
                "  the source ends inside a chunk (a writer killed while writing it): "
                "its messages after the cut were counted nowhere and cannot be known"
            )
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``endo-bag``; returns the process exit status."""
    args = list(sys.argv[1:] if argv is None else argv[1:])
    try:
        options = build_parser().parse_args(args)
    except SystemExit as stop:  # --help, or a usage error already printed in one line
        return stop.code if isinstance(stop.code, int) else 2
    handlers = {"info": _info, "reindex": _reindex, "recover": _recover}
    try:
        return handlers[options.command](options)
    except (Endo3dError, OSError) as error:
        return _error(str(error))


if __name__ == "__main__":
    sys.exit(main())
